//! The closed loop's report folder (`visnav sim --out DIR`):
//!
//! | file | content |
//! | --- | --- |
//! | `summary.json` | the summary `visnav sim --json` prints |
//! | `steps.csv` | every 0.1 s: truth, the vision and the control filters' positions, NED errors, horizontal 1-sigma, health; last their heading errors (`vis_yaw_err_deg`, `ctl_yaw_err_deg`, wrapped to +-180 deg) |
//! | `fixes.csv` | every vision fix: capture time, latency, accepted/reason, position, NED error, sigma, 3-sigma test |
//! | `dtm_poses.csv` | with `[dtm_nav]`: every pose of the DTM navigator: capture time, its partner's, baseline, inliers, NED error, sigma, 3-sigma test, Euler angle error |
//! | `injections.csv` | every GPS_INPUT the emulators received (vision and control), with its NED error |
//! | `track.geojson` | truth, visnav and no-vision tracks (LineString, WGS84 lon/lat) and the accepted fixes (Point), for QGIS |
//! | `track.png` | truth, visnav, no-vision and the accepted fixes over the camera-year orthophoto (axes in the map's CRS), beside a zoom on the GPS outage where visnav is farthest from the truth |
//! | `errors.png` | horizontal error against time: visnav with its claimed 1- and 3-sigma and the accepted fixes (linear), visnav against no-vision (log); GPS-on periods shaded |
//! | `residuals.png` | the accepted fixes' north / east errors against time within their claimed 3-sigma, the rejected attempts' times; east against north with the median claimed 3-sigma circle |
//!
//! The plots are drawn by [`plot`].
//!
//! CSV: comma separated, a header line, `NaN` for missing values (before the filter is
//! initialised, rejected fixes), times in scenario seconds.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use super::closed_loop::{ClosedLoopError, ClosedLoopRun, Latency};
use super::plot::{self, ErrorsData, Residual, ResidualsData, TrackData};

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> ClosedLoopError + '_ {
    move |source| ClosedLoopError::Io {
        path: path.to_path_buf(),
        cause: source,
    }
}

fn write(dir: &Path, name: &str, text: &str) -> Result<PathBuf, ClosedLoopError> {
    let p = dir.join(name);
    std::fs::write(&p, text).map_err(io_err(&p))?;
    Ok(p)
}

fn f(v: f64) -> String {
    if v.is_finite() {
        format!("{v:.3}")
    } else {
        "NaN".into()
    }
}

fn deg(v: f64) -> String {
    if v.is_finite() {
        format!("{v:.8}")
    } else {
        "NaN".into()
    }
}

/// `steps.csv`.
pub fn steps_csv(run: &ClosedLoopRun) -> String {
    let mut s = String::from(
        "t_s,gps_on,truth_lat_deg,truth_lon_deg,truth_alt_amsl_m,vis_lat_deg,vis_lon_deg,vis_err_n_m,vis_err_e_m,vis_err_d_m,vis_sigma_h_m,vis_health,ctl_lat_deg,ctl_lon_deg,ctl_err_n_m,ctl_err_e_m,ctl_err_d_m,ctl_sigma_h_m,ctl_health,vis_yaw_err_deg,ctl_yaw_err_deg\n",
    );
    for r in &run.steps {
        let _ = writeln!(
            s,
            "{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}",
            f(r.t_s),
            u8::from(r.gps_on),
            deg(r.truth_lat_deg),
            deg(r.truth_lon_deg),
            f(r.truth_alt_amsl_m),
            deg(r.vis_lat_deg),
            deg(r.vis_lon_deg),
            f(r.vis_err_ned_m[0]),
            f(r.vis_err_ned_m[1]),
            f(r.vis_err_ned_m[2]),
            f(r.vis_sigma_h_m),
            r.vis_health,
            deg(r.ctl_lat_deg),
            deg(r.ctl_lon_deg),
            f(r.ctl_err_ned_m[0]),
            f(r.ctl_err_ned_m[1]),
            f(r.ctl_err_ned_m[2]),
            f(r.ctl_sigma_h_m),
            r.ctl_health,
            f(r.vis_yaw_err_deg),
            f(r.ctl_yaw_err_deg),
        );
    }
    s
}

/// `fixes.csv`.
pub fn fixes_csv(run: &ClosedLoopRun) -> String {
    let mut s = String::from(
        "t_capture_s,latency_ms,accepted,reason,lat_deg,lon_deg,err_n_m,err_e_m,err_d_m,sigma_h_m,beyond_3sigma,inliers,fix_ms\n",
    );
    for r in &run.fixes {
        let reason = r.reason.replace([',', '\n', '"'], ";");
        let _ = writeln!(
            s,
            "{},{},{},{},{},{},{},{},{},{},{},{},{}",
            f(r.t_capture_s),
            f(r.latency_ms),
            u8::from(r.accepted),
            reason,
            deg(r.lat_deg),
            deg(r.lon_deg),
            f(r.err_ned_m[0]),
            f(r.err_ned_m[1]),
            f(r.err_ned_m[2]),
            f(r.sigma_h_m),
            u8::from(r.beyond_3sigma),
            r.inliers,
            f(r.ms),
        );
    }
    s
}

/// `dtm_poses.csv`.
pub fn dtm_poses_csv(run: &ClosedLoopRun) -> String {
    let mut s = String::from(
        "t_capture_s,t_first_s,baseline_m,inliers,err_n_m,err_e_m,err_d_m,sigma_h_m,beyond_3sigma,euler_err_deg\n",
    );
    for r in &run.dtm_poses {
        let _ = writeln!(
            s,
            "{},{},{},{},{},{},{},{},{},{}",
            f(r.t_capture_s),
            f(r.t_first_s),
            f(r.baseline_m),
            r.inliers,
            f(r.err_ned_m[0]),
            f(r.err_ned_m[1]),
            f(r.err_ned_m[2]),
            f(r.sigma_h_m),
            u8::from(r.beyond_3sigma),
            f(r.euler_err_deg),
        );
    }
    s
}

/// `injections.csv`.
pub fn injections_csv(run: &ClosedLoopRun) -> String {
    let mut s = String::from(
        "t_s,run,message,lat_deg,lon_deg,alt_amsl_m,horiz_accuracy_m,err_n_m,err_e_m,err_d_m\n",
    );
    for r in &run.injections {
        let _ = writeln!(
            s,
            "{},{},{},{},{},{},{},{},{},{}",
            f(r.t_s),
            if r.control { "control" } else { "vision" },
            r.kind,
            deg(r.lat_deg),
            deg(r.lon_deg),
            f(r.alt_amsl_m),
            f(r.horiz_accuracy_m),
            f(r.err_ned_m[0]),
            f(r.err_ned_m[1]),
            f(r.err_ned_m[2]),
        );
    }
    s
}

/// `track.geojson`: a FeatureCollection (RFC 7946, WGS84 lon/lat).
pub fn geojson(run: &ClosedLoopRun) -> serde_json::Value {
    let line = |name: &str, pts: Vec<[f64; 2]>| {
        serde_json::json!({
            "type": "Feature",
            "properties": { "name": name },
            "geometry": { "type": "LineString", "coordinates": pts },
        })
    };
    let finite = |p: &[f64; 2]| p[0].is_finite() && p[1].is_finite();
    let truth: Vec<[f64; 2]> = run
        .steps
        .iter()
        .map(|r| [r.truth_lon_deg, r.truth_lat_deg])
        .filter(finite)
        .collect();
    let vis: Vec<[f64; 2]> = run
        .steps
        .iter()
        .map(|r| [r.vis_lon_deg, r.vis_lat_deg])
        .filter(finite)
        .collect();
    let ctl: Vec<[f64; 2]> = run
        .steps
        .iter()
        .map(|r| [r.ctl_lon_deg, r.ctl_lat_deg])
        .filter(finite)
        .collect();
    let mut features = vec![
        line("truth", truth),
        line("visnav", vis),
        line("no-vision control", ctl),
    ];
    for fx in run.fixes.iter().filter(|f| f.accepted) {
        if fx.lat_deg.is_finite() && fx.lon_deg.is_finite() {
            features.push(serde_json::json!({
                "type": "Feature",
                "properties": {
                    "name": "vision fix",
                    "t_capture_s": fx.t_capture_s,
                    "err_h_m": fx.err_ned_m[0].hypot(fx.err_ned_m[1]),
                    "sigma_h_m": fx.sigma_h_m,
                    "inliers": fx.inliers,
                },
                "geometry": { "type": "Point", "coordinates": [fx.lon_deg, fx.lat_deg] },
            }));
        }
    }
    serde_json::json!({ "type": "FeatureCollection", "features": features })
}

/// Writes the text files of the report folder (creating it); returns the files written.
pub fn write_text_files(run: &ClosedLoopRun, dir: &Path) -> Result<Vec<PathBuf>, ClosedLoopError> {
    std::fs::create_dir_all(dir).map_err(io_err(dir))?;
    let summary = serde_json::to_string_pretty(&run.summary).unwrap_or_default();
    let gj = serde_json::to_string(&geojson(run)).unwrap_or_default();
    let mut files = vec![
        write(dir, "summary.json", &summary)?,
        write(dir, "steps.csv", &steps_csv(run))?,
        write(dir, "fixes.csv", &fixes_csv(run))?,
    ];
    if !run.dtm_poses.is_empty() {
        files.push(write(dir, "dtm_poses.csv", &dtm_poses_csv(run))?);
    }
    files.push(write(dir, "injections.csv", &injections_csv(run))?);
    files.push(write(dir, "track.geojson", &gj)?);
    Ok(files)
}

/// The run's time span, s.
fn time_span(run: &ClosedLoopRun) -> (f64, f64) {
    let t = || run.steps.iter().map(|r| r.t_s).filter(|t| t.is_finite());
    (
        t().fold(f64::INFINITY, f64::min),
        t().fold(f64::NEG_INFINITY, f64::max),
    )
}

fn h(e: &[f64; 3]) -> f64 {
    e[0].hypot(e[1])
}

/// The GPS-on periods from the steps' flags.
fn gps_on(run: &ClosedLoopRun) -> Vec<(f64, f64)> {
    let t: Vec<f64> = run.steps.iter().map(|r| r.t_s).collect();
    let on: Vec<bool> = run.steps.iter().map(|r| r.gps_on).collect();
    plot::periods(&t, &on)
}

/// What the summary's figures cover, in words: "in the GPS outage (30-330 s)" when the
/// evaluation window is the outage (to the second), else "in the evaluation window (60-120 s)".
pub fn window_scope(window_s: [f64; 2], gps_outage_s: Option<[f64; 2]>) -> String {
    let same = |a: f64, b: f64| (a - b).abs() < 0.5;
    let span = format!("{:.0}-{:.0} s", window_s[0], window_s[1]);
    match gps_outage_s {
        Some(o) if same(o[0], window_s[0]) && same(o[1], window_s[1]) => {
            format!("in the GPS outage ({span})")
        }
        _ => format!("in the evaluation window ({span})"),
    }
}

/// The accepted vision fixes, counted in the evaluation window (the summary's figures) and
/// over the whole flight (what the plots draw): the console and `errors.png` both state them
/// from here, each number with its scope.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FixCounts {
    /// Accepted fixes in the window (the summary's `fixes_accepted`).
    pub accepted: usize,
    /// Fix attempts in the window (the summary's `fix_attempts`).
    pub attempts: usize,
    /// The window in words ([`window_scope`]).
    pub scope: String,
    /// Accepted fixes over the whole flight.
    pub flight_accepted: usize,
}

impl FixCounts {
    /// The run's counts.
    pub fn of(run: &ClosedLoopRun) -> Self {
        let s = &run.summary;
        Self {
            accepted: s.fixes_accepted,
            attempts: s.fix_attempts,
            scope: window_scope(s.evaluation_window_s, s.gps_outage_s),
            flight_accepted: run.fixes.iter().filter(|f| f.accepted).count(),
        }
    }

    /// "586 in the GPS outage (30-330 s), 636 in the whole flight".
    pub fn accepted_text(&self) -> String {
        format!(
            "{} {}, {} in the whole flight",
            self.accepted, self.scope, self.flight_accepted
        )
    }
}

/// The capture-to-fix latency in words, for the console. In real time it is measured (the
/// summary's p50 / p95 over the window, `scope`). In lock-step every fix result arrives a
/// configured time after its capture (`lockstep_latency_s`, `[closed_loop]
/// lockstep_fix_latency_s`) and the simulated clock stands still while a fix is computed: there
/// is nothing measured to show, and the constant is named as what it is.
pub fn latency_text(lockstep_latency_s: Option<f64>, latency_ms: &Latency, scope: &str) -> String {
    match lockstep_latency_s {
        Some(l) => format!(
            "capture-to-fix latency: {:.0} ms, simulated (lock-step: the configured [closed_loop] lockstep_fix_latency_s, not a measurement; --realtime measures it)",
            l * 1e3
        ),
        None if latency_ms.p50.is_finite() && latency_ms.p95.is_finite() => format!(
            "capture-to-fix latency p50 / p95 {scope}: {:.0} / {:.0} ms (measured, real time)",
            latency_ms.p50, latency_ms.p95
        ),
        None => format!("capture-to-fix latency: no fix result {scope}"),
    }
}

/// `errors.png`'s data: horizontal errors, visnav's sigma, the GPS-on periods, accepted fixes.
pub fn errors_data(run: &ClosedLoopRun) -> ErrorsData {
    ErrorsData {
        title: format!("{}: horizontal position error", run.summary.scenario),
        t_s: run.steps.iter().map(|r| r.t_s).collect(),
        visnav_m: run.steps.iter().map(|r| h(&r.vis_err_ned_m)).collect(),
        sigma_m: run.steps.iter().map(|r| r.vis_sigma_h_m).collect(),
        control_m: run.steps.iter().map(|r| h(&r.ctl_err_ned_m)).collect(),
        gps_on: gps_on(run),
        fixes: run
            .fixes
            .iter()
            .filter(|f| f.accepted)
            .map(|f| (f.t_capture_s, h(&f.err_ned_m)))
            .collect(),
        fixes_count: FixCounts::of(run).accepted_text(),
    }
}

/// `track.png`'s data: the tracks in the orthophoto's CRS.
pub fn track_data(run: &ClosedLoopRun) -> TrackData<'_> {
    let xy = |lat: f64, lon: f64| -> (f64, f64) {
        if !(lat.is_finite() && lon.is_finite()) {
            return (f64::NAN, f64::NAN);
        }
        run.crs
            .from_geodetic(lat, lon)
            .unwrap_or((f64::NAN, f64::NAN))
    };
    let st = &run.steps;
    TrackData {
        title: format!("{}: track", run.summary.scenario),
        crs: run.crs.to_string(),
        background: run.background.as_ref().map(|(i, e)| (i, *e)),
        t_s: st.iter().map(|r| r.t_s).collect(),
        truth: st
            .iter()
            .map(|r| xy(r.truth_lat_deg, r.truth_lon_deg))
            .collect(),
        visnav: st
            .iter()
            .map(|r| xy(r.vis_lat_deg, r.vis_lon_deg))
            .collect(),
        control: st
            .iter()
            .map(|r| xy(r.ctl_lat_deg, r.ctl_lon_deg))
            .collect(),
        outage: st.iter().map(|r| !r.gps_on).collect(),
        fixes: run
            .fixes
            .iter()
            .filter(|f| f.accepted)
            .map(|f| xy(f.lat_deg, f.lon_deg))
            .collect(),
    }
}

/// `residuals.png`'s data: the accepted fixes' errors, the rejected attempts' times.
pub fn residuals_data(run: &ClosedLoopRun) -> ResidualsData {
    ResidualsData {
        title: format!("{}: vision fix residuals", run.summary.scenario),
        accepted: run
            .fixes
            .iter()
            .filter(|f| f.accepted)
            .map(|f| Residual {
                t_s: f.t_capture_s,
                north_m: f.err_ned_m[0],
                east_m: f.err_ned_m[1],
                sigma_m: f.sigma_h_m,
                beyond_3sigma: f.beyond_3sigma,
            })
            .collect(),
        rejected_t_s: run
            .fixes
            .iter()
            .filter(|f| !f.accepted)
            .map(|f| f.t_capture_s)
            .collect(),
        gps_on: gps_on(run),
        t_range: time_span(run),
    }
}

/// Writes the whole report folder (text files and plots); returns the files written.
pub fn write_report(run: &ClosedLoopRun, dir: &Path) -> Result<Vec<PathBuf>, ClosedLoopError> {
    let mut files = write_text_files(run, dir)?;
    let plot_err = |e: plot::PlotError| ClosedLoopError::Setup(e.to_string());
    for (name, img) in [
        ("track.png", plot::track(&track_data(run))),
        ("errors.png", plot::errors(&errors_data(run))),
        ("residuals.png", plot::residuals(&residuals_data(run))),
    ] {
        let p = dir.join(name);
        plot::save_png(&img.map_err(plot_err)?, &p).map_err(plot_err)?;
        files.push(p);
    }
    Ok(files)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_window_is_named_by_what_it_covers() {
        // The outage's end is the flight's duration, a sum of steps: not exactly the window's.
        assert_eq!(
            window_scope([30.0, 330.0], Some([30.0, 330.000_000_000_06])),
            "in the GPS outage (30-330 s)"
        );
        assert_eq!(
            window_scope([60.0, 120.0], Some([30.0, 330.0])),
            "in the evaluation window (60-120 s)"
        );
        assert_eq!(
            window_scope([0.0, 90.0], None),
            "in the evaluation window (0-90 s)"
        );
    }

    #[test]
    fn lockstep_latency_is_named_a_constant() {
        let lat = Latency {
            p50: 150.0,
            p95: 150.0,
        };
        let scope = "in the GPS outage (30-330 s)";
        let l = latency_text(Some(0.15), &lat, scope);
        assert!(
            l.starts_with("capture-to-fix latency: 150 ms, simulated"),
            "{l}"
        );
        assert!(
            l.contains("configured") && l.contains("not a measurement"),
            "{l}"
        );
        assert!(!l.contains("p50"), "{l}");
        let r = latency_text(None, &lat, scope);
        assert_eq!(
            r,
            "capture-to-fix latency p50 / p95 in the GPS outage (30-330 s): 150 / 150 ms (measured, real time)"
        );
        let none = Latency {
            p50: f64::NAN,
            p95: f64::NAN,
        };
        assert!(!latency_text(None, &none, scope).contains("NaN"));
    }

    #[test]
    fn fix_counts_say_their_scope() {
        let c = FixCounts {
            accepted: 586,
            attempts: 600,
            scope: window_scope([30.0, 330.0], Some([30.0, 330.0])),
            flight_accepted: 636,
        };
        assert_eq!(
            c.accepted_text(),
            "586 in the GPS outage (30-330 s), 636 in the whole flight"
        );
    }
}
