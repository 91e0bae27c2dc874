//! Loading a terrain model from a file: a one-band GeoTIFF of heights (metres) becomes a
//! [`Dem`] (the model itself, its surface and ray casting, is `visnav_core::geo::dem`).

use std::path::Path;

use super::geotiff::{GeoTiffError, load_geotiff};
use visnav_core::geo::Crs;
use visnav_core::geo::dem::{Dem, DemError};

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
    let raster = load_geotiff(path, crs_override)?;
    let dem = Dem::from_raster(&raster).map_err(|error| DemFileError::Dem {
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
