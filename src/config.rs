//! TOML configuration: schema, loading and validation.
//!
//! Every section is a serde struct with `deny_unknown_fields`, so a misspelt key is an error that
//! names the key. After parsing, every value is validated through [`Validate`]: each section reports
//! the dotted key path (`camera.fx_px`), the offending value and the reason, and all problems are
//! reported at once, prefixed with the file name.

use std::fmt;
use std::path::{Path, PathBuf};

use serde::Deserialize;

use crate::camera::CameraConfig;
use crate::geo::Crs;
use crate::nav::config::NavConfig;

/// One invalid configuration value.
#[derive(Debug, Clone, PartialEq)]
pub struct Invalid {
    /// Dotted key path, e.g. `camera.distortion.k1`.
    pub key: String,
    /// Why the value is rejected (include the value and the accepted range).
    pub reason: String,
}

impl fmt::Display for Invalid {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}: {}", self.key, self.reason)
    }
}

/// Collects validation problems under a key prefix.
#[derive(Debug, Default)]
pub struct Problems {
    prefix: Vec<String>,
    /// Problems found so far.
    pub list: Vec<Invalid>,
}

impl Problems {
    /// Run `f` with `name` appended to the key prefix (for nested sections).
    pub fn section(&mut self, name: &str, f: impl FnOnce(&mut Problems)) {
        self.prefix.push(name.to_string());
        f(self);
        self.prefix.pop();
    }

    /// Record that `key` (relative to the current section) is invalid.
    pub fn push(&mut self, key: &str, reason: impl Into<String>) {
        let mut full = self.prefix.join(".");
        if !key.is_empty() {
            if !full.is_empty() {
                full.push('.');
            }
            full.push_str(key);
        }
        self.list.push(Invalid {
            key: full,
            reason: reason.into(),
        });
    }

    /// Require `lo <= v <= hi` and finite.
    pub fn range(&mut self, key: &str, v: f64, lo: f64, hi: f64) {
        if !v.is_finite() || v < lo || v > hi {
            self.push(
                key,
                format!("{v} is outside the accepted range [{lo}, {hi}]"),
            );
        }
    }

    /// Require a finite value strictly greater than zero.
    pub fn positive(&mut self, key: &str, v: f64) {
        if !v.is_finite() || v <= 0.0 {
            self.push(key, format!("{v} must be a finite number greater than 0"));
        }
    }

    /// Require a finite value.
    pub fn finite(&mut self, key: &str, v: f64) {
        if !v.is_finite() {
            self.push(key, format!("{v} must be a finite number"));
        }
    }
}

/// A configuration section that can check its own values.
pub trait Validate {
    /// Push every invalid value into `p` (keys relative to this section).
    fn validate(&self, p: &mut Problems);
}

/// Why a configuration file could not be used. Every variant names the file.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("{path}: cannot read: {source}")]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// TOML syntax, a wrong type or an unknown key (the message names the key, line and column).
    #[error("{path}: {message}")]
    Parse { path: PathBuf, message: String },
    /// Parsed, but values are out of range, inconsistent or name missing files.
    #[error("{path}: {} invalid value(s):\n  {}", problems.len(), problems.iter().map(|p| p.to_string()).collect::<Vec<_>>().join("\n  "))]
    Invalid {
        path: PathBuf,
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
}

/// `[link]`: the MAVLink connection.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LinkConfig {
    /// mavlink connection string: `udpin:ADDR:PORT`, `udpout:HOST:PORT`, `tcpin:ADDR:PORT`,
    /// `tcpout:HOST:PORT` or `serial:DEVICE:BAUD`.
    pub connection: String,
    /// Our MAVLink system id; absent = adopt the autopilot's (the MAVLink convention for a
    /// companion computer).
    #[serde(default)]
    pub system_id: Option<u8>,
    /// Our MAVLink component id (default 197 = MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY).
    #[serde(default = "default_component_id")]
    pub component_id: u8,
    /// Only talk to this autopilot system id; absent = lock onto the first autopilot heard.
    #[serde(default)]
    pub autopilot_system_id: Option<u8>,
    /// Our HEARTBEAT rate.
    #[serde(default = "default_heartbeat_hz")]
    pub heartbeat_hz: f64,
}

fn default_component_id() -> u8 {
    197
}
fn default_heartbeat_hz() -> f64 {
    1.0
}

/// `[map]`: the georeferenced imagery and terrain the fixes are computed against.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MapConfig {
    /// Orthophoto GeoTIFF file(s), relative to the config file's folder unless absolute.
    pub ortho: Vec<PathBuf>,
    /// Elevation model GeoTIFF (heights AMSL). Exactly one of `dem` and `ground_height_amsl_m`.
    #[serde(default)]
    pub dem: Option<PathBuf>,
    /// Constant ground height AMSL for flat areas without a DEM.
    #[serde(default)]
    pub ground_height_amsl_m: Option<f64>,
    /// CRS to assume for rasters whose GeoKeys are missing or not understood.
    #[serde(default)]
    pub crs_override: Option<Crs>,
}

/// One way of injecting the navigation solution into the autopilot.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum OutputMode {
    /// GPS_INPUT (ArduPilot GPS1_TYPE = 14).
    GpsInput,
    /// VISION_POSITION_ESTIMATE (ArduPilot ExternalNav, PX4 external vision).
    VisionPositionEstimate,
    /// ODOMETRY (MAV_FRAME_LOCAL_FRD / MAV_FRAME_BODY_FRD).
    Odometry,
}

/// `[output]`: injection into the autopilot.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OutputConfig {
    /// One or several injection modes.
    #[serde(default = "default_modes")]
    pub modes: Vec<OutputMode>,
    /// Injection rate (PX4 external vision needs at least 5 Hz).
    #[serde(default = "default_rate_hz")]
    pub rate_hz: f64,
    /// GPS_INPUT.gps_id: must equal the autopilot's GPS instance (ArduPilot drops any other).
    #[serde(default)]
    pub gps_id: u8,
}

fn default_modes() -> Vec<OutputMode> {
    vec![OutputMode::GpsInput]
}
fn default_rate_hz() -> f64 {
    5.0
}

impl Default for OutputConfig {
    fn default() -> Self {
        Self {
            modes: default_modes(),
            rate_hz: default_rate_hz(),
            gps_id: 0,
        }
    }
}

impl Validate for LinkConfig {
    fn validate(&self, p: &mut Problems) {
        if let Err(reason) = check_connection(&self.connection) {
            p.push("connection", format!("\"{}\": {reason}", self.connection));
        }
        if self.system_id == Some(0) {
            p.push(
                "system_id",
                "0 is the broadcast id; use 1..=255 or leave it out",
            );
        }
        if self.component_id == 0 {
            p.push(
                "component_id",
                "0 is the broadcast id; use 1..=255 (default 197)",
            );
        }
        if self.autopilot_system_id == Some(0) {
            p.push(
                "autopilot_system_id",
                "0 is the broadcast id; use 1..=255 or leave it out",
            );
        }
        p.range("heartbeat_hz", self.heartbeat_hz, 0.2, 10.0);
    }
}

/// Check a mavlink connection string beyond what the mavlink crate parses: a known scheme, and for
/// network schemes a host and a numeric port; for serial a device and a numeric baud rate.
pub fn check_connection(s: &str) -> Result<(), String> {
    const SCHEMES: &str = "udpin, udpout, udpbcast, tcpin, tcpout, serial";
    let Some((scheme, rest)) = s.split_once(':') else {
        return Err(format!(
            "expected SCHEME:ADDRESS with SCHEME one of {SCHEMES}"
        ));
    };
    match scheme {
        "udpin" | "udpout" | "udpbcast" | "tcpin" | "tcpout" => {
            let Some((host, port)) = rest.rsplit_once(':') else {
                return Err("expected HOST:PORT after the scheme".into());
            };
            if host.is_empty() {
                return Err("the host is empty (use 0.0.0.0 to listen on every interface)".into());
            }
            match port.parse::<u16>() {
                Ok(0) | Err(_) => Err(format!("port \"{port}\" is not a number in 1..=65535")),
                Ok(_) => Ok(()),
            }
        }
        "serial" => {
            let Some((dev, baud)) = rest.rsplit_once(':') else {
                return Err("expected serial:DEVICE:BAUD".into());
            };
            if dev.is_empty() {
                return Err("the serial device is empty".into());
            }
            match baud.parse::<u32>() {
                Ok(b) if (1200..=12_000_000).contains(&b) => Ok(()),
                _ => Err(format!(
                    "baud rate \"{baud}\" is not a number in 1200..=12000000"
                )),
            }
        }
        other => Err(format!(
            "unknown scheme \"{other}\"; expected one of {SCHEMES}"
        )),
    }
    .and_then(|()| {
        mavlink::ConnectionAddress::parse_address(s)
            .map(|_| ())
            .map_err(|e| e.to_string())
    })
}

impl MapConfig {
    fn validate_in(&self, base: &Path, p: &mut Problems) {
        if self.ortho.is_empty() {
            p.push("ortho", "at least one orthophoto GeoTIFF is needed");
        }
        for (i, f) in self.ortho.iter().enumerate() {
            check_file(p, &format!("ortho[{i}]"), base, f);
        }
        match (&self.dem, self.ground_height_amsl_m) {
            (Some(_), Some(_)) => p.push(
                "dem",
                "give either dem or ground_height_amsl_m, not both",
            ),
            (None, None) => p.push(
                "dem",
                "missing: give a DEM GeoTIFF (dem) or a constant ground height (ground_height_amsl_m)",
            ),
            (Some(f), None) => check_file(p, "dem", base, f),
            (None, Some(h)) => p.range("ground_height_amsl_m", h, -500.0, 9000.0),
        }
        if let Some(crs) = &self.crs_override {
            crs.validate_in("crs_override", p);
        }
    }
}

impl Crs {
    fn validate_in(&self, key: &str, p: &mut Problems) {
        match *self {
            Crs::Geographic | Crs::WebMercator => {}
            Crs::Utm { zone, .. } => {
                if !(1..=60).contains(&zone) {
                    p.push(
                        &format!("{key}.zone"),
                        format!("{zone} is not a UTM zone (1..=60)"),
                    );
                }
            }
            Crs::TransverseMercator {
                lat0_deg,
                lon0_deg,
                k0,
                false_easting_m,
                false_northing_m,
            } => {
                p.range(&format!("{key}.lat0_deg"), lat0_deg, -90.0, 90.0);
                p.range(&format!("{key}.lon0_deg"), lon0_deg, -180.0, 180.0);
                p.range(&format!("{key}.k0"), k0, 0.9, 1.1);
                p.range(
                    &format!("{key}.false_easting_m"),
                    false_easting_m,
                    -1e8,
                    1e8,
                );
                p.range(
                    &format!("{key}.false_northing_m"),
                    false_northing_m,
                    -1e8,
                    1e8,
                );
            }
        }
    }
}

fn check_file(p: &mut Problems, key: &str, base: &Path, f: &Path) {
    let full = resolve(base, f);
    match std::fs::metadata(&full) {
        Ok(m) if m.is_file() => {}
        Ok(_) => p.push(key, format!("{} is not a regular file", full.display())),
        Err(e) => p.push(key, format!("{}: {e}", full.display())),
    }
}

/// Resolve `f` against `base` (the config file's folder) unless it is absolute.
pub fn resolve(base: &Path, f: &Path) -> PathBuf {
    if f.is_absolute() {
        f.to_path_buf()
    } else {
        base.join(f)
    }
}

impl Validate for OutputConfig {
    fn validate(&self, p: &mut Problems) {
        if self.modes.is_empty() {
            p.push("modes", "at least one output mode is needed");
        }
        let mut seen = Vec::new();
        for m in &self.modes {
            if seen.contains(m) {
                p.push("modes", format!("{m:?} is listed twice"));
            }
            seen.push(*m);
        }
        p.range("rate_hz", self.rate_hz, 1.0, 50.0);
        if self.gps_id > 1 {
            p.push(
                "gps_id",
                format!(
                    "{} is not a GPS instance of ArduPilot (0 or 1)",
                    self.gps_id
                ),
            );
        }
    }
}

impl Config {
    /// Parse TOML text. `path` is used in messages and `base` (its folder) to resolve relative paths.
    pub fn from_toml_str(text: &str, path: &Path) -> Result<Config, ConfigError> {
        let mut cfg: Config = toml::from_str(text).map_err(|e| ConfigError::Parse {
            path: path.to_path_buf(),
            message: e.to_string().trim_end().to_string(),
        })?;
        let base = path.parent().unwrap_or(Path::new("."));
        let mut p = Problems::default();
        p.section("link", |p| cfg.link.validate(p));
        p.section("camera", |p| cfg.camera.validate(p));
        p.section("map", |p| cfg.map.validate_in(base, p));
        p.section("output", |p| cfg.output.validate(p));
        p.section("nav", |p| cfg.nav.validate(p));
        if !p.list.is_empty() {
            return Err(ConfigError::Invalid {
                path: path.to_path_buf(),
                problems: p.list,
            });
        }
        cfg.map.ortho = cfg.map.ortho.iter().map(|f| resolve(base, f)).collect();
        cfg.map.dem = cfg.map.dem.as_deref().map(|f| resolve(base, f));
        Ok(cfg)
    }

    /// Open every data file the configuration names (orthophotos, DEM) and check that it is a
    /// usable GeoTIFF with a known CRS, consistent with the others. Slower than [`Config::load`]
    /// (it decodes the rasters), so `check-config` calls it and the daemon does it once at start.
    pub fn check_data(&self, path: &Path) -> Result<(), ConfigError> {
        use crate::geo::dem::Dem;
        use crate::geo::geotiff::{crs_equivalent, load_geotiff};
        let mut p = Problems::default();
        let mut first_crs: Option<Crs> = None;
        p.section("map", |p| {
            for (i, f) in self.map.ortho.iter().enumerate() {
                match load_geotiff(f, self.map.crs_override) {
                    Ok(r) => match first_crs {
                        None => first_crs = Some(r.crs()),
                        Some(c) if !crs_equivalent(&c, &r.crs()) => p.push(
                            &format!("ortho[{i}]"),
                            format!(
                                "{}: CRS {:?} differs from the first orthophoto's {:?}",
                                f.display(),
                                r.crs(),
                                c
                            ),
                        ),
                        Some(_) => {}
                    },
                    Err(e) => p.push(&format!("ortho[{i}]"), e.to_string()),
                }
            }
            if let Some(f) = &self.map.dem
                && let Err(e) = Dem::load_geotiff(f, self.map.crs_override)
            {
                p.push("dem", e.to_string());
            }
        });
        if p.list.is_empty() {
            Ok(())
        } else {
            Err(ConfigError::Invalid {
                path: path.to_path_buf(),
                problems: p.list,
            })
        }
    }

    /// Read, parse and validate a configuration file.
    pub fn load(path: &Path) -> Result<Config, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        Self::from_toml_str(&text, path)
    }
}
