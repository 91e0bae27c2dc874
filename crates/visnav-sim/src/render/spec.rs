//! Scenario configuration of the simulated camera's rendering (`RenderSpec`).
//!
//! ```toml
//! colour = "grey"          # "grey" (Rec. 601 luma) or "rgb"
//! supersample = 2          # samples per pixel side inside the pixel's ground footprint (1-4)
//! max_range_m = 30000.0    # rays longer than this are off-map (sky, horizon)
//! fill_dn = 0.0            # value of off-map pixels, 8-bit digital numbers
//! seed = 0                 # noise seed (frame k uses the stream (seed, k))
//! quantise = true          # round to integers (8-bit output)
//!
//! [exposure]
//! gain = 1.0               # multiplies the radiance
//! offset_dn = 0.0          # then added, DN
//! gamma = 1.0              # response 255 (v/255)^gamma after noise
//! vignetting_corner = 0.0  # fraction of light lost in the image corners (quadratic falloff)
//!
//! [blur]
//! sigma_px = 0.0           # Gaussian blur
//! motion_length_px = 0.0   # linear motion blur length
//! motion_angle_deg = 0.0   # its direction, from image +u towards +v
//!
//! [noise]
//! read_dn = 0.0                  # Gaussian read noise, DN (1 sigma)
//! conversion_gain_dn_per_e = 0.0 # shot noise: variance = signal_DN * gain; 0 = none
//! ```
//!
//! Every table and key is optional (defaults above); unknown keys are errors.

use super::photometric::PhotometricSpec;
use super::pyramid::ColourMode;
use serde::{Deserialize, Serialize};
use visnav_core::validate::{Problems, Validate};

/// Rendering parameters of the simulated camera (geometry options + photometric effects).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RenderSpec {
    /// Grey (Rec. 601 luma) or RGB output.
    pub colour: ColourMode,
    /// Samples per pixel side inside the pixel's ground footprint (1-4).
    pub supersample: u32,
    /// Rays longer than this are off-map (sky, horizon), m.
    pub max_range_m: f64,
    /// Value of off-map pixels, 8-bit digital numbers.
    pub fill_dn: f64,
    /// Noise seed (frame k uses the stream (seed, k)).
    pub seed: u64,
    /// Round to integers (8-bit output).
    pub quantise: bool,
    /// `[exposure]`.
    pub exposure: ExposureSpec,
    /// `[blur]`.
    pub blur: BlurSpec,
    /// `[noise]`.
    pub noise: NoiseSpec,
}

/// `[exposure]`: gain, offset, response gamma, vignetting.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ExposureSpec {
    /// Multiplies the radiance.
    pub gain: f64,
    /// Then added, DN.
    pub offset_dn: f64,
    /// Response `255 (v/255)^gamma`, applied after the noise.
    pub gamma: f64,
    /// Fraction of light lost in the image corners (quadratic falloff).
    pub vignetting_corner: f64,
}

/// `[blur]`: optical (Gaussian) and motion blur.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct BlurSpec {
    /// Gaussian blur sigma, px.
    pub sigma_px: f64,
    /// Linear motion blur length, px.
    pub motion_length_px: f64,
    /// Motion blur direction, from image +u towards +v, deg.
    pub motion_angle_deg: f64,
}

/// `[noise]`: read and shot noise.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct NoiseSpec {
    /// Gaussian read noise, DN (1 sigma).
    pub read_dn: f64,
    /// Shot noise: variance = signal (DN) x this gain; 0: none.
    pub conversion_gain_dn_per_e: f64,
}

impl Default for RenderSpec {
    fn default() -> Self {
        Self {
            colour: ColourMode::Grey,
            supersample: 2,
            max_range_m: 30_000.0,
            fill_dn: 0.0,
            seed: 0,
            quantise: true,
            exposure: ExposureSpec::default(),
            blur: BlurSpec::default(),
            noise: NoiseSpec::default(),
        }
    }
}

impl Default for ExposureSpec {
    fn default() -> Self {
        Self {
            gain: 1.0,
            offset_dn: 0.0,
            gamma: 1.0,
            vignetting_corner: 0.0,
        }
    }
}

impl RenderSpec {
    /// A clean render: no photometric effect, no quantisation (float output).
    pub fn clean() -> Self {
        Self {
            quantise: false,
            ..Self::default()
        }
    }

    /// The photometric part.
    pub fn photometric(&self) -> PhotometricSpec {
        PhotometricSpec {
            gain: self.exposure.gain,
            offset_dn: self.exposure.offset_dn,
            gamma: self.exposure.gamma,
            vignetting_corner: self.exposure.vignetting_corner,
            blur_sigma_px: self.blur.sigma_px,
            motion_length_px: self.blur.motion_length_px,
            motion_angle_deg: self.blur.motion_angle_deg,
            read_noise_dn: self.noise.read_dn,
            conversion_gain_dn_per_e: self.noise.conversion_gain_dn_per_e,
            quantise: self.quantise,
            fill_dn: self.fill_dn,
            seed: self.seed,
        }
    }

    /// Validate and return the problems as one error (keys relative to this section).
    pub fn check(&self) -> Result<(), super::RenderError> {
        let mut p = Problems::default();
        self.validate(&mut p);
        if p.list.is_empty() {
            Ok(())
        } else {
            Err(super::RenderError::Spec { list: p.list })
        }
    }
}

impl Validate for RenderSpec {
    fn validate(&self, p: &mut Problems) {
        p.range("supersample", f64::from(self.supersample), 1.0, 4.0);
        p.range("max_range_m", self.max_range_m, 1.0, 1.0e6);
        p.range("fill_dn", self.fill_dn, 0.0, 255.0);
        p.section("exposure", |p| self.exposure.validate(p));
        p.section("blur", |p| self.blur.validate(p));
        p.section("noise", |p| self.noise.validate(p));
    }
}

impl Validate for ExposureSpec {
    fn validate(&self, p: &mut Problems) {
        p.range("gain", self.gain, 0.0, 100.0);
        p.range("offset_dn", self.offset_dn, -255.0, 255.0);
        p.range("gamma", self.gamma, 0.1, 10.0);
        p.range("vignetting_corner", self.vignetting_corner, 0.0, 0.95);
    }
}

impl Validate for BlurSpec {
    fn validate(&self, p: &mut Problems) {
        p.range("sigma_px", self.sigma_px, 0.0, 50.0);
        p.range("motion_length_px", self.motion_length_px, 0.0, 200.0);
        p.range("motion_angle_deg", self.motion_angle_deg, -360.0, 360.0);
    }
}

impl Validate for NoiseSpec {
    fn validate(&self, p: &mut Problems) {
        p.range("read_dn", self.read_dn, 0.0, 100.0);
        p.range(
            "conversion_gain_dn_per_e",
            self.conversion_gain_dn_per_e,
            0.0,
            100.0,
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn problems(s: &RenderSpec) -> Vec<String> {
        let mut p = Problems::default();
        p.section("camera_render", |p| s.validate(p));
        p.list.iter().map(|i| i.to_string()).collect()
    }

    #[test]
    fn empty_is_default_and_full_round_trips() {
        let s: RenderSpec = toml::from_str("").unwrap();
        assert_eq!(s, RenderSpec::default());
        assert!(problems(&s).is_empty());
        let text = r#"
            colour = "rgb"
            supersample = 3
            seed = 7
            quantise = false
            [exposure]
            gain = 0.8
            gamma = 1.2
            vignetting_corner = 0.3
            [blur]
            sigma_px = 0.7
            motion_length_px = 4.0
            motion_angle_deg = 45.0
            [noise]
            read_dn = 1.5
            conversion_gain_dn_per_e = 0.1
        "#;
        let s: RenderSpec = toml::from_str(text).unwrap();
        assert!(problems(&s).is_empty(), "{:?}", problems(&s));
        assert_eq!(s.colour, ColourMode::Rgb);
        assert_eq!(s.photometric().motion_length_px, 4.0);
        assert_eq!(s.photometric().seed, 7);
        let again: RenderSpec = toml::from_str(&toml::to_string(&s).unwrap()).unwrap();
        assert_eq!(again, s);
    }

    #[test]
    fn unknown_keys_and_bad_values_are_reported() {
        let e = toml::from_str::<RenderSpec>("[noise]\nread_noise = 1").unwrap_err();
        assert!(e.to_string().contains("read_noise"), "{e}");
        let e = toml::from_str::<RenderSpec>("colour = \"infrared\"").unwrap_err();
        assert!(e.to_string().contains("infrared"), "{e}");
        let s: RenderSpec =
            toml::from_str("supersample = 9\n[exposure]\ngamma = 0.0\n[blur]\nsigma_px = -1")
                .unwrap();
        let list = problems(&s);
        assert_eq!(list.len(), 3, "{list:?}");
        assert!(list[0].starts_with("camera_render.supersample"), "{list:?}");
        assert!(
            list[1].starts_with("camera_render.exposure.gamma"),
            "{list:?}"
        );
        assert!(
            list[2].starts_with("camera_render.blur.sigma_px"),
            "{list:?}"
        );
        assert!(s.check().is_err());
        let nan = RenderSpec {
            max_range_m: f64::NAN,
            ..RenderSpec::default()
        };
        assert_eq!(problems(&nan).len(), 1);
    }
}
