//! visnav: vision-aided navigation for drones without GPS.
//!
//! The modules read as the data flow (see `docs/architecture.md`):
//! `geo` (geodesy, projections, rasters) -> `camera` (sensor model) -> `vision` (SURF) ->
//! `map` (reference map) -> `pose` (resection) -> `nav` (INS + EKF) -> `link` (MAVLink) -> `daemon`.
//! Algorithm modules are pure (no I/O besides explicit file loaders, no async); the daemon wires them.
//! Every frame and rotation convention is defined once in `docs/conventions.md`.

pub mod camera;
pub mod daemon;
pub mod fix;
pub use visnav_core::nav;
pub use visnav_io::geo;
pub use visnav_io::map;
pub use visnav_link as link;
pub mod pose;
#[cfg(feature = "sim")]
pub mod sitl;
pub use visnav_core::stats;
pub mod vision;
