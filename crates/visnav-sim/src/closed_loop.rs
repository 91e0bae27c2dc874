//! The closed loop behind `visnav sim`: the built-in autopilot emulator and the real visnav daemon
//! talk MAVLink 2 over real loopback UDP sockets, the simulated camera renders the camera-year
//! orthophoto at the true pose, and the daemon's vision fixes, its filter and what it injects
//! (GPS_INPUT / VISION_POSITION_ESTIMATE / ODOMETRY, as configured) are scored against the truth.
//! A second emulator + daemon pair without a camera runs beside it as the no-vision control.
//!
//! Timeline: each emulator's run time is the scenario time (`t_s = 0` at its start; its boot
//! clock, which the messages carry, equals it until a scripted reboot restarts it); the
//! trajectory, the IMU errors, the GPS outage and the scripted faults (`[[faults]]`,
//! `sitl::faults`) follow it. Fix capture times are mapped back from the boot clock.
//!
//! Clock (`[closed_loop] lockstep`, default true): in lock-step the caller runs [`run`] on a
//! current-thread tokio runtime started paused (`visnav sim` does). Every timer of the emulators,
//! the links and the daemons is on that runtime's clock, which jumps to the next timer whenever
//! every task waits; frames are taken on the same clock and rendered and fixed on the blocking
//! pool, during which the paused clock does not move (tokio inhibits auto-advance while a
//! blocking task runs on a current-thread runtime); a fix result is delivered
//! `lockstep_fix_latency_s` after its capture (`visnav_daemon::frames::lockstep_frames`). UDP
//! still carries every message over loopback. The emulator sends one instant's messages in
//! message-id order and a lock-step run starts its UTC at 2024-01-01, so a seed gives the same
//! numbers on every run, at whatever speed the CPU allows (the 90 s demo in about 8 s). Without
//! lock-step: real time on a multi-thread runtime, fixes on worker threads (a 90 s scenario takes
//! 90 s; `visnav sim --realtime`).
//!
//! Truth and sensors ([`SimSensors`], the emulator's `TruthSource`):
//! * the trajectory is integrated once at 200 Hz ([`TruthTable`]; WGS84 ellipsoidal heights,
//!   AMSL = h - N with the EGM96 geoid); states between samples are interpolated linearly
//!   (angles along the shorter arc);
//! * IMU: the scenario's `[imu]` errors (`visnav_core::nav::synth::imu`) applied over each interval between two IMU
//!   messages, sent as SCALED_IMU / RAW_IMU (mG, mrad/s: what ArduPilot streams);
//! * GPS: truth + white noise (`[gps] sigma_h_m`, `sigma_v_m`) inside `[gps] from_s..until_s`,
//!   NO_FIX outside (the outage), on GPS_RAW_INT and GPS2_RAW; with `[closed_loop]
//!   gps_velocity` also the ground speed and course (+ `sigma_vel_m_s` per axis), else unknown;
//! * ATTITUDE (and GLOBAL_POSITION_INT's heading): the truth plus the AHRS error, a first-order
//!   Gauss-Markov process per axis (`[closed_loop] ahrs_*`; sampled at 1 Hz, interpolated);
//!   ATTITUDE's body rates: the last simulated gyro sample plus, with
//!   `[closed_loop] ahrs_rate_error_deg_h` > 0, another such process per axis (`ahrs_rate_*`:
//!   ArduPilot's rates are its gyro minus EKF3's wandering bias estimate);
//! * GLOBAL_POSITION_INT, SCALED_PRESSURE: the true position (not used by visnav's filter).
//!
//! Scoring (`[evaluation] from_s..until_s`, horizontal errors unless named otherwise):
//! * `fix_err_m`: accepted vision fixes' camera position against the true camera position at the
//!   capture time; `fix_beyond_3sigma`: accepted fixes outside their own 3-sigma horizontal
//!   ellipse (chi-square, 2 dof, 99.73 %);
//! * `nav_err_m`: every injected position (GPS_INPUT as the emulator received it) against the
//!   truth at its arrival (visnav propagates GPS_INPUT to the send time);
//! * `nav_output_err_m` / `control_err_m`: the vision and the control filters' outputs, sampled
//!   at 10 Hz, against the truth at the output's own time;
//! * `nav_err_over_sigma` / `control_err_over_sigma`: the same horizontal errors divided by the
//!   filter's own horizontal 1-sigma (major semi-axis of its covariance, what GPS_INPUT's
//!   `horiz_accuracy` reports): the integrity of the claimed accuracy. For an honest filter with
//!   a round error ellipse the ratio is Rayleigh-distributed: median 1.18, above 3 for 1.1 % of
//!   the time (e^{-4.5}); an elongated ellipse gives smaller ratios; `nav_sigma_h_m` /
//!   `control_sigma_h_m`: that sigma itself (the accuracy each filter claims);
//! * `latency_ms`: capture to fix result (autopilot clock);
//! * over the whole flight rather than the window ([`FlightFigures`]): `final_err_h_m` /
//!   `control_final_err_h_m`, each filter's horizontal error at its last initialised step;
//!   `distance_flown_m`, the true track's horizontal length from the GPS loss to the end;
//!   `yaw_err_deg_max` / `ctl_yaw_err_deg_max`, each filter's largest heading error (its yaw
//!   against the true yaw at the output's time, wrapped to +-180 deg) from the GPS loss on;
//! * `faults` (with `[[faults]]`): per fault, the vision daemon's injections and fixes around it
//!   (`sitl::faults::FaultOutcome`), and `fault_counters`: its reboot, relock, clock-step,
//!   stale-message, IMU-timeout and frozen-frame counters, GPS_INPUT time steps back and
//!   non-finite or foreign injections as the emulator received them. A `map_withheld` fault
//!   refuses the fixes of the frames captured in its window (capture time mapped to the run
//!   time) in `RecordingFixer` with `faults::MAP_WITHHELD_REASON`, without running the engine;
//!   they are scored and counted like any rejected fix.
//!
//! Given a log folder (`visnav sim` passes its report folder) and with visual odometry on, the
//! vision daemon writes its VO log there ([`VO_LOG_FILE`], `[daemon] vo_log`) and the camera its
//! true pose per frame ([`FRAMES_TRUTH_FILE`]): `python3 sitl/vo_check.py FOLDER` scores every
//! motion against the truth, as for a real SITL flight.

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use nalgebra::Vector3;
use serde::Serialize;
use tracing::{Instrument, info, warn};

mod recording;
mod standalone;

pub use standalone::{AutopilotOnlyReport, FramesWritten, autopilot_only, write_frames};

/// The vision daemon's VO log in the log folder (`[daemon] vo_log`), with VO on.
pub const VO_LOG_FILE: &str = "vo.jsonl";
/// The simulated camera's true pose per frame in the log folder, with VO on.
pub const FRAMES_TRUTH_FILE: &str = "frames_truth.jsonl";

use recording::{InjectionCollector, OutputSample, StepSample, health_code, resident_vec};

use super::Scenario;
use super::autopilot::{
    AbortOnDrop, AutopilotEmulator, EmulatorConfig, LinkFaults, TruthSource, TruthState,
};
use super::camera_sim::{SimCamera, SimCameraSpec, TruthFeed};
use super::faults::{
    self, CameraFault, FaultCounters, FaultKind, FaultOutcome, FaultPlan, ScoredFix, ScoredOutput,
    spoof_heartbeats,
};
use super::fixeval::Stats;
use super::render::degrade::degrade;
use super::render::{ColourMode, Renderer, Scene};
use super::scenario::{ClosedLoopConfig, GpsConfig};
use visnav_core::fix::{FixPrior, FixReport};
use visnav_core::geo::GeoError;
use visnav_core::geo::dem::Dem;
use visnav_core::geo::geoid::geoid_undulation_m;
use visnav_core::nav::NavOutput;
use visnav_core::nav::synth::imu::ImuErrors;
use visnav_core::rng::Rng;
use visnav_core::stats::percentile;
use visnav_core::vision::GrayImage;
use visnav_daemon::config::Config;
use visnav_daemon::heap::{heap_in_use_bytes, heap_peak_bytes, reset_heap_peak};
use visnav_daemon::{Daemon, DaemonSetup, FrameFixer, FramePipeline};
use visnav_io::geo::geotiff::load_geotiff;
use visnav_io::geo::geotiff_write::write_geotiff;

/// Truth sampling interval, s.
const TRUTH_DT_S: f64 = 0.005;
/// Extra truth beyond the scenario's end (the daemons stop a little later), s.
const TRUTH_MARGIN_S: f64 = 30.0;

/// UTC at the start of a lock-step run (2024-01-01T00:00:00Z), µs.
const LOCKSTEP_UNIX_START_US: u64 = 1_704_067_200_000_000;
/// Chi-square 2 dof at 99.73 % (the 3-sigma ellipse).
const CHI2_2DOF_3SIGMA: f64 = 11.829;

/// Why the closed loop could not run.
#[derive(Debug, thiserror::Error)]
pub enum ClosedLoopError {
    /// The scenario is not a closed-loop one.
    #[error("the scenario has no [closed_loop] section")]
    NotClosedLoop,
    /// The scenario's configuration, maps, camera, sockets or emulators could not be set up (the
    /// message names what).
    #[error("{0}")]
    Setup(String),
    /// A daemon failed to start or run.
    #[error(transparent)]
    Daemon(#[from] visnav_daemon::DaemonError),
    /// A file of the run could not be read or written.
    #[error("{path}: {cause}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        cause: std::io::Error,
    },
}

/// One truth sample.
#[derive(Debug, Clone, Copy)]
struct Sample {
    lat_deg: f64,
    lon_deg: f64,
    h_ellip_m: f64,
    alt_amsl_m: f64,
    vel_ned_m_s: [f64; 3],
    rpy_rad: [f64; 3],
    gyro_body_rad_s: [f64; 3],
    accel_body_m_s2: [f64; 3],
}

/// The scenario's trajectory sampled at 200 Hz (see the module doc).
#[derive(Debug, Clone)]
pub struct TruthTable {
    samples: Vec<Sample>,
}

fn lerp(a: f64, b: f64, u: f64) -> f64 {
    a + (b - a) * u
}

/// Angle in [-pi, pi).
fn wrap_pi(a: f64) -> f64 {
    (a + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU) - std::f64::consts::PI
}

fn lerp_angle(a: f64, b: f64, u: f64) -> f64 {
    wrap_pi(a + wrap_pi(b - a) * u)
}

/// Why a scenario's truth could not be tabulated.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TruthTableError {
    /// The geoid undulation could not be had at a point of the trajectory.
    #[error("truth at t = {t_s} s: geoid: {error}")]
    Geoid {
        /// Scenario time of the sample, s.
        t_s: f64,
        /// Why the geoid model failed there.
        error: GeoError,
    },
    /// The integrated trajectory left the finite numbers.
    #[error("the trajectory integration produced non-finite positions")]
    NonFinite,
}

impl TruthTable {
    /// Integrates the scenario's trajectory (its duration plus a margin).
    pub fn from_scenario(sc: &Scenario) -> Result<Self, TruthTableError> {
        let traj = sc.trajectory();
        let mut integ = traj.truth();
        let n = ((sc.duration_s() + TRUTH_MARGIN_S) / TRUTH_DT_S).ceil() as usize + 1;
        let mut samples = Vec::with_capacity(n);
        let mut undulation = None;
        let mut prev_rates = ([0.0; 3], [0.0; 3]);
        for i in 0..n {
            let st = integ.state();
            let (lat_deg, lon_deg) = (st.lat_rad.to_degrees(), st.lon_rad.to_degrees());
            // The geoid changes by millimetres over a scenario's area: refreshed every 10 s.
            if i % 2000 == 0 || undulation.is_none() {
                undulation = Some(geoid_undulation_m(lat_deg, lon_deg).map_err(|error| {
                    TruthTableError::Geoid {
                        t_s: i as f64 * TRUTH_DT_S,
                        error,
                    }
                })?);
            }
            let n_m = undulation.unwrap_or(0.0);
            let (roll, pitch, yaw) = st.q_nb.euler_angles();
            // Rates over the next interval (the last sample repeats the previous ones).
            let rates = if i + 1 < n {
                let (dth, dv) = integ.step(TRUTH_DT_S);
                let r = ((dth / TRUTH_DT_S).into(), (dv / TRUTH_DT_S).into());
                prev_rates = r;
                r
            } else {
                prev_rates
            };
            let v: Vector3<f64> = st.v_ned_m_s;
            samples.push(Sample {
                lat_deg,
                lon_deg,
                h_ellip_m: st.h_m,
                alt_amsl_m: st.h_m - n_m,
                vel_ned_m_s: [v.x, v.y, v.z],
                rpy_rad: [roll, pitch, yaw],
                gyro_body_rad_s: rates.0,
                accel_body_m_s2: rates.1,
            });
        }
        if samples
            .iter()
            .any(|s| !(s.lat_deg.is_finite() && s.lon_deg.is_finite() && s.h_ellip_m.is_finite()))
        {
            return Err(TruthTableError::NonFinite);
        }
        Ok(Self { samples })
    }

    fn sample_at(&self, t_s: f64) -> (Sample, Sample, f64) {
        let x = (t_s / TRUTH_DT_S).max(0.0);
        let last = self.samples.len().saturating_sub(1);
        let i = (x.floor() as usize).min(last);
        let j = (i + 1).min(last);
        (
            self.samples[i],
            self.samples[j],
            (x - i as f64).clamp(0.0, 1.0),
        ) // ok: non-empty table
    }

    /// The true state at scenario time `t_s` (held at the ends).
    pub fn at(&self, t_s: f64) -> TruthState {
        let (a, b, u) = self.sample_at(t_s);
        let l3 = |x: [f64; 3], y: [f64; 3]| {
            [
                lerp(x[0], y[0], u),
                lerp(x[1], y[1], u),
                lerp(x[2], y[2], u),
            ]
        };
        TruthState {
            lat_deg: lerp(a.lat_deg, b.lat_deg, u),
            lon_deg: lerp(a.lon_deg, b.lon_deg, u),
            alt_amsl_m: lerp(a.alt_amsl_m, b.alt_amsl_m, u),
            vel_ned_m_s: l3(a.vel_ned_m_s, b.vel_ned_m_s),
            rpy_rad: [
                lerp_angle(a.rpy_rad[0], b.rpy_rad[0], u),
                lerp_angle(a.rpy_rad[1], b.rpy_rad[1], u),
                lerp_angle(a.rpy_rad[2], b.rpy_rad[2], u),
            ],
            gyro_body_rad_s: a.gyro_body_rad_s,
            accel_body_m_s2: a.accel_body_m_s2,
        }
    }

    /// Ellipsoidal height at `t_s`, m.
    pub fn h_ellip_m(&self, t_s: f64) -> f64 {
        let (a, b, u) = self.sample_at(t_s);
        lerp(a.h_ellip_m, b.h_ellip_m, u)
    }
}

struct ImuState {
    last_t_s: Option<f64>,
    /// The last gyro sample (rad/s), what ATTITUDE reports as the body rates.
    last_gyro: Option<[f64; 3]>,
    errors: ImuErrors,
    rng: Rng,
}

/// Truth plus the scenario's sensor errors, as the emulator's `TruthSource` (module doc).
pub struct SimSensors {
    table: Arc<TruthTable>,
    /// AHRS error (roll, pitch, yaw) at 1 Hz, rad.
    ahrs_err_rad: Vec<[f64; 3]>,
    /// Error of ATTITUDE's body rates (x, y, z) at 1 Hz, rad/s (empty: none).
    ahrs_rate_err_rad_s: Vec<[f64; 3]>,
    imu: Mutex<ImuState>,
    gps: Option<GpsConfig>,
    gps_rng: Mutex<Rng>,
    /// Whether the GPS messages carry a (noisy) velocity (`[closed_loop] gps_velocity`).
    gps_velocity: bool,
    /// The scenario's scripted faults.
    faults: FaultPlan,
}

impl SimSensors {
    /// The sensors of `sc` over its truth table: the IMU errors, the AHRS error processes and
    /// the GPS noise drawn from the scenario's seed, and its scripted faults.
    pub fn new(sc: &Scenario, table: Arc<TruthTable>) -> Self {
        let mut rng = Rng::new(sc.seed);
        let errors = ImuErrors::for_run(sc.imu.clone(), &mut rng, false);
        let n_s = (sc.duration_s() + TRUTH_MARGIN_S).ceil() as usize + 2;
        let mut ahrs_err_rad = Vec::new();
        let mut ahrs_rate_err_rad_s = Vec::new();
        if let Some(cl) = &sc.closed_loop {
            let s = [
                cl.ahrs_tilt_sigma_deg.to_radians(),
                cl.ahrs_tilt_sigma_deg.to_radians(),
                cl.ahrs_yaw_sigma_deg.to_radians(),
            ];
            ahrs_err_rad =
                gauss_markov_1hz(sc.seed.wrapping_add(0x51_7cc1), s, cl.ahrs_corr_time_s, n_s);
            if cl.ahrs_rate_error_deg_h > 0.0 {
                let s = (cl.ahrs_rate_error_deg_h / 3600.0).to_radians();
                ahrs_rate_err_rad_s = gauss_markov_1hz(
                    sc.seed.wrapping_add(0x7a7e_5eed),
                    [s; 3],
                    cl.ahrs_rate_corr_time_s,
                    n_s,
                );
            }
        }
        Self {
            table,
            ahrs_err_rad,
            ahrs_rate_err_rad_s,
            imu: Mutex::new(ImuState {
                last_t_s: None,
                last_gyro: None,
                errors,
                rng,
            }),
            gps: sc.gps.clone(),
            gps_rng: Mutex::new(Rng::new(sc.seed.wrapping_add(0x9e37_79b9))),
            gps_velocity: sc.closed_loop.as_ref().is_some_and(|c| c.gps_velocity),
            faults: FaultPlan::new(sc.faults.clone()),
        }
    }

    /// The AHRS attitude error (roll, pitch, yaw) at `t_s`, rad.
    pub fn ahrs_error_rad(&self, t_s: f64) -> [f64; 3] {
        at_1hz(&self.ahrs_err_rad, t_s)
    }

    /// The error of ATTITUDE's body rates (x, y, z) at `t_s`, rad/s (zero unless
    /// `[closed_loop] ahrs_rate_error_deg_h` > 0).
    pub fn ahrs_rate_error_rad_s(&self, t_s: f64) -> [f64; 3] {
        at_1hz(&self.ahrs_rate_err_rad_s, t_s)
    }

    /// Whether the GPS has a fix at `t_s`.
    pub fn gps_on(&self, t_s: f64) -> bool {
        self.gps.as_ref().is_some_and(|g| g.available(t_s))
    }
}

/// `n` samples at 1 Hz of a first-order Gauss-Markov process per axis (stationary: the first
/// sample is drawn with the full sigma), seeded.
fn gauss_markov_1hz(seed: u64, sigma: [f64; 3], corr_time_s: f64, n: usize) -> Vec<[f64; 3]> {
    let mut rng = Rng::new(seed);
    let a = (-1.0 / corr_time_s).exp();
    let q = (1.0 - a * a).sqrt();
    let mut e = [0.0; 3];
    for k in 0..3 {
        e[k] = sigma[k] * rng.normal();
    }
    let mut out = Vec::with_capacity(n);
    for _ in 0..n {
        out.push(e);
        for k in 0..3 {
            e[k] = a * e[k] + sigma[k] * q * rng.normal();
        }
    }
    out
}

/// A 1 Hz series at `t_s`, interpolated linearly (held at the ends; zero when empty).
fn at_1hz(series: &[[f64; 3]], t_s: f64) -> [f64; 3] {
    let n = series.len();
    if n == 0 {
        return [0.0; 3];
    }
    let x = t_s.max(0.0);
    let i = (x.floor() as usize).min(n - 1);
    let j = (i + 1).min(n - 1);
    let u = (x - i as f64).clamp(0.0, 1.0);
    let (a, b) = (series[i], series[j]);
    [
        lerp(a[0], b[0], u),
        lerp(a[1], b[1], u),
        lerp(a[2], b[2], u),
    ]
}

/// Shares one [`SimSensors`] with the emulator.
struct SensorsHandle(Arc<SimSensors>);

impl TruthSource for SensorsHandle {
    fn state(&self, t_s: f64) -> TruthState {
        let mut s = self.0.table.at(t_s);
        let e = self.0.ahrs_error_rad(t_s);
        for (a, d) in s.rpy_rad.iter_mut().zip(e) {
            *a = wrap_pi(*a + d);
        }
        s
    }

    fn imu(&self, t_s: f64) -> ([f64; 3], [f64; 3]) {
        let s = self.0.table.at(t_s);
        let mut st = self.0.imu.lock().unwrap_or_else(|e| e.into_inner());
        let dt_s = match st.last_t_s {
            Some(l) if t_s > l => (t_s - l).min(1.0),
            Some(_) => return (s.gyro_body_rad_s, s.accel_body_m_s2),
            None => 0.01,
        };
        st.last_t_s = Some(t_s);
        let ImuState { errors, rng, .. } = &mut *st;
        let w = Vector3::from(s.gyro_body_rad_s) * dt_s;
        let f = Vector3::from(s.accel_body_m_s2) * dt_s;
        let (dth, dv) = errors.corrupt(rng, &w, &f, dt_s);
        let g = dth / dt_s;
        let a = dv / dt_s + Vector3::from(self.0.faults.extra_accel_m_s2(t_s));
        st.last_gyro = Some([g.x, g.y, g.z]);
        ([g.x, g.y, g.z], [a.x, a.y, a.z])
    }

    fn link_faults(&self, t_s: f64) -> LinkFaults {
        let f = &self.0.faults;
        LinkFaults {
            silent: f.link_silent(t_s),
            reboots: f.reboots_by(t_s),
            utc_offset_us: f.utc_offset_us(t_s),
        }
    }

    fn attitude_rates(&self, t_s: f64) -> [f64; 3] {
        let gyro = {
            let st = self.0.imu.lock().unwrap_or_else(|e| e.into_inner());
            st.last_gyro
                .unwrap_or_else(|| self.0.table.at(t_s).gyro_body_rad_s)
        };
        let e = self.0.ahrs_rate_error_rad_s(t_s);
        [gyro[0] + e[0], gyro[1] + e[1], gyro[2] + e[2]]
    }

    fn gps(&self, t_s: f64) -> Option<TruthState> {
        let g = self.0.gps.as_ref()?;
        if !self.0.gps_on(t_s) {
            return None;
        }
        // The receiver's epoch: `latency_s` before the message's time stamp.
        let mut s = self.0.table.at((t_s - g.latency_s).max(0.0));
        let mut rng = self.0.gps_rng.lock().unwrap_or_else(|e| e.into_inner());
        let (m_m, n_m) = radii_m(s.lat_deg);
        s.lat_deg += (g.sigma_h_m * rng.normal() / (m_m + s.alt_amsl_m)).to_degrees();
        s.lon_deg += (g.sigma_h_m * rng.normal()
            / ((n_m + s.alt_amsl_m) * s.lat_deg.to_radians().cos()))
        .to_degrees();
        s.alt_amsl_m += g.sigma_v_m * rng.normal();
        if self.0.gps_velocity {
            for v in &mut s.vel_ned_m_s {
                *v += g.sigma_vel_m_s * rng.normal();
            }
        }
        let [dn, de] = self.0.faults.gps_offset_ne_m(t_s);
        s.lat_deg += (dn / (m_m + s.alt_amsl_m)).to_degrees();
        s.lon_deg += (de / ((n_m + s.alt_amsl_m) * s.lat_deg.to_radians().cos())).to_degrees();
        Some(s)
    }
}

/// Meridian and prime-vertical radii of curvature at `lat_deg`, m.
fn radii_m(lat_deg: f64) -> (f64, f64) {
    visnav_core::nav::earth::radii_m(lat_deg.to_radians())
}

/// NED difference `b - a`, m (small distances).
fn ned_diff_m(a: (f64, f64, f64), b: (f64, f64, f64)) -> [f64; 3] {
    let (m_m, n_m) = radii_m(a.0);
    [
        (b.0 - a.0).to_radians() * (m_m + a.2),
        (b.1 - a.1).to_radians() * (n_m + a.2) * a.0.to_radians().cos(),
        -(b.2 - a.2),
    ]
}

/// The camera's truth: the truth table at the emulator's run time, stamped with its boot
/// time (what a trigger wired to the autopilot logs); the scenario's camera faults.
struct EmuFeed {
    emu: Arc<AutopilotEmulator>,
    table: Arc<TruthTable>,
    /// Run time window of the camera, µs.
    from_us: u64,
    until_us: u64,
    faults: FaultPlan,
}

impl TruthFeed for EmuFeed {
    fn latest(&self) -> Option<(u64, TruthState)> {
        let (boot, run) = self.emu.times_us();
        (run >= self.from_us && run <= self.until_us)
            .then(|| (boot, self.table.at(run as f64 * 1e-6)))
    }
    fn ended(&self) -> bool {
        self.emu.time_run_us() > self.until_us
    }
    fn camera_fault(&self) -> CameraFault {
        self.faults.camera(self.emu.time_run_us() as f64 * 1e-6)
    }
}

/// Wraps the daemon's fix engine and scores every result, with its timing, as it is made
/// (the report itself is not kept: `recording`); refuses the fixes of frames captured while
/// the scenario withholds the map (`faults::FaultKind::MapWithheld`).
struct RecordingFixer {
    inner: Arc<dyn FrameFixer>,
    emu: Arc<AutopilotEmulator>,
    table: Arc<TruthTable>,
    mount: visnav_core::camera::Mount,
    log: Mutex<Vec<FixRow>>,
    /// The DTM navigator's poses scored against the truth (its observer's record).
    dtm_log: Arc<Mutex<Vec<DtmRow>>>,
    /// In lock-step the fix takes no simulated time: its result is delivered this much later.
    delivery_us: u64,
    /// The scenario's faults (`map_withheld` and `heading_bias` concern the fixes).
    faults: FaultPlan,
    /// The process's memory every [`RSS_PROBE_AFTER_M`] of flight.
    rss: Mutex<RssProbe>,
}

/// Distance flown (the truth camera's track, fix by fix) after which the process's resident
/// memory is taken as the reference for the end's: the map's first tiles, the filter's and the
/// recorders' buffers are in place by then.
pub const RSS_PROBE_AFTER_M: f64 = 10_000.0;

/// The truth track's length at the fixes so far and the resident memory at every multiple of
/// [`RSS_PROBE_AFTER_M`] it passed (the first is the reference for the end's).
#[derive(Default)]
struct RssProbe {
    last: Option<(f64, f64)>,
    flown_m: f64,
    /// The resident memory at every [`RSS_PROBE_AFTER_M`] flown.
    every: Vec<f64>,
}

impl RecordingFixer {
    /// The prior with its heading turned by the scenario's `heading_bias` at the capture time
    /// (its sigma as claimed).
    fn biased(&self, prior: &FixPrior, t_capture_us: u64) -> FixPrior {
        let bias_deg = self.faults.heading_bias_deg(t_capture_us as f64 * 1e-6);
        let mut p = *prior;
        if bias_deg != 0.0
            && let Some(a) = p.attitude.as_mut()
        {
            a.attitude = visnav_core::camera::Attitude::new(
                a.attitude.roll_rad,
                a.attitude.pitch_rad,
                a.attitude.yaw_rad + bias_deg.to_radians(),
            );
        }
        p
    }

    /// Adds the truth camera's step to the track flown and takes the resident memory at every
    /// multiple of [`RSS_PROBE_AFTER_M`] it passes.
    fn probe_rss(&self, t_capture_us: u64) {
        let (lat, lon, _) = truth_camera(&self.table, t_capture_us as f64 * 1e-6, &self.mount);
        let mut p = self.rss.lock().unwrap_or_else(|e| e.into_inner());
        if let Some((la, lo)) = p.last {
            let m_per_deg = 111_320.0;
            p.flown_m +=
                ((lat - la) * m_per_deg).hypot((lon - lo) * m_per_deg * lat.to_radians().cos());
        }
        p.last = Some((lat, lon));
        if p.flown_m >= RSS_PROBE_AFTER_M * (p.every.len() + 1) as f64
            && let Some(now) = rss_mb()
        {
            p.every.push(now);
        }
    }
}

impl FrameFixer for RecordingFixer {
    fn fix(&self, image: &GrayImage, prior: &FixPrior) -> FixReport {
        // The prior's capture time is on the autopilot's boot clock; the truth's clock and the
        // faults' is the emulator's run time (the scenario time, as for the camera's faults).
        let t_capture_us = self.emu.run_us_of_boot_us(prior.t_capture_us);
        let report = if self.faults.map_withheld(t_capture_us as f64 * 1e-6) {
            FixReport::rejected(
                visnav_core::fix::Rejection::Withheld {
                    reason: faults::MAP_WITHHELD_REASON,
                },
                prior.t_capture_us,
                0.0,
            )
        } else {
            let prior = self.biased(prior, t_capture_us);
            // The engine reads no clock; the compute time is the process's own measurement,
            // kept in fixes.csv only (no simulated figure depends on it).
            let start = std::time::Instant::now();
            let mut r = self.inner.fix(image, &prior);
            r.ms = start.elapsed().as_secs_f64() * 1e3;
            r
        };
        let t_done_us = self.emu.time_run_us() + self.delivery_us;
        self.probe_rss(t_capture_us);
        let row = score_fix(t_capture_us, t_done_us, &report, &self.table, &self.mount);
        self.log.lock().unwrap_or_else(|e| e.into_inner()).push(row);
        report
    }

    /// The engine's own odometer: visual odometry is not a fix and no fault withholds it.
    fn odometer(&self, cfg: &visnav_core::vo::VoConfig) -> Option<visnav_core::vo::Odometer> {
        self.inner.odometer(cfg)
    }

    fn paging(&self) -> Option<visnav_io::map::paged::PagingStats> {
        self.inner.paging()
    }

    /// The engine's own DTM navigator (it reads no map image, so no fault withholds it), each
    /// pose scored against the truth at its capture time.
    fn dtm_navigator(
        &self,
        cfg: &visnav_core::dtm_nav::DtmNavConfig,
    ) -> Option<visnav_core::dtm_nav::DtmNavigator> {
        let (emu, table, mount) = (self.emu.clone(), self.table.clone(), self.mount);
        let log = self.dtm_log.clone();
        let record = move |t_boot_us: u64, step: &visnav_core::dtm_nav::DtmStep| {
            if let visnav_core::dtm_nav::DtmStep::Fix(f) = step {
                let t_run_us = emu.run_us_of_boot_us(t_boot_us);
                let t_first_s = emu.run_us_of_boot_us(f.t_first_us) as f64 * 1e-6;
                if let Some(row) = score_dtm_pose(t_run_us, f, t_first_s, &table, &mount) {
                    log.lock().unwrap_or_else(|e| e.into_inner()).push(row);
                }
            }
        };
        self.inner
            .dtm_navigator(cfg)
            .map(|n| n.with_observer(Box::new(record)))
    }
}

/// One 10 Hz sample of the run.
#[derive(Debug, Clone, Serialize)]
pub struct StepRow {
    /// Scenario time (vision emulator's boot clock), s.
    pub t_s: f64,
    /// Whether the simulated GPS had a fix at `t_s`.
    pub gps_on: bool,
    /// True vehicle latitude at `t_s`, deg.
    pub truth_lat_deg: f64,
    /// True vehicle longitude at `t_s`, deg.
    pub truth_lon_deg: f64,
    /// True vehicle altitude above mean sea level (EGM96) at `t_s`, m.
    pub truth_alt_amsl_m: f64,
    /// Vision filter output's latitude, deg (NaN before initialisation).
    pub vis_lat_deg: f64,
    /// Vision filter output's longitude, deg (NaN before initialisation).
    pub vis_lon_deg: f64,
    /// Vision filter output's position error against the truth, NED, m (NaN before
    /// initialisation).
    pub vis_err_ned_m: [f64; 3],
    /// Vision filter's claimed horizontal 1-sigma (sqrt of the larger eigenvalue of its
    /// horizontal covariance), m (NaN before initialisation).
    pub vis_sigma_h_m: f64,
    /// Vision filter's health: `ok`, `degraded`, `lost` or `uninitialised`.
    pub vis_health: &'static str,
    /// Control filter (no vision) output's latitude, deg (NaN before initialisation).
    pub ctl_lat_deg: f64,
    /// Control filter output's longitude, deg (NaN before initialisation).
    pub ctl_lon_deg: f64,
    /// Control filter output's position error against the truth, NED, m.
    pub ctl_err_ned_m: [f64; 3],
    /// Control filter's claimed horizontal 1-sigma, m.
    pub ctl_sigma_h_m: f64,
    /// Control filter's health, as `vis_health`.
    pub ctl_health: &'static str,
    /// Horizontal velocity error of the vision filter's output (NaN before initialisation),
    /// m/s (not in steps.csv).
    pub vis_vel_err_h_m_s: f64,
    /// The same for the control filter.
    pub ctl_vel_err_h_m_s: f64,
    /// Heading error of the vision filter's output: the output's yaw (ZYX Euler,
    /// `NavOutput::rpy_deg`) minus the true yaw at the output's own time, wrapped to
    /// [-180, 180) deg (NaN before initialisation).
    pub vis_yaw_err_deg: f64,
    /// The same for the control filter.
    pub ctl_yaw_err_deg: f64,
    /// Largest absolute Euler angle error (roll, pitch, yaw, each wrapped) of the vision filter's
    /// output at the output's own time, deg (NaN before initialisation).
    pub vis_euler_err_deg: f64,
    /// The same for the control filter.
    pub ctl_euler_err_deg: f64,
}

/// An injected position as the emulator received it.
#[derive(Debug, Clone, Serialize)]
pub struct InjectionRow {
    /// Emulator run time (scenario time) at arrival, s.
    pub t_s: f64,
    /// `gps_input`, `vision_position_estimate` or `odometry`.
    pub kind: &'static str,
    /// Injected latitude, deg.
    pub lat_deg: f64,
    /// Injected longitude, deg.
    pub lon_deg: f64,
    /// Injected altitude above mean sea level, m.
    pub alt_amsl_m: f64,
    /// The horizontal accuracy the message claims, m.
    pub horiz_accuracy_m: f64,
    /// Injected position minus the truth at arrival, NED, m.
    pub err_ned_m: [f64; 3],
    /// Whether the control daemon (no vision) sent it.
    pub control: bool,
}

/// Scored fix.
#[derive(Debug, Clone, Serialize)]
pub struct FixRow {
    /// Capture time of the frame (emulator run time), s.
    pub t_capture_s: f64,
    /// Capture to fix result (delivery in lock-step), ms.
    pub latency_ms: f64,
    /// Whether the fix engine accepted the fix.
    pub accepted: bool,
    /// "ok", or the rejection in words.
    pub reason: String,
    /// "ok", or the rejection's class (`visnav_core::fix::Rejection::class`).
    pub class: &'static str,
    /// The fix's camera latitude, deg.
    pub lat_deg: f64,
    /// The fix's camera longitude, deg.
    pub lon_deg: f64,
    /// The fix's camera position minus the true camera position at capture, NED, m (NaN when
    /// rejected).
    pub err_ned_m: [f64; 3],
    /// The fix's claimed horizontal 1-sigma (major semi-axis of its covariance), m (NaN when
    /// rejected).
    pub sigma_h_m: f64,
    /// Whether the horizontal error lies outside the fix's own 3-sigma ellipse (chi-square,
    /// 2 dof).
    pub beyond_3sigma: bool,
    /// The fix's pose inliers (`FixReport::inliers`).
    pub inliers: usize,
    /// The engine's compute time for this frame, wall clock, ms (0 for a frame refused because
    /// the scenario withholds the map).
    pub ms: f64,
}

impl FixRow {
    /// A filler for reserving the fix log ([`recording::resident_vec`]).
    const FILL: Self = Self {
        t_capture_s: f64::NAN,
        latency_ms: f64::NAN,
        accepted: false,
        reason: String::new(),
        class: "ok",
        lat_deg: f64::NAN,
        lon_deg: f64::NAN,
        err_ned_m: [f64::NAN; 3],
        sigma_h_m: f64::NAN,
        beyond_3sigma: false,
        inliers: 0,
        ms: f64::NAN,
    };
}

/// `{p50, p95}`.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Latency {
    /// Median.
    pub p50: f64,
    /// 95th percentile.
    pub p95: f64,
}

/// Max absolute error per axis (east, north, up), m.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Enu {
    /// East.
    pub e: f64,
    /// North.
    pub n: f64,
    /// Up.
    pub u: f64,
}

/// A DTM navigator's pose against the truth at its capture time.
#[derive(Debug, Clone, Copy)]
pub struct DtmRow {
    /// Capture time of the frame (emulator run time), s.
    pub t_capture_s: f64,
    /// Capture time of its partner frame, s.
    pub t_first_s: f64,
    /// The distance flown between the two frames, m.
    pub baseline_m: f64,
    /// Flow vectors kept as inliers.
    pub inliers: usize,
    /// Camera position error against the true camera position, NED, m.
    pub err_ned_m: [f64; 3],
    /// Claimed horizontal 1-sigma (major semi-axis), m.
    pub sigma_h_m: f64,
    /// Whether the error lies outside its own 3-sigma horizontal ellipse.
    pub beyond_3sigma: bool,
    /// Largest Euler angle error (roll, pitch, yaw of the vehicle, each wrapped), deg.
    pub euler_err_deg: f64,
}

/// The DTM navigator's poses in the evaluation window (`visnav sim --json`: `dtm_poses`).
#[derive(Debug, Clone, Copy, Serialize)]
pub struct DtmScore {
    /// Poses in the window.
    pub poses: usize,
    /// Horizontal position error, m.
    pub err_h_m: Stats,
    /// Absolute vertical position error, m.
    pub err_v_m: Stats,
    /// Largest Euler angle error per pose, deg.
    pub euler_err_deg: Stats,
    /// The claimed horizontal 1-sigma, m.
    pub sigma_h_m: Stats,
    /// Poses outside their own 3-sigma horizontal ellipse.
    pub beyond_3sigma: usize,
}

impl DtmScore {
    fn of(rows: &[&DtmRow]) -> Self {
        let v = |f: &dyn Fn(&DtmRow) -> f64| rows.iter().map(|r| f(r)).collect::<Vec<f64>>();
        Self {
            poses: rows.len(),
            err_h_m: Stats::of(&v(&|r| hnorm(&r.err_ned_m))),
            err_v_m: Stats::of(&v(&|r| r.err_ned_m[2].abs())),
            euler_err_deg: Stats::of(&v(&|r| r.euler_err_deg)),
            sigma_h_m: Stats::of(&v(&|r| r.sigma_h_m)),
            beyond_3sigma: rows.iter().filter(|r| r.beyond_3sigma).count(),
        }
    }
}

/// A tiled map's paging over a flight (`[closed_loop] map_tile_m`).
#[derive(Debug, Clone, Serialize)]
pub struct MapPagingSummary {
    /// Ground the map's tiles cover, km².
    pub area_km2: f64,
    /// Tiles of the map.
    pub tiles: usize,
    /// The tiles' budget (`[map] memory_mb`), MB.
    pub memory_mb: u64,
    /// Tiles loaded over the flight.
    pub loads: u64,
    /// Tiles dropped for the budget.
    pub evictions: u64,
    /// Tiles a fix's select or level window needed that were not in memory.
    pub misses: u64,
    /// Tiles of a frame's own footprint that the look-ahead had not brought when its request
    /// came (loaded on the frame path in lock-step; missing for the frame in real time).
    pub late: u64,
    /// Frames with at least one such tile (the first frame's, when nothing is in memory yet).
    pub late_frames: u64,
    /// Tiles that failed to load.
    pub load_errors: u64,
    /// Requested tiles the budget could not take.
    pub over_budget: u64,
    /// The tiles in memory at the end, MB.
    pub resident_mb_end: f64,
    /// The process's resident memory once the aircraft had flown 10 km (the truth camera's
    /// track at the fixes), MB.
    pub rss_mb_after_10km: Option<f64>,
    /// The process's resident memory at the end of the flight, MB.
    pub rss_mb_end: Option<f64>,
    /// The process's resident memory every 10 km flown, MB (the memory's course over the route).
    pub rss_mb_every_10km: Vec<f64>,
    /// Fix attempts in the evaluation window whose true camera was within
    /// [`SEAM_BAND_M`] of a square's edge (the footprint spans two or four tiles).
    pub attempts_near_seams: usize,
    /// Of those, the accepted share (null without any).
    pub fix_rate_near_seams: Option<f64>,
}

/// How near a square's edge a fix counts as at a seam, m: a third of the footprint's half-width
/// at 1 500 m with the demo's lens, so the frame sees both tiles well.
pub const SEAM_BAND_M: f64 = 300.0;

/// A tiled map's paging counters and the process's memory at a flight's end.
struct PagingEnd {
    stats: visnav_io::map::paged::PagingStats,
    rss_every: Vec<f64>,
    rss_end: Option<f64>,
}

impl MapPagingSummary {
    /// The summary of `end` over the map `tiled` within `memory_mb`, with the fix attempts at
    /// the seams and their accepted share (`seams`).
    fn new(
        end: PagingEnd,
        tiled: Option<TiledMapBuilt>,
        memory_mb: u64,
        seams: (usize, Option<f64>),
    ) -> Self {
        let s = end.stats;
        Self {
            area_km2: tiled.map_or(0.0, |t| t.area_km2),
            tiles: tiled.map_or(0, |t| t.tiles),
            memory_mb,
            loads: s.loads,
            evictions: s.evictions,
            misses: s.misses,
            late: s.late,
            late_frames: s.late_frames,
            load_errors: s.load_errors,
            over_budget: s.over_budget,
            resident_mb_end: s.resident_bytes as f64 / 1e6,
            rss_mb_after_10km: end.rss_every.first().copied(),
            rss_mb_every_10km: end.rss_every,
            rss_mb_end: end.rss_end,
            attempts_near_seams: seams.0,
            fix_rate_near_seams: seams.1,
        }
    }
}

/// The fix attempts `fixes` whose true camera (`map_xy` of the capture time, map metres) lay
/// within [`SEAM_BAND_M`] of the edge of a square of `tile_m`, and their accepted share.
fn seam_fix_rate(
    fixes: &[&FixRow],
    tile_m: f64,
    map_xy: impl Fn(f64) -> Option<(f64, f64)>,
) -> (usize, Option<f64>) {
    let edge = |v: f64| {
        let r = v.rem_euclid(tile_m);
        r.min(tile_m - r)
    };
    let near: Vec<bool> = fixes
        .iter()
        .filter(|f| {
            tile_m > 0.0
                && map_xy(f.t_capture_s).is_some_and(|(x, y)| edge(x).min(edge(y)) < SEAM_BAND_M)
        })
        .map(|f| f.accepted)
        .collect();
    let rate =
        (!near.is_empty()).then(|| near.iter().filter(|a| **a).count() as f64 / near.len() as f64);
    (near.len(), rate)
}

/// The closed-loop summary (`visnav sim --json`).
#[derive(Debug, Clone, Serialize)]
pub struct ClosedLoopSummary {
    /// The scenario's name.
    pub scenario: String,
    /// The scenario's description.
    pub description: String,
    /// The scenario's flight duration, s.
    pub duration_s: f64,
    /// Scenario time at which the run was stopped early (Ctrl-C): the figures cover the flight
    /// up to there only.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub interrupted_at_s: Option<f64>,
    /// The evaluation window `[from_s, until_s]` (`[evaluation]`), scenario time, s.
    pub evaluation_window_s: [f64; 2],
    /// The GPS outage from the GPS's `until_s` to the end of the flight, s (null without GPS).
    pub gps_outage_s: Option<[f64; 2]>,
    /// The simulated camera in words (its frame source's description).
    pub camera: String,
    /// Height of the aircraft above the camera's terrain (the surface it renders on) over the
    /// window, m: the median.
    pub agl_m: f64,
    /// The lowest and highest of those heights, m.
    pub agl_range_m: [f64; 2],
    /// A tiled map's paging (`[closed_loop] map_tile_m`; absent for a one-file map).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub map_paging: Option<MapPagingSummary>,
    /// Accepted fixes / fix attempts in the window.
    pub fix_rate: f64,
    /// Frames the vision daemon took in over the whole run.
    pub frames_rendered: u64,
    /// Fix attempts on frames captured in the window.
    pub fix_attempts: usize,
    /// Of those, the fixes the engine accepted.
    pub fixes_accepted: usize,
    /// Frames the vision daemon dropped unfixed (superseded by a newer frame, or stale).
    pub frames_dropped: u64,
    /// Accepted fixes the filter's innovation gate rejected.
    pub fixes_filter_rejected: u64,
    /// Horizontal error of the accepted fixes' camera position against the true camera
    /// position at capture, m.
    pub fix_err_m: Stats,
    /// Accepted fixes outside their own 3-sigma horizontal ellipse.
    pub fix_beyond_3sigma: usize,
    /// Horizontal error of the vision daemon's injections of the scored kind
    /// (`injected_message`) against the truth at arrival, m.
    pub nav_err_m: Stats,
    /// Absolute vertical error of the same injections, m.
    pub nav_vert_err_m: Stats,
    /// Horizontal error of the vision filter's output (10 Hz samples) against the truth at the
    /// output's time, m.
    pub nav_output_err_m: Stats,
    /// The same for the control filter's output, m.
    pub control_err_m: Stats,
    /// Horizontal error of the control daemon's injections of the scored kind, m.
    pub control_injected_err_m: Stats,
    /// Horizontal error over the vision filter's horizontal sigma (module doc).
    pub nav_err_over_sigma: Stats,
    /// The same for the control filter.
    pub control_err_over_sigma: Stats,
    /// The vision filter's horizontal 1-sigma (major semi-axis), m.
    pub nav_sigma_h_m: Stats,
    /// The control filter's horizontal 1-sigma, m.
    pub control_sigma_h_m: Stats,
    /// Horizontal velocity error of the vision filter's output (10 Hz samples), m/s: a filter
    /// whose velocity collapses while the vehicle flies on shows here.
    pub nav_vel_err_m_s: Stats,
    /// The same for the control filter.
    pub control_vel_err_m_s: Stats,
    /// Largest per-axis and 3-D position errors of both filters' outputs in the window.
    pub max_err_m: MaxErr,
    /// Largest Euler angle error of both filters' outputs in the window.
    pub max_euler_err_deg: MaxEuler,
    /// The vision daemon's visual odometry over the whole run (frames, what came out, what the
    /// filter did, refusals by reason); null when off.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub vo: Option<visnav_daemon::metrics::VoSnapshot>,
    /// The same for its DTM navigation; null when off.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub dtm: Option<visnav_daemon::metrics::VoSnapshot>,
    /// The DTM navigator's poses in the window against the truth; null when none.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub dtm_poses: Option<DtmScore>,
    /// Capture to fix result of the window's attempts, ms.
    pub latency_ms: Latency,
    /// Position messages of the scored kind received in the window.
    pub injections: usize,
    /// The message `nav_err_m` scores (the first of `[output] modes`).
    pub injected_message: String,
    /// Every injected position message kind: (count, horizontal error stats) in the window.
    pub nav_err_by_message: std::collections::BTreeMap<String, (usize, Stats)>,
    /// The control daemon's position messages of the scored kind received in the window.
    pub control_injections: usize,
    /// The window's rejected attempts by class ([`visnav_core::fix::Rejection::class`]), most frequent first, each
    /// with its latest reason as the engine wrote it.
    pub rejections: Vec<visnav_core::reasons::ReasonCount>,
    /// What the vision daemon did around each scripted fault (`[[faults]]`).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub faults: Vec<FaultOutcome>,
    /// Its counters at the end of a run with scripted faults.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fault_counters: Option<FaultCounters>,
    /// The vision filter's health at the last step (`ok`, `degraded`, `lost`, `uninitialised`).
    pub vision_final_health: String,
    /// The control filter's health at the last step.
    pub control_final_health: String,
    /// Horizontal error of the vision filter's output at the last step with an initialised
    /// output, m (whole flight, not the window; null: never initialised).
    pub final_err_h_m: Option<f64>,
    /// The same for the control filter.
    pub control_final_err_h_m: Option<f64>,
    /// Horizontal distance along the true track from the GPS loss to the end, m ([`FlightFigures`];
    /// 0 when the GPS never goes off).
    pub distance_flown_m: f64,
    /// Largest absolute heading error of the vision filter's output over the steps from the GPS
    /// loss on, deg (null: none).
    pub yaw_err_deg_max: Option<f64>,
    /// The same for the control filter.
    pub ctl_yaw_err_deg_max: Option<f64>,
    /// Soak figure (runs of at least twice [`SOAK_WINDOW_S`] in the window): accepted fixes
    /// over attempts in the window's first `SOAK_WINDOW_S`.
    pub fix_rate_first_window: Option<f64>,
    /// The same over the window's last `SOAK_WINDOW_S`.
    pub fix_rate_last_window: Option<f64>,
    /// Resident memory of the whole process (simulator, both daemons), MB: after the first
    /// `SOAK_WINDOW_S` of the window (everything is built and warm) and at the end of the flight,
    /// before the daemons stop and the scoring allocates (Linux `/proc/self/statm`; None
    /// elsewhere). The simulator's recordings are resident from the start (reserved for the
    /// whole run: `recording::resident_vec`), so the growth is the daemons', the emulators' and
    /// the camera's.
    pub rss_mb_after_first_window: Option<f64>,
    /// Resident memory at the end of the flight, MB (as above).
    pub rss_mb_end: Option<f64>,
    /// The heap in use at the same instants (`visnav_daemon::heap`: what was allocated and not
    /// freed), total and the simulator's recordings in it (the reserved buffers of the compact
    /// steps, fix rows and injections, and the fixes' reason strings), MB.
    pub heap_mb_after_first_window: Option<HeapSample>,
    /// The heap at the end of the flight (as above).
    pub heap_mb_end: Option<HeapSample>,
    /// Growth of the heap without the recordings over the soak (both daemons, both emulators,
    /// the camera; everything but what the simulator keeps to score the run), MB.
    pub heap_growth_mb_without_recordings: Option<f64>,
    /// The report folder `visnav sim` writes, set by the caller (null: none).
    pub report_dir: Option<String>,
}

/// The end-of-flight figures of a run, from its 10 Hz steps (the summary's keys of the same
/// names). The GPS loss is the first step without GPS after one with it (the first step when
/// the GPS never has a fix).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FlightFigures {
    /// Horizontal error of the vision filter's output at the last step whose output is
    /// initialised (any health but `uninitialised`), m; None when there is none.
    pub final_err_h_m: Option<f64>,
    /// The same for the control filter.
    pub control_final_err_h_m: Option<f64>,
    /// Horizontal length of the true track from the GPS loss's step to the last step (the sum
    /// over consecutive 10 Hz steps), m; 0 when the GPS never goes off.
    pub distance_flown_m: f64,
    /// Largest absolute heading error of the vision filter's output (wrapped to +-180 deg) over
    /// the steps from the GPS loss on, deg; None without a loss or an output.
    pub yaw_err_deg_max: Option<f64>,
    /// The same for the control filter.
    pub ctl_yaw_err_deg_max: Option<f64>,
}

impl FlightFigures {
    /// The figures of `steps` (in time order).
    pub fn of(steps: &[StepRow]) -> Self {
        let after = gps_loss_index(steps).map_or(&steps[..0], |i| &steps[i..]);
        Self {
            final_err_h_m: final_err_h_m(steps, |s| (s.vis_health, s.vis_err_ned_m)),
            control_final_err_h_m: final_err_h_m(steps, |s| (s.ctl_health, s.ctl_err_ned_m)),
            distance_flown_m: track_length_m(after),
            yaw_err_deg_max: max_abs_yaw_err_deg(after.iter().map(|s| s.vis_yaw_err_deg)),
            ctl_yaw_err_deg_max: max_abs_yaw_err_deg(after.iter().map(|s| s.ctl_yaw_err_deg)),
        }
    }
}

/// The index of the GPS loss (see [`FlightFigures`]); None when the GPS never goes off.
fn gps_loss_index(steps: &[StepRow]) -> Option<usize> {
    match steps.iter().position(|s| s.gps_on) {
        Some(on) => steps[on..]
            .iter()
            .position(|s| !s.gps_on)
            .map(|off| on + off),
        None => (!steps.is_empty()).then_some(0),
    }
}

/// The horizontal error of the last step whose output (`f`: health, NED error) is initialised.
fn final_err_h_m(
    steps: &[StepRow],
    f: impl Fn(&StepRow) -> (&'static str, [f64; 3]),
) -> Option<f64> {
    steps
        .iter()
        .map(f)
        .rfind(|(health, _)| *health != "uninitialised")
        .map(|(_, e)| hnorm(&e))
}

/// Horizontal length of the true track through the steps, m.
fn track_length_m(steps: &[StepRow]) -> f64 {
    let pos = |s: &StepRow| (s.truth_lat_deg, s.truth_lon_deg, s.truth_alt_amsl_m);
    steps
        .windows(2)
        .map(|w| hnorm(&ned_diff_m(pos(&w[0]), pos(&w[1]))))
        .filter(|d| d.is_finite())
        .sum()
}

/// The largest absolute heading error (each wrapped to +-180 deg) of the finite ones, deg.
fn max_abs_yaw_err_deg(errs: impl Iterator<Item = f64>) -> Option<f64> {
    errs.filter(|e| e.is_finite())
        .map(|e| wrap_deg(e).abs())
        .reduce(f64::max)
}

/// The largest of the finite values (NaN: none).
fn max_finite(v: impl Iterator<Item = f64>) -> f64 {
    v.filter(|e| e.is_finite()).fold(f64::NAN, f64::max)
}

fn norm3(e: &[f64; 3]) -> f64 {
    (e[0] * e[0] + e[1] * e[1] + e[2] * e[2]).sqrt()
}

/// The soak figures' window, s (10 minutes: the soak compares the first and last 10 minutes).
pub const SOAK_WINDOW_S: f64 = 600.0;

/// Resident set size of this process, MB (Linux; None where `/proc/self/statm` is absent).
fn rss_mb() -> Option<f64> {
    let statm = std::fs::read_to_string("/proc/self/statm").ok()?;
    let pages: f64 = statm.split_whitespace().nth(1)?.parse().ok()?;
    Some(pages * 4096.0 / 1e6)
}

/// The heap in use and the simulator's recordings in it, and the most the heap held at once
/// since the previous sample (the start for the first), MB.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct HeapSample {
    /// The heap in use, MB.
    pub total_mb: f64,
    /// The simulator's recordings in it, MB.
    pub recordings_mb: f64,
    /// The most the heap held at once since the previous sample, MB.
    pub peak_mb: f64,
}

impl HeapSample {
    fn new(total_bytes: usize, recorded_bytes: usize, peak_bytes: usize) -> Self {
        Self {
            total_mb: total_bytes as f64 / 1e6,
            recordings_mb: recorded_bytes as f64 / 1e6,
            peak_mb: peak_bytes as f64 / 1e6,
        }
    }
}

/// How many samples of `T` a recording at `rate_hz` takes over `duration_s`, with 5 % to spare
/// (a capacity, never a limit: a longer recording grows), at most
/// [`MAX_RESERVED_BYTES_PER_RECORDING`] of them.
fn expected_count<T>(duration_s: f64, rate_hz: f64) -> usize {
    let n = duration_s * rate_hz * 1.05 + 16.0;
    let max = (MAX_RESERVED_BYTES_PER_RECORDING / std::mem::size_of::<T>().max(1)) as f64;
    if n.is_finite() && n > 0.0 {
        n.min(max) as usize
    } else {
        16
    }
}

/// Largest reservation of one recording, bytes: 64 MB holds a million steps (28 hours) and keeps a
/// mistyped duration from reserving gigabytes.
const MAX_RESERVED_BYTES_PER_RECORDING: usize = 64 << 20;

/// The process's memory at one instant of the flight.
#[derive(Debug, Clone, Copy)]
struct MemorySample {
    rss_mb: Option<f64>,
    heap: Option<HeapSample>,
}

/// RSS, heap in use, and the bytes the simulator's recordings hold: the compact steps, the fix
/// rows (buffer and reasons), the injections.
fn memory_sample(
    steps: &Vec<StepSample>,
    fixes: &Mutex<Vec<FixRow>>,
    injections: [&InjectionCollector; 2],
) -> MemorySample {
    let fix_bytes = fixes.lock().map_or(0, |l| {
        l.capacity() * std::mem::size_of::<FixRow>()
            + l.iter().map(|f| f.reason.capacity()).sum::<usize>()
    });
    let recorded = steps.capacity() * std::mem::size_of::<StepSample>()
        + fix_bytes
        + injections.iter().map(|c| c.recorded_bytes()).sum::<usize>();
    let peak = heap_peak_bytes().unwrap_or(0);
    reset_heap_peak();
    MemorySample {
        rss_mb: rss_mb(),
        heap: heap_in_use_bytes().map(|h| HeapSample::new(h, recorded, peak)),
    }
}

/// Accepted over attempted fixes captured in `[from_s, until_s)`.
fn fix_rate_in(fixes: &[&FixRow], from_s: f64, until_s: f64) -> Option<f64> {
    let w: Vec<_> = fixes
        .iter()
        .filter(|f| f.t_capture_s >= from_s && f.t_capture_s < until_s)
        .collect();
    (!w.is_empty()).then(|| w.iter().filter(|f| f.accepted).count() as f64 / w.len() as f64)
}

/// Max per-axis errors of the filter outputs in the window, vision and control side by side.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct MaxErr {
    /// The vision filter's largest error per axis.
    pub vision: Enu,
    /// The control filter's largest error per axis.
    pub control: Enu,
    /// The vision filter's largest 3-D error (not the axes' maxima together), m.
    pub vision_3d: f64,
    /// The control filter's largest 3-D error, m.
    pub control_3d: f64,
}

/// The largest Euler angle error (any of roll, pitch, yaw, each wrapped) of the vision and the
/// control filters' outputs in the window, deg (NaN: no output).
#[derive(Debug, Clone, Copy, Serialize)]
pub struct MaxEuler {
    /// The vision filter's, deg.
    pub vision: f64,
    /// The control filter's, deg.
    pub control: f64,
}

/// Everything a run produced.
#[derive(Debug, Clone)]
pub struct ClosedLoopRun {
    /// The scores.
    pub summary: ClosedLoopSummary,
    /// The run at 10 Hz, whole flight.
    pub steps: Vec<StepRow>,
    /// Every fix attempt, scored, whole flight.
    pub fixes: Vec<FixRow>,
    /// Every position injection both emulators received, scored, whole flight.
    pub injections: Vec<InjectionRow>,
    /// Every pose of the DTM navigator, scored (empty without `[dtm_nav]`).
    pub dtm_poses: Vec<DtmRow>,
    /// CRS of the camera-year orthophoto (the plots' map frame).
    pub crs: visnav_core::geo::Crs,
    /// The camera-year orthophoto as an RGB image (at most ~1600 px wide) and its extent
    /// `[min_x, min_y, max_x, max_y]` in `crs`, the track plot's background.
    pub background: Option<(image::RgbImage, [f64; 4])>,
    /// GPS outage start, s (for the plots).
    pub gps_until_s: Option<f64>,
}

/// An RGB picture of a raster (bands 1-3, or the first band as grey), decimated to at most
/// `max_px` on its longer side, and its extent.
fn background_of(
    raster: &visnav_core::geo::raster::Raster,
    max_px: usize,
) -> Option<(image::RgbImage, [f64; 4])> {
    let (w, h) = (raster.width(), raster.height());
    if w == 0 || h == 0 {
        return None;
    }
    let step = w.max(h).div_ceil(max_px).max(1);
    let (ow, oh) = (w.div_ceil(step), h.div_ceil(step));
    let bands = raster.bands();
    // 16-bit and float rasters are stretched by their 98th percentile of band 1.
    let mut vals: Vec<f64> = (0..oh)
        .flat_map(|r| (0..ow).map(move |c| (c, r)))
        .filter_map(|(c, r)| raster.value(c * step, r * step, 0))
        .collect();
    let scale = match raster.data() {
        visnav_core::geo::raster::RasterData::U8(_) => 1.0,
        _ => {
            let p98 = percentile(&std::mem::take(&mut vals), 0.98);
            if p98.is_finite() && p98 > 0.0 {
                255.0 / p98
            } else {
                1.0
            }
        }
    };
    let mut img = image::RgbImage::new(ow as u32, oh as u32);
    for r in 0..oh {
        for c in 0..ow {
            let get = |b: usize| {
                raster
                    .value(c * step, r * step, b.min(bands - 1))
                    .map_or(0u8, |v| (v * scale).clamp(0.0, 255.0) as u8)
            };
            let px = if bands >= 3 {
                [get(0), get(1), get(2)]
            } else {
                [get(0); 3]
            };
            img.put_pixel(c as u32, r as u32, image::Rgb(px));
        }
    }
    let b = raster.bounds();
    Some((img, [b.min_x_m, b.min_y_m, b.max_x_m, b.max_y_m]))
}

fn free_udp_port() -> Result<u16, ClosedLoopError> {
    std::net::UdpSocket::bind("127.0.0.1:0")
        .and_then(|s| s.local_addr())
        .map(|a| a.port())
        .map_err(|e| ClosedLoopError::Setup(format!("no free loopback UDP port: {e}")))
}

fn same_file(a: &Path, b: &Path) -> bool {
    match (a.canonicalize(), b.canonicalize()) {
        (Ok(x), Ok(y)) => x == y,
        _ => a == b,
    }
}

fn sigma_h_m(cov: &[[f64; 3]; 3]) -> f64 {
    let (a, b, c) = (cov[0][0], cov[1][1], cov[0][1]);
    let tr = 0.5 * (a + b);
    let det = (0.25 * (a - b) * (a - b) + c * c).sqrt();
    (tr + det).max(0.0).sqrt()
}

/// A filter output's velocity against the truth at the output's time, NED, m/s.
fn output_vel_error(out: &NavOutput, table: &TruthTable, emu: &AutopilotEmulator) -> [f64; 3] {
    let v = table.at(run_s_of(out, emu)).vel_ned_m_s;
    [
        out.v_ned_m_s[0] - v[0],
        out.v_ned_m_s[1] - v[1],
        out.v_ned_m_s[2] - v[2],
    ]
}

/// The run time of an output (its time is on the autopilot's boot clock), s.
fn run_s_of(out: &NavOutput, emu: &AutopilotEmulator) -> f64 {
    emu.run_us_of_boot_us(out.t_us) as f64 * 1e-6
}

/// The vision + control daemons' output sampled against the truth.
fn output_error(out: &NavOutput, table: &TruthTable, emu: &AutopilotEmulator) -> [f64; 3] {
    let t = run_s_of(out, emu);
    let s = table.at(t);
    ned_diff_m(
        (s.lat_deg, s.lon_deg, table.h_ellip_m(t)),
        (out.lat_deg, out.lon_deg, out.h_m),
    )
}

/// An angle wrapped to [-180, 180) deg.
fn wrap_deg(a_deg: f64) -> f64 {
    wrap_pi(a_deg.to_radians()).to_degrees()
}

/// Heading error of an estimated yaw against the true yaw, wrapped to [-180, 180) deg.
fn yaw_err_deg(est_deg: f64, truth_rad: f64) -> f64 {
    wrap_pi(est_deg.to_radians() - truth_rad).to_degrees()
}

/// A filter output's heading error against the truth at the output's time, deg.
fn output_yaw_error_deg(out: &NavOutput, table: &TruthTable, emu: &AutopilotEmulator) -> f64 {
    yaw_err_deg(out.rpy_deg[2], table.at(run_s_of(out, emu)).rpy_rad[2])
}

/// A filter output's largest Euler angle error (roll, pitch, yaw against the truth at the
/// output's time, each wrapped), deg.
fn output_euler_error_deg(out: &NavOutput, table: &TruthTable, emu: &AutopilotEmulator) -> f64 {
    let truth = table.at(run_s_of(out, emu)).rpy_rad;
    (0..3)
        .map(|i| yaw_err_deg(out.rpy_deg[i], truth[i]).abs())
        .fold(0.0, f64::max)
}

/// A filter output sampled at a step against the truth `s` at the step's time: position offset,
/// error, velocity error and heading error (at the output's own time), horizontal sigma; its
/// health name.
fn sample_output(
    o: Option<&NavOutput>,
    s: &TruthState,
    table: &TruthTable,
    emu: &AutopilotEmulator,
) -> (OutputSample, &'static str) {
    use visnav_core::nav::Health;
    match o {
        Some(o) => {
            let v = output_vel_error(o, table, emu);
            (
                OutputSample {
                    dlat_deg: (o.lat_deg - s.lat_deg) as f32,
                    dlon_deg: (o.lon_deg - s.lon_deg) as f32,
                    err_ned_m: output_error(o, table, emu).map(|e| e as f32),
                    sigma_h_m: sigma_h_m(&o.cov_pos_ned_m2) as f32,
                    vel_err_h_m_s: v[0].hypot(v[1]) as f32,
                    yaw_err_deg: output_yaw_error_deg(o, table, emu) as f32,
                    euler_err_deg: output_euler_error_deg(o, table, emu) as f32,
                },
                match o.health {
                    Health::Ok => "ok",
                    Health::Degraded => "degraded",
                    Health::Lost => "lost",
                },
            )
        }
        None => (OutputSample::NONE, "uninitialised"),
    }
}

fn hnorm(e: &[f64; 3]) -> f64 {
    e[0].hypot(e[1])
}

/// The scenario's daemon configuration (`[closed_loop] config`) with `map_ortho` and
/// `map_upsample` applied, and the configuration file's path.
pub(crate) fn scenario_config(
    cl: &ClosedLoopConfig,
    base: &Path,
) -> Result<(Config, PathBuf), ClosedLoopError> {
    let setup_err = ClosedLoopError::Setup;
    let cfg_path = visnav_core::validate::resolve(base, &cl.config);
    let mut cfg =
        Config::load(&cfg_path).map_err(|e| setup_err(format!("[closed_loop] config: {e}")))?;
    if !cl.map_ortho.is_empty() {
        if let Some(f) = &cfg.map.file {
            return Err(setup_err(format!(
                "[closed_loop] map_ortho replaces [map] ortho, but {} uses the map file {}: remove one",
                cfg_path.display(),
                f.display()
            )));
        }
        for p in &cl.map_ortho {
            let p = visnav_core::validate::resolve(base, p);
            if !p.is_file() {
                return Err(setup_err(format!(
                    "[closed_loop] map_ortho {}: no such file",
                    p.display()
                )));
            }
        }
        cfg.map.ortho = cl
            .map_ortho
            .iter()
            .map(|p| visnav_core::validate::resolve(base, p))
            .collect();
    }
    if let Some(n) = cl.map_upsample {
        if let Some(f) = &cfg.map.file {
            return Err(setup_err(format!(
                "[closed_loop] map_upsample applies to a map built from ortho, but {} uses the map file {}: remove one",
                cfg_path.display(),
                f.display()
            )));
        }
        // The value (1, 2 or 4) is checked by `Scenario::parse`.
        cfg.map.upsample = Some(n);
    }
    Ok((cfg, cfg_path))
}

/// The simulated camera of a scenario: the camera-year scene, the renderer of the configured
/// camera, the scene's CRS, the mount, and the track plot's background.
pub(crate) struct CameraRig {
    pub scene: Arc<Scene>,
    pub renderer: Arc<Renderer>,
    pub crs: visnav_core::geo::Crs,
    pub mount: visnav_core::camera::Mount,
    pub background: Option<(image::RgbImage, [f64; 4])>,
}

/// The scenario's [`CameraRig`] (`[closed_loop] camera_ortho`, `camera_dem` or
/// `camera_ground_height_amsl_m`, `[closed_loop.render]`, the configuration's `[camera]`).
pub(crate) fn camera_rig(
    cl: &ClosedLoopConfig,
    base: &Path,
    cfg: &Config,
    cfg_path: &Path,
) -> Result<CameraRig, ClosedLoopError> {
    let setup_err = ClosedLoopError::Setup;
    let cam_ortho = visnav_core::validate::resolve(base, &cl.camera_ortho);
    // Two differently degraded copies of one image are two images (the scenario checks that
    // the two specs differ).
    let own_copies = cl.map_degrade.is_some() && cl.camera_degrade.is_some();
    if !own_copies && cfg.map.ortho.iter().any(|m| same_file(m, &cam_ortho)) {
        return Err(setup_err(format!(
            "[closed_loop] camera_ortho {} is also a map orthophoto of {}: render the camera from another year",
            cam_ortho.display(),
            cfg_path.display()
        )));
    }
    // Scene of the camera year.
    let raster = load_geotiff(&cam_ortho, cfg.map.crs_override).map_err(|e| {
        setup_err(format!(
            "[closed_loop] camera_ortho {}: {e}",
            cam_ortho.display()
        ))
    })?;
    let dem = match (&cl.camera_dem, cl.camera_ground_height_amsl_m) {
        (Some(p), _) => {
            let p = visnav_core::validate::resolve(base, p);
            visnav_io::geo::dem::load_dem(&p, cfg.map.crs_override)
                .map_err(|e| setup_err(format!("[closed_loop] camera_dem {}: {e}", p.display())))?
        }
        (None, Some(h)) => Dem::flat(h)
            .map_err(|e| setup_err(format!("[closed_loop] camera_ground_height_amsl_m: {e}")))?,
        (None, None) => {
            return Err(setup_err(
                "[closed_loop]: give camera_dem or camera_ground_height_amsl_m".into(),
            ));
        }
    };
    let raster = match &cl.camera_degrade {
        None => raster,
        Some(spec) => degrade(&raster, Some(&dem), spec).map_err(|e| {
            setup_err(format!(
                "[closed_loop] camera_degrade of {}: {e}",
                cam_ortho.display()
            ))
        })?,
    };
    let crs = raster.crs();
    let background = background_of(&raster, 1600);
    let mut scene = Scene::new(&raster, dem, ColourMode::Grey)
        .map_err(|e| setup_err(format!("camera scene: {e}")))?;
    if let Some([cols, rows]) = cl.mosaic {
        scene = scene.mirror_tiled(cols, rows);
    }
    let scene = Arc::new(scene);
    let camera = cfg
        .camera
        .build()
        .map_err(|e| setup_err(format!("{} [camera]: {e}", cfg_path.display())))?;
    let mount = camera.mount;
    let renderer = Arc::new(
        Renderer::new(camera, cl.render)
            .map_err(|e| setup_err(format!("[closed_loop.render]: {e}")))?,
    );
    Ok(CameraRig {
        scene,
        renderer,
        crs,
        mount,
        background,
    })
}

/// The map's degraded copies (`[closed_loop] map_degrade`): each map orthophoto of `cfg` degraded
/// (with the map's DEM as the surface its shadows fall on) and written to a temporary folder,
/// `cfg.map.ortho` then naming the copies. The folder lives as long as the returned guard: the
/// map build reads the copies.
fn degraded_map_copies(
    cl: &ClosedLoopConfig,
    cfg: &mut Config,
) -> Result<Option<tempfile::TempDir>, ClosedLoopError> {
    let setup_err = ClosedLoopError::Setup;
    let Some(spec) = &cl.map_degrade else {
        return Ok(None);
    };
    let surface = match &cfg.map.dem {
        Some(p) => Some(
            visnav_io::geo::dem::load_dem(p, cfg.map.crs_override)
                .map_err(|e| setup_err(format!("[map] dem {}: {e}", p.display())))?,
        ),
        None => None,
    };
    let dir = tempfile::tempdir()
        .map_err(|e| setup_err(format!("a temporary folder for the map's copies: {e}")))?;
    let mut copies = Vec::new();
    for (i, p) in cfg.map.ortho.iter().enumerate() {
        let what = |e: &dyn std::fmt::Display| {
            setup_err(format!("[closed_loop] map_degrade of {}: {e}", p.display()))
        };
        let raster = load_geotiff(p, cfg.map.crs_override).map_err(|e| what(&e))?;
        let copy = degrade(&raster, surface.as_ref(), spec).map_err(|e| what(&e))?;
        let out = dir.path().join(format!("map_copy_{i}.tif"));
        write_geotiff(&copy, &out).map_err(|e| what(&e))?;
        copies.push(out);
    }
    cfg.map.ortho = copies;
    Ok(Some(dir))
}

/// The map's mosaic and tiled build (`[closed_loop] mosaic`, `map_tile_m`): each map
/// orthophoto of `cfg` repeated into the mosaic and written to a temporary folder; with
/// `map_tile_m`, a tiled map built there from them and `cfg.map.file` naming it (the ortho list
/// emptied). The folder lives as long as the returned guard; with a tiled map, its area (km²)
/// and tile count.
fn mosaic_and_tiles(
    cl: &ClosedLoopConfig,
    cfg: &mut Config,
) -> Result<(Option<tempfile::TempDir>, Option<TiledMapBuilt>), ClosedLoopError> {
    let setup_err = ClosedLoopError::Setup;
    if cl.mosaic.is_none() && cl.map_tile_m.is_none() {
        return Ok((None, None));
    }
    let dir = tempfile::tempdir()
        .map_err(|e| setup_err(format!("a temporary folder for the map's mosaic: {e}")))?;
    if let Some([cols, rows]) = cl.mosaic {
        let mut copies = Vec::new();
        for (i, p) in cfg.map.ortho.iter().enumerate() {
            let what = |e: &dyn std::fmt::Display| {
                setup_err(format!("[closed_loop] mosaic of {}: {e}", p.display()))
            };
            let raster = load_geotiff(p, cfg.map.crs_override).map_err(|e| what(&e))?;
            let mosaic = mirror_mosaic(&raster, cols, rows).map_err(|e| what(&e))?;
            let out = dir.path().join(format!("map_mosaic_{i}.tif"));
            write_geotiff(&mosaic, &out).map_err(|e| what(&e))?;
            copies.push(out);
        }
        cfg.map.ortho = copies;
    }
    let Some(tile_m) = cl.map_tile_m else {
        return Ok((Some(dir), None));
    };
    let spec = cfg.map.build_spec().ok_or_else(|| {
        setup_err("[closed_loop] map_tile_m: the configuration's [map] names no terrain".into())
    })?;
    let out = dir.path().join("tiled");
    let t0 = std::time::Instant::now();
    let built = visnav_io::map::tiled::build_tiled(&spec, tile_m, &out, None, &mut |_| {})
        .map_err(|e| {
            setup_err(format!(
                "[closed_loop] map_tile_m: building the tiled map: {e}"
            ))
        })?;
    let ix = &built.index;
    info!(
        tiles = ix.tiles.len(),
        features = ix.total_features(),
        mb = ix.total_bytes() as f64 / 1e6,
        seconds = t0.elapsed().as_secs_f64(),
        "tiled map built"
    );
    let area_km2 = ix.tiles_area_km2();
    cfg.map.file = Some(out);
    if ix.tiles.iter().all(|t| t.heights.is_some()) {
        // The tiles carry the DEM's heights: the flight pages them, as the daemon would.
        cfg.map.dem = None;
    }
    cfg.map.ortho.clear();
    cfg.map.upsample = None;
    cfg.map.height_sigma_m = None;
    cfg.map.height_slope_sigma = None;
    cfg.map.height_point_sigma_m = None;
    let tiles = ix.tiles.len();
    Ok((Some(dir), Some(TiledMapBuilt { area_km2, tiles })))
}

/// The tiled map `mosaic_and_tiles` built.
#[derive(Clone, Copy)]
struct TiledMapBuilt {
    area_km2: f64,
    tiles: usize,
}

/// `raster` repeated `cols x rows` times east and south of its place, every other copy mirrored
/// (as `render::OrthoPyramid::mirror_tiled` renders the camera's); its RGB bands (or its first).
fn mirror_mosaic(
    raster: &visnav_core::geo::raster::Raster,
    cols: usize,
    rows: usize,
) -> Result<visnav_core::geo::raster::Raster, MosaicError> {
    use visnav_core::geo::raster::{Raster, RasterData};
    let (w, h, b) = (raster.width(), raster.height(), raster.bands());
    // The bands the map reads (RGB of an RGB + NIR photo; the grey band), as the writer takes.
    let kept = if b >= 3 { 3 } else { 1 };
    let (mw, mh) = (w * cols, h * rows);
    let fold = |v: usize, n: usize| {
        let p = v % (2 * n);
        if p < n { p } else { 2 * n - 1 - p }
    };
    let RasterData::U8(src) = raster.data() else {
        return Err(MosaicError::NotEightBit);
    };
    let mut data = Vec::with_capacity(mw * mh * kept);
    for y in 0..mh {
        let sy = fold(y, h);
        for x in 0..mw {
            let s = (sy * w + fold(x, w)) * b;
            data.extend_from_slice(&src[s..s + kept]);
        }
    }
    Raster::new(
        mw,
        mh,
        kept,
        RasterData::U8(data),
        *raster.transform(),
        raster.crs(),
        raster.nodata(),
    )
    .map_err(MosaicError::Raster)
}

/// Why an orthophoto could not be repeated into a mosaic.
#[derive(Debug, thiserror::Error)]
pub enum MosaicError {
    /// Only 8-bit imagery is repeated.
    #[error("a mosaic needs 8-bit imagery")]
    NotEightBit,
    /// The mosaic's raster could not be made (its size).
    #[error("{0}")]
    Raster(visnav_core::geo::raster::RasterError),
}

/// The camera world of a scenario's `[closed_loop]` for a real autopilot's SITL (`visnav
/// sitl-run --scenario`): the scene, renderer, CRS and mount `camera_rig` builds (the camera
/// orthophoto on `camera_dem`, `camera_degrade` applied, `[closed_loop.render]`'s light, blur and
/// noise), and `cfg`'s map orthophotos replaced by their `map_degrade` copies. The returned
/// folder holds the copies: keep it until the map is built.
pub struct ScenarioCamera {
    /// The camera-year orthophoto on its terrain.
    pub scene: Arc<Scene>,
    /// The renderer of the configured camera.
    pub renderer: Arc<Renderer>,
    /// The scene's CRS.
    pub crs: visnav_core::geo::Crs,
    /// The camera's mount on the vehicle (lever arm, rotation).
    pub mount: visnav_core::camera::Mount,
    /// The folder of the map's degraded copies (None without `map_degrade`).
    pub map_copies: Option<tempfile::TempDir>,
}

/// [`ScenarioCamera`] of `sc` (its file's folder `base`) for the configuration `cfg` read from
/// `cfg_path` (the run's own, not necessarily the scenario's `config`).
pub fn scenario_camera(
    sc: &Scenario,
    base: &Path,
    cfg: &mut Config,
    cfg_path: &Path,
) -> Result<ScenarioCamera, ClosedLoopError> {
    let cl = sc
        .closed_loop
        .as_ref()
        .ok_or(ClosedLoopError::NotClosedLoop)?;
    let rig = camera_rig(cl, base, cfg, cfg_path)?;
    let map_copies = degraded_map_copies(cl, cfg)?;
    Ok(ScenarioCamera {
        scene: rig.scene,
        renderer: rig.renderer,
        crs: rig.crs,
        mount: rig.mount,
        map_copies,
    })
}

/// Runs the scenario's closed loop. `base` is the scenario file's folder (for its paths).
pub async fn run(
    sc: &Scenario,
    base: &Path,
    logs: Option<&Path>,
) -> Result<ClosedLoopRun, ClosedLoopError> {
    // Never stopped early: the sender lives until the run ends.
    let (_keep, stop) = tokio::sync::watch::channel(false);
    run_until_stopped(sc, base, logs, stop).await
}

/// [`run`], ended early when `stop` turns true (a Ctrl-C): the flight so far is scored and
/// reported as usual, with `interrupted_at_s` in the summary.
pub async fn run_until_stopped(
    sc: &Scenario,
    base: &Path,
    logs: Option<&Path>,
    stop: tokio::sync::watch::Receiver<bool>,
) -> Result<ClosedLoopRun, ClosedLoopError> {
    let cl = sc
        .closed_loop
        .as_ref()
        .ok_or(ClosedLoopError::NotClosedLoop)?;
    let (mut cfg, cfg_path) = scenario_config(cl, base)?;
    let CameraRig {
        scene,
        renderer,
        crs,
        mount,
        background,
    } = camera_rig(cl, base, &cfg, &cfg_path)?;
    let setup_err = ClosedLoopError::Setup;
    let copies = degraded_map_copies(cl, &mut cfg)?;
    // The tiled map is read while the aircraft flies: its folder lives to the end of the run.
    let (_tiled_map, tiled) = mosaic_and_tiles(cl, &mut cfg)?;
    info!(
        "building the vision fix engine (map) from {}",
        cfg_path.display()
    );
    let engine = visnav_daemon::wiring::fixer_from_config_with(&cfg, cl.tile_loading())
        .map_err(|e| setup_err(format!("{}: vision fix engine: {e}", cfg_path.display())))?;
    drop(copies);
    let table =
        Arc::new(TruthTable::from_scenario(sc).map_err(|e| setup_err(format!("truth: {e}")))?);
    let duration_s = sc.duration_s();
    // Lock-step runs are reproducible to the bit: their UTC starts at a fixed instant.
    let unix_now_us = if cl.lockstep {
        Some(LOCKSTEP_UNIX_START_US)
    } else {
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_micros() as u64)
            .ok()
    };

    // Emulators and daemons: vision, then the control.
    let mk_setup = |port: u16| {
        let mut s = DaemonSetup::from_config(&cfg);
        s.link.connection = format!("udpin:127.0.0.1:{port}");
        s.nav = sc
            .nav
            .clone()
            .with_camera_lever_arm(mount.lever_arm_body_frd_m.into());
        s.frames = None;
        s
    };
    let start_emu = |port: u16| {
        let sensors = Arc::new(SimSensors::new(sc, table.clone()));
        let mut ecfg = EmulatorConfig::new(&format!("udpout:127.0.0.1:{port}"));
        ecfg.gps_fix = true;
        ecfg.gps_velocity = cl.gps_velocity;
        ecfg.unix_at_boot_us = unix_now_us;
        (ecfg, sensors)
    };
    let port_v = free_udp_port()?;
    let (ecfg_v, sens_v) = start_emu(port_v);
    let local_frame = ecfg_v.local_frame();
    let port_c = free_udp_port()?;
    let (ecfg_c, sens_c) = start_emu(port_c);
    let emu_v = Arc::new(
        AutopilotEmulator::start(ecfg_v, SensorsHandle(sens_v.clone()))
            .await
            .map_err(|e| setup_err(format!("emulator: {e}")))?,
    );
    let emu_c = if cl.control {
        Some(Arc::new(
            AutopilotEmulator::start(ecfg_c, SensorsHandle(sens_c.clone()))
                .await
                .map_err(|e| setup_err(format!("control emulator: {e}")))?,
        ))
    } else {
        None
    };
    let fixer = Arc::new(RecordingFixer {
        inner: engine,
        emu: emu_v.clone(),
        table: table.clone(),
        mount,
        log: Mutex::new(resident_vec(
            expected_count::<FixRow>(duration_s, cl.camera_rate_hz),
            FixRow::FILL,
        )),
        dtm_log: Arc::new(Mutex::new(Vec::new())),
        delivery_us: if cl.lockstep {
            (cl.lockstep_fix_latency_s.max(0.0) * 1e6) as u64
        } else {
            0
        },
        faults: FaultPlan::new(sc.faults.clone()),
        rss: Mutex::new(RssProbe::default()),
    });
    let end_us = (duration_s * 1e6) as u64;
    let mut cam = SimCamera::new(
        SimCameraSpec {
            scene: scene.clone(),
            renderer: renderer.clone(),
            crs,
            mount,
            rate_hz: cl.camera_rate_hz,
            max_frames: None,
            lockstep: cl.lockstep,
        },
        Arc::new(EmuFeed {
            emu: emu_v.clone(),
            table: table.clone(),
            from_us: (cl.camera_from_s * 1e6) as u64,
            until_us: end_us,
            faults: FaultPlan::new(sc.faults.clone()),
        }),
    );
    // With VO on and a log folder: the vision daemon's VO log and the camera's true poses
    // (`sitl/vo_check.py` scores them; the module doc).
    let vo_on = cl.vo.as_ref().map_or(cfg.vo.enabled, |v| v.enabled);
    let vo_log = match logs {
        Some(dir) if vo_on => {
            let truth = dir.join(FRAMES_TRUTH_FILE);
            let f = std::fs::File::create(&truth)
                .map_err(|e| setup_err(format!("{}: {e}", truth.display())))?;
            cam = cam.with_truth_log(Box::new(std::io::BufWriter::new(f)));
            Some(dir.join(VO_LOG_FILE))
        }
        _ => None,
    };
    let camera_desc = {
        use visnav_io::frames::FrameSource;
        cam.describe()
    };
    let pipeline = FramePipeline {
        source: Box::new(cam),
        lossless: false,
        max_age_s: cl.frame_max_age_s,
        workers: cl.workers,
        lockstep_latency: cl
            .lockstep
            .then(|| Duration::from_secs_f64(cl.lockstep_fix_latency_s.max(0.0))),
        release: visnav_daemon::frames::Release::AsRead,
    };
    // Visual odometry: the scenario's `[closed_loop.vo]` for the vision run (the control has no
    // camera).
    let setup_v = {
        let mut s = mk_setup(port_v);
        if let Some(vo) = &cl.vo {
            s.vo = vo.clone();
        }
        s.daemon.vo_log = vo_log;
        s
    };
    // Each daemon's log lines carry its run's name (`vision:` / `control:`): its tasks and
    // threads run in the span it was started in.
    let d_v = Daemon::start_with(setup_v, Some(fixer.clone()), Some(pipeline))
        .instrument(tracing::info_span!("vision"))
        .await?;
    let d_c = match &emu_c {
        Some(_) => Some(
            Daemon::start_with(mk_setup(port_c), None, None)
                .instrument(tracing::info_span!("control"))
                .await?,
        ),
        None => None,
    };
    let plan = FaultPlan::new(sc.faults.clone());
    let _spoofer = plan.has(FaultKind::SpoofedHeartbeat).then(|| {
        let emu = emu_v.clone();
        let to = std::net::SocketAddr::from(([127, 0, 0, 1], port_v));
        AbortOnDrop(tokio::spawn(async move {
            if let Err(e) =
                spoof_heartbeats(to, plan, move || emu.time_run_us() as f64 * 1e-6).await
            {
                warn!("scripted spoofer: {e}");
            }
        }))
    });
    info!(
        "closed loop running: {duration_s:.0} s of scenario time ({}), vision on udp {port_v}, control on udp {port_c}",
        if cl.lockstep {
            "lock-step"
        } else {
            "real time"
        }
    );

    // Sample at 10 Hz until the scenario's end; the emulators' received messages are folded into
    // compact injections as they come (`recording`).
    // The recordings are reserved for the whole run up front and made resident
    // (`recording::resident_vec`): the resident memory then grows with what is being tested,
    // not with the simulator's notes (an hour's: 4 MB over the last 50 minutes), and no
    // doubling leaves old buffers behind in the allocator.
    let mut steps = resident_vec(
        expected_count::<StepSample>(duration_s, 10.0),
        StepSample::FILL,
    );
    let injections_hz = cfg.output.rate_hz * cfg.output.modes.len() as f64;
    let mut collect_v = InjectionCollector::new(
        false,
        expected_count::<recording::InjectionSample>(duration_s, injections_hz),
        local_frame,
    );
    let mut collect_c = InjectionCollector::new(
        true,
        if emu_c.is_some() {
            expected_count::<recording::InjectionSample>(duration_s, injections_hz)
        } else {
            0
        },
        local_frame,
    );
    let out_v = d_v.nav_outputs();
    let out_c = d_c.as_ref().map(|d| d.nav_outputs());
    let mut tick = tokio::time::interval(Duration::from_millis(100));
    let mut last_log_s = 0.0;
    let mut memory_after_first_window = None;
    let emu_ctl = emu_c.as_deref().unwrap_or(&emu_v);
    let mut interrupted_at_s = None;
    loop {
        tick.tick().await;
        collect_v.take(emu_v.take_received(), &table);
        if let Some(e) = &emu_c {
            collect_c.take(e.take_received(), &table);
        }
        let t_run_us = emu_v.time_run_us();
        let t_s = t_run_us as f64 * 1e-6;
        if memory_after_first_window.is_none() && t_s >= sc.evaluation.from_s + SOAK_WINDOW_S {
            memory_after_first_window =
                Some(memory_sample(&steps, &fixer.log, [&collect_v, &collect_c]));
        }
        if t_s > duration_s {
            break;
        }
        if *stop.borrow() {
            info!("interrupted at t = {t_s:.1} s: scoring and reporting the flight so far");
            interrupted_at_s = Some(t_s);
            break;
        }
        let t_ms = u32::try_from(t_run_us / 1000).unwrap_or(u32::MAX);
        let s = table.at(f64::from(t_ms) * 1e-3);
        let ov = out_v.borrow().clone();
        let oc = out_c.as_ref().and_then(|o| o.borrow().clone());
        let (vis, vh) = sample_output(ov.as_ref(), &s, &table, &emu_v);
        let (ctl, ch) = sample_output(oc.as_ref(), &s, &table, emu_ctl);
        if t_s - last_log_s >= 10.0 {
            last_log_s = t_s;
            let (attempts, accepted) = fixer
                .log
                .lock()
                .map(|l| (l.len(), l.iter().filter(|f| f.accepted).count()))
                .unwrap_or((0, 0));
            info!(
                "t = {t_s:5.1} s  gps {}  vision: err {:.1} m ({vh})  control: err {:.1} m ({ch})  fixes accepted {accepted} of {attempts} attempts",
                if sens_v.gps_on(t_s) { "on " } else { "off" },
                f32::hypot(vis.err_ned_m[0], vis.err_ned_m[1]),
                f32::hypot(ctl.err_ned_m[0], ctl.err_ned_m[1]),
            );
        }
        steps.push(StepSample {
            t_ms,
            gps_on: sens_v.gps_on(t_s),
            vis_health: health_code(vh),
            ctl_health: health_code(ch),
            vis,
            ctl,
        });
    }
    // The flight's end, before the daemons stop and the scoring allocates.
    let memory_end = memory_sample(&steps, &fixer.log, [&collect_v, &collect_c]);
    // A tiled map's counters and the memory's course, at the flight's end.
    let paging_end = fixer.paging().map(|stats| PagingEnd {
        stats,
        rss_every: fixer.rss.lock().map_or(Vec::new(), |p| p.every.clone()),
        rss_end: memory_end.rss_mb,
    });
    let link_v = d_v.link().metrics();
    let metrics_v = d_v.shutdown().await;
    if let Some(d) = d_c {
        d.shutdown().await;
    }
    collect_v.take(emu_v.take_received(), &table);
    if let Some(e) = &emu_c {
        collect_c.take(e.take_received(), &table);
    }

    // Score.
    let (w0, w1) = (sc.evaluation.from_s, sc.evaluation.until_s);
    let in_window = |t: f64| t >= w0 && t <= w1;
    let soak = w1 - w0 >= 2.0 * SOAK_WINDOW_S;
    let steps: Vec<StepRow> = steps.iter().map(|s| s.expand(&table)).collect();
    let injections: Vec<InjectionRow> = collect_v
        .samples
        .iter()
        .chain(&collect_c.samples)
        .map(|i| i.expand())
        .collect();
    let fixes: Vec<FixRow> = fixer
        .log
        .lock()
        .map(|mut l| std::mem::take(&mut *l))
        .unwrap_or_default();
    let wf: Vec<&FixRow> = fixes.iter().filter(|f| in_window(f.t_capture_s)).collect();
    let map_paging = paging_end.map(|end| {
        let seams = seam_fix_rate(&wf, cl.map_tile_m.unwrap_or(0.0), |t| {
            let (lat, lon, _) = truth_camera(&table, t, &mount);
            crs.from_geodetic(lat, lon).ok()
        });
        let memory_mb = cfg
            .map
            .memory_mb
            .unwrap_or(visnav_daemon::wiring::DEFAULT_MAP_MEMORY_MB);
        MapPagingSummary::new(end, tiled, memory_mb, seams)
    });
    let dtm_all: Vec<DtmRow> = fixer
        .dtm_log
        .lock()
        .map(|mut l| std::mem::take(&mut *l))
        .unwrap_or_default();
    let dtm_rows: Vec<&DtmRow> = dtm_all
        .iter()
        .filter(|r| in_window(r.t_capture_s))
        .collect();
    let accepted: Vec<&&FixRow> = wf.iter().filter(|f| f.accepted).collect();
    let fix_errs: Vec<f64> = accepted.iter().map(|f| hnorm(&f.err_ned_m)).collect();
    let lat: Vec<f64> = wf.iter().map(|f| f.latency_ms).collect();
    let mut tally = visnav_core::reasons::ReasonTally::default();
    for f in wf.iter().filter(|f| !f.accepted) {
        tally.add(f.class, &f.reason);
    }
    let rejections = tally.counts();
    // nav_err_m scores the first configured output message; every kind is in nav_err_by_message.
    let scored_kind = match cfg.output.modes.first() {
        Some(visnav_link::config::OutputMode::VisionPositionEstimate) => "vision_position_estimate",
        Some(visnav_link::config::OutputMode::Odometry) => "odometry",
        _ => "gps_input",
    };
    let mut nav_err_by_message = std::collections::BTreeMap::new();
    for kind in ["gps_input", "vision_position_estimate", "odometry"] {
        let e: Vec<f64> = injections
            .iter()
            .filter(|i| !i.control && i.kind == kind && in_window(i.t_s))
            .map(|i| hnorm(&i.err_ned_m))
            .collect();
        if !e.is_empty() {
            nav_err_by_message.insert(kind.to_string(), (e.len(), Stats::of(&e)));
        }
    }
    let inj_v: Vec<&InjectionRow> = injections
        .iter()
        .filter(|i| !i.control && i.kind == scored_kind && in_window(i.t_s))
        .collect();
    let inj_c: Vec<&InjectionRow> = injections
        .iter()
        .filter(|i| i.control && i.kind == scored_kind && in_window(i.t_s))
        .collect();
    let ws: Vec<&StepRow> = steps.iter().filter(|s| in_window(s.t_s)).collect();
    let max_enu = |f: &dyn Fn(&StepRow) -> [f64; 3]| {
        let m = |k: usize| max_finite(ws.iter().map(|s| f(s)[k].abs()));
        Enu {
            e: m(1),
            n: m(0),
            u: m(2),
        }
    };
    // Horizontal error over the claimed sigma; NaN (no output yet) is left out, an error over a
    // zero sigma stays (infinite).
    let over_sigma = |f: &dyn Fn(&StepRow) -> ([f64; 3], f64)| {
        Stats::of(
            &ws.iter()
                .map(|s| {
                    let (e, sigma) = f(s);
                    hnorm(&e) / sigma
                })
                .filter(|r| !r.is_nan())
                .collect::<Vec<_>>(),
        )
    };
    let gps_outage_s = sc.gps.as_ref().map(|g| [g.until_s, duration_s]);
    let flight = FlightFigures::of(&steps);
    let agl: Vec<f64> = ws
        .iter()
        .filter_map(|s| {
            let (x, y) = crs.from_geodetic(s.truth_lat_deg, s.truth_lon_deg).ok()?;
            Some(s.truth_alt_amsl_m - scene.dem().height_at(x, y)?)
        })
        .collect();
    let agl_stats = Stats::of(&agl);
    let summary = ClosedLoopSummary {
        scenario: sc.name.clone(),
        description: sc.description.clone(),
        duration_s,
        interrupted_at_s,
        evaluation_window_s: [w0, w1],
        gps_outage_s,
        camera: camera_desc,
        agl_m: agl_stats.median,
        agl_range_m: [
            agl.iter().copied().fold(f64::INFINITY, f64::min),
            agl_stats.max,
        ],
        map_paging,
        fix_rate: if wf.is_empty() {
            0.0
        } else {
            accepted.len() as f64 / wf.len() as f64
        },
        frames_rendered: metrics_v.frames_in,
        fix_attempts: wf.len(),
        fixes_accepted: accepted.len(),
        frames_dropped: metrics_v.frames_superseded + metrics_v.frames_stale,
        fixes_filter_rejected: metrics_v.fixes_filter_rejected,
        vo: (metrics_v.vo.frames > 0).then(|| metrics_v.vo.clone()),
        dtm: (metrics_v.dtm.frames > 0).then(|| metrics_v.dtm.clone()),
        dtm_poses: (!dtm_rows.is_empty()).then(|| DtmScore::of(&dtm_rows)),
        fix_err_m: Stats::of(&fix_errs),
        fix_beyond_3sigma: accepted.iter().filter(|f| f.beyond_3sigma).count(),
        nav_err_m: Stats::of(
            &inj_v
                .iter()
                .map(|i| hnorm(&i.err_ned_m))
                .collect::<Vec<_>>(),
        ),
        nav_vert_err_m: Stats::of(
            &inj_v
                .iter()
                .map(|i| i.err_ned_m[2].abs())
                .collect::<Vec<_>>(),
        ),
        nav_output_err_m: Stats::of(
            &ws.iter()
                .map(|s| hnorm(&s.vis_err_ned_m))
                .collect::<Vec<_>>(),
        ),
        control_err_m: Stats::of(
            &ws.iter()
                .map(|s| hnorm(&s.ctl_err_ned_m))
                .collect::<Vec<_>>(),
        ),
        control_injected_err_m: Stats::of(
            &inj_c
                .iter()
                .map(|i| hnorm(&i.err_ned_m))
                .collect::<Vec<_>>(),
        ),
        nav_err_over_sigma: over_sigma(&|s| (s.vis_err_ned_m, s.vis_sigma_h_m)),
        control_err_over_sigma: over_sigma(&|s| (s.ctl_err_ned_m, s.ctl_sigma_h_m)),
        nav_sigma_h_m: Stats::of(&ws.iter().map(|s| s.vis_sigma_h_m).collect::<Vec<_>>()),
        control_sigma_h_m: Stats::of(&ws.iter().map(|s| s.ctl_sigma_h_m).collect::<Vec<_>>()),
        nav_vel_err_m_s: Stats::of(&ws.iter().map(|s| s.vis_vel_err_h_m_s).collect::<Vec<_>>()),
        control_vel_err_m_s: Stats::of(&ws.iter().map(|s| s.ctl_vel_err_h_m_s).collect::<Vec<_>>()),
        max_err_m: MaxErr {
            vision: max_enu(&|s| s.vis_err_ned_m),
            control: max_enu(&|s| s.ctl_err_ned_m),
            vision_3d: max_finite(ws.iter().map(|s| norm3(&s.vis_err_ned_m))),
            control_3d: max_finite(ws.iter().map(|s| norm3(&s.ctl_err_ned_m))),
        },
        max_euler_err_deg: MaxEuler {
            vision: max_finite(ws.iter().map(|s| s.vis_euler_err_deg)),
            control: max_finite(ws.iter().map(|s| s.ctl_euler_err_deg)),
        },
        latency_ms: Latency {
            p50: percentile(&lat, 0.5),
            p95: percentile(&lat, 0.95),
        },
        injections: inj_v.len(),
        injected_message: scored_kind.to_string(),
        nav_err_by_message,
        control_injections: inj_c.len(),
        rejections,
        fix_rate_first_window: soak
            .then(|| fix_rate_in(&wf, w0, w0 + SOAK_WINDOW_S))
            .flatten(),
        fix_rate_last_window: soak
            .then(|| fix_rate_in(&wf, w1 - SOAK_WINDOW_S, w1))
            .flatten(),
        rss_mb_after_first_window: memory_after_first_window.and_then(|m| m.rss_mb),
        rss_mb_end: memory_end.rss_mb,
        heap_mb_after_first_window: memory_after_first_window.and_then(|m| m.heap),
        heap_mb_end: memory_end.heap,
        heap_growth_mb_without_recordings: memory_after_first_window
            .and_then(|m| m.heap)
            .zip(memory_end.heap)
            .map(|(a, b)| (b.total_mb - b.recordings_mb) - (a.total_mb - a.recordings_mb)),
        faults: fault_outcomes(sc, &injections, scored_kind, &fixes),
        fault_counters: (!sc.faults.is_empty())
            .then(|| fault_counters(&collect_v, emu_v.companion(), &metrics_v, &link_v)),
        vision_final_health: steps
            .last()
            .map(|s| s.vis_health.to_string())
            .unwrap_or_default(),
        control_final_health: steps
            .last()
            .map(|s| s.ctl_health.to_string())
            .unwrap_or_default(),
        final_err_h_m: flight.final_err_h_m,
        control_final_err_h_m: flight.control_final_err_h_m,
        distance_flown_m: flight.distance_flown_m,
        yaw_err_deg_max: flight.yaw_err_deg_max,
        ctl_yaw_err_deg_max: flight.ctl_yaw_err_deg_max,

        report_dir: None,
    };
    if summary.injections == 0 {
        warn!("the vision daemon injected nothing in the evaluation window");
    }
    Ok(ClosedLoopRun {
        summary,
        steps,
        fixes,
        injections,
        dtm_poses: dtm_all,
        crs,
        background,
        gps_until_s: sc.gps.as_ref().map(|g| g.until_s),
    })
}

/// Score the scripted faults on the vision daemon's injections of the scored kind and its fixes.
fn fault_outcomes(
    sc: &Scenario,
    injections: &[InjectionRow],
    scored_kind: &str,
    fixes: &[FixRow],
) -> Vec<FaultOutcome> {
    if sc.faults.is_empty() {
        return Vec::new();
    }
    let outputs: Vec<ScoredOutput> = injections
        .iter()
        .filter(|i| !i.control && i.kind == scored_kind)
        .map(|i| ScoredOutput {
            t_s: i.t_s,
            err_h_m: hnorm(&i.err_ned_m),
            claimed_h_m: i.horiz_accuracy_m,
        })
        .collect();
    let fixes: Vec<ScoredFix> = fixes
        .iter()
        .map(|f| ScoredFix {
            t_capture_s: f.t_capture_s,
            accepted: f.accepted,
            beyond_3sigma: f.beyond_3sigma,
        })
        .collect();
    faults::outcomes(
        &FaultPlan::new(sc.faults.clone()),
        &outputs,
        &fixes,
        sc.duration_s(),
    )
}

/// The vision daemon's counters that the fault table names, and what the emulator received.
fn fault_counters(
    received: &InjectionCollector,
    companion: Option<(u8, u8)>,
    m: &visnav_daemon::metrics::MetricsSnapshot,
    link: &visnav_link::metrics::Metrics,
) -> FaultCounters {
    FaultCounters {
        autopilot_reboots: m.autopilot_reboots,
        relocks: link.relocks.get(),
        utc_steps: link.utc_steps.get(),
        rx_stale: link.rx_stale.get(),
        imu_timeouts: m.imu_timeouts,
        frames_frozen: m.frames_frozen,
        gps_input_time_backsteps: received.gps_time_backsteps,
        non_finite_injections: received.non_finite,
        foreign_injections: received.foreign(companion),
    }
}

/// A fix against the true camera position at its capture time (run times, µs).
/// The true camera centre at run time `t` s: body + R_ned_body lever arm (lat, lon deg, AMSL m).
fn truth_camera(table: &TruthTable, t: f64, mount: &visnav_core::camera::Mount) -> (f64, f64, f64) {
    let s = table.at(t);
    let att = visnav_core::camera::Attitude::new(s.rpy_rad[0], s.rpy_rad[1], s.rpy_rad[2]);
    let lever_ned = att.r_ned_body() * mount.lever_arm_body_frd_m;
    let (m_m, n_m) = radii_m(s.lat_deg);
    (
        s.lat_deg + (lever_ned.x / (m_m + s.alt_amsl_m)).to_degrees(),
        s.lon_deg
            + (lever_ned.y / ((n_m + s.alt_amsl_m) * s.lat_deg.to_radians().cos())).to_degrees(),
        s.alt_amsl_m - lever_ned.z,
    )
}

/// Whether a horizontal error `e` lies outside the 3-sigma ellipse of the covariance `c`.
fn beyond_3sigma_h(e: &[f64; 3], c: &[[f64; 3]; 3]) -> bool {
    let (a, b, cc) = (c[0][0], c[1][1], c[0][1]);
    let det = a * b - cc * cc;
    let d2 = if det > 0.0 {
        (b * e[0] * e[0] - 2.0 * cc * e[0] * e[1] + a * e[1] * e[1]) / det
    } else {
        f64::INFINITY
    };
    d2 > CHI2_2DOF_3SIGMA
}

/// A DTM pose (ellipsoidal height) against the truth at run time `t_run_us`; None when the
/// geoid cannot give its height above sea level.
fn score_dtm_pose(
    t_run_us: u64,
    pose: &visnav_core::dtm_nav::DtmPoseFix,
    t_first_s: f64,
    table: &TruthTable,
    mount: &visnav_core::camera::Mount,
) -> Option<DtmRow> {
    let fix = &pose.fix;
    let t = t_run_us as f64 * 1e-6;
    let p = &fix.position;
    let (lat, lon) = (p.lat_rad.to_degrees(), p.lon_rad.to_degrees());
    let n = visnav_core::geo::geoid::geoid_undulation_m(lat, lon).ok()?;
    let e = ned_diff_m(truth_camera(table, t, mount), (lat, lon, p.h_m - n));
    let c: [[f64; 3]; 3] = std::array::from_fn(|i| std::array::from_fn(|j| p.cov_ned_m2[(i, j)]));
    let (r, pi, y) = fix.q_nb.euler_angles();
    let truth = table.at(t).rpy_rad;
    let euler = [r, pi, y]
        .iter()
        .zip(truth)
        .map(|(est, tr)| wrap_pi(est - tr).to_degrees().abs())
        .fold(0.0, f64::max);
    Some(DtmRow {
        t_capture_s: t,
        t_first_s,
        baseline_m: pose.baseline_m,
        inliers: pose.inliers,
        err_ned_m: e,
        sigma_h_m: sigma_h_m(&c),
        beyond_3sigma: beyond_3sigma_h(&e, &c),
        euler_err_deg: euler,
    })
}

fn score_fix(
    t_capture_us: u64,
    t_done_us: u64,
    rep: &FixReport,
    table: &TruthTable,
    mount: &visnav_core::camera::Mount,
) -> FixRow {
    let t = t_capture_us as f64 * 1e-6;
    let cam = truth_camera(table, t, mount);
    let (err, sig, beyond) = if rep.accepted {
        let e = ned_diff_m(cam, (rep.lat_deg, rep.lon_deg, rep.alt_amsl_m));
        let c = &rep.cov_ned_m2;
        (e, sigma_h_m(c), beyond_3sigma_h(&e, c))
    } else {
        ([f64::NAN; 3], f64::NAN, false)
    };
    FixRow {
        t_capture_s: t,
        latency_ms: (t_done_us as f64 - t_capture_us as f64) * 1e-3,
        accepted: rep.accepted,
        reason: rep.reason(),
        class: rep.class(),
        lat_deg: rep.lat_deg,
        lon_deg: rep.lon_deg,
        err_ned_m: err,
        sigma_h_m: sig,
        beyond_3sigma: beyond,
        inliers: rep.inliers,
        ms: rep.ms,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scenario::Scenario;

    #[test]
    fn angle_interpolation_takes_the_short_arc() {
        let a = 179f64.to_radians();
        let b = -179f64.to_radians();
        let m = lerp_angle(a, b, 0.5).to_degrees();
        assert!((m.abs() - 180.0).abs() < 1e-9, "{m}");
        assert!((lerp_angle(0.1, 0.3, 0.5) - 0.2).abs() < 1e-12);
    }

    #[test]
    fn ned_difference_of_a_known_offset() {
        let (m_m, n_m) = radii_m(47.0);
        let a = (47.0, -97.0, 500.0);
        let b = (
            47.0 + (100.0 / (m_m + 500.0)).to_degrees(),
            -97.0 + (50.0 / ((n_m + 500.0) * 47f64.to_radians().cos())).to_degrees(),
            490.0,
        );
        let d = ned_diff_m(a, b);
        assert!(
            (d[0] - 100.0).abs() < 1e-6 && (d[1] - 50.0).abs() < 1e-6 && (d[2] - 10.0).abs() < 1e-9
        );
    }

    /// A step at `t_s` flying east at 25 m/s from 47 N, 99 W; both filters uninitialised.
    fn step(t_s: f64, gps_on: bool) -> StepRow {
        let (_, n_m) = radii_m(47.0);
        let de_deg = (25.0 * t_s / ((n_m + 600.0) * 47f64.to_radians().cos())).to_degrees();
        StepRow {
            t_s,
            gps_on,
            truth_lat_deg: 47.0,
            truth_lon_deg: -99.0 + de_deg,
            truth_alt_amsl_m: 600.0,
            vis_lat_deg: f64::NAN,
            vis_lon_deg: f64::NAN,
            vis_err_ned_m: [f64::NAN; 3],
            vis_sigma_h_m: f64::NAN,
            vis_health: "uninitialised",
            ctl_lat_deg: f64::NAN,
            ctl_lon_deg: f64::NAN,
            ctl_err_ned_m: [f64::NAN; 3],
            ctl_sigma_h_m: f64::NAN,
            ctl_health: "uninitialised",
            vis_vel_err_h_m_s: f64::NAN,
            ctl_vel_err_h_m_s: f64::NAN,
            vis_yaw_err_deg: f64::NAN,
            ctl_yaw_err_deg: f64::NAN,
            vis_euler_err_deg: f64::NAN,
            ctl_euler_err_deg: f64::NAN,
        }
    }

    #[test]
    fn heading_errors_wrap_at_180_degrees() {
        assert!((yaw_err_deg(-179.0, 179f64.to_radians()) - 2.0).abs() < 1e-9);
        assert!((yaw_err_deg(179.0, (-179f64).to_radians()) + 2.0).abs() < 1e-9);
        assert!((yaw_err_deg(10.0, 350f64.to_radians()) - 20.0).abs() < 1e-9);
        assert!((wrap_deg(358.0) + 2.0).abs() < 1e-9);
        assert!((wrap_deg(-180.0) + 180.0).abs() < 1e-9);
    }

    #[test]
    fn flight_figures_from_synthetic_steps() {
        // 0-10 s with GPS, 10-20 s without; the vision filter from 1 s, its output lost (but
        // initialised) at the end; the control initialised from 2 s, uninitialised again (a
        // restart) for the last second.
        let mut steps: Vec<StepRow> = (0..=200)
            .map(|i| step(f64::from(i) * 0.1, i < 100))
            .collect();
        for (i, s) in steps.iter_mut().enumerate() {
            if i >= 10 {
                s.vis_health = if i == 200 { "lost" } else { "ok" };
                s.vis_err_ned_m = [3.0, 4.0, 100.0];
                s.vis_yaw_err_deg = 1.0;
            }
            if (20..190).contains(&i) {
                s.ctl_health = "degraded";
                // 5 m at the last initialised step (189), more before it.
                s.ctl_err_ned_m = [0.0, 23.9 - i as f64 * 0.1, 0.0];
                s.ctl_yaw_err_deg = -3.0;
            }
        }
        steps[200].vis_err_ned_m = [6.0, -8.0, 0.0];
        // Across +-180 deg: 358 and -357 deg are 2 and 3 deg off; before the loss, never counted.
        steps[150].vis_yaw_err_deg = 358.0;
        steps[160].vis_yaw_err_deg = -357.0;
        steps[50].vis_yaw_err_deg = 90.0;
        steps[120].ctl_yaw_err_deg = 179.5;
        let f = FlightFigures::of(&steps);
        assert_eq!(f.final_err_h_m, Some(10.0));
        assert!(
            (f.control_final_err_h_m.unwrap_or(f64::NAN) - 5.0).abs() < 1e-9,
            "{f:?}"
        );
        // From the loss at 10 s to 20 s at 25 m/s.
        assert!((f.distance_flown_m - 250.0).abs() < 0.01, "{f:?}");
        assert!(
            (f.yaw_err_deg_max.unwrap_or(f64::NAN) - 3.0).abs() < 1e-9,
            "{f:?}"
        );
        assert!(
            (f.ctl_yaw_err_deg_max.unwrap_or(f64::NAN) - 179.5).abs() < 1e-9,
            "{f:?}"
        );

        // A GPS that never goes off: no distance, no heading error after a loss.
        let always: Vec<StepRow> = steps
            .iter()
            .map(|s| StepRow {
                gps_on: true,
                ..s.clone()
            })
            .collect();
        let f = FlightFigures::of(&always);
        assert_eq!((f.distance_flown_m, f.yaw_err_deg_max), (0.0, None));
        assert_eq!(f.final_err_h_m, Some(10.0));
        // A GPS that comes on late: the loss is its end, not the first step.
        steps[..5].iter_mut().for_each(|s| s.gps_on = false);
        assert!((FlightFigures::of(&steps).distance_flown_m - 250.0).abs() < 0.01);
        // Never a fix: the whole flight counts. Nothing initialised: no errors.
        let none: Vec<StepRow> = (0..=40).map(|i| step(f64::from(i) * 0.1, false)).collect();
        let f = FlightFigures::of(&none);
        assert!((f.distance_flown_m - 100.0).abs() < 0.01, "{f:?}");
        assert_eq!((f.final_err_h_m, f.control_final_err_h_m), (None, None));
        assert_eq!((f.yaw_err_deg_max, f.ctl_yaw_err_deg_max), (None, None));
        assert_eq!(FlightFigures::of(&[]).distance_flown_m, 0.0);
    }

    #[test]
    fn horizontal_sigma_is_the_major_semi_axis() {
        let c = [[9.0, 0.0, 0.0], [0.0, 4.0, 0.0], [0.0, 0.0, 1.0]];
        assert!((sigma_h_m(&c) - 3.0).abs() < 1e-12);
        let c = [[5.0, 4.0, 0.0], [4.0, 5.0, 0.0], [0.0, 0.0, 1.0]];
        assert!((sigma_h_m(&c) - 3.0).abs() < 1e-12);
    }

    const SCENARIO: &str = r#"
name = "gps_latency"
seed = 3
[start]
lat_deg = 47.0
lon_deg = -99.3
height_m = 2000.0
speed_m_s = 50.0
heading_deg = 90.0
[[segments]]
kind = "straight"
duration_s = 20.0
[imu]
rate_hz = 100.0
[attitude]
rate_hz = 10.0
sigma_tilt_deg = 0.5
sigma_yaw_deg = 2.0
[evaluation]
from_s = 0.0
until_s = 20.0
[gps]
rate_hz = 5.0
until_s = 20.0
sigma_h_m = 0.001
sigma_v_m = 0.001
sigma_vel_m_s = 0.001
"#;

    /// Along-track distance (east) of the reported fix from the truth at its time stamp, m.
    fn lag_m(latency: Option<f64>) -> f64 {
        let mut text = SCENARIO.to_string();
        if let Some(l) = latency {
            text.push_str(&format!("latency_s = {l}\n"));
        }
        let sc = Scenario::parse(&text, "gps_latency.toml").unwrap();
        let table = Arc::new(TruthTable::from_scenario(&sc).unwrap());
        let h = SensorsHandle(Arc::new(SimSensors::new(&sc, table.clone())));
        let fix = h.gps(10.0).unwrap();
        let truth = table.at(10.0);
        let d = ned_diff_m(
            (fix.lat_deg, fix.lon_deg, fix.alt_amsl_m),
            (truth.lat_deg, truth.lon_deg, truth.alt_amsl_m),
        );
        assert!(d[0].abs() < 0.05, "{d:?}");
        d[1]
    }

    /// The test scenario with a `[closed_loop]` section carrying `extra` lines.
    fn closed_loop_scenario(extra: &str) -> Scenario {
        let text = format!(
            "{SCENARIO}[closed_loop]\nconfig = \"c.toml\"\ncamera_ortho = \"o.tif\"\ncamera_ground_height_amsl_m = 580.0\n{extra}"
        );
        Scenario::parse(&text, "rates.toml").unwrap()
    }

    #[test]
    fn attitude_rates_carry_the_ahrs_rate_error_only_when_asked() {
        let run = |extra: &str| {
            let sc = closed_loop_scenario(extra);
            let table = Arc::new(TruthTable::from_scenario(&sc).unwrap());
            let sens = Arc::new(SimSensors::new(&sc, table));
            let h = SensorsHandle(sens.clone());
            let mut out = Vec::new();
            for i in 0..1500 {
                let t = 0.01 * f64::from(i);
                let (gyro, _) = h.imu(t);
                let rates = h.attitude_rates(t);
                out.push((t, gyro, rates, sens.ahrs_rate_error_rad_s(t)));
            }
            out
        };
        // Default: ATTITUDE's rates are the simulated gyro itself.
        for (_, gyro, rates, e) in run("") {
            assert_eq!(gyro, rates);
            assert_eq!(e, [0.0; 3]);
        }
        // With the error: gyro + the Gauss-Markov error, the same for the same seed.
        let a = run("ahrs_rate_error_deg_h = 60.0\nahrs_rate_corr_time_s = 60.0\n");
        let b = run("ahrs_rate_error_deg_h = 60.0\nahrs_rate_corr_time_s = 60.0\n");
        let mut largest = 0.0f64;
        for ((t, gyro, rates, e), (_, gyro_b, rates_b, _)) in a.iter().zip(&b) {
            for k in 0..3 {
                assert!((rates[k] - gyro[k] - e[k]).abs() < 1e-15, "t {t}");
                largest = largest.max(e[k].abs());
            }
            assert_eq!((gyro, rates), (gyro_b, rates_b), "t {t}: not reproducible");
        }
        let deg_h = largest.to_degrees() * 3600.0;
        assert!(deg_h > 5.0 && deg_h < 300.0, "{deg_h} deg/h");
    }

    #[test]
    fn the_gauss_markov_series_has_its_sigma_and_correlation_time() {
        let s = 1e-4;
        let x = gauss_markov_1hz(7, [s; 3], 60.0, 400_000);
        for k in 0..3 {
            let rms = (x.iter().map(|v| v[k] * v[k]).sum::<f64>() / x.len() as f64).sqrt();
            assert!((rms / s - 1.0).abs() < 0.05, "axis {k}: rms {rms}");
            let lag = 60;
            let c = x.windows(lag + 1).map(|w| w[0][k] * w[lag][k]).sum::<f64>()
                / (x.len() - lag) as f64
                / (rms * rms);
            assert!(
                (c - (-1.0f64).exp()).abs() < 0.05,
                "axis {k}: correlation {c}"
            );
        }
        assert_eq!(at_1hz(&x, 2.5)[0], 0.5 * (x[2][0] + x[3][0]));
        assert_eq!(at_1hz(&[], 2.5), [0.0; 3]);
    }

    #[test]
    fn the_receiver_reports_a_noisy_velocity_only_when_asked() {
        let fix = |extra: &str| {
            let sc = closed_loop_scenario(extra);
            let table = Arc::new(TruthTable::from_scenario(&sc).unwrap());
            let h = SensorsHandle(Arc::new(SimSensors::new(&sc, table.clone())));
            let g = h.gps(10.0).unwrap();
            (g, table.at(10.0 - 0.1).vel_ned_m_s)
        };
        let (off, truth) = fix("");
        assert_eq!(off.vel_ned_m_s, truth);
        let (on, truth_on) = fix("gps_velocity = true\n");
        assert_eq!(truth, truth_on);
        // The position draws come first and are the same; then sigma_vel_m_s (0.001) per axis.
        assert_eq!(
            (on.lat_deg, on.lon_deg, on.alt_amsl_m),
            (off.lat_deg, off.lon_deg, off.alt_amsl_m)
        );
        let d: Vec<f64> = (0..3).map(|k| on.vel_ned_m_s[k] - truth[k]).collect();
        assert!(
            d.iter().any(|x| *x != 0.0) && d.iter().all(|x| x.abs() < 0.005),
            "{d:?}"
        );
    }

    #[test]
    fn the_simulated_receiver_reports_the_state_its_latency_ago() {
        // Default 0.1 s (the daemon's gps_delay_s): 5 m behind at 50 m/s.
        assert!((lag_m(None) - 5.0).abs() < 0.05, "{}", lag_m(None));
        assert!((lag_m(Some(0.2)) - 10.0).abs() < 0.05);
        assert!(lag_m(Some(0.0)).abs() < 0.05);
        let bad = format!("{SCENARIO}latency_s = -1.0\n");
        let e = Scenario::parse(&bad, "gps_latency.toml")
            .unwrap_err()
            .to_string();
        assert!(e.contains("latency_s"), "{e}");
    }
}
