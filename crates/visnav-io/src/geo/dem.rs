//! Loading a terrain model from a file: a one-band GeoTIFF of heights (metres) becomes a
//! [`Dem`] (the model itself, its surface and ray casting, is `visnav_core::geo::dem`).

use std::path::Path;

use super::geotiff::{GeoTiffError, load_geotiff};
use super::window::open_geotiff_window;
use visnav_core::geo::Crs;
use visnav_core::geo::dem::{Dem, DemError};
use visnav_core::geo::raster::{Bounds, Raster};

/// The lowest terrain height accepted, metres AMSL: the shore of the Dead Sea, the lowest dry
/// land, is at -430 m (orthometric; its ellipsoidal height is about the same). A DEM or a
/// constant ground height below it is an undeclared nodata value, a wrong unit or a typo.
pub const MIN_TERRAIN_HEIGHT_M: f64 = -500.0;
/// The highest terrain height accepted, metres AMSL: Everest is 8 849 m (its ellipsoidal height
/// is about 8 820 m). Anything above (e.g. a DEM of 3.4e38, float32's largest value, used as an
/// undeclared nodata value) is not terrain.
pub const MAX_TERRAIN_HEIGHT_M: f64 = 9000.0;

/// Why a DEM file could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum DemFileError {
    /// Reading the GeoTIFF failed (the message names the file).
    #[error(transparent)]
    GeoTiff(#[from] GeoTiffError),
    /// The raster is not a usable height model.
    #[error("{path}: {error}")]
    Dem {
        /// The file.
        path: String,
        /// Why the raster is not a usable height model.
        error: DemError,
    },
    /// Heights outside the terrain range: an undeclared nodata value or another unit.
    #[error(
        "{path}: heights {min_m} to {max_m} m are outside the terrain range \
         {MIN_TERRAIN_HEIGHT_M} to {MAX_TERRAIN_HEIGHT_M} m: a nodata value the file does not \
         declare (declare it: `gdal_edit.py -a_nodata VALUE {path}`), or heights not in metres"
    )]
    Heights {
        /// The file.
        path: String,
        /// Lowest height, metres.
        min_m: f64,
        /// Highest height, metres.
        max_m: f64,
    },
}

/// Loads a one-band GeoTIFF of heights (metres). See `geotiff::load_geotiff` for `crs_override`.
pub fn load_dem(path: &Path, crs_override: Option<Crs>) -> Result<Dem, DemFileError> {
    checked_dem(path, &load_geotiff(path, crs_override)?)
}

/// Cells of the terrain model kept around the area [`load_dem_covering`] is asked for: the
/// bilinear surface at a point reads the four samples around it, so one cell would do; the
/// second keeps a point on the area's edge clear of any rounding of the window's corners.
pub const DEM_WINDOW_MARGIN_CELLS: usize = 2;

/// The part of the one-band GeoTIFF of heights at `path` that covers `area` (map coordinates in
/// the DEM's CRS) and [`DEM_WINDOW_MARGIN_CELLS`] around it, decoded from the strips or tiles
/// under it only: a DEM of a whole region costs the memory of the area a map needs. Heights
/// inside `area` are the same as [`load_dem`]'s, bit for bit. Where the area does not overlap
/// the DEM by at least two cells each way, the whole DEM is loaded (its heights then say what
/// they cover, as before).
pub fn load_dem_covering(
    path: &Path,
    crs_override: Option<Crs>,
    area: &Bounds,
) -> Result<Dem, DemFileError> {
    let mut r = open_geotiff_window(path, crs_override)?;
    let (width, height) = (r.info().width, r.info().height);
    let Some((c0, r0, w, h)) = covering_window(r.info().transform, width, height, area) else {
        return load_dem(path, crs_override);
    };
    if (w, h) == (width, height) {
        return load_dem(path, crs_override);
    }
    checked_dem(path, &r.read_window(c0, r0, w, h)?)
}

/// The part of the DEM at `path` under `area` and [`DEM_WINDOW_MARGIN_CELLS`] around it, as
/// [`load_dem_covering`] reads it, but never more: `None` where the area does not overlap the
/// DEM by two cells each way or the window holds no height (a tiled map's tile then carries no
/// heights rather than the whole DEM).
pub fn load_dem_window(
    path: &Path,
    crs_override: Option<Crs>,
    area: &Bounds,
) -> Result<Option<Dem>, DemFileError> {
    let mut r = open_geotiff_window(path, crs_override)?;
    let (width, height) = (r.info().width, r.info().height);
    let Some((c0, r0, w, h)) = covering_window(r.info().transform, width, height, area) else {
        return Ok(None);
    };
    match checked_dem(path, &r.read_window(c0, r0, w, h)?) {
        Ok(d) => Ok(Some(d)),
        Err(DemFileError::Dem {
            error: DemError::NoValidHeights,
            ..
        }) => Ok(None),
        Err(e) => Err(e),
    }
}

/// The pixel window `(col0, row0, width, height)` of a `width x height` grid with `transform`
/// that holds `area` and the margin, clipped to the grid; `None` when that is under 2 x 2 cells
/// or the area is not finite.
fn covering_window(
    transform: visnav_core::geo::raster::GeoTransform,
    width: usize,
    height: usize,
    area: &Bounds,
) -> Option<(usize, usize, usize, usize)> {
    let corners = [
        (area.min_x_m, area.min_y_m),
        (area.min_x_m, area.max_y_m),
        (area.max_x_m, area.min_y_m),
        (area.max_x_m, area.max_y_m),
    ]
    .map(|(x, y)| transform.map_to_pixel(x, y));
    if corners
        .iter()
        .any(|(c, r)| !(c.is_finite() && r.is_finite()))
    {
        return None;
    }
    let m = DEM_WINDOW_MARGIN_CELLS as f64;
    let lo_c = corners.iter().map(|p| p.0).fold(f64::INFINITY, f64::min) - m;
    let hi_c = corners
        .iter()
        .map(|p| p.0)
        .fold(f64::NEG_INFINITY, f64::max)
        + m;
    let lo_r = corners.iter().map(|p| p.1).fold(f64::INFINITY, f64::min) - m;
    let hi_r = corners
        .iter()
        .map(|p| p.1)
        .fold(f64::NEG_INFINITY, f64::max)
        + m;
    let clip = |v: f64, n: usize| v.clamp(0.0, n as f64);
    let (c0, c1) = (clip(lo_c.floor(), width), clip(hi_c.ceil(), width));
    let (r0, r1) = (clip(lo_r.floor(), height), clip(hi_r.ceil(), height));
    let (c0, c1, r0, r1) = (c0 as usize, c1 as usize, r0 as usize, r1 as usize); // ok: clipped
    (c1 >= c0 + 2 && r1 >= r0 + 2).then_some((c0, r0, c1 - c0, r1 - r0))
}

/// The raster read from `path` as a terrain model, its heights checked against the terrain
/// range.
fn checked_dem(path: &Path, raster: &Raster) -> Result<Dem, DemFileError> {
    let dem = Dem::from_raster(raster).map_err(|error| DemFileError::Dem {
        path: path.display().to_string(),
        error,
    })?;
    let (min_m, max_m) = dem.height_range_m();
    if !(min_m >= MIN_TERRAIN_HEIGHT_M && max_m <= MAX_TERRAIN_HEIGHT_M) {
        return Err(DemFileError::Heights {
            path: path.display().to_string(),
            min_m,
            max_m,
        });
    }
    Ok(dem)
}
