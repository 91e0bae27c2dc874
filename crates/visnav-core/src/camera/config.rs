//! `[camera]` configuration section: schema, validation and construction of a [`Camera`].
//!
//! ```toml
//! [camera]
//! width_px = 640
//! height_px = 1152
//! # exactly one intrinsics form:
//! fx_px = 833.33          # (a) pixels: fx_px + fy_px, optional cx_px + cy_px (default: image centre)
//! fy_px = 833.33
//! # focal_length_mm = 120 # (b) focal length + sensor active area, principal point at the centre
//! # sensor_width_mm = 92.16
//! # sensor_height_mm = 165.888
//! # hfov_deg = 62.0       # (c) horizontal field of view across the image width, square pixels
//!
//! [camera.distortion]     # optional, OpenCV Brown-Conrady on normalised coordinates, default 0
//! k1 = -0.1
//! k2 = 0.02
//! k3 = 0.0
//! p1 = 0.0
//! p2 = 0.0
//!
//! [camera.mount]          # optional, default: nadir, image top towards the nose, no lever arm
//! roll_deg = 0.0          # ZYX angles of the camera plate relative to the nadir mount
//! pitch_deg = 0.0         # (+pitch tilts the view forward; 90 = forward-looking)
//! yaw_deg = 0.0
//! lever_arm_body_frd_m = [0.0, 0.0, 0.0]   # camera centre in body FRD, metres
//! ```
//!
//! Validation ([`Validate`]) reports every problem with its key, value and accepted range. Besides
//! ranges it checks that the distortion is invertible over the whole image: each image corner must
//! undistort to a point inside the radius where the radial polynomial is still increasing.

use super::{Camera, CameraError, Distortion, Intrinsics, Mount};
use crate::validate::{Problems, Validate};
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

/// Accepted `|k1|`.
const K1_MAX: f64 = 1.0;
/// Accepted `|k2|`.
const K2_MAX: f64 = 2.0;
/// Accepted `|k3|`.
const K3_MAX: f64 = 5.0;
/// Accepted `|p1|`, `|p2|`.
const P_MAX: f64 = 0.05;
/// Accepted image side length, pixels.
const SIDE_MAX_PX: f64 = 65_535.0;
/// Accepted focal length in pixels.
const F_MAX_PX: f64 = 1.0e6;
/// Accepted `|lever arm component|`, metres.
const LEVER_MAX_M: f64 = 100.0;

/// `[camera]` section.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraConfig {
    /// Image width, pixels.
    pub width_px: u32,
    /// Image height, pixels.
    pub height_px: u32,
    /// Focal length along u, pixels (pixel form, with `fy_px`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fx_px: Option<f64>,
    /// Focal length along v, pixels (pixel form, with `fx_px`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fy_px: Option<f64>,
    /// Principal point u, pixels; with `cy_px`, default the image centre.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cx_px: Option<f64>,
    /// Principal point v, pixels; with `cx_px`, default the image centre.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cy_px: Option<f64>,
    /// Focal length, millimetres (millimetre form, with the sensor size).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub focal_length_mm: Option<f64>,
    /// Width of the sensor's active area across `width_px`, millimetres.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sensor_width_mm: Option<f64>,
    /// Height of the sensor's active area across `height_px`, millimetres.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sensor_height_mm: Option<f64>,
    /// Horizontal field of view across the image width, degrees (field-of-view form, square pixels).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub hfov_deg: Option<f64>,
    /// Lens distortion (`[camera.distortion]`), default none.
    #[serde(default)]
    pub distortion: DistortionConfig,
    /// Camera mount on the body (`[camera.mount]`), default nadir.
    #[serde(default)]
    pub mount: MountConfig,
}

/// `[camera.distortion]`: Brown-Conrady coefficients (OpenCV meaning), all default 0.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DistortionConfig {
    /// Radial coefficient of r^2, |k1| <= 1.
    pub k1: f64,
    /// Radial coefficient of r^4, |k2| <= 2.
    pub k2: f64,
    /// Radial coefficient of r^6, |k3| <= 5.
    pub k3: f64,
    /// First tangential coefficient, |p1| <= 0.05.
    pub p1: f64,
    /// Second tangential coefficient, |p2| <= 0.05.
    pub p2: f64,
}

/// `[camera.mount]`: tilt of the camera from the nadir mount (see [`Mount::from_angles`]) and lever arm.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MountConfig {
    /// Roll of the camera plate, degrees (positive tilts the view left), [-180, 180].
    pub roll_deg: f64,
    /// Pitch of the camera plate, degrees (positive tilts the view forward; 90 = forward-looking).
    pub pitch_deg: f64,
    /// Yaw of the camera plate, degrees (positive turns the image top to the right), [-180, 180].
    pub yaw_deg: f64,
    /// Camera centre in the body FRD frame, metres (each component within 100 m).
    pub lever_arm_body_frd_m: [f64; 3],
}

impl DistortionConfig {
    /// The model coefficients.
    pub fn to_distortion(&self) -> Distortion {
        Distortion {
            k1: self.k1,
            k2: self.k2,
            k3: self.k3,
            p1: self.p1,
            p2: self.p2,
        }
    }
}

impl MountConfig {
    /// The mount (no validation).
    pub fn to_mount(&self) -> Mount {
        Mount::from_angles(
            self.roll_deg.to_radians(),
            self.pitch_deg.to_radians(),
            self.yaw_deg.to_radians(),
            Vector3::from(self.lever_arm_body_frd_m),
        )
    }
}

impl Validate for DistortionConfig {
    fn validate(&self, p: &mut Problems) {
        p.range("k1", self.k1, -K1_MAX, K1_MAX);
        p.range("k2", self.k2, -K2_MAX, K2_MAX);
        p.range("k3", self.k3, -K3_MAX, K3_MAX);
        p.range("p1", self.p1, -P_MAX, P_MAX);
        p.range("p2", self.p2, -P_MAX, P_MAX);
    }
}

impl Validate for MountConfig {
    fn validate(&self, p: &mut Problems) {
        p.range("roll_deg", self.roll_deg, -180.0, 180.0);
        p.range("pitch_deg", self.pitch_deg, -90.0, 90.0);
        p.range("yaw_deg", self.yaw_deg, -180.0, 180.0);
        for (i, c) in self.lever_arm_body_frd_m.iter().enumerate() {
            if !c.is_finite() || c.abs() > LEVER_MAX_M {
                p.push(
                    "lever_arm_body_frd_m",
                    format!(
                        "component {i} = {c} is outside the accepted range [-{LEVER_MAX_M}, {LEVER_MAX_M}] m"
                    ),
                );
            }
        }
    }
}

impl CameraConfig {
    /// Config for the given intrinsics (pixel form), no distortion, nadir mount.
    pub fn from_intrinsics(k: &Intrinsics) -> Self {
        Self {
            width_px: k.width_px,
            height_px: k.height_px,
            fx_px: Some(k.fx_px),
            fy_px: Some(k.fy_px),
            cx_px: Some(k.cx_px),
            cy_px: Some(k.cy_px),
            focal_length_mm: None,
            sensor_width_mm: None,
            sensor_height_mm: None,
            hfov_deg: None,
            distortion: DistortionConfig::default(),
            mount: MountConfig::default(),
        }
    }

    /// Intrinsics from whichever form is given, assuming the section is otherwise valid.
    fn intrinsics(&self) -> Result<Intrinsics, CameraError> {
        let (w, h) = (self.width_px, self.height_px);
        let mut k = if let (Some(fx), Some(fy)) = (self.fx_px, self.fy_px) {
            Intrinsics::centred(fx, fy, w, h)?
        } else if let (Some(f), Some(sw), Some(sh)) = (
            self.focal_length_mm,
            self.sensor_width_mm,
            self.sensor_height_mm,
        ) {
            Intrinsics::from_focal_length_mm(f, sw, sh, w, h)?
        } else if let Some(hfov) = self.hfov_deg {
            Intrinsics::from_hfov(hfov.to_radians(), w, h)?
        } else {
            return Err(CameraError::InvalidParameter {
                name: "intrinsics",
                reason: "no intrinsics form given".into(),
            });
        };
        if let (Some(cx), Some(cy)) = (self.cx_px, self.cy_px) {
            k = Intrinsics::new(k.fx_px, k.fy_px, cx, cy, w, h)?;
        }
        Ok(k)
    }

    /// Validate, then build the camera. On failure the error lists every problem (keys relative to
    /// the camera section, e.g. `distortion.k1`).
    pub fn build(&self) -> Result<Camera, CameraError> {
        let mut p = Problems::default();
        self.validate(&mut p);
        if !p.list.is_empty() {
            return Err(CameraError::Config { list: p.list });
        }
        Camera::new(
            self.intrinsics()?,
            self.distortion.to_distortion(),
            self.mount.to_mount(),
        )
    }
}

impl Validate for CameraConfig {
    fn validate(&self, p: &mut Problems) {
        let before = p.list.len();
        p.range("width_px", f64::from(self.width_px), 1.0, SIDE_MAX_PX);
        p.range("height_px", f64::from(self.height_px), 1.0, SIDE_MAX_PX);

        let pixel_form = self.fx_px.is_some() || self.fy_px.is_some();
        let mm_form = self.focal_length_mm.is_some()
            || self.sensor_width_mm.is_some()
            || self.sensor_height_mm.is_some();
        let fov_form = self.hfov_deg.is_some();
        let forms = [pixel_form, mm_form, fov_form]
            .iter()
            .filter(|f| **f)
            .count();
        if forms != 1 {
            p.push(
                "",
                format!(
                    "exactly one intrinsics form must be given (fx_px + fy_px; focal_length_mm + \
                     sensor_width_mm + sensor_height_mm; or hfov_deg), found {forms}"
                ),
            );
        }
        let require = |p: &mut Problems, key: &str, v: Option<f64>, lo: f64, hi: f64| match v {
            None => p.push(key, "is required by this intrinsics form but missing"),
            Some(v) => {
                if !v.is_finite() || v <= lo || v > hi {
                    p.push(
                        key,
                        format!("{v} is outside the accepted range ({lo}, {hi}]"),
                    );
                }
            }
        };
        if forms == 1 {
            if pixel_form {
                require(p, "fx_px", self.fx_px, 0.0, F_MAX_PX);
                require(p, "fy_px", self.fy_px, 0.0, F_MAX_PX);
                if let (Some(fx), Some(fy)) = (self.fx_px, self.fy_px) {
                    let ratio = fy / fx;
                    if fx > 0.0 && fy > 0.0 && !(0.5..=2.0).contains(&ratio) {
                        p.push(
                            "fy_px",
                            format!(
                                "fy_px / fx_px = {ratio} is outside the accepted range [0.5, 2] \
                                 (pixel aspect ratio)"
                            ),
                        );
                    }
                }
            } else if mm_form {
                require(p, "focal_length_mm", self.focal_length_mm, 0.0, 5000.0);
                require(p, "sensor_width_mm", self.sensor_width_mm, 0.0, 1000.0);
                require(p, "sensor_height_mm", self.sensor_height_mm, 0.0, 1000.0);
            } else {
                p.range("hfov_deg", self.hfov_deg.unwrap_or(f64::NAN), 0.1, 170.0);
            }
        }
        match (self.cx_px, self.cy_px) {
            (None, None) => {}
            (Some(cx), Some(cy)) => {
                p.range("cx_px", cx, -0.5, f64::from(self.width_px) - 0.5);
                p.range("cy_px", cy, -0.5, f64::from(self.height_px) - 0.5);
            }
            (Some(_), None) => p.push("cy_px", "must be given together with cx_px"),
            (None, Some(_)) => p.push("cx_px", "must be given together with cy_px"),
        }
        p.section("distortion", |p| self.distortion.validate(p));
        p.section("mount", |p| self.mount.validate(p));

        // Only with sane values so far: the lens model must be invertible over the whole image.
        if p.list.len() == before {
            match self.intrinsics() {
                Err(e) => p.push("", e.to_string()),
                Ok(k) => {
                    let d = self.distortion.to_distortion();
                    let r_max = d.max_radius();
                    for c in k.corners() {
                        if d.undistort_within(&k.to_normalised(&c), r_max).is_none() {
                            p.push(
                                "distortion",
                                format!(
                                    "the model k1, k2, k3, p1, p2 = {} is not invertible at image corner ({}, {}) px: \
                                     the radial polynomial folds over at normalised radius {r_max:.3}",
                                    crate::text::numbers(&d.coefficients()),
                                    c.x, c.y
                                ),
                            );
                            break;
                        }
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(s: &str) -> Result<CameraConfig, toml::de::Error> {
        toml::from_str(s)
    }

    fn problems(c: &CameraConfig) -> Vec<String> {
        let mut p = Problems::default();
        p.section("camera", |p| c.validate(p));
        p.list.iter().map(|i| i.to_string()).collect()
    }

    #[test]
    fn ngi_three_forms_agree() {
        let a = parse(
            "width_px = 640\nheight_px = 1152\nfx_px = 833.3333333333\nfy_px = 833.3333333333",
        )
        .unwrap()
        .build()
        .unwrap();
        let b = parse(
            "width_px = 640\nheight_px = 1152\nfocal_length_mm = 120\nsensor_width_mm = 92.16\n\
             sensor_height_mm = 165.888",
        )
        .unwrap()
        .build()
        .unwrap();
        let hfov = 2.0 * (320.0f64 / 833.333_333_333_3).atan().to_degrees();
        let c = parse(&format!(
            "width_px = 640\nheight_px = 1152\nhfov_deg = {hfov}"
        ))
        .unwrap()
        .build()
        .unwrap();
        for cam in [&b, &c] {
            assert!((cam.intrinsics.fx_px - a.intrinsics.fx_px).abs() < 1e-6);
            assert!((cam.intrinsics.fy_px - a.intrinsics.fy_px).abs() < 1e-6);
            assert_eq!((cam.intrinsics.cx_px, cam.intrinsics.cy_px), (319.5, 575.5));
        }
        assert_eq!(a.mount, Mount::nadir());
        assert!(a.distortion.is_zero());
    }

    #[test]
    fn full_section_with_distortion_and_mount() {
        let s = r#"
            width_px = 1280
            height_px = 960
            fx_px = 900.0
            fy_px = 905.0
            cx_px = 645.0
            cy_px = 470.0
            [distortion]
            k1 = -0.28
            k2 = 0.07
            p1 = 0.0012
            p2 = -0.0008
            [mount]
            pitch_deg = 10.0
            lever_arm_body_frd_m = [0.2, 0.0, 0.1]
        "#;
        let cfg = parse(s).unwrap();
        assert!(problems(&cfg).is_empty(), "{:?}", problems(&cfg));
        let cam = cfg.build().unwrap();
        assert_eq!(cam.intrinsics.cx_px, 645.0);
        assert_eq!(cam.distortion.k1, -0.28);
        assert_eq!(cam.distortion.k3, 0.0);
        assert_eq!(cam.mount.lever_arm_body_frd_m, Vector3::new(0.2, 0.0, 0.1));
        let (_, pitch, _) = cam.mount.angles_rad();
        assert!((pitch.to_degrees() - 10.0).abs() < 1e-9);
        // Serialising and parsing again gives the same section.
        let again: CameraConfig = toml::from_str(&toml::to_string(&cfg).unwrap()).unwrap();
        assert_eq!(again, cfg);
    }

    #[test]
    fn unknown_keys_are_errors() {
        let e = parse("width_px = 640\nheight_px = 480\nhfov_deg = 60\nfocal_px = 3").unwrap_err();
        assert!(e.to_string().contains("focal_px"), "{e}");
        let e = parse("width_px = 640\nheight_px = 480\nhfov_deg = 60\n[distortion]\nk4 = 0.1")
            .unwrap_err();
        assert!(e.to_string().contains("k4"), "{e}");
        let e =
            parse("width_px = 640\nheight_px = 480\nhfov_deg = 60\n[mount]\nlever_arm = [0,0,0]")
                .unwrap_err();
        assert!(e.to_string().contains("lever_arm"), "{e}");
    }

    #[test]
    fn intrinsics_form_must_be_unique_and_complete() {
        let both =
            parse("width_px = 640\nheight_px = 480\nhfov_deg = 60\nfx_px = 500\nfy_px = 500")
                .unwrap();
        let p = problems(&both);
        assert!(
            p.iter().any(|s| s.starts_with("camera: exactly one")),
            "{p:?}"
        );
        assert!(both.build().is_err());
        let none = parse("width_px = 640\nheight_px = 480").unwrap();
        assert!(problems(&none).iter().any(|s| s.contains("found 0")));
        let half = parse("width_px = 640\nheight_px = 480\nfx_px = 500").unwrap();
        assert!(
            problems(&half)
                .iter()
                .any(|s| s.starts_with("camera.fy_px:"))
        );
        let mm = parse("width_px = 640\nheight_px = 480\nfocal_length_mm = 8\nsensor_width_mm = 6")
            .unwrap();
        assert!(
            problems(&mm)
                .iter()
                .any(|s| s.starts_with("camera.sensor_height_mm:"))
        );
        let cx = parse("width_px = 640\nheight_px = 480\nhfov_deg = 60\ncx_px = 300").unwrap();
        assert!(problems(&cx).iter().any(|s| s.starts_with("camera.cy_px:")));
    }

    #[test]
    fn out_of_range_values_are_reported_with_keys() {
        let s = r#"
            width_px = 0
            height_px = 480
            fx_px = -5.0
            fy_px = 500.0
            cx_px = 700.0
            cy_px = 240.0
            [distortion]
            k1 = 3.0
            p2 = 0.2
            [mount]
            pitch_deg = 95.0
            lever_arm_body_frd_m = [0.0, 1e9, 0.0]
        "#;
        let p = problems(&parse(s).unwrap());
        for key in [
            "camera.width_px:",
            "camera.fx_px:",
            "camera.cx_px:",
            "camera.distortion.k1:",
            "camera.distortion.p2:",
            "camera.mount.pitch_deg:",
            "camera.mount.lever_arm_body_frd_m:",
        ] {
            assert!(
                p.iter().any(|s| s.starts_with(key)),
                "{key} missing in {p:?}"
            );
        }
        // The messages give the value and the range.
        assert!(
            p.iter()
                .any(|s| s.contains("3 is outside the accepted range [-1, 1]")),
            "{p:?}"
        );
        let hfov = parse("width_px = 640\nheight_px = 480\nhfov_deg = 180").unwrap();
        assert!(
            problems(&hfov)
                .iter()
                .any(|s| s.starts_with("camera.hfov_deg:"))
        );
        let aspect = parse("width_px = 640\nheight_px = 480\nfx_px = 500\nfy_px = 1500").unwrap();
        assert!(problems(&aspect).iter().any(|s| s.contains("aspect")));
    }

    #[test]
    fn distortion_folding_inside_the_image_is_rejected() {
        // k1 = -0.9 folds at r = 0.61, but a 90 deg lens has corners at r ~ 1.25.
        let s = "width_px = 640\nheight_px = 480\nhfov_deg = 90\n[distortion]\nk1 = -0.9";
        let cfg = parse(s).unwrap();
        let p = problems(&cfg);
        assert!(
            p.iter()
                .any(|s| s.starts_with("camera.distortion:") && s.contains("not invertible")),
            "{p:?}"
        );
        match cfg.build() {
            Err(CameraError::Config { list }) => assert_eq!(list[0].key, "distortion"),
            other => panic!("expected a config error, got {other:?}"),
        }
        // The same coefficient on a narrow lens is fine.
        let s = "width_px = 640\nheight_px = 480\nhfov_deg = 30\n[distortion]\nk1 = -0.9";
        assert!(problems(&parse(s).unwrap()).is_empty());
    }
}
