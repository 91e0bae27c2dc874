//! Geodesy and georeferenced rasters.
//!
//! * `crs`: the coordinate reference systems visnav understands (shared by projections and GeoTIFF).
//! * `wgs84`: ellipsoid constants.

pub mod crs;
pub mod wgs84;
pub use crs::Crs;
