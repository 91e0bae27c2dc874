//! The camera: its model ([`visnav_core::camera`], re-exported here; the frame and rotation
//! conventions are written down there and in docs/conventions.md) and where its frames come from
//! (`source`: files, a capture command, GStreamer, V4L2; `visnav_io::frames`).

pub use visnav_core::camera::*;

pub use visnav_io::frames as source;
