//! `visnav run --config F [--duration S]`: the navigation service. Talks to the autopilot, runs
//! the navigation pipeline and injects the solution until SIGINT/SIGTERM (or `--duration`).

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use anyhow::Context;
use visnav::daemon::app_config::Config;

#[derive(clap::Args, Debug)]
pub struct RunArgs {
    /// The TOML configuration file.
    #[arg(long)]
    pub config: PathBuf,
    /// Stop after this many seconds (default: run until SIGINT/SIGTERM).
    #[arg(long)]
    pub duration: Option<f64>,
}

pub fn run(args: RunArgs) -> anyhow::Result<ExitCode> {
    // The validation `visnav check-config` does: what it passes, run starts.
    let cfg = Config::load_checked(&args.config)?;
    let duration = match args.duration {
        Some(s) if s.is_finite() && s > 0.0 && s < 1e9 => Some(Duration::from_secs_f64(s)),
        Some(s) => anyhow::bail!("--duration {s}: expected a positive number of seconds"),
        None => None,
    };
    // With a frame source, the vision fix engine of [map], [camera] and [fix].
    let fixer: Option<std::sync::Arc<dyn visnav::daemon::FrameFixer>> = if cfg.frames.is_some() {
        let engine = visnav::daemon::engine_from_config(&cfg)
            .with_context(|| format!("{}: vision fix engine", args.config.display()))?;
        Some(std::sync::Arc::new(engine))
    } else {
        tracing::warn!("{}", super::check_config::NO_CAMERA_WARNING);
        None
    };
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    let m = rt.block_on(visnav::daemon::run(&cfg, fixer, duration))?;
    println!("{}", serde_json::to_string(&m)?);
    Ok(ExitCode::SUCCESS)
}
