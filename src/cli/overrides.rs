//! The options `visnav run` and `visnav check-config` share: the configuration file and the
//! overrides of its connection, map and camera (`visnav_daemon::config::overrides`).

use std::path::PathBuf;

use visnav::daemon::config::{Config, ConfigError, Overrides};

/// The configuration file and its overrides. The command line beats the environment, which
/// beats the file.
#[derive(clap::Args, Debug)]
pub struct OverrideArgs {
    /// The MAVLink connection, replacing [link] connection: udpin:ADDR:PORT, udpout:HOST:PORT,
    /// udpbcast:ADDR:PORT, tcpin:ADDR:PORT, tcpout:HOST:PORT, serial:DEVICE[:BAUD], or as
    /// MAVProxy writes them: udp:ADDR:PORT (listen), tcp:HOST:PORT (connect), DEVICE[,BAUD]
    /// (e.g. udpin:0.0.0.0:14550, /dev/ttyACM0,57600; serial at 115200 baud when none is
    /// given). Environment: VISNAV_CONNECTION.
    #[arg(long, value_name = "STRING")]
    pub connection: Option<String>,
    /// The reference map (.vnm), replacing [map] file (the file's ortho, upsample and
    /// height_sigma_m are then not used). Environment: VISNAV_MAP. A relative path here or in
    /// the environment is relative to the current directory (in the file: to its folder).
    #[arg(long, value_name = "FILE")]
    pub map: Option<PathBuf>,
    /// The camera frame source, replacing the source of [frames] (its other keys stay; the
    /// intrinsics stay those of [camera]): a folder with frames.csv, a .y4m file,
    /// dir:PATH, y4m:PATH, v4l2:DEVICE (at [camera]'s size), gst:PIPELINE or cmd:PROGRAM ARGS
    /// (no shell). Environment: VISNAV_CAMERA. A relative path here or in the environment is
    /// relative to the current directory (in the file: to its folder).
    #[arg(long, value_name = "SPEC")]
    pub camera: Option<String>,
}

/// The environment variable naming the configuration file when no file is given.
pub const CONFIG_VAR: &str = "VISNAV_CONFIG";

impl OverrideArgs {
    /// The overrides: these options, and the environment's for those not given.
    pub fn overrides(&self) -> Overrides {
        Overrides::new(
            self.connection.clone(),
            self.map.clone(),
            self.camera.clone(),
            &|name| std::env::var(name).ok(),
        )
    }
}

/// The configuration file: `given`, else `VISNAV_CONFIG`.
pub fn config_path(given: Option<PathBuf>, option: &str) -> anyhow::Result<PathBuf> {
    match given {
        Some(p) => Ok(p),
        None => std::env::var_os(CONFIG_VAR)
            .filter(|v| !v.is_empty())
            .map(PathBuf::from)
            .ok_or_else(|| {
                anyhow::anyhow!("no configuration file: give {option} or set {CONFIG_VAR}")
            }),
    }
}

/// The configuration with the overrides applied, validated and its data files opened: the one
/// path of `run` and `check-config`.
pub fn load(path: &std::path::Path, overrides: &Overrides) -> Result<Config, ConfigError> {
    Config::load_checked_with(path, overrides)
}
