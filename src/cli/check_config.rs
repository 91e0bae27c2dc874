//! `visnav check-config FILE`: parse and validate a configuration file, printing every problem.

use std::path::PathBuf;
use std::process::ExitCode;

use visnav::config::{Config, ConfigError};

#[derive(clap::Args, Debug)]
pub struct CheckConfigArgs {
    /// The TOML configuration file to check.
    pub file: PathBuf,
}

pub fn run(args: CheckConfigArgs) -> anyhow::Result<ExitCode> {
    match Config::load(&args.file) {
        Ok(cfg) => {
            println!(
                "{}: OK (link {}, {} orthophoto(s), output {:?} at {} Hz)",
                args.file.display(),
                cfg.link.connection,
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
