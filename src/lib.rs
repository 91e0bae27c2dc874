//! visnav: vision-aided navigation for drones without GPS. This library is the workspace's crates
//! under one name for the `visnav` binary and the end-to-end tests in tests/ (docs/architecture.md
//! draws the crates and the data flow):
//!
//! * visnav-core (pure algorithms): `geo` math, `camera`, `vision`, `pose`, `fix`, `nav`, `stats`;
//! * visnav-io (files and devices): `geo::{geotiff, window, dem}` loading, `map` (the `.vnm` file,
//!   its build, [`fix::MapReference`]), `camera::source` (frame sources), `vision::file`;
//! * visnav-link: `link` (MAVLink);
//! * visnav-daemon: `daemon` (the service of `visnav run`);
//! * visnav-sim (the default-on `sim` feature): `sitl` (the built-in simulator), `pose::bench`
//!   and `vision::eval` (evaluation tooling).
//!
//! Every frame and rotation convention is defined once in `docs/conventions.md`.

// Nothing from outside may be unwrapped (clippy.toml allows it in tests; the end-to-end tests
// in tests/ may unwrap too).
#![deny(clippy::unwrap_used, clippy::expect_used)]

pub use visnav_core::{nav, stats};
pub use visnav_daemon as daemon;
/// SURF on the GPU (the `gpu` feature, off by default).
#[cfg(feature = "gpu")]
pub use visnav_gpu as gpu;
pub use visnav_io::map;
pub use visnav_link as link;
#[cfg(feature = "sim")]
pub use visnav_sim as sitl;

/// Geodesy, rasters and the terrain model (visnav-core) with the GeoTIFF files they come from
/// (visnav-io).
pub mod geo {
    pub use visnav_core::geo::*;
    pub use visnav_io::geo::{geotiff, geotiff_info, geotiff_write, window};

    /// The terrain model (visnav-core) and its loading from a file (visnav-io).
    pub mod dem {
        pub use visnav_core::geo::dem::*;
        pub use visnav_io::geo::dem::*;
    }
}

/// The camera model (visnav-core) with the frame sources (visnav-io) as `source` and the reader
/// of other tools' calibration files as `calibration`.
pub mod camera {
    pub use visnav_core::camera::*;
    pub use visnav_io::calibration;
    pub use visnav_io::frames as source;
}

/// The vision fix (visnav-core) with the `.vnm` map file as its reference (visnav-io).
pub mod fix {
    pub use visnav_core::fix::*;
    pub use visnav_io::map::reference::{MapReference, MapReferenceError};
}

/// Space resection with its synthetic scenes (visnav-core) and benchmark (visnav-sim).
pub mod pose {
    pub use visnav_core::pose::*;
    #[cfg(feature = "sim")]
    pub use visnav_sim::pose_bench as bench;
}

/// SURF and matching (visnav-core) with image files (visnav-io) and the repeatability
/// evaluation (visnav-sim).
pub mod vision {
    pub use visnav_core::vision::*;
    pub use visnav_io::image_file as file;
    pub use visnav_io::image_file::GrayImageFile;
    #[cfg(feature = "sim")]
    pub use visnav_sim::surf_eval as eval;
}
