//! `visnav replay --config F --tlog LOG [--out DIR] [--json]`: run a recorded .tlog through the
//! daemon's telemetry conversion and navigation filter offline (see `visnav::daemon::replay`) and
//! print the per-measurement-type NIS statistics and the filter's resets; `--fixes` adds the
//! vision fixes of the flight's fix log (`[daemon] fix_log`); `--out` writes
//! `measurements.csv` (every aiding measurement with outcome, NIS and innovation) and
//! `states.csv` (the filter state at 10 Hz).

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use visnav::daemon::config::Config;
use visnav::daemon::replay::{ReplayOptions, meas_csv, replay_tlog, states_csv};
use visnav::link::tlog::TlogContents;
use visnav_io::files::{self, read_bytes, read_text};

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
    /// The visual odometry log of the same flight (`[daemon] vo_log`): its motions are given to
    /// the filter when they arrived.
    #[arg(long)]
    pub vo_log: Option<PathBuf>,
    /// The terrain model's height sigma the motions were measured with, m (the VO log does not
    /// carry it). Default: the configuration's `[map] height_sigma_m`.
    #[arg(long)]
    pub vo_terrain_sigma_m: Option<f64>,
    /// Folder for measurements.csv and states.csv.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Print the summary as JSON.
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: ReplayArgs) -> anyhow::Result<ExitCode> {
    let cfg = Config::load(&args.config)?;
    let bytes = read_bytes(&args.tlog, files::TLOG)
        .with_context(|| format!("reading {}", args.tlog.display()))?;
    let log = visnav::link::tlog::scan_tlog(&bytes);
    drop(bytes);
    if log.records.is_empty() {
        anyhow::bail!(
            "{}: no MAVLink packet in the file (not a .tlog?)",
            args.tlog.display()
        );
    }
    if log.skipped_bytes > 0 {
        eprintln!("warning: {}", skipped_words(&args.tlog, &log));
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
            let text = read_text(f, files::JSON_LOG)
                .with_context(|| format!("reading {}", f.display()))?;
            visnav::daemon::fixlog::read_fix_log(&text)
                .map_err(|e| anyhow::anyhow!("{}: {e}", f.display()))?
        }
        None => Vec::new(),
    };
    let vo = match &args.vo_log {
        Some(f) => read_vo_motions(f, &args, &cfg)?,
        None => Vec::new(),
    };
    let rep = replay_tlog(&log, &fixes, &vo, &opts);
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
    if log.skipped_bytes > 0 {
        println!("{}", skipped_words(&args.tlog, &log));
    }
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
    if args.vo_log.is_some() {
        println!("visual odometry motions replayed: {}", rep.vo_motions);
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

/// The motions of a VO log as `(arrival Unix µs, motion)`, in arrival order.
fn read_vo_motions(
    path: &std::path::Path,
    args: &ReplayArgs,
    cfg: &Config,
) -> anyhow::Result<Vec<(u64, visnav::nav::VoFix)>> {
    let terrain_sigma_m = match args.vo_terrain_sigma_m.or(cfg.map.height_sigma_m) {
        Some(s) if s.is_finite() && s >= 0.0 => s,
        Some(s) => anyhow::bail!(
            "--vo-terrain-sigma-m {} must be a finite number >= 0",
            visnav_core::text::num(s)
        ),
        None => anyhow::bail!(
            "--vo-log needs the terrain model's height sigma: the configuration has no [map] \
             height_sigma_m, so give --vo-terrain-sigma-m"
        ),
    };
    let text =
        read_text(path, files::JSON_LOG).with_context(|| format!("reading {}", path.display()))?;
    let records = visnav::daemon::volog::read_vo_log(&text)
        .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
    let corr_m = cfg.vo.terrain_error_corr_dist_m;
    let mut out: Vec<(u64, visnav::nav::VoFix)> = records
        .iter()
        .filter_map(|r| Some((r.arrival_unix_us, r.vo_fix(terrain_sigma_m, corr_m)?)))
        .collect();
    out.sort_by_key(|(t, _)| *t);
    Ok(out)
}

/// What the reading of a damaged log skipped, in one line.
fn skipped_words(path: &std::path::Path, log: &TlogContents) -> String {
    format!(
        "{}: skipped {} bytes in {} place(s) that held no valid record (damage or junk); \
         replayed the {} records around them",
        path.display(),
        log.skipped_bytes,
        log.skipped_runs,
        log.records.len()
    )
}
