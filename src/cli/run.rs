//! `visnav run --config F [--duration S]`: the navigation service. Talks to the autopilot, runs
//! the navigation pipeline and injects the solution until SIGINT/SIGTERM (or `--duration`).

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use anyhow::Context;
use visnav::config::Config;

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
    let cfg = Config::load(&args.config)?;
    let duration = match args.duration {
        Some(s) if s.is_finite() && s > 0.0 && s < 1e9 => Some(Duration::from_secs_f64(s)),
        Some(s) => anyhow::bail!("--duration {s}: expected a positive number of seconds"),
        None => None,
    };
    if cfg.frames.is_some() {
        // The lead wires the vision fix engine here (src/fix); until then a configured frame
        // source cannot be served.
        anyhow::bail!(
            "{}: [frames] is configured but the vision fix engine is not available in this build \
             (remove [frames] to run with IMU, GPS, attitude and baro only)",
            args.config.display()
        );
    }
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    let m = rt.block_on(visnav::daemon::run(&cfg, None, duration))?;
    println!("{}", serde_json::to_string(&m)?);
    Ok(ExitCode::SUCCESS)
}
