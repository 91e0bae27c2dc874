//! Georeferenced rasters: sample storage, the affine pixel <-> map transform, nodata-aware
//! bilinear sampling.
//!
//! # Pixel convention (read this before using pixel coordinates)
//!
//! Continuous pixel coordinates `(col, row)` follow GDAL's "pixel is area" convention:
//! **`(0.0, 0.0)` is the outer top-left corner of the first pixel**, `(width, height)` the outer
//! bottom-right corner of the last pixel, and the **centre of pixel `(i, j)` is at
//! `(i + 0.5, j + 0.5)`**. `col` grows to the right (image x), `row` grows down (image y).
//!
//! The affine geotransform has GDAL's coefficient order `[c0, c1, c2, c3, c4, c5]`:
//!
//! ```text
//! x_m = c0 + c1 * col + c2 * row
//! y_m = c3 + c4 * col + c5 * row
//! ```
//!
//! so for a north-up image `c0, c3` are the map coordinates of the top-left corner, `c1` the pixel
//! width and `c5` the (negative) pixel height. GeoTIFF files written as "pixel is point" are
//! converted to this convention when loaded (see `geotiff`).
//!
//! # Samples
//!
//! Samples are stored band-interleaved by pixel ("chunky", like `image::RgbImage`): sample
//! `(col, row, band)` is at index `(row * width + col) * bands + band`. 8-bit files stay `u8`
//! (cheap imagery), 16-bit unsigned stays `u16`; every other sample type (int16, (u)int32, float32,
//! float64) is stored as `f32` (exact for int16; float64 and 32-bit integers are rounded to the
//! nearest `f32`, i.e. 24 significant bits, 0.06 mm at 1000 m).
//!
//! # Nodata
//!
//! One nodata value applies to every band (GDAL_NODATA semantics). A sample is "missing" when it
//! equals the nodata value or is NaN (NaN is always missing, with or without a nodata value).
//!
//! # Bilinear sampling
//!
//! Bilinear interpolation between the four pixel centres around the query point: with
//! `fx = col - 0.5`, `fy = row - 0.5`, `i = floor(fx)`, `a = fx - i` (same for `j`, `b`),
//! `v = (1-a)(1-b) s[i,j] + a(1-b) s[i+1,j] + (1-a) b s[i,j+1] + a b s[i+1,j+1]`.
//! It returns `None` when any contributing sample (a sample with non-zero weight) is outside the
//! raster or missing. Consequently the outer half-pixel margin of the raster is not sampleable
//! (except exactly on the outermost pixel centres).

use super::Crs;

/// Errors building a raster or a geotransform from in-memory parts.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum RasterError {
    /// The geotransform has a non-finite coefficient or is singular.
    #[error("geotransform {} is invalid: {reason}", crate::text::numbers(coeffs))]
    BadGeoTransform {
        /// The coefficients in GDAL order `c0..c5`.
        coeffs: [f64; 6],
        /// What is wrong with them.
        reason: &'static str,
    },
    /// Width, height or band count is zero, or their product overflows.
    #[error("raster dimensions {width} x {height} x {bands} bands are invalid")]
    BadDimensions {
        /// Width, pixels.
        width: usize,
        /// Height, pixels.
        height: usize,
        /// Bands per pixel.
        bands: usize,
    },
    /// The sample buffer length does not match width * height * bands.
    #[error("sample buffer holds {got} samples, expected {expected} (width * height * bands)")]
    DataLength {
        /// Samples in the buffer.
        got: usize,
        /// `width * height * bands`.
        expected: usize,
    },
}

/// Affine transform between continuous pixel coordinates `(col, row)` (corner convention, see the
/// module doc) and map coordinates `(x_m, y_m)` of the raster's CRS.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GeoTransform {
    c: [f64; 6],
    inv: [f64; 6],
}

impl GeoTransform {
    /// Builds a transform from GDAL-ordered coefficients `[c0, c1, c2, c3, c4, c5]`
    /// (`x = c0 + c1 col + c2 row`, `y = c3 + c4 col + c5 row`). Rejects non-finite or singular ones.
    pub fn new(coeffs: [f64; 6]) -> Result<Self, RasterError> {
        if coeffs.iter().any(|v| !v.is_finite()) {
            return Err(RasterError::BadGeoTransform {
                coeffs,
                reason: "non-finite coefficient",
            });
        }
        let [c0, c1, c2, c3, c4, c5] = coeffs;
        let det = c1 * c5 - c2 * c4;
        let scale = (c1.abs() + c2.abs()) * (c4.abs() + c5.abs());
        if det == 0.0 || !det.is_finite() || det.abs() <= 1e-12 * scale {
            return Err(RasterError::BadGeoTransform {
                coeffs,
                reason: "singular (zero pixel size or collinear axes)",
            });
        }
        // Inverse: col = i0 + i1 x + i2 y, row = i3 + i4 x + i5 y.
        let i1 = c5 / det;
        let i2 = -c2 / det;
        let i4 = -c4 / det;
        let i5 = c1 / det;
        let i0 = -(i1 * c0 + i2 * c3);
        let i3 = -(i4 * c0 + i5 * c3);
        Ok(Self {
            c: coeffs,
            inv: [i0, i1, i2, i3, i4, i5],
        })
    }

    /// North-up transform: top-left corner `(x0_m, y0_m)`, pixel size `px_m` (x) and `py_m` (the
    /// row step is `-py_m`, i.e. pass a positive number for a normal north-up image).
    pub fn north_up(x0_m: f64, y0_m: f64, px_m: f64, py_m: f64) -> Result<Self, RasterError> {
        Self::new([x0_m, px_m, 0.0, y0_m, 0.0, -py_m])
    }

    /// GDAL-ordered coefficients `[c0, c1, c2, c3, c4, c5]`.
    pub fn coeffs(&self) -> [f64; 6] {
        self.c
    }

    /// Continuous pixel coordinates (corner convention) -> map coordinates `(x_m, y_m)`.
    #[inline]
    pub fn pixel_to_map(&self, col: f64, row: f64) -> (f64, f64) {
        let c = &self.c;
        (
            c[0] + c[1] * col + c[2] * row,
            c[3] + c[4] * col + c[5] * row,
        )
    }

    /// Map coordinates `(x_m, y_m)` -> continuous pixel coordinates `(col, row)` (corner convention).
    #[inline]
    pub fn map_to_pixel(&self, x_m: f64, y_m: f64) -> (f64, f64) {
        let i = &self.inv;
        (
            i[0] + i[1] * x_m + i[2] * y_m,
            i[3] + i[4] * x_m + i[5] * y_m,
        )
    }

    /// Linear part only: a map-space displacement `(dx_m, dy_m)` -> pixel displacement.
    #[inline]
    pub fn map_delta_to_pixel(&self, dx_m: f64, dy_m: f64) -> (f64, f64) {
        let i = &self.inv;
        (i[1] * dx_m + i[2] * dy_m, i[4] * dx_m + i[5] * dy_m)
    }

    /// Ground size of one pixel step along columns and along rows, metres (or degrees for a
    /// geographic CRS): `(|(c1, c4)|, |(c2, c5)|)`.
    pub fn pixel_size(&self) -> (f64, f64) {
        (self.c[1].hypot(self.c[4]), self.c[2].hypot(self.c[5]))
    }

    /// Map-coordinate bounding box of the outer edges of a `width x height` pixel raster (for a
    /// rotated transform, the box around the four outer corners).
    pub fn bounds(&self, width: usize, height: usize) -> Bounds {
        let (w, h) = (width as f64, height as f64);
        let corners = [
            self.pixel_to_map(0.0, 0.0),
            self.pixel_to_map(w, 0.0),
            self.pixel_to_map(0.0, h),
            self.pixel_to_map(w, h),
        ];
        let mut b = Bounds {
            min_x_m: f64::INFINITY,
            min_y_m: f64::INFINITY,
            max_x_m: f64::NEG_INFINITY,
            max_y_m: f64::NEG_INFINITY,
        };
        for (x, y) in corners {
            b.min_x_m = b.min_x_m.min(x);
            b.min_y_m = b.min_y_m.min(y);
            b.max_x_m = b.max_x_m.max(x);
            b.max_y_m = b.max_y_m.max(y);
        }
        b
    }

    /// The transform of the sub-raster whose pixel `(0, 0)` is this raster's pixel
    /// `(col0, row0)`: same linear part, origin moved to `pixel_to_map(col0, row0)`.
    pub fn window(&self, col0: usize, row0: usize) -> Self {
        if col0 == 0 && row0 == 0 {
            return *self;
        }
        let (x0, y0) = self.pixel_to_map(col0 as f64, row0 as f64);
        let c = self.c;
        let inv = self.inv;
        // Inverse of the shifted transform: the same linear part, offsets shifted by the window.
        Self {
            c: [x0, c[1], c[2], y0, c[4], c[5]],
            inv: [
                inv[0] - col0 as f64,
                inv[1],
                inv[2],
                inv[3] - row0 as f64,
                inv[4],
                inv[5],
            ],
        }
    }

    /// True when the transform has no rotation/shear terms (`c2 == c4 == 0`).
    pub fn is_axis_aligned(&self) -> bool {
        self.c[2] == 0.0 && self.c[4] == 0.0
    }
}

/// Axis-aligned bounding box in map coordinates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bounds {
    /// Western edge (smallest easting), metres (degrees in the geographic CRS).
    pub min_x_m: f64,
    /// Southern edge (smallest northing).
    pub min_y_m: f64,
    /// Eastern edge (largest easting).
    pub max_x_m: f64,
    /// Northern edge (largest northing).
    pub max_y_m: f64,
}

impl Bounds {
    /// True when `(x_m, y_m)` lies inside or on the boundary.
    pub fn contains(&self, x_m: f64, y_m: f64) -> bool {
        x_m >= self.min_x_m && x_m <= self.max_x_m && y_m >= self.min_y_m && y_m <= self.max_y_m
    }
}

/// Sample type of the source file (the storage type is in [`RasterData`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SampleType {
    /// 8-bit unsigned integer (stored as `RasterData::U8`).
    U8,
    /// 16-bit unsigned integer (stored as `RasterData::U16`).
    U16,
    /// 16-bit signed integer (stored as `f32`).
    I16,
    /// 32-bit unsigned integer (stored as `f32`).
    U32,
    /// 32-bit signed integer (stored as `f32`).
    I32,
    /// 32-bit float.
    F32,
    /// 64-bit float (stored as `f32`).
    F64,
}

/// `8-bit unsigned`, `32-bit float`, ... (messages).
impl std::fmt::Display for SampleType {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            SampleType::U8 => "8-bit unsigned",
            SampleType::U16 => "16-bit unsigned",
            SampleType::I16 => "16-bit signed",
            SampleType::U32 => "32-bit unsigned",
            SampleType::I32 => "32-bit signed",
            SampleType::F32 => "32-bit float",
            SampleType::F64 => "64-bit float",
        })
    }
}

/// Sample storage, band-interleaved by pixel (see the module doc).
#[derive(Debug, Clone, PartialEq)]
pub enum RasterData {
    /// 8-bit unsigned samples (imagery).
    U8(Vec<u8>),
    /// 16-bit unsigned samples (imagery).
    U16(Vec<u16>),
    /// Float samples (heights, and every other source type converted).
    F32(Vec<f32>),
}

impl RasterData {
    /// Number of samples.
    pub fn len(&self) -> usize {
        match self {
            RasterData::U8(v) => v.len(),
            RasterData::U16(v) => v.len(),
            RasterData::F32(v) => v.len(),
        }
    }

    /// True when there are no samples.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The samples if stored as `u8` (8-bit imagery), e.g. to wrap them in an `image` buffer
    /// without copying.
    pub fn as_u8(&self) -> Option<&[u8]> {
        match self {
            RasterData::U8(v) => Some(v),
            _ => None,
        }
    }

    /// The samples if stored as `u16`.
    pub fn as_u16(&self) -> Option<&[u16]> {
        match self {
            RasterData::U16(v) => Some(v),
            _ => None,
        }
    }

    /// The samples if stored as `f32`.
    pub fn as_f32(&self) -> Option<&[f32]> {
        match self {
            RasterData::F32(v) => Some(v),
            _ => None,
        }
    }

    /// Sample at a flat index as f64 (caller guarantees the index is in range).
    #[inline]
    fn get(&self, idx: usize) -> f64 {
        match self {
            RasterData::U8(v) => f64::from(v[idx]),
            RasterData::U16(v) => f64::from(v[idx]),
            RasterData::F32(v) => f64::from(v[idx]),
        }
    }
}

/// A georeferenced raster: `bands` samples per pixel, `width x height` pixels.
#[derive(Debug, Clone, PartialEq)]
pub struct Raster {
    width: usize,
    height: usize,
    bands: usize,
    data: RasterData,
    transform: GeoTransform,
    crs: Crs,
    nodata: Option<f64>,
    source_type: SampleType,
}

impl Raster {
    /// Builds a raster from parts. `data` is band-interleaved by pixel and must hold exactly
    /// `width * height * bands` samples. A NaN `nodata` is stored as `None` (NaN samples are always
    /// missing anyway). The source sample type is set to the storage type;
    /// change it with [`Raster::with_source_type`].
    pub fn new(
        width: usize,
        height: usize,
        bands: usize,
        data: RasterData,
        transform: GeoTransform,
        crs: Crs,
        nodata: Option<f64>,
    ) -> Result<Self, RasterError> {
        let source_type = match data {
            RasterData::U8(_) => SampleType::U8,
            RasterData::U16(_) => SampleType::U16,
            RasterData::F32(_) => SampleType::F32,
        };
        let expected = width
            .checked_mul(height)
            .and_then(|n| n.checked_mul(bands))
            .filter(|&n| n > 0)
            .ok_or(RasterError::BadDimensions {
                width,
                height,
                bands,
            })?;
        if data.len() != expected {
            return Err(RasterError::DataLength {
                got: data.len(),
                expected,
            });
        }
        let nodata = nodata.filter(|v| !v.is_nan());
        Ok(Self {
            width,
            height,
            bands,
            data,
            transform,
            crs,
            nodata,
            source_type,
        })
    }

    /// Records the sample type the data had in its source file.
    pub fn with_source_type(mut self, source_type: SampleType) -> Self {
        self.source_type = source_type;
        self
    }

    /// Width in pixels (columns).
    pub fn width(&self) -> usize {
        self.width
    }
    /// Height in pixels (rows).
    pub fn height(&self) -> usize {
        self.height
    }
    /// Samples per pixel.
    pub fn bands(&self) -> usize {
        self.bands
    }
    /// Sample storage (band-interleaved by pixel).
    pub fn data(&self) -> &RasterData {
        &self.data
    }
    /// Consumes the raster and returns its sample storage.
    pub fn into_data(self) -> RasterData {
        self.data
    }
    /// Pixel <-> map transform.
    pub fn transform(&self) -> &GeoTransform {
        &self.transform
    }
    /// Horizontal CRS of the map coordinates.
    pub fn crs(&self) -> Crs {
        self.crs
    }
    /// Nodata value (applies to all bands); `None` when the file declared none or declared NaN.
    /// NaN samples are missing regardless.
    pub fn nodata(&self) -> Option<f64> {
        self.nodata
    }
    /// Sample type in the source file.
    pub fn source_type(&self) -> SampleType {
        self.source_type
    }

    /// Map-coordinate bounding box of the outer pixel edges (for a rotated transform, the box
    /// around the four outer corners).
    pub fn bounds(&self) -> Bounds {
        self.transform.bounds(self.width, self.height)
    }

    /// Map coordinates of the centre of pixel `(col, row)` (integer indices).
    pub fn pixel_centre_to_map(&self, col: usize, row: usize) -> (f64, f64) {
        self.transform
            .pixel_to_map(col as f64 + 0.5, row as f64 + 0.5)
    }

    /// Raw sample value, `None` only when the indices are out of range (nodata is returned as is).
    pub fn sample(&self, col: usize, row: usize, band: usize) -> Option<f64> {
        if col >= self.width || row >= self.height || band >= self.bands {
            return None;
        }
        Some(self.data.get((row * self.width + col) * self.bands + band))
    }

    /// Sample value, `None` when out of range or missing (nodata or NaN).
    pub fn value(&self, col: usize, row: usize, band: usize) -> Option<f64> {
        self.sample(col, row, band).filter(|&v| !self.is_missing(v))
    }

    /// True when `v` is the nodata value or NaN.
    #[inline]
    pub fn is_missing(&self, v: f64) -> bool {
        v.is_nan() || self.nodata == Some(v)
    }

    /// Bilinear weights setup: returns `(i0, i1, j0, j1, a, b)` (pixel indices of the contributing
    /// samples and fractional weights), or `None` when a contributing sample is outside.
    #[inline]
    fn bilinear_cell(&self, col: f64, row: f64) -> Option<(usize, usize, usize, usize, f64, f64)> {
        let fx = col - 0.5;
        let fy = row - 0.5;
        if !(fx.is_finite() && fy.is_finite()) {
            return None;
        }
        let (i0, i1, a) = axis_cell(fx, self.width)?;
        let (j0, j1, b) = axis_cell(fy, self.height)?;
        Some((i0, i1, j0, j1, a, b))
    }

    /// Bilinear value of `band` at continuous pixel coordinates (corner convention). `None` when a
    /// contributing sample is outside or missing, or `band` is out of range.
    pub fn bilinear_px(&self, col: f64, row: f64, band: usize) -> Option<f64> {
        if band >= self.bands {
            return None;
        }
        let (i0, i1, j0, j1, a, b) = self.bilinear_cell(col, row)?;
        let s = |i: usize, j: usize| -> Option<f64> {
            let v = self.data.get((j * self.width + i) * self.bands + band);
            (!self.is_missing(v)).then_some(v)
        };
        let s00 = s(i0, j0)?;
        let s10 = s(i1, j0)?;
        let s01 = s(i0, j1)?;
        let s11 = s(i1, j1)?;
        Some(bilerp(s00, s10, s01, s11, a, b))
    }

    /// Bilinear value of `band` at map coordinates. See [`Raster::bilinear_px`].
    pub fn bilinear(&self, x_m: f64, y_m: f64, band: usize) -> Option<f64> {
        let (col, row) = self.transform.map_to_pixel(x_m, y_m);
        self.bilinear_px(col, row, band)
    }

    /// Bilinear values of all bands at map coordinates into `out` (`out.len()` must equal
    /// `bands()`). Returns false (and leaves `out` unspecified) when `out` has the wrong length or
    /// any contributing sample of any band is outside or missing.
    pub fn bilinear_all_bands(&self, x_m: f64, y_m: f64, out: &mut [f64]) -> bool {
        if out.len() != self.bands {
            return false;
        }
        let (col, row) = self.transform.map_to_pixel(x_m, y_m);
        let Some((i0, i1, j0, j1, a, b)) = self.bilinear_cell(col, row) else {
            return false;
        };
        let base = |i: usize, j: usize| (j * self.width + i) * self.bands;
        let (p00, p10, p01, p11) = (base(i0, j0), base(i1, j0), base(i0, j1), base(i1, j1));
        for (band, o) in out.iter_mut().enumerate() {
            let s00 = self.data.get(p00 + band);
            let s10 = self.data.get(p10 + band);
            let s01 = self.data.get(p01 + band);
            let s11 = self.data.get(p11 + band);
            if [s00, s10, s01, s11].iter().any(|&v| self.is_missing(v)) {
                return false;
            }
            *o = bilerp(s00, s10, s01, s11, a, b);
        }
        true
    }
}

/// Bilinear blend of four corner values with fractions `a` (along columns) and `b` (along rows).
#[inline]
pub fn bilerp(s00: f64, s10: f64, s01: f64, s11: f64, a: f64, b: f64) -> f64 {
    let top = s00 + a * (s10 - s00);
    let bottom = s01 + a * (s11 - s01);
    top + b * (bottom - top)
}

/// For a centre-index coordinate `f` on an axis of `n` samples: the two contributing indices and
/// the fraction. A zero fraction means the second sample does not contribute, so it is clamped to
/// the first (this lets the outermost pixel centres be sampled exactly).
#[inline]
fn axis_cell(f: f64, n: usize) -> Option<(usize, usize, f64)> {
    if f < 0.0 || f > (n - 1) as f64 {
        return None;
    }
    let i0f = f.floor();
    let a = f - i0f;
    let i0 = i0f as usize; // ok: 0 <= f <= n-1 checked above
    if a == 0.0 {
        Some((i0, i0, 0.0))
    } else {
        Some((i0, i0 + 1, a))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn ramp_raster(nodata: Option<f64>) -> Raster {
        // 4 x 3, value = 10 col + row, band 1 = 2 * band 0.
        let (w, h) = (4usize, 3usize);
        let mut v = Vec::new();
        for r in 0..h {
            for c in 0..w {
                let s = 10.0 * c as f32 + r as f32;
                v.push(s);
                v.push(2.0 * s);
            }
        }
        let gt = GeoTransform::north_up(1000.0, 2000.0, 2.0, 2.0).unwrap();
        Raster::new(
            w,
            h,
            2,
            RasterData::F32(v),
            gt,
            Crs::Utm {
                zone: 14,
                north: true,
            },
            nodata,
        )
        .unwrap()
    }

    #[test]
    fn corner_and_centre_convention() {
        let r = ramp_raster(None);
        assert_eq!(r.transform().pixel_to_map(0.0, 0.0), (1000.0, 2000.0));
        assert_eq!(r.pixel_centre_to_map(0, 0), (1001.0, 1999.0));
        assert_eq!(r.pixel_centre_to_map(3, 2), (1007.0, 1995.0));
        let b = r.bounds();
        assert_eq!(
            (b.min_x_m, b.min_y_m, b.max_x_m, b.max_y_m),
            (1000.0, 1994.0, 1008.0, 2000.0)
        );
        // Bilinear at pixel centres returns the sample exactly, including the last one.
        assert_eq!(r.bilinear(1001.0, 1999.0, 0), Some(0.0));
        assert_eq!(r.bilinear(1007.0, 1995.0, 0), Some(32.0));
        assert_eq!(r.bilinear(1007.0, 1995.0, 1), Some(64.0));
        // Half way between centres (col 1.5 -> 2.5 etc.).
        let v = r.bilinear(1004.0, 1997.0, 0).unwrap();
        assert!((v - 16.0).abs() < 1e-12, "{v}");
        // Outer half-pixel margin is not sampleable.
        assert_eq!(r.bilinear(1000.5, 1999.0, 0), None);
        assert_eq!(r.bilinear(1007.5, 1995.0, 0), None);
        assert_eq!(r.bilinear(f64::NAN, 1995.0, 0), None);
        assert_eq!(r.bilinear(1004.0, 1997.0, 2), None);
        let mut out = [0.0; 2];
        assert!(r.bilinear_all_bands(1004.0, 1997.0, &mut out));
        assert!((out[0] - 16.0).abs() < 1e-12 && (out[1] - 32.0).abs() < 1e-12);
        let mut wrong = [0.0; 3];
        assert!(!r.bilinear_all_bands(1004.0, 1997.0, &mut wrong));
    }

    #[test]
    fn nodata_blocks_only_contributing_samples() {
        // value at (col 1,row 1) = 11; mark it nodata.
        let r = ramp_raster(Some(11.0));
        assert_eq!(r.value(1, 1, 0), None);
        assert_eq!(r.sample(1, 1, 0), Some(11.0));
        // A query touching pixel (1,1) fails...
        assert_eq!(r.bilinear_px(1.7, 1.2, 0), None);
        let mut out = [0.0; 2];
        assert!(!r.bilinear_all_bands(1003.4, 1997.6, &mut out));
        // ...one whose cell excludes it works.
        assert!(r.bilinear_px(2.7, 1.2, 0).is_some());
        // Exactly on the centre of pixel (2,1): neighbours have zero weight.
        assert_eq!(r.bilinear_px(2.5, 1.5, 0), Some(21.0));
        // The other band has value 22 there, which is not nodata.
        assert_eq!(r.bilinear_px(1.5, 1.5, 1), Some(22.0));
    }

    #[test]
    fn nan_samples_are_missing() {
        let gt = GeoTransform::north_up(0.0, 0.0, 1.0, 1.0).unwrap();
        let r = Raster::new(
            2,
            2,
            1,
            RasterData::F32(vec![1.0, f32::NAN, 3.0, 4.0]),
            gt,
            Crs::WebMercator,
            Some(f64::NAN),
        )
        .unwrap();
        assert_eq!(r.nodata(), None);
        assert_eq!(r.bilinear_px(1.0, 1.0, 0), None);
        assert_eq!(r.bilinear_px(0.5, 1.2, 0), Some(1.0 + 0.7 * 2.0));
    }

    #[test]
    fn constructor_rejects_bad_parts() {
        let gt = GeoTransform::north_up(0.0, 0.0, 1.0, 1.0).unwrap();
        let mk = |w, h, b, n| {
            Raster::new(
                w,
                h,
                b,
                RasterData::U8(vec![0; n]),
                gt,
                Crs::Geographic,
                None,
            )
        };
        assert!(matches!(
            mk(0, 2, 1, 0),
            Err(RasterError::BadDimensions { .. })
        ));
        assert!(matches!(
            mk(2, 2, 1, 3),
            Err(RasterError::DataLength { .. })
        ));
        assert!(mk(2, 2, 1, 4).is_ok());
        assert!(GeoTransform::new([0.0, 1.0, 0.0, 0.0, 0.0, 0.0]).is_err());
        assert!(GeoTransform::new([0.0, 1.0, 0.0, f64::NAN, 0.0, -1.0]).is_err());
        assert!(GeoTransform::new([0.0, 1.0, 2.0, 0.0, 2.0, 4.0]).is_err());
    }

    proptest! {
        #[test]
        fn geotransform_round_trip(
            c0 in -1e6f64..1e6, c1 in 0.01f64..100.0, c2 in -10.0f64..10.0,
            c3 in -1e7f64..1e7, c4 in -10.0f64..10.0, c5 in -100.0f64..-0.01,
            col in -100.0f64..5000.0, row in -100.0f64..5000.0,
        ) {
            prop_assume!((c1 * c5 - c2 * c4).abs() > 1e-3);
            let gt = GeoTransform::new([c0, c1, c2, c3, c4, c5]).unwrap();
            let (x, y) = gt.pixel_to_map(col, row);
            let (c, r) = gt.map_to_pixel(x, y);
            let scale = 1e-9 * (1.0 + x.abs().max(y.abs())) / (c1 * c5 - c2 * c4).abs().sqrt();
            prop_assert!((c - col).abs() < 1e3 * scale.max(1e-9), "{c} vs {col}");
            prop_assert!((r - row).abs() < 1e3 * scale.max(1e-9), "{r} vs {row}");
            let (dc, dr) = gt.map_delta_to_pixel(c1, c4);
            prop_assert!((dc - 1.0).abs() < 1e-9 && dr.abs() < 1e-9);
        }

        #[test]
        fn bilinear_reproduces_affine_fields(
            col in 0.5f64..3.5, row in 0.5f64..2.5,
        ) {
            // The ramp is affine in (col,row), so bilinear must reproduce it exactly.
            let r = ramp_raster(None);
            let v = r.bilinear_px(col, row, 0).unwrap();
            let expect = 10.0 * (col - 0.5) + (row - 0.5);
            prop_assert!((v - expect).abs() < 1e-9);
        }
    }
}
