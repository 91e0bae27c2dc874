//! Loading a terrain model from a file: a one-band GeoTIFF of heights (metres) becomes a
//! [`Dem`] (the model itself, its surface and ray casting, is `visnav_core::geo::dem`).

use std::path::Path;

pub use visnav_core::geo::dem::*;

use super::Crs;
use super::geotiff::{GeoTiffError, load_geotiff};

/// Why a DEM file could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum DemFileError {
    /// Reading the GeoTIFF failed (the message names the file).
    #[error(transparent)]
    GeoTiff(#[from] GeoTiffError),
    /// The raster is not a usable height model.
    #[error("{path}: {error}")]
    Dem { path: String, error: DemError },
}

/// Loads a one-band GeoTIFF of heights (metres). See `geotiff::load_geotiff` for `crs_override`.
pub fn load_dem(path: &Path, crs_override: Option<Crs>) -> Result<Dem, DemFileError> {
    let raster = load_geotiff(path, crs_override)?;
    Dem::from_raster(&raster).map_err(|error| DemFileError::Dem {
        path: path.display().to_string(),
        error,
    })
}
