//! Error-state (indirect) extended Kalman filter around the strapdown INS, closed loop.
//!
//! Follows Sheta 2012 ch. 5 (21-state error model) and Groves 2013 ch. 14 (local-navigation-frame
//! error equations); Chan 2022 for the image-position aiding at ~1 Hz.
//!
//! Error state `dx` (estimate minus truth), indices:
//! `0..3` position error in NED metres (`dN = dlat (R_M+h)`, `dE = dlon (R_N+h) cos lat`,
//! `dD = -dh`); `3..6` velocity error NED; `6..9` attitude error `psi` in NED with
//! `C_b^n(est) = (I + [psi x]) C_b^n(true)`; `9..12` gyro bias error (rad/s); `12..15` accelerometer
//! bias error (m/s^2); `15..18` gyro scale-factor error; `18..21` accelerometer scale-factor
//! error; `21..24` gyro bias drift error (rad/s); `24..27` accelerometer bias drift error
//! (m/s^2); `27..30` vision position bias (NED, m: `b_est - b_true`). Inactive groups (scale
//! factors without `scale_factor_states`, drifts without `bias_drift_states`, the vision bias
//! without `vision_bias_sigma_h_m`) are frozen at zero with zero covariance (they never receive
//! a gain), which is exactly the smaller filter; the public covariance lists the active states in
//! that order (15 to 30).
//!
//! Vision position bias (`NavConfig::vision_bias_sigma_h_m`): a vision fix measures
//! `z = r_cam + b + e`, `b` a first-order Gauss-Markov process in horizontal distance flown
//! (`phi = e^{-|v_h| dt / L}`, `Qd = sigma^2 (1 - phi^2)` per axis), `e` the fix's own error.
//! GPS fixes do not see `b`, so with both the filter calibrates it; the estimate decays with
//! `phi` like the drift estimates.
//!
//! Bias model (with `bias_drift_states`, the default): the bias of each axis is
//! `b = b_c + b_d`, `b_c` the turn-on bias (random constant, prior sigma `*_bias_deg_h` /
//! `*_bias_ug`, plus the datasheet bias random walk if any) and `b_d` the bias instability, a
//! first-order Gauss-Markov process (sigma `*_bias_instability_*`, correlation time `tau`):
//! `d(b_d)/dt = -b_d / tau + w`, `E[w^2] = 2 sigma^2 / tau`, discretised exactly
//! (`phi = e^{-dt/tau}`, `Qd = sigma^2 (1 - e^{-2 dt/tau})`); the drift estimate decays with
//! `phi` between updates. The total bias compensates the IMU. Without drift states one state per
//! axis carries both (random constant with `q = 2 sigma^2 / tau + q_RW`, conservative).
//!
//! Sensor model: `w_meas = (1 + s_g) w + b_g + n`, `f_meas = (1 + s_a) f + b_a + n`; the INS
//! integrates `w = (w_meas - b_g_est) / (1 + s_g_est)`. Continuous error dynamics (first order):
//! ```text
//! d(dr)/dt   = dv
//! d(dv)/dt   = -[f^n x] psi + (-[(2w_ie + w_en) x] + [v x] dW_en/dv) dv + dg/dr dr
//!              - C_b^n (db_a + db_ad + diag(f^b) ds_a)
//! d(psi)/dt  = -[w_in x] psi - dW_en/dv dv - dW_ie/dr dr - C_b^n (db_g + db_gd + diag(w^b) ds_g)
//! d(b_c)/dt  = w_RW
//! d(b_d)/dt  = -b_d / tau + w_GM
//! ```
//! Discretisation `Phi = I + F dt`, `Qd = G Qc G^T dt` (noise is isotropic, so the rotation `G`
//! drops out for the white-noise terms). Update in Joseph form, `P` symmetrised after every step,
//! then the estimated error is fed back into the INS and the bias/scale estimates (closed loop) and
//! reset to zero. Attitude feedback: `q_nb <- exp(-psi) * q_nb`.
//!
//! Late measurements: every IMU epoch keeps the state/covariance before its measurements, the IMU
//! sample that led to it and the measurements applied at it; a late measurement is applied at the
//! epoch containing its capture time (with the predicted measurement extrapolated over the
//! sub-sample time by the velocity) and the later epochs are re-propagated with their stored IMU
//! samples and measurements.
//!
//! Each measurement type has a chi-square innovation gate on the normalised innovation squared
//! `NIS = dz^T S^-1 dz` and counters. Divergence: `divergence_reject_count` consecutive rejected
//! position fixes reset position/velocity onto the fix when they agree with each other and
//! either the filter could have drifted that far or it has been rejecting them for
//! `step_reset_s` (`super::divergence`); the velocity takes the drift of their innovations. A
//! covariance that loses positive definiteness is re-initialised; a non-finite state or an IMU
//! gap resets the filter to "not initialised".
//!
//! Clipped IMU samples: a gyro or accelerometer sample with an axis at or beyond the sensor's
//! range (`nav.imu.gyro_range_deg_s`, `accel_range_g`; also any finite impossible value such as
//! 1e30) says only that the true value is somewhere at or beyond the range. Integrating it would
//! put up to the range on the velocity every second (4 s at 16 g: 630 m/s), which no later fix
//! can be gated against. Such a sample is replaced by the last good sample's rates held over its
//! interval, and the replaced sensor gets a gap sigma of its full range times the interval
//! (isotropic, added like a bridged gap), so the covariance says what the filter no longer knows
//! and the next fixes pull it back.
//!
//! IMU gaps: a gap longer than `nav.max_imu_gap_s` (the link fell silent, the stream stalled)
//! and at most `nav.max_imu_bridge_s` is bridged instead of restarting the filter: the gap's
//! sample (the daemon's trapezoid of the rates on either side) is propagated in `N` sub-steps of
//! at most `max_imu_gap_s`, each with gap sigmas of `sigma * dt_i * sqrt(N)` for the vehicle's
//! unseen manoeuvres (`nav.imu_bridge_accel_sigma_m_s2`, `imu_bridge_gyro_sigma_deg_s`): a
//! change of rate held through the gap is one error, not `N` independent ones, and these
//! sigmas give the velocity `sigma_a t` and the position `sigma_a t^2 / sqrt 3` (the held
//! error's `t^2 / 2`, slightly conservative). The filter keeps its solution, with the covariance
//! of what it did not see; the next fixes find the aircraft inside it. Counted in `imu_bridged`.

use super::config::DragMode;
use super::config::NavConfig;
use super::divergence::{RejectRun, RejectedFix, RejectedWindow, WindowFit, reset_allowed};
use super::drag::{DragFix, DragLearner};
use super::earth;
use super::ins::{InsState, Strapdown, skew_matrix};
use super::measurement::{
    AltitudeFix, AttitudeFix, ImuSample, Measurement, PositionFix, VelocityFix, VoFix,
};
use crate::stats::chi2_quantile;
pub use health::{HealthCause, HealthReason, ResetCause};
use nalgebra::{Matrix3, SMatrix, SVector, UnitQuaternion, Vector3};
use serde::Serialize;
use std::collections::VecDeque;

mod fuse_altitude;
mod fuse_attitude;
mod fuse_drag;
mod fuse_position;
mod fuse_velocity;
mod fuse_vo;
pub mod health;
mod vo_noise;

/// A sample within this fraction of the sensor's range counts as clipped: a saturated axis
/// reads its full scale minus the last count or two, so equality alone would miss it.
const CLIP_FRACTION: f64 = 0.995;

/// Size of the error state carried internally.
pub const N_STATES: usize = 30;
type Mat = SMatrix<f64, N_STATES, N_STATES>;
type Vecn = SVector<f64, N_STATES>;
const IP: usize = 0;
const IV: usize = 3;
const IA: usize = 6;
const IBG: usize = 9;
const IBA: usize = 12;
const ISG: usize = 15;
const ISA: usize = 18;
const IDG: usize = 21;
const IDA: usize = 24;
const IVB: usize = 27;

/// Filter health.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Health {
    /// Aided, covariance within bounds.
    Ok,
    /// Usable but aiding missing for a while, covariance large or recently reset.
    Degraded,
    /// Not initialised or not trustworthy.
    Lost,
}

/// `ok`, `degraded`, `lost` (as serialised).
impl std::fmt::Display for Health {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Health::Ok => "ok",
            Health::Degraded => "degraded",
            Health::Lost => "lost",
        })
    }
}

/// Counters of one measurement type.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct TypeCounters {
    /// Passed the gate and applied.
    pub accepted: u64,
    /// Failed the chi-square gate.
    pub rejected: u64,
    /// Older than the history window.
    pub too_old: u64,
    /// Malformed (non-finite, bad covariance, capture time in the future).
    pub invalid: u64,
}

/// All counters.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct Counters {
    /// Vision fixes.
    pub vision: TypeCounters,
    /// GPS positions.
    pub gps_position: TypeCounters,
    /// GPS velocities.
    pub gps_velocity: TypeCounters,
    /// Altitudes.
    pub altitude: TypeCounters,
    /// Autopilot attitudes.
    pub attitude: TypeCounters,
    /// Multirotor drag velocity measurements (`nav::drag`).
    pub drag: TypeCounters,
    /// Visual odometry displacements (`crate::vo`).
    pub vo: TypeCounters,
    /// Initialisations (first and after hard resets).
    pub initialisations: u64,
    /// Position/velocity resets after consecutive rejections.
    pub divergence_resets: u64,
    /// Resets refused: the consecutive rejected fixes disagreed with each other
    /// ([`super::divergence`]).
    pub resets_refused: u64,
    /// Covariance re-initialisations after loss of positive definiteness.
    pub covariance_resets: u64,
    /// Hard resets (non-finite state, IMU gap).
    pub hard_resets: u64,
    /// IMU samples dropped (non-finite, time not increasing).
    pub imu_invalid: u64,
    /// IMU samples at or beyond the sensor's range (clipped or impossible), replaced by the last
    /// good sample with the range's uncertainty.
    pub imu_clipped: u64,
    /// IMU gaps bridged (module doc, "IMU gaps").
    pub imu_bridged: u64,
    /// Delayed measurements applied by re-propagation.
    pub replays: u64,
}

/// What happened to a measurement.
#[derive(Debug, Clone, PartialEq)]
pub enum Outcome {
    /// Applied; normalised innovation squared.
    Accepted {
        /// Normalised innovation squared.
        nis: f64,
    },
    /// Rejected by the chi-square gate.
    Rejected {
        /// Normalised innovation squared.
        nis: f64,
        /// Gate threshold.
        gate: f64,
    },
    /// Capture time older than the history.
    TooOld,
    /// Malformed.
    Invalid(&'static str),
    /// Used to initialise the filter.
    Initialised,
    /// Kept for initialisation (filter not yet initialised).
    Held,
    /// Not used (e.g. attitude aiding disabled).
    Ignored,
    /// Caused a divergence reset of position/velocity onto this fix.
    Reset,
}

/// Output record of the filter.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct NavOutput {
    /// Time, microseconds.
    pub t_us: u64,
    /// Latitude, deg.
    pub lat_deg: f64,
    /// Longitude, deg.
    pub lon_deg: f64,
    /// Height above the WGS84 ellipsoid, m.
    pub h_m: f64,
    /// Velocity NED, m/s.
    pub v_ned_m_s: [f64; 3],
    /// Attitude quaternion body FRD -> NED, `[w, x, y, z]`.
    pub q_nb_wxyz: [f64; 4],
    /// ZYX Euler angles `[roll, pitch, yaw]`, deg.
    pub rpy_deg: [f64; 3],
    /// Position covariance NED, m^2 (row major).
    pub cov_pos_ned_m2: [[f64; 3]; 3],
    /// Velocity covariance NED, (m/s)^2.
    pub cov_vel_ned_m2_s2: [[f64; 3]; 3],
    /// Attitude error sigma (NED axes), deg.
    pub att_sigma_deg: [f64; 3],
    /// Estimated gyro bias, deg/h.
    pub gyro_bias_deg_h: [f64; 3],
    /// Body rate w.r.t. inertial space of the last IMU sample, bias- and scale-compensated,
    /// body FRD, rad/s (what moves the attitude on between outputs).
    pub w_body_rad_s: [f64; 3],
    /// Estimated accelerometer bias, micro-g.
    pub accel_bias_ug: [f64; 3],
    /// Health state.
    pub health: Health,
    /// Why the health is not `ok` (empty when ok), cause by cause with their numbers.
    pub reason: HealthReason,
}

#[derive(Debug, Clone)]
struct Core {
    t_us: u64,
    ins: Strapdown,
    bg: Vector3<f64>,
    ba: Vector3<f64>,
    sg: Vector3<f64>,
    sa: Vector3<f64>,
    /// Gauss-Markov bias drift estimates (gyro rad/s, accelerometer m/s^2); zero without drift
    /// states.
    dg: Vector3<f64>,
    da: Vector3<f64>,
    /// Vision position bias estimate, NED, m (zero without bias states).
    vb: Vector3<f64>,
    /// Compensated body rate w.r.t. inertial space of the last IMU sample, rad/s (for the
    /// lever-arm velocity).
    w_b: Vector3<f64>,
    p: Mat,
    /// Capture time of the last applied vision fix, µs (see `vision_error_corr_time_s`).
    last_vision_us: Option<u64>,
    /// Capture time of the last applied autopilot attitude, µs.
    last_att_us: Option<u64>,
    /// Capture time of the last applied drag measurement, µs (`drag::ERROR_CORR_TIME_S`).
    last_drag_us: Option<u64>,
    /// The visual odometry's recent innovations: how much noisier its motions are than they
    /// claim (`vo_noise`).
    vo_noise: vo_noise::VoNoise,
}

#[derive(Debug, Clone)]
struct Epoch {
    imu: ImuSample,
    pre: Core,
    meas: Vec<Measurement>,
}

/// Averages of the bias-corrected specific force and the body velocity over one
/// `drag::WINDOW_S` window.
#[derive(Debug, Clone, Copy, Default)]
struct DragWindow {
    t0_us: Option<u64>,
    f_dt: nalgebra::Vector2<f64>,
    v_dt: nalgebra::Vector2<f64>,
    dt_s: f64,
}

/// Constants derived from the configuration.
#[derive(Debug, Clone)]
struct Params {
    scale: bool,
    drift: bool,
    /// Vision position bias states.
    vbias: bool,
    /// Their stationary variances (N, E, D), m^2, and correlation distance, m.
    var_vb: Vector3<f64>,
    vb_dist_m: f64,
    /// Active error-state indices (15 to 30 of them).
    active: Vec<usize>,
    /// Gauss-Markov correlation times (gyro, accelerometer), s.
    tau_g: f64,
    tau_a: f64,
    /// Gauss-Markov variances (gyro (rad/s)^2, accelerometer (m/s^2)^2).
    var_dg: f64,
    var_da: f64,
    q_arw: f64,
    q_vrw: f64,
    q_bg: f64,
    q_ba: f64,
    gate_vision: f64,
    gate_vision6: f64,
    vision_corr_s: f64,
    gate_gps3: f64,
    gate_alt: f64,
    gate_att: f64,
    gate_att1: f64,
    gate_drag1: f64,
    gate_drag2: f64,
    gate_vo: f64,
    gate_vo4: f64,
    r_att: Matrix3<f64>,
    att_tilt: bool,
    att_corr_s: f64,
    use_att: bool,
    /// Camera and GPS antenna lever arms, body FRD, m.
    l_cam: Vector3<f64>,
    l_gps: Vector3<f64>,
}

/// The navigation filter.
#[derive(Debug, Clone)]
pub struct NavFilter {
    cfg: NavConfig,
    par: Params,
    core: Option<Core>,
    history: VecDeque<Epoch>,
    last_imu_t_us: Option<u64>,
    last_attitude: Option<super::measurement::AttitudeFix>,
    last_gps_vel: Option<VelocityFix>,
    last_pos_for_init: Option<(bool, PositionFix)>,
    counters: Counters,
    last_pos_fix_t_us: Option<u64>,
    consecutive_rejects: u32,
    /// The latest consecutive rejected position fixes (`divergence`).
    rejected: RejectedWindow,
    /// Resets refused because the rejected fixes disagreed with each other.
    last_refusal: Option<super::divergence::Inconsistent>,
    /// Multirotor drag: the law learned while the GPS aids, the current averaging window, the
    /// vehicle type (set by the caller) and the capture time of the last accepted GPS velocity.
    drag_learner: DragLearner,
    drag_window: DragWindow,
    multirotor: bool,
    last_gps_vel_us: Option<u64>,
    last_reset: Option<(u64, ResetCause)>,
    next_output_t_us: Option<u64>,
    /// Rates (gyro rad/s, specific force m/s^2, body FRD) of the last IMU sample inside the
    /// sensor's range: what a clipped sample is replaced by.
    last_good_rates: Option<(Vector3<f64>, Vector3<f64>)>,
    /// Capture time of the first position fix of the current run of rejected ones.
    reject_run_start_us: Option<u64>,
    /// A velocity measurement was rejected since the last accepted position fix: the filter's
    /// own velocity is contradicted, so a step in the position fixes may be the filter's.
    velocity_contradicted: bool,
    /// The horizontal sigma was above the `degraded` / `lost` threshold at the last IMU step:
    /// health improves again only below [`SIGMA_HEALTH_RECOVER_FRACTION`] of it (hysteresis).
    sigma_over_degraded: bool,
    sigma_over_lost: bool,
}

/// Health hysteresis on the horizontal sigma: a state reached because sigma exceeded a threshold
/// is left only once sigma is below this fraction of it. Between fixes the IMU grows sigma and
/// each fix shrinks it, so a sigma hovering at the threshold would otherwise flip the health
/// (and the autopilot's and the ground station's view of it) at every fix; 10 % is about what one
/// fix at the usual rate takes off a sigma at that level.
pub const SIGMA_HEALTH_RECOVER_FRACTION: f64 = 0.9;

/// Whether `sigma` counts as above `threshold`, given whether it was at the last step.
fn sigma_over(sigma: f64, threshold: f64, was_over: bool) -> bool {
    sigma > threshold || (was_over && sigma > threshold * SIGMA_HEALTH_RECOVER_FRACTION)
}

/// Horizontal position sigma, m.
fn sigma_h_m(c: &Core) -> f64 {
    (c.p[(0, 0)] + c.p[(1, 1)]).max(0.0).sqrt()
}

fn dt_s(a_us: u64, b_us: u64) -> f64 {
    (b_us as f64 - a_us as f64) * 1e-6
}

impl NavFilter {
    /// New filter (not initialised) from a validated configuration.
    pub fn new(cfg: NavConfig) -> Self {
        let imu = &cfg.imu;
        let drift = cfg.bias_drift_states;
        // Without drift states the bias instability is carried as the short-term random walk of
        // the Gauss-Markov process, q = 2 sigma^2 / tau, on the constant bias state.
        let gm = |sigma: f64, tau: f64, rw: f64| {
            if drift {
                rw * rw
            } else {
                2.0 * sigma * sigma / tau + rw * rw
            }
        };
        let tilt = cfg.attitude_sigma_tilt_deg.to_radians();
        let yaw = cfg.attitude_sigma_yaw_deg.to_radians();
        let mut active: Vec<usize> = (0..15).collect();
        if cfg.scale_factor_states {
            active.extend(ISG..ISA + 3);
        }
        if drift {
            active.extend(IDG..IDA + 3);
        }
        let vbias = cfg.vision_bias_states();
        if vbias {
            active.extend(IVB..IVB + 3);
        }
        let (bh, bv) = (cfg.vision_bias_sigma_h_m, cfg.vision_bias_sigma_v_m);
        let par = Params {
            scale: cfg.scale_factor_states,
            drift,
            vbias,
            // Floored like the other prior variances: a zero (e.g. `vision_bias_sigma_v_m = 0`
            // beside a horizontal bias) would leave an exactly singular active block.
            var_vb: Vector3::new(bh * bh, bh * bh, bv * bv).map(|v| v.max(1e-20)),
            vb_dist_m: cfg.vision_bias_corr_dist_m,
            active,
            tau_g: imu.gyro_bias_corr_time_s,
            tau_a: imu.accel_bias_corr_time_s,
            var_dg: imu.gyro_bias_instability_si().powi(2),
            var_da: imu.accel_bias_instability_si().powi(2),
            q_arw: imu.gyro_arw_si().powi(2),
            q_vrw: imu.accel_vrw_si().powi(2),
            q_bg: gm(
                imu.gyro_bias_instability_si(),
                imu.gyro_bias_corr_time_s,
                imu.gyro_bias_rw_si(),
            ),
            q_ba: gm(
                imu.accel_bias_instability_si(),
                imu.accel_bias_corr_time_s,
                imu.accel_bias_rw_si(),
            ),
            gate_vision: chi2_quantile(3.0, cfg.gates.vision_prob),
            gate_vision6: chi2_quantile(6.0, cfg.gates.vision_prob),
            vision_corr_s: cfg.vision_error_corr_time_s,
            gate_gps3: chi2_quantile(3.0, cfg.gates.gps_prob),
            gate_alt: chi2_quantile(1.0, cfg.gates.altitude_prob),
            gate_att: chi2_quantile(3.0, cfg.gates.attitude_prob),
            r_att: Matrix3::from_diagonal(&Vector3::new(tilt * tilt, tilt * tilt, yaw * yaw)),
            use_att: cfg.use_autopilot_attitude,
            att_tilt: cfg.autopilot_attitude_tilt,
            att_corr_s: cfg.attitude_error_corr_time_s,
            gate_att1: chi2_quantile(1.0, cfg.gates.attitude_prob),
            gate_drag1: chi2_quantile(1.0, cfg.gates.gps_prob),
            gate_drag2: chi2_quantile(2.0, cfg.gates.gps_prob),
            gate_vo: chi2_quantile(3.0, cfg.gates.vo_prob),
            gate_vo4: chi2_quantile(4.0, cfg.gates.vo_prob),
            l_cam: Vector3::from(cfg.camera_lever_arm()),
            l_gps: Vector3::from(cfg.gps_lever_arm_body_frd_m),
        };
        Self {
            cfg,
            par,
            core: None,
            history: VecDeque::new(),
            last_imu_t_us: None,
            last_attitude: None,
            last_gps_vel: None,
            last_pos_for_init: None,
            counters: Counters::default(),
            last_pos_fix_t_us: None,
            consecutive_rejects: 0,
            rejected: RejectedWindow::default(),
            last_refusal: None,
            drag_learner: DragLearner::default(),
            drag_window: DragWindow::default(),
            multirotor: false,
            last_gps_vel_us: None,
            last_reset: None,
            next_output_t_us: None,
            last_good_rates: None,
            reject_run_start_us: None,
            velocity_contradicted: false,
            sigma_over_degraded: false,
            sigma_over_lost: false,
        }
    }

    /// Configuration in use.
    pub fn config(&self) -> &NavConfig {
        &self.cfg
    }

    /// Number of estimated error states (15 to 30).
    pub fn n_states(&self) -> usize {
        self.cfg.n_states()
    }

    /// True once initialised.
    pub fn is_initialised(&self) -> bool {
        self.core.is_some()
    }

    /// Current navigation state.
    pub fn state(&self) -> Option<&InsState> {
        self.core.as_ref().map(|c| &c.ins.state)
    }

    /// Time of the current state, microseconds.
    pub fn t_us(&self) -> Option<u64> {
        self.core.as_ref().map(|c| c.t_us)
    }

    /// Error covariance of the active states (`n_states` x `n_states`): the 15 navigation
    /// states, then the scale factors (if `scale_factor_states`), then the bias drifts (if
    /// `bias_drift_states`), then the vision position bias (if `vision_bias_sigma_h_m` > 0);
    /// see the module doc.
    pub fn covariance(&self) -> Option<nalgebra::DMatrix<f64>> {
        let a = &self.par.active;
        let n = a.len();
        self.core
            .as_ref()
            .map(|c| nalgebra::DMatrix::from_fn(n, n, |i, j| c.p[(a[i], a[j])]))
    }

    /// Covariance of the 15 navigation errors `[dr_ned, dv_ned, psi_ned, db_gyro, db_accel]`
    /// where the bias errors are those of the total bias used to compensate the IMU (turn-on
    /// plus drift: `T P T^T` with `T` summing the two bias states).
    pub fn nav_error_covariance(&self) -> Option<SMatrix<f64, 15, 15>> {
        let c = self.core.as_ref()?;
        let mut t = SMatrix::<f64, 15, N_STATES>::zeros();
        for i in 0..15 {
            t[(i, i)] = 1.0;
        }
        if self.par.drift {
            for a in 0..3 {
                t[(IBG + a, IDG + a)] = 1.0;
                t[(IBA + a, IDA + a)] = 1.0;
            }
        }
        Some(t * c.p * t.transpose())
    }

    /// Estimated total gyro bias (rad/s) and accelerometer bias (m/s^2), body FRD (turn-on plus
    /// drift).
    pub fn biases(&self) -> Option<(Vector3<f64>, Vector3<f64>)> {
        self.core.as_ref().map(|c| (c.bg + c.dg, c.ba + c.da))
    }

    /// Estimated bias drift (Gauss-Markov states: gyro rad/s, accelerometer m/s^2); zero without
    /// `bias_drift_states`.
    pub fn bias_drifts(&self) -> Option<(Vector3<f64>, Vector3<f64>)> {
        self.core.as_ref().map(|c| (c.dg, c.da))
    }

    /// Estimated vision position bias (NED, m: what the fixes add to the camera position) and
    /// its covariance, m^2; None before initialisation or without bias states.
    pub fn vision_bias(&self) -> Option<(Vector3<f64>, Matrix3<f64>)> {
        let c = self.core.as_ref().filter(|_| self.par.vbias)?;
        Some((c.vb, c.p.fixed_view::<3, 3>(IVB, IVB).into_owned()))
    }

    /// Estimated gyro and accelerometer scale-factor errors (dimensionless).
    pub fn scale_factors(&self) -> Option<(Vector3<f64>, Vector3<f64>)> {
        self.core.as_ref().map(|c| (c.sg, c.sa))
    }

    /// Counters.
    pub fn counters(&self) -> &Counters {
        &self.counters
    }

    /// Process one IMU sample. Returns an output record when one is due at the configured rate.
    pub fn imu(&mut self, s: &ImuSample) -> Option<NavOutput> {
        let gap_ok = |x: f64| x.is_finite() && x >= 0.0;
        if !(s.dtheta_rad_body_frd.iter().all(|x| x.is_finite())
            && s.dv_m_s_body_frd.iter().all(|x| x.is_finite())
            && gap_ok(s.gap_sigma_dtheta_rad)
            && gap_ok(s.gap_sigma_dv_m_s))
        {
            self.counters.imu_invalid += 1;
            return None;
        }
        let Some(last) = self.last_imu_t_us else {
            self.last_imu_t_us = Some(s.t_us);
            return None;
        };
        if s.t_us <= last {
            self.counters.imu_invalid += 1;
            return None;
        }
        self.last_imu_t_us = Some(s.t_us);
        let dt = dt_s(last, s.t_us);
        if dt > self.cfg.max_imu_gap_s {
            if self.core.is_some() {
                if dt <= self.cfg.max_imu_bridge_s {
                    self.bridge(s, last, dt);
                    return self.output_if_due(s.t_us);
                }
                self.hard_reset(s.t_us, ResetCause::ImuGap { dt_s: dt });
            }
            return None;
        }
        let s = &self.within_range(s, dt);
        if !self.step(s) {
            return None;
        }
        self.latch_sigma_health();
        if let Some(d) = self.drag_sample(s, dt) {
            self.measure(Measurement::Drag(d));
        }
        self.output_if_due(s.t_us)
    }

    /// An output record when one is due at `t_us` at the configured rate.
    fn output_if_due(&mut self, t_us: u64) -> Option<NavOutput> {
        let period_us = (1e6 / self.cfg.output_rate_hz).round().max(1.0) as u64;
        let due = self.next_output_t_us.unwrap_or(t_us);
        if t_us >= due {
            self.next_output_t_us = Some(due.max(t_us.saturating_sub(period_us)) + period_us);
            return self.output();
        }
        None
    }

    /// Propagate one (checked) sample and record its epoch; false after a hard reset.
    fn step(&mut self, s: &ImuSample) -> bool {
        let Some(core) = self.core.as_mut() else {
            return false;
        };
        core.propagate(&self.par, s);
        if !core.ins.state.is_finite() || !core.p.iter().all(|x| x.is_finite()) {
            self.hard_reset(s.t_us, ResetCause::NonFinite);
            return false;
        }
        let pre = core.clone();
        self.history.push_back(Epoch {
            imu: *s,
            pre,
            meas: Vec::new(),
        });
        let keep_us = (self.cfg.history_s * 1e6) as u64;
        while self.history.len() > 1
            && self
                .history
                .front()
                .is_some_and(|e| e.pre.t_us + keep_us < s.t_us)
        {
            self.history.pop_front();
        }
        true
    }

    /// Bridge an IMU gap of `dt` s from `last_us` to the sample `s` (module doc, "IMU gaps").
    fn bridge(&mut self, s: &ImuSample, last_us: u64, dt: f64) {
        self.counters.imu_bridged += 1;
        tracing::warn!(
            "IMU gap of {dt:.3} s bridged (nav.max_imu_bridge_s = {}): the solution's covariance \
             grows by what the vehicle may have done unseen",
            self.cfg.max_imu_bridge_s
        );
        let avg = self.within_range(s, dt);
        let (w, f) = (avg.dtheta_rad_body_frd / dt, avg.dv_m_s_body_frd / dt);
        let n = (dt / self.cfg.max_imu_gap_s).ceil().max(1.0) as u64;
        let sqrt_n = (n as f64).sqrt();
        let sigma_a = self.cfg.imu_bridge_accel_sigma_m_s2;
        let sigma_w = self.cfg.imu_bridge_gyro_sigma_deg_s.to_radians();
        let span_us = s.t_us - last_us;
        let mut t_prev = last_us;
        for i in 1..=n {
            let t_i = last_us + span_us * i / n;
            let dt_i = dt_s(t_prev, t_i);
            t_prev = t_i;
            // The sample's own gap sigma (spread over the gap like the bridge's) and the
            // unseen manoeuvres, independent.
            let share = dt_i / dt * sqrt_n;
            let mut sub = ImuSample::from_rates(t_i, w, f, dt_i);
            sub.gap_sigma_dtheta_rad =
                (avg.gap_sigma_dtheta_rad * share).hypot(sigma_w * dt_i * sqrt_n);
            sub.gap_sigma_dv_m_s = (avg.gap_sigma_dv_m_s * share).hypot(sigma_a * dt_i * sqrt_n);
            if !self.step(&sub) {
                return;
            }
        }
    }

    /// The sample, or (when any axis is at or beyond the sensor's range: clipped, or an
    /// impossible value) the last good sample's rates held over `dt` with the range's
    /// uncertainty in its gap sigmas (see the module doc, "Clipped IMU samples").
    fn within_range(&mut self, s: &ImuSample, dt: f64) -> ImuSample {
        if dt <= 0.0 {
            return *s;
        }
        let (w, f) = (s.dtheta_rad_body_frd / dt, s.dv_m_s_body_frd / dt);
        let imu = &self.cfg.imu;
        let w_range = imu.gyro_range_deg_s.to_radians();
        let f_range = imu.accel_range_g * super::config::G0_M_S2;
        let gyro_clipped = w.amax() >= w_range * CLIP_FRACTION;
        let accel_clipped = f.amax() >= f_range * CLIP_FRACTION;
        if !gyro_clipped && !accel_clipped {
            self.last_good_rates = Some((w, f));
            return *s;
        }
        self.counters.imu_clipped += 1;
        if self.counters.imu_clipped == 1 || self.counters.imu_clipped.is_power_of_two() {
            tracing::warn!(
                "IMU sample at or beyond the sensor's range (nav.imu.accel_range_g / \
                 gyro_range_deg_s): held the last good sample ({} so far)",
                self.counters.imu_clipped
            );
        }
        // Without a good sample yet: no rotation and no specific force, with the same sigma.
        let (w0, f0) = self.last_good_rates.unwrap_or_default();
        let mut out = ImuSample::from_rates(s.t_us, w0, f0, dt);
        let sigma = |range: f64, clipped: bool, good: f64| if clipped { range * dt } else { good };
        // The sensor (gyro or accelerometer) that is not clipped keeps its own measurement.
        if !gyro_clipped {
            out.dtheta_rad_body_frd = s.dtheta_rad_body_frd;
        }
        if !accel_clipped {
            out.dv_m_s_body_frd = s.dv_m_s_body_frd;
        }
        out.gap_sigma_dtheta_rad = sigma(w_range, gyro_clipped, s.gap_sigma_dtheta_rad);
        out.gap_sigma_dv_m_s = sigma(f_range, accel_clipped, s.gap_sigma_dv_m_s);
        out
    }

    /// Tell the filter whether the vehicle is a multirotor (`[nav.drag] mode = "auto"` fuses
    /// the drag law only then).
    pub fn set_multirotor(&mut self, multirotor: bool) {
        self.multirotor = multirotor;
    }

    /// The learned drag law per body axis (x, y), or why it is not usable yet.
    pub fn drag_status(&self) -> [Result<super::drag::AxisModel, super::drag::NotLearned>; 2] {
        [self.drag_learner.axis(0), self.drag_learner.axis(1)]
    }

    /// Accumulate the drag window with one IMU sample; at the window's end, learn from it while
    /// the GPS aids, or return it as a measurement once the GPS has been gone
    /// `[nav.drag] after_gps_s` (see `nav::drag`).
    fn drag_sample(&mut self, s: &ImuSample, dt: f64) -> Option<DragFix> {
        let cfg = &self.cfg.drag;
        if cfg.mode == DragMode::Off || dt <= 0.0 {
            return None;
        }
        let core = self.core.as_ref()?;
        let st = &core.ins.state;
        let f_b = s.dv_m_s_body_frd / dt - (core.ba + core.da);
        let v_b = st.q_nb.inverse() * st.v_ned_m_s;
        let w = &mut self.drag_window;
        let t0 = *w
            .t0_us
            .get_or_insert(s.t_us.saturating_sub((dt * 1e6) as u64));
        w.f_dt += f_b.xy() * dt;
        w.v_dt += v_b.xy() * dt;
        w.dt_s += dt;
        if w.dt_s < super::drag::WINDOW_S {
            return None;
        }
        let (f, v, t_mid) = (w.f_dt / w.dt_s, w.v_dt / w.dt_s, t0 + (s.t_us - t0) / 2);
        *w = DragWindow::default();
        let since_gps_s = self
            .last_gps_vel_us
            .map(|t| dt_s(t, t_mid))
            .unwrap_or(f64::INFINITY);
        if since_gps_s < 1.0 {
            self.drag_learner.add(v, f);
            return None;
        }
        let fuse = cfg.mode == DragMode::On || self.multirotor;
        if !fuse || since_gps_s < cfg.after_gps_s {
            return None;
        }
        let model = self.drag_learner.models();
        model.iter().any(|m| m.is_some()).then_some(DragFix {
            t_capture_us: t_mid,
            f_body_xy_m_s2: f,
            model,
            wind_sigma_m_s: cfg.wind_sigma_m_s,
        })
    }

    /// The current output record (None before initialisation).
    pub fn output(&self) -> Option<NavOutput> {
        let c = self.core.as_ref()?;
        let (health, reason) = self.health();
        let s = &c.ins.state;
        let (r, p, y) = s.q_nb.euler_angles();
        let blk = |i: usize| {
            let mut m = [[0.0; 3]; 3];
            for (a, row) in m.iter_mut().enumerate() {
                for (b, v) in row.iter_mut().enumerate() {
                    *v = c.p[(i + a, i + b)];
                }
            }
            m
        };
        let q = s.q_nb.coords; // ok: nalgebra stores [x, y, z, w]
        Some(NavOutput {
            t_us: c.t_us,
            lat_deg: s.lat_rad.to_degrees(),
            lon_deg: s.lon_rad.to_degrees(),
            h_m: s.h_m,
            v_ned_m_s: [s.v_ned_m_s.x, s.v_ned_m_s.y, s.v_ned_m_s.z],
            q_nb_wxyz: [q[3], q[0], q[1], q[2]],
            rpy_deg: [r.to_degrees(), p.to_degrees(), y.to_degrees()],
            cov_pos_ned_m2: blk(IP),
            cov_vel_ned_m2_s2: blk(IV),
            att_sigma_deg: [
                c.p[(IA, IA)].sqrt().to_degrees(),
                c.p[(IA + 1, IA + 1)].sqrt().to_degrees(),
                c.p[(IA + 2, IA + 2)].sqrt().to_degrees(),
            ],
            gyro_bias_deg_h: ((c.bg + c.dg) / super::config::DEG_H_TO_RAD_S).into(),
            w_body_rad_s: c.w_b.into(),
            accel_bias_ug: ((c.ba + c.da) / super::config::UG_TO_M_S2).into(),
            health,
            reason,
        })
    }

    /// Remember which health thresholds the horizontal sigma is over (with the hysteresis of
    /// [`sigma_over`]), for [`Self::health`].
    fn latch_sigma_health(&mut self) {
        let Some(c) = self.core.as_ref() else {
            return;
        };
        let (sig_h, h) = (sigma_h_m(c), &self.cfg.health);
        self.sigma_over_degraded =
            sigma_over(sig_h, h.degraded_pos_sigma_m, self.sigma_over_degraded);
        self.sigma_over_lost = sigma_over(sig_h, h.lost_pos_sigma_m, self.sigma_over_lost);
    }

    /// Health state and its reason. A state reached by the horizontal sigma is left only once
    /// the sigma is below [`SIGMA_HEALTH_RECOVER_FRACTION`] of its threshold.
    pub fn health(&self) -> (Health, HealthReason) {
        let Some(c) = self.core.as_ref() else {
            let why = HealthCause::NotInitialised {
                after_reset: self.last_reset.map(|(_, r)| r),
            };
            return (Health::Lost, HealthReason::of(why));
        };
        let h = &self.cfg.health;
        let sig_h = sigma_h_m(c);
        let since_fix = self
            .last_pos_fix_t_us
            .map(|t| dt_s(t, c.t_us).max(0.0))
            .unwrap_or(f64::INFINITY);
        if sigma_over(sig_h, h.lost_pos_sigma_m, self.sigma_over_lost) {
            return (
                Health::Lost,
                HealthReason::of(HealthCause::SigmaOver {
                    sigma_m: sig_h,
                    limit_m: h.lost_pos_sigma_m,
                }),
            );
        }
        if since_fix > h.lost_no_fix_s {
            return (
                Health::Lost,
                HealthReason::of(HealthCause::NoFixFor { s: since_fix }),
            );
        }
        let mut reasons = Vec::new();
        if sigma_over(sig_h, h.degraded_pos_sigma_m, self.sigma_over_degraded) {
            reasons.push(HealthCause::SigmaOver {
                sigma_m: sig_h,
                limit_m: h.degraded_pos_sigma_m,
            });
        }
        if since_fix > h.degraded_no_fix_s {
            reasons.push(HealthCause::NoFixFor { s: since_fix });
        }
        if let Some((t, r)) = &self.last_reset
            && dt_s(*t, c.t_us) < h.reset_degraded_s
        {
            reasons.push(HealthCause::RecentReset(*r));
        }
        if self.consecutive_rejects > 0 {
            reasons.push(HealthCause::FixesRejected {
                n: self.consecutive_rejects,
            });
        }
        if let Some(why) = &self.last_refusal {
            reasons.push(HealthCause::NoResetOnto(*why));
        }
        if reasons.is_empty() {
            (Health::Ok, HealthReason::default())
        } else {
            (Health::Degraded, HealthReason(reasons))
        }
    }

    /// Forget the current run of rejected position fixes (a fix was accepted, or the filter was
    /// reset or initialised): the divergence window, its refusal, its start and the velocity
    /// contradiction seen during it.
    fn end_reject_run(&mut self) {
        self.consecutive_rejects = 0;
        self.rejected.clear();
        self.last_refusal = None;
        self.reject_run_start_us = None;
        self.velocity_contradicted = false;
    }

    fn hard_reset(&mut self, t_us: u64, reason: ResetCause) {
        tracing::warn!("nav filter hard reset: {reason}");
        self.core = None;
        self.history.clear();
        self.counters.hard_resets += 1;
        self.end_reject_run();
        self.last_pos_for_init = None;
        self.last_reset = Some((t_us, reason));
    }

    fn type_counters(&mut self, m: &Measurement) -> &mut TypeCounters {
        match m {
            Measurement::Vision(_) | Measurement::VisionPose(_) => &mut self.counters.vision,
            Measurement::GpsPosition(_) => &mut self.counters.gps_position,
            Measurement::GpsVelocity(_) => &mut self.counters.gps_velocity,
            Measurement::Altitude(_) => &mut self.counters.altitude,
            Measurement::Attitude(_) => &mut self.counters.attitude,
            Measurement::Drag(_) => &mut self.counters.drag,
            Measurement::Vo(_) => &mut self.counters.vo,
        }
    }

    /// Process one aiding measurement (possibly late: applied at its capture time).
    pub fn measure(&mut self, m: Measurement) -> Outcome {
        if let Err(why) = m.check() {
            self.type_counters(&m).invalid += 1;
            return Outcome::Invalid(why);
        }
        match &m {
            Measurement::Attitude(a) => self.last_attitude = Some(*a),
            Measurement::GpsVelocity(v) => self.last_gps_vel = Some(*v),
            _ => {}
        }
        if self.core.is_none() {
            return self.try_initialise(&m);
        }
        if matches!(m, Measurement::Attitude(_)) && !self.par.use_att {
            return Outcome::Ignored;
        }
        let t_c = m.t_capture_us();
        let Some(cur_t) = self.t_us() else {
            return Outcome::Held;
        };
        if t_c > cur_t + 200_000 {
            self.type_counters(&m).invalid += 1;
            return Outcome::Invalid("capture time more than 0.2 s after the latest IMU sample");
        }
        let is_pos = m.position_fix().is_some();
        let out = if t_c >= cur_t || self.history.back().is_some_and(|e| t_c >= e.pre.t_us) {
            // On time: apply at the current epoch.
            let par = self.par.clone();
            let Some(core) = self.core.as_mut() else {
                return Outcome::Held;
            };
            let out = apply(&par, core, &m);
            if matches!(out, Outcome::Accepted { .. })
                && let Some(e) = self.history.back_mut()
            {
                e.meas.push(m);
            }
            out
        } else {
            self.apply_delayed(m, t_c)
        };
        match &out {
            Outcome::Accepted { .. } => {
                self.type_counters(&m).accepted += 1;
                if let Measurement::GpsVelocity(v) = &m {
                    self.last_gps_vel_us =
                        Some(self.last_gps_vel_us.unwrap_or(0).max(v.t_capture_us));
                }
                if is_pos {
                    self.end_reject_run();
                    self.last_pos_fix_t_us = Some(self.last_pos_fix_t_us.unwrap_or(0).max(t_c));
                }
            }
            Outcome::Rejected { .. } => {
                self.type_counters(&m).rejected += 1;
                if matches!(m, Measurement::GpsVelocity(_)) {
                    self.velocity_contradicted = true;
                }
                if is_pos {
                    self.consecutive_rejects += 1;
                    self.reject_run_start_us.get_or_insert(t_c);
                    self.note_rejected(&m);
                    if self.consecutive_rejects >= self.cfg.health.divergence_reject_count {
                        let run = RejectRun {
                            last_accepted_s: self.last_pos_fix_t_us.map(|t| t as f64 * 1e-6),
                            first_rejected_s: self.reject_run_start_us.unwrap_or(t_c) as f64 * 1e-6,
                            latest_s: t_c as f64 * 1e-6,
                            velocity_contradicted: self.velocity_contradicted,
                        };
                        let step_s = self.cfg.health.step_reset_s;
                        match self
                            .rejected
                            .consistent()
                            .and_then(|fit| reset_allowed(&fit, &run, step_s).map(|()| fit))
                        {
                            Ok(fit) => {
                                self.divergence_reset(&m, &fit);
                                return Outcome::Reset;
                            }
                            Err(why) => {
                                self.counters.resets_refused += 1;
                                if self.last_refusal.is_none() {
                                    tracing::warn!(
                                        "nav filter: {} consecutive position fixes rejected, no \
                                         reset onto them: {why}",
                                        self.consecutive_rejects
                                    );
                                }
                                self.last_refusal = Some(why);
                            }
                        }
                    }
                }
            }
            Outcome::TooOld => self.type_counters(&m).too_old += 1,
            Outcome::Invalid(_) => self.type_counters(&m).invalid += 1,
            _ => {}
        }
        if let Some(c) = &self.core
            && !c.is_pd(&self.par.active)
        {
            self.covariance_reset();
        }
        out
    }

    fn apply_delayed(&mut self, m: Measurement, t_c: u64) -> Outcome {
        // Epoch j: last epoch with t <= t_c.
        let Some(j) = self.history.iter().rposition(|e| e.pre.t_us <= t_c) else {
            return Outcome::TooOld;
        };
        let par = self.par.clone();
        let mut core = self.history[j].pre.clone();
        let pos = self.history[j]
            .meas
            .iter()
            .position(|x| x.t_capture_us() > t_c)
            .unwrap_or(self.history[j].meas.len());
        for x in &self.history[j].meas[..pos] {
            apply(&par, &mut core, x);
        }
        let out = apply(&par, &mut core, &m);
        if !matches!(out, Outcome::Accepted { .. }) {
            return out;
        }
        for x in &self.history[j].meas[pos..] {
            apply(&par, &mut core, x);
        }
        self.history[j].meas.insert(pos, m);
        for i in j + 1..self.history.len() {
            let imu = self.history[i].imu;
            core.propagate(&par, &imu);
            self.history[i].pre = core.clone();
            for x in &self.history[i].meas {
                apply(&par, &mut core, x);
            }
        }
        self.counters.replays += 1;
        self.core = Some(core);
        out
    }

    /// Keep a rejected position fix's horizontal innovation for the divergence test.
    fn note_rejected(&mut self, m: &Measurement) {
        let (Some((f, is_vision)), Some(core)) = (m.position_fix(), self.core.as_ref()) else {
            return;
        };
        let d = fuse_position::position_innovation(&self.par, core, f, is_vision);
        let c = f.cov_ned_m2.fixed_view::<2, 2>(0, 0).into_owned();
        let var_h = c.symmetric_eigenvalues().max();
        let cap = self.cfg.health.divergence_reject_count.max(3) as usize;
        self.rejected.push(
            RejectedFix {
                t_s: f.t_capture_us as f64 * 1e-6,
                innov_ne_m: nalgebra::Vector2::new(d.x, d.y),
                var_h_m2: var_h,
            },
            cap,
        );
    }

    fn divergence_reset(&mut self, m: &Measurement, fit: &WindowFit) {
        let Some((f, is_vision)) = m.position_fix() else {
            return;
        };
        let Some(core) = self.core.as_mut() else {
            return;
        };
        let reason = ResetCause::Divergence {
            rejected: self.consecutive_rejects,
        };
        tracing::warn!("nav filter divergence: {reason}");
        let dt = dt_s(f.t_capture_us, core.t_us);
        let v = core.ins.state.v_ned_m_s;
        let l = if is_vision {
            self.par.l_cam
        } else {
            self.par.l_gps
        };
        let (lat, lon, h) = shift_ned(
            (f.lat_rad, f.lon_rad, f.h_m),
            &(v * dt - core.ins.state.q_nb * l),
        );
        core.ins.state.lat_rad = lat;
        core.ins.state.lon_rad = lon;
        core.ins.state.h_m = h;
        // The drift of the rejected innovations is the filter's horizontal velocity error.
        let vel_var =
            if fit.rate_var_m2_s2.is_finite() && fit.rate_ne_m_s.iter().all(|x| x.is_finite()) {
                core.ins.state.v_ned_m_s.x += fit.rate_ne_m_s.x;
                core.ins.state.v_ned_m_s.y += fit.rate_ne_m_s.y;
                fit.rate_var_m2_s2
            } else {
                0.0
            };
        // A vision reset also restarts the bias (the fixes were rejected: its estimate may be
        // the cause); the position then carries the bias's error as at initialisation.
        let vision_bias = is_vision && self.par.vbias;
        let mut rows: Vec<usize> = (0..6).collect();
        if vision_bias {
            rows.extend(IVB..IVB + 3);
            core.vb = Vector3::zeros();
        }
        for i in rows {
            for k in 0..N_STATES {
                core.p[(i, k)] = 0.0;
                core.p[(k, i)] = 0.0;
            }
        }
        let vs = self.cfg.health.reset_vel_sigma_m_s.powi(2) + vel_var;
        for a in 0..3 {
            for b in 0..3 {
                core.p[(IP + a, IP + b)] = f.cov_ned_m2[(a, b)];
            }
            core.p[(IV + a, IV + a)] = vs;
            if vision_bias {
                let vb = self.par.var_vb[a];
                core.p[(IP + a, IP + a)] += vb;
                core.p[(IVB + a, IVB + a)] = vb;
                core.p[(IP + a, IVB + a)] = -vb;
                core.p[(IVB + a, IP + a)] = -vb;
            }
        }
        let now = core.t_us;
        let pre = core.clone();
        self.history.clear();
        self.history.push_back(Epoch {
            imu: ImuSample {
                t_us: now,
                dtheta_rad_body_frd: Vector3::zeros(),
                dv_m_s_body_frd: Vector3::zeros(),
                gap_sigma_dtheta_rad: 0.0,
                gap_sigma_dv_m_s: 0.0,
            },
            pre,
            meas: Vec::new(),
        });
        self.counters.divergence_resets += 1;
        self.end_reject_run();
        self.last_pos_fix_t_us = Some(f.t_capture_us);
        self.last_reset = Some((now, reason));
    }

    fn covariance_reset(&mut self) {
        let p0 = self.initial_p(None, None);
        if let Some(c) = self.core.as_mut() {
            tracing::warn!("nav filter covariance lost positive definiteness: re-initialised");
            let mut p = p0;
            for i in 0..6 {
                p[(i, i)] = c.p[(i, i)].abs().max(p0[(i, i)]);
            }
            c.p = p;
            let now = c.t_us;
            self.history.clear();
            self.counters.covariance_resets += 1;
            self.last_reset = Some((now, ResetCause::CovarianceNotPositiveDefinite));
        }
    }

    /// Initial covariance; position/velocity blocks from the given covariances (or 100 m, 10 m/s).
    fn initial_p(&self, pos: Option<&Matrix3<f64>>, vel: Option<&Matrix3<f64>>) -> Mat {
        let imu = &self.cfg.imu;
        let mut p = Mat::zeros();
        let pos = pos.copied().unwrap_or(Matrix3::identity() * 1e4);
        let vel = vel.copied().unwrap_or(Matrix3::identity() * 100.0);
        let tilt = self.cfg.init.tilt_sigma_deg.to_radians().powi(2);
        let yaw = self.cfg.init.yaw_sigma_deg.to_radians().powi(2);
        // With drift states the turn-on bias and the Gauss-Markov drift have their own states;
        // without, the constant bias state carries both variances.
        let (bg, ba) = if self.par.drift {
            (imu.gyro_bias_si().powi(2), imu.accel_bias_si().powi(2))
        } else {
            (
                imu.gyro_bias_si().powi(2) + imu.gyro_bias_instability_si().powi(2),
                imu.accel_bias_si().powi(2) + imu.accel_bias_instability_si().powi(2),
            )
        };
        for a in 0..3 {
            for b in 0..3 {
                p[(IP + a, IP + b)] = pos[(a, b)];
                p[(IV + a, IV + b)] = vel[(a, b)];
            }
            p[(IBG + a, IBG + a)] = bg.max(1e-20);
            p[(IBA + a, IBA + a)] = ba.max(1e-20);
            if self.par.scale {
                p[(ISG + a, ISG + a)] = (imu.gyro_scale_ppm * 1e-6).powi(2).max(1e-20);
                p[(ISA + a, ISA + a)] = (imu.accel_scale_ppm * 1e-6).powi(2).max(1e-20);
            }
            if self.par.drift {
                p[(IDG + a, IDG + a)] = self.par.var_dg.max(1e-20);
                p[(IDA + a, IDA + a)] = self.par.var_da.max(1e-20);
            }
            if self.par.vbias {
                p[(IVB + a, IVB + a)] = self.par.var_vb[a];
            }
        }
        p[(IA, IA)] = tilt;
        p[(IA + 1, IA + 1)] = tilt;
        p[(IA + 2, IA + 2)] = yaw;
        p
    }

    fn try_initialise(&mut self, m: &Measurement) -> Outcome {
        let (is_gps, fix) = match m {
            Measurement::Vision(f) => (false, *f),
            Measurement::VisionPose(f) => (false, f.position),
            Measurement::GpsPosition(f) => (true, *f),
            _ => return Outcome::Held,
        };
        let Some(t_now) = self.last_imu_t_us else {
            return Outcome::Held;
        };
        let Some(att) = self.last_attitude else {
            return Outcome::Held;
        };
        if dt_s(att.t_capture_us, fix.t_capture_us).abs() > 1.0 {
            return Outcome::Held;
        }
        // Velocity: a recent GPS velocity, else the difference of two fixes of the same source.
        let mut vel = None;
        if let Some(v) = self.last_gps_vel
            && dt_s(v.t_capture_us, fix.t_capture_us).abs() <= 0.5
        {
            vel = Some((v.v_ned_m_s, v.cov_ned_m2_s2));
        }
        if vel.is_none()
            && let Some((prev_gps, prev)) = self.last_pos_for_init
            && prev_gps == is_gps
        {
            let dt = dt_s(prev.t_capture_us, fix.t_capture_us);
            let ic = &self.cfg.init;
            if dt >= ic.vision_init_min_dt_s && dt <= ic.vision_init_max_dt_s {
                let d = earth::ned_offset_m(
                    (fix.lat_rad, fix.lon_rad, fix.h_m),
                    (prev.lat_rad, prev.lon_rad, prev.h_m),
                );
                let cov = (fix.cov_ned_m2 + prev.cov_ned_m2) / (dt * dt)
                    + Matrix3::identity() * ic.vision_vel_sigma_m_s.powi(2);
                vel = Some((d / dt, cov));
            }
        }
        self.last_pos_for_init = Some((is_gps, fix));
        let Some((v, vcov)) = vel else {
            return Outcome::Held;
        };
        let dt = dt_s(fix.t_capture_us, t_now);
        if !(-0.5..=1.0).contains(&dt) {
            return Outcome::Held;
        }
        // The fix is the camera / antenna position: move it to the IMU and to the current time.
        let l = if is_gps {
            self.par.l_gps
        } else {
            self.par.l_cam
        };
        let (lat_rad, lon_rad, h_m) = shift_ned(
            (fix.lat_rad, fix.lon_rad, fix.h_m),
            &(v * dt - att.q_nb * l),
        );
        let state = InsState {
            lat_rad,
            lon_rad,
            h_m,
            v_ned_m_s: v,
            q_nb: att.q_nb,
        };
        let mut p = self.initial_p(Some(&(fix.cov_ned_m2 + vcov * dt * dt)), Some(&vcov));
        if !is_gps && self.par.vbias {
            // Initialised on a vision fix, the position error is the fix's bias plus its own
            // error: `dr = b + e`, `db = 0 - b`, so `Cov(dr) += Sb`, `Cov(dr, db) = -Sb`.
            for a in 0..3 {
                let vb = self.par.var_vb[a];
                p[(IP + a, IP + a)] += vb;
                p[(IP + a, IVB + a)] = -vb;
                p[(IVB + a, IP + a)] = -vb;
            }
        }
        let core = Core {
            t_us: t_now,
            ins: Strapdown::new(state),
            bg: Vector3::zeros(),
            ba: Vector3::zeros(),
            sg: Vector3::zeros(),
            sa: Vector3::zeros(),
            dg: Vector3::zeros(),
            da: Vector3::zeros(),
            vb: Vector3::zeros(),
            w_b: Vector3::zeros(),
            p,
            last_vision_us: None,
            last_att_us: None,
            last_drag_us: None,
            vo_noise: vo_noise::VoNoise::default(),
        };
        self.history.clear();
        self.history.push_back(Epoch {
            imu: ImuSample {
                t_us: t_now,
                dtheta_rad_body_frd: Vector3::zeros(),
                dv_m_s_body_frd: Vector3::zeros(),
                gap_sigma_dtheta_rad: 0.0,
                gap_sigma_dv_m_s: 0.0,
            },
            pre: core.clone(),
            meas: Vec::new(),
        });
        self.core = Some(core);
        self.counters.initialisations += 1;
        self.last_pos_fix_t_us = Some(fix.t_capture_us);
        self.end_reject_run();
        tracing::info!(
            "nav filter initialised from {} fix",
            if is_gps { "GPS" } else { "vision" }
        );
        Outcome::Initialised
    }
}

impl Core {
    /// Positive definiteness of the active block (15 to 30 states).
    fn is_pd(&self, active: &[usize]) -> bool {
        let n = active.len();
        nalgebra::DMatrix::from_fn(n, n, |i, j| self.p[(active[i], active[j])])
            .cholesky()
            .is_some()
    }

    fn propagate(&mut self, par: &Params, s: &ImuSample) {
        let dt = dt_s(self.t_us, s.t_us);
        if dt <= 0.0 {
            return;
        }
        let one = Vector3::repeat(1.0);
        let dth =
            (s.dtheta_rad_body_frd - (self.bg + self.dg) * dt).component_div(&(one + self.sg));
        let dv = (s.dv_m_s_body_frd - (self.ba + self.da) * dt).component_div(&(one + self.sa));
        self.ins.step(&dth, &dv, dt);
        self.t_us = s.t_us;
        // The drift estimates decay like the Gauss-Markov mean.
        let (phi_g, phi_a) = if par.drift {
            ((-dt / par.tau_g).exp(), (-dt / par.tau_a).exp())
        } else {
            (1.0, 1.0)
        };
        self.dg *= phi_g;
        self.da *= phi_a;
        // The vision bias decorrelates with the horizontal distance flown (Gauss-Markov in
        // distance): its estimate decays like its mean.
        let phi_b = if par.vbias {
            let v = self.ins.state.v_ned_m_s;
            (-v.x.hypot(v.y) * dt / par.vb_dist_m).exp()
        } else {
            1.0
        };
        self.vb *= phi_b;

        let st = &self.ins.state;
        let (lat, h, v) = (st.lat_rad, st.h_m, st.v_ned_m_s);
        let (rm, rn) = earth::radii_m(lat);
        let c_bn = st.q_nb.to_rotation_matrix().into_inner();
        let w_b = dth / dt;
        self.w_b = w_b;
        let f_b = dv / dt;
        let f_n = c_bn * f_b;
        let w_ie = earth::earth_rate_ned(lat);
        let w_en = earth::transport_rate_ned(lat, h, &v);
        let g = earth::normal_gravity_m_s2(lat, h);
        let om = crate::geo::wgs84::OMEGA_E_RAD_S;
        // dW_en / dv
        let mut d_wen_dv = Matrix3::zeros();
        d_wen_dv[(0, 1)] = 1.0 / (rn + h);
        d_wen_dv[(1, 0)] = -1.0 / (rm + h);
        d_wen_dv[(2, 1)] = -lat.tan() / (rn + h);
        // dW_ie / dN (per metre north)
        let d_wie_dn = Vector3::new(-om * lat.sin(), 0.0, -om * lat.cos()) / (rm + h);

        let mut f = Mat::zeros();
        let set = |f: &mut Mat, r: usize, c: usize, m: &Matrix3<f64>| {
            f.fixed_view_mut::<3, 3>(r, c).copy_from(m);
        };
        set(&mut f, IP, IV, &Matrix3::identity());
        set(&mut f, IV, IA, &(-skew_matrix(&f_n)));
        set(
            &mut f,
            IV,
            IV,
            &(-skew_matrix(&(2.0 * w_ie + w_en)) + skew_matrix(&v) * d_wen_dv),
        );
        let mut fvp = Matrix3::zeros();
        fvp.set_column(0, &(skew_matrix(&v) * (2.0 * d_wie_dn)));
        fvp[(2, 2)] += 2.0 * g / ((rm * rn).sqrt() + h);
        set(&mut f, IV, IP, &fvp);
        set(&mut f, IV, IBA, &(-c_bn));
        set(&mut f, IA, IA, &(-skew_matrix(&(w_ie + w_en))));
        set(&mut f, IA, IV, &(-d_wen_dv));
        let mut fap = Matrix3::zeros();
        fap.set_column(0, &(-d_wie_dn));
        set(&mut f, IA, IP, &fap);
        set(&mut f, IA, IBG, &(-c_bn));
        // Bias states: random constant (turn-on bias) driven by the instability's short-term
        // random walk (q = 2 sigma^2 / tau) and the bias random walk; no decay term, because a
        // Gauss-Markov decay would shrink the turn-on bias uncertainty without information.
        if par.scale {
            set(&mut f, IA, ISG, &(-c_bn * Matrix3::from_diagonal(&w_b)));
            set(&mut f, IV, ISA, &(-c_bn * Matrix3::from_diagonal(&f_b)));
        }
        if par.drift {
            set(&mut f, IA, IDG, &(-c_bn));
            set(&mut f, IV, IDA, &(-c_bn));
        }
        let mut phi = Mat::identity() + f * dt;
        if par.drift {
            // Exact first-order Gauss-Markov transition and noise:
            // phi = e^{-dt/tau}, Qd = sigma^2 (1 - e^{-2 dt/tau}).
            for a in 0..3 {
                phi[(IDG + a, IDG + a)] = phi_g;
                phi[(IDA + a, IDA + a)] = phi_a;
            }
        }
        if par.vbias {
            for a in 0..3 {
                phi[(IVB + a, IVB + a)] = phi_b;
            }
        }
        let mut p = phi * self.p * phi.transpose();
        // A bridged gap in the IMU stream (`ImuSample::gap_sigma_*`, isotropic, so the same in
        // any frame).
        let (gap_att, gap_vel) = (s.gap_sigma_dtheta_rad, s.gap_sigma_dv_m_s);
        for a in 0..3 {
            p[(IV + a, IV + a)] += par.q_vrw * dt + gap_vel * gap_vel;
            p[(IA + a, IA + a)] += par.q_arw * dt + gap_att * gap_att;
            p[(IBG + a, IBG + a)] += par.q_bg * dt;
            p[(IBA + a, IBA + a)] += par.q_ba * dt;
            if par.drift {
                p[(IDG + a, IDG + a)] += par.var_dg * (1.0 - phi_g * phi_g);
                p[(IDA + a, IDA + a)] += par.var_da * (1.0 - phi_a * phi_a);
            }
            if par.vbias {
                p[(IVB + a, IVB + a)] += par.var_vb[a] * (1.0 - phi_b * phi_b);
            }
        }
        self.p = 0.5 * (p + p.transpose());
    }

    /// Generic Joseph-form update with `dz = h(x_est) - z`; returns the NIS or the rejection.
    fn update<const M: usize>(
        &mut self,
        par: &Params,
        dz: SVector<f64, M>,
        h: SMatrix<f64, M, N_STATES>,
        r: SMatrix<f64, M, M>,
        gate: f64,
    ) -> Outcome {
        let ph = self.p * h.transpose();
        let s = h * ph + r;
        let Some(s_inv) = s.try_inverse() else {
            return Outcome::Invalid("singular innovation covariance");
        };
        let nis = dz.dot(&(s_inv * dz));
        if !nis.is_finite() {
            return Outcome::Invalid("non-finite innovation");
        }
        if nis > gate {
            return Outcome::Rejected { nis, gate };
        }
        let k = ph * s_inv;
        let dx: Vecn = k * dz;
        let ikh = Mat::identity() - k * h;
        let p = ikh * self.p * ikh.transpose() + k * r * k.transpose();
        self.p = 0.5 * (p + p.transpose());
        self.feedback(par, &dx);
        Outcome::Accepted { nis }
    }

    /// Closed-loop correction: remove the estimated error `dx` (estimate minus truth).
    fn feedback(&mut self, par: &Params, dx: &Vecn) {
        let st = &mut self.ins.state;
        let (rm, rn) = earth::radii_m(st.lat_rad);
        st.lat_rad -= dx[IP] / (rm + st.h_m);
        st.lon_rad -= dx[IP + 1] / ((rn + st.h_m) * st.lat_rad.cos());
        st.h_m += dx[IP + 2];
        st.v_ned_m_s -= dx.fixed_rows::<3>(IV);
        let psi: Vector3<f64> = dx.fixed_rows::<3>(IA).into();
        st.q_nb = UnitQuaternion::from_scaled_axis(-psi) * st.q_nb;
        st.q_nb.renormalize();
        self.bg -= dx.fixed_rows::<3>(IBG);
        self.ba -= dx.fixed_rows::<3>(IBA);
        if par.scale {
            self.sg -= dx.fixed_rows::<3>(ISG);
            self.sa -= dx.fixed_rows::<3>(ISA);
        }
        if par.drift {
            self.dg -= dx.fixed_rows::<3>(IDG);
            self.da -= dx.fixed_rows::<3>(IDA);
        }
        if par.vbias {
            self.vb -= dx.fixed_rows::<3>(IVB);
        }
    }
}

/// Jacobian of `C_b^n(est) l` with respect to the attitude error `psi` (`C_est = (I + [psi x])
/// C_true`): `d(C l) = [psi x] C l = -[(C l) x] psi`, `l_n = C_est l`.
fn lever_arm_jacobian(l_n: &Vector3<f64>) -> Matrix3<f64> {
    -skew_matrix(l_n)
}

/// The geodetic position `p` moved by `d_ned` metres (first order, fine for metres to a few km).
fn shift_ned(p: (f64, f64, f64), d_ned: &Vector3<f64>) -> (f64, f64, f64) {
    let (rm, rn) = earth::radii_m(p.0);
    (
        p.0 + d_ned.x / (rm + p.2),
        p.1 + d_ned.y / ((rn + p.2) * p.0.cos()),
        p.2 - d_ned.z,
    )
}

/// The factor on the covariance of a measurement whose errors persist for `tau_s` (0: independent
/// samples): `max(1, tau / dt)`, `dt` the time since the last fused one of its kind (none yet:
/// 1), capped at `cap`. Fused at that factor, N samples within `tau` carry the information of one.
fn correlation_factor(tau_s: f64, last_us: Option<u64>, t_c: u64, cap: f64) -> f64 {
    if tau_s <= 0.0 {
        return 1.0;
    }
    let dt = last_us.map_or(f64::INFINITY, |l| dt_s(l, t_c).abs());
    (tau_s / dt.max(1e-3)).clamp(1.0, cap)
}

/// Apply one measurement to `core`, whose epoch time is `core.t_us <= t_c`; the prediction is
/// extrapolated over `t_c - core.t_us`. One file per measurement model (as ArduPilot's EKF3
/// splits its fusion): `fuse_position`, `fuse_velocity`, `fuse_altitude`, `fuse_drag`,
/// `fuse_attitude`, `fuse_vo`.
fn apply(par: &Params, core: &mut Core, m: &Measurement) -> Outcome {
    let dt = dt_s(core.t_us, m.t_capture_us());
    match m {
        Measurement::Vision(_) | Measurement::GpsPosition(_) | Measurement::VisionPose(_) => {
            fuse_position::fuse(par, core, m)
        }
        Measurement::GpsVelocity(f) => fuse_velocity::fuse(par, core, f),
        Measurement::Altitude(f) => fuse_altitude::fuse(par, core, f, dt),
        Measurement::Drag(d) => fuse_drag::fuse(par, core, d),
        Measurement::Attitude(f) => fuse_attitude::fuse(par, core, f),
        Measurement::Vo(f) => fuse_vo::fuse(par, core, f),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lever_arm_jacobian_matches_finite_difference() {
        let q_true = UnitQuaternion::from_euler_angles(0.3, -0.2, 2.0);
        let l = Vector3::new(1.5, -0.8, 0.6);
        for psi in [
            Vector3::new(1e-4, 0.0, 0.0),
            Vector3::new(0.0, -2e-4, 0.0),
            Vector3::new(0.0, 0.0, 3e-4),
            Vector3::new(1e-4, 2e-4, -1e-4),
        ] {
            // Estimate with attitude error psi (estimate minus truth, NED).
            let q_est = UnitQuaternion::from_scaled_axis(psi) * q_true;
            let dz = q_est * l - q_true * l;
            let lin = lever_arm_jacobian(&(q_est * l)) * psi;
            assert!(
                (dz - lin).norm() < 1e-3 * psi.norm() * l.norm(),
                "{dz} {lin}"
            );
        }
    }
}
