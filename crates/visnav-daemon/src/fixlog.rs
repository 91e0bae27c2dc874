//! The vision fix log (`[daemon] fix_log`): one JSON line per fix result the navigation task
//! received, with what the filter did with it, stamped with the companion's Unix time (the clock
//! of the `.tlog`), so `visnav replay --fixes` can put the vision fixes back into a replayed
//! flight at the moment they arrived.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use visnav_core::fix::{FixMethod, FixReport, PriorDependenceNed, Rejection, VisionOnlyPose};

/// One fix result.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FixLogRecord {
    /// Companion Unix time when the result reached the navigation task, µs.
    pub arrival_unix_us: u64,
    /// Capture time of the frame, autopilot boot µs.
    pub t_capture_us: u64,
    /// Frame sequence number.
    pub seq: u64,
    /// Frame-to-fix latency, ms.
    pub latency_ms: u64,
    /// The engine accepted the fix.
    pub accepted: bool,
    /// The engine's reason: "ok", or the rejection in words.
    pub reason: String,
    /// The rejection's class (`visnav_core::fix::rejection::CLASSES`; "ok" when accepted; logs
    /// written before it existed lack it and read back as "recorded").
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub reason_class: String,
    /// What the daemon did with it: `accepted`, `rejected` (filter gate), `too_old`, `invalid`,
    /// `unused_before_init`, `engine_rejected`, `initialised`, `held`, `reset`.
    pub outcome: String,
    /// Latitude, deg (accepted fixes).
    pub lat_deg: Option<f64>,
    /// Longitude, deg.
    pub lon_deg: Option<f64>,
    /// Height above the WGS84 ellipsoid, m.
    pub h_ellip_m: Option<f64>,
    /// Altitude AMSL, m.
    pub alt_amsl_m: Option<f64>,
    /// Position covariance NED, m^2.
    pub cov_ned_m2: Option<[[f64; 3]; 3]>,
    /// Inliers of the resection.
    pub inliers: usize,
    /// Reprojection RMS, px.
    pub reproj_rms_px: Option<f64>,
    /// Correspondences given to the resection (logs written before it existed lack it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub matches: Option<usize>,
    /// A-posteriori standard deviation of unit weight of the image-only adjustment (absent where
    /// the engine computed none: a rejection before the adjustment, a placement fix).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sigma0: Option<f64>,
    /// The factor on the a-priori covariance behind `cov_ned_m2` (`pose::PoseCovariance::factor`:
    /// the variance factor, the split-sample factor and the configured inflation together).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cov_factor: Option<f64>,
    /// The image-only pose with its 6x6 covariance (logs written before it existed lack it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub vision_only: Option<VisionOnlyPose>,
    /// The position's dependence on the attitude prior and whether that prior was the filter's
    /// own attitude (logs written before they existed lack them).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub prior_dependence: Option<PriorDependenceNed>,
    #[serde(default)]
    /// The prior's attitude was the navigation filter's own (not the autopilot's).
    pub prior_attitude_from_filter: bool,
    /// How the accepted fix's correspondences were found (`features` or `area`; None for a
    /// rejection, and in logs written before it existed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub method: Option<FixMethod>,
}

impl FixLogRecord {
    /// The record of `report` (NaN and infinite numbers become `None`).
    pub fn new(
        arrival_unix_us: u64,
        seq: u64,
        latency_ms: u64,
        report: &FixReport,
        outcome: &str,
    ) -> Self {
        let f = |v: f64| v.is_finite().then_some(v);
        let cov = report.cov_ned_m2;
        Self {
            arrival_unix_us,
            t_capture_us: report.t_capture_us,
            seq,
            latency_ms,
            accepted: report.accepted,
            reason: report.reason(),
            reason_class: report.class().to_string(),
            outcome: outcome.to_string(),
            lat_deg: f(report.lat_deg),
            lon_deg: f(report.lon_deg),
            h_ellip_m: f(report.h_ellip_m),
            alt_amsl_m: f(report.alt_amsl_m),
            cov_ned_m2: cov.iter().flatten().all(|v| v.is_finite()).then_some(cov),
            inliers: report.inliers,
            reproj_rms_px: f(report.reproj_rms_px),
            matches: Some(report.matches),
            sigma0: f(report.sigma0),
            cov_factor: f(report.cov_factor),
            vision_only: report.vision_only.filter(VisionOnlyPose::is_finite),
            prior_dependence: report
                .prior_dependence
                .filter(PriorDependenceNed::is_finite),
            prior_attitude_from_filter: report.prior_attitude_from_filter,
            method: report.accepted.then_some(report.method),
        }
    }

    /// Back to a report (for `vision_measurement`); missing numbers are NaN.
    pub fn report(&self) -> FixReport {
        let mut r = FixReport::rejected(
            Rejection::recorded(&self.reason_class, &self.reason),
            self.t_capture_us,
            self.latency_ms as f64,
        );
        r.accepted = self.accepted;
        if self.accepted {
            r.rejection = None;
        }
        let n = |v: Option<f64>| v.unwrap_or(f64::NAN);
        r.lat_deg = n(self.lat_deg);
        r.lon_deg = n(self.lon_deg);
        r.h_ellip_m = n(self.h_ellip_m);
        r.alt_amsl_m = n(self.alt_amsl_m);
        r.cov_ned_m2 = self.cov_ned_m2.unwrap_or([[f64::NAN; 3]; 3]);
        r.inliers = self.inliers;
        r.reproj_rms_px = n(self.reproj_rms_px);
        r.matches = self.matches.unwrap_or(0);
        r.sigma0 = n(self.sigma0);
        r.cov_factor = n(self.cov_factor);
        r.vision_only = self.vision_only;
        r.prior_dependence = self.prior_dependence;
        r.prior_attitude_from_filter = self.prior_attitude_from_filter;
        r.method = self.method.unwrap_or_default();
        r
    }
}

/// An open JSON-lines log (the fix log, the VO log `volog`): one serialised record per line,
/// flushed per record (a few to tens per second), so a killed run loses at most its last line.
pub struct JsonLinesLog {
    path: PathBuf,
    out: BufWriter<File>,
}

/// The fix log.
pub type FixLog = JsonLinesLog;

impl JsonLinesLog {
    /// Create (truncate) the file.
    pub fn create(path: &Path) -> std::io::Result<Self> {
        Ok(Self {
            path: path.to_path_buf(),
            out: BufWriter::new(File::create(path)?),
        })
    }

    /// `[daemon]`'s log path with `{t}` expanded to the Unix time now, created; `None` when off.
    pub fn open_configured(path: Option<&Path>) -> Result<Option<Self>, (PathBuf, std::io::Error)> {
        let Some(p) = path else { return Ok(None) };
        let p = visnav_link::tlog::expand_name(p, visnav_link::tlog::unix_now_us() / 1_000_000);
        Self::create(&p).map(Some).map_err(|e| (p, e))
    }

    /// The file's path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Append one record and flush.
    pub fn write<T: Serialize>(&mut self, r: &T) -> std::io::Result<()> {
        let line = serde_json::to_string(r).map_err(std::io::Error::other)?;
        self.out.write_all(line.as_bytes())?;
        self.out.write_all(b"\n")?;
        self.out.flush()
    }
}

/// A fix log line that is not a record.
#[derive(Debug, thiserror::Error)]
#[error("line {line}: {error}")]
pub struct FixLogError {
    /// 1-based line number.
    pub line: usize,
    /// The parser's error.
    pub error: serde_json::Error,
}

/// Parse a fix log; an error names the line.
pub fn read_fix_log(text: &str) -> Result<Vec<FixLogRecord>, FixLogError> {
    read_json_lines(text)
}

/// Parse a JSON-lines log (one record per line, blank lines skipped); an error names the line.
pub fn read_json_lines<T: serde::de::DeserializeOwned>(text: &str) -> Result<Vec<T>, FixLogError> {
    text.lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty())
        .map(|(i, l)| serde_json::from_str(l).map_err(|error| FixLogError { line: i + 1, error }))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_errors() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("fixes.jsonl");
        let mut good = FixReport::rejected(Rejection::NoHypothesis, 5_000_000, 30.0);
        good.accepted = true;
        good.rejection = None;
        good.lat_deg = 47.0;
        good.lon_deg = -99.0;
        good.h_ellip_m = 2400.0;
        good.alt_amsl_m = 2410.0;
        good.cov_ned_m2 = [[25.0, 1.0, 0.0], [1.0, 30.0, 0.0], [0.0, 0.0, 90.0]];
        good.inliers = 40;
        good.reproj_rms_px = 1.2;
        good.matches = 55;
        good.sigma0 = 1.3;
        good.cov_factor = 2.7;
        good.method = FixMethod::Area;
        let mut cov6 = [[0.0; 6]; 6];
        for (i, row) in cov6.iter_mut().enumerate() {
            row[i] = if i < 3 { 400.0 } else { 1e-4 };
        }
        cov6[1][3] = 0.19;
        cov6[3][1] = 0.19;
        good.vision_only = Some(visnav_core::fix::VisionOnlyPose {
            lat_deg: 47.0001,
            lon_deg: -99.0001,
            h_ellip_m: 2401.0,
            roll_deg: 1.0,
            pitch_deg: -2.0,
            yaw_deg: 91.0,
            cov6_ned: cov6,
        });
        let bad = FixReport::rejected(Rejection::FewFeatures { n: 3 }, 5_500_000, 12.0);
        let mut log = FixLog::create(&p).unwrap();
        let r1 = FixLogRecord::new(1_700_000_000_000_000, 7, 30, &good, "accepted");
        let r2 = FixLogRecord::new(1_700_000_000_500_000, 8, 12, &bad, "engine_rejected");
        log.write(&r1).unwrap();
        log.write(&r2).unwrap();
        drop(log);
        let back = read_fix_log(&std::fs::read_to_string(&p).unwrap()).unwrap();
        assert_eq!(back, vec![r1.clone(), r2.clone()]);
        assert_eq!(back[1].lat_deg, None);
        let rep = back[0].report();
        assert!(rep.accepted && rep.lat_deg == 47.0 && rep.cov_ned_m2[1][1] == 30.0);
        assert_eq!(rep.vision_only, good.vision_only, "image-only pose kept");
        assert_eq!((rep.matches, rep.sigma0, rep.cov_factor), (55, 1.3, 2.7));
        assert_eq!(back[1].sigma0, None, "a rejection has no variance factor");
        assert_eq!(back[0].method, Some(FixMethod::Area), "method kept");
        assert_eq!(rep.method, FixMethod::Area);
        assert_eq!(back[1].method, None, "a rejection has no method");
        // A rejection reads back with its words and its class; an acceptance as "ok".
        let rep1 = back[1].report();
        assert_eq!(
            (rep1.reason().as_str(), rep1.class()),
            ("only 3 features in the frame", "few_features")
        );
        assert_eq!((rep.reason().as_str(), rep.class()), ("ok", "ok"));
        // A log written before the image-only pose existed still reads.
        let old = r#"{"arrival_unix_us":1,"t_capture_us":2,"seq":3,"latency_ms":4,"accepted":false,"reason":"x","outcome":"engine_rejected","lat_deg":null,"lon_deg":null,"h_ellip_m":null,"alt_amsl_m":null,"cov_ned_m2":null,"inliers":0,"reproj_rms_px":null}"#;
        assert_eq!(read_fix_log(old).unwrap()[0].vision_only, None);
        assert_eq!(read_fix_log(old).unwrap()[0].method, None);
        assert_eq!(read_fix_log(old).unwrap()[0].cov_factor, None);
        assert!(back[1].report().lat_deg.is_nan());
        let e = read_fix_log("{\"arrival_unix_us\": 1}\nnot json\n")
            .unwrap_err()
            .to_string();
        assert!(e.starts_with("line 1"), "{e}");
    }
}
