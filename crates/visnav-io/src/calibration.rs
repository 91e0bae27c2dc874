//! Camera calibration files of other tools read into visnav's `[camera]` section:
//! - OpenCV's `FileStorage` YAML (the `calibrateCamera` samples): `image_width`, `image_height`,
//!   `camera_matrix` and `distortion_coefficients` as `!!opencv-matrix` with `data: [...]`
//!   (possibly over several lines);
//! - ROS `camera_info` YAML (`camera_calibration`): the same keys, `distortion_model:
//!   plumb_bob` (or `rational_polynomial` with k4-k6 zero);
//! - Kalibr camchain YAML: `camN: camera_model: pinhole`, `intrinsics: [fu, fv, pu, pv]`,
//!   `distortion_model: radtan` (or `none`), `distortion_coeffs: [k1, k2, r1, r2]`,
//!   `resolution: [w, h]`.
//!
//! visnav's lens model is OpenCV's pinhole with k1, k2, p1, p2, k3 (`visnav_core::camera`), and
//! its pixel convention OpenCV's (the top-left pixel's centre at 0, 0), so the numbers are copied
//! unchanged. Other models (fisheye / equidistant, omnidirectional, k4-k6 in use, skew) are
//! refused with what to do. Not a general YAML reader: the `key: value` and `key: [list]`
//! lines these tools write, nested by indentation.

use std::path::{Path, PathBuf};

use visnav_core::camera::{CameraConfig, DistortionConfig};

/// Why a calibration file could not be read. Every variant names the file.
#[derive(Debug, thiserror::Error)]
pub enum CalibrationError {
    #[error("{path}: cannot read: {cause}")]
    Read {
        path: PathBuf,
        cause: std::io::Error,
    },
    #[error("{path}: no `{key}`: not an OpenCV, ROS camera_info or Kalibr camchain calibration")]
    Missing { path: PathBuf, key: String },
    #[error("{path}: `{key}`: {reason}")]
    Bad {
        path: PathBuf,
        key: String,
        reason: String,
    },
    #[error(
        "{path}: {what}; visnav's model is the pinhole camera with OpenCV's k1, k2, p1, p2, k3: calibrate with that model"
    )]
    Unsupported { path: PathBuf, what: String },
}

/// Which tool wrote the file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CalibrationFormat {
    /// OpenCV `FileStorage` YAML or ROS `camera_info` YAML (the same keys).
    OpenCvOrRos,
    /// Kalibr camchain YAML.
    Kalibr,
}

impl std::fmt::Display for CalibrationFormat {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::OpenCvOrRos => "OpenCV / ROS camera_info YAML",
            Self::Kalibr => "Kalibr camchain YAML",
        })
    }
}

/// A calibration read: the `[camera]` intrinsics and distortion (mount left at its defaults),
/// the format, and for Kalibr the camera taken.
#[derive(Debug, Clone, PartialEq)]
pub struct Calibration {
    pub camera: CameraConfig,
    pub format: CalibrationFormat,
    pub camera_name: Option<String>,
}

/// Largest skew accepted, as a fraction of fx (visnav's pinhole has none).
const MAX_SKEW_FRACTION: f64 = 1e-6;

/// Read `path`; for a Kalibr camchain with several cameras, `camera` names the one (`cam0`, ...).
pub fn read_calibration(
    path: &Path,
    camera: Option<&str>,
) -> Result<Calibration, CalibrationError> {
    let text = std::fs::read_to_string(path).map_err(|source| CalibrationError::Read {
        path: path.to_path_buf(),
        cause: source,
    })?;
    parse_calibration(&text, path, camera)
}

/// [`read_calibration`] on text already read (`path` for the messages).
pub fn parse_calibration(
    text: &str,
    path: &Path,
    camera: Option<&str>,
) -> Result<Calibration, CalibrationError> {
    let doc = Doc::parse(text);
    let r = Reader { doc: &doc, path };
    let kalibr: Vec<String> = doc
        .entries
        .iter()
        .filter_map(|(k, _)| k.strip_suffix(".intrinsics").map(str::to_string))
        .collect();
    if kalibr.is_empty() {
        return r.opencv_or_ros();
    }
    let name = match camera {
        Some(c) if kalibr.iter().any(|k| k == c) => c.to_string(),
        Some(c) => {
            return Err(r.bad(
                c,
                format!("no such camera; the file has {}", kalibr.join(", ")),
            ));
        }
        None if kalibr.len() == 1 => kalibr[0].clone(),
        None => {
            return Err(r.bad(
                "camN",
                format!(
                    "{} cameras ({}): choose one",
                    kalibr.len(),
                    kalibr.join(", ")
                ),
            ));
        }
    };
    r.kalibr(&name)
}

/// The file's `dotted.key: value` entries (values as written, flow lists joined onto one line).
struct Doc {
    entries: Vec<(String, String)>,
}

impl Doc {
    fn parse(text: &str) -> Self {
        let mut entries = Vec::new();
        let mut stack: Vec<(usize, String)> = Vec::new();
        let mut lines = text.lines();
        while let Some(raw) = lines.next() {
            let line = raw.split(" #").next().unwrap_or_default();
            let content = line.trim();
            if content.is_empty()
                || content.starts_with('#')
                || content.starts_with('%')
                || content.starts_with("---")
                || content.starts_with('-')
            {
                continue;
            }
            let Some((key, rest)) = content.split_once(':') else {
                continue;
            };
            let indent = line.len() - line.trim_start().len();
            while stack.last().is_some_and(|(i, _)| *i >= indent) {
                stack.pop();
            }
            let key = key.trim().trim_matches(|c| c == '"' || c == '\'');
            let path: String = stack
                .iter()
                .map(|(_, k)| k.as_str())
                .chain([key])
                .collect::<Vec<_>>()
                .join(".");
            // A tag (`!!opencv-matrix`) says nothing visnav needs.
            let mut value = rest.trim().to_string();
            if value.starts_with('!') {
                value = value
                    .split_once(char::is_whitespace)
                    .map_or(String::new(), |(_, v)| v.trim().to_string());
            }
            if value.is_empty() {
                stack.push((indent, key.to_string()));
                continue;
            }
            if value.starts_with('[') {
                while !value.contains(']') {
                    let Some(more) = lines.next() else { break };
                    value.push(' ');
                    value.push_str(more.split(" #").next().unwrap_or_default().trim());
                }
            }
            entries.push((path, value));
        }
        Self { entries }
    }

    fn get(&self, key: &str) -> Option<&str> {
        self.entries
            .iter()
            .find(|(k, _)| k == key)
            .map(|(_, v)| v.as_str())
    }
}

struct Reader<'a> {
    doc: &'a Doc,
    path: &'a Path,
}

impl Reader<'_> {
    fn bad(&self, key: &str, reason: String) -> CalibrationError {
        CalibrationError::Bad {
            path: self.path.to_path_buf(),
            key: key.to_string(),
            reason,
        }
    }

    fn raw(&self, key: &str) -> Result<&str, CalibrationError> {
        self.doc.get(key).ok_or_else(|| CalibrationError::Missing {
            path: self.path.to_path_buf(),
            key: key.to_string(),
        })
    }

    fn text(&self, key: &str) -> Option<String> {
        self.doc
            .get(key)
            .map(|v| v.trim_matches(|c| c == '"' || c == '\'').to_string())
    }

    fn size(&self, key: &str) -> Result<u32, CalibrationError> {
        let v = self.raw(key)?;
        v.parse::<u32>()
            .ok()
            .filter(|&n| n > 0)
            .ok_or_else(|| self.bad(key, format!("{v} is not an image size in pixels")))
    }

    fn list(&self, key: &str) -> Result<Vec<f64>, CalibrationError> {
        let v = self.raw(key)?;
        let inner = v
            .trim()
            .strip_prefix('[')
            .and_then(|s| s.strip_suffix(']'))
            .ok_or_else(|| self.bad(key, format!("{v} is not a [list]")))?;
        inner
            .split(',')
            .map(str::trim)
            .filter(|s| !s.is_empty())
            .map(|s| {
                s.parse::<f64>()
                    .ok()
                    .filter(|x| x.is_finite())
                    .ok_or_else(|| self.bad(key, format!("{s} is not a number")))
            })
            .collect()
    }

    fn unsupported(&self, what: String) -> CalibrationError {
        CalibrationError::Unsupported {
            path: self.path.to_path_buf(),
            what,
        }
    }

    fn opencv_or_ros(&self) -> Result<Calibration, CalibrationError> {
        let (w, h) = (self.size("image_width")?, self.size("image_height")?);
        let k = self.list("camera_matrix.data")?;
        if k.len() != 9 {
            return Err(self.bad("camera_matrix.data", format!("{} values, not 9", k.len())));
        }
        if k[1].abs() > MAX_SKEW_FRACTION * k[0].abs() || k[3] != 0.0 || k[6..] != [0.0, 0.0, 1.0] {
            return Err(self.unsupported(format!(
                "camera_matrix [{}] is not a zero-skew pinhole matrix",
                k.iter()
                    .map(|v| v.to_string())
                    .collect::<Vec<_>>()
                    .join(", ")
            )));
        }
        let model = self.text("distortion_model");
        let d = match self.doc.get("distortion_coefficients.data") {
            Some(_) => self.list("distortion_coefficients.data")?,
            None => Vec::new(),
        };
        let distortion = match model.as_deref() {
            None | Some("plumb_bob") | Some("rational_polynomial") => self.opencv_coeffs(&d)?,
            Some(m) => return Err(self.unsupported(format!("distortion_model {m}"))),
        };
        Ok(Calibration {
            camera: camera(w, h, [k[0], k[4], k[2], k[5]], distortion),
            format: CalibrationFormat::OpenCvOrRos,
            camera_name: self.text("camera_name"),
        })
    }

    /// OpenCV's order: k1, k2, p1, p2[, k3[, k4, k5, k6[, s1..s4[, tx, ty]]]]; beyond k3 only
    /// zeros are visnav's model.
    fn opencv_coeffs(&self, d: &[f64]) -> Result<DistortionConfig, CalibrationError> {
        if !(d.is_empty() || d.len() >= 4) {
            return Err(self.bad(
                "distortion_coefficients.data",
                format!("{} values: OpenCV writes 4, 5, 8, 12 or 14", d.len()),
            ));
        }
        if d.iter().skip(5).any(|&v| v != 0.0) {
            return Err(self.unsupported(
                "coefficients beyond k3 in use (rational, thin-prism or tilted model)".into(),
            ));
        }
        let at = |i: usize| d.get(i).copied().unwrap_or(0.0);
        Ok(DistortionConfig {
            k1: at(0),
            k2: at(1),
            p1: at(2),
            p2: at(3),
            k3: at(4),
        })
    }

    fn kalibr(&self, cam: &str) -> Result<Calibration, CalibrationError> {
        let key = |k: &str| format!("{cam}.{k}");
        let model = self.text(&key("camera_model"));
        if model.as_deref() != Some("pinhole") {
            return Err(self.unsupported(format!(
                "{cam}: camera_model {}",
                model.as_deref().unwrap_or("(none)")
            )));
        }
        let f = self.list(&key("intrinsics"))?;
        let res = self.list(&key("resolution"))?;
        if f.len() != 4 || res.len() != 2 {
            return Err(self.bad(
                &key("intrinsics"),
                "intrinsics [fu, fv, pu, pv] and resolution [w, h] expected".into(),
            ));
        }
        let size = |v: f64| {
            (v >= 1.0 && v.fract() == 0.0 && v <= f64::from(u32::MAX))
                .then_some(v as u32)
                .ok_or_else(|| self.bad(&key("resolution"), format!("{v} is not a size")))
        };
        let (w, h) = (size(res[0])?, size(res[1])?);
        let distortion = match self.text(&key("distortion_model")).as_deref() {
            Some("radtan") => {
                let d = self.list(&key("distortion_coeffs"))?;
                if d.len() != 4 {
                    return Err(self.bad(
                        &key("distortion_coeffs"),
                        format!("{} values, not 4", d.len()),
                    ));
                }
                self.opencv_coeffs(&d)?
            }
            Some("none") | None => DistortionConfig::default(),
            Some(m) => return Err(self.unsupported(format!("{cam}: distortion_model {m}"))),
        };
        Ok(Calibration {
            camera: camera(w, h, [f[0], f[1], f[2], f[3]], distortion),
            format: CalibrationFormat::Kalibr,
            camera_name: Some(cam.to_string()),
        })
    }
}

fn camera(w: u32, h: u32, f: [f64; 4], distortion: DistortionConfig) -> CameraConfig {
    CameraConfig {
        width_px: w,
        height_px: h,
        fx_px: Some(f[0]),
        fy_px: Some(f[1]),
        cx_px: Some(f[2]),
        cy_px: Some(f[3]),
        focal_length_mm: None,
        sensor_width_mm: None,
        sensor_height_mm: None,
        hfov_deg: None,
        distortion,
        mount: Default::default(),
    }
}

/// The `[camera]` and `[camera.distortion]` sections of `cal` as TOML text to paste into a
/// configuration (the mount is the user's: `[camera.mount]`, docs/first-flight.md).
pub fn camera_toml(cal: &Calibration, source: &Path) -> String {
    let c = &cal.camera;
    let d = &c.distortion;
    let num = |v: Option<f64>| v.map_or("0".to_string(), |x| format!("{x}"));
    format!(
        "# from {} ({}{})\n[camera]\nwidth_px = {}\nheight_px = {}\nfx_px = {}\nfy_px = {}\n\
         cx_px = {}\ncy_px = {}\n\n[camera.distortion]\nk1 = {}\nk2 = {}\np1 = {}\np2 = {}\nk3 = {}\n",
        source.display(),
        cal.format,
        cal.camera_name
            .as_ref()
            .map(|n| format!(", camera {n}"))
            .unwrap_or_default(),
        c.width_px,
        c.height_px,
        num(c.fx_px),
        num(c.fy_px),
        num(c.cx_px),
        num(c.cy_px),
        d.k1,
        d.k2,
        d.p1,
        d.p2,
        d.k3
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use visnav_core::validate::{Problems, Validate};

    const OPENCV: &str = "%YAML:1.0\n---\ncalibration_time: \"Tue 01 Jan\"\nimage_width: 640\n\
        image_height: 480\ncamera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n\
        \x20  data: [ 6.5746697944293521e+02, 0., 3.1950000000000000e+02, 0.,\n\
        \x20      6.5746697944293521e+02, 2.3950000000000000e+02, 0., 0., 1. ]\n\
        distortion_coefficients: !!opencv-matrix\n   rows: 5\n   cols: 1\n   dt: d\n\
        \x20  data: [ -4.1802327176423804e-01, 5.0715244063187526e-01, 0., 0.,\n\
        \x20      -5.7843597214487474e-01 ]\n";

    const ROS: &str = "image_width: 1280\nimage_height: 720\ncamera_name: downward\n\
        camera_matrix:\n  rows: 3\n  cols: 3\n  data: [910.5, 0, 640.2, 0, 911.0, 361.7, 0, 0, 1]\n\
        distortion_model: plumb_bob\ndistortion_coefficients:\n  rows: 1\n  cols: 5\n\
        \x20 data: [-0.12, 0.05, 0.001, -0.0005, 0]\nrectification_matrix:\n  rows: 3\n  cols: 3\n\
        \x20 data: [1, 0, 0, 0, 1, 0, 0, 0, 1]\nprojection_matrix:\n  rows: 3\n  cols: 4\n\
        \x20 data: [900, 0, 640, 0, 0, 900, 360, 0, 0, 0, 1, 0]\n";

    const KALIBR: &str = "cam0:\n  cam_overlaps: [1]\n  camera_model: pinhole\n\
        \x20 distortion_coeffs: [-0.28, 0.07, 0.0002, 1.7e-05]\n  distortion_model: radtan\n\
        \x20 intrinsics: [458.6, 457.3, 367.2, 248.4]\n  resolution: [752, 480]\n\
        \x20 rostopic: /cam0/image_raw\n  T_cam_imu:\n  - [0.01, -0.99, 0.0, -0.02]\n\
        \x20 - [0.99, 0.01, 0.02, 0.06]\n  - [0, 0, 1, 0]\n  - [0, 0, 0, 1]\n\
        cam1:\n  camera_model: omni\n  intrinsics: [0.8, 400, 400, 320, 240]\n  resolution: [640, 480]\n";

    fn parse(text: &str, cam: Option<&str>) -> Result<Calibration, CalibrationError> {
        parse_calibration(text, Path::new("cal.yaml"), cam)
    }

    /// The TOML printed for `cal` parses back into the same `[camera]` and validates.
    fn round_trip(cal: &Calibration) {
        #[derive(serde::Deserialize)]
        struct Wrap {
            camera: CameraConfig,
        }
        let text = camera_toml(cal, Path::new("cal.yaml"));
        let back: Wrap = toml::from_str(&text).unwrap();
        assert_eq!(back.camera, cal.camera, "{text}");
        let mut p = Problems::default();
        back.camera.validate(&mut p);
        assert!(p.list.is_empty(), "{:?}", p.list);
    }

    #[test]
    fn opencv_file_storage_yaml_with_multi_line_matrices() {
        let cal = parse(OPENCV, None).unwrap();
        let c = &cal.camera;
        assert_eq!((c.width_px, c.height_px), (640, 480));
        assert!((c.fx_px.unwrap() - 657.466_979_442_935).abs() < 1e-9);
        assert_eq!(c.cy_px, Some(239.5));
        assert!((c.distortion.k1 + 0.418_023_271_764_238).abs() < 1e-12);
        assert!((c.distortion.k3 + 0.578_435_972_144_874_7).abs() < 1e-12);
        assert_eq!((c.distortion.p1, c.distortion.p2), (0.0, 0.0));
        round_trip(&cal);
    }

    #[test]
    fn ros_camera_info_uses_k_not_p() {
        let cal = parse(ROS, None).unwrap();
        let c = &cal.camera;
        assert_eq!(
            (c.fx_px, c.fy_px, c.cx_px, c.cy_px),
            (Some(910.5), Some(911.0), Some(640.2), Some(361.7))
        );
        assert_eq!((c.distortion.p1, c.distortion.p2), (0.001, -0.0005));
        assert_eq!(cal.camera_name.as_deref(), Some("downward"));
        round_trip(&cal);
    }

    #[test]
    fn kalibr_camchain_by_camera() {
        let cal = parse(KALIBR, Some("cam0")).unwrap();
        let c = &cal.camera;
        assert_eq!((c.width_px, c.height_px), (752, 480));
        assert_eq!((c.fx_px, c.cy_px), (Some(458.6), Some(248.4)));
        assert_eq!(
            (c.distortion.k1, c.distortion.p2, c.distortion.k3),
            (-0.28, 1.7e-05, 0.0)
        );
        round_trip(&cal);
        // Two cameras: which one must be said; an omnidirectional one is refused with the reason.
        let e = parse(KALIBR, None).unwrap_err().to_string();
        assert!(e.contains("cam0, cam1") && e.contains("choose"), "{e}");
        let e = parse(KALIBR, Some("cam1")).unwrap_err().to_string();
        assert!(
            e.contains("camera_model omni") && e.contains("pinhole"),
            "{e}"
        );
        let e = parse(KALIBR, Some("cam7")).unwrap_err().to_string();
        assert!(e.contains("no such camera"), "{e}");
    }

    #[test]
    fn other_models_and_broken_files_are_refused_by_name() {
        let fisheye = ROS.replace("plumb_bob", "equidistant");
        let e = parse(&fisheye, None).unwrap_err().to_string();
        assert!(e.contains("distortion_model equidistant"), "{e}");
        let rational = ROS.replace(
            "[-0.12, 0.05, 0.001, -0.0005, 0]",
            "[-0.12, 0.05, 0.001, -0.0005, 0, 0.3, 0, 0]",
        );
        let e = parse(&rational, None).unwrap_err().to_string();
        assert!(e.contains("beyond k3"), "{e}");
        let zeros = rational.replace("0, 0.3, 0, 0]", "0, 0, 0, 0]");
        assert!(parse(&zeros, None).is_ok());
        let skew = ROS.replace("[910.5, 0, 640.2", "[910.5, 3.0, 640.2");
        let e = parse(&skew, None).unwrap_err().to_string();
        assert!(e.contains("zero-skew"), "{e}");
        let e = parse("image_width: 640\n", None).unwrap_err().to_string();
        assert!(e.contains("image_height") && e.contains("cal.yaml"), "{e}");
        let e = parse(&ROS.replace("910.5", "nan"), None)
            .unwrap_err()
            .to_string();
        assert!(e.contains("camera_matrix.data"), "{e}");
        assert!(parse("", None).is_err());
        assert!(parse("::: [[[", None).is_err());
    }
}
