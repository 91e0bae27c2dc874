//! Computer vision: SURF features (Bay et al. 2008) and their matching; KLT feature tracking.
//!
//! * `gray`: grayscale `f32` images on the 8-bit intensity scale, loading and sampling.
//! * `integral`: the summed-area table all box filters read.
//! * `surf`: fast-Hessian detector, orientation, SURF-36/64/128 descriptors, upright mode.
//! * `matcher`: brute-force 2-NN matching (L2 or Hamming by the descriptor's family) with ratio
//!   test, Laplacian gate, mutual and spatial gates.
//! * `detector`: the seam ([`Detector`], [`FeatureSpec`]) the map and the fix use; `orb`: the
//!   ORB-like binary features behind it beside SURF.
//! * `klt`: Shi-Tomasi corners, image pyramid, pyramidal Lucas-Kanade tracking (Bouguet 2000) with
//!   a forward-backward check, for frame-to-frame visual odometry.
//!
//! Reading and writing image files is the application's (the `visnav` crate's `vision::file`).
//!
//! Image coordinates everywhere in this module: `x` right (column), `y` down (row), pixel centres
//! at integer coordinates (OpenCV's convention). Keypoint orientation `orientation_rad` is the
//! angle from the image `+x` axis towards `+y`, i.e. clockwise as seen on screen, in `(-pi, pi]`.

pub mod detector;
pub mod gated;
pub mod gray;
pub mod integral;
pub mod klt;
pub mod matcher;
pub mod orb;
pub mod surf;

use std::path::PathBuf;

pub use detector::{Detector, FeatureSpec};
pub use gated::{GatedMatch, gated_match, hough_cluster};
pub use gray::GrayImage;
pub use integral::IntegralImage;
pub use matcher::{Match, MatchParams, match_features};
pub use orb::{Orb, OrbParams};
pub use surf::{
    CpuFeatures, DescriptorKind, ExtremaWindow, Family, FeatureBackend, Features, KeyPoint,
    LayerSpec, Surf, SurfParams, SurfStage,
};

/// Errors of the vision module.
#[derive(Debug, thiserror::Error)]
pub enum VisionError {
    /// An image file could not be read or decoded.
    #[error("{path}: cannot read image: {reason}")]
    ImageRead {
        /// The file.
        path: PathBuf,
        /// Why, in words.
        reason: String,
    },
    /// An image file could not be encoded or written.
    #[error("{path}: cannot write image: {reason}")]
    ImageWrite {
        /// The file.
        path: PathBuf,
        /// Why, in words.
        reason: String,
    },
    /// Image dimensions or pixel data are unusable (zero size, wrong length).
    #[error("invalid image: {0}")]
    InvalidImage(String),
    /// A detector parameter is out of range.
    #[error("invalid {detector} parameter `{name}`: {reason}")]
    InvalidParam {
        /// The detector the parameter belongs to ("SURF", "ORB").
        detector: &'static str,
        /// The parameter's field name.
        name: &'static str,
        /// The range it breaks, in words.
        reason: String,
    },
    /// The matcher's inputs or settings are inconsistent (descriptor kinds, ratio, gate).
    #[error("matcher: {0}")]
    Matcher(String),
    /// The KLT tracker's inputs or settings are invalid.
    #[error("KLT tracker: {0}")]
    Klt(String),
}
