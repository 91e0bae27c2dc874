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
//!
//! Reading GeoTIFF files and the terrain model built on them is the application's (the `visnav`
//! crate's `geo::{geotiff, window, dem}`).

pub mod crs;
pub mod ecef;
pub mod error;
pub mod geoid;
pub mod local;
pub mod projection;
pub mod raster;
pub mod wgs84;
pub use crs::Crs;
pub use ecef::Geodetic;
pub use error::GeoError;
pub use local::LocalFrame;
