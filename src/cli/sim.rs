//! `visnav sim [--scenario FILE] [--seed N] [--out DIR] [--json] [--monte-carlo N]`.
//!
//! A scenario with a `[closed_loop]` section (the default, `sitl/scenarios/closed_loop_demo.toml`)
//! runs the closed loop (`visnav::sitl::closed_loop`): autopilot emulator + visnav daemon over
//! loopback MAVLink, the camera rendered at the true pose, a no-vision control beside it; it
//! prints the summary and writes the report folder. Other scenarios run offline through the
//! navigation filter, with simulated vision fixes and as the INS-only control.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;
use visnav::sitl::Scenario;
use visnav::sitl::run::{RunOptions, TruthPlusNoise, VisionFixSource, monte_carlo, run};

#[derive(clap::Args, Debug)]
pub struct SimArgs {
    /// Scenario file (sitl/scenarios/*.toml). Default: the bundled closed-loop demo,
    /// sitl/scenarios/closed_loop_demo.toml (looked up in the current folder, then in the source
    /// tree).
    #[arg(long)]
    pub scenario: Option<PathBuf>,
    /// Report folder of a closed-loop run (CSV, PNG plots, GeoJSON, summary.json). Default:
    /// sim-report/<scenario name> in the current folder.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Print one JSON document on stdout.
    #[arg(long)]
    pub json: bool,
    /// Also run an N-run Monte Carlo (vision runs and their INS-only controls) and report the
    /// NEES consistency.
    #[arg(long, default_value_t = 0)]
    pub monte_carlo: usize,
    /// Run a closed loop in real time (the fix's own computing time as its latency) instead of
    /// lock-step (the default: the emulators, the daemons and the camera on one simulated clock,
    /// as fast as the CPU allows and the same for the same seed).
    #[arg(long)]
    pub realtime: bool,
    /// Visual odometry in the closed loop's vision run, `on` or `off`, whatever the scenario's
    /// `[closed_loop.vo] enabled` says (the same flight with and without it, for comparison).
    #[arg(long, value_parser = ["on", "off"])]
    pub vo: Option<String>,
    /// The scenario's `seed` replaced by this one: the same flight with other draws of the
    /// sensors' noise and faults (a seed sweep); the camera's rendering keeps its own seed.
    #[arg(long)]
    pub seed: Option<u64>,
    /// Render the closed-loop scenario's camera frames at the true pose into DIR (PNG files,
    /// frames.csv with t_boot_us on the autopilot emulator's boot clock, frames_truth.jsonl) and
    /// exit: the camera of `--autopilot-only` for a `visnav run` of your own (docs/first-flight.md,
    /// "A first run against the simulated autopilot").
    #[arg(long, value_name = "DIR", conflicts_with_all = ["autopilot_only", "json", "out", "monte_carlo", "realtime", "vo"])]
    pub write_frames: Option<PathBuf>,
    /// Run only the closed-loop scenario's autopilot emulator, in real time, on CONNECTION (e.g.
    /// udpout:127.0.0.1:14550, where config/sim-autopilot.toml listens): a simulated autopilot for
    /// a `visnav run` of your own. At the scenario's end (or Ctrl-C) it scores the positions it
    /// received against the truth.
    #[arg(long, value_name = "CONNECTION", conflicts_with_all = ["out", "monte_carlo", "realtime", "vo"])]
    pub autopilot_only: Option<String>,
}

pub fn run_cmd(args: SimArgs) -> anyhow::Result<ExitCode> {
    let path = args.scenario.clone().unwrap_or_else(default_scenario);
    let mut sc = Scenario::load(&path)?;
    if let Some(seed) = args.seed {
        sc.seed = seed;
    }
    if let Some(cl) = sc.closed_loop.as_mut() {
        cl.lockstep &= !args.realtime;
        if let Some(v) = &args.vo {
            let mut vo = cl.vo.clone().unwrap_or_default();
            vo.enabled = v == "on";
            cl.vo = Some(vo);
        }
    }
    if sc.closed_loop.is_none() && (args.write_frames.is_some() || args.autopilot_only.is_some()) {
        anyhow::bail!(
            "--write-frames and --autopilot-only need a closed-loop scenario ([closed_loop] section); {} has none",
            path.display()
        );
    }
    if let Some(dir) = &args.write_frames {
        return crate::cli::sim_standalone::write_frames(&sc, &path, dir);
    }
    if let Some(connection) = &args.autopilot_only {
        return crate::cli::sim_standalone::autopilot_only(&sc, &path, connection, args.json);
    }
    if sc.closed_loop.is_some() {
        return closed_loop(&sc, &path, &args);
    }
    let t0 = Instant::now();
    let vis = run(&sc, RunOptions::new(true, 0))?;
    let ins = run(&sc, RunOptions::new(false, 0))?;
    let single_s = t0.elapsed().as_secs_f64();
    let t1 = Instant::now();
    let mc = if args.monte_carlo > 0 {
        Some(monte_carlo(&sc, args.monte_carlo)?)
    } else {
        None
    };
    let mc_s = t1.elapsed().as_secs_f64();
    let vision_source = sc.vision.as_ref().map(|v| {
        format!(
            "{}; {} Hz, delivered {}-{} ms after capture and applied at capture time; true camera lever arm {} m body FRD, filter's {} m",
            TruthPlusNoise::from_config(v).describe(),
            v.rate_hz,
            v.latency_min_ms,
            v.latency_max_ms,
            visnav_core::text::numbers(&v.lever_arm_body_frd_m),
            visnav_core::text::numbers(sc.nav.camera_lever_arm().as_slice())
        )
    });
    let target = sc.evaluation.target_max_horiz_err_m;
    let doc = serde_json::json!({
        "scenario": sc.name,
        "description": sc.description,
        "vision_source": vision_source,
        "imu": sc.imu,
        "filter_states": sc.nav.n_states(),
        "evaluation_window_s": [sc.evaluation.from_s, sc.evaluation.until_s],
        "max_err_m": { "vision": vis.max_err_m, "ins_only": ins.max_err_m },
        "max_horiz_err_m": { "vision": vis.max_horiz_err_m, "ins_only": ins.max_horiz_err_m },
        "target_max_horiz_err_m": target,
        "target_met": target.map(|t| vis.max_horiz_err_m <= t),
        "reference": sc.reference,
        "vision_run": vis,
        "ins_only_run": ins,
        "monte_carlo": &mc,
        "runtime_s": { "two_runs": single_s, "monte_carlo": mc_s },
    });
    if args.json {
        println!("{}", serde_json::to_string_pretty(&doc)?);
    } else {
        println!("scenario {}", sc.name);
        println!(
            "max error e/n/u [m]  vision: {:.2} / {:.2} / {:.2}   INS-only: {:.2} / {:.2} / {:.2}",
            vis.max_err_m.e,
            vis.max_err_m.n,
            vis.max_err_m.u,
            ins.max_err_m.e,
            ins.max_err_m.n,
            ins.max_err_m.u
        );
        println!(
            "max horizontal error [m]  vision: {:.2}  INS-only: {:.2}",
            vis.max_horiz_err_m, ins.max_horiz_err_m
        );
        if let Some(mc) = &mc {
            println!(
                "monte carlo, {} runs: max horizontal error with vision mean {:.2} m, median {:.2} m, worst {:.2} m, {} runs over target; INS-only mean {:.2} m",
                mc.runs,
                mc.mean_max_horiz_err_m,
                mc.median_max_horiz_err_m,
                mc.worst_max_horiz_err_m,
                mc.runs_over_target,
                mc.ins_only_mean_max_horiz_err_m
            );
            println!("NEES (run average; two-sided 95 % band; fraction of epochs inside):");
            for (name, s) in &mc.nees {
                if let Some(s) = s {
                    println!(
                        "  {name:<12} dof {:>2}  mean {:>7.3}  band [{:.3}, {:.3}]  {}  inside {:.0} %",
                        s.dof,
                        s.mean,
                        s.band_95[0],
                        s.band_95[1],
                        if s.mean_inside { "in " } else { "OUT" },
                        100.0 * s.fraction_inside
                    );
                }
            }
            let nse: Vec<String> = mc
                .state_nse_mean
                .iter()
                .map(|(n, v)| format!("{n} {v:.2}"))
                .collect();
            println!(
                "mean normalised squared error per state: {}",
                nse.join(", ")
            );
        }
        println!("runtime: two runs {single_s:.2} s, monte carlo {mc_s:.2} s");
    }
    Ok(ExitCode::SUCCESS)
}

/// The bundled default scenario: relative to the current folder (a checkout), else to the source
/// tree this binary was built from.
pub(crate) fn default_scenario() -> PathBuf {
    let rel = PathBuf::from("sitl/scenarios/closed_loop_demo.toml");
    if rel.is_file() {
        rel
    } else {
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(rel)
    }
}

fn fmt_stats(s: &visnav::sitl::fixeval::Stats) -> String {
    format!("{:.1} / {:.1} / {:.1}", s.median, s.p90, s.max)
}

/// A figure with one decimal, `-` when there is none.
fn fmt_opt(v: Option<f64>) -> String {
    v.filter(|x| x.is_finite())
        .map_or_else(|| "-".to_string(), |x| format!("{x:.1}"))
}

/// The closed loop: run, write the report folder, print the summary.
fn closed_loop(sc: &Scenario, path: &std::path::Path, args: &SimArgs) -> anyhow::Result<ExitCode> {
    use anyhow::Context;
    if args.monte_carlo > 0 {
        anyhow::bail!(
            "--monte-carlo runs offline scenarios only; {} is a closed-loop scenario",
            path.display()
        );
    }
    let base = path.parent().unwrap_or(std::path::Path::new("."));
    let out = match args.out.clone() {
        Some(o) => o,
        None => fresh_report_dir(&PathBuf::from("sim-report").join(&sc.name))
            .with_context(|| format!("report folder sim-report/{}", sc.name))?,
    };
    let lockstep = sc.closed_loop.as_ref().is_some_and(|c| c.lockstep);
    // Lock-step: one thread, the clock paused and advanced by the runtime whenever every task
    // waits (tokio's test-util clock), so simulated time costs only the CPU it needs.
    let rt = if lockstep {
        tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .start_paused(true)
            .build()
    } else {
        tokio::runtime::Builder::new_multi_thread()
            .enable_all()
            .build()
    }
    .context("cannot start the async runtime")?;
    let t0 = Instant::now();
    std::fs::create_dir_all(&out)
        .with_context(|| format!("report folder {}: cannot create it", out.display()))?;
    // Ctrl-C ends the flight early and still writes the report of what was flown; a second
    // Ctrl-C exits at once.
    let (stop_tx, stop) = tokio::sync::watch::channel(false);
    let mut run = rt
        .block_on(async {
            tokio::spawn(async move {
                if tokio::signal::ctrl_c().await.is_ok() {
                    tracing::warn!(
                        "interrupted: writing the report of the flight so far (Ctrl-C again to quit at once)"
                    );
                    let _ = stop_tx.send(true);
                    if tokio::signal::ctrl_c().await.is_ok() {
                        std::process::exit(INTERRUPTED_EXIT_CODE.into());
                    }
                }
            });
            visnav::sitl::closed_loop::run_until_stopped(sc, base, Some(&out), stop).await
        })
        .with_context(|| format!("{}: closed loop", path.display()))?;
    run.summary.report_dir = Some(out.display().to_string());
    let files = visnav::sitl::report::write_report(&run, &out)
        .with_context(|| format!("report folder {}", out.display()))?;
    let s = &run.summary;
    if args.json {
        println!("{}", serde_json::to_string_pretty(s)?);
    } else {
        println!(
            "scenario {} ({:.0} s, wall {:.0} s)",
            s.scenario,
            s.duration_s,
            t0.elapsed().as_secs_f64()
        );
        println!("{}", s.description);
        if let Some(t) = s.interrupted_at_s {
            println!("interrupted at {t:.0} s: the figures cover the flight up to there");
        }
        println!(
            "evaluation window {:.0}-{:.0} s{}; {:.0} m above the terrain ({:.0}-{:.0} m)",
            s.evaluation_window_s[0],
            s.evaluation_window_s[1],
            s.gps_outage_s
                .map(|o| format!(", GPS outage from {:.0} s", o[0]))
                .unwrap_or_default(),
            s.agl_m,
            s.agl_range_m[0],
            s.agl_range_m[1]
        );
        let counts = visnav::sitl::report::FixCounts::of(&run);
        println!(
            "vision fixes {}: {} accepted of {} attempts (fix rate {:.0} %; {} accepted in the whole flight), {} frames rendered, {} dropped, {} beyond 3 sigma, {} rejected by the filter gate",
            counts.scope,
            counts.accepted,
            counts.attempts,
            100.0 * s.fix_rate,
            counts.flight_accepted,
            s.frames_rendered,
            s.frames_dropped,
            s.fix_beyond_3sigma,
            s.fixes_filter_rejected
        );
        print_rejections(&s.rejections);
        println!("horizontal error median / p90 / max [m]");
        println!("  vision fixes             {}", fmt_stats(&s.fix_err_m));
        println!(
            "  injected (GPS_INPUT)     {}   ({} messages)",
            fmt_stats(&s.nav_err_m),
            s.injections
        );
        println!(
            "  visnav filter output     {}",
            fmt_stats(&s.nav_output_err_m)
        );
        println!("  no-vision control        {}", fmt_stats(&s.control_err_m));
        println!(
            "horizontal sigma claimed [m]  visnav {}   no-vision {}",
            fmt_stats(&s.nav_sigma_h_m),
            fmt_stats(&s.control_sigma_h_m)
        );
        println!(
            "horizontal error / the filter's own sigma median / p90 / max (honest: ~1.2 / 2.1 / <3.5)"
        );
        println!(
            "  visnav filter output     {:.2} / {:.2} / {:.2}",
            s.nav_err_over_sigma.median, s.nav_err_over_sigma.p90, s.nav_err_over_sigma.max
        );
        println!(
            "  no-vision control        {:.2} / {:.2} / {:.2}",
            s.control_err_over_sigma.median,
            s.control_err_over_sigma.p90,
            s.control_err_over_sigma.max
        );
        println!(
            "max error e/n/u [m]  visnav {:.1} / {:.1} / {:.1}   no-vision {:.1} / {:.1} / {:.1}",
            s.max_err_m.vision.e,
            s.max_err_m.vision.n,
            s.max_err_m.vision.u,
            s.max_err_m.control.e,
            s.max_err_m.control.n,
            s.max_err_m.control.u
        );
        println!(
            "max 3-D error [m]  visnav {:.1}   no-vision {:.1};  max Euler angle error [deg]  visnav {:.2}   no-vision {:.2}",
            s.max_err_m.vision_3d,
            s.max_err_m.control_3d,
            s.max_euler_err_deg.vision,
            s.max_euler_err_deg.control
        );
        if let (Some(d), Some(p)) = (&s.dtm, &s.dtm_poses) {
            println!(
                "DTM navigation: {} poses of {} frames ({} fused, {} refused); in the window {} poses, horizontal error median / p90 / max {:.1} / {:.1} / {:.1} m, {} outside their 3 sigma",
                d.motions,
                d.frames,
                d.fused,
                d.refused.iter().map(|r| r.count).sum::<u64>(),
                p.poses,
                p.err_h_m.median,
                p.err_h_m.p90,
                p.err_h_m.max,
                p.beyond_3sigma
            );
        }
        println!(
            "end of flight: horizontal error [m] visnav {}, no-vision {}; {:.0} m flown since the GPS loss; max heading error since then [deg] visnav {}, no-vision {}",
            fmt_opt(s.final_err_h_m),
            fmt_opt(s.control_final_err_h_m),
            s.distance_flown_m,
            fmt_opt(s.yaw_err_deg_max),
            fmt_opt(s.ctl_yaw_err_deg_max)
        );
        let lockstep_latency_s = sc
            .closed_loop
            .as_ref()
            .filter(|c| c.lockstep)
            .map(|c| c.lockstep_fix_latency_s.max(0.0));
        println!(
            "{}",
            visnav::sitl::report::latency_text(lockstep_latency_s, &s.latency_ms, &counts.scope)
        );
        println!("report: {}", out.display());
        for f in files {
            println!("  {}", f.display());
        }
    }
    if s.interrupted_at_s.is_some() {
        return Ok(ExitCode::from(INTERRUPTED_EXIT_CODE));
    }
    Ok(ExitCode::SUCCESS)
}

/// Exit status of a run stopped by Ctrl-C (128 + SIGINT, as a shell reports it).
const INTERRUPTED_EXIT_CODE: u8 = 130;

/// How many reasons the console lists before summing the rest as "other".
const REJECTION_REASONS_LISTED: usize = 5;

/// The window's rejected attempts by kind (most frequent first), one line each: the count and
/// the latest reason of its kind, numbers included.
fn print_rejections(rejections: &[visnav_core::reasons::ReasonCount]) {
    if rejections.is_empty() {
        return;
    }
    let total: u64 = rejections.iter().map(|r| r.count).sum();
    println!("rejected attempts by reason ({total}; each line the latest of its kind):");
    for r in rejections.iter().take(REJECTION_REASONS_LISTED) {
        println!("  {:>5}  {}", r.count, r.reason);
    }
    let rest: u64 = rejections
        .iter()
        .skip(REJECTION_REASONS_LISTED)
        .map(|r| r.count)
        .sum();
    if rest > 0 {
        println!("  {rest:>5}  other reasons (summary.json lists them all)");
    }
}

/// A report folder no other run uses: `base` when it does not exist yet, else `base-2`, `base-3`,
/// ... (each claimed by creating it, so two runs started together get two folders).
pub(crate) fn fresh_report_dir(base: &std::path::Path) -> std::io::Result<PathBuf> {
    if let Some(parent) = base.parent() {
        std::fs::create_dir_all(parent)?;
    }
    let name = base
        .file_name()
        .map(|n| n.to_string_lossy().to_string())
        .unwrap_or_else(|| "run".into());
    for n in 1..10_000u32 {
        let candidate = if n == 1 {
            base.to_path_buf()
        } else {
            base.with_file_name(format!("{name}-{n}"))
        };
        match std::fs::create_dir(&candidate) {
            Ok(()) => return Ok(candidate),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
            Err(e) => return Err(e),
        }
    }
    Err(std::io::Error::other(format!(
        "{}: 10000 report folders exist already",
        base.display()
    )))
}

#[cfg(test)]
mod report_dir_tests {
    use super::fresh_report_dir;

    #[test]
    fn each_run_gets_its_own_report_folder() {
        let tmp = tempfile::tempdir().unwrap();
        let base = tmp.path().join("sim-report").join("demo");
        let a = fresh_report_dir(&base).unwrap();
        let b = fresh_report_dir(&base).unwrap();
        let c = fresh_report_dir(&base).unwrap();
        assert_eq!(a, base);
        assert_eq!(b, tmp.path().join("sim-report").join("demo-2"));
        assert_eq!(c, tmp.path().join("sim-report").join("demo-3"));
        assert!(a.is_dir() && b.is_dir() && c.is_dir());
    }
}
