//! `[link]` and `[output]` configuration sections: the MAVLink connection and the injection of the
//! navigation solution; validated with the [`Validate`]/[`Problems`] machinery of
//! `visnav_core::validate` (dotted keys, every problem at once).

use std::net::SocketAddr;
use std::path::PathBuf;

use serde::Deserialize;

use visnav_core::text::quote;
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

/// `gps_input`, `vision_position_estimate`, `odometry`, `global_position_sensor` (as written in
/// `[output] modes`).
impl std::fmt::Display for OutputMode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            OutputMode::GpsInput => "gps_input",
            OutputMode::VisionPositionEstimate => "vision_position_estimate",
            OutputMode::Odometry => "odometry",
            OutputMode::GlobalPositionSensor => "global_position_sensor",
        })
    }
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
            p.push(
                "connection",
                format!("{}: {reason}", quote(&self.connection)),
            );
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
                format!(
                    "{} is not an IP:PORT socket address (e.g. 127.0.0.1:9108)",
                    quote(m)
                ),
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

/// The connection schemes `[link] connection` accepts (besides a bare serial device).
const SCHEMES: &str = "udpin, udpout, udpbcast, udp, tcpin, tcpout, tcp, serial";

/// The baud rate of a serial connection written without one (`/dev/ttyACM0`,
/// `serial:/dev/ttyACM0`): pymavlink's (`mavlink_connection(device, baud=115200)`), and the
/// lowest standard rate that carries visnav's default telemetry requests (about 8 kB/s,
/// docs/autopilot-setup.md). MAVProxy's `--baudrate` default, 57600, would not carry them. A USB
/// CDC-ACM port (a flight controller's USB, `/dev/ttyACM*`) ignores the rate.
pub const DEFAULT_SERIAL_BAUD: u32 = 115_200;

/// The baud rates accepted: 1200 is the slowest any telemetry radio or UART offers; 12 Mbaud is
/// beyond every flight controller UART (the fastest run 2-3 Mbaud), so a larger number is a typo.
const BAUD_RANGE: std::ops::RangeInclusive<u32> = 1200..=12_000_000;

/// The longest connection string accepted: a host name is at most 253 characters (DNS) and a
/// serial device path a few dozen; anything longer is not a connection, and its parts are never
/// repeated whole in a message.
pub const MAX_CONNECTION_BYTES: usize = 512;

/// What is wrong with a connection string ([`check_connection`]).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum BadConnection {
    /// Neither `SCHEME:ADDRESS` nor a serial device path.
    #[error(
        "expected SCHEME:ADDRESS with SCHEME one of {SCHEMES}, or a serial device \
         (/dev/ttyACM0, /dev/ttyACM0,57600)"
    )]
    NoScheme,
    /// Longer than any connection string (its length in bytes).
    #[error("{0} bytes, longer than any connection ({MAX_CONNECTION_BYTES} at most)")]
    TooLong(usize),
    /// A scheme no connection form has.
    #[error(
        "unknown scheme {}; expected one of {SCHEMES}, or a serial device path",
        quote(.0)
    )]
    UnknownScheme(String),
    /// No `HOST:PORT` after the scheme.
    #[error("expected HOST:PORT after the scheme")]
    NoPort,
    /// `:PORT` without a host.
    #[error("the host is empty (use 0.0.0.0 to listen on every interface)")]
    EmptyHost,
    /// A port that is not a number in 1..=65535.
    #[error("port {} is not a number in 1..=65535", quote(.0))]
    BadPort(String),
    /// A host of digits and dots that is not a valid IPv4 address.
    #[error(
        "{} is not an IPv4 address (four numbers 0-255 separated by dots, without leading \
         zeros); the link could never open it",
        quote(.0)
    )]
    BadIpv4(String),
    /// A serial connection without a device.
    #[error("the serial device is empty")]
    EmptyDevice,
    /// A baud rate that is not a number in 1200..=12000000.
    #[error("baud rate {} is not a number in 1200..=12000000", quote(.0))]
    BadBaud(String),
}

/// Where a connection string connects ([`parse_connection`]): the forms of MAVProxy and
/// pymavlink written in one canonical way.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Endpoint {
    /// Listen for UDP datagrams on `HOST:PORT` and reply to the locked autopilot (`udpin:`, and
    /// `udp:`, which pymavlink's `mavlink_connection` opens as a listener).
    UdpIn(String),
    /// Send UDP datagrams to `HOST:PORT` (`udpout:`).
    UdpOut(String),
    /// Broadcast UDP datagrams to `ADDR:PORT` (`udpbcast:`).
    UdpBcast(String),
    /// Accept one TCP client on `HOST:PORT` (`tcpin:`).
    TcpIn(String),
    /// Connect to a TCP server at `HOST:PORT` (`tcpout:`, and `tcp:`, pymavlink's client).
    TcpOut(String),
    /// A serial device at a baud rate (`serial:DEVICE[:BAUD]`, `DEVICE[,BAUD]`).
    Serial {
        /// The device path (`/dev/ttyACM0`).
        device: String,
        /// Its baud rate.
        baud: u32,
    },
}

impl Endpoint {
    /// The `HOST:PORT` this endpoint listens on, with its protocol (`"UDP"` or `"TCP"`); `None`
    /// for endpoints that send or connect.
    pub fn listen_address(&self) -> Option<(&'static str, &str)> {
        match self {
            Endpoint::UdpIn(a) => Some(("UDP", a)),
            Endpoint::TcpIn(a) => Some(("TCP", a)),
            _ => None,
        }
    }

    /// The string the mavlink crate's `connect_async` parses; `None` for serial, whose device
    /// may contain `:` (`/dev/serial/by-path/...-usb-0:1.3:1.0-port0`) that its parser would
    /// split at.
    pub fn mavlink_address(&self) -> Option<String> {
        match self {
            Endpoint::UdpIn(a) => Some(format!("udpin:{a}")),
            Endpoint::UdpOut(a) => Some(format!("udpout:{a}")),
            Endpoint::UdpBcast(a) => Some(format!("udpbcast:{a}")),
            Endpoint::TcpIn(a) => Some(format!("tcpin:{a}")),
            Endpoint::TcpOut(a) => Some(format!("tcpout:{a}")),
            Endpoint::Serial { .. } => None,
        }
    }

    /// Bind this endpoint's listen address and release it at once: `Err` when it cannot be
    /// listened on now (another program has the port: a MAVProxy, mavlink-router, a ground
    /// station or a visnav already running). `Ok` for endpoints that do not listen.
    pub fn probe_listen(&self) -> Result<(), ListenError> {
        let Some((proto, addr)) = self.listen_address() else {
            return Ok(());
        };
        probe_listen(proto, addr)
    }
}

/// A listen address that cannot be bound ([`Endpoint::probe_listen`], [`probe_listen`]).
#[derive(Debug, thiserror::Error)]
#[error("{}", listen_message(.proto, .addr, .cause))]
pub struct ListenError {
    /// `"UDP"` or `"TCP"`.
    pub proto: &'static str,
    /// The `HOST:PORT` given.
    pub addr: String,
    /// What binding it said.
    pub cause: std::io::Error,
}

impl ListenError {
    /// Another socket has the port (as opposed to an address not on this machine yet, which
    /// a network coming up later may fix).
    pub fn in_use(&self) -> bool {
        self.cause.kind() == std::io::ErrorKind::AddrInUse
    }
}

fn listen_message(proto: &str, addr: &str, cause: &std::io::Error) -> String {
    let port = addr.rsplit_once(':').map_or(addr, |(_, p)| p);
    if cause.kind() == std::io::ErrorKind::AddrInUse {
        format!(
            "{proto} port {port} ({addr}) is in use by another program (a MAVProxy, \
             mavlink-router, a ground station or a visnav already running?): {cause}"
        )
    } else {
        format!("cannot listen on {proto} {addr}: {cause}")
    }
}

/// Bind `addr` (`HOST:PORT`) for `proto` (`"UDP"` or `"TCP"`) and release it at once. The
/// sockets are bound as the link and the metrics endpoint bind theirs (the standard library's
/// defaults), so what this refuses, they would refuse.
pub fn probe_listen(proto: &'static str, addr: &str) -> Result<(), ListenError> {
    let r = if proto == "UDP" {
        std::net::UdpSocket::bind(addr).map(drop)
    } else {
        std::net::TcpListener::bind(addr).map(drop)
    };
    r.map_err(|cause| ListenError {
        proto,
        addr: addr.to_string(),
        cause,
    })
}

/// Check a connection string ([`parse_connection`]).
pub fn check_connection(s: &str) -> Result<(), BadConnection> {
    parse_connection(s).map(drop)
}

/// Parse a connection string as MAVProxy's `--master` and pymavlink's `mavlink_connection` write
/// them: `udpin:`, `udpout:`, `udpbcast:`, `tcpin:`, `tcpout:` and `udp:` (listen) / `tcp:`
/// (connect) with `HOST:PORT`; `serial:DEVICE[:BAUD]`; a bare device path `DEVICE[,BAUD]`
/// (`/dev/ttyACM0,57600`, `COM3`). Network forms need a host and a numeric port; a host
/// written as dotted numbers must be a valid IPv4 address: the name lookup would refuse
/// `300.1.1.1` only when the link opens, and the link would retry it for ever; host names stay
/// allowed (they are resolved when the link opens, and may be down at check time).
pub fn parse_connection(s: &str) -> Result<Endpoint, BadConnection> {
    if s.len() > MAX_CONNECTION_BYTES {
        return Err(BadConnection::TooLong(s.len()));
    }
    if let Some((scheme, rest)) = s.split_once(':') {
        let net = |make: fn(String) -> Endpoint| {
            check_host_port(rest)?;
            Ok(make(rest.to_string()))
        };
        match scheme {
            "udpin" | "udp" => return net(Endpoint::UdpIn),
            "udpout" => return net(Endpoint::UdpOut),
            "udpbcast" => return net(Endpoint::UdpBcast),
            "tcpin" => return net(Endpoint::TcpIn),
            "tcpout" | "tcp" => return net(Endpoint::TcpOut),
            "serial" => return parse_serial_scheme(rest),
            // A device path may hold a colon (`/dev/serial/by-path/...-usb-0:1.3:1.0-port0`).
            _ if is_device_path(s) => {}
            other => return Err(BadConnection::UnknownScheme(other.to_string())),
        }
    }
    if is_device_path(s) {
        return parse_device_comma_baud(s);
    }
    Err(BadConnection::NoScheme)
}

/// A serial device as MAVProxy takes it bare: an absolute path, or a Windows port (`COM3`,
/// `\\.\COM12`).
fn is_device_path(s: &str) -> bool {
    let com = s.strip_prefix(r"\\.\").unwrap_or(s);
    let com_digits = com
        .get(..3)
        .filter(|p| p.eq_ignore_ascii_case("com"))
        .and_then(|_| com.get(3..))
        .map(|n| n.split(',').next().unwrap_or(n));
    s.starts_with('/')
        || com_digits.is_some_and(|n| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()))
}

/// `DEVICE` or `DEVICE,BAUD` (MAVProxy's `--master` form).
fn parse_device_comma_baud(s: &str) -> Result<Endpoint, BadConnection> {
    let (device, baud) = match s.rsplit_once(',') {
        Some((d, b)) => (d, parse_baud(b)?),
        None => (s, DEFAULT_SERIAL_BAUD),
    };
    serial(device, baud)
}

/// After `serial:`: `DEVICE:BAUD`, or `DEVICE` alone. A last `:` part of digits is the baud
/// rate; a path's other colons belong to the device.
fn parse_serial_scheme(rest: &str) -> Result<Endpoint, BadConnection> {
    match rest.rsplit_once(':') {
        Some((d, b)) if !b.is_empty() && b.bytes().all(|c| c.is_ascii_digit()) => {
            serial(d, parse_baud(b)?)
        }
        // A colon in a path (by-path names) is the device's; elsewhere it was meant as a baud.
        Some((_, b)) if !rest.starts_with('/') => Err(BadConnection::BadBaud(b.to_string())),
        _ => serial(rest, DEFAULT_SERIAL_BAUD),
    }
}

fn serial(device: &str, baud: u32) -> Result<Endpoint, BadConnection> {
    if device.is_empty() {
        return Err(BadConnection::EmptyDevice);
    }
    Ok(Endpoint::Serial {
        device: device.to_string(),
        baud,
    })
}

fn parse_baud(b: &str) -> Result<u32, BadConnection> {
    match b.parse::<u32>() {
        Ok(v) if BAUD_RANGE.contains(&v) => Ok(v),
        _ => Err(BadConnection::BadBaud(b.to_string())),
    }
}

/// `HOST:PORT` of a network form.
fn check_host_port(rest: &str) -> Result<(), BadConnection> {
    let (host, port) = rest.rsplit_once(':').ok_or(BadConnection::NoPort)?;
    if host.is_empty() {
        return Err(BadConnection::EmptyHost);
    }
    let dotted_numbers = host.contains('.') && host.chars().all(|c| c.is_ascii_digit() || c == '.');
    if dotted_numbers && host.parse::<std::net::Ipv4Addr>().is_err() {
        return Err(BadConnection::BadIpv4(host.to_string()));
    }
    match port.parse::<u16>() {
        Ok(0) | Err(_) => Err(BadConnection::BadPort(port.to_string())),
        Ok(_) => Ok(()),
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
                p.push("modes", format!("{m} is listed twice"));
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
            "udq:1.2.3.4:5",
            "udpin:0.0.0.0",
            "udpin::14550",
            "serial:/dev/x:12",
            "nothing",
        ] {
            assert!(check_connection(bad).is_err(), "{bad}");
        }
    }

    fn parsed(s: &str) -> Endpoint {
        match parse_connection(s) {
            Ok(e) => e,
            Err(e) => panic!("{s}: {e}"),
        }
    }

    fn serial_at(device: &str, baud: u32) -> Endpoint {
        Endpoint::Serial {
            device: device.into(),
            baud,
        }
    }

    /// pymavlink's `mavlink_connection` opens `udp:` as a listener (its `input=True` default;
    /// MAVProxy's `--master` too), so `udp:` is `udpin:`.
    #[test]
    fn udp_listens_as_pymavlink_does() {
        assert_eq!(
            parsed("udp:127.0.0.1:14550"),
            Endpoint::UdpIn("127.0.0.1:14550".into())
        );
        assert_eq!(
            parsed("udp:127.0.0.1:14550"),
            parsed("udpin:127.0.0.1:14550")
        );
        assert_eq!(
            parsed("udp:127.0.0.1:14550").listen_address(),
            Some(("UDP", "127.0.0.1:14550"))
        );
        assert!(matches!(
            parse_connection("udp:127.0.0.1"),
            Err(BadConnection::NoPort)
        ));
    }

    /// pymavlink's `tcp:` is a client (`mavtcp`), so `tcp:` is `tcpout:`.
    #[test]
    fn tcp_connects_as_pymavlink_does() {
        assert_eq!(
            parsed("tcp:127.0.0.1:5760"),
            Endpoint::TcpOut("127.0.0.1:5760".into())
        );
        assert_eq!(parsed("tcp:127.0.0.1:5760").listen_address(), None);
        assert_eq!(
            parsed("tcp:127.0.0.1:5760").mavlink_address().as_deref(),
            Some("tcpout:127.0.0.1:5760")
        );
        assert!(matches!(
            parse_connection("tcp:127.0.0.1:0"),
            Err(BadConnection::BadPort(_))
        ));
    }

    /// A bare device path, as `mavproxy.py --master=/dev/ttyACM0`, at the default baud rate.
    #[test]
    fn a_bare_device_is_serial_at_the_default_baud() {
        assert_eq!(
            parsed("/dev/ttyACM0"),
            serial_at("/dev/ttyACM0", DEFAULT_SERIAL_BAUD)
        );
        assert_eq!(parsed("COM3"), serial_at("COM3", DEFAULT_SERIAL_BAUD));
        // A by-path name holds colons; they are the device's.
        let by_path = "/dev/serial/by-path/platform-3f980000.usb-usb-0:1.3:1.0-port0";
        assert_eq!(parsed(by_path), serial_at(by_path, DEFAULT_SERIAL_BAUD));
        assert_eq!(parsed(by_path).mavlink_address(), None);
    }

    /// `DEVICE,BAUD`, MAVProxy's `--master=/dev/ttyACM0,57600`.
    #[test]
    fn a_device_comma_baud_is_serial_at_that_baud() {
        assert_eq!(
            parsed("/dev/ttyACM0,57600"),
            serial_at("/dev/ttyACM0", 57_600)
        );
        assert_eq!(parsed("COM3,115200"), serial_at("COM3", 115_200));
        for bad in ["/dev/ttyACM0,fast", "/dev/ttyACM0,12", "/dev/ttyACM0,"] {
            let e = parse_connection(bad).unwrap_err();
            assert!(matches!(e, BadConnection::BadBaud(_)), "{bad}: {e}");
        }
        assert!(matches!(
            parse_connection(",57600"),
            Err(BadConnection::NoScheme)
        ));
    }

    /// `serial:DEVICE` without a baud takes the default; `serial:DEVICE:BAUD` as before.
    #[test]
    fn serial_without_a_baud_takes_the_default() {
        assert_eq!(
            parsed("serial:/dev/ttyACM0"),
            serial_at("/dev/ttyACM0", DEFAULT_SERIAL_BAUD)
        );
        assert_eq!(
            parsed("serial:/dev/ttyAMA0:921600"),
            serial_at("/dev/ttyAMA0", 921_600)
        );
        assert_eq!(parsed("serial:COM3:57600"), serial_at("COM3", 57_600));
        let e = parse_connection("serial:COM3:fast").unwrap_err();
        assert_eq!(e, BadConnection::BadBaud("fast".into()));
        assert_eq!(
            parse_connection("serial:").unwrap_err(),
            BadConnection::EmptyDevice
        );
    }

    /// Every earlier form parses to what it meant, and unknown ones name the forms.
    #[test]
    fn the_explicit_forms_keep_their_meaning() {
        for (s, e) in [
            (
                "udpin:0.0.0.0:14550",
                Endpoint::UdpIn("0.0.0.0:14550".into()),
            ),
            (
                "udpout:10.0.0.2:14550",
                Endpoint::UdpOut("10.0.0.2:14550".into()),
            ),
            (
                "udpbcast:10.0.0.255:14550",
                Endpoint::UdpBcast("10.0.0.255:14550".into()),
            ),
            ("tcpin:0.0.0.0:5760", Endpoint::TcpIn("0.0.0.0:5760".into())),
            (
                "tcpout:localhost:5760",
                Endpoint::TcpOut("localhost:5760".into()),
            ),
        ] {
            assert_eq!(parsed(s), e, "{s}");
            assert_eq!(e.mavlink_address().as_deref(), Some(s));
        }
        let e = parse_connection("mcast:239.255.145.50:14550").unwrap_err();
        assert!(
            e.to_string()
                .starts_with("unknown scheme \"mcast\"; expected one of udpin,"),
            "{e}"
        );
        let e = parse_connection("ttyACM0").unwrap_err();
        assert!(e.to_string().contains("/dev/ttyACM0,57600"), "{e}");
    }

    /// A port another socket holds is reported as in use, naming the protocol and the port;
    /// released, it probes free.
    #[test]
    fn a_busy_listen_port_is_found() {
        let held = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
        let port = held.local_addr().unwrap().port();
        let e = parsed(&format!("udp:127.0.0.1:{port}"))
            .probe_listen()
            .unwrap_err();
        assert!(e.in_use(), "{e}");
        let m = e.to_string();
        assert!(
            m.starts_with(&format!("UDP port {port} (127.0.0.1:{port}) is in use")),
            "{m}"
        );
        let tcp = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let tport = tcp.local_addr().unwrap().port();
        let e = parsed(&format!("tcpin:127.0.0.1:{tport}"))
            .probe_listen()
            .unwrap_err();
        assert!(e.in_use() && e.to_string().starts_with("TCP port"), "{e}");
        // Senders and connectors have nothing to probe.
        assert!(
            parsed(&format!("udpout:127.0.0.1:{port}"))
                .probe_listen()
                .is_ok()
        );
        drop(held);
        assert!(
            parsed(&format!("udp:127.0.0.1:{port}"))
                .probe_listen()
                .is_ok()
        );
    }

    /// A dotted-number host that is no IPv4 address passed, and the link then retried "failed
    /// to lookup address" for ever: it is refused naming the host; host names stay allowed.
    #[test]
    fn an_invalid_ipv4_literal_is_refused() {
        for bad in [
            "udpin:300.1.1.1:14871",
            "udpout:1.2.3:14550",
            "tcpout:10.0.0.256:5760",
            "tcpin:010.0.0.1:5760",
            "udpbcast:1..2.3:14550",
        ] {
            let e = check_connection(bad).unwrap_err();
            assert!(matches!(e, BadConnection::BadIpv4(_)), "{bad}: {e}");
            assert!(e.to_string().contains("is not an IPv4 address"), "{e}");
        }
        for ok in [
            "udpout:localhost:14550",
            "tcpout:autopilot.local:5760",
            "udpout:10.0.0.255:14550",
            "udpin:0.0.0.0:14871",
        ] {
            assert!(check_connection(ok).is_ok(), "{ok}");
        }
        let mut c = LinkConfig::new("udpin:300.1.1.1:14871");
        c.heartbeat_hz = 1.0;
        let p = problems(&c).join("\n");
        assert!(
            p.starts_with("connection: \"udpin:300.1.1.1:14871\": \"300.1.1.1\" is not an IPv4"),
            "{p}"
        );
    }

    #[test]
    fn a_huge_connection_string_is_not_repeated_whole() {
        let long = format!("udpin:{}:14550", "x".repeat(10_000_000));
        let p = problems(&LinkConfig::new(&long)).join("\n");
        assert!(
            p.len() < 300 && p.contains("longer than any connection"),
            "{p}"
        );
        let p = problems(&LinkConfig::new(&format!("udpin:h:{}", "9".repeat(400)))).join("\n");
        assert!(p.len() < 300 && p.contains("port"), "{p}");
    }
}
