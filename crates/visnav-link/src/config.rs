//! `[link]` and `[output]` configuration sections: the MAVLink connection and the injection of the
//! navigation solution; validated with the [`Validate`]/[`Problems`] machinery of
//! `visnav_core::validate` (dotted keys, every problem at once).

use std::net::SocketAddr;
use std::path::PathBuf;

use serde::Deserialize;

use visnav_core::validate::{Base, Problems, Validate};

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
    /// Only talk to this autopilot system id; absent = lock onto the first autopilot heard (a
    /// vehicle's HEARTBEAT from `autopilot_component_id`; see `session`, "Lock-on"). Set it on an
    /// aircraft: it is the only protection against a second vehicle on the same network.
    #[serde(default)]
    pub autopilot_system_id: Option<u8>,
    /// The autopilot's component id (default 1 = MAV_COMP_ID_AUTOPILOT1, what ArduPilot and
    /// PX4 use). Gimbals, cameras and other components of the same system are never locked onto.
    #[serde(default = "default_autopilot_component_id")]
    pub autopilot_component_id: u8,
    /// Our HEARTBEAT rate.
    #[serde(default = "default_heartbeat_hz")]
    pub heartbeat_hz: f64,
    /// The autopilot is declared lost after this long without its HEARTBEAT.
    #[serde(default = "default_heartbeat_timeout_s")]
    pub heartbeat_timeout_s: f64,
    /// First delay before reconnecting a failed connection; doubles up to `reconnect_max_s`.
    #[serde(default = "default_reconnect_min_s")]
    pub reconnect_min_s: f64,
    /// Longest delay between reconnection attempts.
    #[serde(default = "default_reconnect_max_s")]
    pub reconnect_max_s: f64,
    /// TIMESYNC request rate (clock mapping between companion and autopilot).
    #[serde(default = "default_timesync_hz")]
    pub timesync_hz: f64,
    /// TIMESYNC round trips longer than this are not used for the clock mapping.
    #[serde(default = "default_timesync_max_rtt_ms")]
    pub timesync_max_rtt_ms: f64,
    /// Telemetry rates requested with MAV_CMD_SET_MESSAGE_INTERVAL.
    #[serde(default)]
    pub streams: StreamRates,
    /// MAVLink 2 message signing (absent = unsigned).
    #[serde(default)]
    pub signing: Option<SigningSettings>,
    /// Record all traffic (both directions) to this .tlog file (QGroundControl / MAVExplorer
    /// format). Relative to the config file's folder unless absolute. A `{t}` in the name is
    /// replaced by the start time (Unix seconds).
    #[serde(default)]
    pub tlog: Option<PathBuf>,
    /// Serve the link's Prometheus metrics alone on this address (e.g. `127.0.0.1:9108`); absent =
    /// off. (`daemon.metrics_listen` serves them with the daemon's.)
    #[serde(default)]
    pub metrics_listen: Option<String>,
}

/// `[link.streams]`: requested telemetry rates in Hz (0 = do not request).
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct StreamRates {
    /// ATTITUDE.
    #[serde(default = "default_attitude_hz")]
    pub attitude_hz: f64,
    /// HIGHRES_IMU (falls back to SCALED_IMU and RAW_IMU when it does not arrive).
    #[serde(default = "default_imu_hz")]
    pub imu_hz: f64,
    /// SCALED_IMU besides HIGHRES_IMU, what `daemon.imu_bias_restore` pairs HIGHRES_IMU with
    /// (PX4). Absent (automatic): at `imu_hz` when the autopilot is PX4 or
    /// `daemon.imu_bias_restore = "scaled_imu"`, else only as HIGHRES_IMU's fallback; 0: never
    /// besides HIGHRES_IMU.
    #[serde(default)]
    pub scaled_imu_hz: Option<f64>,
    /// GLOBAL_POSITION_INT.
    #[serde(default = "default_position_hz")]
    pub global_position_hz: f64,
    /// GPS_RAW_INT.
    #[serde(default = "default_gps_raw_hz")]
    pub gps_raw_hz: f64,
    /// SYSTEM_TIME.
    #[serde(default = "default_system_time_hz")]
    pub system_time_hz: f64,
    /// SCALED_PRESSURE and ALTITUDE.
    #[serde(default = "default_pressure_hz")]
    pub pressure_hz: f64,
    /// A stream counts as arriving when its measured rate is at least this fraction of the
    /// requested rate.
    #[serde(default = "default_rate_tolerance")]
    pub min_rate_fraction: f64,
}

impl Default for StreamRates {
    fn default() -> Self {
        Self {
            attitude_hz: default_attitude_hz(),
            imu_hz: default_imu_hz(),
            scaled_imu_hz: None,
            global_position_hz: default_position_hz(),
            gps_raw_hz: default_gps_raw_hz(),
            system_time_hz: default_system_time_hz(),
            pressure_hz: default_pressure_hz(),
            min_rate_fraction: default_rate_tolerance(),
        }
    }
}

/// `[link.signing]`: MAVLink 2 signing.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SigningSettings {
    /// Secret key file: 32 raw bytes, or 64 hexadecimal characters (whitespace ignored).
    /// Relative to the config file's folder unless absolute.
    pub key_file: PathBuf,
    /// Sign every outgoing message.
    #[serde(default = "default_true")]
    pub sign_outgoing: bool,
    /// Drop incoming messages that are not signed with the key (default true: configuring a key
    /// and still accepting unsigned traffic would be signing in name only; set false only while
    /// migrating an autopilot to signing).
    #[serde(default = "default_true")]
    pub reject_unsigned: bool,
    /// Signature link id of this connection.
    #[serde(default)]
    pub link_id: u8,
}

fn default_component_id() -> u8 {
    197
}
fn default_autopilot_component_id() -> u8 {
    1
}
fn default_heartbeat_hz() -> f64 {
    1.0
}
fn default_heartbeat_timeout_s() -> f64 {
    3.0
}
fn default_reconnect_min_s() -> f64 {
    0.5
}
fn default_reconnect_max_s() -> f64 {
    10.0
}
fn default_timesync_hz() -> f64 {
    2.0
}
fn default_timesync_max_rtt_ms() -> f64 {
    50.0
}
fn default_attitude_hz() -> f64 {
    50.0
}
fn default_imu_hz() -> f64 {
    100.0
}
fn default_position_hz() -> f64 {
    10.0
}
fn default_gps_raw_hz() -> f64 {
    5.0
}
fn default_system_time_hz() -> f64 {
    1.0
}
fn default_pressure_hz() -> f64 {
    10.0
}
fn default_rate_tolerance() -> f64 {
    0.7
}
fn default_true() -> bool {
    true
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
    /// GLOBAL_POSITION_SENSOR (id 296; PX4's auxiliary global position).
    GlobalPositionSensor,
}

/// What to send while the filter reports `Lost`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum OnLost {
    /// Send nothing: the autopilot's own GPS/EV timeout failsafe takes over.
    #[default]
    Stop,
    /// Keep sending GPS_INPUT with fix_type NO_FIX (other modes stop), so ArduPilot reports the
    /// loss at once instead of after its timeout.
    NoFix,
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
    /// GPS_INPUT.satellites_visible reported with a healthy solution (ArduPilot's arming checks
    /// want at least 6).
    #[serde(default = "default_satellites")]
    pub gps_satellites: u8,
    /// Send the yaw in GPS_INPUT (needs EK3_SRC1_YAW = 2 "GPS" on ArduPilot).
    #[serde(default)]
    pub gps_yaw: bool,
    /// Estimates older than this (at send time) are not sent.
    #[serde(default = "default_max_age_s")]
    pub max_age_s: f64,
    /// Behaviour while the filter reports the solution lost.
    #[serde(default)]
    pub on_lost: OnLost,
    /// Send SET_GPS_GLOBAL_ORIGIN from the first healthy estimate when the autopilot has not
    /// reported an EKF origin (needed by VISION_POSITION_ESTIMATE / ODOMETRY without GPS).
    #[serde(default = "default_true")]
    pub set_origin: bool,
    /// GLOBAL_POSITION_SENSOR.id.
    #[serde(default)]
    pub sensor_id: u8,
}

fn default_modes() -> Vec<OutputMode> {
    vec![OutputMode::GpsInput]
}
fn default_rate_hz() -> f64 {
    5.0
}
fn default_satellites() -> u8 {
    10
}
fn default_max_age_s() -> f64 {
    0.5
}

impl Default for OutputConfig {
    fn default() -> Self {
        Self {
            modes: default_modes(),
            rate_hz: default_rate_hz(),
            gps_id: 0,
            gps_satellites: default_satellites(),
            gps_yaw: false,
            max_age_s: default_max_age_s(),
            on_lost: OnLost::Stop,
            set_origin: true,
            sensor_id: 0,
        }
    }
}

impl LinkConfig {
    /// A configuration with every default and the given connection string.
    pub fn new(connection: &str) -> Self {
        Self {
            connection: connection.to_string(),
            system_id: None,
            component_id: default_component_id(),
            autopilot_system_id: None,
            autopilot_component_id: default_autopilot_component_id(),
            heartbeat_hz: default_heartbeat_hz(),
            heartbeat_timeout_s: default_heartbeat_timeout_s(),
            reconnect_min_s: default_reconnect_min_s(),
            reconnect_max_s: default_reconnect_max_s(),
            timesync_hz: default_timesync_hz(),
            timesync_max_rtt_ms: default_timesync_max_rtt_ms(),
            streams: StreamRates::default(),
            signing: None,
            tlog: None,
            metrics_listen: None,
        }
    }

    /// Validate, resolving relative file names against `base` (the config file's folder).
    pub fn validate_in(&self, base: &Base, p: &mut Problems) {
        self.validate(p);
        if let Some(s) = &self.signing {
            let why = base
                .file_problem(
                    &s.key_file,
                    std::fs::metadata(base.resolve(&s.key_file)).map(|m| m.is_file()),
                )
                .or_else(|| {
                    crate::signing::load_key(&base.resolve(&s.key_file))
                        .err()
                        .map(|e| e.to_string())
                });
            if let Some(why) = why {
                p.push("signing.key_file", why);
            }
        }
        if let Some(t) = &self.tlog {
            let f = base.resolve(t);
            let dir = f.parent().filter(|d| !d.as_os_str().is_empty());
            if let Some(d) = dir
                && !d.is_dir()
            {
                p.push(
                    "tlog",
                    base.problem(t, "is in a folder that does not exist"),
                );
            }
        }
    }

    /// Make the file names absolute against `base` (the config file's folder).
    pub fn resolve_paths(&mut self, base: &Base) {
        if let Some(s) = &mut self.signing {
            s.key_file = base.resolve(&s.key_file);
        }
        if let Some(t) = &mut self.tlog {
            *t = base.resolve(t);
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
        p.range("heartbeat_timeout_s", self.heartbeat_timeout_s, 1.0, 60.0);
        p.range("reconnect_min_s", self.reconnect_min_s, 0.05, 60.0);
        p.range("reconnect_max_s", self.reconnect_max_s, 0.05, 600.0);
        if self.reconnect_max_s < self.reconnect_min_s {
            p.push(
                "reconnect_max_s",
                format!(
                    "{} is less than reconnect_min_s = {}",
                    self.reconnect_max_s, self.reconnect_min_s
                ),
            );
        }
        p.range("timesync_hz", self.timesync_hz, 0.1, 20.0);
        p.range("timesync_max_rtt_ms", self.timesync_max_rtt_ms, 1.0, 2000.0);
        p.section("streams", |p| self.streams.validate(p));
        if let Some(m) = &self.metrics_listen
            && m.parse::<SocketAddr>().is_err()
        {
            p.push(
                "metrics_listen",
                format!("\"{m}\" is not an IP:PORT socket address (e.g. 127.0.0.1:9108)"),
            );
        }
    }
}

impl Validate for StreamRates {
    fn validate(&self, p: &mut Problems) {
        for (k, v) in [
            ("attitude_hz", self.attitude_hz),
            ("imu_hz", self.imu_hz),
            ("scaled_imu_hz", self.scaled_imu_hz.unwrap_or(0.0)),
            ("global_position_hz", self.global_position_hz),
            ("gps_raw_hz", self.gps_raw_hz),
            ("system_time_hz", self.system_time_hz),
            ("pressure_hz", self.pressure_hz),
        ] {
            p.range(k, v, 0.0, 400.0);
        }
        p.range("min_rate_fraction", self.min_rate_fraction, 0.1, 1.0);
    }
}

/// The connection schemes `[link] connection` accepts.
const SCHEMES: &str = "udpin, udpout, udpbcast, tcpin, tcpout, serial";

/// What is wrong with a connection string ([`check_connection`]).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum BadConnection {
    #[error("expected SCHEME:ADDRESS with SCHEME one of {SCHEMES}")]
    NoScheme,
    #[error("unknown scheme \"{0}\"; expected one of {SCHEMES}")]
    UnknownScheme(String),
    #[error("expected HOST:PORT after the scheme")]
    NoPort,
    #[error("the host is empty (use 0.0.0.0 to listen on every interface)")]
    EmptyHost,
    #[error("port \"{0}\" is not a number in 1..=65535")]
    BadPort(String),
    #[error("expected serial:DEVICE:BAUD")]
    NoBaud,
    #[error("the serial device is empty")]
    EmptyDevice,
    #[error("baud rate \"{0}\" is not a number in 1200..=12000000")]
    BadBaud(String),
    /// The mavlink crate's own parser refused it (its message).
    #[error("{0}")]
    Mavlink(String),
}

/// Check a mavlink connection string beyond what the mavlink crate parses: a known scheme, and for
/// network schemes a host and a numeric port; for serial a device and a numeric baud rate.
pub fn check_connection(s: &str) -> Result<(), BadConnection> {
    let Some((scheme, rest)) = s.split_once(':') else {
        return Err(BadConnection::NoScheme);
    };
    match scheme {
        "udpin" | "udpout" | "udpbcast" | "tcpin" | "tcpout" => {
            let (host, port) = rest.rsplit_once(':').ok_or(BadConnection::NoPort)?;
            if host.is_empty() {
                return Err(BadConnection::EmptyHost);
            }
            match port.parse::<u16>() {
                Ok(0) | Err(_) => return Err(BadConnection::BadPort(port.to_string())),
                Ok(_) => {}
            }
        }
        "serial" => {
            let (dev, baud) = rest.rsplit_once(':').ok_or(BadConnection::NoBaud)?;
            if dev.is_empty() {
                return Err(BadConnection::EmptyDevice);
            }
            match baud.parse::<u32>() {
                Ok(b) if (1200..=12_000_000).contains(&b) => {}
                _ => return Err(BadConnection::BadBaud(baud.to_string())),
            }
        }
        other => return Err(BadConnection::UnknownScheme(other.to_string())),
    }
    mavlink::ConnectionAddress::parse_address(s)
        .map(|_| ())
        .map_err(|e| BadConnection::Mavlink(e.to_string()))
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
        let needs_5hz = self
            .modes
            .iter()
            .any(|m| matches!(m, OutputMode::Odometry | OutputMode::VisionPositionEstimate));
        if needs_5hz && self.rate_hz.is_finite() && self.rate_hz < 5.0 {
            p.push(
                "rate_hz",
                format!(
                    "{} Hz is too slow for external vision (PX4 needs at least 5 Hz)",
                    self.rate_hz
                ),
            );
        }
        if self.gps_id > 1 {
            p.push(
                "gps_id",
                format!(
                    "{} is not a GPS instance of ArduPilot (0 or 1)",
                    self.gps_id
                ),
            );
        }
        if self.gps_satellites > 60 {
            p.push(
                "gps_satellites",
                format!(
                    "{} is not a plausible satellite count (0..=60)",
                    self.gps_satellites
                ),
            );
        }
        p.range("max_age_s", self.max_age_s, 0.01, 5.0);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn problems(c: &impl Validate) -> Vec<String> {
        let mut p = Problems::default();
        c.validate(&mut p);
        p.list.iter().map(|i| i.to_string()).collect()
    }

    #[test]
    fn defaults_are_valid() {
        assert!(problems(&LinkConfig::new("udpin:0.0.0.0:14550")).is_empty());
        assert!(problems(&OutputConfig::default()).is_empty());
    }

    #[test]
    fn bad_values_name_their_keys() {
        let mut c = LinkConfig::new("tcpout:localhost:0");
        c.reconnect_min_s = 5.0;
        c.reconnect_max_s = 1.0;
        c.streams.imu_hz = -1.0;
        c.metrics_listen = Some("localhost".into());
        let p = problems(&c).join("\n");
        for k in [
            "connection",
            "reconnect_max_s",
            "streams.imu_hz",
            "metrics_listen",
        ] {
            assert!(p.contains(k), "{k} missing in {p}");
        }
        let o = OutputConfig {
            modes: vec![OutputMode::Odometry],
            rate_hz: 2.0,
            ..OutputConfig::default()
        };
        let p = problems(&o).join("\n");
        assert!(p.contains("rate_hz") && p.contains("5 Hz"), "{p}");
    }

    #[test]
    fn files_are_checked_against_the_config_folder() {
        let d = tempfile::tempdir().unwrap();
        std::fs::write(d.path().join("key.hex"), "zz").unwrap();
        let text = "connection = \"udpin:0.0.0.0:14550\"\ntlog = \"nofolder/x.tlog\"\n\
                    [signing]\nkey_file = \"key.hex\"\nreject_unsigned = true\n";
        let mut c: LinkConfig = toml::from_str(text).unwrap();
        let mut p = Problems::default();
        c.validate_in(&Base::config_folder(d.path()), &mut p);
        let s: Vec<String> = p.list.iter().map(|i| i.to_string()).collect();
        assert!(
            s.iter()
                .any(|m| m.starts_with("signing.key_file") && m.contains("key.hex")),
            "{s:?}"
        );
        assert!(
            s.iter()
                .any(|m| m.starts_with("tlog") && m.contains("nofolder")),
            "{s:?}"
        );
        // A good key and folder pass, and paths become absolute.
        std::fs::write(d.path().join("key.hex"), "ab".repeat(32)).unwrap();
        std::fs::create_dir(d.path().join("nofolder")).unwrap();
        let mut p = Problems::default();
        c.validate_in(&Base::config_folder(d.path()), &mut p);
        assert!(p.list.is_empty(), "{:?}", p.list);
        c.resolve_paths(&Base::config_folder(d.path()));
        assert!(c.tlog.unwrap().is_absolute());
        assert!(c.signing.unwrap().key_file.is_absolute());
        // Unknown keys in the new sections are rejected.
        assert!(
            toml::from_str::<LinkConfig>("connection = \"udpin:0.0.0.0:1\"\n[streams]\nimu = 5\n")
                .is_err()
        );
    }

    #[test]
    fn connection_strings() {
        for ok in [
            "udpin:0.0.0.0:14550",
            "udpout:127.0.0.1:14550",
            "tcpin:0.0.0.0:5760",
            "tcpout:127.0.0.1:5760",
            "serial:/dev/ttyAMA0:921600",
        ] {
            assert!(check_connection(ok).is_ok(), "{ok}");
        }
        for bad in [
            "udp:1.2.3.4:5",
            "udpin:0.0.0.0",
            "udpin::14550",
            "serial:/dev/x:12",
            "nothing",
        ] {
            assert!(check_connection(bad).is_err(), "{bad}");
        }
    }
}
