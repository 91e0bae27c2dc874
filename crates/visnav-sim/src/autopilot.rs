//! MAVLink autopilot emulator: a tokio task that behaves like ArduPilot on a telemetry link, over
//! real UDP/TCP sockets, for the link's end-to-end tests and the closed-loop simulator.
//!
//! Behaviour (as ArduPilot 4.x on a serial/UDP port):
//! * HEARTBEAT at 1 Hz as MAV_TYPE_QUADROTOR / MAV_AUTOPILOT_ARDUPILOTMEGA, MAVLink 2.
//! * Streams nothing else until MAV_CMD_SET_MESSAGE_INTERVAL asks; then honours the interval
//!   (param2 µs; -1 disables; 0 = default rate, taken as 4 Hz). Supported: SYSTEM_TIME,
//!   GPS_RAW_INT, GPS2_RAW (the same receiver data), SCALED_IMU, RAW_IMU, SCALED_PRESSURE, ATTITUDE, GLOBAL_POSITION_INT. Others
//!   (e.g. HIGHRES_IMU, which ArduPilot does not send) are answered MAV_RESULT_FAILED.
//! * Every COMMAND_LONG is answered with COMMAND_ACK; MAV_CMD_REQUEST_MESSAGE for
//!   GPS_GLOBAL_ORIGIN sends the origin when one is set.
//! * TIMESYNC requests (tc1 = 0) are answered with tc1 = boot time in ns.
//! * SET_GPS_GLOBAL_ORIGIN sets the origin and is echoed with GPS_GLOBAL_ORIGIN.
//! * [`AutopilotEmulator::reboot`] restarts its boot clock at 0 and forgets intervals and origin.
//! * [`EmulatorConfig::px4_imu`]: the IMU as PX4 v1.14 streams it instead. HEARTBEAT says
//!   MAV_AUTOPILOT_PX4; HIGHRES_IMU becomes streamable and carries the IMU sample minus the
//!   autopilot's bias estimate ([`TruthSource::autopilot_imu_bias`], EKF2's), while SCALED_IMU
//!   carries the same sample without it, truncated to int16 mrad/s and mG; both take the newest
//!   sample of a 250 Hz IMU (PX4's `vehicle_imu`), so the two streams share samples.
//! * Every GPS_INPUT, VISION_POSITION_ESTIMATE, ODOMETRY, GLOBAL_POSITION_SENSOR,
//!   SET_GPS_GLOBAL_ORIGIN and STATUSTEXT received is recorded with its boot time of arrival.
//!
//! Telemetry comes from a caller-provided [`TruthSource`] evaluated at the emulator's run time in
//! seconds (time since it started: a reboot restarts the boot clock the messages carry, not the
//! flight), its `imu` and `gps` methods give the IMU and GPS readings, by default the truth itself
//! (the closed-loop simulator adds sensor errors, GPS outages and scripted faults there), and its
//! `link_faults` scripts silence, reboots and UTC clock steps ([`LinkFaults`]).
//! Units sent follow the MAVLink definitions (ATTITUDE rad, GLOBAL_POSITION_INT 1e7 deg / mm /
//! cm/s, SCALED_IMU mG / mrad/s, SCALED_PRESSURE hPa from the ISA troposphere model
//! `p = 1013.25 (1 - 2.25577e-5 h)^5.25588`).

use std::collections::HashMap;
use std::sync::atomic::{AtomicU8, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;
// tokio's clock: real time, or the lock-step simulator's when the runtime runs paused.
use tokio::time::Instant;

#[allow(deprecated)] // SET_GPS_GLOBAL_ORIGIN: still what ArduPilot acts on
use mavlink::dialects::ardupilotmega::{
    ATTITUDE_DATA, COMMAND_ACK_DATA, GLOBAL_POSITION_INT_DATA, GPS_GLOBAL_ORIGIN_DATA,
    GPS_RAW_INT_DATA, GPS2_RAW_DATA, GpsFixType, HEARTBEAT_DATA, HIGHRES_IMU_DATA, MavAutopilot,
    MavCmd, MavMessage, MavModeFlag, MavResult, MavState, MavType, RAW_IMU_DATA, SCALED_IMU_DATA,
    SCALED_PRESSURE_DATA, SYSTEM_TIME_DATA, TIMESYNC_DATA,
};
use mavlink::{AsyncMavConnection, MavHeader, Message, SigningConfig};
use tokio::task::JoinHandle;

/// Standard gravity, m/s^2.
const G0_M_S2: f64 = 9.806_65;

/// Vehicle truth at one instant (the emulator's sensors read it without error).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TruthState {
    /// Latitude, degrees.
    pub lat_deg: f64,
    /// Longitude, degrees.
    pub lon_deg: f64,
    /// Altitude AMSL, metres.
    pub alt_amsl_m: f64,
    /// Velocity NED, m/s.
    pub vel_ned_m_s: [f64; 3],
    /// Roll, pitch, yaw (ZYX, `R_ned_body = Rz(yaw) Ry(pitch) Rx(roll)`), rad.
    pub rpy_rad: [f64; 3],
    /// Body angular rate (FRD), rad/s.
    pub gyro_body_rad_s: [f64; 3],
    /// Specific force in body FRD (accelerometer reading), m/s^2.
    pub accel_body_m_s2: [f64; 3],
}

/// Scripted link faults at an instant (`sitl::faults`), asked by the emulator on every tick.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct LinkFaults {
    /// Send nothing (still receive).
    pub silent: bool,
    /// Reboots scripted so far: the emulator reboots when this exceeds the ones it has done.
    pub reboots: u32,
    /// Added to SYSTEM_TIME's UTC, µs (a stepped autopilot clock).
    pub utc_offset_us: i64,
}

/// Source of truth: the vehicle state at run time `t_s` (seconds since the emulator started; a
/// reboot does not reset it).
pub trait TruthSource: Send + Sync + 'static {
    /// State at `t_s`.
    fn state(&self, t_s: f64) -> TruthState;
    /// The IMU sample sent at `t_s` (SCALED_IMU / RAW_IMU): `(gyro_body_rad_s,
    /// accel_body_m_s2)`. Default: the truth without error. Called once per IMU message, with
    /// increasing `t_s`, so a source can model sensor errors over the interval since the last
    /// call.
    fn imu(&self, t_s: f64) -> ([f64; 3], [f64; 3]) {
        let s = self.state(t_s);
        (s.gyro_body_rad_s, s.accel_body_m_s2)
    }
    /// The body rates ATTITUDE reports at `t_s` (`rollspeed`, `pitchspeed`, `yawspeed`, float
    /// rad/s; ArduPilot sends its AHRS's gyro). Default: the truth.
    fn attitude_rates(&self, t_s: f64) -> [f64; 3] {
        self.state(t_s).gyro_body_rad_s
    }
    /// The autopilot's own IMU bias estimate at `t_s` that a PX4-like emulator subtracts from
    /// HIGHRES_IMU ([`EmulatorConfig::px4_imu`]): `(gyro rad/s, accel m/s^2)`. Default: zero.
    fn autopilot_imu_bias(&self, t_s: f64) -> ([f64; 3], [f64; 3]) {
        let _ = t_s;
        ([0.0; 3], [0.0; 3])
    }
    /// What the GPS receiver reports at `t_s` (GPS_RAW_INT): `None` = no fix (an outage).
    /// Default: the truth without error, always available.
    fn gps(&self, t_s: f64) -> Option<TruthState> {
        Some(self.state(t_s))
    }
    /// Scripted link faults at `t_s`. Default: none.
    fn link_faults(&self, t_s: f64) -> LinkFaults {
        let _ = t_s;
        LinkFaults::default()
    }
}

impl<F: Fn(f64) -> TruthState + Send + Sync + 'static> TruthSource for F {
    fn state(&self, t_s: f64) -> TruthState {
        self(t_s)
    }
}

/// Level flight at constant NED velocity from a start point (small-area flat-earth propagation).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ConstantVelocity {
    /// Start latitude, degrees.
    pub lat_deg: f64,
    /// Start longitude, degrees.
    pub lon_deg: f64,
    /// Start altitude AMSL, metres.
    pub alt_amsl_m: f64,
    /// Velocity NED, m/s.
    pub vel_ned_m_s: [f64; 3],
    /// Heading, rad.
    pub yaw_rad: f64,
}

impl TruthSource for ConstantVelocity {
    fn state(&self, t_s: f64) -> TruthState {
        let r_earth_m = 6_371_000.0;
        let [vn, ve, vd] = self.vel_ned_m_s;
        TruthState {
            lat_deg: self.lat_deg + (vn * t_s / r_earth_m).to_degrees(),
            lon_deg: self.lon_deg
                + (ve * t_s / (r_earth_m * self.lat_deg.to_radians().cos())).to_degrees(),
            alt_amsl_m: self.alt_amsl_m - vd * t_s,
            vel_ned_m_s: self.vel_ned_m_s,
            rpy_rad: [0.0, 0.0, self.yaw_rad],
            gyro_body_rad_s: [0.0; 3],
            accel_body_m_s2: [0.0, 0.0, -G0_M_S2],
        }
    }
}

/// GPS_RAW_INT's `vel` (ground speed, cm/s) and `cog` (course over ground, cdeg in
/// [0, 36000)) of a NED velocity; a speed beyond the field's range is sent as unknown.
fn gps_vel_cog(v_ned_m_s: [f64; 3]) -> (u16, u16) {
    let speed_cm_s = (v_ned_m_s[0].hypot(v_ned_m_s[1]) * 100.0).round();
    if !(speed_cm_s.is_finite() && (0.0..f64::from(u16::MAX)).contains(&speed_cm_s)) {
        return (u16::MAX, u16::MAX);
    }
    let cog_cdeg = (v_ned_m_s[1].atan2(v_ned_m_s[0]).to_degrees() * 100.0)
        .round()
        .rem_euclid(36_000.0);
    (speed_cm_s as u16, cog_cdeg as u16)
}

/// Emulator settings.
#[derive(Debug, Clone)]
pub struct EmulatorConfig {
    /// mavlink connection string: `udpout:127.0.0.1:PORT` (like SITL's `--out`) or
    /// `tcpin:127.0.0.1:PORT` (like SITL's TCP 5760 server).
    pub connection: String,
    /// Our system id.
    pub system_id: u8,
    /// Our component id (1 = MAV_COMP_ID_AUTOPILOT1).
    pub component_id: u8,
    /// Unix time at boot (µs) for SYSTEM_TIME; `None` = no clock (GPS-denied: time_unix_usec 0).
    pub unix_at_boot_us: Option<u64>,
    /// GPS_RAW_INT reports a 3D fix (true) or NO_FIX (false).
    pub gps_fix: bool,
    /// Require signed messages with this key (MAVLink 2 signing); unsigned ones are dropped.
    pub signing_key: Option<[u8; 32]>,
    /// Stream the IMU as PX4 does (see the module doc) and announce MAV_AUTOPILOT_PX4.
    pub px4_imu: bool,
    /// GPS_RAW_INT / GPS2_RAW carry the receiver's ground speed and course (`vel` cm/s, `cog`
    /// cdeg, from [`TruthSource::gps`]'s velocity), as ArduPilot sends them; false: both
    /// UINT16_MAX (unknown).
    pub gps_velocity: bool,
}

impl EmulatorConfig {
    /// The flight stack the emulator announces: PX4 with [`Self::px4_imu`], else ArduPilot.
    pub fn autopilot(&self) -> MavAutopilot {
        if self.px4_imu {
            MavAutopilot::MAV_AUTOPILOT_PX4
        } else {
            MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA
        }
    }

    /// The local frame the announced flight stack keeps (its projection about its origin): how
    /// the local positions it receives are read back.
    pub fn local_frame(&self) -> visnav_core::geo::AutopilotFrame {
        visnav_link::inject::projection_of(Some(self.autopilot()))
    }

    /// ArduPilot-like defaults on `connection`: system 1, component 1, no clock, no GPS fix.
    pub fn new(connection: &str) -> Self {
        Self {
            connection: connection.to_string(),
            system_id: 1,
            component_id: 1,
            unix_at_boot_us: None,
            gps_fix: false,
            signing_key: None,
            px4_imu: false,
            gps_velocity: false,
        }
    }
}

/// A message received by the emulator.
#[derive(Debug, Clone)]
pub struct Received {
    /// Emulator boot time at arrival, µs.
    pub t_boot_us: u64,
    /// Emulator run time at arrival (not reset by a reboot), µs.
    pub t_run_us: u64,
    /// Boot counter at arrival (0 before the first reboot).
    pub boot: u32,
    /// Sender header.
    pub header: MavHeader,
    /// The message.
    pub msg: MavMessage,
}

#[derive(Debug)]
struct EmuState {
    /// When the emulator started (run time 0).
    start: Instant,
    boot: Instant,
    /// The boot before the current one.
    previous_boot: Option<Instant>,
    boots: u32,
    /// Reboots done for [`LinkFaults::reboots`].
    fault_reboots: u32,
    /// [`LinkFaults::silent`] now.
    fault_silent: bool,
    intervals: HashMap<u32, (Duration, Instant)>,
    origin: Option<GPS_GLOBAL_ORIGIN_DATA>,
    received: Vec<Received>,
    all_ids: HashMap<u32, u64>,
    companion: Option<(u8, u8)>,
    muted: bool,
    /// Booting after [`AutopilotEmulator::reboot`]: silent until then.
    booting_until: Option<Instant>,
}

struct Inner {
    cfg: EmulatorConfig,
    state: Mutex<EmuState>,
    seq: AtomicU8,
    truth: Box<dyn TruthSource>,
    /// PX4 mode: the newest 250 Hz IMU sample (slot index, gyro rad/s, accel m/s^2).
    px4_sample: Mutex<Option<Px4Sample>>,
}

/// A PX4 `vehicle_imu` sample: (slot index, gyro rad/s, accel m/s^2).
type Px4Sample = (u64, [f64; 3], [f64; 3]);

/// PX4's `vehicle_imu` interval, µs.
const PX4_IMU_SLOT_US: u64 = 4_000;

/// A running emulator. Dropping it stops it.
pub struct AutopilotEmulator {
    inner: Arc<Inner>,
    task: JoinHandle<()>,
}

type Conn = mavlink::AsyncConnection<MavMessage>;

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// Message ids the emulator can stream (and HIGHRES_IMU, 105, with `px4_imu`).
pub const STREAMABLE: [u32; 8] = [2, 24, 26, 27, 29, 30, 33, 124];

impl AutopilotEmulator {
    /// Open the connection and start emulating. For `tcpin` this returns at once and the task
    /// waits for the client.
    pub async fn start(cfg: EmulatorConfig, truth: impl TruthSource) -> std::io::Result<Self> {
        let inner = Arc::new(Inner {
            cfg,
            state: Mutex::new(EmuState {
                start: Instant::now(),
                boot: Instant::now(),
                previous_boot: None,
                boots: 0,
                fault_reboots: 0,
                fault_silent: false,
                intervals: HashMap::new(),
                origin: None,
                received: Vec::new(),
                all_ids: HashMap::new(),
                companion: None,
                muted: false,
                booting_until: None,
            }),
            seq: AtomicU8::new(0),
            truth: Box::new(truth),
            px4_sample: Mutex::new(None),
        });
        // Validate the address now so a typo fails the caller, not the task.
        mavlink::ConnectionAddress::parse_address(&inner.cfg.connection)?;
        let task = tokio::spawn(run(inner.clone()));
        Ok(Self { inner, task })
    }

    /// Boot time now, µs.
    pub fn time_boot_us(&self) -> u64 {
        lock(&self.inner.state).boot.elapsed().as_micros() as u64
    }

    /// Run time now (since the emulator started; not reset by a reboot), µs.
    pub fn time_run_us(&self) -> u64 {
        lock(&self.inner.state).start.elapsed().as_micros() as u64
    }

    /// Boot time and run time now, µs (read together: a reboot cannot fall between them).
    pub fn times_us(&self) -> (u64, u64) {
        let st = lock(&self.inner.state);
        (
            st.boot.elapsed().as_micros() as u64,
            st.start.elapsed().as_micros() as u64,
        )
    }

    /// The run time of boot time `t_boot_us`, µs: of the current boot, or of the one before
    /// when `t_boot_us` is later than the current boot's clock (a time stamped just before a
    /// reboot).
    pub fn run_us_of_boot_us(&self, t_boot_us: u64) -> u64 {
        let st = lock(&self.inner.state);
        let boot_start = if t_boot_us <= st.boot.elapsed().as_micros() as u64 {
            st.boot
        } else {
            st.previous_boot.unwrap_or(st.boot)
        };
        (boot_start - st.start).as_micros() as u64 + t_boot_us
    }

    /// Restart the boot clock at 0; forget stream intervals and the EKF origin (like a reboot).
    /// Like a real autopilot it is silent while it boots ([`BOOT_SILENCE`]).
    pub fn reboot(&self) {
        reboot(&mut lock(&self.inner.state));
    }

    /// Stop (true) or resume (false) sending anything, keeping the connection open (a hung
    /// autopilot or a half-open TCP connection).
    pub fn set_muted(&self, muted: bool) {
        lock(&self.inner.state).muted = muted;
    }

    /// Every recorded injection / status message so far.
    pub fn received(&self) -> Vec<Received> {
        lock(&self.inner.state).received.clone()
    }

    /// Every recorded message so far, moved out (the recording starts again empty).
    pub fn take_received(&self) -> Vec<Received> {
        std::mem::take(&mut lock(&self.inner.state).received)
    }

    /// Bytes held by the recording of [`Self::received`] (its buffer).
    pub fn recorded_bytes(&self) -> usize {
        lock(&self.inner.state).received.capacity() * std::mem::size_of::<Received>()
    }

    /// Count of messages received per message id (everything, not only recorded ones).
    pub fn received_counts(&self) -> HashMap<u32, u64> {
        lock(&self.inner.state).all_ids.clone()
    }

    /// Current interval of a stream, if requested.
    pub fn stream_interval(&self, id: u32) -> Option<Duration> {
        lock(&self.inner.state).intervals.get(&id).map(|(d, _)| *d)
    }

    /// The (system, component) of the last companion heard.
    pub fn companion(&self) -> Option<(u8, u8)> {
        lock(&self.inner.state).companion
    }

    /// The origin set by SET_GPS_GLOBAL_ORIGIN, if any.
    pub fn origin(&self) -> Option<GPS_GLOBAL_ORIGIN_DATA> {
        lock(&self.inner.state).origin.clone()
    }

    /// Stop the emulator.
    pub fn stop(self) {
        self.task.abort();
    }
}

impl Drop for AutopilotEmulator {
    fn drop(&mut self) {
        self.task.abort();
    }
}

/// How long a rebooting autopilot says nothing (ArduPilot and PX4 take 1-3 s to boot).
pub const BOOT_SILENCE: Duration = Duration::from_millis(1000);

fn reboot(st: &mut EmuState) {
    st.previous_boot = Some(st.boot);
    st.boot = Instant::now();
    st.booting_until = Some(st.boot + BOOT_SILENCE);
    st.boots += 1;
    st.intervals.clear();
    st.origin = None;
}

async fn send(inner: &Inner, conn: &Conn, msg: &MavMessage) {
    {
        let st = lock(&inner.state);
        if st.muted || st.fault_silent || st.booting_until.is_some_and(|t| Instant::now() < t) {
            return;
        }
    }
    let header = MavHeader {
        system_id: u32::from(inner.cfg.system_id),
        component_id: inner.cfg.component_id,
        sequence: inner.seq.fetch_add(1, Ordering::Relaxed),
    };
    let _ = conn.send(&header, msg).await;
}

/// Aborts its task when dropped.
pub(crate) struct AbortOnDrop(pub(crate) JoinHandle<()>);

impl Drop for AbortOnDrop {
    fn drop(&mut self) {
        self.0.abort();
    }
}

async fn run(inner: Arc<Inner>) {
    loop {
        let Ok(mut conn) = mavlink::connect_async::<MavMessage>(&inner.cfg.connection).await else {
            tokio::time::sleep(Duration::from_millis(200)).await;
            continue;
        };
        conn.set_allow_recv_any_version(true);
        if let Some(key) = inner.cfg.signing_key {
            conn.setup_signing(Some(SigningConfig::new(key, 0, true, false)));
        }
        let conn = Arc::new(conn);
        // Aborted when this task is (emulator dropped) or the client goes away.
        let _tx = AbortOnDrop(tokio::spawn(tx_loop(inner.clone(), conn.clone())));
        loop {
            match conn.recv().await {
                Ok((h, m)) => handle(&inner, &conn, h, m).await,
                Err(mavlink::error::MessageReadError::Io(_)) => break,
                Err(_) => continue,
            }
        }
        // TCP client went away: listen again.
    }
}

#[allow(deprecated)] // SET_GPS_GLOBAL_ORIGIN: still what ArduPilot acts on
async fn handle(inner: &Inner, conn: &Conn, h: MavHeader, m: MavMessage) {
    let (t_boot_us, t_run_us, boot) = {
        let mut st = lock(&inner.state);
        *st.all_ids.entry(m.message_id()).or_default() += 1;
        if let MavMessage::HEARTBEAT(_) = &m {
            st.companion = u8::try_from(h.system_id).ok().map(|s| (s, h.component_id));
        }
        (
            st.boot.elapsed().as_micros() as u64,
            st.start.elapsed().as_micros() as u64,
            st.boots,
        )
    };
    let record = matches!(
        m,
        MavMessage::GPS_INPUT(_)
            | MavMessage::VISION_POSITION_ESTIMATE(_)
            | MavMessage::ODOMETRY(_)
            | MavMessage::GLOBAL_POSITION_SENSOR(_)
            | MavMessage::SET_GPS_GLOBAL_ORIGIN(_)
            | MavMessage::STATUSTEXT(_)
    );
    if record {
        lock(&inner.state).received.push(Received {
            t_boot_us,
            t_run_us,
            boot,
            header: h,
            msg: m.clone(),
        });
    }
    match m {
        MavMessage::TIMESYNC(t) if t.tc1 == 0 => {
            let r = MavMessage::TIMESYNC(TIMESYNC_DATA {
                tc1: t_boot_us as i64 * 1000,
                ts1: t.ts1,
                target_system: u8::try_from(h.system_id).unwrap_or(0),
                target_component: h.component_id,
            });
            send(inner, conn, &r).await;
        }
        MavMessage::COMMAND_LONG(c) => {
            if c.target_system != inner.cfg.system_id && c.target_system != 0 {
                return;
            }
            let mut extra = None;
            let result = match c.command {
                MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL => {
                    let id = c.param1 as u32;
                    if !(STREAMABLE.contains(&id) || (id == 105 && inner.cfg.px4_imu)) {
                        MavResult::MAV_RESULT_FAILED
                    } else {
                        let mut st = lock(&inner.state);
                        if c.param2 < 0.0 {
                            st.intervals.remove(&id);
                        } else {
                            let us = if c.param2 == 0.0 {
                                250_000.0
                            } else {
                                c.param2 as f64
                            };
                            let d = Duration::from_secs_f64((us * 1e-6).max(0.001));
                            st.intervals.insert(id, (d, Instant::now()));
                        }
                        MavResult::MAV_RESULT_ACCEPTED
                    }
                }
                MavCmd::MAV_CMD_REQUEST_MESSAGE => {
                    if c.param1 as u32 == 49 {
                        match lock(&inner.state).origin.clone() {
                            Some(o) => {
                                extra = Some(MavMessage::GPS_GLOBAL_ORIGIN(o));
                                MavResult::MAV_RESULT_ACCEPTED
                            }
                            None => MavResult::MAV_RESULT_FAILED,
                        }
                    } else {
                        MavResult::MAV_RESULT_UNSUPPORTED
                    }
                }
                _ => MavResult::MAV_RESULT_UNSUPPORTED,
            };
            let ack = MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
                command: c.command,
                result,
                progress: 0,
                result_param2: 0,
                target_system: u8::try_from(h.system_id).unwrap_or(0),
                target_component: h.component_id,
            });
            send(inner, conn, &ack).await;
            if let Some(e) = extra {
                send(inner, conn, &e).await;
            }
        }
        MavMessage::SET_GPS_GLOBAL_ORIGIN(o) if o.target_system == inner.cfg.system_id => {
            let origin = GPS_GLOBAL_ORIGIN_DATA {
                latitude: o.latitude,
                longitude: o.longitude,
                altitude: o.altitude,
                time_usec: t_boot_us,
            };
            lock(&inner.state).origin = Some(origin.clone());
            send(inner, conn, &MavMessage::GPS_GLOBAL_ORIGIN(origin)).await;
        }
        _ => {}
    }
}

fn sat_i16(v: f64) -> i16 {
    v.round().clamp(f64::from(i16::MIN), f64::from(i16::MAX)) as i16
}

fn trunc_i16(v: f64) -> i16 {
    v.trunc().clamp(f64::from(i16::MIN), f64::from(i16::MAX)) as i16
}

fn isa_pressure_hpa(alt_m: f64) -> f64 {
    1013.25 * (1.0 - 2.255_77e-5 * alt_m).powf(5.255_88)
}

/// The emulator's clocks at one tick.
#[derive(Debug, Clone, Copy)]
struct Clocks {
    /// Boot time, µs (what the messages carry).
    boot_us: u64,
    /// Run time minus boot time, µs (the truth's time is `boot_us + run_minus_boot_us`).
    run_minus_boot_us: u64,
    /// Added to the UTC of SYSTEM_TIME, µs.
    utc_offset_us: i64,
}

impl Clocks {
    /// The truth's (run) time of a boot time, s.
    fn run_s(&self, boot_us: u64) -> f64 {
        (boot_us + self.run_minus_boot_us) as f64 * 1e-6
    }
}

/// The telemetry message `id` at the tick's clocks `c`.
fn telemetry(inner: &Inner, id: u32, c: Clocks) -> Option<MavMessage> {
    let t_us = c.boot_us;
    let t_s = c.run_s(t_us);
    let s = inner.truth.state(t_s);
    let boot_ms = (t_us / 1000) as u32;
    Some(match id {
        2 => MavMessage::SYSTEM_TIME(SYSTEM_TIME_DATA {
            time_unix_usec: inner
                .cfg
                .unix_at_boot_us
                .map_or(0, |u| (u + t_us).saturating_add_signed(c.utc_offset_us)),
            time_boot_ms: boot_ms,
        }),
        24 | 124 => gps_message(inner, id == 124, t_us, t_s),
        105 if inner.cfg.px4_imu => {
            let (t_sample_us, g, a) = px4_sample(inner, c);
            let (bg, ba) = inner.truth.autopilot_imu_bias(c.run_s(t_sample_us));
            MavMessage::HIGHRES_IMU(HIGHRES_IMU_DATA {
                time_usec: t_sample_us,
                xacc: (a[0] - ba[0]) as f32,
                yacc: (a[1] - ba[1]) as f32,
                zacc: (a[2] - ba[2]) as f32,
                xgyro: (g[0] - bg[0]) as f32,
                ygyro: (g[1] - bg[1]) as f32,
                zgyro: (g[2] - bg[2]) as f32,
                abs_pressure: isa_pressure_hpa(s.alt_amsl_m) as f32,
                ..HIGHRES_IMU_DATA::DEFAULT
            })
        }
        26 => {
            let (gyro_mrad, acc_mg) = imu_counts(inner, c);
            MavMessage::SCALED_IMU(SCALED_IMU_DATA {
                time_boot_ms: boot_ms,
                xacc: acc_mg[0],
                yacc: acc_mg[1],
                zacc: acc_mg[2],
                xgyro: gyro_mrad[0],
                ygyro: gyro_mrad[1],
                zgyro: gyro_mrad[2],
                ..SCALED_IMU_DATA::DEFAULT
            })
        }
        27 => {
            let (gyro_mrad, acc_mg) = imu_counts(inner, c);
            MavMessage::RAW_IMU(RAW_IMU_DATA {
                time_usec: t_us,
                xacc: acc_mg[0],
                yacc: acc_mg[1],
                zacc: acc_mg[2],
                xgyro: gyro_mrad[0],
                ygyro: gyro_mrad[1],
                zgyro: gyro_mrad[2],
                ..RAW_IMU_DATA::DEFAULT
            })
        }
        29 => MavMessage::SCALED_PRESSURE(SCALED_PRESSURE_DATA {
            time_boot_ms: boot_ms,
            press_abs: isa_pressure_hpa(s.alt_amsl_m) as f32,
            temperature: 2000,
            ..SCALED_PRESSURE_DATA::DEFAULT
        }),
        30 => {
            let rates = inner.truth.attitude_rates(t_s);
            MavMessage::ATTITUDE(ATTITUDE_DATA {
                time_boot_ms: boot_ms,
                roll: s.rpy_rad[0] as f32,
                pitch: s.rpy_rad[1] as f32,
                yaw: s.rpy_rad[2] as f32,
                rollspeed: rates[0] as f32,
                pitchspeed: rates[1] as f32,
                yawspeed: rates[2] as f32,
            })
        }
        33 => MavMessage::GLOBAL_POSITION_INT(GLOBAL_POSITION_INT_DATA {
            time_boot_ms: boot_ms,
            lat: (s.lat_deg * 1e7).round() as i32,
            lon: (s.lon_deg * 1e7).round() as i32,
            alt: (s.alt_amsl_m * 1000.0).round() as i32,
            relative_alt: 0,
            vx: sat_i16(s.vel_ned_m_s[0] * 100.0),
            vy: sat_i16(s.vel_ned_m_s[1] * 100.0),
            vz: sat_i16(s.vel_ned_m_s[2] * 100.0),
            hdg: (s.rpy_rad[2].to_degrees().rem_euclid(360.0) * 100.0).round() as u16 % 36000,
        }),
        _ => return None,
    })
}

/// PX4: the newest sample of a 250 Hz IMU, shared by HIGHRES_IMU and SCALED_IMU: its boot time,
/// gyro and accelerometer.
fn px4_sample(inner: &Inner, c: Clocks) -> (u64, [f64; 3], [f64; 3]) {
    let slot = c.boot_us / PX4_IMU_SLOT_US;
    let mut cache = lock(&inner.px4_sample);
    match *cache {
        Some((k, g, a)) if k == slot => (slot * PX4_IMU_SLOT_US, g, a),
        _ => {
            let t_slot_us = slot * PX4_IMU_SLOT_US;
            let (g, a) = inner.truth.imu(c.run_s(t_slot_us));
            *cache = Some((slot, g, a));
            (t_slot_us, g, a)
        }
    }
}

/// The IMU as SCALED_IMU / RAW_IMU carry it: mrad/s and mg, truncated toward zero as
/// ArduPilot's C float-to-int16 conversion does.
fn imu_counts(inner: &Inner, c: Clocks) -> ([i16; 3], [i16; 3]) {
    let (gyro, accel) = if inner.cfg.px4_imu {
        let (_, g, a) = px4_sample(inner, c);
        (g, a)
    } else {
        inner.truth.imu(c.run_s(c.boot_us))
    };
    (
        gyro.map(|g| trunc_i16(g * 1000.0)),
        accel.map(|a| trunc_i16(a / G0_M_S2 * 1000.0)),
    )
}

/// GPS_RAW_INT, or GPS2_RAW for the second receiver (the real GPS when GPS_INPUT feeds instance
/// 0). No fix: what a receiver without satellites reports (zero position, no satellites).
fn gps_message(inner: &Inner, second: bool, t_us: u64, t_s: f64) -> MavMessage {
    let fix = inner.cfg.gps_fix.then(|| inner.truth.gps(t_s)).flatten();
    let (fix_type, lat, lon, alt, sats) = match &fix {
        Some(g) => (
            GpsFixType::GPS_FIX_TYPE_3D_FIX,
            (g.lat_deg * 1e7).round() as i32,
            (g.lon_deg * 1e7).round() as i32,
            (g.alt_amsl_m * 1000.0).round() as i32,
            12,
        ),
        None => (GpsFixType::GPS_FIX_TYPE_NO_FIX, 0, 0, 0, 0),
    };
    let (vel, cog) = match &fix {
        Some(g) if inner.cfg.gps_velocity => gps_vel_cog(g.vel_ned_m_s),
        _ => (u16::MAX, u16::MAX),
    };
    if second {
        return MavMessage::GPS2_RAW(GPS2_RAW_DATA {
            time_usec: t_us,
            fix_type,
            lat,
            lon,
            alt,
            eph: u16::MAX,
            epv: u16::MAX,
            vel,
            cog,
            satellites_visible: sats,
            ..GPS2_RAW_DATA::DEFAULT
        });
    }
    MavMessage::GPS_RAW_INT(GPS_RAW_INT_DATA {
        time_usec: t_us,
        fix_type,
        lat,
        lon,
        alt,
        eph: u16::MAX,
        epv: u16::MAX,
        vel,
        cog,
        satellites_visible: sats,
        ..GPS_RAW_INT_DATA::DEFAULT
    })
}

async fn tx_loop(inner: Arc<Inner>, conn: Arc<Conn>) {
    let mut tick = tokio::time::interval(Duration::from_millis(2));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let mut next_hb = Instant::now();
    loop {
        tick.tick().await;
        let now = Instant::now();
        if now >= next_hb {
            next_hb = now + Duration::from_secs(1);
            let hb = MavMessage::HEARTBEAT(HEARTBEAT_DATA {
                custom_mode: 0,
                mavtype: MavType::MAV_TYPE_QUADROTOR,
                autopilot: inner.cfg.autopilot(),
                base_mode: MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                system_status: MavState::MAV_STATE_STANDBY,
                mavlink_version: 3,
            });
            send(&inner, &conn, &hb).await;
        }
        let (due, clocks): (Vec<u32>, Clocks) = {
            let mut st = lock(&inner.state);
            let faults = inner
                .truth
                .link_faults(st.start.elapsed().as_micros() as f64 * 1e-6);
            if faults.reboots > st.fault_reboots {
                st.fault_reboots = faults.reboots;
                reboot(&mut st);
            }
            st.fault_silent = faults.silent;
            let t_us = st.boot.elapsed().as_micros() as u64;
            let clocks = Clocks {
                boot_us: t_us,
                run_minus_boot_us: (st.boot - st.start).as_micros() as u64,
                utc_offset_us: faults.utc_offset_us,
            };
            let mut due = Vec::new();
            for (id, (every, next)) in st.intervals.iter_mut() {
                if now >= *next {
                    due.push(*id);
                    // Keep the long-run rate exact; if far behind, resynchronise.
                    *next += *every;
                    if *next < now {
                        *next = now + *every;
                    }
                }
            }
            // In message-id order: a HashMap's order differs between runs, and the order in
            // which the daemon receives one instant's messages must not (lock-step runs are
            // reproducible).
            due.sort_unstable();
            (due, clocks)
        };
        for id in due {
            if let Some(m) = telemetry(&inner, id, clocks) {
                send(&inner, &conn, &m).await;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn constant_velocity_truth_moves() {
        let cv = ConstantVelocity {
            lat_deg: 47.0,
            lon_deg: -97.0,
            alt_amsl_m: 500.0,
            vel_ned_m_s: [10.0, 5.0, -1.0],
            yaw_rad: 0.3,
        };
        let s = cv.state(10.0);
        let dn = (s.lat_deg - 47.0).to_radians() * 6_371_000.0;
        assert!((dn - 100.0).abs() < 1e-6);
        assert!((s.alt_amsl_m - 510.0).abs() < 1e-9);
        assert_eq!(s.rpy_rad[2], 0.3);
    }

    #[test]
    fn isa_pressure() {
        assert!((isa_pressure_hpa(0.0) - 1013.25).abs() < 1e-9);
        // ~ 898.7 hPa at 1000 m (ISA table).
        assert!((isa_pressure_hpa(1000.0) - 898.75).abs() < 0.1);
    }

    #[test]
    fn gps_ground_speed_and_course() {
        assert_eq!(gps_vel_cog([3.0, 4.0, 1.0]), (500, 5313));
        assert_eq!(gps_vel_cog([0.0, -12.0, 0.0]), (1200, 27000));
        assert_eq!(gps_vel_cog([-12.0, -0.0001, 0.0]), (1200, 18000));
        assert_eq!(gps_vel_cog([0.0, 0.0, 0.0]), (0, 0));
        assert_eq!(gps_vel_cog([700.0, 0.0, 0.0]), (u16::MAX, u16::MAX));
        assert_eq!(gps_vel_cog([f64::NAN, 0.0, 0.0]), (u16::MAX, u16::MAX));
        assert!(!EmulatorConfig::new("udpout:127.0.0.1:1").gps_velocity);
    }
}
