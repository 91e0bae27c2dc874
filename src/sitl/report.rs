//! The closed loop's report folder (`visnav sim --out DIR`):
//!
//! | file | content |
//! | --- | --- |
//! | `summary.json` | the summary `visnav sim --json` prints |
//! | `steps.csv` | every 0.1 s: truth, the vision and the control filters' positions, NED errors, horizontal 1-sigma, health |
//! | `fixes.csv` | every vision fix: capture time, latency, accepted/reason, position, NED error, sigma, 3-sigma test |
//! | `injections.csv` | every GPS_INPUT the emulators received (vision and control), with its NED error |
//! | `track.geojson` | truth, visnav and no-vision tracks (LineString, WGS84 lon/lat) and the accepted fixes (Point), for QGIS |
//! | `track.png` | the tracks over the map orthophoto |
//! | `errors.png` | horizontal error against time: visnav, no-vision, accepted fixes, visnav's 3-sigma bound, the GPS outage |
//!
//! CSV: comma separated, a header line, `NaN` for missing values (before the filter is
//! initialised, rejected fixes), times in scenario seconds.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use super::closed_loop::{ClosedLoopError, ClosedLoopRun};

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> ClosedLoopError + '_ {
    move |source| ClosedLoopError::Io {
        path: path.to_path_buf(),
        source,
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
        "t_s,gps_on,truth_lat_deg,truth_lon_deg,truth_alt_amsl_m,vis_lat_deg,vis_lon_deg,vis_err_n_m,vis_err_e_m,vis_err_d_m,vis_sigma_h_m,vis_health,ctl_lat_deg,ctl_lon_deg,ctl_err_n_m,ctl_err_e_m,ctl_err_d_m,ctl_sigma_h_m,ctl_health\n",
    );
    for r in &run.steps {
        let _ = writeln!(
            s,
            "{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}",
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

/// `injections.csv`.
pub fn injections_csv(run: &ClosedLoopRun) -> String {
    let mut s = String::from(
        "t_s,run,lat_deg,lon_deg,alt_amsl_m,horiz_accuracy_m,err_n_m,err_e_m,err_d_m\n",
    );
    for r in &run.injections {
        let _ = writeln!(
            s,
            "{},{},{},{},{},{},{},{},{}",
            f(r.t_s),
            if r.control { "control" } else { "vision" },
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
    Ok(vec![
        write(dir, "summary.json", &summary)?,
        write(dir, "steps.csv", &steps_csv(run))?,
        write(dir, "fixes.csv", &fixes_csv(run))?,
        write(dir, "injections.csv", &injections_csv(run))?,
        write(dir, "track.geojson", &gj)?,
    ])
}

/// Writes the whole report folder (text files and plots); returns the files written.
pub fn write_report(run: &ClosedLoopRun, dir: &Path) -> Result<Vec<PathBuf>, ClosedLoopError> {
    write_text_files(run, dir)
}
