//! The detector seam: which features a map and its query frames are described with.
//!
//! A [`FeatureSpec`] names a detector family and its settings; a map records it (the query frames
//! must use the same) and [`FeatureSpec::detector`] builds the extractor. Every [`Detector`] gives
//! [`Features`] of one [`DescriptorKind`], whose [`super::surf::Family`] decides the matcher's
//! distance (L2 or Hamming, [`super::matcher::row_distance2`]). The fix engine, the map and the
//! matcher know only this seam; SURF ([`Surf`], on the CPU or the GPU through a
//! [`super::FeatureBackend`]) and the ORB-like binary features ([`Orb`]) sit behind it.

use std::sync::Arc;

use super::orb::{Orb, OrbParams};
use super::{DescriptorKind, Features, GrayImage, Surf, SurfParams, VisionError};

/// A detector family with its settings.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(tag = "detector", rename_all = "snake_case")]
pub enum FeatureSpec {
    /// SURF (docs/surf.md): float descriptors, the default.
    Surf(SurfParams),
    /// ORB-like binary features ([`super::orb`]).
    Orb(OrbParams),
}

impl Default for FeatureSpec {
    fn default() -> Self {
        Self::Surf(SurfParams::default())
    }
}

impl FeatureSpec {
    /// The descriptors this detector gives.
    pub fn kind(&self) -> DescriptorKind {
        match self {
            Self::Surf(p) => p.descriptor,
            Self::Orb(_) => DescriptorKind::Binary256,
        }
    }
    /// Check the settings; the error names the offending field.
    pub fn validate(&self) -> Result<(), VisionError> {
        match self {
            Self::Surf(p) => p.validate(),
            Self::Orb(p) => p.validate(),
        }
    }
    /// The same settings keeping at most `max` features per image (`None`: all).
    pub fn with_max_features(mut self, max: Option<usize>) -> Self {
        match &mut self {
            Self::Surf(p) => p.max_features = max,
            Self::Orb(p) => p.max_features = max,
        }
        self
    }
    /// The SURF settings, when this is SURF.
    pub fn surf(&self) -> Option<&SurfParams> {
        match self {
            Self::Surf(p) => Some(p),
            Self::Orb(_) => None,
        }
    }
    /// Build the extractor.
    pub fn detector(&self) -> Result<Arc<dyn Detector>, VisionError> {
        Ok(match self {
            Self::Surf(p) => Arc::new(Surf::new(p.clone())?),
            Self::Orb(p) => Arc::new(Orb::new(p.clone())?),
        })
    }
}

impl From<SurfParams> for FeatureSpec {
    fn from(p: SurfParams) -> Self {
        Self::Surf(p)
    }
}

impl From<OrbParams> for FeatureSpec {
    fn from(p: OrbParams) -> Self {
        Self::Orb(p)
    }
}

/// The family name, for logs and map summaries: `SURF-64`, `binary-256 (ORB)`.
impl std::fmt::Display for FeatureSpec {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Surf(p) => write!(f, "{}", p.descriptor),
            Self::Orb(_) => write!(f, "{} (ORB)", DescriptorKind::Binary256),
        }
    }
}

/// A feature extractor.
pub trait Detector: Send + Sync + std::fmt::Debug {
    /// Its family and settings.
    fn spec(&self) -> FeatureSpec;
    /// Keypoints (strongest first) with their descriptors.
    fn detect_and_describe(&self, img: &GrayImage) -> Features;
    /// The SURF extractor, when this is SURF (an accelerator that computes SURF itself asks).
    fn as_surf(&self) -> Option<&Surf> {
        None
    }
}

impl Detector for Surf {
    fn spec(&self) -> FeatureSpec {
        FeatureSpec::Surf(self.params().clone())
    }
    fn detect_and_describe(&self, img: &GrayImage) -> Features {
        Surf::detect_and_describe(self, img)
    }
    fn as_surf(&self) -> Option<&Surf> {
        Some(self)
    }
}

impl Detector for Orb {
    fn spec(&self) -> FeatureSpec {
        FeatureSpec::Orb(self.params().clone())
    }
    fn detect_and_describe(&self, img: &GrayImage) -> Features {
        Orb::detect_and_describe(self, img)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_spec_round_trips_through_toml_and_builds_its_detector() {
        for spec in [
            FeatureSpec::default(),
            FeatureSpec::Orb(OrbParams::default()),
        ] {
            let text = toml::to_string(&spec).unwrap();
            let back: FeatureSpec = toml::from_str(&text).unwrap();
            assert_eq!(back, spec);
            let d = spec.detector().unwrap();
            assert_eq!(d.spec(), spec);
            assert_eq!(d.as_surf().is_some(), spec.surf().is_some());
            let img = GrayImage::from_fn(96, 96, |x, y| ((x / 8 + y / 8) % 2) as f32 * 200.0);
            assert_eq!(d.detect_and_describe(&img).kind(), spec.kind());
        }
        assert_eq!(
            FeatureSpec::Orb(OrbParams::default()).to_string(),
            "binary-256 (ORB)"
        );
    }

    #[test]
    fn surf_refuses_a_binary_descriptor() {
        let spec = FeatureSpec::Surf(SurfParams {
            descriptor: DescriptorKind::Binary256,
            ..SurfParams::default()
        });
        let e = spec.validate().unwrap_err();
        assert!(e.to_string().contains("descriptor"), "{e}");
    }
}
