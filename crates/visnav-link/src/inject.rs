//! Injection messages: pure functions from a navigation estimate (plus the send time) to the
//! MAVLink message the autopilot fuses. Every value is checked finite and in range; a message
//! that cannot be filled honestly is refused with an [`InjectError`] naming the field.
//!
//! # Conventions
//! * Input attitude `q_ned_body` (Hamilton, scalar first): `v_ned = R(q_ned_body) v_body_frd`,
//!   i.e. `R_ned_body = Rz(yaw) Ry(pitch) Rx(roll)` (docs/conventions.md).
//! * Local positions are NED metres about the autopilot's EKF origin ([`GeoOrigin`]) in the
//!   autopilot's own projection ([`AutopilotLocal`]: ArduPilot's equirectangular sphere, PX4's
//!   azimuthal equidistant one, the exact tangent plane for any other autopilot; see
//!   `visnav_core::geo::autopilot_frame`), with down as the altitude difference to the origin:
//!   the position the autopilot fuses then maps back to the latitude and longitude sent.
//! * 6x6 covariances are sent as the row-major upper triangle (21 values):
//!   indices 0..=5 row 0, 6..=10 row 1, 11..=14 row 2, 15..=17 row 3, 18..=19 row 4, 20 row 5.
//!
//! # GPS_INPUT (ArduPilot GPS1_TYPE = 14)
//! ArduPilot time-stamps GPS_INPUT on arrival (minus GPS_DELAY_MS) and ignores `time_usec`, so the
//! estimate is propagated to the send time: `p(t_send) = p(t_valid) + v_ned * age` and its
//! position covariance grows by `P_v age^2`. `time_usec` is the Unix time of the send instant and
//! `time_week`/`time_week_ms` the matching GPS time (UTC + 18 s). Accuracies are 1-sigma:
//! `horiz_accuracy = sqrt(lambda_max(P_ne))`, `vert_accuracy = sqrt(P_dd)`,
//! `speed_accuracy = sqrt(lambda_max(P_v))`. DOPs are accuracies divided by a nominal user range
//! error [`DOP_UERE_M`]. Yaw in centidegrees, 36000 = north, 0 = not sent.
//!
//! # VISION_POSITION_ESTIMATE / ODOMETRY
//! Time-stamped with the validity time in the clock this link answers TIMESYNC requests with
//! (the companion's monotonic clock, as MAVROS does), so PX4 and ArduPilot map it with their own
//! time sync / jitter correction. ODOMETRY: `child_frame_id = MAV_FRAME_BODY_FRD`, velocity in
//! the body frame `v_body = R_ned_body^T v_ned` with covariance `R^T P_v R`; angular rates are not
//! estimated: sent as 0 with variance [`UNKNOWN_RATE_VAR`]. `frame_id` ([`PoseFrame`]) is
//! `MAV_FRAME_LOCAL_NED` for PX4 and `MAV_FRAME_LOCAL_FRD` for every other autopilot; the position
//! is the same north-aligned NED vector in both. ArduPilot takes only LOCAL_FRD (with BODY_FRD).
//! PX4's EKF2 treats LOCAL_FRD as an arbitrary vision frame: without vision yaw fusion it rotates
//! the position by `R(q_ekf2 * q_odometry^-1)` (`ev_pos_control.cpp`, PX4 v1.14), the full 3-D
//! difference between its attitude and ours, so at 1800 m above the origin 1 deg of tilt
//! difference moves the measurement 31 m horizontally; LOCAL_NED is used as it is.

// SET_GPS_GLOBAL_ORIGIN is marked superseded by MAV_CMD_DO_SET_GLOBAL_ORIGIN (2025), but ArduPilot
// and PX4 releases in the field still act on the message; it stays until they do not.
#[allow(deprecated)]
use mavlink::dialects::ardupilotmega::{
    GLOBAL_POSITION_SENSOR_DATA, GPS_INPUT_DATA, GlobalPositionFlags, GlobalPositionSrc,
    GpsFixType, GpsInputIgnoreFlags, MavAutopilot, MavEstimatorType, MavFrame, MavMessage,
    ODOMETRY_DATA, SET_GPS_GLOBAL_ORIGIN_DATA, VISION_POSITION_ESTIMATE_DATA,
};
use nalgebra::{Matrix3, SymmetricEigen, UnitQuaternion, Vector3};

use crate::config::OutputConfig;
use crate::time::gps_week_ms;
use visnav_core::geo::local::offset_geodetic;
use visnav_core::geo::{AutopilotFrame, GeoOrigin};

/// Nominal user-equivalent range error used to express accuracies as DOPs (hdop = h_acc / UERE).
pub const DOP_UERE_M: f64 = 4.0;
/// Variance sent for the (unestimated) angular rates in ODOMETRY, (rad/s)^2.
pub const UNKNOWN_RATE_VAR: f32 = 1e4;
/// Estimates stamped more than this in the future of the send time are refused (s).
pub const MAX_FUTURE_S: f64 = 0.05;
/// Smallest horizontal accuracy GPS_INPUT claims, m. The filter fuses a receiver's 5 Hz fixes
/// as independent while their errors persist for minutes, so its sigma sinks below any
/// receiver's real accuracy (0.3 m from 1.5 m fixes in ArduCopter SITL), and the position is
/// carried to the send time with the estimated velocity (0.1 s of timing error at 15 m/s is
/// 1.5 m). Measured there: injected positions up to 2.5 m off the truth at a claimed 0.3 m
/// (docs/real-sitl.md). No claim below this.
pub const MIN_CLAIMED_H_ACC_M: f64 = 1.0;
/// Smallest vertical accuracy GPS_INPUT claims, m (the same reasons; barometric heights).
pub const MIN_CLAIMED_V_ACC_M: f64 = 1.5;

/// Health of the navigation solution, as the filter judges it.
#[derive(Debug, Clone, PartialEq)]
pub enum Health {
    /// Fixes are arriving and consistent.
    Ok,
    /// Usable, with the covariance honestly inflated (e.g. coasting on the IMU).
    Degraded {
        /// Why, in words (logs and status text).
        reason: String,
    },
    /// Not usable: nothing is injected (or a NO_FIX GPS_INPUT, see `output.on_lost`).
    Lost {
        /// Why, in words (logs and status text).
        reason: String,
    },
}

/// `ok`, `degraded: <reason>`, `lost: <reason>` (logs and status text).
impl std::fmt::Display for Health {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Health::Ok => write!(f, "ok"),
            Health::Degraded { reason } => write!(f, "degraded: {reason}"),
            Health::Lost { reason } => write!(f, "lost: {reason}"),
        }
    }
}

/// The navigation solution handed to the injector.
#[derive(Debug, Clone, PartialEq)]
pub struct NavEstimate {
    /// Time of validity, autopilot boot time (µs).
    pub t_boot_us: u64,
    /// WGS84 latitude, degrees.
    pub lat_deg: f64,
    /// WGS84 longitude, degrees.
    pub lon_deg: f64,
    /// Altitude above mean sea level, metres.
    pub alt_amsl_m: f64,
    /// Geoid undulation N (ellipsoid height = AMSL + N), metres; needed only for
    /// GLOBAL_POSITION_SENSOR.
    pub geoid_undulation_m: Option<f64>,
    /// Velocity, NED, m/s.
    pub vel_ned_m_s: Vector3<f64>,
    /// Attitude `R_ned_body` as a Hamilton quaternion.
    pub q_ned_body: UnitQuaternion<f64>,
    /// Position covariance, NED, m^2.
    pub pos_cov_ned_m2: Matrix3<f64>,
    /// Velocity covariance, NED, (m/s)^2.
    pub vel_cov_ned_m2_s2: Matrix3<f64>,
    /// 1-sigma roll, pitch, yaw uncertainty, rad.
    pub att_sigma_rad: Vector3<f64>,
    /// Filter health.
    pub health: Health,
    /// Incremented by the filter on every discontinuity (reset) of the solution.
    pub reset_counter: u8,
}

/// Send-time context supplied by the link.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SendTime {
    /// Autopilot boot time now (µs).
    pub t_boot_us: u64,
    /// Unix time now (µs), if known.
    pub unix_us: Option<u64>,
    /// The estimate's validity time in the companion clock used for TIMESYNC answers (µs).
    pub validity_companion_us: Option<u64>,
}

/// Why a message was not built.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum InjectError {
    /// The estimate was already sent as a pose; a pose is sent once.
    #[error("this estimate was already sent as a pose (no newer one yet)")]
    Repeated,
    /// A field of the message would not be finite.
    #[error("{field} is not finite")]
    NotFinite {
        /// The message field.
        field: &'static str,
    },
    /// A field of the message would lie outside what its type or meaning allows.
    #[error("{field} = {value} is outside [{lo}, {hi}]")]
    OutOfRange {
        /// The message field.
        field: &'static str,
        /// Its value.
        value: f64,
        /// The lowest allowed.
        lo: f64,
        /// The highest allowed.
        hi: f64,
    },
    /// The estimate is older than `output.max_age_s` at send time.
    #[error("estimate is {age_s:.3} s old at send time (limit {max_s} s)")]
    Stale {
        /// Its age at send time, s.
        age_s: f64,
        /// The limit, s.
        max_s: f64,
    },
    /// The estimate is stamped after the send time (a clock went back).
    #[error("estimate is stamped {ahead_s:.3} s after the send time")]
    FromFuture {
        /// By how much, s.
        ahead_s: f64,
    },
    /// The solution is lost: nothing to inject.
    #[error("solution lost: {reason}")]
    Lost {
        /// Why, in words.
        reason: String,
    },
    /// GPS_INPUT needs the GPS week and time of week, and no UTC time is known.
    #[error("no UTC time available for the GPS week/time of week")]
    NoUtc,
    /// A local position needs the autopilot's EKF origin, and none is known.
    #[error("no EKF origin known for local positions")]
    NoOrigin,
    /// The time of validity cannot be put on the autopilot's clock yet.
    #[error("the companion-clock time of validity is unknown (time sync not converged)")]
    NoCompanionTime,
    /// The ellipsoidal altitude needs the geoid undulation, and it is unknown.
    #[error("geoid undulation unknown (needed for GLOBAL_POSITION_SENSOR.alt_ellipsoid)")]
    NoGeoid,
    /// Built, but the link could not send it (not connected, socket error).
    #[error("not sent: {reason}")]
    NotSent {
        /// Why, in words.
        reason: String,
    },
}

fn finite(field: &'static str, v: f64) -> Result<f64, InjectError> {
    if v.is_finite() {
        Ok(v)
    } else {
        Err(InjectError::NotFinite { field })
    }
}

fn in_range(field: &'static str, v: f64, lo: f64, hi: f64) -> Result<f64, InjectError> {
    finite(field, v)?;
    if v < lo || v > hi {
        return Err(InjectError::OutOfRange {
            field,
            value: v,
            lo,
            hi,
        });
    }
    Ok(v)
}

/// f64 -> f32 that refuses overflow to infinity.
fn f32_of(field: &'static str, v: f64) -> Result<f32, InjectError> {
    let f = finite(field, v)? as f32;
    if f.is_finite() {
        Ok(f)
    } else {
        Err(InjectError::NotFinite { field })
    }
}

fn check_cov(field: &'static str, p: &Matrix3<f64>, max_var: f64) -> Result<(), InjectError> {
    for v in p.iter() {
        finite(field, *v)?;
    }
    for i in 0..3 {
        in_range(field, p[(i, i)], 0.0, max_var)?;
    }
    Ok(())
}

/// Check every field of an estimate: finite, physically plausible, covariances non-negative.
pub fn check_estimate(e: &NavEstimate) -> Result<(), InjectError> {
    in_range("lat_deg", e.lat_deg, -90.0, 90.0)?;
    in_range("lon_deg", e.lon_deg, -180.0, 180.0)?;
    in_range("alt_amsl_m", e.alt_amsl_m, -1000.0, 20_000.0)?;
    if let Some(n) = e.geoid_undulation_m {
        in_range("geoid_undulation_m", n, -120.0, 100.0)?;
    }
    for v in e.vel_ned_m_s.iter() {
        in_range("vel_ned_m_s", *v, -300.0, 300.0)?;
    }
    for v in e.q_ned_body.coords.iter() {
        finite("q_ned_body", *v)?;
    }
    in_range("q_ned_body norm", e.q_ned_body.coords.norm(), 0.999, 1.001)?;
    check_cov("pos_cov_ned_m2", &e.pos_cov_ned_m2, 1e8)?;
    check_cov("vel_cov_ned_m2_s2", &e.vel_cov_ned_m2_s2, 1e6)?;
    for v in e.att_sigma_rad.iter() {
        in_range("att_sigma_rad", *v, 0.0, 10.0)?;
    }
    Ok(())
}

/// Largest eigenvalue of a symmetric 3x3 matrix (0 if negative through rounding).
fn lambda_max3(p: &Matrix3<f64>) -> f64 {
    let s = p.symmetric_part();
    SymmetricEigen::new(s).eigenvalues.max().max(0.0)
}

/// Largest eigenvalue of the horizontal (north-east) 2x2 block.
fn lambda_max_ne(p: &Matrix3<f64>) -> f64 {
    let (a, b, d) = (p[(0, 0)], 0.5 * (p[(0, 1)] + p[(1, 0)]), p[(1, 1)]);
    let m = 0.5 * (a + d);
    let r = (0.25 * (a - d) * (a - d) + b * b).sqrt();
    (m + r).max(0.0)
}

fn wrap_deg_0_360(d: f64) -> f64 {
    d.rem_euclid(360.0)
}

/// Degrees -> 1e7 fixed point, refusing overflow.
fn deg_e7(field: &'static str, deg: f64) -> Result<i32, InjectError> {
    let v = (finite(field, deg)? * 1e7).round();
    if v < i32::MIN as f64 || v > i32::MAX as f64 {
        return Err(InjectError::OutOfRange {
            field,
            value: deg,
            lo: -214.0,
            hi: 214.0,
        });
    }
    Ok(v as i32)
}

fn age_s(e: &NavEstimate, now: &SendTime, max_age_s: f64) -> Result<f64, InjectError> {
    let age = (now.t_boot_us as f64 - e.t_boot_us as f64) * 1e-6;
    if age < -MAX_FUTURE_S {
        return Err(InjectError::FromFuture { ahead_s: -age });
    }
    if age > max_age_s {
        return Err(InjectError::Stale {
            age_s: age,
            max_s: max_age_s,
        });
    }
    Ok(age.max(0.0))
}

fn usable(e: &NavEstimate) -> Result<(), InjectError> {
    if let Health::Lost { reason } = &e.health {
        return Err(InjectError::Lost {
            reason: reason.clone(),
        });
    }
    check_estimate(e)
}

/// GPS_INPUT for ArduPilot (see module docs for every field's meaning).
pub fn gps_input(
    e: &NavEstimate,
    now: &SendTime,
    out: &OutputConfig,
) -> Result<MavMessage, InjectError> {
    usable(e)?;
    let age = age_s(e, now, out.max_age_s)?;
    let unix_us = now.unix_us.ok_or(InjectError::NoUtc)?;
    let (week, week_ms) = gps_week_ms(unix_us).ok_or(InjectError::NoUtc)?;

    let d = e.vel_ned_m_s * age;
    let (lat, lon, alt) = offset_geodetic(e.lat_deg, e.lon_deg, e.alt_amsl_m, &d);
    let p = e.pos_cov_ned_m2 + e.vel_cov_ned_m2_s2 * (age * age);
    let h_acc = lambda_max_ne(&p).sqrt().max(MIN_CLAIMED_H_ACC_M);
    let v_acc = p[(2, 2)].max(0.0).sqrt().max(MIN_CLAIMED_V_ACC_M);
    let s_acc = lambda_max3(&e.vel_cov_ned_m2_s2).sqrt();

    let yaw = if out.gps_yaw && e.att_sigma_rad.z < 10f64.to_radians() {
        let (_, _, yaw_rad) = e.q_ned_body.euler_angles();
        let cd = (wrap_deg_0_360(finite("yaw", yaw_rad)?.to_degrees()) * 100.0).round() as u16;
        if cd == 0 || cd > 36000 { 36000 } else { cd }
    } else {
        0
    };
    let msg = GPS_INPUT_DATA {
        time_usec: unix_us,
        time_week_ms: week_ms,
        time_week: week,
        gps_id: out.gps_id,
        fix_type: GpsFixType::GPS_FIX_TYPE_3D_FIX,
        lat: deg_e7("lat_deg", in_range("lat_deg", lat, -90.0, 90.0)?)?,
        lon: deg_e7("lon_deg", lon)?,
        alt: f32_of("alt_amsl_m", alt)?,
        hdop: f32_of("hdop", (h_acc / DOP_UERE_M).clamp(0.01, 99.99))?,
        vdop: f32_of("vdop", (v_acc / DOP_UERE_M).clamp(0.01, 99.99))?,
        vn: f32_of("vn", e.vel_ned_m_s.x)?,
        ve: f32_of("ve", e.vel_ned_m_s.y)?,
        vd: f32_of("vd", e.vel_ned_m_s.z)?,
        speed_accuracy: f32_of("speed_accuracy", s_acc)?,
        horiz_accuracy: f32_of("horiz_accuracy", h_acc)?,
        vert_accuracy: f32_of("vert_accuracy", v_acc)?,
        ignore_flags: GpsInputIgnoreFlags::empty(),
        satellites_visible: out.gps_satellites,
        yaw,
    };
    Ok(MavMessage::GPS_INPUT(msg))
}

/// A GPS_INPUT that tells ArduPilot the fix is lost (fix_type NO_FIX, every optional field
/// flagged as ignored, numbers zero).
pub fn gps_input_no_fix(now: &SendTime, out: &OutputConfig) -> Result<MavMessage, InjectError> {
    let unix_us = now.unix_us.ok_or(InjectError::NoUtc)?;
    let (week, week_ms) = gps_week_ms(unix_us).ok_or(InjectError::NoUtc)?;
    Ok(MavMessage::GPS_INPUT(GPS_INPUT_DATA {
        time_usec: unix_us,
        time_week_ms: week_ms,
        time_week: week,
        gps_id: out.gps_id,
        fix_type: GpsFixType::GPS_FIX_TYPE_NO_FIX,
        ignore_flags: GpsInputIgnoreFlags::all(),
        hdop: 99.99,
        vdop: 99.99,
        satellites_visible: 0,
        ..GPS_INPUT_DATA::DEFAULT
    }))
}

fn upper_triangle_6(diag_blocks: (&Matrix3<f64>, &Matrix3<f64>)) -> Result<[f32; 21], InjectError> {
    let mut full = [[0.0f64; 6]; 6];
    for i in 0..3 {
        for j in 0..3 {
            full[i][j] = 0.5 * (diag_blocks.0[(i, j)] + diag_blocks.0[(j, i)]);
            full[i + 3][j + 3] = 0.5 * (diag_blocks.1[(i, j)] + diag_blocks.1[(j, i)]);
        }
    }
    let mut out = [0f32; 21];
    let mut k = 0;
    for (i, row) in full.iter().enumerate() {
        for v in row.iter().skip(i) {
            out[k] = f32_of("covariance", *v)?;
            k += 1;
        }
    }
    Ok(out)
}

fn quality(h: &Health) -> i8 {
    match h {
        Health::Ok => 100,
        Health::Degraded { .. } => 50,
        Health::Lost { .. } => -1,
    }
}

/// What the local-frame injectors (VISION_POSITION_ESTIMATE, ODOMETRY) share, after the checks
/// they share: the estimate is usable and fresh, the companion time is known, the position is
/// within 1000 km of the origin.
struct LocalPose {
    t_companion_us: u64,
    p_ned_m: Vector3<f64>,
    att_var_rad2: Matrix3<f64>,
}

fn local_pose(
    e: &NavEstimate,
    now: &SendTime,
    local: &AutopilotLocal,
    out: &OutputConfig,
) -> Result<LocalPose, InjectError> {
    usable(e)?;
    age_s(e, now, out.max_age_s)?;
    let t_companion_us = now
        .validity_companion_us
        .ok_or(InjectError::NoCompanionTime)?;
    let p_ned_m = local.to_ned(e.lat_deg, e.lon_deg, e.alt_amsl_m);
    in_range("local position", p_ned_m.amax(), 0.0, 1e6)?;
    let att_var_rad2 = Matrix3::from_diagonal(&e.att_sigma_rad.component_mul(&e.att_sigma_rad));
    Ok(LocalPose {
        t_companion_us,
        p_ned_m,
        att_var_rad2,
    })
}

/// VISION_POSITION_ESTIMATE: local NED about `origin`, Euler angles (ZYX), 6x6 covariance
/// (x, y, z, roll, pitch, yaw) upper triangle, the filter's reset counter.
pub fn vision_position_estimate(
    e: &NavEstimate,
    now: &SendTime,
    local: &AutopilotLocal,
    out: &OutputConfig,
) -> Result<MavMessage, InjectError> {
    let LocalPose {
        t_companion_us: usec,
        p_ned_m: p,
        att_var_rad2: att_var,
    } = local_pose(e, now, local, out)?;
    let (roll, pitch, yaw) = e.q_ned_body.euler_angles();
    Ok(MavMessage::VISION_POSITION_ESTIMATE(
        VISION_POSITION_ESTIMATE_DATA {
            usec,
            x: f32_of("x", p.x)?,
            y: f32_of("y", p.y)?,
            z: f32_of("z", p.z)?,
            roll: f32_of("roll", roll)?,
            pitch: f32_of("pitch", pitch)?,
            yaw: f32_of("yaw", yaw)?,
            covariance: upper_triangle_6((&e.pos_cov_ned_m2, &att_var))?,
            reset_counter: e.reset_counter,
        },
    ))
}

/// ODOMETRY `frame_id` for the north-aligned NED position (see the module doc).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PoseFrame {
    /// MAV_FRAME_LOCAL_NED: PX4 (EKF2 uses it as its own frame).
    LocalNed,
    /// MAV_FRAME_LOCAL_FRD: ArduPilot (the only frame it accepts) and others.
    LocalFrd,
}

impl PoseFrame {
    /// The frame to send to an autopilot of this flight stack.
    pub fn for_autopilot(autopilot: Option<MavAutopilot>) -> Self {
        match autopilot {
            Some(MavAutopilot::MAV_AUTOPILOT_PX4) => PoseFrame::LocalNed,
            _ => PoseFrame::LocalFrd,
        }
    }

    fn mav_frame(self) -> MavFrame {
        match self {
            PoseFrame::LocalNed => MavFrame::MAV_FRAME_LOCAL_NED,
            PoseFrame::LocalFrd => MavFrame::MAV_FRAME_LOCAL_FRD,
        }
    }
}

/// The projection an autopilot of this flight stack keeps its local frame in: ArduPilot's and
/// PX4's own; the exact tangent plane for any other (or not yet known) autopilot, whose
/// projection is not known.
pub fn projection_of(autopilot: Option<MavAutopilot>) -> AutopilotFrame {
    match autopilot {
        Some(MavAutopilot::MAV_AUTOPILOT_PX4) => AutopilotFrame::Px4,
        Some(MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA) => AutopilotFrame::ArduPilot,
        _ => AutopilotFrame::Tangent,
    }
}

/// The local frame a pose is sent in: the autopilot's EKF origin, the projection the autopilot
/// maps latitude and longitude with (`visnav_core::geo::autopilot_frame`) and ODOMETRY's
/// `frame_id`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AutopilotLocal {
    /// The autopilot's EKF origin.
    pub origin: GeoOrigin,
    /// How the autopilot maps latitude and longitude to its local north and east.
    pub projection: AutopilotFrame,
    /// ODOMETRY's `frame_id`.
    pub pose_frame: PoseFrame,
}

impl AutopilotLocal {
    /// The frame of an autopilot of this flight stack ([`projection_of`], [`PoseFrame::for_autopilot`]).
    pub fn for_autopilot(origin: GeoOrigin, autopilot: Option<MavAutopilot>) -> Self {
        Self {
            origin,
            projection: projection_of(autopilot),
            pose_frame: PoseFrame::for_autopilot(autopilot),
        }
    }

    /// Local NED position, metres, of (latitude, longitude in degrees, altitude AMSL in metres).
    pub fn to_ned(&self, lat_deg: f64, lon_deg: f64, alt_amsl_m: f64) -> Vector3<f64> {
        self.projection
            .to_ned(&self.origin, lat_deg, lon_deg, alt_amsl_m)
    }
}

/// ODOMETRY: pose (north-aligned NED in the autopilot's local frame) in its [`PoseFrame`],
/// velocity in MAV_FRAME_BODY_FRD.
pub fn odometry(
    e: &NavEstimate,
    now: &SendTime,
    local: &AutopilotLocal,
    out: &OutputConfig,
) -> Result<MavMessage, InjectError> {
    let LocalPose {
        t_companion_us: time_usec,
        p_ned_m: p,
        att_var_rad2: att_var,
    } = local_pose(e, now, local, out)?;
    let r = e.q_ned_body.to_rotation_matrix();
    let v_body = r.inverse() * e.vel_ned_m_s;
    let pv_body = r.matrix().transpose() * e.vel_cov_ned_m2_s2 * r.matrix();
    let rate_var = Matrix3::from_diagonal_element(f64::from(UNKNOWN_RATE_VAR));
    let q = e.q_ned_body.coords; // nalgebra stores (i, j, k, w)
    Ok(MavMessage::ODOMETRY(ODOMETRY_DATA {
        time_usec,
        x: f32_of("x", p.x)?,
        y: f32_of("y", p.y)?,
        z: f32_of("z", p.z)?,
        q: [
            f32_of("q", q.w)?,
            f32_of("q", q.x)?,
            f32_of("q", q.y)?,
            f32_of("q", q.z)?,
        ],
        vx: f32_of("vx", v_body.x)?,
        vy: f32_of("vy", v_body.y)?,
        vz: f32_of("vz", v_body.z)?,
        rollspeed: 0.0,
        pitchspeed: 0.0,
        yawspeed: 0.0,
        pose_covariance: upper_triangle_6((&e.pos_cov_ned_m2, &att_var))?,
        velocity_covariance: upper_triangle_6((&pv_body, &rate_var))?,
        frame_id: local.pose_frame.mav_frame(),
        child_frame_id: MavFrame::MAV_FRAME_BODY_FRD,
        reset_counter: e.reset_counter,
        estimator_type: MavEstimatorType::MAV_ESTIMATOR_TYPE_VIO,
        quality: quality(&e.health),
    }))
}

/// GLOBAL_POSITION_SENSOR (id 296, PX4 auxiliary global position): position at the validity
/// time, `processing_time` = age at send (µs), 1-sigma eph/epv, source VISION.
pub fn global_position_sensor(
    e: &NavEstimate,
    now: &SendTime,
    target: (u8, u8),
    out: &OutputConfig,
) -> Result<MavMessage, InjectError> {
    usable(e)?;
    let age = age_s(e, now, out.max_age_s)?;
    let n = e.geoid_undulation_m.ok_or(InjectError::NoGeoid)?;
    let unix_valid = now
        .unix_us
        .map(|u| u.saturating_sub((age * 1e6).round() as u64));
    let flags = if matches!(e.health, Health::Degraded { .. }) {
        GlobalPositionFlags::GLOBAL_POSITION_UNHEALTHY
    } else {
        GlobalPositionFlags::empty()
    };
    Ok(MavMessage::GLOBAL_POSITION_SENSOR(
        GLOBAL_POSITION_SENSOR_DATA {
            time_usec: unix_valid.unwrap_or(e.t_boot_us),
            processing_time: (age * 1e6).round() as u32,
            lat: deg_e7("lat_deg", e.lat_deg)?,
            lon: deg_e7("lon_deg", e.lon_deg)?,
            alt_ellipsoid: f32_of("alt_ellipsoid", e.alt_amsl_m + n)?,
            alt: f32_of("alt", e.alt_amsl_m)?,
            eph: f32_of("eph", lambda_max_ne(&e.pos_cov_ned_m2).sqrt())?,
            epv: f32_of("epv", e.pos_cov_ned_m2[(2, 2)].max(0.0).sqrt())?,
            target_system: target.0,
            target_component: target.1,
            id: out.sensor_id,
            source: GlobalPositionSrc::GLOBAL_POSITION_SRC_VISION,
            flags,
        },
    ))
}

/// SET_GPS_GLOBAL_ORIGIN: lat/lon 1e7 degrees, altitude mm AMSL.
#[allow(deprecated)] // see the import
pub fn set_gps_global_origin(
    origin: &GeoOrigin,
    target_system: u8,
    unix_us: Option<u64>,
) -> Result<MavMessage, InjectError> {
    let alt_mm = in_range("origin alt_amsl_m", origin.alt_amsl_m, -1000.0, 20_000.0)? * 1000.0;
    Ok(MavMessage::SET_GPS_GLOBAL_ORIGIN(
        SET_GPS_GLOBAL_ORIGIN_DATA {
            latitude: deg_e7(
                "origin lat_deg",
                in_range("origin lat_deg", origin.lat_deg, -90.0, 90.0)?,
            )?,
            longitude: deg_e7(
                "origin lon_deg",
                in_range("origin lon_deg", origin.lon_deg, -180.0, 180.0)?,
            )?,
            altitude: alt_mm.round() as i32,
            target_system,
            time_usec: unix_us.unwrap_or(0),
        },
    ))
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn health_reads_as_words() {
        assert_eq!(Health::Ok.to_string(), "ok");
        let d = Health::Degraded {
            reason: "no accepted position fix for 10.0 s".into(),
        };
        assert_eq!(
            d.to_string(),
            "degraded: no accepted position fix for 10.0 s"
        );
        let l = Health::Lost {
            reason: "not initialised".into(),
        };
        assert_eq!(l.to_string(), "lost: not initialised");
    }

    pub(crate) fn estimate() -> NavEstimate {
        NavEstimate {
            t_boot_us: 100_000_000,
            lat_deg: 46.9,
            lon_deg: -96.8,
            alt_amsl_m: 400.0,
            geoid_undulation_m: Some(-27.5),
            vel_ned_m_s: Vector3::new(10.0, -2.0, 0.5),
            q_ned_body: UnitQuaternion::from_euler_angles(0.1, -0.05, 1.2),
            pos_cov_ned_m2: Matrix3::new(9.0, 1.0, 0.0, 1.0, 4.0, 0.0, 0.0, 0.0, 16.0),
            vel_cov_ned_m2_s2: Matrix3::from_diagonal_element(0.04),
            att_sigma_rad: Vector3::new(0.01, 0.01, 0.05),
            health: Health::Ok,
            reset_counter: 3,
        }
    }

    pub(crate) fn now() -> SendTime {
        SendTime {
            t_boot_us: 100_200_000,
            unix_us: Some(1_704_067_200_000_000),
            validity_companion_us: Some(55_000_000),
        }
    }

    fn gps(m: MavMessage) -> GPS_INPUT_DATA {
        match m {
            MavMessage::GPS_INPUT(d) => d,
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn gps_input_fields() {
        let e = estimate();
        let out = OutputConfig {
            gps_id: 1,
            gps_yaw: true,
            ..OutputConfig::default()
        };
        let g = gps(gps_input(&e, &now(), &out).unwrap());
        assert_eq!(g.time_usec, 1_704_067_200_000_000);
        assert_eq!((g.time_week, g.time_week_ms), (2295, 86_418_000));
        assert_eq!(g.gps_id, 1);
        assert_eq!(g.fix_type, GpsFixType::GPS_FIX_TYPE_3D_FIX);
        assert_eq!(g.ignore_flags, GpsInputIgnoreFlags::empty());
        assert_eq!(g.satellites_visible, 10);
        // Propagated by 0.2 s: 2 m north, 0.4 m west, 0.1 m down.
        let m_per_deg_lat = 111_200.0; // ~ at 46.9 N
        let dn = (g.lat as f64 * 1e-7 - 46.9) * m_per_deg_lat;
        assert!((dn - 2.0).abs() < 0.02, "dn {dn}");
        let de = (g.lon as f64 * 1e-7 + 96.8) * m_per_deg_lat * 46.9f64.to_radians().cos();
        assert!((de + 0.4).abs() < 0.02, "de {de}");
        assert!((g.alt as f64 - 399.9).abs() < 1e-3);
        assert_eq!((g.vn, g.ve, g.vd), (10.0, -2.0, 0.5));
        // Horizontal: lambda_max([[9,1],[1,4]] + 0.04*0.04 I) = 6.5 + sqrt(6.25 + 1) + 0.0016.
        let h = (6.5 + 7.25f64.sqrt() + 0.0016).sqrt();
        assert!(
            (g.horiz_accuracy as f64 - h).abs() < 1e-5,
            "{}",
            g.horiz_accuracy
        );
        assert!((g.vert_accuracy as f64 - 16.0016f64.sqrt()).abs() < 1e-5);
        assert!((g.speed_accuracy - 0.2).abs() < 1e-6);
        assert!((g.hdop as f64 - h / DOP_UERE_M).abs() < 1e-5);
        // Yaw 1.2 rad = 68.75 deg.
        assert_eq!(g.yaw, (1.2f64.to_degrees() * 100.0).round() as u16);
    }

    #[test]
    fn claimed_accuracies_never_sink_below_the_floors() {
        let mut e = estimate();
        e.pos_cov_ned_m2 = Matrix3::identity() * 0.01; // a GPS-fed filter claiming 0.1 m
        e.vel_cov_ned_m2_s2 = Matrix3::identity() * 1e-6;
        let g = gps(gps_input(&e, &now(), &OutputConfig::default()).unwrap());
        assert_eq!(g.horiz_accuracy as f64, MIN_CLAIMED_H_ACC_M);
        assert_eq!(g.vert_accuracy as f64, MIN_CLAIMED_V_ACC_M);
        assert!((g.hdop as f64 - MIN_CLAIMED_H_ACC_M / DOP_UERE_M).abs() < 1e-6);
    }

    #[test]
    fn gps_yaw_north_is_36000_and_off_is_0() {
        let mut e = estimate();
        e.q_ned_body = UnitQuaternion::from_euler_angles(0.0, 0.0, 0.0);
        let out = OutputConfig {
            gps_yaw: true,
            ..OutputConfig::default()
        };
        assert_eq!(gps(gps_input(&e, &now(), &out).unwrap()).yaw, 36000);
        e.q_ned_body = UnitQuaternion::from_euler_angles(0.0, 0.0, -0.5f64.to_radians());
        assert_eq!(gps(gps_input(&e, &now(), &out).unwrap()).yaw, 35950);
        assert_eq!(
            gps(gps_input(&e, &now(), &OutputConfig::default()).unwrap()).yaw,
            0
        );
    }

    #[test]
    fn refuses_what_it_cannot_send_honestly() {
        let out = OutputConfig::default();
        let mut e = estimate();
        e.lat_deg = f64::NAN;
        assert_eq!(
            gps_input(&e, &now(), &out),
            Err(InjectError::NotFinite { field: "lat_deg" })
        );
        let mut e = estimate();
        e.pos_cov_ned_m2[(1, 1)] = f64::INFINITY;
        assert!(gps_input(&e, &now(), &out).is_err());
        let mut e = estimate();
        e.pos_cov_ned_m2[(0, 0)] = -1.0;
        assert!(gps_input(&e, &now(), &out).is_err());
        let mut e = estimate();
        e.t_boot_us = 10_000_000; // 90 s old
        assert!(matches!(
            gps_input(&e, &now(), &out),
            Err(InjectError::Stale { .. })
        ));
        let mut e = estimate();
        e.t_boot_us = 101_000_000;
        assert!(matches!(
            gps_input(&e, &now(), &out),
            Err(InjectError::FromFuture { .. })
        ));
        let mut e = estimate();
        e.health = Health::Lost {
            reason: "no fix".into(),
        };
        assert!(matches!(
            gps_input(&e, &now(), &out),
            Err(InjectError::Lost { .. })
        ));
        let mut t = now();
        t.unix_us = None;
        assert_eq!(gps_input(&estimate(), &t, &out), Err(InjectError::NoUtc));
        let mut e = estimate();
        e.geoid_undulation_m = None;
        assert_eq!(
            global_position_sensor(&e, &now(), (1, 1), &out),
            Err(InjectError::NoGeoid)
        );
    }

    #[test]
    fn no_fix_message() {
        let g = gps(gps_input_no_fix(&now(), &OutputConfig::default()).unwrap());
        assert_eq!(g.fix_type, GpsFixType::GPS_FIX_TYPE_NO_FIX);
        assert_eq!(g.ignore_flags, GpsInputIgnoreFlags::all());
        assert_eq!(g.satellites_visible, 0);
    }

    fn local(o: GeoOrigin, ap: MavAutopilot) -> AutopilotLocal {
        AutopilotLocal::for_autopilot(o, Some(ap))
    }

    #[test]
    fn each_autopilot_gets_its_own_projection() {
        let o = GeoOrigin {
            lat_deg: 46.9,
            lon_deg: -96.8,
            alt_amsl_m: 300.0,
        };
        let px4 = local(o, MavAutopilot::MAV_AUTOPILOT_PX4);
        let ap = local(o, MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA);
        let other = AutopilotLocal::for_autopilot(o, None);
        assert_eq!(px4.projection, AutopilotFrame::Px4);
        assert_eq!(ap.projection, AutopilotFrame::ArduPilot);
        assert_eq!(other.projection, AutopilotFrame::Tangent);
        assert_eq!(
            local(o, MavAutopilot::MAV_AUTOPILOT_GENERIC).projection,
            AutopilotFrame::Tangent
        );
        // The same point 1.2 km out, in each frame: ArduPilot's sphere is 0.13 % longer north
        // and 0.18 % shorter east than the ellipsoid here, PX4's 0.02 % longer north and 0.29 %
        // shorter east; both take the height above the origin as down.
        let (lat, lon) = (46.9 + 0.0072, -96.8 + 0.0131);
        let t = other.to_ned(lat, lon, 310.0);
        let a = ap.to_ned(lat, lon, 310.0);
        let p = px4.to_ned(lat, lon, 310.0);
        let near = |v: f64, want: f64| (v - want).abs() < 2e-4;
        assert!(
            near(a.x / t.x, 1.00131) && near(a.y / t.y, 0.99816),
            "{a} against {t}"
        );
        assert!(
            near(p.x / t.x, 1.00019) && near(p.y / t.y, 0.99705),
            "{p} against {t}"
        );
        assert_eq!((a.z, p.z), (-10.0, -10.0));
    }

    #[test]
    fn vision_position_estimate_fields() {
        let e = estimate();
        let o = GeoOrigin {
            lat_deg: 46.9,
            lon_deg: -96.8,
            alt_amsl_m: 390.0,
        };
        let MavMessage::VISION_POSITION_ESTIMATE(v) = vision_position_estimate(
            &e,
            &now(),
            &local(o, MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA),
            &OutputConfig::default(),
        )
        .unwrap() else {
            panic!()
        };
        assert_eq!(v.usec, 55_000_000);
        assert!(v.x.abs() < 1e-3 && v.y.abs() < 1e-3 && (v.z + 10.0).abs() < 1e-3);
        assert!((v.roll - 0.1).abs() < 1e-6 && (v.pitch + 0.05).abs() < 1e-6);
        assert!((v.yaw - 1.2).abs() < 1e-6);
        // Upper triangle: [0]=Pnn, [1]=Pne, [6]=Pee, [11]=Pdd, [15]=roll var, [20]=yaw var.
        assert_eq!(v.covariance[0], 9.0);
        assert_eq!(v.covariance[1], 1.0);
        assert_eq!(v.covariance[6], 4.0);
        assert_eq!(v.covariance[11], 16.0);
        assert!((v.covariance[15] - 1e-4).abs() < 1e-9);
        assert!((v.covariance[20] - 2.5e-3).abs() < 1e-9);
        assert_eq!(v.covariance[3], 0.0);
        assert_eq!(v.reset_counter, 3);
    }

    #[test]
    fn odometry_fields() {
        let e = estimate();
        let o = GeoOrigin {
            lat_deg: 46.9,
            lon_deg: -96.8,
            alt_amsl_m: 400.0,
        };
        let MavMessage::ODOMETRY(m) = odometry(
            &e,
            &now(),
            &local(o, MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA),
            &OutputConfig::default(),
        )
        .unwrap() else {
            panic!()
        };
        assert_eq!(m.frame_id, MavFrame::MAV_FRAME_LOCAL_FRD);
        assert_eq!(m.child_frame_id, MavFrame::MAV_FRAME_BODY_FRD);
        assert_eq!(m.quality, 100);
        let q = UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
            m.q[0] as f64,
            m.q[1] as f64,
            m.q[2] as f64,
            m.q[3] as f64,
        ));
        assert!(q.angle_to(&e.q_ned_body) < 1e-6);
        // Body velocity rotated back equals NED velocity.
        let vb = Vector3::new(m.vx as f64, m.vy as f64, m.vz as f64);
        assert!((e.q_ned_body * vb - e.vel_ned_m_s).norm() < 1e-5);
        // Isotropic velocity covariance is unchanged by the rotation.
        assert!((m.velocity_covariance[0] - 0.04).abs() < 1e-7);
        assert!(m.velocity_covariance[1].abs() < 1e-7);
        assert_eq!(m.velocity_covariance[15], UNKNOWN_RATE_VAR);
        assert!(m.rollspeed.is_finite());
    }

    #[test]
    fn odometry_frame_for_px4_is_local_ned_in_its_projection() {
        let e = estimate();
        let o = GeoOrigin {
            lat_deg: 46.9,
            lon_deg: -96.8,
            alt_amsl_m: 400.0,
        };
        assert_eq!(PoseFrame::for_autopilot(None), PoseFrame::LocalFrd);
        let build =
            |ap| match odometry(&e, &now(), &local(o, ap), &OutputConfig::default()).unwrap() {
                MavMessage::ODOMETRY(m) => m,
                _ => panic!("not ODOMETRY"),
            };
        let px4 = build(MavAutopilot::MAV_AUTOPILOT_PX4);
        let ap = build(MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA);
        assert_eq!(px4.frame_id, MavFrame::MAV_FRAME_LOCAL_NED);
        assert_eq!(ap.frame_id, MavFrame::MAV_FRAME_LOCAL_FRD);
        assert_eq!(px4.child_frame_id, MavFrame::MAV_FRAME_BODY_FRD);
        // The frame id and the projection differ: the north-aligned NED position is each
        // autopilot's own (the estimate sits at the origin's latitude and longitude, so only the
        // height remains), the body velocity and the covariances are the same numbers.
        assert_eq!((px4.x, px4.y, px4.z), (ap.x, ap.y, ap.z));
        assert!(px4.x.abs() < 1e-3 && px4.y.abs() < 1e-3 && px4.z.abs() < 1e-3);
        assert_eq!((px4.vx, px4.vy, px4.vz), (ap.vx, ap.vy, ap.vz));
        assert_eq!(px4.pose_covariance, ap.pose_covariance);
        assert_eq!(px4.q, ap.q);
    }

    #[test]
    fn global_position_sensor_fields() {
        let MavMessage::GLOBAL_POSITION_SENSOR(g) =
            global_position_sensor(&estimate(), &now(), (1, 1), &OutputConfig::default()).unwrap()
        else {
            panic!()
        };
        assert_eq!(g.lat, 469_000_000);
        assert_eq!(g.lon, -968_000_000);
        assert_eq!(g.processing_time, 200_000);
        assert_eq!(g.time_usec, 1_704_067_200_000_000 - 200_000);
        assert!((g.alt_ellipsoid - 372.5).abs() < 1e-4);
        assert!((g.epv - 4.0).abs() < 1e-6);
        assert_eq!(g.source, GlobalPositionSrc::GLOBAL_POSITION_SRC_VISION);
        assert_eq!(g.flags, GlobalPositionFlags::empty());
    }

    #[test]
    #[allow(deprecated)]
    fn origin_message() {
        let o = GeoOrigin {
            lat_deg: -33.9,
            lon_deg: 18.4,
            alt_amsl_m: 12.345,
        };
        let MavMessage::SET_GPS_GLOBAL_ORIGIN(m) = set_gps_global_origin(&o, 7, None).unwrap()
        else {
            panic!()
        };
        assert_eq!(
            (m.latitude, m.longitude, m.altitude),
            (-339_000_000, 184_000_000, 12_345)
        );
        assert_eq!(m.target_system, 7);
    }

    proptest! {
        #[test]
        fn every_float_sent_is_finite(
            lat in -89.0..89.0f64, lon in -180.0..180.0f64, alt in -400.0..9000.0f64,
            vn in -50.0..50.0f64, ve in -50.0..50.0f64, vd in -10.0..10.0f64,
            roll in -1.0..1.0f64, pitch in -1.0..1.0f64, yaw in -3.2..3.2f64,
            s in 0.0..1e3f64, age_ms in 0u64..400,
        ) {
            let mut e = estimate();
            e.lat_deg = lat; e.lon_deg = lon; e.alt_amsl_m = alt;
            e.vel_ned_m_s = Vector3::new(vn, ve, vd);
            e.q_ned_body = UnitQuaternion::from_euler_angles(roll, pitch, yaw);
            e.pos_cov_ned_m2 = Matrix3::from_diagonal_element(s * s);
            let mut t = now();
            t.t_boot_us = e.t_boot_us + age_ms * 1000;
            let out = OutputConfig { gps_yaw: true, ..OutputConfig::default() };
            let g = gps(gps_input(&e, &t, &out).unwrap());
            for f in [g.alt, g.hdop, g.vdop, g.vn, g.ve, g.vd, g.speed_accuracy, g.horiz_accuracy, g.vert_accuracy] {
                prop_assert!(f.is_finite());
            }
            prop_assert!(g.yaw >= 1 && g.yaw <= 36000);
            prop_assert!(g.lat.abs() <= 900_000_000 && g.lon.abs() <= 1_800_000_000);
            let o = GeoOrigin { lat_deg: lat, lon_deg: lon, alt_amsl_m: alt };
            let MavMessage::ODOMETRY(m) = odometry(&e, &t, &local(o, MavAutopilot::MAV_AUTOPILOT_PX4), &out).unwrap() else { panic!() };
            prop_assert!(m.frame_id == MavFrame::MAV_FRAME_LOCAL_NED);
            prop_assert!(m.q.iter().chain(m.pose_covariance.iter()).chain(m.velocity_covariance.iter()).all(|v| v.is_finite()));
        }
    }
}
