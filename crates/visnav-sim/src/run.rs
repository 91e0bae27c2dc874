//! Runs a scenario through the navigation filter and measures the errors against truth.
//!
//! Per IMU epoch: advance the truth, synthesise the IMU sample, feed the filter; capture the
//! sensors due at that epoch (GPS, altitude, attitude delivered at once; vision captured at a
//! random sub-sample instant and delivered after its latency). Errors are evaluated on the
//! filter's output records inside the evaluation window; NEES (position, 3 dof, and
//! position/velocity/attitude, 9 dof) every `nees_interval_s`.
//!
//! Vision fixes come from a [`VisionFixSource`]: today only [`TruthPlusNoise`] (the true camera
//! projection centre, `r_imu + C_b^n l_cam`, plus Gaussian noise with a full 3x3 NED covariance
//! that is also the reported covariance); the real pipeline's fixes and covariances plug in
//! through the same trait. GPS positions are antenna positions `r_imu + C_b^n l_gps`, GPS
//! velocities `v + C_b^n (w_nb x l_gps)`.
//!
//! Monte Carlo consistency (Bar-Shalom, Li & Kirubarajan 2001, 5.4.2): the N-run average NEES
//! `eps_bar(t)` is compared with the two-sided 95 % band `[chi2_{0.025}(N n) / N,
//! chi2_{0.975}(N n) / N]`.

use super::scenario::{Scenario, VisionNoiseFrame};
use nalgebra::{Matrix3, UnitQuaternion, Vector3};
use serde::Serialize;
use visnav_core::nav::earth;
use visnav_core::nav::filter::Counters;
use visnav_core::nav::synth::imu::ImuErrors;
use visnav_core::nav::{
    AltitudeFix, AttitudeFix, ImuSample, Measurement, NavFilter, PositionFix, VelocityFix,
};
use visnav_core::rng::Rng;

/// East/north/up triple.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Enu {
    /// East, m.
    pub e: f64,
    /// North, m.
    pub n: f64,
    /// Up, m.
    pub u: f64,
}

/// Options of one run.
#[derive(Debug, Clone, Copy)]
pub struct RunOptions {
    /// Feed the vision fixes. False is the INS-only control run: the vision fixes captured inside
    /// the evaluation window are withheld (earlier ones, if any, still initialise/calibrate).
    pub vision: bool,
    /// Added to the scenario seed.
    pub seed_offset: u64,
    /// Control experiment: stamp vision fixes with their arrival time instead of the capture
    /// time (what a filter without latency handling would do).
    pub stamp_at_arrival: bool,
    /// Draw the IMU turn-on biases from `[imu] gyro_bias_sigma_deg_h` / `accel_bias_sigma_ug`
    /// (Monte Carlo runs) instead of using the fixed `gyro_bias_deg_h` / `accel_bias_ug`.
    pub draw_turn_on_bias: bool,
}

impl RunOptions {
    /// Vision on/off, given seed offset, fixes stamped with their capture time.
    pub fn new(vision: bool, seed_offset: u64) -> Self {
        Self {
            vision,
            seed_offset,
            stamp_at_arrival: false,
            draw_turn_on_bias: false,
        }
    }
}

/// Result of one run.
#[derive(Debug, Clone, Serialize)]
pub struct RunResult {
    /// Maximum absolute error per axis in the evaluation window, m.
    pub max_err_m: Enu,
    /// RMS error per axis in the window, m.
    pub rms_err_m: Enu,
    /// Maximum horizontal error in the window, m.
    pub max_horiz_err_m: f64,
    /// Error at the end of the window, m.
    pub final_err_m: Enu,
    /// Mean (signed) error in the window, m.
    pub mean_err_m: Enu,
    /// Mean (signed) position error in the window expressed in the true body frame (FRD, m):
    /// an uncompensated lever arm shows up here as a constant offset even through turns.
    pub mean_err_body_frd_m: [f64; 3],
    /// Number of output records evaluated.
    pub n_eval: usize,
    /// Filter counters.
    pub counters: Counters,
    /// Health at the end of the window and its reason.
    pub final_health: String,
    /// Time of initialisation, s.
    pub initialised_at_s: Option<f64>,
    /// NEES samples every `nees_interval_s` inside the evaluation window.
    #[serde(skip)]
    pub nees: Vec<NeesSample>,
    /// Final gyro bias estimation error, deg/h.
    pub gyro_bias_err_deg_h: [f64; 3],
    /// Final accelerometer bias estimation error, micro-g.
    pub accel_bias_err_ug: [f64; 3],
    /// Final filter sigma of the gyro bias, deg/h.
    pub gyro_bias_sigma_deg_h: [f64; 3],
    /// Final filter sigma of the accelerometer bias, micro-g.
    pub accel_bias_sigma_ug: [f64; 3],
}

/// A source of simulated vision fixes.
pub trait VisionFixSource: Sync {
    /// What the fixes are (goes into the JSON `vision_source`).
    fn describe(&self) -> String;
    /// Error to add to the true camera projection centre (NED, m) and the NED covariance to
    /// report with the fix, for a frame taken with the true attitude `q_nb_true`.
    fn sample(
        &self,
        rng: &mut Rng,
        q_nb_true: &UnitQuaternion<f64>,
    ) -> (Vector3<f64>, Matrix3<f64>);
}

/// Truth plus Gaussian noise (the stand-in until the fix pipeline lands): covariance
/// `sigma_h^2 (I - d d^T) + sigma_v^2 d d^T` with `d` the line of sight (`C_b^n [0, 0, 1]`, a
/// nadir camera) or `diag(sigma_h^2, sigma_h^2, sigma_v^2)` in NED; the error is `L w`,
/// `L L^T` the covariance (Cholesky), `w ~ N(0, I)`; an outlier adds `outlier_m` in a random
/// horizontal direction (not in the reported covariance).
#[derive(Debug, Clone)]
pub struct TruthPlusNoise {
    /// Sigma across the line of sight (horizontal at nadir), m.
    pub sigma_h_m: f64,
    /// Sigma along the line of sight (vertical at nadir), m.
    pub sigma_v_m: f64,
    /// Noise frame.
    pub frame: VisionNoiseFrame,
    /// Outlier probability.
    pub outlier_prob: f64,
    /// Outlier offset, m.
    pub outlier_m: f64,
}

impl TruthPlusNoise {
    /// From the scenario's `[vision]` section.
    pub fn from_config(v: &super::scenario::VisionConfig) -> Self {
        Self {
            sigma_h_m: v.sigma_h_m,
            sigma_v_m: v.sigma_v_m,
            frame: v.noise_frame,
            outlier_prob: v.outlier_prob,
            outlier_m: v.outlier_m,
        }
    }

    /// The covariance for a frame taken with attitude `q_nb`.
    pub fn covariance_ned_m2(&self, q_nb: &UnitQuaternion<f64>) -> Matrix3<f64> {
        let (h2, v2) = (self.sigma_h_m.powi(2), self.sigma_v_m.powi(2));
        match self.frame {
            VisionNoiseFrame::Ned => sym3([h2, h2, v2]),
            VisionNoiseFrame::LineOfSight => {
                let d = q_nb * Vector3::z();
                let ddt = d * d.transpose();
                (Matrix3::identity() - ddt) * h2 + ddt * v2
            }
        }
    }
}

impl VisionFixSource for TruthPlusNoise {
    fn describe(&self) -> String {
        format!(
            "truth+noise (fix pipeline not landed): true camera projection centre plus Gaussian noise, sigma {} m across and {} m along the {} (full 3x3 NED covariance, reported with the fix), outlier probability {} ({} m)",
            self.sigma_h_m,
            self.sigma_v_m,
            match self.frame {
                VisionNoiseFrame::LineOfSight => "line of sight of a nadir camera",
                VisionNoiseFrame::Ned => "vertical (NED axes)",
            },
            self.outlier_prob,
            self.outlier_m
        )
    }

    fn sample(
        &self,
        rng: &mut Rng,
        q_nb_true: &UnitQuaternion<f64>,
    ) -> (Vector3<f64>, Matrix3<f64>) {
        let cov = self.covariance_ned_m2(q_nb_true);
        let l = cov
            .cholesky()
            .map(|c| c.l())
            .unwrap_or_else(|| sym3([self.sigma_h_m, self.sigma_h_m, self.sigma_v_m]));
        let w = Vector3::new(rng.normal(), rng.normal(), rng.normal());
        let mut n = l * w;
        if self.outlier_prob > 0.0 && rng.uniform() < self.outlier_prob {
            let ang = 2.0 * std::f64::consts::PI * rng.uniform();
            n += Vector3::new(ang.cos(), ang.sin(), 0.0) * self.outlier_m;
        }
        (n, cov)
    }
}

/// Run errors.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    /// The filter never initialised.
    #[error("scenario {0}: the filter never initialised (check gps/vision/attitude sections)")]
    NeverInitialised(String),
}

/// The NEES blocks of the 15 navigation error states `[dr_ned (m), dv_ned (m/s), psi_ned (rad),
/// db_gyro (rad/s), db_accel (m/s^2)]` (estimate minus truth; the bias errors are the errors of the
/// total bias, turn-on plus drift): name, first index, size.
pub const NEES_BLOCKS: [(&str, usize, usize); 7] = [
    ("position", 0, 3),
    ("velocity", 3, 3),
    ("attitude", 6, 3),
    ("pos_vel_att", 0, 9),
    ("gyro_bias", 9, 3),
    ("accel_bias", 12, 3),
    ("all15", 0, 15),
];

/// Names of the 15 navigation error states (for the per-state normalised squared errors).
pub const STATE_NAMES: [&str; 15] = [
    "pos_n", "pos_e", "pos_d", "vel_n", "vel_e", "vel_d", "att_n", "att_e", "att_d", "bg_x",
    "bg_y", "bg_z", "ba_x", "ba_y", "ba_z",
];

/// One NEES sample of one run.
#[derive(Debug, Clone, PartialEq)]
pub struct NeesSample {
    /// Time, s.
    pub t_s: f64,
    /// `x_b^T P_b^-1 x_b` for every block of [`NEES_BLOCKS`].
    pub block: [f64; NEES_BLOCKS.len()],
    /// Per-state normalised squared error `x_i^2 / P_ii`.
    pub nse: [f64; 15],
}

impl NeesSample {
    /// From the 15 navigation errors and their covariance; None if a block is singular.
    pub fn new(
        t_s: f64,
        x: &nalgebra::SVector<f64, 15>,
        p: &nalgebra::SMatrix<f64, 15, 15>,
    ) -> Option<Self> {
        let mut block = [0.0; NEES_BLOCKS.len()];
        for (b, &(_, i0, n)) in block.iter_mut().zip(NEES_BLOCKS.iter()) {
            let pb = p.view((i0, i0), (n, n)).into_owned();
            let xb = x.rows(i0, n).into_owned();
            let chol = pb.cholesky()?;
            *b = xb.dot(&chol.solve(&xb));
        }
        let nse = std::array::from_fn(|i| x[i] * x[i] / p[(i, i)]);
        Some(Self { t_s, block, nse })
    }
}

fn sym3(d: [f64; 3]) -> Matrix3<f64> {
    Matrix3::from_diagonal(&Vector3::from(d))
}

/// Run a scenario once, vision fixes from [`TruthPlusNoise`] of the `[vision]` section.
pub fn run(sc: &Scenario, opt: RunOptions) -> Result<RunResult, RunError> {
    let src = sc.vision.as_ref().map(TruthPlusNoise::from_config);
    run_with_source(sc, opt, src.as_ref().map(|s| s as &dyn VisionFixSource))
}

/// Run a scenario once with the given vision fix source (timing, rate and latency from the
/// `[vision]` section).
pub fn run_with_source(
    sc: &Scenario,
    opt: RunOptions,
    vision_source: Option<&dyn VisionFixSource>,
) -> Result<RunResult, RunError> {
    let traj = sc.trajectory();
    let mut truth = traj.truth();
    let seed = sc.seed.wrapping_add(opt.seed_offset);
    let mut rng = Rng::new(seed);
    let mut imu_err = ImuErrors::for_run(sc.imu.clone(), &mut rng, opt.draw_turn_on_bias);
    let mut filter = NavFilter::new(sc.nav.clone());
    let dt_us = (1e6 / sc.imu.rate_hz).round() as u64;
    let dt_s = dt_us as f64 * 1e-6;
    let n_steps = (sc.duration_s() / dt_s).floor() as u64;
    let mut pending: Vec<(u64, Measurement)> = Vec::new();
    let ev = &sc.evaluation;
    let (ev0, ev1) = ((ev.from_s * 1e6) as u64, (ev.until_s * 1e6) as u64);
    let nees_us = period_us(1.0 / ev.nees_interval_s);
    let mut next_nees = ev0;
    let mut stats = ErrorStats::default();
    let mut nees = Vec::new();
    let mut init_at = None;
    let mut prev_truth = truth.state();
    let mut next = NextCapture::default();

    filter.imu(&ImuSample {
        t_us: 0,
        dtheta_rad_body_frd: Vector3::zeros(),
        dv_m_s_body_frd: Vector3::zeros(),
        gap_sigma_dtheta_rad: 0.0,
        gap_sigma_dv_m_s: 0.0,
    });
    for k in 1..=n_steps {
        let t_us = k * dt_us;
        let (dth, dv) = truth.step(dt_s);
        let (mdth, mdv) = imu_err.corrupt(&mut rng, &dth, &dv, dt_s);
        let ts = truth.state();
        let out = filter.imu(&ImuSample {
            t_us,
            dtheta_rad_body_frd: mdth,
            dv_m_s_body_frd: mdv,
            gap_sigma_dtheta_rad: 0.0,
            gap_sigma_dv_m_s: 0.0,
        });
        if init_at.is_none() && filter.is_initialised() {
            init_at = Some(t_us as f64 * 1e-6);
        }
        if let Some(o) = &out
            && t_us >= ev0
            && t_us <= ev1
        {
            stats.add(o, &ts);
        }
        if t_us >= next_nees
            && t_us <= ev1
            && let Some((x, p)) = nees_error(&filter, &imu_err, &ts)
        {
            next_nees += nees_us;
            if let Some(s) = NeesSample::new(t_us as f64 * 1e-6, &x, &p) {
                nees.push(s);
            }
        }
        // Sensors captured at this epoch, in a fixed order (the random draws follow it).
        if due(&mut next.attitude_us, t_us, sc.attitude.rate_hz) {
            filter.measure(attitude_measurement(sc, &ts, t_us, &mut rng));
        }
        if let Some(a) = &sc.altitude
            && due(&mut next.altitude_us, t_us, a.rate_hz)
        {
            filter.measure(Measurement::Altitude(AltitudeFix {
                t_capture_us: t_us,
                h_m: ts.h_m + a.bias_m + a.sigma_m * rng.normal(),
                var_m2: a.sigma_m * a.sigma_m,
            }));
        }
        if let Some(g) = &sc.gps
            && g.available(t_us as f64 * 1e-6)
            && due(&mut next.gps_us, t_us, g.rate_hz)
        {
            let w_nb = truth.kin.w_nb_body_rad_s;
            for m in gps_measurements(g, &ts, &w_nb, t_us, &mut rng) {
                filter.measure(m);
            }
        }
        if let Some(v) = &sc.vision
            && let Some(src) = vision_source
        {
            let ts_s = t_us as f64 * 1e-6;
            let withheld = !opt.vision && ts_s >= ev.from_s;
            if ts_s >= v.from_s
                && ts_s <= v.until_s
                && due(&mut next.vision_us, t_us, v.rate_hz)
                && !withheld
            {
                let span = (&prev_truth, &ts, t_us, dt_us);
                pending.push(vision_capture(v, src, span, opt.stamp_at_arrival, &mut rng));
            }
        }
        pending.sort_by_key(|p| p.0);
        while pending.first().is_some_and(|p| p.0 <= t_us) {
            let (_, m) = pending.remove(0);
            filter.measure(m);
        }
        prev_truth = ts;
    }
    let Some(biases) = filter.biases() else {
        return Err(RunError::NeverInitialised(sc.name.clone()));
    };
    Ok(stats.result(&filter, biases, &imu_err, init_at, nees))
}

/// The period of a rate, µs.
fn period_us(hz: f64) -> u64 {
    (1e6 / hz).round() as u64
}

/// Whether a sensor of rate `hz` whose next capture is `next` captures at `t` (it fires at the
/// first IMU epoch at or after its time); moves `next` on when it does.
fn due(next: &mut u64, t: u64, hz: f64) -> bool {
    if t < *next {
        return false;
    }
    *next += period_us(hz);
    if *next <= t {
        *next = t + period_us(hz);
    }
    true
}

/// The next capture time of each sensor, µs.
#[derive(Default)]
struct NextCapture {
    attitude_us: u64,
    altitude_us: u64,
    gps_us: u64,
    vision_us: u64,
}

/// The output's errors against the truth over the evaluation window.
#[derive(Default)]
struct ErrorStats {
    maxe: Enu,
    sum2: Enu,
    n_eval: usize,
    max_h: f64,
    final_err: Enu,
    sum_err_ned: Vector3<f64>,
    sum_err_body: Vector3<f64>,
    final_health: String,
}

impl ErrorStats {
    fn add(&mut self, o: &visnav_core::nav::NavOutput, ts: &visnav_core::nav::InsState) {
        let d = earth::ned_offset_m(
            (o.lat_deg.to_radians(), o.lon_deg.to_radians(), o.h_m),
            (ts.lat_rad, ts.lon_rad, ts.h_m),
        );
        let e = Enu {
            e: d.y,
            n: d.x,
            u: -d.z,
        };
        self.maxe.e = self.maxe.e.max(e.e.abs());
        self.maxe.n = self.maxe.n.max(e.n.abs());
        self.maxe.u = self.maxe.u.max(e.u.abs());
        self.sum2.e += e.e * e.e;
        self.sum2.n += e.n * e.n;
        self.sum2.u += e.u * e.u;
        self.max_h = self.max_h.max(e.e.hypot(e.n));
        self.sum_err_ned += d;
        self.sum_err_body += ts.q_nb.inverse() * d;
        self.n_eval += 1;
        self.final_err = e;
        self.final_health = format!("{}: {}", o.health, o.reason);
    }

    /// The run's figures: these errors, the filter's counters and its bias errors and sigmas
    /// (`biases`: the filter's gyro and accelerometer bias estimates) against the IMU's truth.
    fn result(
        self,
        filter: &NavFilter,
        (bg, ba): (Vector3<f64>, Vector3<f64>),
        imu_err: &ImuErrors,
        init_at: Option<f64>,
        nees: Vec<NeesSample>,
    ) -> RunResult {
        let (tbg, tba) = imu_err.biases();
        let sig = |i: usize, unit: f64| -> [f64; 3] {
            let p = filter.covariance();
            std::array::from_fn(|k| {
                p.as_ref()
                    .map(|p| p[(i + k, i + k)].max(0.0).sqrt() / unit)
                    .unwrap_or(f64::NAN)
            })
        };
        let n = self.n_eval.max(1) as f64;
        RunResult {
            max_err_m: self.maxe,
            rms_err_m: Enu {
                e: (self.sum2.e / n).sqrt(),
                n: (self.sum2.n / n).sqrt(),
                u: (self.sum2.u / n).sqrt(),
            },
            max_horiz_err_m: self.max_h,
            final_err_m: self.final_err,
            mean_err_m: Enu {
                e: self.sum_err_ned.y / n,
                n: self.sum_err_ned.x / n,
                u: -self.sum_err_ned.z / n,
            },
            mean_err_body_frd_m: (self.sum_err_body / n).into(),
            n_eval: self.n_eval,
            counters: *filter.counters(),
            final_health: self.final_health,
            initialised_at_s: init_at,
            nees,
            gyro_bias_err_deg_h: ((bg - tbg) / visnav_core::nav::config::DEG_H_TO_RAD_S).into(),
            accel_bias_err_ug: ((ba - tba) / visnav_core::nav::config::UG_TO_M_S2).into(),
            gyro_bias_sigma_deg_h: sig(9, visnav_core::nav::config::DEG_H_TO_RAD_S),
            accel_bias_sigma_ug: sig(12, visnav_core::nav::config::UG_TO_M_S2),
        }
    }
}

/// The filter's 15-state error against the truth (position, velocity, attitude, gyro and
/// accelerometer biases) and its covariance, once the filter has a state.
fn nees_error(
    filter: &NavFilter,
    imu_err: &ImuErrors,
    ts: &visnav_core::nav::InsState,
) -> Option<(nalgebra::SVector<f64, 15>, nalgebra::SMatrix<f64, 15, 15>)> {
    let (st, p) = (filter.state()?, filter.nav_error_covariance()?);
    let (bg, ba) = filter.biases()?;
    let (tbg, tba) = imu_err.biases();
    let mut x = nalgebra::SVector::<f64, 15>::zeros();
    x.fixed_rows_mut::<3>(0).copy_from(&earth::ned_offset_m(
        (st.lat_rad, st.lon_rad, st.h_m),
        (ts.lat_rad, ts.lon_rad, ts.h_m),
    ));
    x.fixed_rows_mut::<3>(3)
        .copy_from(&(st.v_ned_m_s - ts.v_ned_m_s));
    x.fixed_rows_mut::<3>(6)
        .copy_from(&(st.q_nb * ts.q_nb.inverse()).scaled_axis());
    x.fixed_rows_mut::<3>(9).copy_from(&(bg - tbg));
    x.fixed_rows_mut::<3>(12).copy_from(&(ba - tba));
    Some((x, p))
}

/// The autopilot attitude: the truth turned by the scenario's tilt and yaw noise.
fn attitude_measurement(
    sc: &Scenario,
    ts: &visnav_core::nav::InsState,
    t_us: u64,
    rng: &mut Rng,
) -> Measurement {
    let a = &sc.attitude;
    let n = Vector3::new(
        a.sigma_tilt_deg.to_radians() * rng.normal(),
        a.sigma_tilt_deg.to_radians() * rng.normal(),
        a.sigma_yaw_deg.to_radians() * rng.normal(),
    );
    Measurement::Attitude(AttitudeFix {
        t_capture_us: t_us,
        q_nb: UnitQuaternion::from_scaled_axis(n) * ts.q_nb,
    })
}

/// The GPS velocity and position of the antenna (lever arm `l_gps`), with their noise.
fn gps_measurements(
    g: &super::scenario::GpsConfig,
    ts: &visnav_core::nav::InsState,
    w_nb_body_rad_s: &Vector3<f64>,
    t_us: u64,
    rng: &mut Rng,
) -> [Measurement; 2] {
    let vcov = sym3([g.sigma_vel_m_s.powi(2); 3]);
    let l_b = Vector3::from(g.lever_arm_body_frd_m);
    let lv_n = ts.q_nb * w_nb_body_rad_s.cross(&l_b);
    let velocity = Measurement::GpsVelocity(VelocityFix {
        t_capture_us: t_us,
        v_ned_m_s: ts.v_ned_m_s + lv_n + rng.normal3() * g.sigma_vel_m_s,
        cov_ned_m2_s2: vcov,
    });
    let cov = sym3([
        g.sigma_h_m.powi(2),
        g.sigma_h_m.powi(2),
        g.sigma_v_m.powi(2),
    ]);
    let n = Vector3::new(
        g.sigma_h_m * rng.normal(),
        g.sigma_h_m * rng.normal(),
        g.sigma_v_m * rng.normal(),
    );
    let position =
        Measurement::GpsPosition(offset_fix(&ts_pos(ts), &(ts.q_nb * l_b + n), t_us, cov));
    [velocity, position]
}

/// A vision fix captured at a random instant inside the last IMU interval (`span`: the truth
/// at its start and end, the epoch's time and the interval, µs): its delivery time after the
/// latency and the measurement, stamped with its capture time (or its arrival, for the control
/// experiment).
fn vision_capture(
    v: &super::scenario::VisionConfig,
    src: &dyn VisionFixSource,
    span: (
        &visnav_core::nav::InsState,
        &visnav_core::nav::InsState,
        u64,
        u64,
    ),
    stamp_at_arrival: bool,
    rng: &mut Rng,
) -> (u64, Measurement) {
    let (prev, ts, t_us, dt_us) = span;
    let frac = rng.uniform();
    let t_c = t_us - (frac * dt_us as f64) as u64;
    let a = (t_c - (t_us - dt_us)) as f64 / dt_us as f64;
    let p0 = ts_pos(prev);
    let p1 = ts_pos(ts);
    let pi = (
        p0.0 + a * (p1.0 - p0.0),
        p0.1 + a * (p1.1 - p0.1),
        p0.2 + a * (p1.2 - p0.2),
    );
    let q_c = prev.q_nb.slerp(&ts.q_nb, a);
    let l_n = q_c * Vector3::from(v.lever_arm_body_frd_m);
    let (n, cov) = src.sample(rng, &q_c);
    let lat_ms = v.latency_min_ms + rng.uniform() * (v.latency_max_ms - v.latency_min_ms);
    let deliver = t_c + (lat_ms * 1e3) as u64;
    let stamp = if stamp_at_arrival { deliver } else { t_c };
    (
        deliver,
        Measurement::Vision(offset_fix(&pi, &(l_n + n), stamp, cov)),
    )
}

fn ts_pos(s: &visnav_core::nav::InsState) -> (f64, f64, f64) {
    (s.lat_rad, s.lon_rad, s.h_m)
}

fn offset_fix(
    p: &(f64, f64, f64),
    n_ned: &Vector3<f64>,
    t_us: u64,
    cov: Matrix3<f64>,
) -> PositionFix {
    let (rm, rn) = earth::radii_m(p.0);
    PositionFix {
        t_capture_us: t_us,
        lat_rad: p.0 + n_ned.x / (rm + p.2),
        lon_rad: p.1 + n_ned.y / ((rn + p.2) * p.0.cos()),
        h_m: p.2 - n_ned.z,
        cov_ned_m2: cov,
        att_dependence_ned: None,
    }
}

/// NEES consistency summary of a Monte Carlo.
#[derive(Debug, Clone, Serialize)]
pub struct NeesSummary {
    /// Degrees of freedom per sample.
    pub dof: usize,
    /// Number of runs.
    pub runs: usize,
    /// Number of epochs.
    pub epochs: usize,
    /// Mean over epochs of the run-averaged NEES.
    pub mean: f64,
    /// Smallest and largest run-averaged NEES over the epochs.
    pub min_max: [f64; 2],
    /// Two-sided 95 % band for the run-averaged NEES.
    pub band_95: [f64; 2],
    /// Fraction of epochs whose run-averaged NEES lies in the band (about 0.95 expected).
    pub fraction_inside: f64,
    /// Whether the mean lies in the band.
    pub mean_inside: bool,
}

/// Summarise per-run NEES series (same epochs in every run).
pub fn nees_summary(series: &[Vec<(f64, f64)>], dof: usize) -> Option<NeesSummary> {
    let runs = series.len();
    let epochs = series.iter().map(|s| s.len()).min()?;
    if runs == 0 || epochs == 0 {
        return None;
    }
    let nd = (runs * dof) as f64;
    let band = [
        visnav_core::stats::chi2_quantile(nd, 0.025) / runs as f64,
        visnav_core::stats::chi2_quantile(nd, 0.975) / runs as f64,
    ];
    let avg: Vec<f64> = (0..epochs)
        .map(|k| series.iter().map(|s| s[k].1).sum::<f64>() / runs as f64)
        .collect();
    let mean = avg.iter().sum::<f64>() / epochs as f64;
    let inside = avg
        .iter()
        .filter(|&&a| a >= band[0] && a <= band[1])
        .count();
    Some(NeesSummary {
        dof,
        runs,
        epochs,
        mean,
        min_max: [
            avg.iter().copied().fold(f64::INFINITY, f64::min),
            avg.iter().copied().fold(f64::NEG_INFINITY, f64::max),
        ],
        band_95: band,
        fraction_inside: inside as f64 / epochs as f64,
        mean_inside: mean >= band[0] && mean <= band[1],
    })
}

/// Monte Carlo result.
#[derive(Debug, Clone, Serialize)]
pub struct MonteCarlo {
    /// Runs.
    pub runs: usize,
    /// Position NEES (3 dof).
    pub nees_pos: Option<NeesSummary>,
    /// Position/velocity/attitude NEES (9 dof).
    pub nees_pva: Option<NeesSummary>,
    /// Every block of [`NEES_BLOCKS`] by name (position, velocity, attitude, pos_vel_att,
    /// gyro_bias, accel_bias, all15).
    pub nees: Vec<(String, Option<NeesSummary>)>,
    /// Mean over runs and epochs of `x_i^2 / P_ii` per navigation error state (1 expected), by
    /// [`STATE_NAMES`].
    pub state_nse_mean: Vec<(String, f64)>,
    /// Mean over the vision runs of the max error per axis, m.
    pub mean_max_err_m: Enu,
    /// Mean over the INS-only control runs (same seeds) of the max error per axis, m.
    pub ins_only_mean_max_err_m: Enu,
    /// Mean over the INS-only control runs of the max horizontal error, m.
    pub ins_only_mean_max_horiz_err_m: f64,
    /// Mean over runs of the max horizontal error, m.
    pub mean_max_horiz_err_m: f64,
    /// Median over runs of the max horizontal error, m.
    pub median_max_horiz_err_m: f64,
    /// Largest max horizontal error over runs, m.
    pub worst_max_horiz_err_m: f64,
    /// Runs whose max horizontal error exceeds the scenario target.
    pub runs_over_target: usize,
}

fn median(v: &[f64]) -> f64 {
    let mut s: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
    if s.is_empty() {
        return f64::NAN;
    }
    s.sort_by(f64::total_cmp);
    let m = s.len() / 2;
    if s.len() % 2 == 1 {
        s[m]
    } else {
        0.5 * (s[m - 1] + s[m])
    }
}

fn mean_enu(rs: &[RunResult]) -> Enu {
    let n = rs.len().max(1) as f64;
    Enu {
        e: rs.iter().map(|r| r.max_err_m.e).sum::<f64>() / n,
        n: rs.iter().map(|r| r.max_err_m.n).sum::<f64>() / n,
        u: rs.iter().map(|r| r.max_err_m.u).sum::<f64>() / n,
    }
}

/// Run `runs` vision runs with seeds `seed + 1000 + i` and the INS-only control runs with the
/// same seeds (in parallel); every run draws its IMU turn-on biases (`draw_turn_on_bias`).
pub fn monte_carlo(sc: &Scenario, runs: usize) -> Result<MonteCarlo, RunError> {
    use rayon::prelude::*;
    let both: Result<Vec<(RunResult, RunResult)>, RunError> = (0..runs)
        .into_par_iter()
        .map(|i| {
            let opt = |vision| RunOptions {
                draw_turn_on_bias: true,
                ..RunOptions::new(vision, 1000 + i as u64)
            };
            Ok((run(sc, opt(true))?, run(sc, opt(false))?))
        })
        .collect();
    let (results, ins): (Vec<RunResult>, Vec<RunResult>) = both?.into_iter().unzip();
    let series = |b: usize| -> Vec<Vec<(f64, f64)>> {
        results
            .iter()
            .map(|r| r.nees.iter().map(|s| (s.t_s, s.block[b])).collect())
            .collect()
    };
    let nees: Vec<(String, Option<NeesSummary>)> = NEES_BLOCKS
        .iter()
        .enumerate()
        .map(|(b, &(name, _, n))| (name.to_string(), nees_summary(&series(b), n)))
        .collect();
    let n_samples = results.iter().map(|r| r.nees.len()).sum::<usize>().max(1) as f64;
    let state_nse_mean = STATE_NAMES
        .iter()
        .enumerate()
        .map(|(i, name)| {
            let sum: f64 = results
                .iter()
                .flat_map(|r| r.nees.iter().map(move |s| s.nse[i]))
                .sum();
            (name.to_string(), sum / n_samples)
        })
        .collect();
    let mh: Vec<f64> = results.iter().map(|r| r.max_horiz_err_m).collect();
    let target = sc
        .evaluation
        .target_max_horiz_err_m
        .unwrap_or(f64::INFINITY);
    Ok(MonteCarlo {
        runs,
        mean_max_err_m: mean_enu(&results),
        ins_only_mean_max_err_m: mean_enu(&ins),
        ins_only_mean_max_horiz_err_m: ins.iter().map(|r| r.max_horiz_err_m).sum::<f64>()
            / runs.max(1) as f64,
        nees_pos: nees[0].1.clone(),
        nees_pva: nees[3].1.clone(),
        nees,
        state_nse_mean,
        mean_max_horiz_err_m: mh.iter().sum::<f64>() / runs.max(1) as f64,
        median_max_horiz_err_m: median(&mh),
        worst_max_horiz_err_m: mh.iter().copied().fold(0.0, f64::max),
        runs_over_target: mh.iter().filter(|&&m| m > target).count(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn src(frame: VisionNoiseFrame) -> TruthPlusNoise {
        TruthPlusNoise {
            sigma_h_m: 2.0,
            sigma_v_m: 5.0,
            frame,
            outlier_prob: 0.0,
            outlier_m: 0.0,
        }
    }

    #[test]
    fn line_of_sight_covariance_is_nadir_diagonal_and_correlated_when_banked() {
        let s = src(VisionNoiseFrame::LineOfSight);
        let level = UnitQuaternion::from_euler_angles(0.0, 0.0, 1.0);
        let c = s.covariance_ned_m2(&level);
        assert!((c - sym3([4.0, 4.0, 25.0])).abs().max() < 1e-12, "{c}");
        // Banked 30 deg heading north: the line of sight leans east, east and down correlate.
        let banked = UnitQuaternion::from_euler_angles(30f64.to_radians(), 0.0, 0.0);
        let c = s.covariance_ned_m2(&banked);
        let d = banked * Vector3::z();
        assert!((c[(1, 2)] - c[(2, 1)]).abs() < 1e-12);
        assert!(c[(1, 2)].abs() > 5.0, "{c}");
        // Eigen-structure: sigma_v^2 along the line of sight, sigma_h^2 across it.
        assert!(((c * d) - d * 25.0).norm() < 1e-9);
        let across = d.cross(&Vector3::x()).normalize();
        assert!(((c * across) - across * 4.0).norm() < 1e-9);
        // The NED frame ignores the attitude.
        let n = src(VisionNoiseFrame::Ned).covariance_ned_m2(&banked);
        assert!((n - sym3([4.0, 4.0, 25.0])).abs().max() < 1e-12);
    }

    #[test]
    fn sampled_noise_has_the_reported_covariance() {
        let s = src(VisionNoiseFrame::LineOfSight);
        let q = UnitQuaternion::from_euler_angles(25f64.to_radians(), -10f64.to_radians(), 0.7);
        let mut rng = Rng::new(11);
        let n = 40_000;
        let mut acc = Matrix3::zeros();
        let mut cov = Matrix3::zeros();
        for _ in 0..n {
            let (e, c) = s.sample(&mut rng, &q);
            acc += e * e.transpose();
            cov = c;
        }
        let emp = acc / n as f64;
        // Whitened empirical covariance close to identity (sampling error ~ 1/sqrt(n)).
        let li = cov.cholesky().expect("pd").l().try_inverse().expect("inv");
        let w = li * emp * li.transpose();
        assert!((w - Matrix3::identity()).abs().max() < 0.03, "{w}");
    }
}
