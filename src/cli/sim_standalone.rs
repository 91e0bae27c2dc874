//! `visnav sim --write-frames DIR` and `visnav sim --autopilot-only CONNECTION`: a closed-loop
//! scenario's camera as a frames folder and its autopilot emulator as a simulated autopilot, for
//! a `visnav run` of your own (`visnav::sitl::closed_loop::{write_frames, autopilot_only}`;
//! docs/first-flight.md, "A first run against the simulated autopilot").

use std::path::Path;
use std::process::ExitCode;
use std::time::Instant;

use anyhow::Context;
use visnav::sitl::Scenario;
use visnav::sitl::closed_loop::AutopilotOnlyReport;

/// Exit status of a run stopped by Ctrl-C (128 + SIGINT).
const INTERRUPTED_EXIT_CODE: u8 = 130;

/// Renders the frames and says what was written.
pub fn write_frames(sc: &Scenario, path: &Path, dir: &Path) -> anyhow::Result<ExitCode> {
    let base = path.parent().unwrap_or(Path::new("."));
    let t0 = Instant::now();
    let w = visnav::sitl::closed_loop::write_frames(sc, base, dir)
        .with_context(|| format!("{}: writing the camera frames", path.display()))?;
    println!(
        "wrote {} frames ({} x {} px, {} Hz, taken at {:.1}-{:.1} s of the flight) to {} in {:.0} s",
        w.frames,
        w.width_px,
        w.height_px,
        w.rate_hz,
        w.from_s,
        w.until_s,
        w.dir.display(),
        t0.elapsed().as_secs_f64()
    );
    println!(
        "  frames.csv stamps them on the autopilot emulator's boot clock (t_boot_us): read them with [frames] source = \"directory\", stamp = \"source\" against `visnav sim --autopilot-only` of the same scenario and seed"
    );
    Ok(ExitCode::SUCCESS)
}

/// Runs the emulator until the scenario's end or Ctrl-C, then prints the score.
pub fn autopilot_only(
    sc: &Scenario,
    path: &Path,
    connection: &str,
    json: bool,
) -> anyhow::Result<ExitCode> {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    let (stop_tx, stop) = tokio::sync::watch::channel(false);
    let report = rt
        .block_on(async {
            tokio::spawn(async move {
                if tokio::signal::ctrl_c().await.is_ok() {
                    tracing::warn!("interrupted: scoring what was received so far (Ctrl-C again to quit at once)");
                    let _ = stop_tx.send(true);
                    if tokio::signal::ctrl_c().await.is_ok() {
                        std::process::exit(INTERRUPTED_EXIT_CODE.into());
                    }
                }
            });
            visnav::sitl::closed_loop::autopilot_only(sc, connection, stop).await
        })
        .with_context(|| format!("{}: autopilot emulator", path.display()))?;
    if json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print_report(&report);
    }
    if report.interrupted_at_s.is_some() {
        return Ok(ExitCode::from(INTERRUPTED_EXIT_CODE));
    }
    Ok(ExitCode::SUCCESS)
}

fn print_report(r: &AutopilotOnlyReport) {
    println!(
        "autopilot emulator, scenario {} on {}: {:.0} s flown{}",
        r.scenario,
        r.connection,
        r.flown_s,
        r.interrupted_at_s
            .map(|t| format!(" (interrupted at {t:.0} s)"))
            .unwrap_or_default()
    );
    match r.companion {
        Some((s, c)) => println!("companion heard: system {s}, component {c}"),
        None => println!(
            "no companion heard: nothing reached {} (is visnav run listening on the other end?)",
            r.connection
        ),
    }
    let kinds: Vec<String> = r
        .injections
        .iter()
        .map(|(k, n)| format!("{n} {k}"))
        .collect();
    println!(
        "positions received: {}",
        if kinds.is_empty() {
            "none".to_string()
        } else {
            kinds.join(", ")
        }
    );
    if let Some([a, b]) = r.gps_on_s {
        println!("GPS on from {a:.0} s until {b:.0} s");
    }
    if r.injections_scored == 0 {
        println!(
            "no position received in the evaluation window {:.0}-{:.0} s: nothing to score",
            r.evaluation_window_s[0], r.evaluation_window_s[1]
        );
    } else {
        println!(
            "horizontal error of the {} positions received in {:.0}-{:.0} s against the truth, median / p90 / max: {:.1} / {:.1} / {:.1} m (claimed accuracy median {:.1} m)",
            r.injections_scored,
            r.evaluation_window_s[0],
            r.evaluation_window_s[1],
            r.injected_err_m.median,
            r.injected_err_m.p90,
            r.injected_err_m.max,
            r.claimed_accuracy_m.median
        );
    }
    if r.non_finite > 0 {
        println!("{} positions had a non-finite value", r.non_finite);
    }
}
