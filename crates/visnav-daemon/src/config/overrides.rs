//! Command-line and environment overrides of the configuration file, as MAVProxy and
//! mavlink-router users expect them: `--connection STRING`, `--map FILE`, `--camera SPEC` on
//! `visnav run` and `visnav check-config`, and the environment variables `VISNAV_CONNECTION`,
//! `VISNAV_MAP`, `VISNAV_CAMERA`. The command line beats the environment, which beats the file.
//!
//! They are applied to the parsed configuration before its validation
//! (`Config::load_checked_with` in [`super`]), so the validation sees the final values
//! and its messages name the override (`link.connection (from --connection): ...`). A relative
//! path in an override is relative to the current directory, not to the config file's folder.
//!
//! What each replaces:
//! * `--connection`: `[link] connection` (the same syntax: `udpin:0.0.0.0:14550`,
//!   `tcpout:127.0.0.1:5760`, `serial:/dev/ttyAMA0:921600`, ...).
//! * `--map`: `[map] file` (a `.vnm` map); the file's `ortho`, `upsample` and height sigmas
//!   (`height_sigma_m`, `height_slope_sigma`, `height_point_sigma_m`), which describe building a
//!   map from orthophotos, are then not used; `dem` /
//!   `ground_height_amsl_m` still override the map's terrain.
//! * `--camera`: the source of `[frames]` (`FramesConfig::from_spec`: a folder with
//!   `frames.csv`, a `.y4m` file, `v4l2:DEVICE`, `gst:PIPELINE`, `cmd:PROGRAM ARGS`); the file's
//!   other `[frames]` keys (`latency_s`, `timeout_s`, `realtime`, `max_age_s`, `workers`, and
//!   `rate_hz` / `stamp` where the new kind uses them) are kept. The intrinsics stay those of
//!   `[camera]`, which must be there.

use std::fmt;
use std::path::PathBuf;

use visnav_core::validate::{Base, Invalid};
use visnav_io::frames::{FramesConfig, SourceKind, StampMode};

/// Where an override's value came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Origin {
    /// A command-line option (`--map`).
    Flag(&'static str),
    /// An environment variable (`VISNAV_MAP`).
    Env(&'static str),
}

impl fmt::Display for Origin {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Origin::Flag(s) | Origin::Env(s) => f.write_str(s),
        }
    }
}

/// One overridden value and where it came from.
#[derive(Debug, Clone, PartialEq)]
pub struct Given<T> {
    /// The value.
    pub value: T,
    /// Where it came from.
    pub origin: Origin,
}

/// The overrides of one start (each `None`: the file's value).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Overrides {
    /// `[link] connection`.
    pub connection: Option<Given<String>>,
    /// `[map] file`, relative to the current directory.
    pub map: Option<Given<PathBuf>>,
    /// The `[frames]` source, a `--camera` spec.
    pub camera: Option<Given<String>>,
}

/// The command-line options, environment variables and configuration keys of each override.
const CONNECTION: (&str, &str) = ("--connection", "VISNAV_CONNECTION");
const MAP: (&str, &str) = ("--map", "VISNAV_MAP");
const CAMERA: (&str, &str) = ("--camera", "VISNAV_CAMERA");

/// The `[frames]` keys a `--camera` spec sets.
const CAMERA_KEYS: [&str; 7] = [
    "frames.source",
    "frames.path",
    "frames.command",
    "frames.pipeline",
    "frames.width_px",
    "frames.height_px",
    "frames.pixel_format",
];

/// An override that cannot be applied (a `--camera` spec that names no source, or one given
/// for a configuration without `[camera]`).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{origin} {}: {reason}", visnav_core::text::excerpt(.value))]
pub struct OverrideError {
    /// Where the value came from.
    pub origin: Origin,
    /// The value, as given.
    pub value: String,
    /// What is wrong, in words.
    pub reason: String,
}

/// The command line's value, else the environment's (`env` looks a variable up; an empty value
/// counts as unset).
fn pick<T>(
    flag: Option<T>,
    (flag_name, var): (&'static str, &'static str),
    env: &dyn Fn(&str) -> Option<String>,
    from_env: impl Fn(String) -> T,
) -> Option<Given<T>> {
    match flag {
        Some(value) => Some(Given {
            value,
            origin: Origin::Flag(flag_name),
        }),
        None => env(var).filter(|v| !v.is_empty()).map(|v| Given {
            value: from_env(v),
            origin: Origin::Env(var),
        }),
    }
}

impl Overrides {
    /// The overrides from the command line's options and, for those not given, the environment
    /// (`env`: `std::env::var(..).ok()` in the binary).
    pub fn new(
        connection: Option<String>,
        map: Option<PathBuf>,
        camera: Option<String>,
        env: &dyn Fn(&str) -> Option<String>,
    ) -> Overrides {
        Overrides {
            connection: pick(connection, CONNECTION, env, |v| v),
            map: pick(map, MAP, env, PathBuf::from),
            camera: pick(camera, CAMERA, env, |v| v),
        }
    }

    /// One line per override, for the log at start and `check-config`:
    /// `connection udpin:0.0.0.0:14550 (from --connection)`.
    pub fn describe(&self) -> Vec<String> {
        let mut lines = Vec::new();
        if let Some(g) = &self.connection {
            lines.push(format!("connection {} (from {})", g.value, g.origin));
        }
        if let Some(g) = &self.map {
            lines.push(format!("map {} (from {})", g.value.display(), g.origin));
        }
        if let Some(g) = &self.camera {
            lines.push(format!("camera {} (from {})", g.value, g.origin));
        }
        lines
    }

    /// `--camera` given for a configuration that has no `[camera]` section.
    pub(crate) fn camera_without_intrinsics(&self) -> Option<OverrideError> {
        self.camera.as_ref().map(|g| OverrideError {
            origin: g.origin,
            value: g.value.clone(),
            reason: "the configuration has no [camera] section: a camera source needs the \
                     camera's size and intrinsics (width_px, height_px, fx_px, ...; `visnav camera \
                     import` prints the section from a calibration file)"
                .to_string(),
        })
    }

    /// The folder the `[map] file` path is relative to: the current directory when `--map`
    /// gave it, else the config file's folder.
    pub(crate) fn map_base(&self, file: &Base) -> Base {
        if self.map.is_some() {
            Base::current_dir()
        } else {
            file.clone()
        }
    }

    /// The folder the `[frames]` paths are relative to.
    pub(crate) fn frames_base(&self, file: &Base) -> Base {
        if self.camera.is_some() {
            Base::current_dir()
        } else {
            file.clone()
        }
    }

    /// The frame source after the `--camera` override (the file's `frames` when there is none;
    /// `size`: the camera's image size, px). `Config::apply_overrides` puts every override in.
    pub(crate) fn frames(
        &self,
        file: Option<FramesConfig>,
        size: (usize, usize),
    ) -> Result<Option<FramesConfig>, OverrideError> {
        let Some(g) = &self.camera else {
            return Ok(file);
        };
        let new = FramesConfig::from_spec(&g.value, &Base::current_dir(), size).map_err(|e| {
            OverrideError {
                origin: g.origin,
                value: g.value.clone(),
                reason: e.to_string(),
            }
        })?;
        Ok(Some(match file {
            Some(old) => with_source_of(old, new),
            None => new,
        }))
    }

    /// Name the override in a problem with a value it set: `link.connection (from
    /// --connection)`.
    pub(crate) fn tag(&self, problem: &mut Invalid) {
        let origin = if problem.key == "link.connection" {
            self.connection.as_ref().map(|g| g.origin)
        } else if problem.key == "map.file" {
            self.map.as_ref().map(|g| g.origin)
        } else if CAMERA_KEYS.contains(&problem.key.as_str()) {
            self.camera.as_ref().map(|g| g.origin)
        } else {
            None
        };
        if let Some(o) = origin {
            problem.key = format!("{} (from {o})", problem.key);
        }
    }
}

/// The file's `[frames]` with the source of `new`: its timing and worker keys kept, `rate_hz`
/// and `stamp = "source"` only where the new kind uses them.
fn with_source_of(old: FramesConfig, new: FramesConfig) -> FramesConfig {
    let recorded = matches!(new.source, SourceKind::Directory | SourceKind::Y4m);
    FramesConfig {
        rate_hz: old.rate_hz.filter(|_| recorded),
        stamp: if new.source == SourceKind::Directory {
            old.stamp
        } else {
            StampMode::Arrival
        },
        timeout_s: old.timeout_s,
        latency_s: old.latency_s,
        realtime: old.realtime,
        max_age_s: old.max_age_s,
        workers: old.workers,
        ..new
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn env_of(pairs: &[(&str, &str)]) -> impl Fn(&str) -> Option<String> {
        let pairs: Vec<(String, String)> = pairs
            .iter()
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .collect();
        move |k| pairs.iter().find(|(n, _)| n == k).map(|(_, v)| v.clone())
    }

    #[test]
    fn command_line_beats_environment() {
        let env = env_of(&[
            ("VISNAV_CONNECTION", "udpin:0.0.0.0:14551"),
            ("VISNAV_MAP", "env.vnm"),
            ("VISNAV_CAMERA", ""),
        ]);
        let o = Overrides::new(Some("tcpout:127.0.0.1:5760".into()), None, None, &env);
        assert_eq!(
            o.connection,
            Some(Given {
                value: "tcpout:127.0.0.1:5760".into(),
                origin: Origin::Flag("--connection"),
            })
        );
        assert_eq!(
            o.map,
            Some(Given {
                value: PathBuf::from("env.vnm"),
                origin: Origin::Env("VISNAV_MAP"),
            })
        );
        assert_eq!(o.camera, None, "an empty variable is unset");
        assert_eq!(
            o.describe(),
            [
                "connection tcpout:127.0.0.1:5760 (from --connection)",
                "map env.vnm (from VISNAV_MAP)"
            ]
        );
        assert_eq!(
            Overrides::new(None, None, None, &env_of(&[])),
            Overrides::default()
        );
    }

    #[test]
    fn camera_keeps_the_files_timing_keys() {
        let mut old = FramesConfig::new(SourceKind::Directory, "frames");
        old.latency_s = 0.04;
        old.workers = 2;
        old.rate_hz = Some(10.0);
        old.stamp = StampMode::Source;
        let new = FramesConfig::from_spec("v4l2:/dev/video0", &Base::current_dir(), (640, 480));
        let merged = with_source_of(old.clone(), new.unwrap_or_else(|e| panic!("{e}")));
        assert_eq!(merged.source, SourceKind::V4l2);
        assert_eq!((merged.width_px, merged.height_px), (Some(640), Some(480)));
        assert_eq!((merged.latency_s, merged.workers), (0.04, 2));
        assert_eq!((merged.rate_hz, merged.stamp), (None, StampMode::Arrival));
        let y4m = FramesConfig::from_spec("f.y4m", &Base::current_dir(), (640, 480));
        let merged = with_source_of(old, y4m.unwrap_or_else(|e| panic!("{e}")));
        assert_eq!(merged.rate_hz, Some(10.0));
    }

    #[test]
    fn problems_name_the_override() {
        let o = Overrides::new(None, Some("m.vnm".into()), None, &env_of(&[]));
        let mut p = Invalid {
            key: "map.file".into(),
            reason: "r".into(),
        };
        o.tag(&mut p);
        assert_eq!(p.to_string(), "map.file (from --map): r");
        let mut p = Invalid {
            key: "map.dem".into(),
            reason: "r".into(),
        };
        o.tag(&mut p);
        assert_eq!(p.key, "map.dem");
    }
}
