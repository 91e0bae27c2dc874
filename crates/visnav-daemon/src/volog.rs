//! The visual odometry log (`[daemon] vo_log`): one JSON line per frame the odometer ran on, with
//! the motion it measured (camera displacement NED and its covariance over the two capture times)
//! and what the filter did with it, stamped with the companion's Unix time like the fix log
//! (`fixlog`). With the camera's true poses (`visnav sitl-run --truth-log`) `sitl/vo_check.py`
//! scores every motion against the truth: its error, and that error over the claimed covariance.

use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

use visnav_core::nav::{VoFix, VoRotation};
use visnav_core::vo::VoStep;

/// One odometry result.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VoLogRecord {
    /// Companion Unix time when the result reached the navigation task, µs.
    pub arrival_unix_us: u64,
    /// Frame sequence number.
    pub seq: u64,
    /// Capture time of the frame, autopilot boot µs.
    pub t_capture_us: u64,
    /// `started` (first frame of a sequence), `motion` or `refused`.
    pub step: String,
    /// Why there is no motion (`refused`), else empty.
    pub reason: String,
    /// The refusal's class (`visnav_core::vo::VoRefusal::class`; logs written before it existed
    /// lack it), else empty.
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub reason_class: String,
    /// What the filter did with a motion: `fused`, `filter_rejected` or `unused`; else empty.
    pub outcome: String,
    /// The filter's normalised innovation squared (fused or gate-rejected motions).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub nis: Option<f64>,
    /// Capture time of the previous frame, autopilot boot µs (motions).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub t_prev_us: Option<u64>,
    /// Camera displacement from the previous frame to this one, NED, m.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dp_ned_m: Option<[f64; 3]>,
    /// Its covariance as measured (before the filter adds the terrain term), NED, m^2.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cov_ned_m2: Option<[[f64; 3]; 3]>,
    /// Height of the previous camera above the terrain that gave the scale, m.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub agl_m: Option<f64>,
    /// Mean line of sight from the next camera to the ground points, NED, m.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub look_ned_m: Option<[f64; 3]>,
    /// The rotation the images saw beyond the gyros' about that line of sight and its 1-sigma
    /// (the images' and the gyros' sampling), deg (`nav::VoRotation`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rot_los_deg: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    /// Its 1-sigma, deg.
    pub rot_los_sigma_deg: Option<f64>,
    /// How the displacement moved with an error of the gyros' rotation, NED, m/rad, rows
    /// (`nav::VoFix::rotation_sensitivity_ned`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rot_sensitivity_ned: Option<[[f64; 3]; 3]>,
    /// Tracks followed, tracks on the terrain, inliers, reprojection RMS (px).
    #[serde(default)]
    pub tracks: usize,
    #[serde(default)]
    /// Tracks on the terrain.
    pub on_ground: usize,
    #[serde(default)]
    /// Inliers of the motion.
    pub inliers: usize,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    /// Reprojection RMS, px.
    pub rms_px: Option<f64>,
    /// The filter's attitude the frame was given: roll, pitch, yaw (deg) and the tilt and yaw
    /// sigma (deg).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub prior_rpy_deg: Option<[f64; 3]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    /// Sigma of the tilt and of the yaw, deg.
    pub prior_sigma_tilt_yaw_deg: Option<[f64; 2]>,
}

impl VoLogRecord {
    /// With the filter's attitude the frame was given (`vo_path::VoResult`).
    pub fn with_prior_attitude(mut self, a: Option<([f64; 3], [f64; 2])>) -> Self {
        if let Some((rpy, sig)) = a.filter(|(r, s)| r.iter().chain(s).all(|v| v.is_finite())) {
            self.prior_rpy_deg = Some(rpy);
            self.prior_sigma_tilt_yaw_deg = Some(sig);
        }
        self
    }

    /// The record of one odometry step; `outcome` and `nis` are the filter's (motions only).
    /// Non-finite numbers become `None` (JSON has no NaN).
    pub fn new(
        arrival_unix_us: u64,
        seq: u64,
        t_capture_us: u64,
        step: &VoStep,
        outcome: &str,
        nis: Option<f64>,
    ) -> Self {
        let mut r = Self {
            arrival_unix_us,
            seq,
            t_capture_us,
            step: String::new(),
            reason: String::new(),
            reason_class: String::new(),
            outcome: String::new(),
            nis: nis.filter(|v| v.is_finite()),
            t_prev_us: None,
            dp_ned_m: None,
            cov_ned_m2: None,
            agl_m: None,
            look_ned_m: None,
            rot_los_deg: None,
            rot_los_sigma_deg: None,
            rot_sensitivity_ned: None,
            tracks: 0,
            on_ground: 0,
            inliers: 0,
            rms_px: None,
            prior_rpy_deg: None,
            prior_sigma_tilt_yaw_deg: None,
        };
        match step {
            VoStep::Started => r.step = "started".into(),
            VoStep::Refused(why) => {
                r.step = "refused".into();
                r.reason = why.to_string();
                r.reason_class = why.class().to_string();
            }
            VoStep::Motion(m) => {
                let fix = &m.fix;
                let dp = [fix.dp_ned_m.x, fix.dp_ned_m.y, fix.dp_ned_m.z];
                let cov: [[f64; 3]; 3] =
                    std::array::from_fn(|i| std::array::from_fn(|j| fix.cov_ned_m2[(i, j)]));
                r.step = "motion".into();
                r.outcome = outcome.to_string();
                r.t_prev_us = Some(fix.t_prev_us);
                r.dp_ned_m = dp.iter().all(|v| v.is_finite()).then_some(dp);
                r.cov_ned_m2 = cov.iter().flatten().all(|v| v.is_finite()).then_some(cov);
                r.agl_m = fix.agl_m.is_finite().then_some(fix.agl_m);
                let l = [fix.look_ned_m.x, fix.look_ned_m.y, fix.look_ned_m.z];
                r.look_ned_m = l.iter().all(|v| v.is_finite()).then_some(l);
                if let Some(rot) = &fix.rotation {
                    let (a, s) = (rot.about_los_rad.to_degrees(), rot.sigma_rad.to_degrees());
                    r.rot_los_deg = a.is_finite().then_some(a);
                    r.rot_los_sigma_deg = s.is_finite().then_some(s);
                }
                r.rot_sensitivity_ned = fix
                    .rotation_sensitivity_ned
                    .map(|g| std::array::from_fn(|i| std::array::from_fn(|j| g[(i, j)])))
                    .filter(|g: &[[f64; 3]; 3]| g.iter().flatten().all(|v| v.is_finite()));
                r.tracks = m.tracks;
                r.on_ground = m.on_ground;
                r.inliers = m.inliers;
                r.rms_px = m.rms_px.is_finite().then_some(m.rms_px);
            }
        }
        r
    }
}

impl VoLogRecord {
    /// A `motion` record as the filter's measurement again (`visnav replay --vo-log`), with the
    /// terrain model's height sigma and the distance over which it stays the same, which the log
    /// does not carry (the map's and `[vo] terrain_error_corr_dist_m`). `None` for the other
    /// steps and for a motion missing a number (the log leaves non-finite numbers out).
    pub fn vo_fix(&self, terrain_sigma_m: f64, terrain_corr_dist_m: f64) -> Option<VoFix> {
        if self.step != "motion" {
            return None;
        }
        let (dp, cov, look) = (self.dp_ned_m?, self.cov_ned_m2?, self.look_ned_m?);
        let rotation = match (self.rot_los_deg, self.rot_los_sigma_deg) {
            (Some(a), Some(s)) => Some(VoRotation {
                about_los_rad: a.to_radians(),
                sigma_rad: s.to_radians(),
            }),
            _ => None,
        };
        Some(VoFix {
            t_prev_us: self.t_prev_us?,
            t_next_us: self.t_capture_us,
            dp_ned_m: Vector3::from(dp),
            cov_ned_m2: Matrix3::from_fn(|i, j| cov[i][j]),
            agl_m: self.agl_m?,
            terrain_sigma_m,
            terrain_corr_dist_m,
            look_ned_m: Vector3::from(look),
            rotation,
            rotation_sensitivity_ned: self
                .rot_sensitivity_ned
                .map(|g| Matrix3::from_fn(|i, j| g[i][j])),
        })
    }
}

/// Parse a VO log; an error names the line.
pub fn read_vo_log(text: &str) -> Result<Vec<VoLogRecord>, crate::fixlog::FixLogError> {
    crate::fixlog::read_json_lines(text)
}

/// The VO log (one [`VoLogRecord`] per line).
pub type VoLog = crate::fixlog::JsonLinesLog;

#[cfg(test)]
mod tests {
    use super::*;
    use visnav_core::vo::VoMotion;

    #[test]
    fn every_step_is_one_json_line_and_reads_back() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("vo.jsonl");
        let motion = VoStep::Motion(Box::new(VoMotion {
            fix: VoFix {
                t_prev_us: 1_000_000,
                t_next_us: 1_200_000,
                dp_ned_m: Vector3::new(3.0, -1.0, 0.2),
                cov_ned_m2: Matrix3::from_diagonal(&Vector3::new(0.04, 0.05, 0.3)),
                agl_m: 1500.0,
                terrain_sigma_m: 5.0,
                terrain_corr_dist_m: 1000.0,
                look_ned_m: Vector3::new(10.0, 0.0, 1500.0),
                rotation: Some(visnav_core::nav::VoRotation {
                    about_los_rad: 1e-4,
                    sigma_rad: 2e-4,
                }),
                rotation_sensitivity_ned: Some(Matrix3::new(
                    0.0, -1500.0, 0.5, 1500.0, 0.0, -10.0, -0.5, 10.0, 0.0,
                )),
            },
            tracks: 250,
            on_ground: 240,
            inliers: 230,
            rms_px: f64::NAN,
        }));
        let recs = [
            VoLogRecord::new(1, 0, 800_000, &VoStep::Started, "", None),
            VoLogRecord::new(2, 1, 1_200_000, &motion, "fused", Some(1.5))
                .with_prior_attitude(Some(([1.0, -2.0, 90.0], [0.1, 0.5]))),
            VoLogRecord::new(
                3,
                2,
                1_400_000,
                &VoStep::Refused(visnav_core::vo::VoRefusal::Frame("blank".into())),
                "",
                None,
            ),
        ];
        let mut log = VoLog::create(&p).unwrap();
        for r in &recs {
            log.write(r).unwrap();
        }
        drop(log);
        let text = std::fs::read_to_string(&p).unwrap();
        let back: Vec<VoLogRecord> = text
            .lines()
            .map(|l| serde_json::from_str(l).unwrap())
            .collect();
        assert_eq!(back, recs.to_vec());
        assert_eq!(back[1].dp_ned_m, Some([3.0, -1.0, 0.2]));
        assert_eq!(back[1].cov_ned_m2.unwrap()[2][2], 0.3);
        assert_eq!(back[1].t_prev_us, Some(1_000_000));
        assert_eq!(back[1].rms_px, None, "NaN is not JSON: left out");
        assert_eq!(back[1].prior_rpy_deg, Some([1.0, -2.0, 90.0]));
        // The motion reads back as the filter's measurement (the terrain figures given again).
        let VoStep::Motion(m) = &motion else {
            unreachable!()
        };
        let again = back[1].vo_fix(5.0, 1000.0).expect("a motion");
        assert_eq!(again.dp_ned_m, m.fix.dp_ned_m);
        assert_eq!(again.cov_ned_m2, m.fix.cov_ned_m2);
        assert_eq!((again.t_prev_us, again.t_next_us), (1_000_000, 1_200_000));
        assert_eq!(again.look_ned_m, m.fix.look_ned_m);
        assert_eq!(
            again.rotation_sensitivity_ned,
            m.fix.rotation_sensitivity_ned
        );
        let (r0, r1) = (again.rotation.unwrap(), m.fix.rotation.unwrap());
        assert!((r0.about_los_rad - r1.about_los_rad).abs() < 1e-15);
        assert!((r0.sigma_rad - r1.sigma_rad).abs() < 1e-15);
        assert!(back[0].vo_fix(5.0, 1000.0).is_none());
        assert!(back[2].vo_fix(5.0, 1000.0).is_none());
        let text_back = read_vo_log(&text).unwrap();
        assert_eq!(text_back, back);
        let err = read_vo_log("{}\nnot json\n").unwrap_err();
        assert_eq!(err.line, 1);
        assert_eq!(back[0].prior_rpy_deg, None);
        let rot = back[1].rot_los_deg.unwrap();
        assert!((rot - 1e-4f64.to_degrees()).abs() < 1e-12, "{rot}");
        assert_eq!(
            (
                back[2].step.as_str(),
                back[2].reason.as_str(),
                back[2].reason_class.as_str()
            ),
            ("refused", "frame: blank", "bad_frame")
        );
        assert!(!text.contains("dp_ned_m\":null"), "{text}");
    }
}
