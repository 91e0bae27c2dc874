//! visnav: vision-aided navigation for drones without GPS.
//!
//! The modules read as the data flow (see `docs/architecture.md`):
//! `geo` (geodesy, projections, rasters) -> `camera` (sensor model) -> `vision` (SURF) ->
//! `map` (reference map) -> `pose` (resection) -> `nav` (INS + EKF) -> `link` (MAVLink) -> `daemon`.
//! Most are the workspace's crates re-exported (visnav-core: pure algorithms; visnav-io: files and
//! devices; visnav-link: MAVLink); `fix`, `daemon` and `sitl` (the `sim` feature) live here.
//! Every frame and rotation convention is defined once in `docs/conventions.md`.

// Nothing from outside may be unwrapped (clippy.toml allows it in tests; the end-to-end tests
// in tests/ may unwrap too).
#![deny(clippy::unwrap_used, clippy::expect_used)]

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
