//! The closed-loop scenario's two halves for a `visnav run` of your own (`visnav sim
//! --write-frames DIR`, `visnav sim --autopilot-only CONNECTION`): the scenario's camera as a
//! folder of frames, and its autopilot emulator as a SITL autopilot in real time.
//!
//! * [`write_frames`] renders the camera-year orthophoto at the true pose (the same camera, mount,
//!   scene and photometry as the closed loop's simulated camera, `sitl::camera_sim`) at
//!   `[closed_loop] camera_rate_hz` from `camera_from_s` to the scenario's end, into PNG files
//!   and a `frames.csv` with `t_boot_us` (the `visnav_io::frames` format). The times are the
//!   emulator's boot clock, which is the scenario time (`t_s = 0` when the emulator starts; the
//!   closed-loop module doc), so `[frames] stamp = "source"` puts each frame where the emulated
//!   aircraft was when it was taken. Also `frames_truth.jsonl`: the true pose of each frame
//!   (the format of `closed_loop::FRAMES_TRUTH_FILE`).
//! * [`autopilot_only`] starts the scenario's autopilot emulator (truth plus the scenario's
//!   sensor errors, GPS on inside `[gps] from_s..until_s`, [`SimSensors`]) on a connection of the
//!   caller's choice, in real time, for the scenario's duration or until stopped, and scores the
//!   positions it receives (GPS_INPUT, VISION_POSITION_ESTIMATE, ODOMETRY) against the truth at
//!   their arrival: the closed loop's `nav_err_m`, without the daemon and the control.
//!
//! No scripted faults are played here (`[[faults]]` belong to the closed loop's scoring).

use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use rayon::prelude::*;
use serde::Serialize;
use tracing::info;

use super::recording::InjectionCollector;
use super::{
    ClosedLoopError, SensorsHandle, SimSensors, TruthTable, camera_rig, expected_count, hnorm,
    scenario_config,
};
use crate::Scenario;
use crate::autopilot::{AutopilotEmulator, EmulatorConfig};
use crate::camera_sim::{pose_of, truth_line};
use crate::fixeval::Stats;

/// Frames rendered per batch (each batch in parallel, then written in order).
const RENDER_BATCH: usize = 32;

/// What [`write_frames`] wrote.
#[derive(Debug, Clone, Serialize)]
pub struct FramesWritten {
    /// The folder of the frames.
    pub dir: PathBuf,
    /// Frames written.
    pub frames: usize,
    /// Frame width, px.
    pub width_px: usize,
    /// Frame height, px.
    pub height_px: usize,
    /// Frame rate (`[closed_loop] camera_rate_hz`), Hz.
    pub rate_hz: f64,
    /// Capture time of the first frame, s (the emulator's boot clock).
    pub from_s: f64,
    /// Capture time of the last frame, s (the emulator's boot clock).
    pub until_s: f64,
}

/// Renders the scenario's camera frames into `dir` (module doc). `dir` must not exist or be
/// empty: frames of two flights never mix.
pub fn write_frames(
    sc: &Scenario,
    base: &Path,
    dir: &Path,
) -> Result<FramesWritten, ClosedLoopError> {
    let cl = sc
        .closed_loop
        .as_ref()
        .ok_or(ClosedLoopError::NotClosedLoop)?;
    let io_err = |path: &Path, cause: std::io::Error| ClosedLoopError::Io {
        path: path.to_path_buf(),
        cause,
    };
    let occupied = match std::fs::read_dir(dir) {
        Ok(mut entries) => entries.next().is_some(),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => false,
        Err(e) => return Err(io_err(dir, e)),
    };
    if occupied {
        return Err(ClosedLoopError::Setup(format!(
            "{}: the folder is not empty; give a new or an empty folder (frames of two flights must not mix)",
            dir.display()
        )));
    }
    std::fs::create_dir_all(dir).map_err(|e| io_err(dir, e))?;
    let (cfg, cfg_path) = scenario_config(cl, base)?;
    let rig = camera_rig(cl, base, &cfg, &cfg_path)?;
    let table =
        TruthTable::from_scenario(sc).map_err(|e| ClosedLoopError::Setup(format!("truth: {e}")))?;
    let times_us = capture_times_us(cl.camera_from_s, sc.duration_s(), cl.camera_rate_hz);
    let csv_path = dir.join(visnav_io::frames::FRAMES_CSV);
    let truth_path = dir.join(super::FRAMES_TRUTH_FILE);
    let mut csv = std::io::BufWriter::new(
        std::fs::File::create(&csv_path).map_err(|e| io_err(&csv_path, e))?,
    );
    let mut truth = std::io::BufWriter::new(
        std::fs::File::create(&truth_path).map_err(|e| io_err(&truth_path, e))?,
    );
    writeln!(
        csv,
        "# visnav sim --write-frames: scenario {} (seed {}), camera {} x {} px at {} Hz rendered from {}\n\
         # t_boot_us: the autopilot emulator's boot clock (visnav sim --autopilot-only); use [frames] stamp = \"source\"\n\
         file,t_boot_us",
        sc.name,
        sc.seed,
        cfg.camera.width_px,
        cfg.camera.height_px,
        cl.camera_rate_hz,
        visnav_core::validate::resolve(base, &cl.camera_ortho).display()
    )
    .map_err(|e| io_err(&csv_path, e))?;
    let mut size = (cfg.camera.width_px as usize, cfg.camera.height_px as usize);
    for (batch_no, batch) in times_us.chunks(RENDER_BATCH).enumerate() {
        let first_seq = batch_no * RENDER_BATCH;
        let rendered: Vec<Result<(image::GrayImage, u64), ClosedLoopError>> = batch
            .par_iter()
            .enumerate()
            .map(|(i, &t_us)| {
                let seq = (first_seq + i) as u64;
                let state = table.at(t_us as f64 * 1e-6);
                let pose = pose_of(&rig.crs, &rig.mount, &state)
                    .map_err(|e| ClosedLoopError::Setup(format!("frame {seq}: {e}")))?;
                let f = rig
                    .renderer
                    .render(&rig.scene, &pose, seq)
                    .map_err(|e| ClosedLoopError::Setup(format!("frame {seq}: {e}")))?;
                Ok((f.to_gray_image(), t_us))
            })
            .collect();
        for (i, r) in rendered.into_iter().enumerate() {
            let (img, t_us) = r?;
            let seq = first_seq + i;
            size = (img.width() as usize, img.height() as usize);
            let name = format!("frame_{seq:06}.png");
            let path = dir.join(&name);
            img.save(&path).map_err(|e| {
                ClosedLoopError::Setup(format!("{}: cannot write the PNG: {e}", path.display()))
            })?;
            writeln!(csv, "{name},{t_us}").map_err(|e| io_err(&csv_path, e))?;
            let line = truth_line(seq as u64, t_us, &table.at(t_us as f64 * 1e-6));
            writeln!(truth, "{line}").map_err(|e| io_err(&truth_path, e))?;
        }
    }
    csv.flush().map_err(|e| io_err(&csv_path, e))?;
    truth.flush().map_err(|e| io_err(&truth_path, e))?;
    Ok(FramesWritten {
        dir: dir.to_path_buf(),
        frames: times_us.len(),
        width_px: size.0,
        height_px: size.1,
        rate_hz: cl.camera_rate_hz,
        from_s: times_us.first().map_or(0.0, |t| *t as f64 * 1e-6),
        until_s: times_us.last().map_or(0.0, |t| *t as f64 * 1e-6),
    })
}

/// Capture times from `from_s` to `until_s` at `rate_hz`, whole microseconds (the k-th frame at
/// `from_s + k / rate_hz`, not accumulated: no drift over an hour).
fn capture_times_us(from_s: f64, until_s: f64, rate_hz: f64) -> Vec<u64> {
    if !(rate_hz > 0.0 && from_s.is_finite() && until_s.is_finite()) {
        return Vec::new();
    }
    let n = ((until_s - from_s.max(0.0)) * rate_hz).floor().max(-1.0) as i64 + 1;
    (0..n.max(0))
        .map(|k| ((from_s.max(0.0) + k as f64 / rate_hz) * 1e6).round() as u64)
        .collect()
}

/// What the emulator of [`autopilot_only`] received and how it scores.
#[derive(Debug, Clone, Serialize)]
pub struct AutopilotOnlyReport {
    /// The scenario's name.
    pub scenario: String,
    /// The MAVLink connection the emulator spoke on.
    pub connection: String,
    /// Scenario time flown, s.
    pub flown_s: f64,
    /// Set when stopped before the scenario's end.
    pub interrupted_at_s: Option<f64>,
    /// The companion heard (system id, component id).
    pub companion: Option<(u8, u8)>,
    /// `[gps] from_s..until_s`.
    pub gps_on_s: Option<[f64; 2]>,
    /// `[evaluation] from_s..until_s`, ending where the flight did when interrupted.
    pub evaluation_window_s: [f64; 2],
    /// Position messages received over the whole flight, by kind.
    pub injections: std::collections::BTreeMap<String, usize>,
    /// Horizontal error of the received positions in the evaluation window against the truth
    /// at their arrival, m; NaN without any.
    pub injected_err_m: Stats,
    /// Received positions in the evaluation window.
    pub injections_scored: usize,
    /// The horizontal accuracy those positions claimed (median, 90th percentile, largest), m
    /// (GPS_INPUT's `horiz_accuracy`).
    pub claimed_accuracy_m: Stats,
    /// Positions with a non-finite value (must be 0).
    pub non_finite: usize,
}

/// Console line interval of [`autopilot_only`], s.
const STATUS_EVERY_S: f64 = 5.0;

/// Runs the scenario's autopilot emulator alone on `connection` in real time (module doc), until
/// the scenario's end or `stop`. Call on a multi-thread tokio runtime.
pub async fn autopilot_only(
    sc: &Scenario,
    connection: &str,
    stop: tokio::sync::watch::Receiver<bool>,
) -> Result<AutopilotOnlyReport, ClosedLoopError> {
    let cl = sc
        .closed_loop
        .as_ref()
        .ok_or(ClosedLoopError::NotClosedLoop)?;
    let table = Arc::new(
        TruthTable::from_scenario(sc).map_err(|e| ClosedLoopError::Setup(format!("truth: {e}")))?,
    );
    let sensors = Arc::new(SimSensors::new(sc, table.clone()));
    let mut ecfg = EmulatorConfig::new(connection);
    ecfg.gps_fix = true;
    ecfg.gps_velocity = cl.gps_velocity;
    ecfg.unix_at_boot_us = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_micros() as u64)
        .ok();
    let local_frame = ecfg.local_frame();
    let emu = AutopilotEmulator::start(ecfg, SensorsHandle(sensors.clone()))
        .await
        .map_err(|e| ClosedLoopError::Setup(format!("autopilot emulator on {connection}: {e}")))?;
    let duration_s = sc.duration_s();
    info!(
        "autopilot emulator on {connection}: flying {} for {duration_s:.0} s in real time{}",
        sc.name,
        sc.gps
            .as_ref()
            .map(|g| format!(", GPS on from {:.0} s until {:.0} s", g.from_s, g.until_s))
            .unwrap_or_default()
    );
    let mut collect =
        InjectionCollector::new(false, expected_count::<u64>(duration_s, 50.0), local_frame);
    let mut tick = tokio::time::interval(Duration::from_millis(100));
    let mut last_status_s = f64::NEG_INFINITY;
    let mut interrupted_at_s = None;
    let flown_s = loop {
        tick.tick().await;
        collect.take(emu.take_received(), &table);
        let t_s = emu.time_run_us() as f64 * 1e-6;
        if t_s > duration_s {
            break duration_s;
        }
        if *stop.borrow() {
            interrupted_at_s = Some(t_s);
            break t_s;
        }
        if t_s - last_status_s >= STATUS_EVERY_S {
            last_status_s = t_s;
            info!("{}", status_line(t_s, &sensors, &emu, &collect));
        }
    };
    let companion = emu.companion();
    emu.stop();
    Ok(score(
        sc,
        connection,
        flown_s,
        interrupted_at_s,
        companion,
        &collect,
    ))
}

/// One console line of the emulator's state.
fn status_line(
    t_s: f64,
    sensors: &SimSensors,
    emu: &AutopilotEmulator,
    collect: &InjectionCollector,
) -> String {
    let companion = match emu.companion() {
        Some((s, c)) => format!("companion sys {s} comp {c}"),
        None => "no companion heard yet".to_string(),
    };
    let last = collect.samples.last().map_or_else(String::new, |r| {
        format!(
            ", last position {:.1} m from the truth",
            hnorm(&r.err_ned_m.map(f64::from))
        )
    });
    format!(
        "t = {t_s:5.1} s  gps {}  {companion}  positions received {}{last}",
        if sensors.gps_on(t_s) { "on " } else { "off" },
        collect.samples.len()
    )
}

/// The report of what was received.
fn score(
    sc: &Scenario,
    connection: &str,
    flown_s: f64,
    interrupted_at_s: Option<f64>,
    companion: Option<(u8, u8)>,
    collect: &InjectionCollector,
) -> AutopilotOnlyReport {
    let rows: Vec<_> = collect.samples.iter().map(|s| s.expand()).collect();
    let mut injections = std::collections::BTreeMap::new();
    for r in &rows {
        *injections.entry(r.kind.to_string()).or_insert(0) += 1;
    }
    // Stopped early: the window ends where the flight did.
    let window = [sc.evaluation.from_s, sc.evaluation.until_s.min(flown_s)];
    let scored: Vec<_> = rows
        .iter()
        .filter(|r| r.t_s >= window[0] && r.t_s <= window[1])
        .collect();
    let err: Vec<f64> = scored.iter().map(|r| hnorm(&r.err_ned_m)).collect();
    let acc: Vec<f64> = scored
        .iter()
        .map(|r| r.horiz_accuracy_m)
        .filter(|a| a.is_finite())
        .collect();
    AutopilotOnlyReport {
        scenario: sc.name.clone(),
        connection: connection.to_string(),
        flown_s,
        interrupted_at_s,
        companion,
        gps_on_s: sc.gps.as_ref().map(|g| [g.from_s, g.until_s]),
        evaluation_window_s: window,
        injections,
        injected_err_m: Stats::of(&err),
        injections_scored: scored.len(),
        claimed_accuracy_m: Stats::of(&acc),
        non_finite: collect.non_finite,
    }
}

#[cfg(test)]
mod tests {
    use super::capture_times_us;

    #[test]
    fn capture_times_are_on_the_rate_grid_without_drift() {
        let t = capture_times_us(0.0, 10.0, 2.0);
        assert_eq!(t.len(), 21);
        assert_eq!(t[0], 0);
        assert_eq!(t[20], 10_000_000);
        // 1 s + k / 3 Hz up to the hour: the last at 3600 s exactly, k = 10797, no drift.
        let t = capture_times_us(1.0, 3600.0, 3.0);
        assert_eq!(t.len(), 10_798);
        assert_eq!(t[1], 1_333_333);
        assert_eq!(*t.last().unwrap(), 3_600_000_000);
        assert!(capture_times_us(5.0, 4.0, 2.0).is_empty());
        assert!(capture_times_us(0.0, 10.0, 0.0).is_empty());
    }
}
