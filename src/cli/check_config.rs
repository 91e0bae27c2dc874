//! `visnav check-config FILE`: parse and validate a configuration file (`-`: standard input),
//! printing every problem, and a warning for every value the file marks as a placeholder.

use std::io::Read;
use std::path::PathBuf;
use std::process::ExitCode;

use visnav::daemon::config::{Config, ConfigError};
use visnav::link::config::OutputMode;

use super::overrides::OverrideArgs;

#[derive(clap::Args, Debug)]
pub struct CheckConfigArgs {
    /// The TOML configuration file to check (default: the environment's VISNAV_CONFIG),
    /// relative to the current directory; `-` reads it from standard input (its relative paths
    /// are then relative to the current directory).
    pub file: Option<PathBuf>,
    #[command(flatten)]
    pub overrides: OverrideArgs,
}

pub fn run(args: CheckConfigArgs) -> anyhow::Result<ExitCode> {
    let file = super::overrides::config_path(args.file, "FILE")?;
    let overrides = args.overrides.overrides();
    let from_stdin = file.as_os_str() == "-";
    let (text, file) = match from_stdin {
        true => (read_stdin()?, PathBuf::from(STDIN_NAME)),
        // Read again by the load below, which names the file in its errors.
        false => (
            visnav_io::files::read_text(&file, visnav_io::files::CONFIG).unwrap_or_default(),
            file,
        ),
    };
    let warnings = placeholder_warnings(&text);
    // The validation `visnav run` does before it starts: what passes here, run starts.
    let loaded = match from_stdin {
        true => Config::from_toml_str_checked(&text, &file, &overrides),
        false => super::overrides::load(&file, &overrides),
    };
    match loaded {
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
            for w in &warnings {
                println!("{w}");
            }
            Ok(ExitCode::SUCCESS)
        }
        Err(
            e @ (ConfigError::Invalid { .. }
            | ConfigError::Parse { .. }
            | ConfigError::Override { .. }),
        ) => {
            eprintln!("{e}");
            for w in &warnings {
                eprintln!("{w}");
            }
            Ok(ExitCode::from(2))
        }
        Err(e) => Err(e.into()),
    }
}

/// How a configuration read from standard input is named in messages (its relative paths are
/// relative to the current directory, the folder of this relative name).
const STDIN_NAME: &str = "(standard input)";

/// The configuration from standard input, at most the size a configuration file may have.
fn read_stdin() -> anyhow::Result<String> {
    let kind = visnav_io::files::CONFIG;
    let mut bytes = Vec::new();
    std::io::stdin()
        .lock()
        .take(kind.max_bytes + 1)
        .read_to_end(&mut bytes)
        .map_err(|e| anyhow::anyhow!("{STDIN_NAME}: cannot read: {e}"))?;
    if bytes.len() as u64 > kind.max_bytes {
        anyhow::bail!(
            "{STDIN_NAME}: more than the {} {} may have",
            visnav_io::files::size_words(kind.max_bytes),
            kind.what
        );
    }
    let text = String::from_utf8(bytes).map_err(|e| {
        anyhow::anyhow!(
            "{STDIN_NAME}: not UTF-8 text (byte {}); {} is text",
            e.utf8_error().valid_up_to(),
            kind.what
        )
    })?;
    Ok(match text.strip_prefix(visnav_io::files::BOM) {
        Some(rest) => rest.to_string(),
        None => text,
    })
}

/// One warning per value the file marks as a placeholder (`# placeholder` after it): a value
/// that parses and may even pass, but is the example's, not this installation's.
pub fn placeholder_warnings(text: &str) -> Vec<String> {
    visnav::daemon::config::placeholders(text)
        .into_iter()
        .map(|p| {
            let note = match p.note.is_empty() {
                true => String::new(),
                false => format!(" ({})", p.note),
            };
            format!(
                "warning: {} (line {}) is a placeholder{note}: replace it with this \
                 installation's value and remove the \"# placeholder\" mark",
                p.key, p.line
            )
        })
        .collect()
}

/// What the configuration's vision does, in one line; without a camera (`[frames]`) it says
/// loudly that `visnav run` navigates without vision (otherwise a config without a camera passes
/// silently and the daemon logs `frames_in=0` forever).
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
fn surf_words(b: visnav::daemon::config::vision::VisionBackend) -> &'static str {
    use visnav::daemon::config::vision::VisionBackend as B;
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
