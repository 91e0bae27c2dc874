//! Geodesy and georeferenced rasters.
//!
//! * `crs`: the coordinate reference systems visnav understands (shared by projections and GeoTIFF).
//! * `wgs84`: ellipsoid constants.
//! * `error`: `GeoError`, returned by every geodesy function on invalid input.
//! * `ecef`: WGS84 geodetic (`Geodetic`) <-> ECEF.
//! * `local`: local tangent frames (NED / ENU) about an origin (`LocalFrame`).
//! * `autopilot_frame`: the local frame an autopilot keeps about its EKF origin, as ArduPilot or PX4
//!   computes it (`AutopilotFrame`, `GeoOrigin`).
//! * `projection`: `Crs::{from_geodetic, to_geodetic}`, EPSG codes, UTM zones, grid convergence.
//! * `geoid`: EGM96 geoid undulation and AMSL <-> ellipsoidal height.
//! * `raster`: georeferenced rasters (geotransform, nodata-aware bilinear sampling).
//! * `dem`: the terrain model (gridded or constant height) and exact ray/terrain intersection.
//!
//! Reading GeoTIFF files (and DEMs from them) is `visnav_io::geo::{geotiff, window, dem}`.

pub mod autopilot_frame;
pub mod crs;
pub mod dem;
pub mod ecef;
pub mod error;
pub mod geoid;
pub mod local;
pub mod projection;
pub mod raster;
pub mod wgs84;
pub use autopilot_frame::{AutopilotFrame, GeoOrigin};
pub use crs::Crs;
pub use ecef::Geodetic;
pub use error::GeoError;
pub use local::LocalFrame;
