//! Computer vision: SURF features and their matching ([`visnav_core::vision`], re-exported here),
//! with the parts that are not pure algorithms:
//!
//! * `file`: image files to and from `GrayImage` ([`GrayImageFile`]; `visnav_io::image_file`).
//! * `eval`: Mikolajczyk & Schmid repeatability / matching-score protocol and synthetic warps
//!   (tooling for `visnav bench surf` and the quality tests).

pub use visnav_core::vision::*;

pub mod eval;

pub use visnav_io::image_file as file;
pub use visnav_io::image_file::GrayImageFile;
