//! `visnav check-config FILE`: parse and validate a configuration file, printing every problem.

use std::path::PathBuf;
use std::process::ExitCode;

use visnav::daemon::app_config::{Config, ConfigError};

#[derive(clap::Args, Debug)]
pub struct CheckConfigArgs {
    /// The TOML configuration file to check.
    pub file: PathBuf,
}

pub fn run(args: CheckConfigArgs) -> anyhow::Result<ExitCode> {
    match Config::load(&args.file).and_then(|cfg| cfg.check_data(&args.file).map(|()| cfg)) {
        Ok(cfg) => {
            println!(
                "{}: OK (link {}, camera {}x{} px, {} orthophoto(s) loaded, output {:?} at {} Hz)",
                args.file.display(),
                cfg.link.connection,
                cfg.camera.width_px,
                cfg.camera.height_px,
                cfg.map.ortho.len(),
                cfg.output.modes,
                cfg.output.rate_hz
            );
            Ok(ExitCode::SUCCESS)
        }
        Err(e @ (ConfigError::Invalid { .. } | ConfigError::Parse { .. })) => {
            eprintln!("{e}");
            Ok(ExitCode::from(2))
        }
        Err(e) => Err(e.into()),
    }
}
