//! The application's TOML configuration (`visnav run --config F`, `visnav check-config F`): the
//! one type that names every section, loading and validation. Each section's type lives with its
//! module (`[camera]` in the camera model, `[nav]` in the filter, `[link]`/`[output]` in the
//! link, ...) and checks itself through `visnav_core::validate`.
//!
//! Every section is a serde struct with `deny_unknown_fields`, so a misspelt key is an error that
//! names the key (and every other unknown key of the file, [`unknown_keys`]). After parsing,
//! every value is validated through [`Validate`]: each section reports the dotted key path
//! (`camera.fx_px`), the offending value and the reason, and all problems are reported at once,
//! prefixed with the file name.
//!
//! The daemon's own sections sit beside this file: [`daemon`] (`[daemon]`), [`map`] (`[map]`),
//! [`vision`] (`[vision]`), [`fix`] (`[fix]` as the engine's parameters), with the command-line
//! and environment [`overrides`] and the generated key [`reference`](mod@reference).

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use visnav_core::camera::CameraConfig;
use visnav_core::geo::Crs;
use visnav_core::nav::config::NavConfig;
use visnav_link::config::{LinkConfig, OutputConfig};

use visnav_core::validate::{Base, Invalid, Problems, Validate};

pub mod daemon;
pub mod fix;
pub mod map;
pub mod overrides;
pub mod reference;
pub mod unknown_keys;
pub mod vision;

pub use daemon::{DaemonConfig, GpsSource, ImuBiasRestore};
pub use map::MapConfig;
pub use overrides::{Given, Origin, OverrideError, Overrides};

/// Why a configuration file could not be used. Every variant names the file.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The file could not be read.
    #[error("{path}: cannot read: {cause}")]
    Read {
        /// The file.
        path: PathBuf,
        /// The operating system's error.
        cause: std::io::Error,
    },
    /// TOML syntax, a wrong type or an unknown key (the message names the key, line and column).
    /// The file is not valid TOML or a key or value is refused.
    #[error("{path}: {message}")]
    Parse {
        /// The file.
        path: PathBuf,
        /// The parser's message (key, line and column).
        message: String,
    },
    /// A command-line or environment override that cannot be applied.
    /// A command-line or environment override is not usable.
    #[error("{path}: {error}")]
    Override {
        /// The file.
        path: PathBuf,
        /// What is wrong with the override.
        error: OverrideError,
    },
    /// Parsed, but values are out of range, inconsistent or name missing files.
    #[error("{path}: {} invalid value(s):\n  {}", problems.len(), problems.iter().map(|p| p.to_string()).collect::<Vec<_>>().join("\n  "))]
    Invalid {
        /// The file.
        path: PathBuf,
        /// Every problem found (key, value, reason).
        problems: Vec<Invalid>,
    },
}

/// The whole daemon configuration (`visnav run --config F`, `visnav check-config F`).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// MAVLink connection to the autopilot.
    pub link: LinkConfig,
    /// The camera: intrinsics, distortion, mount.
    pub camera: CameraConfig,
    /// Reference map sources.
    pub map: MapConfig,
    /// What is injected into the autopilot, and how often.
    #[serde(default)]
    pub output: OutputConfig,
    /// The navigation filter (INS + error-state EKF); every key has a default.
    #[serde(default)]
    pub nav: NavConfig,
    /// The vision fix pipeline; every key has a default, a partial table merges over them.
    #[serde(
        default,
        deserialize_with = "crate::config::fix::deserialize_fix_params"
    )]
    pub fix: visnav_core::fix::FixParams,
    /// Camera frame source (absent: no vision fixes, IMU/GPS/attitude only).
    #[serde(default)]
    pub frames: Option<visnav_io::frames::FramesConfig>,
    /// Visual odometry between fixes (off unless `enabled`); every key has a default.
    #[serde(default)]
    pub vo: visnav_core::vo::VoConfig,
    /// DTM navigation: the pose from the flow between two frames and the terrain model alone
    /// (off unless `enabled`); every key has a default.
    #[serde(default)]
    pub dtm_nav: visnav_core::dtm_nav::DtmNavConfig,
    /// The daemon's pipeline settings; every key has a default.
    #[serde(default)]
    pub daemon: crate::config::DaemonConfig,
    /// Where the vision's SURF features are computed (`[vision] backend`).
    #[serde(default)]
    pub vision: crate::config::vision::VisionConfig,
}

/// A file the daemon will create (`link.tlog`, `daemon.fix_log`): its name with `{t}` expanded
/// as the daemon expands it must not be a directory, and its folder must exist.
fn check_output_file(p: &mut Problems, key: &str, base: &Base, f: &Path) {
    let now_s = visnav_link::tlog::unix_now_us() / 1_000_000;
    let full = base.resolve(&visnav_link::tlog::expand_name(f, now_s));
    if full.is_dir() {
        p.push(
            key,
            base.problem(f, "is a directory; give a file name in it"),
        );
        return;
    }
    if let Some(d) = full.parent().filter(|d| !d.as_os_str().is_empty())
        && !d.is_dir()
    {
        p.push(key, base.problem(f, "is in a folder that does not exist"));
    }
}

/// A serial `link.connection` (`serial:DEVICE[:BAUD]`, `DEVICE[,BAUD]`): the device must exist
/// and be a character device (the serial port the link opens at start).
fn check_serial_device(p: &mut Problems, connection: &str) {
    let Ok(visnav_link::config::Endpoint::Serial { device: dev, .. }) =
        visnav_link::config::parse_connection(connection)
    else {
        return; // not serial, or malformed (reported by the link's own check)
    };
    match std::fs::metadata(&dev) {
        Err(e) => p.push(
            "connection",
            format!("the serial device {dev} cannot be used: {e}"),
        ),
        Ok(m) => {
            use std::os::unix::fs::FileTypeExt;
            if !m.file_type().is_char_device() {
                p.push(
                    "connection",
                    format!("{dev} is not a serial device (not a character device)"),
                );
            }
        }
    }
}

fn check_file(p: &mut Problems, key: &str, base: &Base, f: &Path) {
    if let Some(why) = base.file_problem(f, std::fs::metadata(base.resolve(f)).map(|m| m.is_file()))
    {
        p.push(key, why);
    }
}

/// A parse error's text: TOML's own (line, column, the key), and when the key is unknown, every
/// other unknown key of the file too ([`crate::config::unknown_keys`]).
fn parse_message(e: &toml::de::Error, text: &str) -> String {
    let first = e.to_string().trim_end().to_string();
    if !e.message().starts_with("unknown field") {
        return first;
    }
    let all = crate::config::unknown_keys::unknown_keys::<Config>(text);
    if all.len() < 2 {
        return first;
    }
    format!(
        "{first}\n{} unknown keys in all:\n  {}",
        all.len(),
        all.join("\n  ")
    )
}

/// The marker of a value to replace: a trailing comment starting with it (`ortho = [...]  #
/// placeholder: your area's orthophoto`) makes `check-config` warn, naming the key.
pub const PLACEHOLDER_MARK: &str = "placeholder";

/// A value the file marks as one to replace: a key whose line carries a trailing
/// `# placeholder` comment (`config/companion.toml`, `visnav config default`).
#[derive(Debug, Clone, PartialEq)]
pub struct Placeholder {
    /// Dotted key (`map.ortho`).
    pub key: String,
    /// 1-based line of the file.
    pub line: usize,
    /// What the comment says after the mark (`your area's orthophoto`), may be empty.
    pub note: String,
}

/// The keys the TOML `text` marks as placeholders. Lines are read as TOML writes them by hand:
/// `[table]` headers set the section, `key = value  # placeholder: note` marks the key; a `#`
/// inside a quoted string is not a comment.
pub fn placeholders(text: &str) -> Vec<Placeholder> {
    let mark = PLACEHOLDER_MARK;
    let mut section = String::new();
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let (code, comment) = split_comment(line);
        let code = code.trim();
        if let Some(h) = code.strip_prefix('[').and_then(|h| h.strip_suffix(']')) {
            section = h.trim_matches(|c| c == '[' || c == ']').trim().to_string();
            continue;
        }
        let Some(comment) = comment else { continue };
        let comment = comment.trim_start_matches('#').trim();
        let Some(note) = comment
            .get(..mark.len())
            .filter(|m| m.eq_ignore_ascii_case(mark))
            .map(|_| comment[mark.len()..].trim_start_matches(':').trim())
        else {
            continue;
        };
        let Some((key, _)) = code.split_once('=') else {
            continue;
        };
        let key = key.trim().trim_matches('"');
        out.push(Placeholder {
            key: match section.is_empty() {
                true => key.to_string(),
                false => format!("{section}.{key}"),
            },
            line: i + 1,
            note: note.to_string(),
        });
    }
    out
}

/// A line's code and its comment (from the first `#` outside a string).
fn split_comment(line: &str) -> (&str, Option<&str>) {
    let mut quote: Option<char> = None;
    let mut escaped = false;
    for (i, c) in line.char_indices() {
        match quote {
            Some('"') if escaped => escaped = false,
            Some('"') if c == '\\' => escaped = true,
            Some(q) if c == q => quote = None,
            Some(_) => {}
            None if c == '"' || c == '\'' => quote = Some(c),
            None if c == '#' => return (&line[..i], Some(&line[i..])),
            None => {}
        }
    }
    (line, None)
}

impl Config {
    /// Parse TOML text. `path` is used in messages and its folder to resolve relative paths.
    pub fn from_toml_str(text: &str, path: &Path) -> Result<Config, ConfigError> {
        Self::from_toml_str_with(text, path, &Overrides::default())
    }

    /// Put the overridden values in (parsed, not yet validated): `--map` replaces `[map] file`
    /// and drops what only building a map from orthophotos uses.
    fn apply_overrides(&mut self, o: &Overrides) -> Result<(), OverrideError> {
        if let Some(g) = &o.connection {
            self.link.connection = g.value.clone();
        }
        if let Some(g) = &o.map {
            self.map.file = Some(g.value.clone());
            self.map.ortho.clear();
            self.map.upsample = None;
            self.map.height_sigma_m = None;
            self.map.height_slope_sigma = None;
            self.map.height_point_sigma_m = None;
        }
        let size = (
            self.camera.width_px as usize,
            self.camera.height_px as usize,
        );
        self.frames = o.frames(self.frames.take(), size)?;
        Ok(())
    }

    /// Parse TOML text, apply the command-line / environment overrides, validate the result and
    /// make its paths absolute (the file's against its folder, the overrides' against the
    /// current directory).
    pub fn from_toml_str_with(
        text: &str,
        path: &Path,
        overrides: &Overrides,
    ) -> Result<Config, ConfigError> {
        let mut cfg = Self::parse(text, path, overrides)?;
        cfg.apply_overrides(overrides)
            .map_err(|error| ConfigError::Override {
                path: path.to_path_buf(),
                error,
            })?;
        let base = Base::config_file(path);
        let mut problems = cfg.problems(&base, overrides);
        if !problems.is_empty() {
            problems.iter_mut().for_each(|p| overrides.tag(p));
            return Err(ConfigError::Invalid {
                path: path.to_path_buf(),
                problems,
            });
        }
        cfg.resolve_paths(&base, overrides);
        Ok(cfg)
    }

    /// The TOML text as a configuration; a `--camera` for a file without `[camera]` is named as
    /// such rather than as TOML's missing field.
    fn parse(text: &str, path: &Path, overrides: &Overrides) -> Result<Config, ConfigError> {
        toml::from_str(text).map_err(|e| {
            let no_camera =
                || toml::from_str::<toml::Table>(text).is_ok_and(|t| !t.contains_key("camera"));
            match overrides.camera_without_intrinsics() {
                Some(error) if no_camera() => ConfigError::Override {
                    path: path.to_path_buf(),
                    error,
                },
                _ => ConfigError::Parse {
                    path: path.to_path_buf(),
                    message: parse_message(&e, text),
                },
            }
        })
    }

    /// Every invalid value, with its dotted key.
    pub(crate) fn problems(&self, base: &Base, overrides: &Overrides) -> Vec<Invalid> {
        let mut p = Problems::default();
        p.section("link", |p| {
            self.link.validate_in(base, p);
            check_serial_device(p, &self.link.connection);
            // The link checks the folder; a directory by that name is refused here.
            if let Some(t) = &self.link.tlog
                && base.resolve(t).is_dir()
            {
                check_output_file(p, "tlog", base, t);
            }
        });
        p.section("camera", |p| self.camera.validate(p));
        let map_base = overrides.map_base(base);
        p.section("map", |p| self.map.validate_in(base, &map_base, p));
        p.section("output", |p| self.output.validate(p));
        p.section("nav", |p| self.nav.validate(p));
        p.section("fix", |p| self.fix.validate(p));
        p.section("vo", |p| self.vo.validate(p));
        p.section("dtm_nav", |p| self.dtm_nav.validate(p));
        if let Some(f) = &self.frames {
            let frames_base = overrides.frames_base(base);
            p.section("frames", |p| f.validate_in(&frames_base, p));
        }
        p.section("daemon", |p| {
            self.daemon.validate_in(&self.output, p);
            if let Some(f) = &self.daemon.fix_log {
                check_output_file(p, "fix_log", base, f);
            }
            if let Some(f) = &self.daemon.vo_log {
                check_output_file(p, "vo_log", base, f);
            }
        });
        if self.daemon.imu_bias_restore == crate::config::ImuBiasRestore::ScaledImu {
            match self.link.streams.scaled_imu_hz {
                Some(hz) if hz <= 0.0 => p.push(
                    "daemon.imu_bias_restore",
                    "\"scaled_imu\" pairs HIGHRES_IMU with SCALED_IMU, which \
                     link.streams.scaled_imu_hz = 0 does not request: remove that key (SCALED_IMU \
                     at link.streams.imu_hz) or give a rate"
                        .to_string(),
                ),
                // None: the daemon requests it at the IMU rate whatever the autopilot.
                _ => {}
            }
        }
        p.list
    }

    /// Make every path absolute: the file's against its folder (`base`), the overrides' against
    /// the current directory.
    fn resolve_paths(&mut self, base: &Base, overrides: &Overrides) {
        let map_base = overrides.map_base(base);
        self.map.ortho = self.map.ortho.iter().map(|f| base.resolve(f)).collect();
        self.map.file = self.map.file.as_deref().map(|f| map_base.resolve(f));
        self.map.dem = self.map.dem.as_deref().map(|f| base.resolve(f));
        self.link.resolve_paths(base);
        self.daemon.fix_log = self.daemon.fix_log.as_deref().map(|f| base.resolve(f));
        self.daemon.vo_log = self.daemon.vo_log.as_deref().map(|f| base.resolve(f));
        if let Some(f) = &mut self.frames {
            f.resolve_paths(&overrides.frames_base(base));
        }
    }

    /// Open every data file the configuration names (orthophotos, DEM) and check that it is a
    /// usable GeoTIFF with a known CRS, consistent with the others, and read what the camera
    /// source reads before its first frame (a directory's `frames.csv`, a y4m header) as the
    /// source reads it. Slower than [`Config::load`] (it decodes the rasters), so `check-config`
    /// calls it and the daemon does it once at start.
    pub fn check_data(&self, path: &Path) -> Result<(), ConfigError> {
        use visnav_io::geo::geotiff::{crs_equivalent, load_geotiff};
        use visnav_io::geo::geotiff_info::describe_crs;
        let mut p = Problems::default();
        let mut first_crs: Option<Crs> = None;
        p.section("map", |p| {
            if let Some(f) = &self.map.file {
                let opened = if f.is_dir() {
                    visnav_io::map::tiled::TiledIndex::read(f).map(|_| ())
                } else {
                    visnav_io::map::ReferenceMap::open(f).map(|_| ())
                };
                if let Err(e) = opened {
                    p.push("file", e.to_string());
                }
            }
            for (i, f) in self.map.ortho.iter().enumerate() {
                match load_geotiff(f, self.map.crs_override) {
                    Ok(r) => match first_crs {
                        None => first_crs = Some(r.crs()),
                        Some(c) if !crs_equivalent(&c, &r.crs()) => p.push(
                            &format!("ortho[{i}]"),
                            format!(
                                "{}: CRS {} differs from the first orthophoto's {}",
                                f.display(),
                                describe_crs(&r.crs()),
                                describe_crs(&c)
                            ),
                        ),
                        Some(_) => {}
                    },
                    Err(e) => p.push(&format!("ortho[{i}]"), e.to_string()),
                }
            }
            if let Some(f) = &self.map.dem
                && let Err(e) = visnav_io::geo::dem::load_dem(f, self.map.crs_override)
            {
                p.push("dem", e.to_string());
            }
        });
        // The same reading the source does at start, so a frames.csv check-config passes is one
        // run opens (an empty one, a bad header, NaN or repeated times are refused by both).
        if let Some(f) = &self.frames
            && let Err(e) = visnav_io::frames::check_files(f)
        {
            p.section("frames", |p| p.push("path", e.to_string()));
        }
        if p.list.is_empty() {
            Ok(())
        } else {
            Err(ConfigError::Invalid {
                path: path.to_path_buf(),
                problems: p.list,
            })
        }
    }

    /// Everything `visnav run` needs before it starts, and what `visnav check-config` checks: the
    /// file read, parsed and validated ([`Config::load`]), and its data files opened
    /// ([`Config::check_data`]). The one validation both commands share, so `check-config`
    /// passes exactly what `run` starts.
    pub fn load_checked(path: &Path) -> Result<Config, ConfigError> {
        Self::load_checked_with(path, &Overrides::default())
    }

    /// [`Config::load_checked`] with command-line / environment overrides applied before the
    /// validation (`visnav run` and `visnav check-config`).
    pub fn load_checked_with(path: &Path, overrides: &Overrides) -> Result<Config, ConfigError> {
        let cfg = Self::load_with(path, overrides)?;
        cfg.check_data(path)?;
        cfg.check_ports(path, overrides)?;
        Ok(cfg)
    }

    /// [`Config::load_checked_with`] for a configuration already read (`visnav check-config -`
    /// reads it from standard input): `path` names it in messages, and its folder is the one its
    /// relative paths are relative to.
    pub fn from_toml_str_checked(
        text: &str,
        path: &Path,
        overrides: &Overrides,
    ) -> Result<Config, ConfigError> {
        let cfg = Self::from_toml_str_with(text, path, overrides)?;
        cfg.check_data(path)?;
        cfg.check_ports(path, overrides)?;
        Ok(cfg)
    }

    /// Bind and release at once every port `run` will listen on: the connection's (`udpin:`,
    /// `udp:`, `tcpin:`) and the metrics endpoints (`daemon.metrics_listen`,
    /// `link.metrics_listen`). A port another program holds (a MAVProxy, mavlink-router, a
    /// ground station, a visnav already running) is a problem naming the key and the port; the
    /// link would otherwise wait on it for ever. Other bind errors are not reported here: an
    /// address the network assigns later (a radio's interface at boot) may bind at run time.
    pub fn check_ports(&self, path: &Path, overrides: &Overrides) -> Result<(), ConfigError> {
        use visnav_link::config::{ListenError, parse_connection, probe_listen};
        let mut p = Problems::default();
        let busy = |p: &mut Problems, key: &str, r: Result<(), ListenError>| {
            if let Err(e) = r
                && e.in_use()
            {
                p.push(key, e.to_string());
            }
        };
        if let Ok(endpoint) = parse_connection(&self.link.connection) {
            busy(&mut p, "link.connection", endpoint.probe_listen());
        }
        for (key, addr) in [
            ("daemon.metrics_listen", &self.daemon.metrics_listen),
            ("link.metrics_listen", &self.link.metrics_listen),
        ] {
            if let Some(a) = addr {
                busy(&mut p, key, probe_listen("TCP", a.trim()));
            }
        }
        if p.list.is_empty() {
            return Ok(());
        }
        p.list.iter_mut().for_each(|i| overrides.tag(i));
        Err(ConfigError::Invalid {
            path: path.to_path_buf(),
            problems: p.list,
        })
    }

    /// Read, parse and validate a configuration file.
    pub fn load(path: &Path) -> Result<Config, ConfigError> {
        Self::load_with(path, &Overrides::default())
    }

    /// Read a configuration file, apply the overrides, validate.
    pub fn load_with(path: &Path, overrides: &Overrides) -> Result<Config, ConfigError> {
        let text =
            visnav_io::files::read_text(path, visnav_io::files::CONFIG).map_err(|cause| {
                ConfigError::Read {
                    path: path.to_path_buf(),
                    cause,
                }
            })?;
        Self::from_toml_str_with(&text, path, overrides)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn naip() -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../sitl/maps/naip_nd_2009.tif")
    }

    /// A valid configuration with a directory camera source `frames`.
    fn config_with_frames(frames: &Path) -> String {
        format!(
            "[link]\nconnection = \"udpin:127.0.0.1:14999\"\n[camera]\nwidth_px = 640\n\
             height_px = 480\nhfov_deg = 60.0\n[map]\northo = [\"{}\"]\n\
             ground_height_amsl_m = 580.0\n[frames]\nsource = \"directory\"\npath = \"{}\"\n",
            naip().display(),
            frames.display()
        )
    }

    #[test]
    fn a_configuration_naming_a_device_or_too_large_is_refused_not_read() {
        let e = Config::load(Path::new("/dev/zero"))
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("/dev/zero: cannot read: a character device")
                && e.contains("a TOML configuration must be a file"),
            "{e}"
        );
        let d = tempfile::tempdir().unwrap();
        let f = d.path().join("big.toml");
        std::fs::write(&f, "#".repeat(5 << 20)).unwrap();
        let e = Config::load(&f).unwrap_err().to_string();
        assert!(e.contains("big.toml") && e.contains("4 MiB"), "{e}");
    }

    /// A listen port another socket holds is a problem naming the key and the port, for the
    /// connection (every listening form) and the metrics endpoints; free, the check passes.
    #[test]
    fn a_busy_listen_port_is_reported_naming_the_key() {
        let d = tempfile::tempdir().unwrap();
        let udp = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
        let uport = udp.local_addr().unwrap().port();
        let tcp = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let tport = tcp.local_addr().unwrap().port();
        let cfg = d.path().join("c.toml");
        let write = |connection: &str, metrics: &str| {
            let text = format!(
                "[link]\nconnection = \"{connection}\"\n[camera]\nwidth_px = 640\n\
                 height_px = 480\nhfov_deg = 60.0\n[map]\northo = [\"{}\"]\n\
                 ground_height_amsl_m = 580.0\n",
                naip().display()
            );
            let text = if metrics.is_empty() {
                text
            } else {
                format!("{text}[daemon]\nmetrics_listen = \"{metrics}\"\n")
            };
            std::fs::write(&cfg, text).unwrap();
        };
        for connection in [
            format!("udpin:127.0.0.1:{uport}"),
            format!("udp:127.0.0.1:{uport}"),
        ] {
            write(&connection, "");
            let e = Config::load_checked(&cfg).unwrap_err().to_string();
            assert!(
                e.contains(&format!(
                    "link.connection: UDP port {uport} (127.0.0.1:{uport}) is in use"
                )),
                "{e}"
            );
        }
        write(
            &format!("tcpin:127.0.0.1:{tport}"),
            &format!("127.0.0.1:{tport}"),
        );
        let e = Config::load_checked(&cfg).unwrap_err().to_string();
        assert!(
            e.contains(&format!("link.connection: TCP port {tport}")),
            "{e}"
        );
        assert!(
            e.contains(&format!("daemon.metrics_listen: TCP port {tport}")),
            "{e}"
        );
        // Overridden on the command line, the problem says so.
        let o = Overrides::new(Some(format!("udp:127.0.0.1:{uport}")), None, None, &|_| {
            None
        });
        let e = Config::load_checked_with(&cfg, &o).unwrap_err().to_string();
        assert!(
            e.contains("link.connection (from --connection): UDP port"),
            "{e}"
        );
        // A sender has nothing to probe; freed ports pass.
        write(&format!("udpout:127.0.0.1:{uport}"), "");
        Config::load_checked(&cfg).unwrap();
        drop((udp, tcp));
        write(
            &format!("udp:127.0.0.1:{uport}"),
            &format!("127.0.0.1:{tport}"),
        );
        Config::load_checked(&cfg).unwrap();
    }

    /// check-config and run share `load_checked`: the frames.csv is read there as the source
    /// reads it, so a file the source refuses fails the check, naming `frames.path` and the line.
    #[test]
    fn the_check_reads_frames_csv_as_the_source_does() {
        let d = tempfile::tempdir().unwrap();
        let frames = d.path().join("frames");
        std::fs::create_dir(&frames).unwrap();
        let cfg = d.path().join("c.toml");
        std::fs::write(&cfg, config_with_frames(&frames)).unwrap();
        let csv = frames.join("frames.csv");
        for (text, want) in [
            ("", ":1: empty"),
            ("name,t_s\na.png,0\n", "header \"name,t_s\""),
            ("file,t_s\na.png,NaN\n", ":2: t_s \"NaN\""),
            ("file,t_s\na.png,inf\n", ":2: t_s \"inf\""),
            (
                "file,t_s\na.png,2\nb.png,1\n",
                ":3: time \"1\" is not after",
            ),
            (
                "file,t_boot_us\na.png,7\nb.png,7\n",
                ":3: time \"7\" is not after",
            ),
            ("file,t_boot_us\na.png,-1\n", ":2: t_boot_us \"-1\""),
            ("file,t_boot_us\na.png,2.5\n", ":2: t_boot_us \"2.5\""),
        ] {
            std::fs::write(&csv, text).unwrap();
            // Parsed and validated alone it passes: the file is only read by the data check.
            assert!(Config::load(&cfg).is_ok(), "{text:?}");
            let e = Config::load_checked(&cfg).unwrap_err().to_string();
            assert!(
                e.contains("frames.path: ") && e.contains("frames.csv") && e.contains(want),
                "{text:?}: {e}"
            );
        }
        std::fs::write(&csv, "\u{feff}file,t_boot_us\na.png,7\nb.png,8\n").unwrap();
        Config::load_checked(&cfg).unwrap();
    }
}
