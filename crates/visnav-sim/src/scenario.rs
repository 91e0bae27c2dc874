//! Scenario files (`sitl/scenarios/*.toml`): trajectory, simulated sensors, evaluation window and
//! the `[nav]` filter configuration. Parsed with `deny_unknown_fields` and validated; every error
//! names the file and the dotted key.

use serde::{Deserialize, Serialize};
use std::path::Path;
use visnav_core::nav::NavConfig;
use visnav_core::nav::synth::imu::SimImuConfig;
use visnav_core::nav::synth::trajectory::{Segment, Trajectory};
use visnav_core::validate::{Problems, Validate};

/// Scenario loading errors.
#[derive(Debug, thiserror::Error)]
pub enum ScenarioError {
    /// File unreadable.
    #[error("{file}: cannot read: {err}")]
    Read {
        /// File.
        file: String,
        /// Cause.
        err: std::io::Error,
    },
    /// TOML syntax or schema error (names the key).
    #[error("{file}: {message}")]
    Parse {
        /// File.
        file: String,
        /// Parser message.
        message: String,
    },
    /// Values out of range.
    #[error("{file}: invalid values: {}", .problems.join("; "))]
    Invalid {
        /// File.
        file: String,
        /// `key: reason` for every problem.
        problems: Vec<String>,
    },
}

/// Start of the trajectory.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StartConfig {
    /// Latitude, deg.
    pub lat_deg: f64,
    /// Longitude, deg.
    pub lon_deg: f64,
    /// Height above the WGS84 ellipsoid, m.
    pub height_m: f64,
    /// Ground speed, m/s.
    pub speed_m_s: f64,
    /// Heading, deg (0 = north, 90 = east).
    pub heading_deg: f64,
}

/// Segment kind.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SegmentKind {
    /// Constant heading and height.
    Straight,
    /// Coordinated turn (may also climb).
    Turn,
    /// Straight climb or descent.
    Climb,
}

/// One `[[segments]]` entry.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SegmentConfig {
    /// Kind.
    pub kind: SegmentKind,
    /// Duration, s.
    pub duration_s: f64,
    /// Turn rate, deg/s (turn only; positive = right).
    #[serde(default)]
    pub turn_rate_deg_s: f64,
    /// Climb rate, m/s (climb or turn; negative = descent).
    #[serde(default)]
    pub climb_rate_m_s: f64,
    /// New speed, m/s (default: keep).
    #[serde(default)]
    pub speed_m_s: Option<f64>,
    /// Transition time, s.
    #[serde(default = "default_ramp")]
    pub ramp_s: f64,
}

fn default_ramp() -> f64 {
    3.0
}

/// Vehicle kind (`[vehicle] kind`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum VehicleKind {
    /// Fixed-wing kinematics: pitch = flight-path angle, coordinated turns.
    #[default]
    FixedWing,
    /// Multirotor: tilted by its acceleration and its drag, the thrust along body -z
    /// (`visnav_core::nav::synth::trajectory` module doc).
    Multirotor,
}

/// `[vehicle]`: how the aircraft holds its attitude along the trajectory.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VehicleConfig {
    /// `fixed_wing` (default) or `multirotor`.
    #[serde(default)]
    pub kind: VehicleKind,
    /// Multirotor drag law `D(v) = a v + b v |v|` per body axis (specific force): `a`, 1/s
    /// (negative; ArduCopter SITL: -0.215) ...
    #[serde(default)]
    pub drag_linear_per_s: Option<f64>,
    /// ... and `b`, 1/m (negative; ArduCopter SITL: -0.028).
    #[serde(default)]
    pub drag_quadratic_per_m: Option<f64>,
}

/// The largest tilt a multirotor scenario may ask for, deg.
pub const MULTIROTOR_MAX_TILT_DEG: f64 = 60.0;

/// Simulated GPS (white noise, no latency).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GpsConfig {
    /// Rate, Hz.
    pub rate_hz: f64,
    /// Available from this time, s.
    #[serde(default)]
    pub from_s: f64,
    /// Available until this time (the outage starts here), s.
    pub until_s: f64,
    /// Horizontal position sigma per axis, m.
    pub sigma_h_m: f64,
    /// Vertical position sigma, m.
    pub sigma_v_m: f64,
    /// Velocity sigma per axis, m/s.
    pub sigma_vel_m_s: f64,
    /// True antenna position in the body frame (FRD, m from the IMU); the filter's is
    /// `[nav] gps_lever_arm_body_frd_m`.
    #[serde(default)]
    pub lever_arm_body_frd_m: [f64; 3],
    /// More outage windows `[[from_s, until_s], ...]` inside `from_s..until_s` (e.g. jamming
    /// bursts), s.
    #[serde(default)]
    pub outages_s: Vec<[f64; 2]>,
    /// Receiver latency, s (closed loop): the autopilot emulator's GPS_RAW_INT / GPS2_RAW stamped
    /// at `t` report the state at `t - latency_s`, as a real receiver's fix arrives 0.1-0.2 s
    /// after its epoch. The daemon's `[daemon] gps_delay_s` (default 0.1 s) undoes it; a mismatch
    /// offsets the GPS-aided position along the track by speed x mismatch (5 m at 51 m/s and
    /// 0.1 s). The filter-only `visnav sim` applies GPS at its true epoch and ignores this key.
    #[serde(default = "default_gps_latency_s")]
    pub latency_s: f64,
}

/// The simulated receiver's latency: 0.1 s, the daemon's default `gps_delay_s`.
fn default_gps_latency_s() -> f64 {
    0.1
}

impl GpsConfig {
    /// Whether the receiver has a fix at `t_s`: inside `from_s..until_s` and outside every
    /// `outages_s` window.
    pub fn available(&self, t_s: f64) -> bool {
        t_s >= self.from_s
            && t_s < self.until_s
            && !self.outages_s.iter().any(|w| t_s >= w[0] && t_s < w[1])
    }
}

/// Frame of the simulated vision noise.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum VisionNoiseFrame {
    /// `sigma_h_m` across the camera's line of sight (boresight `+z` of the body frame, i.e. a
    /// nadir camera), `sigma_v_m` along it, rotated with the true attitude: at nadir
    /// `diag(sigma_h^2, sigma_h^2, sigma_v^2)`, banked or pitched the horizontal and vertical
    /// errors are correlated.
    #[default]
    LineOfSight,
    /// `diag(sigma_h^2, sigma_h^2, sigma_v^2)` in NED whatever the attitude.
    Ned,
}

/// Simulated vision fixes: truth plus white noise, delivered late.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VisionConfig {
    /// Rate, Hz.
    pub rate_hz: f64,
    /// First capture time, s.
    pub from_s: f64,
    /// Last capture time, s.
    pub until_s: f64,
    /// Horizontal sigma per axis (used for the noise and the reported covariance), m.
    pub sigma_h_m: f64,
    /// Vertical sigma, m.
    pub sigma_v_m: f64,
    /// Delivery latency after capture, uniform in [min, max], ms.
    pub latency_min_ms: f64,
    /// See `latency_min_ms`.
    pub latency_max_ms: f64,
    /// Probability that a fix is an outlier (wrong match).
    #[serde(default)]
    pub outlier_prob: f64,
    /// Horizontal offset of an outlier, m.
    #[serde(default = "default_outlier")]
    pub outlier_m: f64,
    /// Frame of the noise model (default: line of sight).
    #[serde(default)]
    pub noise_frame: VisionNoiseFrame,
    /// True camera projection centre in the body frame (FRD, m from the IMU): the fixes are
    /// positions of this point; the filter's is `[nav] camera_lever_arm_body_frd_m`.
    #[serde(default)]
    pub lever_arm_body_frd_m: [f64; 3],
}

fn default_outlier() -> f64 {
    50.0
}

/// Simulated altitude (white noise plus a constant bias).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AltitudeConfig {
    /// Rate, Hz.
    pub rate_hz: f64,
    /// Sigma, m.
    pub sigma_m: f64,
    /// Constant bias of the simulated sensor (not known to the filter), m.
    #[serde(default)]
    pub bias_m: f64,
}

/// Simulated autopilot attitude (truth plus white noise).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AttitudeConfig {
    /// Rate, Hz.
    pub rate_hz: f64,
    /// Roll/pitch noise sigma, deg.
    pub sigma_tilt_deg: f64,
    /// Yaw noise sigma, deg.
    pub sigma_yaw_deg: f64,
}

/// Evaluation window and consistency sampling.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EvaluationConfig {
    /// Window start, s.
    pub from_s: f64,
    /// Window end, s.
    pub until_s: f64,
    /// Interval of the NEES samples, s.
    #[serde(default = "default_nees_interval")]
    pub nees_interval_s: f64,
    /// Maximum horizontal error target for the vision run, m (reported as pass/fail).
    #[serde(default)]
    pub target_max_horiz_err_m: Option<f64>,
}

fn default_nees_interval() -> f64 {
    1.0
}

/// Reference numbers (e.g. the seed paper's) printed beside the results.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReferenceConfig {
    /// Where the numbers come from.
    pub source: String,
    /// INS-only max error `[e, n, u]`, m.
    pub ins_only_max_err_enu_m: [f64; 3],
    /// With-vision max error `[e, n, u]`, m.
    pub vision_max_err_enu_m: [f64; 3],
}

fn default_camera_rate() -> f64 {
    2.0
}

fn default_true() -> bool {
    true
}

fn default_max_age() -> f64 {
    1.0
}

/// `[closed_loop]`: run the scenario in the closed loop (`visnav sim`): the autopilot emulator and
/// the visnav daemon over real loopback MAVLink, the camera rendered at the true pose. Paths are
/// relative to the scenario file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ClosedLoopConfig {
    /// The visnav configuration the daemon runs with (`[camera]`, `[map]`, `[fix]`, `[output]`,
    /// `[daemon]`, `[link] streams`); its `[link] connection` is replaced by a free loopback port
    /// and its `[nav]` by the scenario's (which matches the simulated IMU).
    pub config: std::path::PathBuf,
    /// The map-year orthophoto(s): when given, they replace the configuration's `[map] ortho`
    /// (same height source), so a scenario states its map year beside its camera year.
    #[serde(default)]
    pub map_ortho: Vec<std::path::PathBuf>,
    /// Replaces the configuration's `[map] upsample` (1, 2 or 4: the finest level's features at
    /// that many times the orthophotos' resolution), so a low flight over a coarse map says so
    /// beside its map year.
    #[serde(default)]
    pub map_upsample: Option<usize>,
    /// The camera-year orthophoto the frames are rendered from. Must not be a map orthophoto
    /// (the matcher would see its own image).
    pub camera_ortho: std::path::PathBuf,
    /// DEM under the camera-year orthophoto (heights AMSL), or
    #[serde(default)]
    pub camera_dem: Option<std::path::PathBuf>,
    /// a flat ground at this height AMSL, m.
    #[serde(default)]
    pub camera_ground_height_amsl_m: Option<f64>,
    /// Camera frame rate, Hz.
    #[serde(default = "default_camera_rate")]
    pub camera_rate_hz: f64,
    /// First camera frame at this time, s (before it the camera is off).
    #[serde(default)]
    pub camera_from_s: f64,
    /// Frames older than this when a fix worker is free are dropped, s.
    #[serde(default = "default_max_age")]
    pub frame_max_age_s: f64,
    /// Fix worker threads.
    #[serde(default = "default_workers")]
    pub workers: usize,
    /// Also run the no-vision control (same truth and sensors, no camera).
    #[serde(default = "default_true")]
    pub control: bool,
    /// The autopilot's attitude estimate (ATTITUDE) errs from the truth by a first-order
    /// Gauss-Markov process per axis (an AHRS's slowly wandering tilt and heading errors, not
    /// white noise): roll/pitch sigma, deg ...
    #[serde(default = "default_ahrs_tilt")]
    pub ahrs_tilt_sigma_deg: f64,
    /// ... heading sigma, deg ...
    #[serde(default = "default_ahrs_yaw")]
    pub ahrs_yaw_sigma_deg: f64,
    /// ... and correlation time, s.
    #[serde(default = "default_ahrs_tau")]
    pub ahrs_corr_time_s: f64,
    /// ATTITUDE's body rates (the daemon's gyro, `[daemon] gyro_from_attitude`) err from the
    /// simulated gyro by a first-order Gauss-Markov process per axis, as ArduPilot's do: they are
    /// its gyro minus EKF3's bias estimate, whose residual wanders by tens of deg/h (about
    /// 60 deg/h in ArduCopter SITL, docs/real-sitl.md; here the whole flight, with or without
    /// GPS). Sigma, deg/h; 0 (default): ATTITUDE carries the simulated gyro itself ...
    #[serde(default)]
    pub ahrs_rate_error_deg_h: f64,
    /// ... and its correlation time, s.
    #[serde(default = "default_ahrs_rate_tau")]
    pub ahrs_rate_corr_time_s: f64,
    /// The emulator's GPS_RAW_INT / GPS2_RAW carry the receiver's ground speed and course (`vel`,
    /// `cog`, with `[gps] sigma_vel_m_s` of noise per axis), as ArduPilot sends them; the daemon
    /// then fuses a GPS velocity (and learns a multirotor's drag law from it, `[nav.drag]`).
    /// Default false: both fields unknown, as the emulator sent them before (the existing
    /// scenarios keep their results).
    #[serde(default)]
    pub gps_velocity: bool,
    /// Light, blur and noise of the simulated camera (`sitl::render::RenderSpec`).
    #[serde(default)]
    pub render: super::render::RenderSpec,
    /// The map's copy of its orthophoto(s) (`sitl::render::degrade`): for an area imaged on one
    /// date only, the map is built from a copy degraded so (written to a temporary GeoTIFF) and
    /// the camera renders another (`camera_degrade`), so no frame is matched against the image it
    /// was rendered from. With both, `camera_ortho` may be a map orthophoto.
    #[serde(default)]
    pub map_degrade: Option<super::render::degrade::DegradeSpec>,
    /// The camera's copy of `camera_ortho`, degraded so before rendering (the camera's own
    /// exposure, blur and noise come on top, `render`).
    #[serde(default)]
    pub camera_degrade: Option<super::render::degrade::DegradeSpec>,
    /// Lock-step (default): the emulators, the daemons and the camera share the runtime's clock,
    /// paused and advanced by the runtime when every task waits. The scenario then runs as fast
    /// as the CPU allows and the same for the same seed; a fix takes no simulated time to compute
    /// and its result arrives `lockstep_fix_latency_s` after the capture. False (or
    /// `visnav sim --realtime`): real time, the fix's own computing time as its latency.
    #[serde(default = "default_true")]
    pub lockstep: bool,
    /// Capture-to-result latency of a fix in lock-step, s (what the real-time runs measure:
    /// docs/closed-loop.md).
    #[serde(default = "default_lockstep_latency")]
    pub lockstep_fix_latency_s: f64,
    /// Replaces the configuration's `[vo]` (visual odometry between fixes) for the vision run.
    #[serde(default)]
    pub vo: Option<visnav_core::vo::VoConfig>,
    /// `[cols, rows]`: the camera's orthophoto and the map's repeated into a mosaic of that many
    /// copies east and south of their place, every other copy mirrored so that neighbours meet
    /// edge to edge (a large area for paging, memory and tile-seam tests out of one real tile:
    /// the same ground again, said so in the report). The map's copies are written to a
    /// temporary GeoTIFF for its build.
    #[serde(default)]
    pub mosaic: Option<[usize; 2]>,
    /// Build the map as a tiled map of squares of this side (metres; `visnav map build
    /// --tile-m`) into a temporary folder and fly it paged within the configuration's `[map]
    /// memory_mb` (loaded inline in lock-step, so a seed's run is the same on any machine).
    #[serde(default)]
    pub map_tile_m: Option<f64>,
}

/// Most copies of a mosaic along one axis (`[closed_loop] mosaic`).
pub const MAX_MOSAIC_COPIES: usize = 64;

fn default_lockstep_latency() -> f64 {
    0.15
}

fn default_ahrs_tilt() -> f64 {
    0.3
}

fn default_ahrs_yaw() -> f64 {
    1.5
}

fn default_ahrs_tau() -> f64 {
    60.0
}

fn default_ahrs_rate_tau() -> f64 {
    60.0
}

fn default_workers() -> usize {
    1
}

/// A whole scenario file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scenario {
    /// Name.
    pub name: String,
    /// Free text.
    #[serde(default)]
    pub description: String,
    /// Random seed of run 0 (Monte Carlo run i uses seed + i).
    #[serde(default)]
    pub seed: u64,
    /// Start point.
    pub start: StartConfig,
    /// Vehicle kind and, for a multirotor, its drag law (default: fixed wing).
    #[serde(default)]
    pub vehicle: VehicleConfig,
    /// Trajectory segments.
    pub segments: Vec<SegmentConfig>,
    /// Simulated IMU.
    pub imu: SimImuConfig,
    /// Simulated GPS.
    #[serde(default)]
    pub gps: Option<GpsConfig>,
    /// Simulated vision fixes.
    #[serde(default)]
    pub vision: Option<VisionConfig>,
    /// Simulated altitude.
    #[serde(default)]
    pub altitude: Option<AltitudeConfig>,
    /// Simulated autopilot attitude (needed for initialisation).
    pub attitude: AttitudeConfig,
    /// Evaluation.
    pub evaluation: EvaluationConfig,
    /// Reference numbers.
    #[serde(default)]
    pub reference: Option<ReferenceConfig>,
    /// Filter configuration.
    #[serde(default)]
    pub nav: NavConfig,
    /// Closed-loop settings (`visnav sim` runs the closed loop when present).
    #[serde(default)]
    pub closed_loop: Option<ClosedLoopConfig>,
    /// Scripted fault events of the closed loop (`sitl::faults`).
    #[serde(default)]
    pub faults: Vec<crate::faults::FaultConfig>,
}

impl Scenario {
    /// Read, parse and validate a scenario file.
    pub fn load(path: &Path) -> Result<Self, ScenarioError> {
        let file = path.display().to_string();
        let text = visnav_io::files::read_text(path, visnav_io::files::CONFIG).map_err(|err| {
            ScenarioError::Read {
                file: file.clone(),
                err,
            }
        })?;
        Self::parse(&text, &file)
    }

    /// Parse and validate scenario text; `file` is used in messages.
    pub fn parse(text: &str, file: &str) -> Result<Self, ScenarioError> {
        let sc: Scenario = toml::from_str(text).map_err(|e| ScenarioError::Parse {
            file: file.to_string(),
            message: e.to_string(),
        })?;
        let mut p = Problems::default();
        sc.validate(&mut p);
        if !p.list.is_empty() {
            return Err(ScenarioError::Invalid {
                file: file.to_string(),
                problems: p.list.iter().map(|i| i.to_string()).collect(),
            });
        }
        Ok(sc)
    }

    /// Build the trajectory.
    pub fn trajectory(&self) -> Trajectory {
        let mut speed = self.start.speed_m_s;
        let segs = self
            .segments
            .iter()
            .map(|s| {
                if let Some(v) = s.speed_m_s {
                    speed = v;
                }
                Segment {
                    duration_s: s.duration_s,
                    speed_m_s: speed,
                    turn_rate_rad_s: s.turn_rate_deg_s.to_radians(),
                    // A hovering multirotor (speed 0) cannot climb (validated): level.
                    path_angle_rad: if speed > 0.0 {
                        (s.climb_rate_m_s / speed).clamp(-1.0, 1.0).asin()
                    } else {
                        0.0
                    },
                    ramp_s: s.ramp_s,
                }
            })
            .collect();
        let traj = Trajectory::new(
            self.start.lat_deg.to_radians(),
            self.start.lon_deg.to_radians(),
            self.start.height_m,
            self.start.speed_m_s,
            self.start.heading_deg.to_radians(),
            segs,
        );
        match (
            self.vehicle.kind,
            self.vehicle.drag_linear_per_s,
            self.vehicle.drag_quadratic_per_m,
        ) {
            (VehicleKind::Multirotor, Some(a), Some(b)) => traj.with_multirotor_drag(a, b),
            // A multirotor without its law does not pass validation.
            _ => traj,
        }
    }

    /// Total duration, s.
    pub fn duration_s(&self) -> f64 {
        self.segments.iter().map(|s| s.duration_s).sum()
    }
}

impl Scenario {
    /// `[vehicle]`: the keys of the kind, and a multirotor's tilt along the trajectory (checked
    /// only when `trajectory_ok`: the start and segments are valid).
    fn validate_vehicle(&self, p: &mut Problems, trajectory_ok: bool) {
        let v = &self.vehicle;
        let keys = [
            ("drag_linear_per_s", v.drag_linear_per_s, -10.0, "-0.215"),
            (
                "drag_quadratic_per_m",
                v.drag_quadratic_per_m,
                -1.0,
                "-0.028",
            ),
        ];
        match v.kind {
            VehicleKind::FixedWing => {
                for (key, val, _, _) in keys {
                    if val.is_some() {
                        p.push(key, "only for kind = \"multirotor\"");
                    }
                }
            }
            VehicleKind::Multirotor => {
                for (key, val, lo, sitl) in keys {
                    match val {
                        None => p.push(
                            key,
                            format!(
                                "a multirotor needs its drag law (ArduCopter SITL: {key} = {sitl})"
                            ),
                        ),
                        Some(x) => p.range(key, x, lo, 0.0),
                    }
                }
                if v.drag_linear_per_s == Some(0.0) && v.drag_quadratic_per_m == Some(0.0) {
                    p.push(
                        "drag_linear_per_s",
                        "drag_linear_per_s and drag_quadratic_per_m are both 0: a multirotor's drag opposes its motion",
                    );
                }
                if !(trajectory_ok && p.list.is_empty()) {
                    return;
                }
                // The attitude along the trajectory, every 0.1 s.
                let traj = self.trajectory();
                let n = (self.duration_s() / 0.1).ceil() as usize;
                for i in 0..=n {
                    let t = i as f64 * 0.1;
                    let Some(tilt) = traj.multirotor_tilt_at(t) else {
                        break;
                    };
                    let deg = (tilt.roll_rad.cos() * tilt.pitch_rad.cos())
                        .clamp(-1.0, 1.0)
                        .acos()
                        .to_degrees();
                    if !tilt.converged || deg.is_nan() || deg > MULTIROTOR_MAX_TILT_DEG {
                        p.push(
                            "kind",
                            format!(
                                "the multirotor would tilt {deg:.0} deg at t = {t:.1} s (at most {MULTIROTOR_MAX_TILT_DEG} deg): lower the speed, the accelerations or the turn rates"
                            ),
                        );
                        return;
                    }
                }
            }
        }
    }
}

impl Validate for Scenario {
    fn validate(&self, p: &mut Problems) {
        if self.name.trim().is_empty() {
            p.push("name", "must not be empty");
        }
        // A multirotor may hover (speed 0, no climb then: the path has no direction to climb
        // along); an aeroplane keeps flying.
        let min_speed = match self.vehicle.kind {
            VehicleKind::Multirotor => 0.0,
            VehicleKind::FixedWing => 1.0,
        };
        p.section("start", |p| {
            p.range("lat_deg", self.start.lat_deg, -80.0, 80.0);
            p.range("lon_deg", self.start.lon_deg, -180.0, 180.0);
            p.range("height_m", self.start.height_m, -500.0, 20_000.0);
            p.range("speed_m_s", self.start.speed_m_s, min_speed, 400.0);
            p.range("heading_deg", self.start.heading_deg, -360.0, 360.0);
        });
        self.validate_segments(p, min_speed);
        let segments_ok = p.list.is_empty();
        p.section("vehicle", |p| self.validate_vehicle(p, segments_ok));
        let dur = self.duration_s();
        p.section("imu", |p| self.imu.validate(p));
        self.validate_sensors(p, dur);
        p.section("evaluation", |p| {
            let e = &self.evaluation;
            p.range("from_s", e.from_s, 0.0, dur);
            p.range("until_s", e.until_s, e.from_s, dur);
            p.range("nees_interval_s", e.nees_interval_s, 0.01, 3600.0);
            if let Some(t) = e.target_max_horiz_err_m {
                p.positive("target_max_horiz_err_m", t);
            }
        });
        if let Some(r) = &self.reference {
            p.section("reference", |p| {
                for v in r.ins_only_max_err_enu_m {
                    p.range("ins_only_max_err_enu_m", v, 0.0, 1e7);
                }
                for v in r.vision_max_err_enu_m {
                    p.range("vision_max_err_enu_m", v, 0.0, 1e7);
                }
            });
        }
        if self.gps.is_none() && self.vision.is_none() {
            p.push(
                "gps",
                "a scenario needs gps or vision to initialise the filter",
            );
        }
        p.section("nav", |p| self.nav.validate(p));
        if !self.faults.is_empty() && self.closed_loop.is_none() {
            p.push("faults", "scripted faults need a [closed_loop] section");
        }
        for (i, f) in self.faults.iter().enumerate() {
            p.section(&format!("faults[{i}]"), |p| f.validate(p, dur));
        }
        if let Some(c) = &self.closed_loop {
            p.section("closed_loop", |p| c.validate_in(p, dur));
        }
    }
}

impl Scenario {
    /// The flight's segments: each in range and consistent with its kind.
    fn validate_segments(&self, p: &mut Problems, min_speed: f64) {
        if self.segments.is_empty() {
            p.push("segments", "at least one segment is required");
        }
        let mut speed = self.start.speed_m_s;
        for (i, s) in self.segments.iter().enumerate() {
            p.section(&format!("segments[{i}]"), |p| {
                p.range("duration_s", s.duration_s, 0.1, 86_400.0);
                p.range("ramp_s", s.ramp_s, 0.1, 600.0);
                p.range("turn_rate_deg_s", s.turn_rate_deg_s, -30.0, 30.0);
                if let Some(v) = s.speed_m_s {
                    p.range("speed_m_s", v, min_speed, 400.0);
                    speed = v;
                }
                p.range(
                    "climb_rate_m_s",
                    s.climb_rate_m_s,
                    -0.5 * speed,
                    0.5 * speed,
                );
                match s.kind {
                    SegmentKind::Straight => {
                        if s.turn_rate_deg_s != 0.0 || s.climb_rate_m_s != 0.0 {
                            p.push(
                                "kind",
                                "a straight segment has no turn_rate_deg_s or climb_rate_m_s",
                            );
                        }
                    }
                    SegmentKind::Turn => {
                        if s.turn_rate_deg_s == 0.0 {
                            p.push("turn_rate_deg_s", "a turn needs a non-zero turn rate");
                        }
                    }
                    SegmentKind::Climb => {
                        if s.turn_rate_deg_s != 0.0 {
                            p.push("turn_rate_deg_s", "a climb has no turn rate (use a turn)");
                        }
                        if s.climb_rate_m_s == 0.0 {
                            p.push("climb_rate_m_s", "a climb needs a non-zero climb rate");
                        }
                    }
                }
            });
        }
    }

    /// The simulated sensors: GPS, vision, altitude and attitude streams.
    fn validate_sensors(&self, p: &mut Problems, dur: f64) {
        if let Some(g) = &self.gps {
            p.section("gps", |p| {
                p.range("rate_hz", g.rate_hz, 0.1, 100.0);
                p.range("from_s", g.from_s, 0.0, dur);
                p.range("until_s", g.until_s, g.from_s, dur);
                p.positive("sigma_h_m", g.sigma_h_m);
                p.positive("sigma_v_m", g.sigma_v_m);
                p.positive("sigma_vel_m_s", g.sigma_vel_m_s);
                p.range("latency_s", g.latency_s, 0.0, 2.0);
                for v in g.lever_arm_body_frd_m {
                    p.range("lever_arm_body_frd_m", v, -100.0, 100.0);
                }
                for w in &g.outages_s {
                    p.range("outages_s", w[0], 0.0, dur);
                    p.range("outages_s", w[1], w[0], dur);
                }
            });
        }
        if let Some(v) = &self.vision {
            p.section("vision", |p| {
                p.range("rate_hz", v.rate_hz, 0.1, 100.0);
                p.range("from_s", v.from_s, 0.0, dur);
                p.range("until_s", v.until_s, v.from_s, dur);
                p.positive("sigma_h_m", v.sigma_h_m);
                p.positive("sigma_v_m", v.sigma_v_m);
                p.range("latency_min_ms", v.latency_min_ms, 0.0, 5000.0);
                p.range("latency_max_ms", v.latency_max_ms, v.latency_min_ms, 5000.0);
                p.range("outlier_prob", v.outlier_prob, 0.0, 1.0);
                p.range("outlier_m", v.outlier_m, 0.0, 10_000.0);
                for x in v.lever_arm_body_frd_m {
                    p.range("lever_arm_body_frd_m", x, -100.0, 100.0);
                }
            });
        }
        if let Some(a) = &self.altitude {
            p.section("altitude", |p| {
                p.range("rate_hz", a.rate_hz, 0.1, 100.0);
                p.positive("sigma_m", a.sigma_m);
                p.range("bias_m", a.bias_m, -1000.0, 1000.0);
            });
        }
        p.section("attitude", |p| {
            p.range("rate_hz", self.attitude.rate_hz, 0.1, 400.0);
            p.positive("sigma_tilt_deg", self.attitude.sigma_tilt_deg);
            p.positive("sigma_yaw_deg", self.attitude.sigma_yaw_deg);
        });
    }
}

impl ClosedLoopConfig {
    /// How a tiled map's tiles load: inline in lock-step (a seed's run meets the same tiles on
    /// any machine), in the background in real time (as in flight).
    pub fn tile_loading(&self) -> visnav_io::map::paged::LoadMode {
        if self.lockstep {
            visnav_io::map::paged::LoadMode::Inline
        } else {
            visnav_io::map::paged::LoadMode::Background
        }
    }

    /// The closed loop's camera, AHRS, workers, map and camera worlds (`dur`: the flight's
    /// duration, s).
    fn validate_in(&self, p: &mut Problems, dur: f64) {
        let c = self;
        p.range("camera_rate_hz", c.camera_rate_hz, 0.05, 30.0);
        p.range("camera_from_s", c.camera_from_s, 0.0, dur);
        p.range("frame_max_age_s", c.frame_max_age_s, 0.01, 60.0);
        p.range("ahrs_tilt_sigma_deg", c.ahrs_tilt_sigma_deg, 0.0, 20.0);
        p.range("ahrs_yaw_sigma_deg", c.ahrs_yaw_sigma_deg, 0.0, 90.0);
        p.range("ahrs_corr_time_s", c.ahrs_corr_time_s, 0.1, 1e6);
        p.range(
            "ahrs_rate_error_deg_h",
            c.ahrs_rate_error_deg_h,
            0.0,
            36_000.0,
        );
        p.range("ahrs_rate_corr_time_s", c.ahrs_rate_corr_time_s, 0.1, 1e6);
        if c.workers == 0 || c.workers > 16 {
            p.push("workers", "must be 1 to 16");
        }
        if let Some(v) = &c.vo {
            p.section("vo", |p| v.validate(p));
        }
        if let Some([cols, rows]) = c.mosaic
            && !((1..=MAX_MOSAIC_COPIES).contains(&cols) && (1..=MAX_MOSAIC_COPIES).contains(&rows))
        {
            p.push(
                "mosaic",
                format!("[{cols}, {rows}]: each must be 1 to {MAX_MOSAIC_COPIES}"),
            );
        }
        if let Some(t) = c.map_tile_m {
            use visnav_io::map::tiled::{MAX_TILE_M, MIN_TILE_M};
            p.range("map_tile_m", t, MIN_TILE_M, MAX_TILE_M);
        }
        if let Some(n) = c.map_upsample
            && !matches!(n, 1 | 2 | 4)
        {
            p.push("map_upsample", format!("{n}: must be 1, 2 or 4"));
        }
        match (&c.camera_dem, c.camera_ground_height_amsl_m) {
            (Some(_), Some(_)) => p.push(
                "camera_dem",
                "give camera_dem or camera_ground_height_amsl_m, not both",
            ),
            (None, None) => p.push(
                "camera_ground_height_amsl_m",
                "give camera_dem or camera_ground_height_amsl_m",
            ),
            (None, Some(h)) => p.range("camera_ground_height_amsl_m", h, -500.0, 9000.0),
            _ => {}
        }
        p.section("render", |p| c.render.validate(p));
        if let Some(d) = &c.map_degrade {
            p.section("map_degrade", |p| d.validate(p));
        }
        if let Some(d) = &c.camera_degrade {
            p.section("camera_degrade", |p| d.validate(p));
        }
        if c.map_degrade.is_some() && c.map_degrade == c.camera_degrade {
            p.push(
                "camera_degrade",
                "must differ from map_degrade (the camera would see the map's own image)",
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bundled(name: &str) -> Scenario {
        let p = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../.."))
            .join("sitl/scenarios")
            .join(name);
        Scenario::load(&p).unwrap_or_else(|e| panic!("{e}"))
    }

    #[test]
    fn every_bundled_scenario_loads() {
        for n in [
            "seed_outage.toml",
            "gps_calibration.toml",
            "turns_vision_only.toml",
            "closed_loop_demo.toml",
            "closed_loop_short.toml",
            "closed_loop_long.toml",
            "seed_outage_closed_loop.toml",
        ] {
            let sc = bundled(n);
            assert_eq!(sc.closed_loop.is_some(), n.contains("closed_loop"), "{n}");
            assert_eq!(sc.vehicle, VehicleConfig::default(), "{n}: fixed wing");
            assert!(sc.trajectory().drag_law().is_none());
        }
        let sc = bundled("copter_ardupilot.toml");
        assert!(sc.closed_loop.is_some());
        assert_eq!(sc.vehicle.kind, VehicleKind::Multirotor);
        let law = sc.trajectory().drag_law().expect("a multirotor trajectory");
        assert_eq!((law.linear_per_s, law.quadratic_per_m), (-0.215, -0.028));
    }

    fn copter_text() -> String {
        std::fs::read_to_string(
            Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../.."))
                .join("sitl/scenarios/copter_ardupilot.toml"),
        )
        .unwrap()
    }

    #[test]
    fn vehicle_section_is_validated() {
        let text = copter_text();
        let err = |t: &str| Scenario::parse(t, "x.toml").unwrap_err().to_string();
        let e = err(&text.replace("drag_quadratic_per_m = -0.028", ""));
        assert!(
            e.contains("vehicle.drag_quadratic_per_m") && e.contains("needs its drag law"),
            "{e}"
        );
        let e = err(&text.replace("drag_linear_per_s = -0.215", "drag_linear_per_s = 0.215"));
        assert!(e.contains("vehicle.drag_linear_per_s"), "{e}");
        let e = err(&text
            .replace("drag_linear_per_s = -0.215", "drag_linear_per_s = 0.0")
            .replace(
                "drag_quadratic_per_m = -0.028",
                "drag_quadratic_per_m = 0.0",
            ));
        assert!(e.contains("both 0"), "{e}");
        let e = err(&text.replace("kind = \"multirotor\"", "kind = \"fixed_wing\""));
        assert!(
            e.contains("vehicle.drag_linear_per_s") && e.contains("only for kind"),
            "{e}"
        );
        let e = err(&text.replace("kind = \"multirotor\"", "kind = \"blimp\""));
        assert!(e.contains("blimp"), "{e}");
        let e = err(&text.replace("[vehicle]\n", "[vehicle]\nmass_kg = 2.0\n"));
        assert!(e.contains("mass_kg"), "{e}");
        // A multirotor asked for 40 m/s with SITL's drag would have to lean past 60 deg.
        let e = err(&text.replacen("speed_m_s = 12.0", "speed_m_s = 40.0", 1));
        assert!(
            e.contains("vehicle.kind") && e.contains("would tilt"),
            "{e}"
        );
        // Without the section: a fixed wing.
        let fw = Scenario::parse(
            &text
                .replace("[vehicle]\nkind = \"multirotor\"\n", "")
                .replace("drag_linear_per_s = -0.215 ", "# ")
                .replace("drag_quadratic_per_m = -0.028", ""),
            "x.toml",
        )
        .unwrap();
        assert_eq!(fw.vehicle.kind, VehicleKind::FixedWing);
    }

    #[test]
    fn ahrs_rate_error_keys_are_validated() {
        let text = copter_text();
        let sc = Scenario::parse(&text, "x.toml").unwrap();
        let cl = sc.closed_loop.unwrap();
        assert_eq!(cl.ahrs_rate_error_deg_h, 60.0);
        assert!(cl.gps_velocity);
        for (from, to, key) in [
            (
                "ahrs_rate_error_deg_h = 60.0",
                "ahrs_rate_error_deg_h = -1.0",
                "closed_loop.ahrs_rate_error_deg_h",
            ),
            (
                "ahrs_rate_corr_time_s = 60.0",
                "ahrs_rate_corr_time_s = 0.0",
                "closed_loop.ahrs_rate_corr_time_s",
            ),
        ] {
            let e = Scenario::parse(&text.replace(from, to), "x.toml")
                .unwrap_err()
                .to_string();
            assert!(e.contains(key), "{e}");
        }
        // The defaults (the demo has none of the keys): no rate error, no GPS velocity.
        let demo = bundled("closed_loop_demo.toml").closed_loop.unwrap();
        assert_eq!(demo.ahrs_rate_error_deg_h, 0.0);
        assert!(!demo.gps_velocity);
    }

    #[test]
    fn gps_outage_windows() {
        let mut sc = bundled("closed_loop_demo.toml");
        let g = sc.gps.as_mut().unwrap();
        g.outages_s = vec![[10.0, 12.0]];
        assert!(g.available(9.99) && !g.available(10.0) && !g.available(11.9) && g.available(12.0));
        assert!(!g.available(30.0), "the outage after until_s");
        let text = std::fs::read_to_string(
            Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../.."))
                .join("sitl/scenarios/closed_loop_demo.toml"),
        )
        .unwrap()
        .replace(
            "until_s = 30.0\n",
            "until_s = 30.0\noutages_s = [[20.0, 10.0]]\n",
        );
        let e = Scenario::parse(&text, "x.toml").unwrap_err().to_string();
        assert!(e.contains("gps.outages_s"), "{e}");
    }

    #[test]
    fn a_multirotor_hovers_and_an_aeroplane_does_not() {
        let text = std::fs::read_to_string(
            Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../.."))
                .join("sitl/scenarios/drone_autzen.toml"),
        )
        .unwrap();
        let sc = Scenario::parse(&text, "x.toml").unwrap_or_else(|e| panic!("{e}"));
        let traj = sc.trajectory();
        // Hovering (speed 0) from the start, with no direction to climb along: level and still.
        let k = traj.kinematics(4.0);
        assert!(k.v_ned_m_s.norm() < 1e-9, "{:?}", k.v_ned_m_s);
        assert!(k.rpy_rad.iter().all(|v| v.is_finite()));
        assert!(k.rpy_rad.x.abs() < 1e-9 && k.rpy_rad.y.abs() < 1e-9);
        // The climb takes it from 60 to about 150 m above the start.
        let mut t = traj.truth();
        let h0 = t.state().h_m;
        let mut h_max = h0;
        for _ in 0..(sc.duration_s() / 0.01) as usize {
            t.step(0.01);
            h_max = h_max.max(t.state().h_m);
        }
        assert!(
            (85.0..100.0).contains(&(h_max - h0)),
            "climbed {}",
            h_max - h0
        );
        // An aeroplane cannot hover; a hovering multirotor cannot climb.
        let fw = text.replace("kind = \"multirotor\"", "kind = \"fixed_wing\"");
        let e = Scenario::parse(&fw, "x.toml").unwrap_err().to_string();
        assert!(e.contains("start.speed_m_s"), "{e}");
        let climb = text.replacen(
            "kind = \"straight\"\nduration_s = 8.0",
            "kind = \"climb\"\nduration_s = 8.0\nclimb_rate_m_s = 1.0",
            1,
        );
        let e = Scenario::parse(&climb, "x.toml").unwrap_err().to_string();
        assert!(e.contains("segments[0].climb_rate_m_s"), "{e}");
    }

    #[test]
    fn the_map_and_camera_copies_are_validated_and_must_differ() {
        let text = std::fs::read_to_string(
            Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../.."))
                .join("sitl/scenarios/drone_autzen.toml"),
        )
        .unwrap();
        let bad = text.replace("jpeg_quality = 75", "jpeg_quality = 101");
        let e = Scenario::parse(&bad, "x.toml").unwrap_err().to_string();
        assert!(e.contains("closed_loop.map_degrade.jpeg_quality"), "{e}");
        // The camera's copy made the map's: the body of one section in the other.
        let body = |header: &str, next: &str| {
            let h = text.find(header).unwrap();
            let start = h + text[h..].find('\n').unwrap() + 1;
            text[start..text.find(next).unwrap()].to_string()
        };
        let map_body = body("[closed_loop.map_degrade]", "[closed_loop.camera_degrade]");
        let cam_body = body("[closed_loop.camera_degrade]", "[closed_loop.render]");
        let same = text.replace(&cam_body, &map_body);
        let e = Scenario::parse(&same, "x.toml").unwrap_err().to_string();
        assert!(
            e.contains("closed_loop.camera_degrade") && e.contains("differ"),
            "{e}"
        );
    }

    #[test]
    fn closed_loop_section_is_validated() {
        let text = std::fs::read_to_string(
            Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../.."))
                .join("sitl/scenarios/closed_loop_demo.toml"),
        )
        .unwrap();
        let bad = text.replace("camera_rate_hz = 2.0", "camera_rate_hz = -2.0");
        let e = Scenario::parse(&bad, "x.toml").unwrap_err().to_string();
        assert!(e.contains("closed_loop.camera_rate_hz"), "{e}");
        let bad = text.replace("camera_ground_height_amsl_m = 580.0\n", "");
        let e = Scenario::parse(&bad, "x.toml").unwrap_err().to_string();
        assert!(e.contains("closed_loop.camera_ground_height_amsl_m"), "{e}");
        let bad = text.replace("[closed_loop]\n", "[closed_loop]\nmap_upsample = 3\n");
        let e = Scenario::parse(&bad, "x.toml").unwrap_err().to_string();
        assert!(
            e.contains("closed_loop.map_upsample") && e.contains("must be 1, 2 or 4"),
            "{e}"
        );
        let bad = text.replace("control = true", "contrl = true");
        let e = Scenario::parse(&bad, "x.toml").unwrap_err().to_string();
        assert!(e.contains("contrl"), "{e}");
    }
}
