//! `[daemon]` configuration section: which autopilot telemetry aids the filter and how much it is
//! trusted, and the daemon's watchdogs. Every key has a default.
//!
//! ```toml
//! [daemon]
//! gps = "auto"            # "auto" | "gps1" (GPS_RAW_INT) | "gps2" (GPS2_RAW) | "none"
//! gps_sigma_h_m = 2.5     # used when the message carries no h_acc
//! gps_sigma_v_m = 5.0     # used when the message carries no v_acc
//! gps_min_sigma_h_m = 1.5 # floor of the receiver's own h_acc (see below)
//! gps_min_sigma_v_m = 3.0 # floor of the receiver's own v_acc
//! gps_vel_sigma_m_s = 0.5 # horizontal velocity (ground speed + course), when vel_acc is absent
//! gps_vz_sigma_m_s = 30.0 # GPS_RAW_INT has no vertical velocity: 0 with this sigma
//! baro = true             # SCALED_PRESSURE altitude, offset calibrated against GPS / the filter
//! baro_sigma_m = 2.0
//! imu_timeout_s = 0.5     # no IMU for this long: the solution is declared lost (nothing injected)
//! imu_bias_restore = "auto" # "auto" (PX4: on) | "scaled_imu" | "off": PX4's HIGHRES_IMU is
//!                           # the IMU minus EKF2's bias, restored with SCALED_IMU (see below)
//! log_interval_s = 10.0   # metrics summary in the log
//! # metrics_listen = "127.0.0.1:9187"  # Prometheus endpoint GET /metrics (absent: off)
//! ```
//!
//! `metrics_listen` serves the one metrics registry: every metric of the daemon and the link plus
//! the navigation health ([`crate::metrics::registry`], [`crate::prometheus`], docs/operations.md). It is an `IP:PORT` socket address; port 0
//! picks a free port ([`crate::daemon::Daemon::metrics_addr`] tells which).
//!
//! Sigma floors: a receiver's h_acc / v_acc describe its position at the fix time, but the daemon
//! time-stamps GPS_RAW_INT / GPS2_RAW on arrival (ArduPilot's `time_usec` is the Unix time now,
//! not of the fix): the fix is up to a receiver lag plus one update period old (0.1-0.3 s). An
//! ArduCopter SITL receiver reports h_acc of a few decimetres; at 8-10 m/s that age is metres.
//! The floors keep the sigma at least that age's error. (They did not stop the filter resets seen
//! in the ArduCopter SITL climb, whose cause is still open: docs/real-sitl.md, run 5.)
//!
//! Feedback guard: with `output.modes` containing `gps_input`, the autopilot reports our own
//! injection back as the GPS instance `output.gps_id` (GPS_RAW_INT for instance 0, GPS2_RAW for
//! instance 1). Fusing it would feed the solution back into itself, so `auto` picks the other
//! instance and an explicit choice of the injected instance is rejected by validation.

use serde::{Deserialize, Serialize};

use visnav_core::validate::{Problems, Validate};
use visnav_link::config::{OutputConfig, OutputMode};

/// Which autopilot GPS message aids the filter.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum GpsSource {
    /// `gps2` when we inject GPS_INPUT into instance 0, else `gps1`.
    #[default]
    Auto,
    /// GPS_RAW_INT (the autopilot's first GPS).
    Gps1,
    /// GPS2_RAW (the second GPS; requested by the daemon).
    Gps2,
    /// No GPS aiding.
    None,
}

impl std::fmt::Display for GpsSource {
    /// The configuration's spelling, with the message it reads.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            GpsSource::Auto => "auto",
            GpsSource::Gps1 => "gps1 (GPS_RAW_INT)",
            GpsSource::Gps2 => "gps2 (GPS2_RAW)",
            GpsSource::None => "none (no GPS aiding)",
        })
    }
}

/// Whether the autopilot's bias estimates are added back to HIGHRES_IMU.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum ImuBiasRestore {
    /// `scaled_imu` when the locked autopilot's HEARTBEAT says MAV_AUTOPILOT_PX4, else `off`
    /// (the link then also asks PX4 for SCALED_IMU at the IMU rate).
    #[default]
    Auto,
    /// HIGHRES_IMU is the raw IMU (ArduPilot does not send it; a companion IMU bridge).
    Off,
    /// HIGHRES_IMU is the IMU minus the autopilot's bias estimates (PX4): restored with the
    /// SCALED_IMU of the same samples ([`crate::imu_bias`]).
    ScaledImu,
}

/// `[daemon]` section.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct DaemonConfig {
    /// GPS aiding source.
    pub gps: GpsSource,
    /// GPS horizontal sigma when the message has no accuracy, m.
    pub gps_sigma_h_m: f64,
    /// GPS vertical sigma when the message has no accuracy, m.
    pub gps_sigma_v_m: f64,
    /// GPS horizontal velocity sigma when the message has no accuracy, m/s.
    pub gps_vel_sigma_m_s: f64,
    /// Smallest horizontal GPS sigma used, whatever the message says, m.
    pub gps_min_sigma_h_m: f64,
    /// Smallest vertical GPS sigma used, m.
    pub gps_min_sigma_v_m: f64,
    /// Smallest horizontal GPS velocity sigma used, m/s. Receivers report a few cm/s (ArduPilot
    /// SITL: 0.04), but the message is stamped on arrival with the receiver's latency not
    /// modelled: 0.1 s at 2 m/s^2 is 0.2 m/s.
    pub gps_min_sigma_vel_m_s: f64,
    /// Sigma of the (unmeasured, zero) vertical GPS velocity, m/s. GPS_RAW_INT / GPS2_RAW carry
    /// no vertical velocity; the default 30 m/s makes the zero carry almost no weight, so a
    /// climbing copter (8 m/s in ArduPilot SITL) does not pull the filter into resets, as 5 m/s
    /// did (docs/real-sitl.md, run 1).
    pub gps_vz_sigma_m_s: f64,
    /// GPS receiver latency, s: a GPS message's position and velocity are applied this long before
    /// its time stamp (ArduPilot stamps GPS_RAW_INT / GPS2_RAW with the time the receiver's
    /// message arrived; u-blox receivers lag about 0.1-0.2 s). 0.1 s fitted ArduCopter SITL's
    /// GPS2 best in `visnav replay` (0.0 / 0.1 / 0.2 s: cruise position 1.1 / 0.5 / 1.3 m from
    /// EKF3's).
    pub gps_delay_s: f64,
    /// Take the gyro rates from ATTITUDE's float `rollspeed/pitchspeed/yawspeed` (body rates,
    /// the latest within 0.06 s) instead of SCALED_IMU / RAW_IMU, whose 16-bit mrad/s integers
    /// (truncated toward zero by ArduPilot) lose every rotation slower than 1 mrad/s = 206 deg/h:
    /// in ArduCopter SITL this tilted the filter 0.7 deg in 25 s of climb and reset it every
    /// 5-10 s (docs/real-sitl.md, run 6). HIGHRES_IMU (float) is always used as it is.
    pub gyro_from_attitude: bool,
    /// Add the autopilot's bias estimates back to HIGHRES_IMU. PX4 (v1.14) sends HIGHRES_IMU
    /// minus EKF2's gyro and accelerometer bias estimates, which swing by 100-220 deg/h once
    /// EKF2 loses the GPS: integrated as the raw IMU that tilted visnav by 0.5-0.7 deg in 20 s
    /// (docs/real-sitl.md, PX4 section). `"scaled_imu"` restores the raw samples from the
    /// SCALED_IMU of the same samples (int16, without the bias; the link requests it at
    /// `link.streams.imu_hz` unless `link.streams.scaled_imu_hz` says otherwise); `"auto"`
    /// (default) does so when the autopilot is PX4.
    pub imu_bias_restore: ImuBiasRestore,
    /// Use the barometric altitude.
    pub baro: bool,
    /// Barometric altitude sigma, m.
    pub baro_sigma_m: f64,
    /// No IMU sample for this long: solution lost, s.
    pub imu_timeout_s: f64,
    /// Interval of the metrics summary in the log, s (0 = off).
    pub log_interval_s: f64,
    /// Prometheus endpoint address (`IP:PORT`); `None` = off.
    pub metrics_listen: Option<String>,
    /// Vision fix log (JSON lines, one per fix result, `visnav replay --fixes`), relative to the
    /// config file's folder unless absolute; `{t}` becomes the start time in Unix seconds.
    /// `None` = off.
    pub fix_log: Option<std::path::PathBuf>,
    /// Visual odometry log (JSON lines, one per frame the odometer ran on: the motion, its
    /// covariance, what the filter did; `sitl/vo_check.py` scores it against a SITL's truth),
    /// relative to the config file's folder unless absolute; `{t}` as in `fix_log`. `None` = off.
    pub vo_log: Option<std::path::PathBuf>,
}

impl Default for DaemonConfig {
    fn default() -> Self {
        Self {
            gps: GpsSource::Auto,
            gps_sigma_h_m: 2.5,
            gps_sigma_v_m: 5.0,
            gps_vel_sigma_m_s: 0.5,
            gps_min_sigma_h_m: 1.5,
            gps_min_sigma_v_m: 3.0,
            gps_min_sigma_vel_m_s: 0.3,
            gps_vz_sigma_m_s: 30.0,
            gps_delay_s: 0.1,
            gyro_from_attitude: true,
            imu_bias_restore: ImuBiasRestore::Auto,
            baro: true,
            baro_sigma_m: 2.0,
            imu_timeout_s: 0.5,
            log_interval_s: 10.0,
            metrics_listen: None,
            fix_log: None,
            vo_log: None,
        }
    }
}

/// The GPS instance our GPS_INPUT feeds, if any.
fn injected_gps(out: &OutputConfig) -> Option<GpsSource> {
    out.modes
        .contains(&OutputMode::GpsInput)
        .then_some(if out.gps_id == 0 {
            GpsSource::Gps1
        } else {
            GpsSource::Gps2
        })
}

impl DaemonConfig {
    /// The GPS source actually used (resolves `auto` against the output configuration).
    pub fn gps_source(&self, out: &OutputConfig) -> GpsSource {
        match self.gps {
            GpsSource::Auto => match injected_gps(out) {
                Some(GpsSource::Gps1) => GpsSource::Gps2,
                _ => GpsSource::Gps1,
            },
            g => g,
        }
    }

    /// The parsed `metrics_listen` address (`None` when off or not an `IP:PORT`).
    pub fn metrics_addr(&self) -> Option<std::net::SocketAddr> {
        self.metrics_listen.as_deref()?.trim().parse().ok()
    }

    /// Validate, including the feedback guard against `[output]`.
    pub fn validate_in(&self, out: &OutputConfig, p: &mut Problems) {
        self.validate(p);
        if let Some(inj) = injected_gps(out)
            && self.gps == inj
        {
            p.push(
                "gps",
                format!(
                    "{inj} is the GPS instance our GPS_INPUT feeds (output.gps_id = {}): fusing it \
                     would feed the solution back into itself; use \"auto\" or the other instance",
                    out.gps_id
                )
                .to_lowercase(),
            );
        }
    }
}

impl Validate for DaemonConfig {
    fn validate(&self, p: &mut Problems) {
        p.range("gps_sigma_h_m", self.gps_sigma_h_m, 0.01, 1000.0);
        p.range("gps_sigma_v_m", self.gps_sigma_v_m, 0.01, 1000.0);
        p.range("gps_vel_sigma_m_s", self.gps_vel_sigma_m_s, 0.01, 100.0);
        p.range("gps_vz_sigma_m_s", self.gps_vz_sigma_m_s, 0.01, 100.0);
        p.range("gps_min_sigma_h_m", self.gps_min_sigma_h_m, 0.0, 1000.0);
        p.range("gps_min_sigma_v_m", self.gps_min_sigma_v_m, 0.0, 1000.0);
        p.range(
            "gps_min_sigma_vel_m_s",
            self.gps_min_sigma_vel_m_s,
            0.0,
            100.0,
        );
        p.range("baro_sigma_m", self.baro_sigma_m, 0.01, 1000.0);
        p.range("imu_timeout_s", self.imu_timeout_s, 0.05, 10.0);
        p.range("log_interval_s", self.log_interval_s, 0.0, 3600.0);
        if let Some(m) = &self.metrics_listen
            && self.metrics_addr().is_none()
        {
            p.push(
                "metrics_listen",
                format!(
                    "\"{m}\" is not an IP:PORT socket address (e.g. \"127.0.0.1:9187\"; \
                     host names are not resolved)"
                ),
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn feedback_guard_and_auto() {
        let mut out = OutputConfig::default(); // gps_input, gps_id 0
        let mut c = DaemonConfig::default();
        assert_eq!(c.gps_source(&out), GpsSource::Gps2);
        c.gps = GpsSource::Gps1;
        let mut p = Problems::default();
        c.validate_in(&out, &mut p);
        assert_eq!(p.list.len(), 1);
        assert!(
            p.list[0].key == "gps" && p.list[0].reason.contains("feed"),
            "{:?}",
            p.list
        );
        out.gps_id = 1;
        let mut p = Problems::default();
        c.validate_in(&out, &mut p);
        assert!(p.list.is_empty());
        c.gps = GpsSource::Auto;
        assert_eq!(c.gps_source(&out), GpsSource::Gps1);
        out.modes = vec![OutputMode::Odometry];
        assert_eq!(c.gps_source(&out), GpsSource::Gps1);
    }

    #[test]
    fn parse_and_ranges() {
        let c: DaemonConfig = toml::from_str("gps = \"none\"\nbaro_sigma_m = -1\n").unwrap();
        assert_eq!(c.gps, GpsSource::None);
        let mut p = Problems::default();
        c.validate(&mut p);
        assert!(p.list.iter().any(|i| i.key == "baro_sigma_m"));
        assert!(toml::from_str::<DaemonConfig>("gps_sigma = 1\n").is_err());
    }

    #[test]
    fn metrics_listen_parses_and_validates() {
        assert_eq!(DaemonConfig::default().metrics_listen, None);
        let c: DaemonConfig = toml::from_str("metrics_listen = \"127.0.0.1:9187\"\n").unwrap();
        assert_eq!(c.metrics_addr(), Some("127.0.0.1:9187".parse().unwrap()));
        let mut p = Problems::default();
        c.validate(&mut p);
        assert!(p.list.is_empty(), "{:?}", p.list);
        let c: DaemonConfig = toml::from_str("metrics_listen = \"[::1]:0\"\n").unwrap();
        assert!(c.metrics_addr().is_some_and(|a| a.is_ipv6()));
        for bad in ["localhost:9187", "127.0.0.1", "127.0.0.1:99999", ""] {
            let c = DaemonConfig {
                metrics_listen: Some(bad.into()),
                ..DaemonConfig::default()
            };
            let mut p = Problems::default();
            c.validate(&mut p);
            assert_eq!(p.list.len(), 1, "{bad}: {:?}", p.list);
            assert_eq!(p.list[0].key, "metrics_listen");
            assert!(p.list[0].reason.contains("IP:PORT"), "{:?}", p.list);
        }
        assert!(toml::from_str::<DaemonConfig>("metrics_listen = 9187\n").is_err());
    }
}
