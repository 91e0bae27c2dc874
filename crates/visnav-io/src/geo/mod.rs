//! The files geodesy and rasters ([`visnav_core::geo`]) come from:
//!
//! * `geotiff_info`: the GeoTIFF structure, georeferencing keys, info and errors (tiff crate, no
//!   GDAL).
//! * `geotiff`: the whole first image as a `Raster`.
//! * `window`: windowed GeoTIFF reader (decodes only the strips/tiles under a pixel window).
//! * `dem`: terrain heights and ray/terrain intersection (gridded DEM or constant height).

pub mod dem;
pub mod geotiff;
pub mod geotiff_info;
pub mod geotiff_write;
pub mod window;
