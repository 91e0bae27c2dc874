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
//! lines these tools write, nested by indentation. A key given twice is refused (which one the
//! tool meant is unknowable), a matrix's `rows` x `cols` must match its `data`, a leading UTF-8
//! byte order mark is ignored, and OpenCV's XML form of `FileStorage` is refused by name (save
//! the calibration as YAML). A file without distortion coefficients is read as distortion-free
//! with a note ([`Calibration::notes`]) that says so.

use std::path::{Path, PathBuf};

use visnav_core::camera::{CameraConfig, DistortionConfig};

use visnav_core::text::{num, quote};

/// Why a calibration file could not be read. Every variant names the file.
#[derive(Debug, thiserror::Error)]
pub enum CalibrationError {
    /// The file could not be read.
    #[error("{path}: cannot read: {cause}")]
    Read {
        /// The file.
        path: PathBuf,
        /// The operating system's error.
        cause: std::io::Error,
    },
    /// A key every supported format has is missing: not a calibration file.
    #[error("{path}: no `{key}`: not an OpenCV, ROS camera_info or Kalibr camchain calibration")]
    Missing {
        /// The file.
        path: PathBuf,
        /// The key.
        key: String,
    },
    /// A key holds a value that cannot be used.
    #[error("{path}: `{key}`: {reason}")]
    Bad {
        /// The file.
        path: PathBuf,
        /// The key.
        key: String,
        /// What is wrong, in words.
        reason: String,
    },
    /// The file holds a model or form the import does not take.
    #[error(
        "{path}: {what}; visnav's model is the pinhole camera with OpenCV's k1, k2, p1, p2, k3: calibrate with that model"
    )]
    Unsupported {
        /// The file.
        path: PathBuf,
        /// What the file holds.
        what: String,
    },
    /// An OpenCV XML file (only the YAML form is read).
    #[error(
        "{path}: an OpenCV FileStorage XML file, which visnav does not read: save the calibration \
         as YAML (cv::FileStorage writes YAML when the file name ends in .yaml or .yml) and import that"
    )]
    Xml {
        /// The file.
        path: PathBuf,
    },
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
    /// The `[camera]` intrinsics and distortion (the mount at its defaults).
    pub camera: CameraConfig,
    /// The format the file was read as.
    pub format: CalibrationFormat,
    /// For a Kalibr camchain: the camera taken (`cam0`, ...).
    pub camera_name: Option<String>,
    /// What the import assumed that the file did not say (no distortion coefficients): for the
    /// user to read before flying with it.
    pub notes: Vec<String>,
}

/// Largest skew accepted, as a fraction of fx (visnav's pinhole has none).
const MAX_SKEW_FRACTION: f64 = 1e-6;

/// The note for a calibration without distortion coefficients.
const NO_DISTORTION_NOTE: &str = "the file gives no distortion coefficients: written as a \
distortion-free lens (k1 = k2 = p1 = p2 = k3 = 0); unless the lens really has none, calibrate \
with distortion, or the fixes will be off towards the image edges";

/// Read `path`; for a Kalibr camchain with several cameras, `camera` names the one (`cam0`, ...).
pub fn read_calibration(
    path: &Path,
    camera: Option<&str>,
) -> Result<Calibration, CalibrationError> {
    let text = crate::files::read_text(path, crate::files::CALIBRATION).map_err(|source| {
        CalibrationError::Read {
            path: path.to_path_buf(),
            cause: source,
        }
    })?;
    parse_calibration(&text, path, camera)
}

/// [`read_calibration`] on text already read (`path` for the messages).
pub fn parse_calibration(
    text: &str,
    path: &Path,
    camera: Option<&str>,
) -> Result<Calibration, CalibrationError> {
    let text = text.strip_prefix(crate::files::BOM).unwrap_or(text);
    let head = text.trim_start();
    if head.starts_with("<?xml") || head.starts_with("<opencv_storage") {
        return Err(CalibrationError::Xml {
            path: path.to_path_buf(),
        });
    }
    let doc = Doc::parse(text).map_err(|(key, first, second)| CalibrationError::Bad {
        path: path.to_path_buf(),
        key,
        reason: format!(
            "given twice (lines {first} and {second}): which one is meant is unknowable; keep one"
        ),
    })?;
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
                "--camera",
                format!(
                    "no such camera {}; the file has {}",
                    quote(c),
                    kalibr.join(", ")
                ),
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
    /// The entries; a dotted key given twice is `Err((key, first line, second line))`.
    fn parse(text: &str) -> Result<Self, (String, usize, usize)> {
        let mut entries = Vec::new();
        // The line each key was given on (1-based), for a key given twice.
        let mut seen: std::collections::HashMap<String, usize> = std::collections::HashMap::new();
        let mut stack: Vec<(usize, String)> = Vec::new();
        let mut lines = text.lines().enumerate();
        while let Some((index, raw)) = lines.next() {
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
                    let Some((_, more)) = lines.next() else { break };
                    value.push(' ');
                    value.push_str(more.split(" #").next().unwrap_or_default().trim());
                }
            }
            if let Some(&first) = seen.get(&path) {
                return Err((path, first, index + 1));
            }
            seen.insert(path.clone(), index + 1);
            entries.push((path, value));
        }
        Ok(Self { entries })
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
            .ok_or_else(|| self.bad(key, format!("{} is not an image size in pixels", quote(v))))
    }

    fn list(&self, key: &str) -> Result<Vec<f64>, CalibrationError> {
        let v = self.raw(key)?;
        let inner = v
            .trim()
            .strip_prefix('[')
            .and_then(|s| s.strip_suffix(']'))
            .ok_or_else(|| self.bad(key, format!("{} is not a [list]", quote(v))))?;
        inner
            .split(',')
            .map(str::trim)
            .filter(|s| !s.is_empty())
            .map(|s| {
                s.parse::<f64>()
                    .ok()
                    .filter(|x| x.is_finite())
                    .ok_or_else(|| self.bad(key, format!("{} is not a number", quote(s))))
            })
            .collect()
    }

    fn unsupported(&self, what: String) -> CalibrationError {
        CalibrationError::Unsupported {
            path: self.path.to_path_buf(),
            what,
        }
    }

    /// A matrix's `data` (`name.data`), checked against its `rows` and `cols` when given.
    fn matrix(&self, name: &str) -> Result<Vec<f64>, CalibrationError> {
        let data = self.list(&format!("{name}.data"))?;
        let dim = |k: &str| -> Result<Option<u64>, CalibrationError> {
            let key = format!("{name}.{k}");
            match self.doc.get(&key) {
                None => Ok(None),
                Some(v) => v
                    .parse::<u64>()
                    .map(Some)
                    .map_err(|_| self.bad(&key, format!("{} is not a count", quote(v)))),
            }
        };
        if let (Some(rows), Some(cols)) = (dim("rows")?, dim("cols")?)
            && rows.checked_mul(cols) != Some(data.len() as u64)
        {
            return Err(self.bad(
                name,
                format!(
                    "rows {rows} x cols {cols} does not match the {} values of its data",
                    data.len()
                ),
            ));
        }
        Ok(data)
    }

    fn opencv_or_ros(&self) -> Result<Calibration, CalibrationError> {
        let (w, h) = (self.size("image_width")?, self.size("image_height")?);
        let k = self.matrix("camera_matrix")?;
        if k.len() != 9 {
            return Err(self.bad("camera_matrix.data", format!("{} values, not 9", k.len())));
        }
        if k[1].abs() > MAX_SKEW_FRACTION * k[0].abs() || k[3] != 0.0 || k[6..] != [0.0, 0.0, 1.0] {
            return Err(self.unsupported(format!(
                "camera_matrix [{}] is not a zero-skew pinhole matrix",
                k.iter().map(|&v| num(v)).collect::<Vec<_>>().join(", ")
            )));
        }
        let model = self.text("distortion_model");
        let d = match self.doc.get("distortion_coefficients.data") {
            Some(_) => self.matrix("distortion_coefficients")?,
            None => Vec::new(),
        };
        let distortion = match model.as_deref() {
            None | Some("plumb_bob") | Some("rational_polynomial") => self.opencv_coeffs(&d)?,
            Some(m) => return Err(self.unsupported(format!("distortion_model {}", quote(m)))),
        };
        Ok(Calibration {
            camera: camera(w, h, [k[0], k[4], k[2], k[5]], distortion),
            format: CalibrationFormat::OpenCvOrRos,
            camera_name: self.text("camera_name"),
            notes: if d.is_empty() {
                vec![NO_DISTORTION_NOTE.to_string()]
            } else {
                Vec::new()
            },
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
                model.as_deref().map_or("(none)".to_string(), quote)
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
                .ok_or_else(|| self.bad(&key("resolution"), format!("{} is not a size", num(v))))
        };
        let (w, h) = (size(res[0])?, size(res[1])?);
        let mut notes = Vec::new();
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
            // Said so by the file: a lens without distortion, nothing assumed.
            Some("none") => DistortionConfig::default(),
            None => {
                notes.push(NO_DISTORTION_NOTE.to_string());
                DistortionConfig::default()
            }
            Some(m) => {
                return Err(self.unsupported(format!("{cam}: distortion_model {}", quote(m))));
            }
        };
        Ok(Calibration {
            camera: camera(w, h, [f[0], f[1], f[2], f[3]], distortion),
            format: CalibrationFormat::Kalibr,
            camera_name: Some(cam.to_string()),
            notes,
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
    let notes: String = cal.notes.iter().map(|n| format!("# note: {n}\n")).collect();
    format!(
        "# from {} ({}{})\n{notes}[camera]\nwidth_px = {}\nheight_px = {}\nfx_px = {}\nfy_px = {}\n\
         cx_px = {}\ncy_px = {}\n\n[camera.distortion]\nk1 = {}\nk2 = {}\np1 = {}\np2 = {}\nk3 = {}\n",
        source.display(),
        cal.format,
        cal.camera_name
            .as_deref()
            .map(|n| format!(", camera {}", quote(n)))
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
            e.contains("camera_model \"omni\"") && e.contains("pinhole"),
            "{e}"
        );
        let e = parse(KALIBR, Some("cam7")).unwrap_err().to_string();
        assert!(e.contains("no such camera"), "{e}");
    }

    #[test]
    fn other_models_and_broken_files_are_refused_by_name() {
        let fisheye = ROS.replace("plumb_bob", "equidistant");
        let e = parse(&fisheye, None).unwrap_err().to_string();
        assert!(e.contains("distortion_model \"equidistant\""), "{e}");
        let rational = ROS
            .replace(
                "[-0.12, 0.05, 0.001, -0.0005, 0]",
                "[-0.12, 0.05, 0.001, -0.0005, 0, 0.3, 0, 0]",
            )
            .replace("  cols: 5\n", "  cols: 8\n");
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

    #[test]
    fn a_key_given_twice_is_refused_naming_both_lines() {
        let twice = ROS.replace(
            "image_height: 720\n",
            "image_height: 720\nimage_width: 1920\n",
        );
        let e = parse(&twice, None).unwrap_err().to_string();
        assert!(
            e.contains("`image_width`") && e.contains("lines 1 and 3"),
            "{e}"
        );
        let two_matrices = format!("{ROS}camera_matrix:\n  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]\n");
        let e = parse(&two_matrices, None).unwrap_err().to_string();
        assert!(
            e.contains("camera_matrix.data") && e.contains("twice"),
            "{e}"
        );
    }

    #[test]
    fn a_matrix_size_that_disagrees_with_its_data_is_refused() {
        let e = parse(&ROS.replace("  rows: 1\n", "  rows: 999999999999\n"), None)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("distortion_coefficients") && e.contains("rows 999999999999 x cols 5"),
            "{e}"
        );
        let e = parse(
            &ROS.replace("  rows: 3\n  cols: 3\n", "  rows: 3\n  cols: x\n"),
            None,
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("camera_matrix.cols") && e.contains("\"x\""),
            "{e}"
        );
        // The OpenCV and ROS examples' sizes agree with their data.
        assert!(parse(OPENCV, None).is_ok());
    }

    #[test]
    fn no_distortion_coefficients_is_said_not_assumed_silently() {
        let empty = ROS.replace("[-0.12, 0.05, 0.001, -0.0005, 0]", "[]");
        let empty = empty.replace("  rows: 1\n  cols: 5\n", "  rows: 1\n  cols: 0\n");
        let cal = parse(&empty, None).unwrap();
        assert_eq!(cal.camera.distortion, DistortionConfig::default());
        assert_eq!(cal.notes.len(), 1);
        assert!(cal.notes[0].contains("no distortion coefficients"));
        let text = camera_toml(&cal, Path::new("cal.yaml"));
        assert!(
            text.contains("# note: the file gives no distortion"),
            "{text}"
        );
        round_trip(&cal);
        assert!(parse(ROS, None).unwrap().notes.is_empty());
        // Kalibr's explicit "none" says it; a missing model is noted.
        let none = KALIBR.replace("distortion_model: radtan", "distortion_model: none");
        assert!(parse(&none, Some("cam0")).unwrap().notes.is_empty());
        let missing = KALIBR.replace("  distortion_model: radtan\n", "");
        assert_eq!(parse(&missing, Some("cam0")).unwrap().notes.len(), 1);
    }

    #[test]
    fn byte_order_mark_and_xml() {
        let cal = parse(&format!("\u{feff}{ROS}"), None).unwrap();
        assert_eq!(cal.camera.width_px, 1280);
        let xml = "<?xml version=\"1.0\"?>\n<opencv_storage>\n<image_width>640</image_width>\n\
                   </opencv_storage>\n";
        let e = parse(xml, None).unwrap_err().to_string();
        assert!(
            e.contains("cal.yaml") && e.contains("XML") && e.contains(".yaml"),
            "{e}"
        );
        assert!(!e.contains("image_width"), "{e}");
    }

    #[test]
    fn a_huge_value_is_quoted_by_a_short_prefix() {
        let long = "7".repeat(10_000_000);
        let e = parse(
            &ROS.replace("image_width: 1280", &format!("image_width: {long}")),
            None,
        )
        .unwrap_err()
        .to_string();
        assert!(e.len() < 300 && e.contains("(10000000 bytes)"), "{e}");
        let e = parse(&ROS.replace("910.5, 0, 640.2", "910.5, 1e300, 640.2"), None)
            .unwrap_err()
            .to_string();
        assert!(e.contains("1e300") && e.len() < 400, "{e}");
    }

    #[test]
    fn reading_refuses_a_device_and_an_oversized_file() {
        let e = read_calibration(Path::new("/dev/zero"), None)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("/dev/zero") && e.contains("not a regular file"),
            "{e}"
        );
        let d = tempfile::tempdir().unwrap();
        let f = d.path().join("big.yaml");
        std::fs::write(&f, vec![b'#'; 2 << 20]).unwrap();
        let e = read_calibration(&f, None).unwrap_err().to_string();
        assert!(e.contains("big.yaml") && e.contains("1 MiB"), "{e}");
    }
}
