//! Truth from a real autopilot SITL (ArduPilot or PX4) for the simulated camera
//! ([`super::camera_sim::SimCamera`]): a second MAVLink connection to the simulator reads the
//! simulator's own vehicle state and publishes it, stamped with the autopilot boot time, as a
//! [`TruthFeed`].
//!
//! # Where the truth comes from
//!
//! **ArduPilot SITL** (`libraries/SITL/SITL.cpp`, `SIM::simstate_send` / `SIM::sim_state_send`):
//! * `SIMSTATE` (ardupilotmega id 164): the physics model's roll/pitch/yaw (rad, ZYX Euler angles
//!   of `R_ned_body`, yaw wrapped to (-pi, pi]), body angular rates (rad/s), accelerometer
//!   (specific force, body FRD, m/s²) and latitude/longitude as int32 degE7 (exact to 1 cm).
//!   It carries no altitude and no velocity.
//! * `SIM_STATE` (common id 108): the same state with altitude (m AMSL, the simulator's
//!   `state.altitude`) and NED velocity. Its float `lat`/`lon` fields are version dependent
//!   (ArduPilot up to 4.5 writes degE7 into these "deg" floats, later versions degrees plus
//!   `lat_int`/`lon_int`), and float32 quantises them to ~0.4 m, so only `alt` and `vn/ve/vd`
//!   are taken from it.
//! * Neither message has a timestamp. Both are sent from the autopilot's main loop at the
//!   simulation time of the physics step, so the boot time of a sample is taken from the latest
//!   message of the same connection that carries `time_boot_ms` (ATTITUDE, requested at the same
//!   rate, or GLOBAL_POSITION_INT / SYSTEM_TIME) plus the companion time elapsed since that
//!   message arrived. The error is at most one autopilot loop (2.5 ms at 400 Hz) plus the
//!   transport jitter of a loopback socket.
//!
//! A truth sample is published on every SIMSTATE for which a SIM_STATE at most
//! [`MAX_PAIR_AGE_S`] old is held: horizontal position, attitude, rates and specific force from
//! SIMSTATE, velocity from SIM_STATE, altitude from SIM_STATE propagated to the SIMSTATE's
//! arrival with its vertical velocity (`alt = alt_108 - vd * dt`).
//!
//! **PX4 SITL** (SIH or Gazebo): `HIL_STATE_QUATERNION` (id 115), which PX4's mavlink stream
//! `HIL_STATE_QUATERNION` (called `GROUND_TRUTH` in older versions,
//! `src/modules/mavlink/streams/`) fills from the simulator's
//! `vehicle_*_groundtruth` topics: attitude quaternion (`R_ned_body`, Hamilton, w first), body
//! rates, lat/lon degE7, alt mm AMSL, velocity cm/s NED. That stream leaves `time_usec` at 0, so
//! the time comes from the latest `time_boot_ms` as for ArduPilot (ATTITUDE is requested too); a
//! non-zero `time_usec` below 10^12 µs (boot time, not Unix time) is used as it is. Its
//! `xacc/yacc/zacc` are the NED kinematic acceleration in whole m/s², not the accelerometer's
//! specific force, so `accel_body_m_s2` is reported as zero for PX4 (the camera does not use it).
//! Every such message is one truth sample.
//!
//! # The connection
//!
//! [`TruthLink::start`] opens a connection string of the `mavlink` crate (e.g.
//! `udpin:127.0.0.1:14552`, where ArduPilot SITL sends with `--serial2 udpclient:127.0.0.1:14552`
//! or MAVProxy with `--out udp:127.0.0.1:14552`), sends a GCS HEARTBEAT at 1 Hz (so the autopilot
//! routes to it) and asks with `MAV_CMD_SET_MESSAGE_INTERVAL` for the truth messages at `rate_hz`,
//! again every 2 s for each one that has not arrived in the last second (ArduPilot forgets the
//! request on reboot, PX4 on link loss). It listens to `autopilot_system_id` only.
//!
//! Every value is checked (finite, latitude within +-90, longitude within +-180, altitude within
//! -1000..100000 m); a message failing a check is counted and ignored, never published.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use mavlink::dialects::ardupilotmega::{
    COMMAND_LONG_DATA, HEARTBEAT_DATA, MavAutopilot, MavCmd, MavMessage, MavModeFlag, MavState,
    MavType,
};
use mavlink::{AsyncMavConnection, MavHeader};
use nalgebra::{Quaternion, UnitQuaternion};
use tokio::sync::watch;
use tokio::task::JoinHandle;
use tracing::{debug, info, warn};

use super::autopilot::TruthState;
use super::camera_sim::TruthFeed;

/// MAVLink message ids read here.
pub mod ids {
    /// ATTITUDE (common): carries `time_boot_ms`, requested for the time.
    pub const ATTITUDE: u32 = 30;
    /// GLOBAL_POSITION_INT (common): carries `time_boot_ms`.
    pub const GLOBAL_POSITION_INT: u32 = 33;
    /// SYSTEM_TIME (common): carries `time_boot_ms`.
    pub const SYSTEM_TIME: u32 = 2;
    /// SIM_STATE (common): ArduPilot's simulator state with altitude and NED velocity.
    pub const SIM_STATE: u32 = 108;
    /// HIL_STATE_QUATERNION (common): PX4's ground truth.
    pub const HIL_STATE_QUATERNION: u32 = 115;
    /// SIMSTATE (ardupilotmega): ArduPilot's physics model attitude, rates, specific force and
    /// position.
    pub const SIMSTATE: u32 = 164;
}

/// SIM_STATE older than this (companion time) is not paired with a SIMSTATE, s.
pub const MAX_PAIR_AGE_S: f64 = 0.25;
/// A `time_boot_ms` reference older than this (companion time) is not used, s.
pub const MAX_TIME_REF_AGE_S: f64 = 0.5;

/// Which simulator speaks on the truth connection.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SitlKind {
    /// ArduPilot SITL: SIMSTATE + SIM_STATE (+ ATTITUDE for the time).
    ArduPilot,
    /// PX4 SITL: HIL_STATE_QUATERNION (+ ATTITUDE for the time).
    Px4,
}

impl std::fmt::Display for SitlKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            SitlKind::ArduPilot => "ardupilot",
            SitlKind::Px4 => "px4",
        })
    }
}

impl SitlKind {
    /// The message ids to request on the truth connection.
    pub fn requested_ids(self) -> &'static [u32] {
        match self {
            SitlKind::ArduPilot => &[ids::SIMSTATE, ids::SIM_STATE, ids::ATTITUDE],
            SitlKind::Px4 => &[ids::HIL_STATE_QUATERNION, ids::ATTITUDE],
        }
    }
}

/// Why a truth message was not used.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TruthReject {
    /// A field's value is not finite or outside its plausible range.
    #[error("{msg}: field {field} = {value} is not finite or out of range")]
    BadField {
        /// The message's name.
        msg: &'static str,
        /// The field's name.
        field: &'static str,
        /// Its value (converted to the checked unit).
        value: f64,
    },
}

/// Decodes truth messages into [`TruthState`] samples (pure; no I/O). `now` is the companion's
/// arrival time of the message.
#[derive(Debug, Default)]
pub struct TruthDecoder {
    /// (arrival, altitude AMSL m, velocity NED m/s) of the latest SIM_STATE.
    sim_state: Option<(Instant, f64, [f64; 3])>,
    /// (arrival, autopilot boot time µs) of the latest message with `time_boot_ms`.
    time_ref: Option<(Instant, u64)>,
}

fn check(
    msg: &'static str,
    field: &'static str,
    value: f64,
    lo: f64,
    hi: f64,
) -> Result<f64, TruthReject> {
    if value.is_finite() && (lo..=hi).contains(&value) {
        Ok(value)
    } else {
        Err(TruthReject::BadField { msg, field, value })
    }
}

fn f3(msg: &'static str, field: &'static str, v: [f32; 3]) -> Result<[f64; 3], TruthReject> {
    let mut out = [0.0; 3];
    for (o, x) in out.iter_mut().zip(v) {
        *o = check(msg, field, f64::from(x), -1e6, 1e6)?;
    }
    Ok(out)
}

impl TruthDecoder {
    /// A decoder holding no SIM_STATE and no time reference yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// Feed one message; returns a truth sample `(t_boot_us, state)` when this message
    /// completes one, `Ok(None)` when it only updates the decoder's state (or is not a truth
    /// message), `Err` when its values are unusable.
    pub fn on_message(
        &mut self,
        msg: &MavMessage,
        now: Instant,
    ) -> Result<Option<(u64, TruthState)>, TruthReject> {
        match msg {
            MavMessage::ATTITUDE(a) => {
                self.time_ref = Some((now, u64::from(a.time_boot_ms) * 1000));
                Ok(None)
            }
            MavMessage::GLOBAL_POSITION_INT(g) => {
                self.time_ref = Some((now, u64::from(g.time_boot_ms) * 1000));
                Ok(None)
            }
            MavMessage::SYSTEM_TIME(s) => {
                self.time_ref = Some((now, u64::from(s.time_boot_ms) * 1000));
                Ok(None)
            }
            MavMessage::SIM_STATE(s) => {
                const M: &str = "SIM_STATE";
                let alt = check(M, "alt", f64::from(s.alt), -1000.0, 100_000.0)?;
                let v = [
                    check(M, "vn", f64::from(s.vn), -1e4, 1e4)?,
                    check(M, "ve", f64::from(s.ve), -1e4, 1e4)?,
                    check(M, "vd", f64::from(s.vd), -1e4, 1e4)?,
                ];
                self.sim_state = Some((now, alt, v));
                Ok(None)
            }
            MavMessage::SIMSTATE(s) => {
                const M: &str = "SIMSTATE";
                let lat = check(M, "lat", f64::from(s.lat) * 1e-7, -90.0, 90.0)?;
                let lon = check(M, "lng", f64::from(s.lng) * 1e-7, -180.0, 180.0)?;
                let rpy = [
                    check(M, "roll", f64::from(s.roll), -7.0, 7.0)?,
                    check(M, "pitch", f64::from(s.pitch), -7.0, 7.0)?,
                    check(M, "yaw", f64::from(s.yaw), -7.0, 7.0)?,
                ];
                let gyro = f3(M, "gyro", [s.xgyro, s.ygyro, s.zgyro])?;
                let accel = f3(M, "acc", [s.xacc, s.yacc, s.zacc])?;
                let Some((t_alt, alt, vel)) = self.sim_state else {
                    return Ok(None);
                };
                let dt_alt_s = now.saturating_duration_since(t_alt).as_secs_f64();
                let Some((t_ref, boot_us)) = self.time_ref else {
                    return Ok(None);
                };
                let dt_ref = now.saturating_duration_since(t_ref);
                if dt_alt_s > MAX_PAIR_AGE_S || dt_ref.as_secs_f64() > MAX_TIME_REF_AGE_S {
                    return Ok(None);
                }
                let t_us = boot_us + dt_ref.as_micros() as u64;
                Ok(Some((
                    t_us,
                    TruthState {
                        lat_deg: lat,
                        lon_deg: lon,
                        alt_amsl_m: alt - vel[2] * dt_alt_s,
                        vel_ned_m_s: vel,
                        rpy_rad: rpy,
                        gyro_body_rad_s: gyro,
                        accel_body_m_s2: accel,
                    },
                )))
            }
            MavMessage::HIL_STATE_QUATERNION(h) => {
                const M: &str = "HIL_STATE_QUATERNION";
                let q = h.attitude_quaternion.map(f64::from);
                if q.iter().any(|v| !v.is_finite()) {
                    return Err(TruthReject::BadField {
                        msg: M,
                        field: "attitude_quaternion",
                        value: f64::NAN,
                    });
                }
                let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
                check(M, "attitude_quaternion norm", n, 0.5, 1.5)?;
                let uq = UnitQuaternion::from_quaternion(Quaternion::new(q[0], q[1], q[2], q[3]));
                let (roll, pitch, yaw) = uq.euler_angles();
                let lat = check(M, "lat", f64::from(h.lat) * 1e-7, -90.0, 90.0)?;
                let lon = check(M, "lon", f64::from(h.lon) * 1e-7, -180.0, 180.0)?;
                let alt = check(M, "alt", f64::from(h.alt) * 1e-3, -1000.0, 100_000.0)?;
                let t_us = if h.time_usec != 0 && h.time_usec < 1_000_000_000_000 {
                    h.time_usec
                } else {
                    match self.time_ref {
                        Some((t_ref, boot_us))
                            if now.saturating_duration_since(t_ref).as_secs_f64()
                                <= MAX_TIME_REF_AGE_S =>
                        {
                            boot_us + now.saturating_duration_since(t_ref).as_micros() as u64
                        }
                        _ => return Ok(None),
                    }
                };
                Ok(Some((
                    t_us,
                    TruthState {
                        lat_deg: lat,
                        lon_deg: lon,
                        alt_amsl_m: alt,
                        vel_ned_m_s: [
                            f64::from(h.vx) * 0.01,
                            f64::from(h.vy) * 0.01,
                            f64::from(h.vz) * 0.01,
                        ],
                        rpy_rad: [roll, pitch, yaw],
                        gyro_body_rad_s: f3(M, "rates", [h.rollspeed, h.pitchspeed, h.yawspeed])?,
                        // Not in PX4's ground truth (see the module doc).
                        accel_body_m_s2: [0.0; 3],
                    },
                )))
            }
            _ => Ok(None),
        }
    }
}

/// Settings of the truth connection.
#[derive(Debug, Clone)]
pub struct TruthLinkConfig {
    /// `mavlink` crate connection string, e.g. `udpin:127.0.0.1:14552`.
    pub connection: String,
    /// Which simulator speaks there.
    pub kind: SitlKind,
    /// System id of the simulated autopilot (ArduPilot and PX4 SITL: 1).
    pub autopilot_system_id: u8,
    /// Our system id on this connection (a GCS id that the daemon's link does not use).
    pub system_id: u8,
    /// Rate asked for the truth messages, Hz.
    pub rate_hz: f64,
}

impl TruthLinkConfig {
    /// The settings for `connection` and `kind`: autopilot system id 1, our system id 246,
    /// 50 Hz.
    pub fn new(connection: impl Into<String>, kind: SitlKind) -> Self {
        Self {
            connection: connection.into(),
            kind,
            autopilot_system_id: 1,
            system_id: 246,
            rate_hz: 50.0,
        }
    }
}

/// Why the truth connection could not start.
#[derive(Debug, thiserror::Error)]
pub enum TruthLinkError {
    /// The connection could not be opened.
    #[error("truth connection {connection}: {cause}")]
    Connect {
        /// The connection string.
        connection: String,
        /// Why it failed.
        cause: std::io::Error,
    },
    /// The requested rate (Hz) is outside 1..=400.
    #[error("truth connection: rate_hz {0} must be within 1..=400")]
    Rate(f64),
}

/// Counters of the truth connection.
#[derive(Debug, Default)]
pub struct TruthCounters {
    /// Truth samples published (newer than the one held, or after a reboot).
    pub samples: AtomicU64,
    /// Truth messages ignored for an unusable value.
    pub rejected: AtomicU64,
    /// Message interval requests (MAV_CMD_SET_MESSAGE_INTERVAL) sent.
    pub requests: AtomicU64,
}

/// The latest truth sample, shared between the reader task and the camera.
#[derive(Debug, Default)]
pub struct SharedTruth {
    latest: Mutex<Option<(u64, TruthState)>>,
    /// The connection's counters.
    pub counters: TruthCounters,
}

impl SharedTruth {
    /// Publish a sample (ignored when not newer than the held one, unless the autopilot time
    /// went back by more than 1 s: a reboot).
    pub fn publish(&self, t_us: u64, s: TruthState) {
        let mut l = self.latest.lock().unwrap_or_else(|e| e.into_inner());
        let take = match *l {
            Some((t0, _)) => t_us > t0 || t_us + 1_000_000 < t0,
            None => true,
        };
        if take {
            *l = Some((t_us, s));
            self.counters.samples.fetch_add(1, Ordering::Relaxed);
        }
    }
}

impl TruthFeed for SharedTruth {
    fn latest(&self) -> Option<(u64, TruthState)> {
        *self.latest.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// The running truth connection (stops when dropped or on [`TruthLink::shutdown`]).
pub struct TruthLink {
    shared: Arc<SharedTruth>,
    stop: watch::Sender<bool>,
    task: Option<JoinHandle<()>>,
}

type Conn = mavlink::AsyncConnection<MavMessage>;

impl TruthLink {
    /// Open the connection and start reading (see the module doc).
    pub async fn start(cfg: TruthLinkConfig) -> Result<TruthLink, TruthLinkError> {
        if !(cfg.rate_hz.is_finite() && (1.0..=400.0).contains(&cfg.rate_hz)) {
            return Err(TruthLinkError::Rate(cfg.rate_hz));
        }
        let mut conn = mavlink::connect_async::<MavMessage>(&cfg.connection)
            .await
            .map_err(|source| TruthLinkError::Connect {
                connection: cfg.connection.clone(),
                cause: source,
            })?;
        conn.set_allow_recv_any_version(true);
        info!(connection = %cfg.connection, kind = %cfg.kind, "truth connection open");
        let shared = Arc::new(SharedTruth::default());
        let (stop, stop_rx) = watch::channel(false);
        let task = tokio::spawn(run(Arc::new(conn), cfg, shared.clone(), stop_rx));
        Ok(TruthLink {
            shared,
            stop,
            task: Some(task),
        })
    }

    /// The feed for [`super::camera_sim::SimCamera`].
    pub fn feed(&self) -> Arc<SharedTruth> {
        self.shared.clone()
    }

    /// Wait until the first truth sample arrives (or `timeout`); true when one did.
    pub async fn wait_first(&self, timeout: Duration) -> bool {
        let until = Instant::now() + timeout;
        while Instant::now() < until {
            if self.shared.latest().is_some() {
                return true;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        self.shared.latest().is_some()
    }

    /// Stop the reader task.
    pub async fn shutdown(mut self) {
        let _ = self.stop.send(true);
        if let Some(t) = self.task.take() {
            let _ = tokio::time::timeout(Duration::from_secs(2), t).await;
        }
    }
}

impl Drop for TruthLink {
    fn drop(&mut self) {
        if let Some(t) = self.task.take() {
            t.abort();
        }
    }
}

async fn send(conn: &Conn, cfg: &TruthLinkConfig, seq: &mut u8, msg: &MavMessage) {
    let header = MavHeader {
        system_id: u32::from(cfg.system_id),
        component_id: 190, // MAV_COMP_ID_MISSIONPLANNER (a GCS)
        sequence: *seq,
    };
    *seq = seq.wrapping_add(1);
    if let Err(e) = conn.send(&header, msg).await {
        debug!("truth connection send: {e}");
    }
}

async fn run(
    conn: Arc<Conn>,
    cfg: TruthLinkConfig,
    shared: Arc<SharedTruth>,
    mut stop: watch::Receiver<bool>,
) {
    let mut decoder = TruthDecoder::new();
    let mut seq = 0u8;
    let mut last_seen: std::collections::HashMap<u32, Instant> = Default::default();
    let mut tick = tokio::time::interval(Duration::from_secs(1));
    let mut n_tick = 0u64;
    let mut last_reject_log: Option<Instant> = None;
    loop {
        tokio::select! {
            _ = stop.changed() => return,
            _ = tick.tick() => {
                let hb = MavMessage::HEARTBEAT(HEARTBEAT_DATA {
                    custom_mode: 0,
                    mavtype: MavType::MAV_TYPE_GCS,
                    autopilot: MavAutopilot::MAV_AUTOPILOT_INVALID,
                    base_mode: MavModeFlag::empty(),
                    system_status: MavState::MAV_STATE_ACTIVE,
                    mavlink_version: 3,
                });
                send(&conn, &cfg, &mut seq, &hb).await;
                n_tick += 1;
                if n_tick % 2 == 1 {
                    let now = Instant::now();
                    for &id in cfg.kind.requested_ids() {
                        let fresh = last_seen
                            .get(&id)
                            .is_some_and(|t| now.duration_since(*t) < Duration::from_secs(1));
                        if fresh {
                            continue;
                        }
                        let m = MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
                            param1: id as f32,
                            param2: (1e6 / cfg.rate_hz) as f32,
                            target_system: cfg.autopilot_system_id,
                            target_component: 1,
                            command: MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL,
                            ..COMMAND_LONG_DATA::DEFAULT
                        });
                        shared.counters.requests.fetch_add(1, Ordering::Relaxed);
                        send(&conn, &cfg, &mut seq, &m).await;
                    }
                }
            }
            r = conn.recv() => match r {
                Ok((h, m)) => {
                    if h.system_id != u32::from(cfg.autopilot_system_id) {
                        continue;
                    }
                    let now = Instant::now();
                    last_seen.insert(mavlink::Message::message_id(&m), now);
                    match decoder.on_message(&m, now) {
                        Ok(Some((t_us, s))) => shared.publish(t_us, s),
                        Ok(None) => {}
                        Err(e) => {
                            shared.counters.rejected.fetch_add(1, Ordering::Relaxed);
                            if last_reject_log.is_none_or(|t| now.duration_since(t) > Duration::from_secs(5)) {
                                warn!("truth connection: {e}; ignored");
                                last_reject_log = Some(now);
                            }
                        }
                    }
                }
                Err(e) => {
                    // UDP: a malformed datagram; TCP: the peer went away (retry shortly).
                    debug!("truth connection receive: {e}");
                    tokio::time::sleep(Duration::from_millis(10)).await;
                }
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mavlink::dialects::ardupilotmega::{
        ATTITUDE_DATA, HIL_STATE_QUATERNION_DATA, SIM_STATE_DATA, SIMSTATE_DATA,
    };

    fn simstate(lat: i32, lng: i32) -> MavMessage {
        MavMessage::SIMSTATE(SIMSTATE_DATA {
            roll: 0.1,
            pitch: -0.05,
            yaw: 2.0,
            xacc: 0.5,
            yacc: -0.25,
            zacc: -9.75,
            xgyro: 0.01,
            ygyro: 0.02,
            zgyro: -0.03,
            lat,
            lng,
        })
    }

    fn sim_state(alt: f32, vd: f32) -> MavMessage {
        MavMessage::SIM_STATE(SIM_STATE_DATA {
            alt,
            vn: 3.0,
            ve: -4.0,
            vd,
            ..SIM_STATE_DATA::DEFAULT
        })
    }

    #[test]
    fn simstate_needs_sim_state_and_a_time_reference() {
        let t0 = Instant::now();
        let mut d = TruthDecoder::new();
        assert_eq!(d.on_message(&simstate(470203485, -991548094), t0), Ok(None));
        d.on_message(&sim_state(980.0, -2.0), t0).unwrap();
        assert_eq!(d.on_message(&simstate(470203485, -991548094), t0), Ok(None));
        let att = MavMessage::ATTITUDE(ATTITUDE_DATA {
            time_boot_ms: 123_456,
            ..ATTITUDE_DATA::DEFAULT
        });
        d.on_message(&att, t0).unwrap();
        let t1 = t0 + Duration::from_millis(20);
        let (t_us, s) = d
            .on_message(&simstate(470203485, -991548094), t1)
            .unwrap()
            .unwrap();
        assert_eq!(t_us, 123_456_000 + 20_000);
        assert_eq!(s.lat_deg, 470203485.0 * 1e-7);
        assert_eq!(s.lon_deg, -991548094.0 * 1e-7);
        // Climbing at 2 m/s for 20 ms since the SIM_STATE.
        assert!((s.alt_amsl_m - 980.04).abs() < 1e-9, "{}", s.alt_amsl_m);
        assert_eq!(s.vel_ned_m_s, [3.0, -4.0, -2.0]);
        assert_eq!(s.rpy_rad, [0.1f32, -0.05, 2.0].map(f64::from));
        assert_eq!(s.gyro_body_rad_s, [0.01f32, 0.02, -0.03].map(f64::from));
        assert_eq!(s.accel_body_m_s2, [0.5, -0.25, -9.75]);
        // Stale SIM_STATE: no sample.
        let late = t0 + Duration::from_secs_f64(MAX_PAIR_AGE_S + 0.01);
        d.on_message(&att, late).unwrap();
        assert_eq!(d.on_message(&simstate(1, 1), late), Ok(None));
    }

    #[test]
    fn bad_values_are_rejected() {
        let t0 = Instant::now();
        let mut d = TruthDecoder::new();
        assert!(d.on_message(&sim_state(f32::NAN, 0.0), t0).is_err());
        assert!(d.on_message(&simstate(910_000_000, 0), t0).is_err());
        let mut m = simstate(0, 0);
        if let MavMessage::SIMSTATE(s) = &mut m {
            s.roll = f32::INFINITY;
        }
        assert!(d.on_message(&m, t0).is_err());
        let h = MavMessage::HIL_STATE_QUATERNION(HIL_STATE_QUATERNION_DATA {
            attitude_quaternion: [0.0; 4],
            ..HIL_STATE_QUATERNION_DATA::DEFAULT
        });
        assert!(d.on_message(&h, t0).is_err());
    }

    #[test]
    fn hil_state_quaternion_is_one_sample() {
        let (r, p, y) = (0.2f64, -0.1f64, -2.5f64);
        let q = UnitQuaternion::from_euler_angles(r, p, y);
        let h = MavMessage::HIL_STATE_QUATERNION(HIL_STATE_QUATERNION_DATA {
            time_usec: 77_000_123,
            attitude_quaternion: [q.w as f32, q.i as f32, q.j as f32, q.k as f32],
            lat: 470_000_001,
            lon: -991_000_002,
            alt: 1_080_250,
            vx: 150,
            vy: -20,
            vz: 5,
            xacc: 3,
            ..HIL_STATE_QUATERNION_DATA::DEFAULT
        });
        let t0 = Instant::now();
        let mut d = TruthDecoder::new();
        let (t, s) = d.on_message(&h, t0).unwrap().unwrap();
        assert_eq!(t, 77_000_123);
        assert_eq!((s.lat_deg, s.lon_deg), (47.0000001, -99.1000002));
        assert!((s.alt_amsl_m - 1080.25).abs() < 1e-9);
        assert_eq!(s.vel_ned_m_s, [1.5, -0.2, 0.05]);
        for (a, b) in s.rpy_rad.iter().zip([r, p, y]) {
            assert!((a - b).abs() < 1e-6, "{a} vs {b}");
        }
        assert_eq!(s.accel_body_m_s2, [0.0; 3]);
        // PX4's GROUND_TRUTH stream sends time_usec = 0: the time of the latest ATTITUDE.
        let mut h0 = h.clone();
        if let MavMessage::HIL_STATE_QUATERNION(x) = &mut h0 {
            x.time_usec = 0;
        }
        assert_eq!(d.on_message(&h0, t0), Ok(None));
        let att = MavMessage::ATTITUDE(ATTITUDE_DATA {
            time_boot_ms: 5_000,
            ..ATTITUDE_DATA::DEFAULT
        });
        d.on_message(&att, t0).unwrap();
        let (t, _) = d
            .on_message(&h0, t0 + Duration::from_millis(3))
            .unwrap()
            .unwrap();
        assert_eq!(t, 5_003_000);
    }

    #[test]
    fn publish_keeps_the_newest_and_follows_a_reboot() {
        let s = SharedTruth::default();
        let st = TruthState {
            lat_deg: 1.0,
            lon_deg: 2.0,
            alt_amsl_m: 3.0,
            vel_ned_m_s: [0.0; 3],
            rpy_rad: [0.0; 3],
            gyro_body_rad_s: [0.0; 3],
            accel_body_m_s2: [0.0; 3],
        };
        s.publish(5_000_000, st);
        s.publish(4_900_000, TruthState { lat_deg: 9.0, ..st });
        assert_eq!(s.latest().map(|l| l.0), Some(5_000_000));
        s.publish(1_000, TruthState { lat_deg: 9.0, ..st });
        assert_eq!(s.latest().map(|l| (l.0, l.1.lat_deg)), Some((1_000, 9.0)));
    }
}
