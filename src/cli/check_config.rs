//! `visnav check-config FILE`: parse and validate a configuration file, printing every problem.

use std::path::PathBuf;
use std::process::ExitCode;

use visnav::daemon::app_config::{Config, ConfigError};
use visnav::link::config::OutputMode;

use super::overrides::OverrideArgs;

#[derive(clap::Args, Debug)]
pub struct CheckConfigArgs {
    /// The TOML configuration file to check (default: the environment's VISNAV_CONFIG),
    /// relative to the current directory.
    pub file: Option<PathBuf>,
    #[command(flatten)]
    pub overrides: OverrideArgs,
}

pub fn run(args: CheckConfigArgs) -> anyhow::Result<ExitCode> {
    let file = super::overrides::config_path(args.file, "FILE")?;
    let overrides = args.overrides.overrides();
    // The validation `visnav run` does before it starts: what passes here, run starts.
    match super::overrides::load(&file, &overrides) {
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
                "{}: OK (link {}, camera {}x{} px, {}, output [{}] at {} Hz)",
                file.display(),
                cfg.link.connection,
                cfg.camera.width_px,
                cfg.camera.height_px,
                map_words(&cfg),
                modes.join(", "),
                cfg.output.rate_hz
            );
            println!("{}", vision_line(&cfg));
            for line in overrides.describe() {
                println!("override: {line}");
            }
            Ok(ExitCode::SUCCESS)
        }
        Err(
            e @ (ConfigError::Invalid { .. }
            | ConfigError::Parse { .. }
            | ConfigError::Override { .. }),
        ) => {
            eprintln!("{e}");
            Ok(ExitCode::from(2))
        }
        Err(e) => Err(e.into()),
    }
}

/// What the configuration's vision does, in one line; without a camera (`[frames]`) it says
/// loudly that `visnav run` navigates without vision (issue 24: a config without a camera used to
/// pass silently and the daemon logged `frames_in=0` forever).
pub fn vision_line(cfg: &Config) -> String {
    match &cfg.frames {
        None => NO_CAMERA_WARNING.to_string(),
        Some(f) => format!(
            "vision: camera frames from [frames] ({}); map fixes on; visual odometry {}; DTM \
             navigation {}; {}",
            f.describe_source(),
            on_off(cfg.vo.enabled),
            on_off(cfg.dtm_nav.enabled),
            surf_words(cfg.vision.backend)
        ),
    }
}

/// Where `[vision] backend` puts SURF, for this binary.
fn surf_words(b: visnav::daemon::wiring::VisionBackend) -> &'static str {
    use visnav::daemon::wiring::VisionBackend as B;
    match (b, cfg!(feature = "gpu")) {
        (B::Cpu, _) => "SURF on the CPU",
        (B::Gpu, true) => "SURF on the GPU (any adapter; the CPU when none opens)",
        (B::Auto, true) => "SURF on a hardware GPU when there is one, else the CPU",
        (B::Gpu, false) => {
            "SURF on the CPU: [vision] backend = \"gpu\", but this visnav is built without the \
             GPU path (cargo build --release --features gpu)"
        }
        (B::Auto, false) => "SURF on the CPU (built without the GPU path)",
    }
}

/// The map in a few words: `map /abs/area.vnm` or `2 orthophoto(s) loaded`.
fn map_words(cfg: &Config) -> String {
    match &cfg.map.file {
        Some(f) => format!("map {}", f.display()),
        None => format!("{} orthophoto(s) loaded", cfg.map.ortho.len()),
    }
}

/// The warning for a configuration without a camera.
pub const NO_CAMERA_WARNING: &str = "warning: no [frames] section: no camera, so no vision \
fixes; visnav run navigates on the autopilot's IMU, attitude and GPS alone (add [frames], \
docs/operations.md)";

fn on_off(b: bool) -> &'static str {
    if b { "on" } else { "off" }
}
