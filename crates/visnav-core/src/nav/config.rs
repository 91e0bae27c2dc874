//! Navigation filter configuration (the `[nav]` section of the main configuration).
//!
//! IMU noise and bias parameters are given in datasheet units and converted to SI by the
//! accessor methods (`*_si`). Conversions: angle random walk `deg/sqrt(h)` -> `rad/sqrt(s)`:
//! `x * pi/180 / 60`; velocity random walk `m/s/sqrt(h)` -> `m/s/sqrt(s)`: `x / 60`; bias
//! `deg/h` -> `rad/s`: `x * pi/180 / 3600`; `ug` -> `m/s^2`: `x * 1e-6 * 9.80665`; bias random walk
//! `deg/h/sqrt(h)` -> `rad/s/sqrt(s)`: `x * pi/180 / 3600 / 60`; `ug/sqrt(h)` -> `m/s^2/sqrt(s)`:
//! `x * 9.80665e-6 / 60`.

use crate::validate::{Problems, Validate};
use serde::{Deserialize, Serialize};

/// Standard gravity used for `g` and `ug` units, m/s^2.
pub const G0_M_S2: f64 = 9.806_65;
/// deg/h -> rad/s.
pub const DEG_H_TO_RAD_S: f64 = std::f64::consts::PI / 180.0 / 3600.0;
/// micro-g -> m/s^2.
pub const UG_TO_M_S2: f64 = 1e-6 * G0_M_S2;

/// Default longest IMU gap bridged, s: a link glitch or a stalled stream of seconds; beyond
/// 10 s of unseen manoeuvres the position sigma (about 0.6 sigma_a t^2: 170 m) is a restart's.
pub const DEFAULT_MAX_IMU_BRIDGE_S: f64 = 10.0;
/// Default change of specific force in a bridged gap, m/s^2 (1 sigma): 0.3 g covers a fixed
/// wing's turn entry and a multirotor's braking at 3 sigma.
pub const DEFAULT_BRIDGE_ACCEL_SIGMA_M_S2: f64 = 3.0;
/// Default change of angular rate in a bridged gap, deg/s (1 sigma): a turn started or ended.
pub const DEFAULT_BRIDGE_GYRO_SIGMA_DEG_S: f64 = 5.0;

/// IMU error model in datasheet units (1-sigma values).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ImuNoiseConfig {
    /// Gyro angle random walk, deg/sqrt(h).
    pub gyro_arw_deg_sqrt_h: f64,
    /// Gyro turn-on bias (initial uncertainty, 1 sigma per axis), deg/h.
    pub gyro_bias_deg_h: f64,
    /// Gyro bias instability (first-order Gauss-Markov sigma), deg/h.
    pub gyro_bias_instability_deg_h: f64,
    /// Correlation time of the gyro bias instability, s (the filter uses the short-term random
    /// walk of that Gauss-Markov process, `q = 2 sigma^2 / tau`).
    pub gyro_bias_corr_time_s: f64,
    /// Gyro bias (rate) random walk, deg/h/sqrt(h).
    pub gyro_bias_rw_deg_h_sqrt_h: f64,
    /// Gyro scale-factor uncertainty (1 sigma per axis), ppm (used with 21 states).
    pub gyro_scale_ppm: f64,
    /// Accelerometer velocity random walk, m/s/sqrt(h).
    pub accel_vrw_m_s_sqrt_h: f64,
    /// Accelerometer turn-on bias (initial uncertainty, 1 sigma per axis), micro-g.
    pub accel_bias_ug: f64,
    /// Accelerometer bias instability (first-order Gauss-Markov sigma), micro-g.
    pub accel_bias_instability_ug: f64,
    /// Correlation time of the accelerometer bias instability, s (see the gyro's).
    pub accel_bias_corr_time_s: f64,
    /// Accelerometer bias random walk, micro-g/sqrt(h).
    pub accel_bias_rw_ug_sqrt_h: f64,
    /// Accelerometer scale-factor uncertainty (1 sigma per axis), ppm (used with 21 states).
    pub accel_scale_ppm: f64,
    /// Accelerometer full-scale range (per axis), g. A sample at or beyond it is clipped: the
    /// true value is unknown, so the filter holds the last good sample and adds the range's
    /// uncertainty (`nav::filter`, "Clipped IMU samples"). 16 g is the usual range of the MEMS
    /// IMUs on autopilots (ICM-42688, ICM-20602, BMI088 at its 24 g setting reads more).
    pub accel_range_g: f64,
    /// Gyro full-scale range (per axis), deg/s; see `accel_range_g`. 2000 deg/s is the usual
    /// autopilot setting.
    pub gyro_range_deg_s: f64,
}

impl Default for ImuNoiseConfig {
    /// A tactical-grade MEMS IMU.
    fn default() -> Self {
        Self {
            gyro_arw_deg_sqrt_h: 0.1,
            gyro_bias_deg_h: 10.0,
            gyro_bias_instability_deg_h: 0.5,
            gyro_bias_corr_time_s: 300.0,
            gyro_bias_rw_deg_h_sqrt_h: 0.0,
            gyro_scale_ppm: 300.0,
            accel_vrw_m_s_sqrt_h: 0.03,
            accel_bias_ug: 100.0,
            accel_bias_instability_ug: 10.0,
            accel_bias_corr_time_s: 300.0,
            accel_bias_rw_ug_sqrt_h: 0.0,
            accel_scale_ppm: 300.0,
            accel_range_g: 16.0,
            gyro_range_deg_s: 2000.0,
        }
    }
}

impl ImuNoiseConfig {
    /// Gyro white-noise density, rad/sqrt(s) (= rad/s/sqrt(Hz)).
    pub fn gyro_arw_si(&self) -> f64 {
        self.gyro_arw_deg_sqrt_h.to_radians() / 60.0
    }
    /// Accelerometer white-noise density, m/s/sqrt(s).
    pub fn accel_vrw_si(&self) -> f64 {
        self.accel_vrw_m_s_sqrt_h / 60.0
    }
    /// Gyro turn-on bias sigma, rad/s.
    pub fn gyro_bias_si(&self) -> f64 {
        self.gyro_bias_deg_h * DEG_H_TO_RAD_S
    }
    /// Gyro bias instability sigma, rad/s.
    pub fn gyro_bias_instability_si(&self) -> f64 {
        self.gyro_bias_instability_deg_h * DEG_H_TO_RAD_S
    }
    /// Gyro bias random walk, rad/s/sqrt(s).
    pub fn gyro_bias_rw_si(&self) -> f64 {
        self.gyro_bias_rw_deg_h_sqrt_h * DEG_H_TO_RAD_S / 60.0
    }
    /// Accelerometer turn-on bias sigma, m/s^2.
    pub fn accel_bias_si(&self) -> f64 {
        self.accel_bias_ug * UG_TO_M_S2
    }
    /// Accelerometer bias instability sigma, m/s^2.
    pub fn accel_bias_instability_si(&self) -> f64 {
        self.accel_bias_instability_ug * UG_TO_M_S2
    }
    /// Accelerometer bias random walk, m/s^2/sqrt(s).
    pub fn accel_bias_rw_si(&self) -> f64 {
        self.accel_bias_rw_ug_sqrt_h * UG_TO_M_S2 / 60.0
    }
}

impl Validate for ImuNoiseConfig {
    fn validate(&self, p: &mut Problems) {
        p.positive("gyro_arw_deg_sqrt_h", self.gyro_arw_deg_sqrt_h);
        p.range("gyro_arw_deg_sqrt_h", self.gyro_arw_deg_sqrt_h, 0.0, 100.0);
        p.range("gyro_bias_deg_h", self.gyro_bias_deg_h, 0.0, 36_000.0);
        p.range(
            "gyro_bias_instability_deg_h",
            self.gyro_bias_instability_deg_h,
            0.0,
            36_000.0,
        );
        p.range(
            "gyro_bias_corr_time_s",
            self.gyro_bias_corr_time_s,
            1.0,
            1e7,
        );
        p.range(
            "gyro_bias_rw_deg_h_sqrt_h",
            self.gyro_bias_rw_deg_h_sqrt_h,
            0.0,
            1e4,
        );
        p.range("gyro_scale_ppm", self.gyro_scale_ppm, 0.0, 1e5);
        p.positive("accel_vrw_m_s_sqrt_h", self.accel_vrw_m_s_sqrt_h);
        p.range(
            "accel_vrw_m_s_sqrt_h",
            self.accel_vrw_m_s_sqrt_h,
            0.0,
            1000.0,
        );
        p.range("accel_bias_ug", self.accel_bias_ug, 0.0, 1e6);
        p.range(
            "accel_bias_instability_ug",
            self.accel_bias_instability_ug,
            0.0,
            1e6,
        );
        p.range(
            "accel_bias_corr_time_s",
            self.accel_bias_corr_time_s,
            1.0,
            1e7,
        );
        p.range(
            "accel_bias_rw_ug_sqrt_h",
            self.accel_bias_rw_ug_sqrt_h,
            0.0,
            1e6,
        );
        p.range("accel_scale_ppm", self.accel_scale_ppm, 0.0, 1e5);
        // Below 2 g a level hover's gravity alone would be near the clip.
        p.range("accel_range_g", self.accel_range_g, 2.0, 1000.0);
        p.range("gyro_range_deg_s", self.gyro_range_deg_s, 100.0, 1e5);
    }
}

/// Chi-square innovation gates: the probability mass accepted per measurement type (the
/// threshold is the chi-square quantile of that probability for the measurement's dimension).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GateConfig {
    /// Vision position fixes (3 dof).
    pub vision_prob: f64,
    /// GPS position (3 dof) and velocity (3 dof).
    pub gps_prob: f64,
    /// Barometric / AMSL altitude (1 dof).
    pub altitude_prob: f64,
    /// Autopilot attitude (3 dof).
    pub attitude_prob: f64,
    /// Visual odometry displacements between frames (3 dof).
    pub vo_prob: f64,
}

impl Default for GateConfig {
    fn default() -> Self {
        Self {
            vision_prob: 0.9999,
            gps_prob: 0.9999,
            altitude_prob: 0.9999,
            attitude_prob: 0.9999,
            vo_prob: 0.9999,
        }
    }
}

impl Validate for GateConfig {
    fn validate(&self, p: &mut Problems) {
        for (k, v) in [
            ("vision_prob", self.vision_prob),
            ("gps_prob", self.gps_prob),
            ("altitude_prob", self.altitude_prob),
            ("attitude_prob", self.attitude_prob),
            ("vo_prob", self.vo_prob),
        ] {
            p.range(k, v, 0.5, 0.999_999_9);
        }
    }
}

/// Initial uncertainties not given by the initialising measurements.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct InitConfig {
    /// Roll/pitch uncertainty of the autopilot attitude used for initialisation, deg.
    pub tilt_sigma_deg: f64,
    /// Yaw uncertainty of the autopilot attitude used for initialisation, deg.
    pub yaw_sigma_deg: f64,
    /// Velocity uncertainty added to a velocity derived from two vision fixes, m/s.
    pub vision_vel_sigma_m_s: f64,
    /// Minimum spacing of the two vision fixes that give the initial velocity, s.
    pub vision_init_min_dt_s: f64,
    /// Maximum spacing of the two vision fixes that give the initial velocity, s.
    pub vision_init_max_dt_s: f64,
}

impl Default for InitConfig {
    fn default() -> Self {
        Self {
            tilt_sigma_deg: 1.0,
            yaw_sigma_deg: 3.0,
            vision_vel_sigma_m_s: 2.0,
            vision_init_min_dt_s: 0.5,
            vision_init_max_dt_s: 3.0,
        }
    }
}

impl Validate for InitConfig {
    fn validate(&self, p: &mut Problems) {
        p.positive("tilt_sigma_deg", self.tilt_sigma_deg);
        p.range("tilt_sigma_deg", self.tilt_sigma_deg, 0.0, 45.0);
        p.positive("yaw_sigma_deg", self.yaw_sigma_deg);
        p.range("yaw_sigma_deg", self.yaw_sigma_deg, 0.0, 180.0);
        p.positive("vision_vel_sigma_m_s", self.vision_vel_sigma_m_s);
        p.range(
            "vision_init_min_dt_s",
            self.vision_init_min_dt_s,
            0.05,
            60.0,
        );
        p.range(
            "vision_init_max_dt_s",
            self.vision_init_max_dt_s,
            0.05,
            60.0,
        );
        if self.vision_init_max_dt_s < self.vision_init_min_dt_s {
            p.push(
                "vision_init_max_dt_s",
                format!(
                    "{} must be >= vision_init_min_dt_s ({})",
                    self.vision_init_max_dt_s, self.vision_init_min_dt_s
                ),
            );
        }
    }
}

/// When the multirotor drag law aids the velocity (`[nav.drag] mode`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DragMode {
    /// Learn always; fuse once the GPS is gone when the vehicle is a multirotor (the daemon
    /// tells the filter from the autopilot's HEARTBEAT type).
    Auto,
    /// Learn always; fuse once the GPS is gone whatever the vehicle.
    On,
    /// Neither learn nor fuse.
    Off,
}

/// Multirotor drag aiding (`nav::drag`): the horizontal body velocity from the accelerometer,
/// with the drag law learned while the GPS aids the filter.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DragConfig {
    /// Auto (default): multirotors only; on; off.
    pub mode: DragMode,
    /// How far the wind may have changed since the law was learned, m/s (1 sigma): the wind is
    /// not estimated, so this enters each measurement's noise.
    pub wind_sigma_m_s: f64,
    /// Fuse once no GPS velocity has been accepted for this long, s.
    pub after_gps_s: f64,
}

impl Default for DragConfig {
    fn default() -> Self {
        Self {
            mode: DragMode::Auto,
            wind_sigma_m_s: 1.0,
            after_gps_s: 2.0,
        }
    }
}

impl Validate for DragConfig {
    fn validate(&self, p: &mut Problems) {
        p.range("wind_sigma_m_s", self.wind_sigma_m_s, 0.0, 50.0);
        p.range("after_gps_s", self.after_gps_s, 0.0, 600.0);
    }
}

/// Health thresholds, divergence detection and reset.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct HealthConfig {
    /// Horizontal position sigma above which health is `degraded`, m.
    pub degraded_pos_sigma_m: f64,
    /// Horizontal position sigma above which health is `lost`, m.
    pub lost_pos_sigma_m: f64,
    /// Time without an accepted position fix after which health is `degraded`, s.
    pub degraded_no_fix_s: f64,
    /// Time without an accepted position fix after which health is `lost`, s.
    pub lost_no_fix_s: f64,
    /// Consecutive gate rejections of position fixes that declare divergence and reset the
    /// position/velocity onto the next fix.
    pub divergence_reject_count: u32,
    /// Velocity sigma after a divergence reset, m/s (at least; the reset takes the velocity
    /// error from the rejected fixes' drift, with that fit's uncertainty).
    pub reset_vel_sigma_m_s: f64,
    /// Rejected position fixes that stepped away from the filter (further than its error could
    /// have grown since the last accepted fix, and with no contradicted velocity: a jumping or
    /// spoofed receiver, a wrong relocalisation) are reset onto only after they have been
    /// rejected this long, s (`nav::divergence`, "Steps").
    pub step_reset_s: f64,
    /// Health stays at least `degraded` this long after a reset, s.
    pub reset_degraded_s: f64,
}

impl Default for HealthConfig {
    fn default() -> Self {
        Self {
            degraded_pos_sigma_m: 15.0,
            lost_pos_sigma_m: 100.0,
            degraded_no_fix_s: 10.0,
            lost_no_fix_s: 120.0,
            divergence_reject_count: 5,
            reset_vel_sigma_m_s: 5.0,
            step_reset_s: 10.0,
            reset_degraded_s: 10.0,
        }
    }
}

impl Validate for HealthConfig {
    fn validate(&self, p: &mut Problems) {
        p.positive("degraded_pos_sigma_m", self.degraded_pos_sigma_m);
        p.positive("lost_pos_sigma_m", self.lost_pos_sigma_m);
        if self.lost_pos_sigma_m < self.degraded_pos_sigma_m {
            p.push(
                "lost_pos_sigma_m",
                format!(
                    "{} must be >= degraded_pos_sigma_m ({})",
                    self.lost_pos_sigma_m, self.degraded_pos_sigma_m
                ),
            );
        }
        p.positive("degraded_no_fix_s", self.degraded_no_fix_s);
        p.positive("lost_no_fix_s", self.lost_no_fix_s);
        if self.lost_no_fix_s < self.degraded_no_fix_s {
            p.push(
                "lost_no_fix_s",
                format!(
                    "{} must be >= degraded_no_fix_s ({})",
                    self.lost_no_fix_s, self.degraded_no_fix_s
                ),
            );
        }
        if self.divergence_reject_count == 0 || self.divergence_reject_count > 1000 {
            p.push(
                "divergence_reject_count",
                format!("{} is outside [1, 1000]", self.divergence_reject_count),
            );
        }
        p.positive("reset_vel_sigma_m_s", self.reset_vel_sigma_m_s);
        p.range("step_reset_s", self.step_reset_s, 0.0, 3600.0);
        p.range("reset_degraded_s", self.reset_degraded_s, 0.0, 3600.0);
    }
}

/// The `[nav]` section.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct NavConfig {
    /// Estimate gyro and accelerometer scale factors (6 more states).
    pub scale_factor_states: bool,
    /// Carry the bias instability as its own first-order Gauss-Markov states (6 more states:
    /// gyro and accelerometer drift, sigma `*_bias_instability_*`, correlation time
    /// `*_bias_corr_time_s`) beside the constant turn-on bias states. False: one bias state per
    /// axis, a random constant driven by the short-term random walk `q = 2 sigma^2 / tau` of the
    /// instability (conservative).
    pub bias_drift_states: bool,
    /// Output (position/velocity/attitude/covariance) rate, Hz.
    pub output_rate_hz: f64,
    /// Length of the state/covariance history used to apply late measurements at their capture
    /// time, s. Older measurements are rejected as `too_old`.
    pub history_s: f64,
    /// Use the autopilot attitude as a measurement (it is always used for initialisation). By
    /// default only its heading is fused (see `autopilot_attitude_tilt`).
    pub use_autopilot_attitude: bool,
    /// Also fuse the autopilot's roll and pitch. Off by default: while visnav feeds the
    /// autopilot, the autopilot's tilt follows visnav's own errors (its EKF fits its attitude to
    /// the injected velocity), so fusing it closes a loop: in ArduCopter SITL with the GPS off
    /// both tilts drifted 1.4 deg together and the filter reported a 6 m sigma at 85 m of error
    /// (docs/real-sitl.md, run 7). The heading comes from the compass and stays independent.
    pub autopilot_attitude_tilt: bool,
    /// Correlation time of the autopilot attitude's errors, s (0 = independent samples). An
    /// AHRS's error persists for seconds to minutes; ATTITUDE arrives at 10-50 Hz. Each
    /// sample's covariance is multiplied by `max(1, tau / dt)`, `dt` the time since the last
    /// fused attitude, like `vision_error_corr_time_s`.
    pub attitude_error_corr_time_s: f64,
    /// Autopilot attitude measurement noise, roll/pitch, deg (1 sigma).
    pub attitude_sigma_tilt_deg: f64,
    /// Autopilot attitude measurement noise, yaw, deg (1 sigma).
    pub attitude_sigma_yaw_deg: f64,
    /// Largest gap between IMU samples propagated as one step, s. Longer gaps up to
    /// `max_imu_bridge_s` are bridged (the filter's module doc, "IMU gaps"); longer ones reset
    /// the filter.
    pub max_imu_gap_s: f64,
    /// Longest IMU gap bridged (a silent link, a stalled stream), s; 0 = never bridge.
    pub max_imu_bridge_s: f64,
    /// What the vehicle's specific force can change by, unseen, during a bridged gap
    /// (1 sigma, m/s^2): its manoeuvres, not the sensor's range.
    pub imu_bridge_accel_sigma_m_s2: f64,
    /// The same for its angular rate, deg/s (1 sigma).
    pub imu_bridge_gyro_sigma_deg_s: f64,
    /// Correlation time of the vision fixes' errors, s (0 = independent fixes). Consecutive
    /// frames see the same ground against the same map, so their errors (changed ground between
    /// the map's and the camera's year, a weak geometry) persist for seconds; fused as if
    /// independent, N fixes within that time would shrink the covariance N-fold although the
    /// error stays. Each fix's covariance is multiplied by `max(1, tau / dt)`, `dt` the time
    /// since the last applied vision fix (the information of one independent fix per `tau`).
    pub vision_error_corr_time_s: f64,
    /// Fuse each vision fix as a full pose: the image-only position and attitude with their 6x6
    /// covariance (`fix::VisionOnlyPose`), instead of the position alone. The position of a fix
    /// is computed with the filter's attitude as a prior, so over flat ground (position and tilt
    /// correlated above 0.99) it carries the filter's own tilt error back into the filter as if
    /// confirmed; the joint pose does not, and it makes the tilt and heading observable at every
    /// fix (what a noisy gyro needs). Fixes whose report has no image-only pose are fused as
    /// positions.
    pub vision_attitude: bool,
    /// Fuse a position fix (not a pose) with its dependence on the attitude prior it was solved
    /// with, when that prior was this filter's own attitude (`fix::PriorDependenceNed`): the
    /// measurement Jacobian gets `-D` in its attitude columns and the covariance is the image's
    /// part alone, so the filter's attitude is not fused a second time through the position.
    /// Off by default: in the closed-loop demo it has not yet shown a gain over the plain
    /// position (docs/fix.md, "The attitude prior").
    pub vision_prior_dependence: bool,
    /// Vision position bias states (3 more error states, NED): the part of the fixes' error that
    /// the ground shares over a distance, chiefly the reference map's registration against the
    /// true ground (a few metres for NAIP, up to ~10 m for Sentinel-2) and the changed ground
    /// between the map's and the camera's year. Modelled as a first-order Gauss-Markov process
    /// in distance flown, `b(s + ds) = e^{-ds/L} b(s) + w`, stationary sigma `sigma_h` per
    /// horizontal axis and `sigma_v` down, `L = vision_bias_corr_dist_m`; a fix is
    /// `z = p_cam + b + e`. With GPS on, fixes calibrate `b` and it is carried into the outage;
    /// without GPS the position covariance never shrinks below `b`'s, so the filter stays
    /// honest after long vision-only flight. Horizontal sigma, m; 0 (default) = no bias states.
    pub vision_bias_sigma_h_m: f64,
    /// Vision position bias: vertical sigma, m (with `vision_bias_sigma_h_m` > 0).
    pub vision_bias_sigma_v_m: f64,
    /// Vision position bias: correlation distance `L`, m (the decay per metre flown
    /// horizontally; a hovering vehicle keeps its bias).
    pub vision_bias_corr_dist_m: f64,
    /// Camera projection centre in the body frame (FRD, metres from the IMU, the point the
    /// filter's position refers to): vision fixes are positions of this point. Not set: the
    /// caller fills it from `[camera.mount] lever_arm_body_frd_m`
    /// ([`NavConfig::with_camera_lever_arm`]); the filter treats "not set" as zero.
    pub camera_lever_arm_body_frd_m: Option<[f64; 3]>,
    /// GPS antenna phase centre in the body frame (FRD, metres from the IMU).
    pub gps_lever_arm_body_frd_m: [f64; 3],
    /// IMU error model.
    pub imu: ImuNoiseConfig,
    /// Innovation gates.
    pub gates: GateConfig,
    /// Initialisation.
    pub init: InitConfig,
    /// Health and divergence handling.
    pub health: HealthConfig,
    /// Multirotor drag aiding.
    pub drag: DragConfig,
}

impl Default for NavConfig {
    fn default() -> Self {
        Self {
            scale_factor_states: false,
            bias_drift_states: true,
            output_rate_hz: 50.0,
            history_s: 1.0,
            use_autopilot_attitude: false,
            autopilot_attitude_tilt: false,
            attitude_error_corr_time_s: 1.0,
            attitude_sigma_tilt_deg: 1.0,
            attitude_sigma_yaw_deg: 3.0,
            max_imu_gap_s: 0.1,
            max_imu_bridge_s: DEFAULT_MAX_IMU_BRIDGE_S,
            imu_bridge_accel_sigma_m_s2: DEFAULT_BRIDGE_ACCEL_SIGMA_M_S2,
            imu_bridge_gyro_sigma_deg_s: DEFAULT_BRIDGE_GYRO_SIGMA_DEG_S,
            vision_error_corr_time_s: 0.0,
            vision_attitude: false,
            vision_prior_dependence: false,
            vision_bias_sigma_h_m: 0.0,
            vision_bias_sigma_v_m: 0.0,
            vision_bias_corr_dist_m: 2000.0,
            camera_lever_arm_body_frd_m: None,
            gps_lever_arm_body_frd_m: [0.0; 3],
            imu: ImuNoiseConfig::default(),
            gates: GateConfig::default(),
            init: InitConfig::default(),
            health: HealthConfig::default(),
            drag: DragConfig::default(),
        }
    }
}

impl NavConfig {
    /// This configuration with the camera lever arm taken from the camera mount when `[nav]`
    /// does not give one.
    pub fn with_camera_lever_arm(mut self, mount_lever_arm_body_frd_m: [f64; 3]) -> Self {
        if self.camera_lever_arm_body_frd_m.is_none() {
            self.camera_lever_arm_body_frd_m = Some(mount_lever_arm_body_frd_m);
        }
        self
    }

    /// Camera lever arm in use (zero when not set).
    pub fn camera_lever_arm(&self) -> [f64; 3] {
        self.camera_lever_arm_body_frd_m.unwrap_or([0.0; 3])
    }

    /// Number of error states: 15, plus 6 with scale factors, plus 6 with bias drift states,
    /// plus 3 with vision position bias states.
    pub fn n_states(&self) -> usize {
        15 + 6 * usize::from(self.scale_factor_states)
            + 6 * usize::from(self.bias_drift_states)
            + 3 * usize::from(self.vision_bias_states())
    }

    /// Whether the vision position bias states are estimated (`vision_bias_sigma_h_m` > 0).
    pub fn vision_bias_states(&self) -> bool {
        self.vision_bias_sigma_h_m > 0.0
    }
}

impl Validate for NavConfig {
    fn validate(&self, p: &mut Problems) {
        p.range("output_rate_hz", self.output_rate_hz, 0.1, 1000.0);
        p.range("history_s", self.history_s, 0.0, 10.0);
        p.positive("attitude_sigma_tilt_deg", self.attitude_sigma_tilt_deg);
        p.range(
            "attitude_sigma_tilt_deg",
            self.attitude_sigma_tilt_deg,
            0.0,
            45.0,
        );
        p.positive("attitude_sigma_yaw_deg", self.attitude_sigma_yaw_deg);
        p.range(
            "attitude_sigma_yaw_deg",
            self.attitude_sigma_yaw_deg,
            0.0,
            180.0,
        );
        p.range("max_imu_gap_s", self.max_imu_gap_s, 0.001, 10.0);
        p.range("max_imu_bridge_s", self.max_imu_bridge_s, 0.0, 60.0);
        p.range(
            "imu_bridge_accel_sigma_m_s2",
            self.imu_bridge_accel_sigma_m_s2,
            0.01,
            100.0,
        );
        p.range(
            "imu_bridge_gyro_sigma_deg_s",
            self.imu_bridge_gyro_sigma_deg_s,
            0.01,
            500.0,
        );
        p.range(
            "vision_bias_sigma_h_m",
            self.vision_bias_sigma_h_m,
            0.0,
            1000.0,
        );
        p.range(
            "vision_bias_sigma_v_m",
            self.vision_bias_sigma_v_m,
            0.0,
            1000.0,
        );
        p.range(
            "vision_bias_corr_dist_m",
            self.vision_bias_corr_dist_m,
            1.0,
            1e7,
        );
        p.range(
            "vision_error_corr_time_s",
            self.vision_error_corr_time_s,
            0.0,
            600.0,
        );
        for v in self.camera_lever_arm_body_frd_m.unwrap_or([0.0; 3]) {
            p.range("camera_lever_arm_body_frd_m", v, -100.0, 100.0);
        }
        for v in self.gps_lever_arm_body_frd_m {
            p.range("gps_lever_arm_body_frd_m", v, -100.0, 100.0);
        }
        p.section("imu", |p| self.imu.validate(p));
        p.section("gates", |p| self.gates.validate(p));
        p.section("init", |p| self.init.validate(p));
        p.section("health", |p| self.health.validate(p));
        p.section("drag", |p| self.drag.validate(p));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_is_valid_and_round_trips() {
        let c = NavConfig::default();
        let mut p = Problems::default();
        c.validate(&mut p);
        assert!(p.list.is_empty(), "{:?}", p.list);
        let text = toml::to_string(&c).expect("serialise");
        let back: NavConfig = toml::from_str(&text).expect("parse");
        assert_eq!(back, c);
    }

    #[test]
    fn unknown_key_and_bad_value_are_named() {
        let e = toml::from_str::<NavConfig>("[imu]\ngyro_arw_deg_per_h = 1.0\n");
        assert!(e.is_err());
        assert!(format!("{:?}", e).contains("gyro_arw_deg_per_h"));
        let c: NavConfig =
            toml::from_str("output_rate_hz = -1\n[imu]\ngyro_arw_deg_sqrt_h = nan\n")
                .expect("parse");
        let mut p = Problems::default();
        p.section("nav", |p| c.validate(p));
        let keys: Vec<_> = p.list.iter().map(|i| i.key.as_str()).collect();
        assert!(keys.contains(&"nav.output_rate_hz"), "{keys:?}");
        assert!(keys.contains(&"nav.imu.gyro_arw_deg_sqrt_h"), "{keys:?}");
    }

    #[test]
    fn unit_conversions() {
        let c = ImuNoiseConfig {
            gyro_arw_deg_sqrt_h: 60.0,
            gyro_bias_deg_h: 3600.0,
            accel_bias_ug: 1e6,
            accel_vrw_m_s_sqrt_h: 60.0,
            ..Default::default()
        };
        assert!((c.gyro_arw_si() - 1f64.to_radians()).abs() < 1e-15);
        assert!((c.gyro_bias_si() - 1f64.to_radians()).abs() < 1e-15);
        assert!((c.accel_bias_si() - G0_M_S2).abs() < 1e-12);
        assert!((c.accel_vrw_si() - 1.0).abs() < 1e-15);
    }
}
