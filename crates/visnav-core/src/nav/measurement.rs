//! Inputs of the navigation filter: IMU increments and aiding measurements.
//!
//! Every measurement carries the time it describes (`t_capture_us`, microseconds on the
//! autopilot's boot clock, the same clock as the IMU samples). A measurement may arrive late (a
//! vision fix is delivered after the frame has been processed); the filter applies it at its
//! capture time. Covariances are in NED (north, east, down), metres / metres per second.
//! Heights are above the WGS84 ellipsoid; the caller converts AMSL altitudes with its geoid model.

use nalgebra::{Matrix3, Matrix6, SMatrix, UnitQuaternion, Vector3};

/// One IMU sample: increments over the interval ending at `t_us` (body FRD).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImuSample {
    /// End of the integration interval, microseconds.
    pub t_us: u64,
    /// Integrated angular rate w.r.t. inertial space, rad.
    pub dtheta_rad_body_frd: Vector3<f64>,
    /// Integrated specific force, m/s.
    pub dv_m_s_body_frd: Vector3<f64>,
    /// 1-sigma (each axis) of the rotation over the interval that the increments above do not
    /// capture: a gap in the sample stream bridged by interpolation (`daemon::inputs`), rad; 0
    /// for an ordinary sample. Added to the filter's attitude covariance by the propagation.
    pub gap_sigma_dtheta_rad: f64,
    /// 1-sigma (each axis) of the velocity change the increments do not capture (the same gap),
    /// m/s; 0 for an ordinary sample. Added to the filter's velocity covariance.
    pub gap_sigma_dv_m_s: f64,
}

impl ImuSample {
    /// Build from rates (rad/s, m/s^2) held over `dt_s` (for IMUs that report rates).
    pub fn from_rates(
        t_us: u64,
        gyro_rad_s_body_frd: Vector3<f64>,
        accel_m_s2_body_frd: Vector3<f64>,
        dt_s: f64,
    ) -> Self {
        Self {
            t_us,
            dtheta_rad_body_frd: gyro_rad_s_body_frd * dt_s,
            dv_m_s_body_frd: accel_m_s2_body_frd * dt_s,
            gap_sigma_dtheta_rad: 0.0,
            gap_sigma_dv_m_s: 0.0,
        }
    }
}

/// A global position fix (vision resection or GPS).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PositionFix {
    /// Capture time of the fix, microseconds.
    pub t_capture_us: u64,
    /// Geodetic latitude, rad.
    pub lat_rad: f64,
    /// Longitude, rad.
    pub lon_rad: f64,
    /// Height above the WGS84 ellipsoid, m.
    pub h_m: f64,
    /// Position covariance in NED, m^2.
    pub cov_ned_m2: Matrix3<f64>,
    /// A vision fix solved with the filter's own attitude as a prior depends on that attitude's
    /// error: `z = p + D psi + e` (D in m/rad, `psi` the filter's attitude error, NED rotation
    /// vector, `R_est = Exp(psi) R_true`), and `cov_ned_m2` is then `Cov(e)`, the image's part
    /// alone. The filter puts `-D` into the measurement Jacobian's attitude columns (the
    /// innovation is `estimate - measurement`), so its attitude is not fused a second time
    /// through the position. `None`: no such dependence (GPS, image-only positions).
    pub att_dependence_ned: Option<Matrix3<f64>>,
}

/// A velocity measurement (GPS).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VelocityFix {
    /// Capture time, microseconds.
    pub t_capture_us: u64,
    /// Velocity in NED, m/s.
    pub v_ned_m_s: Vector3<f64>,
    /// Covariance in NED, (m/s)^2.
    pub cov_ned_m2_s2: Matrix3<f64>,
}

/// A height measurement (barometric or AMSL altitude converted to ellipsoidal height).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AltitudeFix {
    /// Capture time, microseconds.
    pub t_capture_us: u64,
    /// Height above the WGS84 ellipsoid, m.
    pub h_m: f64,
    /// Variance, m^2.
    pub var_m2: f64,
}

/// The autopilot's attitude estimate (noise from the configuration).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AttitudeFix {
    /// Capture time, microseconds.
    pub t_capture_us: u64,
    /// Rotates body FRD vectors into NED.
    pub q_nb: UnitQuaternion<f64>,
}

/// A vision fix with the attitude: the image-only camera pose and the covariance of all six
/// degrees of freedom (`fix::VisionOnlyPose`). The position and the tilt of a resection over
/// flat ground are strongly correlated; fused jointly they make the tilt (and the heading)
/// observable at every fix without counting the filter's own attitude prior twice.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseFix {
    /// The camera position; its `cov_ned_m2` is the position block of `cov6`.
    pub position: PositionFix,
    /// Vehicle attitude (body FRD to NED) from the camera attitude through the mount.
    pub q_nb: UnitQuaternion<f64>,
    /// Covariance of `[position error NED (m), attitude error psi NED (rad)]` with
    /// `R_estimate = Exp(psi) R_true` (the filter's convention).
    pub cov6: Matrix6<f64>,
}

/// Visual odometry between two frames (`crate::vo`): the camera's displacement from the previous
/// frame's capture time to the next one's, computed from this filter's own pose at the previous
/// frame. How that pose's errors reach it (`crate::vo`, module doc): a horizontal position error
/// not at all; a yaw error `psi_z` rotates it, `z = dp + psi_z e_D x dp`; a height error scales it,
/// `z = dp (1 + dh / agl)` with `dh = h_est - h_true`. The filter puts both into the Jacobian
/// (`nav::filter::fuse_vo`), so they are its own error states and not noise; `cov_ned_m2` is
/// the images' part plus the tilt term. The terrain model's height error scales it too, and is
/// the same for every frame over the same ground: the filter adds it as
/// `k (terrain_sigma_m / agl_m)^2 dp dp^T` with `k = terrain_corr_dist_m / |dp|` (at least 1), so
/// that over a correlation distance the displacements carry one terrain error, not `k`
/// independent ones. The next frame's tilt comes from the gyros' rotation since the previous
/// frame (a frame cannot tell a small tilt from a sideways shift: `crate::vo`), integrated from
/// this filter's bias-compensated rates: their bias error moves the displacement
/// ([`VoFix::gyro_rotation_sensitivity`]), which the filter also puts into the Jacobian.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VoFix {
    /// Capture time of the previous frame, microseconds.
    pub t_prev_us: u64,
    /// Capture time of the next frame, microseconds.
    pub t_next_us: u64,
    /// Camera displacement between the two capture times, NED, m.
    pub dp_ned_m: Vector3<f64>,
    /// Its covariance, NED, m^2.
    pub cov_ned_m2: Matrix3<f64>,
    /// Height of the previous camera above the terrain that gave the scale, m.
    pub agl_m: f64,
    /// 1-sigma error of the terrain model's height under the footprint, m.
    pub terrain_sigma_m: f64,
    /// Distance over which that error stays the same, m (a datum offset: the whole map).
    pub terrain_corr_dist_m: f64,
    /// Mean line of sight from the next camera to the ground points that gave the motion, NED,
    /// m (straight down, `agl_m` long, for a nadir camera over flat ground).
    pub look_ned_m: Vector3<f64>,
    /// The rotation between the frames that the images saw beyond the gyros' (`None` when the
    /// odometer was given no gyro rotation).
    pub rotation: Option<VoRotation>,
    /// How the displacement moved with the gyros' rotation as the resection weighed it against
    /// the images, `d(dp_ned) / d e` (m/rad; [`Self::gyro_rotation_sensitivity`]); `None`: not
    /// known (no gyro rotation given, or an older log), and the rays' lever arm is taken.
    pub rotation_sensitivity_ned: Option<Matrix3<f64>>,
}

/// The part of a frame pair's rotation the images measure on their own, against the gyros'.
///
/// A rotation about the line of sight turns the whole image about its centre: no shift of the
/// camera looks like it, so the images fix it to hundredths of a degree at any height (the
/// other two axes trade against a sideways shift; `crate::vo`). Measured against the rotation
/// integrated from the filter's bias-compensated rates over the frame interval, it is the gyro
/// bias error's component along the line of sight times the interval: with a nadir camera, the
/// yaw-rate bias that otherwise turns the heading, and with it every displacement, unseen.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VoRotation {
    /// Rotation about the unit mean line of sight `look_ned_m / |look_ned_m|` (right-handed)
    /// taking the gyros' rotation between the frames to the images': `R_images = Exp(a u)
    /// R_gyros` with `u` that axis, both as rotations of the next camera in NED, rad.
    pub about_los_rad: f64,
    /// Its 1-sigma: the images' and what integrating the gyros' sampled rates leaves unknown (a
    /// turn's onset between two samples; the gyros' white noise over the interval is the
    /// filter's to add, their bias is its state), rad.
    pub sigma_rad: f64,
}

/// Longest frame interval a VO displacement may span, s: the filter applies it as the mean
/// velocity at the middle of the interval, exact for constant acceleration; over longer spans a
/// manoeuvre's jerk makes that wrong (and the history does not reach back so far).
pub const VO_MAX_SPAN_S: f64 = 2.0;

impl VoFix {
    /// The middle of the frame interval, where the filter applies it, microseconds.
    pub fn t_mid_us(&self) -> u64 {
        self.t_prev_us + (self.t_next_us.saturating_sub(self.t_prev_us)) / 2
    }

    /// The frame interval, s.
    pub fn span_s(&self) -> f64 {
        self.t_next_us.saturating_sub(self.t_prev_us) as f64 * 1e-6
    }

    /// How the measured displacement moves with an error `e` of the gyros' rotation between
    /// the frames (a NED rotation vector, `R_used = Exp(e) R_true`, the filter's attitude
    /// convention): `d(dp) = G e`.
    ///
    /// Where the images cannot tell a tilt from a sideways shift (a narrow view of flat ground
    /// from high up) the resection follows the gyros: the next camera turned by `e` about its
    /// centre sees every ground point along a ray turned by `e`, and the centre moves by
    /// `-e x s d` for a ray `d` of range `s`, on average `G = [look x]`. Where they can (a wide
    /// view, relief: a drone at 100 m over roofs and trees) the resection follows the images and
    /// `G` is a fraction of that: the odometer then gives the resection's own `d C / d phi_prior`
    /// ([`Self::rotation_sensitivity_ned`]). Taking `[look x]` there made the filter read every
    /// motion's error as a gyro bias, hundreds of deg/h, and turn its tilt a degree off in a
    /// minute (ArduCopter SITL at 100 m, 2 Hz; docs/vo.md). First order; the part about the
    /// line of sight moves nothing. `crate::vo::odometer`'s tests check both against the
    /// odometer.
    pub fn gyro_rotation_sensitivity(&self) -> Matrix3<f64> {
        self.rotation_sensitivity_ned
            .unwrap_or_else(|| crate::nav::ins::skew_matrix(&self.look_ned_m))
    }
}

/// Every entry finite, symmetric (to 1e-9 relative) and positive definite (Cholesky succeeds).
fn symmetric_pd<const N: usize>(c: &SMatrix<f64, N, N>) -> bool {
    c.iter().all(|x| x.is_finite())
        && (c - c.transpose()).abs().max() <= 1e-9 * c.abs().max().max(1e-12)
        && c.cholesky().is_some()
}

/// Any aiding measurement.
// A pose fix (6x6 covariance) is about 400 bytes, the others under 110: measurements are few
// per second and short-lived (the late-measurement history keeps a few seconds), so they stay
// unboxed and `Copy`.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Measurement {
    /// Image-derived global position fix.
    Vision(PositionFix),
    /// Image-derived position and attitude with their joint covariance.
    VisionPose(PoseFix),
    /// GPS position.
    GpsPosition(PositionFix),
    /// GPS velocity.
    GpsVelocity(VelocityFix),
    /// Barometric / AMSL altitude.
    Altitude(AltitudeFix),
    /// Autopilot attitude.
    Attitude(AttitudeFix),
    /// Multirotor drag: the body-frame horizontal specific force as a measurement of the body
    /// velocity ([`super::drag`]).
    Drag(super::drag::DragFix),
    /// Visual odometry: the camera's displacement between two frames.
    Vo(VoFix),
}

impl Measurement {
    /// Capture time, microseconds.
    pub fn t_capture_us(&self) -> u64 {
        match self {
            Measurement::Vision(f) | Measurement::GpsPosition(f) => f.t_capture_us,
            Measurement::VisionPose(f) => f.position.t_capture_us,
            Measurement::GpsVelocity(f) => f.t_capture_us,
            Measurement::Altitude(f) => f.t_capture_us,
            Measurement::Attitude(f) => f.t_capture_us,
            Measurement::Drag(f) => f.t_capture_us,
            Measurement::Vo(f) => f.t_mid_us(),
        }
    }

    /// The position fix in it (GPS position, vision, vision pose) and whether it is a vision
    /// fix (the camera's lever arm) rather than a GPS one (the antenna's).
    pub fn position_fix(&self) -> Option<(&PositionFix, bool)> {
        match self {
            Measurement::Vision(f) => Some((f, true)),
            Measurement::VisionPose(f) => Some((&f.position, true)),
            Measurement::GpsPosition(f) => Some((f, false)),
            _ => None,
        }
    }

    /// Check that every value is finite and every covariance symmetric positive definite.
    pub fn check(&self) -> Result<(), &'static str> {
        if let Measurement::VisionPose(f) = self {
            if !f.q_nb.coords.iter().all(|x| x.is_finite()) {
                return Err("non-finite attitude");
            }
            let c = &f.cov6;
            if !symmetric_pd(c) {
                return Err("pose covariance not symmetric positive definite");
            }
            if (c.fixed_view::<3, 3>(0, 0) - f.position.cov_ned_m2)
                .abs()
                .max()
                > 1e-9 * c.abs().max().max(1e-12)
            {
                return Err("pose covariance and position covariance differ");
            }
            return Measurement::Vision(f.position).check();
        }
        match self {
            Measurement::VisionPose(_) => {}
            Measurement::Vision(f) | Measurement::GpsPosition(f) => {
                if !(f.lat_rad.is_finite() && f.lon_rad.is_finite() && f.h_m.is_finite()) {
                    return Err("non-finite position");
                }
                if f.lat_rad.abs() > 1.5 || f.lon_rad.abs() > std::f64::consts::PI + 1e-9 {
                    return Err("latitude beyond +-86 deg or longitude beyond +-180 deg");
                }
                if f.h_m.abs() > 100_000.0 {
                    return Err("height beyond +-100 km");
                }
                if f.att_dependence_ned
                    .is_some_and(|d| !d.iter().all(|v| v.is_finite()))
                {
                    return Err("non-finite attitude dependence");
                }
                if !symmetric_pd(&f.cov_ned_m2) {
                    return Err("position covariance not symmetric positive definite");
                }
            }
            Measurement::GpsVelocity(f) => {
                if !f.v_ned_m_s.iter().all(|x| x.is_finite()) || f.v_ned_m_s.norm() > 1000.0 {
                    return Err("non-finite or implausible velocity");
                }
                if !symmetric_pd(&f.cov_ned_m2_s2) {
                    return Err("velocity covariance not symmetric positive definite");
                }
            }
            Measurement::Altitude(f) => {
                if !f.h_m.is_finite() || f.h_m.abs() > 100_000.0 {
                    return Err("non-finite or implausible height");
                }
                if !(f.var_m2.is_finite() && f.var_m2 > 0.0) {
                    return Err("altitude variance not positive");
                }
            }
            Measurement::Attitude(f) => {
                if !f.q_nb.coords.iter().all(|x| x.is_finite()) {
                    return Err("non-finite attitude");
                }
            }
            Measurement::Drag(f) => {
                if !(f.f_body_xy_m_s2.iter().all(|x| x.is_finite())
                    && f.wind_sigma_m_s.is_finite()
                    && f.wind_sigma_m_s >= 0.0)
                {
                    return Err("non-finite drag specific force or wind sigma");
                }
                if f.model
                    .iter()
                    .flatten()
                    .any(|m| !(m.a.is_finite() && m.b.is_finite() && m.resid_m_s2.is_finite()))
                {
                    return Err("non-finite drag law");
                }
                if f.model.iter().all(|m| m.is_none()) {
                    return Err("drag measurement without a learned law");
                }
            }
            Measurement::Vo(f) => {
                if f.t_next_us <= f.t_prev_us || f.span_s() > VO_MAX_SPAN_S {
                    return Err("VO frame interval not increasing or longer than 2 s");
                }
                if !f.dp_ned_m.iter().all(|x| x.is_finite())
                    || f.dp_ned_m.norm() > 1000.0 * f.span_s()
                {
                    return Err("non-finite or implausible VO displacement");
                }
                if !(f.agl_m.is_finite() && f.agl_m > 0.0) {
                    return Err("VO height above ground not positive");
                }
                if !(f.look_ned_m.iter().all(|x| x.is_finite()) && f.look_ned_m.z > 0.0) {
                    return Err("VO line of sight non-finite or not towards the ground");
                }
                if !(f.terrain_sigma_m.is_finite()
                    && f.terrain_sigma_m >= 0.0
                    && f.terrain_corr_dist_m.is_finite()
                    && f.terrain_corr_dist_m >= 0.0)
                {
                    return Err("VO terrain sigma or correlation distance negative or non-finite");
                }
                if !symmetric_pd(&f.cov_ned_m2) {
                    return Err("VO covariance not symmetric positive definite");
                }
                if let Some(r) = &f.rotation {
                    // A rotation error beyond 90 deg between two frames is not a gyro error.
                    let ok = r.about_los_rad.is_finite()
                        && r.about_los_rad.abs() < std::f64::consts::FRAC_PI_2
                        && r.sigma_rad.is_finite()
                        && r.sigma_rad > 0.0;
                    if !ok {
                        return Err("VO rotation non-finite, beyond 90 deg, or sigma not positive");
                    }
                }
            }
        }
        Ok(())
    }
}
