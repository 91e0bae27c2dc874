//! The reference map: SURF features of georeferenced orthophotos with 3-D world coordinates,
//! built once offline (`visnav map build`) and memory-mapped by the fix pipeline.
//!
//! * `build`: [`build_map`] tiles the orthophoto(s) level by level, extracts SURF per tile, attaches
//!   DEM heights and streams the features into a `.vnm` file with bounded memory.
//! * `tiled`: [`tiled::build_tiled`] cuts the orthophotos along a fixed grid into one `.vnm` per
//!   square with an index (a tiled map).
//! * `paged`: [`paged::PagedMap`], a tiled map in flight: the tiles near the aircraft in
//!   memory, loaded in the background, dropped by a memory budget.
//! * `format`: the `.vnm` byte layout ([`ReferenceMap::open`], [`ReferenceMap::select`]); the full
//!   layout is documented in `docs/map-format.md`.
//!
//! # Conventions
//! * Pyramid levels: level 0 has the orthophoto's own pixel size `gsd_m`; level `L` has pixel size
//!   `gsd_m * 2^L`, and its pixel `(i, j)` is the mean of the `2^L x 2^L` block of level-0 pixels
//!   `[i 2^L, (i+1) 2^L) x [j 2^L, (j+1) 2^L)` (area averaging, the same as `L` successive 2 x 2
//!   box averages). Level `L` is `floor(W / 2^L) x floor(H / 2^L)` pixels (a partial block at the
//!   right/bottom edge is dropped). A map built with `upsample = 2^s` (`BuildSpec::upsample`) has
//!   its level-0 grid `2^s` times finer than the orthophoto (`gsd_m / 2^s`, `W 2^s x H 2^s`, the
//!   orthophoto's geotransform with its pixel steps divided by `2^s`): its levels `L < s` are the
//!   orthophoto interpolated (Keys cubic) by `2^(s - L)`, its levels `L >= s` the orthophoto's own
//!   level `L - s`; "level 0" and "the geotransform" below mean that grid. The header's `orthos`
//!   keep the orthophotos' own sizes and pixel.
//! * Grey: Rec. 601 luma `0.299 R + 0.587 G + 0.114 B` of bands 1-3 (a 4th band such as NIR is
//!   ignored), the single band of a 1-2-band image; on the 8-bit scale (16-bit samples are scaled
//!   by 255/65535), as `vision::file::GrayImageFile::from_dynamic` and the renderer's `ColourMode::Grey`.
//!   A pixel with a missing sample (nodata/NaN) in any used band is missing; a level pixel is
//!   missing when under 3/4 of its block is valid.
//! * Pixel coordinates: SURF keypoints have pixel centres at integer coordinates, rasters are
//!   GDAL pixel-is-area (centre of pixel `i` at `i + 0.5`). A keypoint at level-`L` SURF coordinate
//!   `(u, v)` therefore lies at level-0 continuous raster coordinate `((u + 0.5) 2^L, (v + 0.5) 2^L)`,
//!   which the level-0 grid's geotransform maps to `(x_m, y_m)`.
//! * Heights: `z_amsl_m` is the DEM's bilinear height at `(x_m, y_m)` in the DEM's vertical datum
//!   (orthometric/AMSL for the DEMs visnav uses, see `docs/conventions.md`), or the constant ground
//!   height. Keypoints without a DEM height are dropped and counted.
//! * Scale: `scale_m = KeyPoint::scale * gsd_m * 2^L` (SURF's `s = 1.2 L / 9`, in ground metres).
//! * Descriptors are stored as `i8` with one `f32` scale per feature (`d = q * scale`, `q` in
//!   `-127..=127`, `scale = max|d| / 127`), then re-normalised to unit length when read.

pub mod build;
pub mod convert;
pub mod coreg;
pub mod format;
pub mod paged;
pub mod reference;
pub mod terrain_mosaic;
pub mod tiled;

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use visnav_core::geo::Crs;
use visnav_core::geo::raster::Bounds;
use visnav_core::vision::{DescriptorKind, FeatureSpec, OrbParams, SurfParams};

pub use build::{BuildProgress, BuildSpec, BuildSummary, HeightSource, build_map};
pub use format::{FORMAT_VERSION, MAGIC, ReferenceMap};
pub use reference::{MapReference, MapReferenceError};

/// Errors building or opening a reference map. Every variant names the file involved.
#[derive(Debug, thiserror::Error)]
pub enum MapError {
    /// Reading or writing a file failed.
    #[error("{}: {what}: {cause}", .path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// What was being done.
        what: &'static str,
        /// The operating system's error.
        cause: std::io::Error,
    },
    /// An orthophoto or DEM GeoTIFF could not be loaded.
    #[error(transparent)]
    GeoTiff(Box<crate::geo::geotiff::GeoTiffError>),
    /// The DEM is unusable.
    #[error("DEM: {cause}")]
    Dem {
        /// The file.
        path: PathBuf,
        /// Why the DEM could not be used.
        cause: Box<crate::geo::dem::DemFileError>,
    },
    /// An input raster cannot be used for a map (rotated, non-square pixels, CRS mismatch, ...).
    #[error("{}: {reason}", .path.display())]
    Input {
        /// The file.
        path: PathBuf,
        /// What is wrong, in words.
        reason: String,
    },
    /// The build parameters are invalid.
    #[error("invalid map build parameter `{name}`: {reason}")]
    Param {
        /// The build setting.
        name: &'static str,
        /// What is wrong, in words.
        reason: String,
    },
    /// The orthophotos gave no feature at all (blank, uniform or all nodata; or the DEM covers
    /// none of them): a map without features can fix nothing.
    #[error(
        "{orthos}: no features found ({dropped_nodata} keypoints dropped at nodata, \
         {dropped_no_height} where the DEM has no height): the orthophoto has no texture SURF \
         finds at Hessian threshold {threshold} (blank, uniform or all nodata?), or the DEM does \
         not cover it; no map written"
    )]
    NoFeatures {
        /// The orthophotos, as given.
        orthos: String,
        /// The SURF Hessian threshold used.
        threshold: f32,
        /// Keypoints dropped because their descriptor window touched nodata.
        dropped_nodata: u64,
        /// Keypoints dropped because the DEM has no height there.
        dropped_no_height: u64,
    },
    /// A `.vnm` file is malformed: wrong magic, unsupported version, truncated, bad checksum,
    /// inconsistent tables.
    #[error("{}: not a valid visnav map: {reason}", .path.display())]
    Format {
        /// The file.
        path: PathBuf,
        /// What is wrong, in words.
        reason: String,
    },
}

impl From<crate::geo::geotiff::GeoTiffError> for MapError {
    fn from(e: crate::geo::geotiff::GeoTiffError) -> Self {
        MapError::GeoTiff(Box::new(e))
    }
}

/// One map feature (decoded from the file).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MapFeature {
    /// Map CRS grid easting of the keypoint centre, metres.
    pub x_m: f64,
    /// Map CRS grid northing of the keypoint centre, metres.
    pub y_m: f64,
    /// Terrain height at `(x_m, y_m)`: the DEM's datum (orthometric/AMSL) or the constant height.
    pub z_amsl_m: f64,
    /// SURF scale `s` on the ground, metres (`KeyPoint::scale * level gsd`).
    pub scale_m: f32,
    /// SURF `det(H)` response at the level it was detected.
    pub response: f32,
    /// Sign of the Laplacian: -1 bright blob, +1 dark blob.
    pub laplacian: i8,
    /// Pyramid level (0 = the ortho's own resolution).
    pub level: u8,
}

/// The spatial index grid of one level: cells of `cell_m` x `cell_m` metres, row 0 at the top
/// (north). Cell `(c, r)` covers `x in [origin_x_m + c cell_m, origin_x_m + (c+1) cell_m)`,
/// `y in (origin_y_m - (r+1) cell_m, origin_y_m - r cell_m]`; points outside are clamped into the
/// border cells.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct IndexGrid {
    /// West edge of column 0, metres.
    pub origin_x_m: f64,
    /// North edge of row 0, metres.
    pub origin_y_m: f64,
    /// Cell side, metres.
    pub cell_m: f64,
    /// Number of columns.
    pub cols: u32,
    /// Number of rows.
    pub rows: u32,
}

impl IndexGrid {
    /// Number of cells.
    pub fn n_cells(&self) -> usize {
        self.cols as usize * self.rows as usize
    }
    /// Column of easting `x_m`, clamped to the grid (NaN maps to 0).
    pub fn col_of(&self, x_m: f64) -> usize {
        clamp_index((x_m - self.origin_x_m) / self.cell_m, self.cols)
    }
    /// Row of northing `y_m`, clamped to the grid (NaN maps to 0).
    pub fn row_of(&self, y_m: f64) -> usize {
        clamp_index((self.origin_y_m - y_m) / self.cell_m, self.rows)
    }
    /// Cell index (row-major) of a point.
    pub fn cell_of(&self, x_m: f64, y_m: f64) -> usize {
        self.row_of(y_m) * self.cols as usize + self.col_of(x_m)
    }
}

fn clamp_index(f: f64, n: u32) -> usize {
    let f = f.floor();
    if f >= 0.0 {
        (f as u64).min(u64::from(n.saturating_sub(1))) as usize // ok: n >= 1, saturating cast
    } else {
        0
    }
}

/// One pyramid level of the map.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LevelInfo {
    /// Pixel size of this level on the ground, metres (`gsd_m` of level 0 times `2^level`).
    pub gsd_m: f64,
    /// Number of features stored for this level.
    pub n_features: u64,
    /// Spatial index geometry.
    pub grid: IndexGrid,
    /// File layout: byte offsets from the data start (see `docs/map-format.md`).
    pub cells_offset: u64,
    /// Byte offset of the feature records.
    pub records_offset: u64,
    /// Byte offset of the descriptors.
    pub descriptors_offset: u64,
    /// The level's grey image (format 2; `None` in version-1 files).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub image: Option<LevelImageInfo>,
}

/// Where a level's grey image lies: `width_px x height_px` bytes, row-major, row 0 north, pixel
/// `(i, j)` covering `[origin_x_m + i gsd, origin_x_m + (i+1) gsd) x (origin_y_m - (j+1) gsd,
/// origin_y_m - j gsd]` (gsd = the level's `gsd_m`). Value = the level's grey rounded into
/// `1..=255`; 0 = no data.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct LevelImageInfo {
    /// Offset from the data offset, a multiple of 8.
    pub offset: u64,
    /// Image width, pixels.
    pub width_px: u64,
    /// Image height, pixels.
    pub height_px: u64,
    /// West edge of column 0, metres.
    pub origin_x_m: f64,
    /// North edge of row 0, metres.
    pub origin_y_m: f64,
}

/// Where the feature heights come from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum HeightInfo {
    /// A gridded DEM (file name as given, height range over its valid samples, metres).
    Dem {
        /// The DEM file, as given to the build.
        file: String,
        /// Lowest height over the DEM's valid samples, metres.
        min_m: f64,
        /// Highest height over the DEM's valid samples, metres.
        max_m: f64,
    },
    /// A constant ground height, metres AMSL.
    Constant {
        /// The height, metres above mean sea level.
        amsl_m: f64,
    },
}

/// One source orthophoto.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct OrthoInfo {
    /// File name as given to the build.
    pub file: String,
    /// Width, pixels.
    pub width_px: u64,
    /// Height, pixels.
    pub height_px: u64,
    /// Number of bands.
    pub bands: u32,
    /// Ground pixel size, metres.
    pub pixel_size_m: f64,
}

#[derive(Serialize, Deserialize)]
#[serde(remote = "Bounds")]
pub(crate) struct BoundsDef {
    min_x_m: f64,
    min_y_m: f64,
    max_x_m: f64,
    max_y_m: f64,
}

/// The map file header (stored as JSON after the fixed preamble).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MapHeader {
    /// Format version ([`FORMAT_VERSION`]).
    pub version: u32,
    /// Horizontal CRS of all coordinates.
    pub crs: Crs,
    /// SURF parameters the features were extracted with (apply the same to camera frames).
    pub surf: SurfParams,
    /// With it, the features are ORB-like binary features of these settings
    /// (`visnav_core::vision::orb`) and `surf` is not used; absent (every file written before it):
    /// SURF ([`Self::feature_spec`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub orb: Option<OrbParams>,
    /// Pyramid levels, finest first.
    pub levels: Vec<LevelInfo>,
    /// Union of the orthophotos' outer pixel edges, metres.
    #[serde(with = "BoundsDef")]
    pub bounds: Bounds,
    /// Height source.
    pub height: HeightInfo,
    /// Standard deviation of the features' heights against the surface the camera sees, metres
    /// (roofs, trees and relief a constant height or a bare-earth DEM leaves out, and the DEM's own
    /// error). The fix weighs each point by it and adds it to its vertical covariance
    /// (docs/map-format.md, "Height uncertainty"). Files written before it existed read 0.
    #[serde(default)]
    pub height_sigma_m: f64,
    /// How fast the height error changes across a footprint, metres per metre (1 sigma per
    /// horizontal axis; docs/map-format.md, "Height uncertainty"). Absent in files written before
    /// it: no slope (and `height_sigma_m` again per point).
    #[serde(default)]
    pub height_slope_sigma: Option<f64>,
    /// The height error left per point once the footprint's offset and slope are taken out,
    /// metres (1 sigma). Absent in files written before it: `height_sigma_m`.
    #[serde(default)]
    pub height_point_sigma_m: Option<f64>,
    /// Vertical datum of `z_amsl_m`, free text (e.g. "DEM datum (orthometric, AMSL)").
    pub vertical_datum: String,
    /// Source orthophotos.
    pub orthos: Vec<OrthoInfo>,
    /// Tile core size in level pixels and per-tile feature cap used by the build.
    pub tile_px: u32,
    /// Per-tile, per-level feature cap.
    pub max_features_per_tile: u32,
    /// Build time, seconds since the Unix epoch (UTC).
    pub built_unix_s: u64,
    /// visnav version that built the file.
    pub built_by: String,
}

impl MapHeader {
    /// The height errors the fix models ([`visnav_core::fix::reference::HeightErrors`]): the
    /// stated offset, slope and per-point sigmas, with the defaults of files written before the
    /// last two existed.
    pub fn height_errors(&self) -> visnav_core::fix::reference::HeightErrors {
        visnav_core::fix::reference::HeightErrors {
            offset_sigma_m: self.height_sigma_m,
            slope_sigma: self.height_slope_sigma.unwrap_or(0.0),
            point_sigma_m: self.height_point_sigma_m.unwrap_or(self.height_sigma_m),
        }
    }
    /// The detector and settings of the features (the query frames use the same).
    pub fn feature_spec(&self) -> FeatureSpec {
        match &self.orb {
            Some(o) => FeatureSpec::Orb(o.clone()),
            None => FeatureSpec::Surf(self.surf.clone()),
        }
    }
    /// Descriptor variant of every feature.
    pub fn descriptor_kind(&self) -> DescriptorKind {
        self.feature_spec().kind()
    }
    /// Total number of features over all levels.
    pub fn n_features(&self) -> u64 {
        self.levels.iter().map(|l| l.n_features).sum()
    }
}

/// Features selected from one level, with dequantised descriptors.
#[derive(Clone, Debug)]
pub struct MapSelection {
    /// The selected features.
    pub features: Vec<MapFeature>,
    /// Row-major, `kind.stride()` floats per row, zero padded beyond `kind.len()` (the layout of
    /// `vision::Features::descriptors_padded`), unit length.
    pub descriptors: Vec<f32>,
    /// The descriptors' kind.
    pub kind: DescriptorKind,
}

impl MapSelection {
    /// Number of features.
    pub fn len(&self) -> usize {
        self.features.len()
    }
    /// True when nothing was selected.
    pub fn is_empty(&self) -> bool {
        self.features.is_empty()
    }
    /// Descriptor `i` (`kind.len()` values).
    pub fn descriptor(&self, i: usize) -> &[f32] {
        let k = self.kind;
        &self.descriptors[i * k.stride()..i * k.stride() + k.len()]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_header_without_the_height_split_reads_as_it_was_built() {
        let h = super::format::tests::tiny_header(1);
        let e = h.height_errors();
        assert_eq!(
            (e.offset_sigma_m, e.slope_sigma, e.point_sigma_m),
            (10.0, 0.01, 10.0)
        );
        // A file written before the slope and per-point sigmas existed: the offset per point
        // too, no slope (what every fix did with such a map).
        let mut v = serde_json::to_value(&h).unwrap();
        let o = v.as_object_mut().unwrap();
        o.remove("height_slope_sigma");
        o.remove("height_point_sigma_m");
        let old: MapHeader = serde_json::from_value(v).unwrap();
        let e = old.height_errors();
        assert_eq!(
            (e.offset_sigma_m, e.slope_sigma, e.point_sigma_m),
            (10.0, 0.0, 10.0)
        );
    }

    #[test]
    fn index_grid_clamps_and_orders_rows_north_first() {
        let g = IndexGrid {
            origin_x_m: 100.0,
            origin_y_m: 1000.0,
            cell_m: 10.0,
            cols: 3,
            rows: 2,
        };
        assert_eq!(g.col_of(100.0), 0);
        assert_eq!(g.col_of(109.999), 0);
        assert_eq!(g.col_of(110.0), 1);
        assert_eq!(g.col_of(1e9), 2);
        assert_eq!(g.col_of(-1e9), 0);
        assert_eq!(g.col_of(f64::NAN), 0);
        assert_eq!(g.row_of(1000.0), 0);
        assert_eq!(g.row_of(990.5), 0);
        assert_eq!(g.row_of(985.0), 1);
        assert_eq!(g.cell_of(125.0, 985.0), 5);
        assert_eq!(g.n_cells(), 6);
    }
}
