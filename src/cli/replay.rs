//! `visnav replay --config F --tlog LOG [--out DIR] [--json]`: run a recorded .tlog through the
//! daemon's telemetry conversion and navigation filter offline (see `visnav::daemon::replay`) and
//! print the per-measurement-type NIS statistics and the filter's resets; `--fixes` adds the
//! vision fixes of the flight's fix log (`[daemon] fix_log`); `--out` writes
//! `measurements.csv` (every aiding measurement with outcome, NIS and innovation) and
//! `states.csv` (the filter state at 10 Hz).

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use visnav::daemon::app_config::Config;
use visnav::daemon::replay::{ReplayOptions, meas_csv, replay, states_csv};

#[derive(clap::Args, Debug)]
pub struct ReplayArgs {
    /// The visnav configuration the log was recorded with (its [daemon], [nav], [output] and
    /// [link] autopilot_system_id are used).
    #[arg(long)]
    pub config: PathBuf,
    /// The .tlog file (the daemon writes one with `[link] tlog = "F"`).
    #[arg(long)]
    pub tlog: PathBuf,
    /// The vision fix log of the same flight (`[daemon] fix_log`): its fixes are given to the
    /// filter when they arrived.
    #[arg(long)]
    pub fixes: Option<PathBuf>,
    /// Folder for measurements.csv and states.csv.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Print the summary as JSON.
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: ReplayArgs) -> anyhow::Result<ExitCode> {
    let cfg = Config::load(&args.config)?;
    let bytes =
        std::fs::read(&args.tlog).with_context(|| format!("reading {}", args.tlog.display()))?;
    let records = visnav::link::tlog::read_tlog(&bytes);
    if records.is_empty() {
        anyhow::bail!(
            "{}: no MAVLink packet in the file (not a .tlog?)",
            args.tlog.display()
        );
    }
    let opts = ReplayOptions {
        gps: cfg.daemon.gps_source(&cfg.output),
        daemon: cfg.daemon.clone(),
        nav: cfg.nav.clone(),
        autopilot_system_id: cfg.link.autopilot_system_id,
        autopilot_component_id: cfg.link.autopilot_component_id,
        state_interval_s: 0.1,
    };
    let fixes = match &args.fixes {
        Some(f) => {
            let text =
                std::fs::read_to_string(f).with_context(|| format!("reading {}", f.display()))?;
            visnav::daemon::fixlog::read_fix_log(&text)
                .map_err(|e| anyhow::anyhow!("{}: {e}", f.display()))?
        }
        None => Vec::new(),
    };
    let rep = replay(&records, &fixes, &opts);
    if rep.from_autopilot == 0 {
        anyhow::bail!(
            "{}: no packet from an autopilot (no autopilot HEARTBEAT{})",
            args.tlog.display(),
            cfg.link
                .autopilot_system_id
                .map(|s| format!(" from system {s}"))
                .unwrap_or_default()
        );
    }
    if let Some(dir) = &args.out {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        for (name, text) in [
            ("measurements.csv", meas_csv(&rep)),
            ("states.csv", states_csv(&rep)),
        ] {
            let f = dir.join(name);
            std::fs::write(&f, text).with_context(|| format!("writing {}", f.display()))?;
        }
    }
    if args.json {
        println!("{}", serde_json::to_string_pretty(&rep)?);
        return Ok(ExitCode::SUCCESS);
    }
    println!(
        "{}: {} packets ({} undecodable, {} from the autopilot{}), {} IMU samples, t {:.1}..{:.1} s",
        args.tlog.display(),
        rep.packets,
        rep.undecodable,
        rep.from_autopilot,
        rep.autopilot_system_id
            .map(|s| format!(", system {s}"))
            .unwrap_or_default(),
        rep.imu_samples,
        rep.t_span_s[0],
        rep.t_span_s[1]
    );
    println!(
        "{:<14} {:>7} {:>8} {:>8} {:>4} {:>9} {:>9} {:>9}",
        "measurement", "n", "accepted", "rejected", "dof", "NIS mean", "NIS p50", "NIS p95"
    );
    for (k, s) in &rep.kinds {
        println!(
            "{:<14} {:>7} {:>8} {:>8} {:>4} {:>9.2} {:>9.2} {:>9.2}",
            k, s.n, s.accepted, s.rejected, s.dof, s.nis_mean, s.nis_p50, s.nis_p95
        );
    }
    if args.fixes.is_some() {
        println!("vision fix results replayed: {}", rep.vision_results);
    }
    println!("resets: {}", rep.resets.len());
    for (t, r) in rep.resets.iter().take(20) {
        println!("  t {t:.2} s: {r}");
    }
    if rep.resets.len() > 20 {
        println!("  ... {} more", rep.resets.len() - 20);
    }
    Ok(ExitCode::SUCCESS)
}
