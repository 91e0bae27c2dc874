//! Telemetry streams: which messages visnav asks the autopilot for (MAV_CMD_SET_MESSAGE_INTERVAL,
//! <https://mavlink.io/en/services/message_interval.html>) and whether they arrive at the asked
//! rate. ArduPilot streams nothing but HEARTBEAT on a link until asked.
//!
//! A [`StreamSpec`] lists alternative message ids (e.g. HIGHRES_IMU, else SCALED_IMU + RAW_IMU):
//! the first is requested; when it is missing at a check, the alternatives are requested too.
//! The [`RateMonitor`] counts arrivals per message id over a sliding window; a stream is
//! satisfied when any of its ids arrives at `min_rate_fraction * requested_hz` or more.

use std::collections::{HashMap, VecDeque};

use mavlink::dialects::ardupilotmega::MavAutopilot;

use crate::config::StreamRates;

/// MAVLink message ids used here.
pub mod ids {
    /// SYSTEM_TIME: the autopilot's UTC and boot time.
    pub const SYSTEM_TIME: u32 = 2;
    /// GPS_RAW_INT: the first GPS receiver.
    pub const GPS_RAW_INT: u32 = 24;
    /// SCALED_IMU: the first IMU, integer units.
    pub const SCALED_IMU: u32 = 26;
    /// RAW_IMU: the first IMU, raw counts.
    pub const RAW_IMU: u32 = 27;
    /// SCALED_PRESSURE: the barometer.
    pub const SCALED_PRESSURE: u32 = 29;
    /// ATTITUDE: the autopilot's attitude.
    pub const ATTITUDE: u32 = 30;
    /// GLOBAL_POSITION_INT: the autopilot's fused position.
    pub const GLOBAL_POSITION_INT: u32 = 33;
    /// GPS_GLOBAL_ORIGIN: the EKF origin.
    pub const GPS_GLOBAL_ORIGIN: u32 = 49;
    /// HIGHRES_IMU: the IMU in floats (PX4).
    pub const HIGHRES_IMU: u32 = 105;
    /// ALTITUDE: the autopilot's altitudes.
    pub const ALTITUDE: u32 = 141;
}

/// One wanted telemetry stream.
#[derive(Debug, Clone, PartialEq)]
pub struct StreamSpec {
    /// Name used in logs and status texts.
    pub name: &'static str,
    /// Message ids: the preferred first, then alternatives.
    pub ids: Vec<u32>,
    /// Requested rate, Hz.
    pub hz: f64,
}

/// The streams visnav needs from `autopilot` (the locked one's flight stack, when known), at the
/// configured rates (rate 0 = not requested). SCALED_IMU beside HIGHRES_IMU: at `scaled_imu_hz`
/// when set, else (automatic) at `imu_hz` from PX4, whose HIGHRES_IMU it restores
/// (`crate::daemon::imu_bias`), and not from others.
pub fn wanted_streams(r: &StreamRates, autopilot: Option<MavAutopilot>) -> Vec<StreamSpec> {
    use ids::*;
    let scaled_hz =
        r.scaled_imu_hz
            .unwrap_or(if autopilot == Some(MavAutopilot::MAV_AUTOPILOT_PX4) {
                r.imu_hz
            } else {
                0.0
            });
    [
        ("ATTITUDE", vec![ATTITUDE], r.attitude_hz),
        // With SCALED_IMU requested beside HIGHRES_IMU it cannot stand in for a missing
        // HIGHRES_IMU in the IMU stream's health (the restorer needs both).
        (
            "IMU",
            if scaled_hz > 0.0 {
                vec![HIGHRES_IMU, RAW_IMU]
            } else {
                vec![HIGHRES_IMU, SCALED_IMU, RAW_IMU]
            },
            r.imu_hz,
        ),
        ("SCALED_IMU", vec![SCALED_IMU], scaled_hz),
        (
            "GLOBAL_POSITION_INT",
            vec![GLOBAL_POSITION_INT],
            r.global_position_hz,
        ),
        ("GPS_RAW_INT", vec![GPS_RAW_INT], r.gps_raw_hz),
        ("SYSTEM_TIME", vec![SYSTEM_TIME], r.system_time_hz),
        ("PRESSURE", vec![SCALED_PRESSURE, ALTITUDE], r.pressure_hz),
    ]
    .into_iter()
    .filter(|(_, _, hz)| *hz > 0.0)
    .map(|(name, ids, hz)| StreamSpec { name, ids, hz })
    .collect()
}

/// Sliding-window arrival counter per message id (times in seconds, any monotonic origin).
#[derive(Debug, Clone)]
pub struct RateMonitor {
    window_s: f64,
    arrivals: HashMap<u32, VecDeque<f64>>,
}

impl RateMonitor {
    /// Count over the last `window_s` seconds.
    pub fn new(window_s: f64) -> Self {
        Self {
            window_s,
            arrivals: HashMap::new(),
        }
    }

    /// Note one message.
    pub fn record(&mut self, id: u32, t_s: f64) {
        let q = self.arrivals.entry(id).or_default();
        q.push_back(t_s);
        while q.front().is_some_and(|f| *f < t_s - self.window_s) {
            q.pop_front();
        }
    }

    /// Messages per second of `id` over the window ending at `t_s`.
    pub fn rate_hz(&mut self, id: u32, t_s: f64) -> f64 {
        let Some(q) = self.arrivals.get_mut(&id) else {
            return 0.0;
        };
        while q.front().is_some_and(|f| *f < t_s - self.window_s) {
            q.pop_front();
        }
        q.len() as f64 / self.window_s
    }

    /// Forget everything (reconnect, reboot).
    pub fn clear(&mut self) {
        self.arrivals.clear();
    }
}

/// Measured state of one stream.
#[derive(Debug, Clone, PartialEq)]
pub struct StreamStatus {
    /// Stream name.
    pub name: &'static str,
    /// Requested rate, Hz.
    pub requested_hz: f64,
    /// Best measured rate among its ids, Hz.
    pub measured_hz: f64,
    /// The id with the best rate.
    pub best_id: u32,
    /// Measured >= fraction * requested.
    pub ok: bool,
}

/// Evaluate every stream at `t_s`.
pub fn evaluate(
    specs: &[StreamSpec],
    mon: &mut RateMonitor,
    t_s: f64,
    min_fraction: f64,
) -> Vec<StreamStatus> {
    specs
        .iter()
        .map(|s| {
            let (best_id, measured_hz) = s
                .ids
                .iter()
                .map(|id| (*id, mon.rate_hz(*id, t_s)))
                .fold((s.ids[0], 0.0), |a, b| if b.1 > a.1 { b } else { a });
            StreamStatus {
                name: s.name,
                requested_hz: s.hz,
                measured_hz,
                best_id,
                ok: measured_hz >= min_fraction * s.hz,
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn measures_rates_and_picks_alternatives() {
        let specs = wanted_streams(&StreamRates::default(), None);
        assert_eq!(specs.len(), 6);
        // From PX4, SCALED_IMU is wanted beside HIGHRES_IMU at the IMU rate (automatic), from
        // ArduPilot not; an explicit rate holds for any autopilot, 0 switches it off.
        let px4 = wanted_streams(
            &StreamRates::default(),
            Some(MavAutopilot::MAV_AUTOPILOT_PX4),
        );
        let scaled = px4
            .iter()
            .find(|s| s.name == "SCALED_IMU")
            .expect("SCALED_IMU");
        assert_eq!(
            (scaled.ids.as_slice(), scaled.hz),
            (&[ids::SCALED_IMU][..], 100.0)
        );
        let ap = MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA;
        assert_eq!(wanted_streams(&StreamRates::default(), Some(ap)).len(), 6);
        let mut r = StreamRates {
            scaled_imu_hz: Some(50.0),
            ..StreamRates::default()
        };
        assert!(
            wanted_streams(&r, Some(ap))
                .iter()
                .any(|s| s.name == "SCALED_IMU" && s.hz == 50.0)
        );
        r.scaled_imu_hz = Some(0.0);
        let px4 = Some(MavAutopilot::MAV_AUTOPILOT_PX4);
        assert!(
            wanted_streams(&r, px4)
                .iter()
                .all(|s| s.name != "SCALED_IMU")
        );
        let mut m = RateMonitor::new(2.0);
        // 3 s of ATTITUDE at 50 Hz, SCALED_IMU (not HIGHRES) at 100 Hz, SYSTEM_TIME at 0.2 Hz.
        for k in 0..300 {
            let t = k as f64 * 0.01;
            if k % 2 == 0 {
                m.record(ids::ATTITUDE, t);
            }
            m.record(ids::SCALED_IMU, t);
            if k % 500 == 0 {
                m.record(ids::SYSTEM_TIME, t);
            }
        }
        let st = evaluate(&specs, &mut m, 3.0, 0.7);
        let get = |n: &str| st.iter().find(|s| s.name == n).unwrap().clone();
        assert!(get("ATTITUDE").ok);
        assert!((get("ATTITUDE").measured_hz - 50.0).abs() < 1.0);
        let imu = get("IMU");
        assert!(imu.ok && imu.best_id == ids::SCALED_IMU);
        assert!(!get("SYSTEM_TIME").ok);
        assert!(!get("GPS_RAW_INT").ok);
        assert_eq!(get("GPS_RAW_INT").measured_hz, 0.0);
        // The window slides: 10 s later nothing is left.
        assert_eq!(m.rate_hz(ids::ATTITUDE, 13.0), 0.0);
    }

    #[test]
    fn zero_rate_is_not_requested() {
        let r = StreamRates {
            pressure_hz: 0.0,
            ..StreamRates::default()
        };
        assert!(
            wanted_streams(&r, None)
                .iter()
                .all(|s| s.name != "PRESSURE")
        );
    }
}
