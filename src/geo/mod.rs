//! Geodesy and georeferenced rasters.
//!
//! * `crs`: the coordinate reference systems visnav understands (shared by projections and GeoTIFF).
//! * `wgs84`: ellipsoid constants.
//! * `error`: `GeoError`, returned by every geodesy function on invalid input.
//! * `ecef`: WGS84 geodetic (`Geodetic`) <-> ECEF.
//! * `local`: local tangent frames (NED / ENU) about an origin (`LocalFrame`).
//! * `projection`: `Crs::{from_geodetic, to_geodetic}`, EPSG codes, UTM zones, grid convergence.
//! * `geoid`: EGM96 geoid undulation and AMSL <-> ellipsoidal height.
//! * `raster`: georeferenced rasters (geotransform, nodata-aware bilinear sampling).
//! * `geotiff`: GeoTIFF reader (tiff crate, no GDAL) producing a `Raster`.
//! * `window`: windowed GeoTIFF reader (decodes only the strips/tiles under a pixel window).
//! * `dem`: terrain heights and ray/terrain intersection (gridded DEM or constant height).

pub mod crs;
pub mod dem;
pub mod ecef;
pub mod error;
pub mod geoid;
pub mod geotiff;
pub mod local;
pub mod projection;
pub mod raster;
pub mod wgs84;
pub mod window;
pub use crs::Crs;
pub use ecef::Geodetic;
pub use error::GeoError;
pub use local::LocalFrame;
