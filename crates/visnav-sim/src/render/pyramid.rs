//! Mipmap pyramid of an orthophoto, for anti-aliased (trilinear) sampling by ground footprint.
//!
//! Level 0 holds the orthophoto converted to the render channels (grey or RGB) as `f32` digital
//! numbers on the 8-bit scale (see [`dn_scale`]); missing samples (nodata/NaN in any used band) are
//! NaN. Level `k + 1` is the 2 x 2 box average of level `k` over its valid samples (Williams,
//! "Pyramidal parametrics", SIGGRAPH 1983); its pixels are `2^(k+1)` level-0 pixels wide and share
//! the level-0 top-left corner, so the continuous pixel coordinates (corner convention, as in
//! `geo::raster`) of a point are `(col_0, row_0) / 2^k`. An odd last column/row is averaged alone.
//!
//! Sampling at level `k` is bilinear between pixel centres (`i + 0.5`); inside the raster's outer
//! half-pixel margin the coordinate is clamped to the outermost centres, so the whole raster area
//! renders. Trilinear sampling blends the two levels around `lod = log2(footprint in level-0
//! pixels)`. A sample is `None` when any contributing sample with non-zero weight is NaN or the
//! point lies outside the raster area.

use serde::{Deserialize, Serialize};
use visnav_core::geo::Crs;
use visnav_core::geo::raster::{GeoTransform, Raster, RasterData};

/// Rec. 601 luma weights for R, G, B (`Y = 0.299 R + 0.587 G + 0.114 B`).
pub const LUMA_REC601: [f32; 3] = [0.299, 0.587, 0.114];

/// Output channels of the renderer.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ColourMode {
    /// One channel: Rec. 601 luma of bands 1-3 for rasters with at least 3 bands, else band 1.
    #[default]
    Grey,
    /// Three channels: bands 1-3, or band 1 replicated for 1- and 2-band rasters.
    Rgb,
}

/// `grey`, `rgb` (as written in a render spec).
impl std::fmt::Display for ColourMode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            ColourMode::Grey => "grey",
            ColourMode::Rgb => "rgb",
        })
    }
}

impl ColourMode {
    /// Channels per output pixel.
    pub fn channels(self) -> usize {
        match self {
            ColourMode::Grey => 1,
            ColourMode::Rgb => 3,
        }
    }
}

/// Factor from source samples to 8-bit digital numbers: 1 for u8, 255/65535 for u16, 1 for
/// float rasters (their values are taken as DN already).
pub fn dn_scale(data: &RasterData) -> f32 {
    match data {
        RasterData::U8(_) => 1.0,
        RasterData::U16(_) => 255.0 / 65535.0,
        RasterData::F32(_) => 1.0,
    }
}

/// One pyramid level: channel-interleaved `f32`, NaN = missing.
#[derive(Debug, Clone)]
struct Level {
    width: usize,
    height: usize,
    data: Vec<f32>,
    /// No sample is missing: sampling needs no NaN test (the common case of a whole orthophoto).
    complete: bool,
}

impl Level {
    fn new(width: usize, height: usize, data: Vec<f32>) -> Self {
        let complete = !data.iter().any(|v| v.is_nan());
        Self {
            width,
            height,
            data,
            complete,
        }
    }
}

/// Box-filtered pyramid of an orthophoto (see the module doc).
#[derive(Debug, Clone)]
pub struct OrthoPyramid {
    levels: Vec<Level>,
    channels: usize,
    mode: ColourMode,
    transform: GeoTransform,
    crs: Crs,
    /// The orthophoto repeated `[cols, rows]` times east and south of its place, every other
    /// copy mirrored so that neighbours meet edge to edge ([`Self::mirror_tiled`]); `[1, 1]`:
    /// the orthophoto alone.
    tiles: [usize; 2],
}

impl OrthoPyramid {
    /// Builds the pyramid from a raster with 1 or more bands (only bands 1-3 are used), down to a
    /// level of at most 2 x 2 pixels.
    pub fn new(ortho: &Raster, mode: ColourMode) -> Self {
        let (w, h, bands) = (ortho.width(), ortho.height(), ortho.bands());
        let channels = mode.channels();
        let scale = dn_scale(ortho.data());
        let mut data = vec![f32::NAN; w * h * channels];
        let used = bands.min(3);
        let mut px = [0.0f32; 3];
        for row in 0..h {
            for col in 0..w {
                let mut ok = true;
                for (b, p) in px.iter_mut().enumerate().take(used) {
                    match ortho.value(col, row, b) {
                        Some(v) => *p = v as f32 * scale,
                        None => ok = false,
                    }
                }
                if !ok {
                    continue;
                }
                let out = &mut data[(row * w + col) * channels..][..channels];
                match (mode, used) {
                    (ColourMode::Grey, 3) => {
                        out[0] = LUMA_REC601[0] * px[0]
                            + LUMA_REC601[1] * px[1]
                            + LUMA_REC601[2] * px[2];
                    }
                    (ColourMode::Grey, _) => out[0] = px[0],
                    (ColourMode::Rgb, 3) => out.copy_from_slice(&px),
                    (ColourMode::Rgb, _) => out.fill(px[0]),
                }
            }
        }
        let mut levels = vec![Level::new(w, h, data)];
        while let Some(last) = levels.last() {
            if last.width <= 2 && last.height <= 2 {
                break;
            }
            let next = downsample(last, channels);
            levels.push(next);
        }
        Self {
            levels,
            channels,
            mode,
            transform: *ortho.transform(),
            crs: ortho.crs(),
            tiles: [1, 1],
        }
    }

    /// The pyramid of a mosaic: the orthophoto at its place and repeated to `cols x rows`
    /// copies east and south of it, every other copy mirrored (a copy's east edge meets the next
    /// one's mirrored east edge: no seam), without holding more than the orthophoto. A large
    /// area for paging and memory tests, honestly the same ground again.
    pub fn mirror_tiled(mut self, cols: usize, rows: usize) -> Self {
        self.tiles = [cols.max(1), rows.max(1)];
        self
    }

    /// The `[cols, rows]` of [`Self::mirror_tiled`].
    pub fn tiles(&self) -> [usize; 2] {
        self.tiles
    }

    /// Channels per pixel (1 grey, 3 RGB).
    pub fn channels(&self) -> usize {
        self.channels
    }
    /// Colour mode the pyramid was built for.
    pub fn mode(&self) -> ColourMode {
        self.mode
    }
    /// Number of levels (level 0 is the full resolution).
    pub fn levels(&self) -> usize {
        self.levels.len()
    }
    /// Size `(width, height)` of a level in pixels, `None` past the last level.
    pub fn level_size(&self, level: usize) -> Option<(usize, usize)> {
        self.levels.get(level).map(|l| (l.width, l.height))
    }
    /// Level-0 pixel <-> map transform of the source raster.
    pub fn transform(&self) -> &GeoTransform {
        &self.transform
    }
    /// CRS of the source raster.
    pub fn crs(&self) -> Crs {
        self.crs
    }

    /// Bilinear sample of all channels at level `level`, at level-0 continuous pixel coordinates
    /// `(col0, row0)` (corner convention). Writes into `out[..channels]`; false when outside the
    /// raster area, past the last level, or a contributing sample is missing.
    #[inline]
    pub fn sample_level(&self, level: usize, col0: f64, row0: f64, out: &mut [f32]) -> bool {
        let Some(l) = self.levels.get(level) else {
            return false;
        };
        let (w0, h0) = (self.levels[0].width as f64, self.levels[0].height as f64);
        let (cols, rows) = (self.tiles[0] as f64, self.tiles[1] as f64);
        if !(col0 >= 0.0 && row0 >= 0.0 && col0 <= w0 * cols && row0 <= h0 * rows) {
            return false; // also rejects NaN
        }
        // A mosaic's copy folded back onto the orthophoto.
        let fold = |v: f64, n: f64| {
            let p = v % (2.0 * n);
            if p <= n { p } else { 2.0 * n - p }
        };
        let (col0, row0) = if self.tiles == [1, 1] {
            (col0, row0)
        } else {
            (fold(col0, w0), fold(row0, h0))
        };
        let s = 1.0 / f64::from(1u32 << level.min(31));
        // Centre-index coordinates at this level, clamped to the outermost centres.
        let fx = (col0 * s - 0.5).clamp(0.0, (l.width - 1) as f64);
        let fy = (row0 * s - 0.5).clamp(0.0, (l.height - 1) as f64);
        let i0 = (fx as usize).min(l.width.saturating_sub(2)); // ok: fx >= 0 finite
        let j0 = (fy as usize).min(l.height.saturating_sub(2)); // ok: fy >= 0 finite
        let i1 = (i0 + 1).min(l.width - 1);
        let j1 = (j0 + 1).min(l.height - 1);
        let a = (fx - i0 as f64) as f32;
        let b = (fy - j0 as f64) as f32;
        let c = self.channels;
        let p00 = (j0 * l.width + i0) * c;
        let p10 = (j0 * l.width + i1) * c;
        let p01 = (j1 * l.width + i0) * c;
        let p11 = (j1 * l.width + i1) * c;
        let (w00, w10, w01, w11) = ((1.0 - a) * (1.0 - b), a * (1.0 - b), (1.0 - a) * b, a * b);
        if l.complete {
            // The sum below in the same order; a zero weight adds +0 to a finite sum, so it is
            // the same number the loop with its tests gives.
            let d = &l.data;
            for (k, o) in out.iter_mut().enumerate().take(c) {
                *o =
                    0.0 + w00 * d[p00 + k] + w10 * d[p10 + k] + w01 * d[p01 + k] + w11 * d[p11 + k];
            }
            return true;
        }
        for (k, o) in out.iter_mut().enumerate().take(c) {
            let mut v = 0.0f32;
            for (p, wt) in [(p00, w00), (p10, w10), (p01, w01), (p11, w11)] {
                if wt != 0.0 {
                    let s = l.data[p + k];
                    if s.is_nan() {
                        return false;
                    }
                    v += wt * s;
                }
            }
            *o = v;
        }
        true
    }

    /// Trilinear sample at level-0 pixel coordinates for a footprint of `footprint_px` level-0
    /// pixels (the side of the ground area one sample stands for). Footprints up to one pixel
    /// sample level 0 bilinearly; larger ones blend levels `floor(lod)` and `floor(lod) + 1` with
    /// `lod = log2(footprint_px)`, clamped to the coarsest level.
    #[inline]
    pub fn sample(&self, col0: f64, row0: f64, footprint_px: f64, out: &mut [f32]) -> bool {
        self.sample_lod(self.lod(footprint_px), col0, row0, out)
    }

    /// The levels and blend weight [`Self::sample`] uses for a footprint of `footprint_px`
    /// level-0 pixels (one logarithm: shared by the samples of one pixel).
    #[inline]
    pub fn lod(&self, footprint_px: f64) -> Lod {
        let lod = if footprint_px > 1.0 {
            footprint_px.log2()
        } else {
            0.0
        };
        let max_level = (self.levels.len() - 1) as f64;
        let lod = lod.min(max_level);
        let l0 = lod.floor();
        Lod {
            level: l0 as usize, // ok: 0 <= lod <= max_level
            blend: (lod - l0) as f32,
        }
    }

    /// [`Self::sample`] with the levels chosen beforehand by [`Self::lod`].
    #[inline]
    pub fn sample_lod(&self, lod: Lod, col0: f64, row0: f64, out: &mut [f32]) -> bool {
        let (l0, t) = (lod.level, lod.blend);
        if t <= 1e-4 || l0 + 1 >= self.levels.len() {
            return self.sample_level(l0, col0, row0, out);
        }
        let mut hi = [0.0f32; 3];
        if !self.sample_level(l0, col0, row0, out)
            || !self.sample_level(l0 + 1, col0, row0, &mut hi)
        {
            return false;
        }
        for (o, h) in out.iter_mut().zip(hi.iter()).take(self.channels) {
            *o += t * (h - *o);
        }
        true
    }
}

/// Pyramid levels of one footprint: `level` and `level + 1` blended by `blend` (0-1).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Lod {
    /// The finer level.
    pub level: usize,
    /// Weight of `level + 1`, 0-1.
    pub blend: f32,
}

/// 2 x 2 box average over valid samples (NaN when none of the up to four is valid).
fn downsample(src: &Level, channels: usize) -> Level {
    let (w, h) = (src.width.div_ceil(2), src.height.div_ceil(2));
    let mut data = vec![f32::NAN; w * h * channels];
    for j in 0..h {
        for i in 0..w {
            for c in 0..channels {
                let (mut sum, mut n) = (0.0f32, 0u32);
                for (di, dj) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                    let (si, sj) = (2 * i + di, 2 * j + dj);
                    if si < src.width && sj < src.height {
                        let v = src.data[(sj * src.width + si) * channels + c];
                        if !v.is_nan() {
                            sum += v;
                            n += 1;
                        }
                    }
                }
                if n > 0 {
                    data[(j * w + i) * channels + c] = sum / n as f32;
                }
            }
        }
    }
    Level::new(w, h, data)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn raster(w: usize, h: usize, bands: usize, f: impl Fn(usize, usize, usize) -> u8) -> Raster {
        let mut v = Vec::with_capacity(w * h * bands);
        for r in 0..h {
            for c in 0..w {
                for b in 0..bands {
                    v.push(f(c, r, b));
                }
            }
        }
        let gt = GeoTransform::north_up(1000.0, 2000.0, 2.0, 2.0).unwrap();
        Raster::new(
            w,
            h,
            bands,
            RasterData::U8(v),
            gt,
            Crs::WebMercator,
            Some(0.0),
        )
        .unwrap()
    }

    #[test]
    fn grey_is_luma_and_rgb_replicates() {
        let r = raster(4, 4, 4, |_, _, b| [100, 200, 50, 255][b]);
        let p = OrthoPyramid::new(&r, ColourMode::Grey);
        let mut out = [0.0f32; 3];
        assert!(p.sample_level(0, 1.5, 1.5, &mut out));
        let luma = 0.299 * 100.0 + 0.587 * 200.0 + 0.114 * 50.0;
        assert!((out[0] - luma).abs() < 1e-3, "{out:?}");
        let one = raster(4, 4, 1, |c, _, _| 10 + c as u8);
        let p = OrthoPyramid::new(&one, ColourMode::Rgb);
        assert!(p.sample_level(0, 2.5, 0.5, &mut out));
        assert_eq!(out, [12.0; 3]);
    }

    #[test]
    fn levels_average_and_track_geometry() {
        // 8 x 6 checkerboard of 0/200 (nodata 0 disabled by using 1 instead).
        let r = raster(
            8,
            6,
            1,
            |c, row, _| if (c + row) % 2 == 0 { 1 } else { 201 },
        );
        let p = OrthoPyramid::new(&r, ColourMode::Grey);
        assert_eq!(p.level_size(0), Some((8, 6)));
        assert_eq!(p.level_size(1), Some((4, 3)));
        assert_eq!(p.level_size(2), Some((2, 2)));
        assert_eq!(p.levels(), 3);
        let mut out = [0.0f32; 1];
        // Level 1 is flat at the mean.
        for (c, r) in [(0.3, 0.2), (3.3, 4.1), (7.9, 5.9)] {
            assert!(p.sample_level(1, c, r, &mut out));
            assert!((out[0] - 101.0).abs() < 1e-4);
        }
        // Trilinear with a footprint of 2 px = level 1 exactly; 1 px = level 0.
        assert!(p.sample(1.5, 0.5, 2.0, &mut out));
        assert!((out[0] - 101.0).abs() < 1e-4);
        assert!(p.sample(1.5, 0.5, 1.0, &mut out));
        assert_eq!(out[0], 201.0);
        // sqrt(2) px: half way between 201 and 101.
        assert!(p.sample(1.5, 0.5, 2f64.sqrt(), &mut out));
        assert!((out[0] - 151.0).abs() < 1e-3, "{out:?}");
        // Whole raster area renders (outer half-pixel margin clamped), outside does not.
        assert!(p.sample_level(0, 0.0, 0.0, &mut out) && out[0] == 1.0);
        assert!(p.sample_level(0, 8.0, 6.0, &mut out));
        assert!(!p.sample_level(0, 8.01, 3.0, &mut out));
        assert!(!p.sample_level(0, f64::NAN, 3.0, &mut out));
        assert!(!p.sample_level(5, 1.0, 1.0, &mut out));
    }

    #[test]
    fn nodata_is_missing_and_pyramid_fills_partially() {
        // Pixel (2, 2) is nodata (0).
        let r = raster(4, 4, 1, |c, row, _| if (c, row) == (2, 2) { 0 } else { 50 });
        let p = OrthoPyramid::new(&r, ColourMode::Grey);
        let mut out = [0.0f32; 1];
        assert!(!p.sample_level(0, 2.5, 2.5, &mut out));
        assert!(!p.sample_level(0, 2.2, 2.9, &mut out));
        assert!(p.sample_level(0, 1.5, 1.5, &mut out));
        // Level 1 averages the three valid samples of that block.
        assert!(p.sample_level(1, 2.5 * 2.0 - 1.0, 2.5 * 2.0 - 1.0, &mut out));
        assert_eq!(out[0], 50.0);
    }
}
