//! The reference the fix matches against: georeferenced SURF features with DEM heights, in pyramid
//! levels, selectable by a map-grid rectangle. [`Reference`] is implemented by the memory-mapped
//! `.vnm` map (`crate::map`) and by [`MemoryReference`], which extracts the features from an
//! orthophoto held in memory (tests, the simulator, small maps).
//!
//! Pixel convention: GeoTIFF rasters are GDAL style (pixel (0,0) is the outer corner, pixel centres
//! at i+0.5), SURF keypoints have pixel centres at integers, so keypoint `(u, v)` of a level image
//! lies at raster pixel `(u + 0.5, v + 0.5)` of that level.

use crate::geo::Crs;
use crate::geo::dem::Dem;
use crate::geo::raster::Raster;
use crate::vision::{DescriptorKind, FeatureSpec, GrayImage, VisionError};

/// One reference feature: its map-grid position, height above mean sea level (the DEM's datum),
/// scale on the ground and Laplacian sign.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RefFeature {
    /// Map-grid easting, metres.
    pub x_m: f64,
    /// Map-grid northing, metres.
    pub y_m: f64,
    /// Height above mean sea level (the DEM's datum), metres.
    pub z_amsl_m: f64,
    /// SURF scale `s` on the ground, metres.
    pub scale_m: f32,
    /// Sign of the Laplacian: -1 bright blob, +1 dark blob (SURF's); matching pairs only equal
    /// signs.
    pub laplacian: i8,
}

/// Features selected from one level, with their descriptors (row-major, `kind.stride()` floats per
/// row, zero padded beyond `kind.len()`, the layout of `vision::Features`).
#[derive(Debug, Clone, PartialEq)]
pub struct RefSelection {
    /// The selected features.
    pub features: Vec<RefFeature>,
    /// Their descriptors, one row per feature in the same order.
    pub descriptors: Vec<f32>,
    /// The descriptor kind, which sets the row length.
    pub kind: DescriptorKind,
}

impl RefSelection {
    /// An empty selection of the given descriptor kind.
    pub fn empty(kind: DescriptorKind) -> Self {
        Self {
            features: Vec::new(),
            descriptors: Vec::new(),
            kind,
        }
    }
}

/// How a map's heights err against the surface the camera sees, split by what each part does to
/// a fix (docs/map-format.md, "Height uncertainty"). A map's height error is mostly shared by a
/// footprint (a constant height's offset from the ground, a DEM's datum) and changes slowly
/// across it (relief under a constant height, a DEM's tilt), plus what varies from point to
/// point (roofs, trees and cars a DEM does not hold). Treating all of it as independent per
/// point lets the points' scatter average it away and drowns the image's own tilt evidence.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct HeightErrors {
    /// A height error shared by the whole footprint, m (1 sigma): it raises the solved camera
    /// by as much and moves nothing else, so it goes whole into the vertical.
    pub offset_sigma_m: f64,
    /// A height error changing linearly across the footprint, metres per metre (1 sigma per
    /// horizontal axis): it tilts the points against the world, which turns the solved attitude
    /// by as much and moves the camera by it times its height above the ground
    /// (`pose::Priors::map_tilt_sigma_rad`).
    pub slope_sigma: f64,
    /// What is left per point, m (1 sigma): each correspondence's pixel sigma grows by its
    /// image displacement.
    pub point_sigma_m: f64,
}

/// A map the fix can match against.
pub trait Reference: Send + Sync {
    /// The map grid's CRS (x east, y north, metres).
    fn crs(&self) -> Crs;
    /// Ground sample distance of each pyramid level, metres per pixel, finest first.
    fn level_gsd_m(&self) -> Vec<f64>;
    /// Pixel size of the (first) orthophoto the map was built from, metres: the unit of
    /// `map_registration_sigma_px` (`visnav map compare` measures in orthophoto pixels). The
    /// finest level's unless the map was upsampled.
    fn ortho_pixel_m(&self) -> f64 {
        self.level_gsd_m().first().copied().unwrap_or(0.0)
    }
    /// The detector and settings the features were extracted with (the query uses the same).
    fn feature_spec(&self) -> FeatureSpec;
    /// Bounds of the mapped area `[min_x, min_y, max_x, max_y]`, metres.
    fn bounds_m(&self) -> [f64; 4];
    /// Ground height at a map position (AMSL, the DEM's datum), when known.
    fn height_amsl_m(&self, x_m: f64, y_m: f64) -> Option<f64>;
    /// The terrain for ray casting (map grid coordinates, heights AMSL): the map's own, or the
    /// part a map of tiles holds now (lent for the caller's use; a later call may lend another).
    fn dem(&self) -> DemRef<'_>;
    /// Features of `level` whose position lies in `[min_x, min_y, max_x, max_y]`.
    fn select(&self, level: usize, rect_m: [f64; 4]) -> RefSelection;
    /// Standard deviation of the features' heights against the surface the camera sees, metres
    /// (`crate::map::MapHeader::height_sigma_m`); 0: the heights are taken as exact. The part a
    /// whole footprint shares ([`HeightErrors::offset_sigma_m`]).
    fn height_sigma_m(&self) -> f64 {
        0.0
    }
    /// How the heights err, split by what the error does to a fix ([`HeightErrors`]). By default
    /// (a map that states only [`Self::height_sigma_m`]) as a shared offset and again per point,
    /// with no slope.
    fn height_errors(&self) -> HeightErrors {
        let s = self.height_sigma_m();
        HeightErrors {
            offset_sigma_m: s,
            slope_sigma: 0.0,
            point_sigma_m: s,
        }
    }
    /// The grey image of `level` (area matching, `fix::area`); `None` when the map has none
    /// (a version-1 `.vnm`).
    fn level_image(&self, _level: usize) -> Option<MapImage<'_>> {
        None
    }
    /// The grey image of `level` covering the map rectangle `rect_m` (`[min_x, min_y, max_x,
    /// max_y]`) as far as the map holds it, on the level's pixel grid: a map that holds its
    /// levels whole lends the whole image (the default); a map of tiles assembles the loaded
    /// tiles under the rectangle. `None` when there is no level image there.
    fn level_window(&self, level: usize, _rect_m: [f64; 4]) -> Option<LevelWindow<'_>> {
        self.level_image(level).map(LevelWindow::Borrowed)
    }
}

/// The terrain lent by a map ([`Reference::dem`]): the map's own, or one assembled from its tiles
/// and shared with the map while the caller holds it. Dereferences to [`Dem`].
#[derive(Debug, Clone)]
pub enum DemRef<'a> {
    /// The map's own terrain.
    Borrowed(&'a Dem),
    /// A terrain assembled from tiles.
    Shared(std::sync::Arc<Dem>),
}

impl std::ops::Deref for DemRef<'_> {
    type Target = Dem;
    fn deref(&self) -> &Dem {
        match self {
            Self::Borrowed(d) => d,
            Self::Shared(d) => d,
        }
    }
}

/// A level image lent by a map ([`Reference::level_window`]): the map's own bytes, or a window
/// assembled for the caller.
#[derive(Debug, Clone)]
pub enum LevelWindow<'a> {
    /// The map's whole level image.
    Borrowed(MapImage<'a>),
    /// A window assembled from tiles.
    Owned(MapImageBuf),
}

impl LevelWindow<'_> {
    /// The image as a [`MapImage`].
    pub fn image(&self) -> MapImage<'_> {
        match self {
            Self::Borrowed(m) => *m,
            Self::Owned(b) => b.image(),
        }
    }
}

/// An owned level image window: [`MapImage`] with its bytes.
#[derive(Debug, Clone, PartialEq)]
pub struct MapImageBuf {
    /// The grey values, row-major, `width * height` bytes; 0 = no data.
    pub data: Vec<u8>,
    /// Width, pixels.
    pub width: usize,
    /// Height, pixels.
    pub height: usize,
    /// Map-grid easting of the image's west edge, metres.
    pub origin_x_m: f64,
    /// Map-grid northing of the image's north edge, metres.
    pub origin_y_m: f64,
    /// Ground sample distance, metres per pixel.
    pub gsd_m: f64,
}

impl MapImageBuf {
    /// The image as a [`MapImage`].
    pub fn image(&self) -> MapImage<'_> {
        MapImage {
            data: &self.data,
            width: self.width,
            height: self.height,
            origin_x_m: self.origin_x_m,
            origin_y_m: self.origin_y_m,
            gsd_m: self.gsd_m,
        }
    }
}

/// A level's grey image: `width x height` bytes, row 0 north, pixel `(i, j)` centred on
/// `(origin_x_m + (i + 0.5) gsd_m, origin_y_m - (j + 0.5) gsd_m)`; 0 = no data.
#[derive(Debug, Clone, Copy)]
pub struct MapImage<'a> {
    /// The grey values, row-major, `width * height` bytes; 0 = no data.
    pub data: &'a [u8],
    /// Width, pixels.
    pub width: usize,
    /// Height, pixels.
    pub height: usize,
    /// Map-grid easting of the image's west edge, metres.
    pub origin_x_m: f64,
    /// Map-grid northing of the image's north edge, metres.
    pub origin_y_m: f64,
    /// Ground sample distance, metres per pixel.
    pub gsd_m: f64,
}

impl MapImage<'_> {
    /// Continuous pixel coordinates (centres at integers) of a map position.
    pub fn to_px(&self, x_m: f64, y_m: f64) -> [f64; 2] {
        [
            (x_m - self.origin_x_m) / self.gsd_m - 0.5,
            (self.origin_y_m - y_m) / self.gsd_m - 0.5,
        ]
    }

    /// The map position of continuous pixel coordinates.
    pub fn to_map(&self, px: [f64; 2]) -> [f64; 2] {
        [
            self.origin_x_m + (px[0] + 0.5) * self.gsd_m,
            self.origin_y_m - (px[1] + 0.5) * self.gsd_m,
        ]
    }

    /// The `w x h` window with top-left pixel `(x0, y0)` (may reach outside: invalid there).
    pub fn crop(&self, x0: i64, y0: i64, w: usize, h: usize) -> Option<super::area::Plane> {
        super::area::Plane::window([self.width, self.height], x0, y0, w, h, |x, y| {
            let v = self.data[y * self.width + x];
            (v != 0).then_some(f32::from(v))
        })
    }
}

/// Grey bytes of a level image: values rounded into `1..=255`, 0 where missing (NaN).
fn image_bytes(img: &GrayImage) -> Vec<u8> {
    img.data()
        .iter()
        .map(|v| {
            if v.is_finite() {
                v.round().clamp(1.0, 255.0) as u8 // ok: clamped
            } else {
                0
            }
        })
        .collect()
}

/// Features of an orthophoto extracted in memory, level by level (level `L` is the orthophoto
/// averaged over `2^L x 2^L` blocks).
#[derive(Debug)]
pub struct MemoryReference {
    crs: Crs,
    spec: FeatureSpec,
    bounds_m: [f64; 4],
    levels: Vec<(f64, RefSelection)>,
    /// Each level's grey image (`image_bytes`), width and height.
    images: Vec<(Vec<u8>, usize, usize)>,
    /// North-west corner of the orthophoto.
    origin_m: [f64; 2],
    dem: Dem,
}

/// Grey level of an orthophoto (Rec. 601 luma of the first three bands, or band 0), with the
/// raster's nodata/missing samples as NaN.
pub fn raster_grey(raster: &Raster) -> GrayImage {
    let (w, h) = (raster.width(), raster.height());
    let rgb = raster.bands() >= 3;
    GrayImage::from_fn(w, h, |x, y| {
        if rgb {
            match (
                raster.value(x, y, 0),
                raster.value(x, y, 1),
                raster.value(x, y, 2),
            ) {
                (Some(r), Some(g), Some(b)) => (0.299 * r + 0.587 * g + 0.114 * b) as f32,
                _ => f32::NAN,
            }
        } else {
            raster.value(x, y, 0).map_or(f32::NAN, |v| v as f32)
        }
    })
}

/// 2x2 block average (odd trailing row/column dropped); NaN propagates.
pub fn half_size(img: &GrayImage) -> GrayImage {
    let (w, h) = (img.width() / 2, img.height() / 2);
    GrayImage::from_fn(w, h, |x, y| {
        0.25 * (img.get(2 * x, 2 * y)
            + img.get(2 * x + 1, 2 * y)
            + img.get(2 * x, 2 * y + 1)
            + img.get(2 * x + 1, 2 * y + 1))
    })
}

impl MemoryReference {
    /// Extract `n_levels` levels of features from an axis-aligned north-up orthophoto, with heights
    /// from `dem` (same CRS as the orthophoto). Keypoints on or next to missing pixels, or without a
    /// height, are dropped.
    pub fn from_raster(
        raster: &Raster,
        dem: Dem,
        spec: impl Into<FeatureSpec>,
        n_levels: usize,
    ) -> Result<Self, VisionError> {
        let spec = spec.into();
        spec.validate()?;
        let tf = *raster.transform();
        let c = tf.coeffs();
        if !(tf.is_axis_aligned() && c[1] > 0.0 && c[5] < 0.0) {
            return Err(VisionError::InvalidImage(
                "the orthophoto must be north-up and axis-aligned".into(),
            ));
        }
        let detector = spec.detector()?;
        let b = raster.bounds();
        let bounds_m = [b.min_x_m, b.min_y_m, b.max_x_m, b.max_y_m];
        let mut img = raster_grey(raster);
        let mut levels = Vec::new();
        let mut images = Vec::new();
        for level in 0..n_levels.max(1) {
            if img.width() < 64 || img.height() < 64 {
                break;
            }
            let f = 1u32 << level;
            let gsd_m = c[1] * f64::from(f);
            // Missing pixels become the mean so SURF runs; keypoints near them are dropped below.
            let (sum, n) = img
                .data()
                .iter()
                .filter(|v| v.is_finite())
                .fold((0.0f64, 0usize), |(s, n), &v| (s + f64::from(v), n + 1));
            let mean = if n > 0 { (sum / n as f64) as f32 } else { 0.0 };
            let filled = GrayImage::from_fn(img.width(), img.height(), |x, y| {
                let v = img.get(x, y);
                if v.is_finite() { v } else { mean }
            });
            let feats = detector.detect_and_describe(&filled);
            let st = feats.kind().stride();
            let mut sel = RefSelection::empty(feats.kind());
            for (i, k) in feats.keypoints.iter().enumerate() {
                let r = (10.0 * k.scale).ceil() as i64;
                let (kx, ky) = (k.x.round() as i64, k.y.round() as i64);
                let near_missing =
                    [(-r, -r), (r, -r), (-r, r), (r, r), (0, 0)]
                        .iter()
                        .any(|&(dx, dy)| {
                            let (x, y) = (kx + dx, ky + dy);
                            x < 0
                                || y < 0
                                || x >= img.width() as i64
                                || y >= img.height() as i64
                                || !img.get(x as usize, y as usize).is_finite()
                        });
                if near_missing {
                    continue;
                }
                let (x_m, y_m) = tf.pixel_to_map(
                    (f64::from(k.x) + 0.5) * f64::from(f),
                    (f64::from(k.y) + 0.5) * f64::from(f),
                );
                let Some(z) = dem.height_at(x_m, y_m) else {
                    continue;
                };
                sel.features.push(RefFeature {
                    x_m,
                    y_m,
                    z_amsl_m: z,
                    scale_m: k.scale * gsd_m as f32,
                    laplacian: k.laplacian,
                });
                sel.descriptors
                    .extend_from_slice(&feats.descriptors_padded()[i * st..(i + 1) * st]);
            }
            levels.push((gsd_m, sel));
            images.push((image_bytes(&img), img.width(), img.height()));
            img = half_size(&img);
        }
        Ok(Self {
            crs: raster.crs(),
            spec,
            bounds_m,
            levels,
            images,
            origin_m: [c[0], c[3]],
            dem,
        })
    }

    /// Number of features per level.
    pub fn counts(&self) -> Vec<usize> {
        self.levels.iter().map(|(_, s)| s.features.len()).collect()
    }
}

impl Reference for MemoryReference {
    fn crs(&self) -> Crs {
        self.crs
    }
    fn level_gsd_m(&self) -> Vec<f64> {
        self.levels.iter().map(|(g, _)| *g).collect()
    }
    fn feature_spec(&self) -> FeatureSpec {
        self.spec.clone()
    }
    fn bounds_m(&self) -> [f64; 4] {
        self.bounds_m
    }
    fn height_amsl_m(&self, x_m: f64, y_m: f64) -> Option<f64> {
        self.dem.height_at(x_m, y_m)
    }
    fn dem(&self) -> DemRef<'_> {
        DemRef::Borrowed(&self.dem)
    }
    fn level_image(&self, level: usize) -> Option<MapImage<'_>> {
        let (data, width, height) = self.images.get(level)?;
        Some(MapImage {
            data,
            width: *width,
            height: *height,
            origin_x_m: self.origin_m[0],
            origin_y_m: self.origin_m[1],
            gsd_m: self.levels.get(level)?.0,
        })
    }
    fn select(&self, level: usize, rect_m: [f64; 4]) -> RefSelection {
        let Some((_, all)) = self.levels.get(level) else {
            return RefSelection::empty(self.spec.kind());
        };
        let st = all.kind.stride();
        let mut out = RefSelection::empty(all.kind);
        for (i, f) in all.features.iter().enumerate() {
            if f.x_m >= rect_m[0] && f.x_m <= rect_m[2] && f.y_m >= rect_m[1] && f.y_m <= rect_m[3]
            {
                out.features.push(*f);
                out.descriptors
                    .extend_from_slice(&all.descriptors[i * st..(i + 1) * st]);
            }
        }
        out
    }
}

#[cfg(test)]
impl MemoryReference {
    /// Keeps the features `keep` accepts (at every level, descriptors with them) and moves them by
    /// `shift_m` (east, north) while the level images stay: a map whose features share an error
    /// its images do not have, for tests of the checks that compare the two.
    pub(crate) fn edit_features(
        &mut self,
        mut keep: impl FnMut(usize, &RefFeature) -> bool,
        shift_m: [f64; 2],
    ) {
        for (level, (_, sel)) in self.levels.iter_mut().enumerate() {
            let st = sel.kind.stride();
            let mut features = Vec::new();
            let mut descriptors = Vec::new();
            for (i, f) in sel.features.iter().enumerate() {
                if keep(level, f) {
                    features.push(RefFeature {
                        x_m: f.x_m + shift_m[0],
                        y_m: f.y_m + shift_m[1],
                        ..*f
                    });
                    descriptors.extend_from_slice(&sel.descriptors[i * st..(i + 1) * st]);
                }
            }
            sel.features = features;
            sel.descriptors = descriptors;
        }
    }

    /// Every level image one grey: a map whose images hold nothing to correlate, for tests of
    /// what the features do alone.
    pub(crate) fn blank_images(&mut self) {
        for (bytes, _, _) in &mut self.images {
            bytes.fill(128);
        }
    }
}
