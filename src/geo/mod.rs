//! Geodesy and georeferenced rasters.
//!
//! * `crs`: the coordinate reference systems visnav understands (shared by projections and GeoTIFF).
//! * `wgs84`: ellipsoid constants.
//! * `raster`: georeferenced rasters (geotransform, nodata-aware bilinear sampling).
//! * `geotiff`: GeoTIFF reader (tiff crate, no GDAL) producing a `Raster`.
//! * `dem`: terrain heights and ray/terrain intersection (gridded DEM or constant height).

pub mod crs;
pub mod dem;
pub mod geotiff;
pub mod raster;
pub mod wgs84;
pub use crs::Crs;
