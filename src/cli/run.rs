//! `visnav run --config F [--duration S]`: the navigation service. Talks to the autopilot, runs
//! the navigation pipeline and injects the solution until SIGINT/SIGTERM (or `--duration`).

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use anyhow::Context;

use super::overrides::OverrideArgs;

#[derive(clap::Args, Debug)]
pub struct RunArgs {
    /// The TOML configuration file (default: the environment's VISNAV_CONFIG), relative to the
    /// current directory.
    #[arg(long)]
    pub config: Option<PathBuf>,
    #[command(flatten)]
    pub overrides: OverrideArgs,
    /// Stop after this many seconds (default: run until SIGINT/SIGTERM).
    #[arg(long)]
    pub duration: Option<f64>,
}

pub fn run(args: RunArgs) -> anyhow::Result<ExitCode> {
    let path = super::overrides::config_path(args.config, "--config")?;
    let overrides = args.overrides.overrides();
    // The validation `visnav check-config` does: what it passes, run starts.
    let cfg = super::overrides::load(&path, &overrides)?;
    tracing::info!("configuration {}", path.display());
    for line in overrides.describe() {
        tracing::info!("override: {line}");
    }
    let duration = match args.duration {
        Some(s) if s.is_finite() && s > 0.0 && s < 1e9 => Some(Duration::from_secs_f64(s)),
        Some(s) => anyhow::bail!(
            "--duration {}: expected a positive number of seconds",
            visnav_core::text::num(s)
        ),
        None => None,
    };
    // With a frame source, the vision fix engine of [map], [camera] and [fix].
    let fixer: Option<std::sync::Arc<dyn visnav::daemon::FrameFixer>> = match &cfg.frames {
        Some(frames) => {
            tracing::info!("camera frames: {}", frames.describe_source());
            let fixer = visnav::daemon::fixer_from_config(&cfg)
                .with_context(|| format!("{}: vision fix engine", path.display()))?;
            Some(fixer)
        }
        None => {
            tracing::warn!("{}", super::check_config::NO_CAMERA_WARNING);
            None
        }
    };
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    let m = rt.block_on(visnav::daemon::run(&cfg, fixer, duration))?;
    println!("{}", serde_json::to_string(&m)?);
    Ok(ExitCode::SUCCESS)
}
