//! `visnav check-config FILE`: parse and validate a configuration file, printing every problem.

use std::path::PathBuf;
use std::process::ExitCode;

use visnav::daemon::app_config::{Config, ConfigError};
use visnav::link::config::OutputMode;

#[derive(clap::Args, Debug)]
pub struct CheckConfigArgs {
    /// The TOML configuration file to check.
    pub file: PathBuf,
}

pub fn run(args: CheckConfigArgs) -> anyhow::Result<ExitCode> {
    // The validation `visnav run` does before it starts: what passes here, run starts.
    match Config::load_checked(&args.file) {
        Ok(cfg) => {
            let modes: Vec<&str> = cfg
                .output
                .modes
                .iter()
                .map(|m| match m {
                    OutputMode::GpsInput => "gps_input",
                    OutputMode::VisionPositionEstimate => "vision_position_estimate",
                    OutputMode::Odometry => "odometry",
                    OutputMode::GlobalPositionSensor => "global_position_sensor",
                })
                .collect();
            println!(
                "{}: OK (link {}, camera {}x{} px, {} orthophoto(s) loaded, output [{}] at {} Hz)",
                args.file.display(),
                cfg.link.connection,
                cfg.camera.width_px,
                cfg.camera.height_px,
                cfg.map.ortho.len(),
                modes.join(", "),
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
