//! IMU error synthesis: turns ideal increments into measured ones.
//!
//! Per axis: `w_meas = (1 + s) w + b0 + b_gm(t) + b_rw(t) + n`, the same for specific force, with
//! a fixed turn-on bias `b0`, a first-order Gauss-Markov bias instability
//! `b_gm(k+1) = e^{-dt/tau} b_gm(k) + sigma sqrt(1 - e^{-2 dt/tau}) N(0,1)`, a bias random walk
//! `b_rw(k+1) = b_rw(k) + q sqrt(dt) N(0,1)` and white noise whose increment has sigma
//! `N sqrt(dt)` (`N` the angle/velocity random walk density). Datasheet units as in
//! [`crate::nav::config`].
//!
//! Per run ([`ImuErrors::for_run`]) the Gauss-Markov bias starts from its stationary distribution
//! `N(0, sigma^2)` (a bias instability is already wandering at switch-on), and with
//! `draw_turn_on = true` (the Monte Carlo runs) the turn-on bias of every axis is drawn from
//! `N(0, gyro_bias_sigma_deg_h^2)` / `N(0, accel_bias_sigma_ug^2)` instead of the fixed
//! `gyro_bias_deg_h` / `accel_bias_ug`: a NEES consistency test needs the truth drawn from the
//! filter's prior, and a fixed bias smaller than the prior sigma sits in the unobservable directions
//! (vertical gyro, horizontal accelerometers in level flight) and makes the NEES too small.

use crate::nav::config::{DEG_H_TO_RAD_S, UG_TO_M_S2};
use crate::rng::Rng;
use crate::validate::{Problems, Validate};
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

/// The simulated IMU (truth error parameters).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimImuConfig {
    /// Sample rate, Hz.
    pub rate_hz: f64,
    /// Fixed gyro turn-on bias per axis (body FRD), deg/h.
    #[serde(default)]
    pub gyro_bias_deg_h: [f64; 3],
    /// Fixed accelerometer turn-on bias per axis, micro-g.
    #[serde(default)]
    pub accel_bias_ug: [f64; 3],
    /// Turn-on gyro bias sigma per axis for runs that draw it (Monte Carlo), deg/h; 0 keeps the
    /// fixed `gyro_bias_deg_h`.
    #[serde(default)]
    pub gyro_bias_sigma_deg_h: f64,
    /// Turn-on accelerometer bias sigma per axis for runs that draw it, micro-g; 0 keeps the fixed
    /// `accel_bias_ug`.
    #[serde(default)]
    pub accel_bias_sigma_ug: f64,
    /// Gyro scale-factor error per axis, ppm.
    #[serde(default)]
    pub gyro_scale_ppm: [f64; 3],
    /// Accelerometer scale-factor error per axis, ppm.
    #[serde(default)]
    pub accel_scale_ppm: [f64; 3],
    /// Gyro angle random walk, deg/sqrt(h).
    #[serde(default)]
    pub gyro_arw_deg_sqrt_h: f64,
    /// Gyro bias instability (Gauss-Markov sigma), deg/h.
    #[serde(default)]
    pub gyro_bias_instability_deg_h: f64,
    /// Its correlation time, s.
    #[serde(default = "default_tau")]
    pub gyro_bias_corr_time_s: f64,
    /// Gyro bias random walk, deg/h/sqrt(h).
    #[serde(default)]
    pub gyro_bias_rw_deg_h_sqrt_h: f64,
    /// Accelerometer velocity random walk, m/s/sqrt(h).
    #[serde(default)]
    pub accel_vrw_m_s_sqrt_h: f64,
    /// Accelerometer bias instability (Gauss-Markov sigma), micro-g.
    #[serde(default)]
    pub accel_bias_instability_ug: f64,
    /// Its correlation time, s.
    #[serde(default = "default_tau")]
    pub accel_bias_corr_time_s: f64,
    /// Accelerometer bias random walk, micro-g/sqrt(h).
    #[serde(default)]
    pub accel_bias_rw_ug_sqrt_h: f64,
    /// A multirotor's vibration left in the accelerometer after the autopilot's IMU filter, m/s^2
    /// RMS per axis and sample (independent from sample to sample: the rotors' 100-200 Hz
    /// folded down by the sampling). Per sample of `dt` it adds `N(0, (v dt)^2)` to the velocity
    /// increment: the same as a velocity random walk of `v sqrt(dt)`, which the filter's model
    /// must cover.
    #[serde(default)]
    pub vibration_accel_m_s2: f64,
    /// The same for the gyro, deg/s RMS per axis and sample.
    #[serde(default)]
    pub vibration_gyro_deg_s: f64,
}

fn default_tau() -> f64 {
    300.0
}

impl SimImuConfig {
    /// A perfect IMU at `rate_hz`.
    pub fn perfect(rate_hz: f64) -> Self {
        Self {
            rate_hz,
            gyro_bias_deg_h: [0.0; 3],
            accel_bias_ug: [0.0; 3],
            gyro_bias_sigma_deg_h: 0.0,
            accel_bias_sigma_ug: 0.0,
            gyro_scale_ppm: [0.0; 3],
            accel_scale_ppm: [0.0; 3],
            gyro_arw_deg_sqrt_h: 0.0,
            gyro_bias_instability_deg_h: 0.0,
            gyro_bias_corr_time_s: 300.0,
            gyro_bias_rw_deg_h_sqrt_h: 0.0,
            accel_vrw_m_s_sqrt_h: 0.0,
            accel_bias_instability_ug: 0.0,
            accel_bias_corr_time_s: 300.0,
            accel_bias_rw_ug_sqrt_h: 0.0,
            vibration_accel_m_s2: 0.0,
            vibration_gyro_deg_s: 0.0,
        }
    }
}

impl Validate for SimImuConfig {
    fn validate(&self, p: &mut Problems) {
        p.range("rate_hz", self.rate_hz, 1.0, 10_000.0);
        for (k, a, hi) in [
            ("gyro_bias_deg_h", &self.gyro_bias_deg_h, 36_000.0),
            ("accel_bias_ug", &self.accel_bias_ug, 1e6),
            ("gyro_scale_ppm", &self.gyro_scale_ppm, 1e5),
            ("accel_scale_ppm", &self.accel_scale_ppm, 1e5),
        ] {
            for v in a {
                p.range(k, *v, -hi, hi);
            }
        }
        p.range(
            "gyro_bias_sigma_deg_h",
            self.gyro_bias_sigma_deg_h,
            0.0,
            36_000.0,
        );
        p.range("accel_bias_sigma_ug", self.accel_bias_sigma_ug, 0.0, 1e6);
        p.range("gyro_arw_deg_sqrt_h", self.gyro_arw_deg_sqrt_h, 0.0, 100.0);
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
        p.range(
            "accel_vrw_m_s_sqrt_h",
            self.accel_vrw_m_s_sqrt_h,
            0.0,
            1000.0,
        );
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
        p.range(
            "vibration_accel_m_s2",
            self.vibration_accel_m_s2,
            0.0,
            100.0,
        );
        p.range(
            "vibration_gyro_deg_s",
            self.vibration_gyro_deg_s,
            0.0,
            100.0,
        );
    }
}

/// Running IMU error state.
#[derive(Debug, Clone)]
pub struct ImuErrors {
    cfg: SimImuConfig,
    bg0: Vector3<f64>,
    ba0: Vector3<f64>,
    gm_g: Vector3<f64>,
    gm_a: Vector3<f64>,
    rw_g: Vector3<f64>,
    rw_a: Vector3<f64>,
}

impl ImuErrors {
    /// Start with zero time-varying bias (the turn-on bias is fixed by the configuration).
    pub fn new(cfg: SimImuConfig) -> Self {
        Self {
            bg0: Vector3::from(cfg.gyro_bias_deg_h) * DEG_H_TO_RAD_S,
            ba0: Vector3::from(cfg.accel_bias_ug) * UG_TO_M_S2,
            cfg,
            gm_g: Vector3::zeros(),
            gm_a: Vector3::zeros(),
            rw_g: Vector3::zeros(),
            rw_a: Vector3::zeros(),
        }
    }

    /// The errors of one simulation run: the Gauss-Markov biases start from their stationary
    /// distribution; with `draw_turn_on` the turn-on biases are drawn from their sigmas (axes
    /// whose sigma is 0 keep the fixed values).
    pub fn for_run(cfg: SimImuConfig, rng: &mut Rng, draw_turn_on: bool) -> Self {
        let mut e = Self::new(cfg);
        let c = &e.cfg;
        if draw_turn_on && c.gyro_bias_sigma_deg_h > 0.0 {
            e.bg0 = rng.normal3() * (c.gyro_bias_sigma_deg_h * DEG_H_TO_RAD_S);
        }
        if draw_turn_on && c.accel_bias_sigma_ug > 0.0 {
            e.ba0 = rng.normal3() * (c.accel_bias_sigma_ug * UG_TO_M_S2);
        }
        e.gm_g = rng.normal3() * (c.gyro_bias_instability_deg_h * DEG_H_TO_RAD_S);
        e.gm_a = rng.normal3() * (c.accel_bias_instability_ug * UG_TO_M_S2);
        e
    }

    /// Turn-on gyro bias (rad/s) and accelerometer bias (m/s^2) of this run.
    pub fn turn_on_biases(&self) -> (Vector3<f64>, Vector3<f64>) {
        (self.bg0, self.ba0)
    }

    /// Current total gyro bias (rad/s) and accelerometer bias (m/s^2).
    pub fn biases(&self) -> (Vector3<f64>, Vector3<f64>) {
        let bg = self.bg0 + self.gm_g + self.rw_g;
        let ba = self.ba0 + self.gm_a + self.rw_a;
        (bg, ba)
    }

    /// Corrupt ideal increments over `dt_s`; advances the bias processes.
    pub fn corrupt(
        &mut self,
        rng: &mut Rng,
        dtheta_rad: &Vector3<f64>,
        dv_m_s: &Vector3<f64>,
        dt_s: f64,
    ) -> (Vector3<f64>, Vector3<f64>) {
        let c = &self.cfg;
        let gm = |x: &mut Vector3<f64>, rng: &mut Rng, sigma: f64, tau: f64| {
            if sigma > 0.0 {
                let a = (-dt_s / tau).exp();
                *x = *x * a + rng.normal3() * (sigma * (1.0 - a * a).sqrt());
            }
        };
        gm(
            &mut self.gm_g,
            rng,
            c.gyro_bias_instability_deg_h * DEG_H_TO_RAD_S,
            c.gyro_bias_corr_time_s,
        );
        gm(
            &mut self.gm_a,
            rng,
            c.accel_bias_instability_ug * UG_TO_M_S2,
            c.accel_bias_corr_time_s,
        );
        if c.gyro_bias_rw_deg_h_sqrt_h > 0.0 {
            self.rw_g +=
                rng.normal3() * (c.gyro_bias_rw_deg_h_sqrt_h * DEG_H_TO_RAD_S / 60.0 * dt_s.sqrt());
        }
        if c.accel_bias_rw_ug_sqrt_h > 0.0 {
            self.rw_a +=
                rng.normal3() * (c.accel_bias_rw_ug_sqrt_h * UG_TO_M_S2 / 60.0 * dt_s.sqrt());
        }
        let (bg, ba) = self.biases();
        let sg = Vector3::from(c.gyro_scale_ppm) * 1e-6;
        let sa = Vector3::from(c.accel_scale_ppm) * 1e-6;
        let n_g = c.gyro_arw_deg_sqrt_h.to_radians() / 60.0 * dt_s.sqrt();
        let n_a = c.accel_vrw_m_s_sqrt_h / 60.0 * dt_s.sqrt();
        let mut dth = dtheta_rad + dtheta_rad.component_mul(&sg) + bg * dt_s;
        let mut dv = dv_m_s + dv_m_s.component_mul(&sa) + ba * dt_s;
        if n_g > 0.0 {
            dth += rng.normal3() * n_g;
        }
        if n_a > 0.0 {
            dv += rng.normal3() * n_a;
        }
        if c.vibration_gyro_deg_s > 0.0 {
            dth += rng.normal3() * (c.vibration_gyro_deg_s.to_radians() * dt_s);
        }
        if c.vibration_accel_m_s2 > 0.0 {
            dv += rng.normal3() * (c.vibration_accel_m_s2 * dt_s);
        }
        (dth, dv)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn white_noise_density_and_bias() {
        let mut cfg = SimImuConfig::perfect(100.0);
        cfg.gyro_arw_deg_sqrt_h = 0.6; // 1.745e-4 rad/sqrt(s)
        cfg.accel_bias_ug = [0.0, 0.0, 1000.0];
        let mut e = ImuErrors::new(cfg);
        let mut rng = Rng::new(3);
        let dt = 0.01;
        let n = 100_000;
        let mut s2 = 0.0;
        let mut sum_dv = Vector3::zeros();
        for _ in 0..n {
            let (dth, dv) = e.corrupt(&mut rng, &Vector3::zeros(), &Vector3::zeros(), dt);
            s2 += dth.x * dth.x;
            sum_dv += dv;
        }
        let density = (s2 / n as f64 / dt).sqrt();
        assert!(
            (density / (0.6f64.to_radians() / 60.0) - 1.0).abs() < 0.02,
            "{density}"
        );
        let mean_acc = sum_dv.z / (n as f64 * dt);
        assert!((mean_acc - 1000.0 * UG_TO_M_S2).abs() < 1e-9);
    }

    #[test]
    fn vibration_is_sample_noise_on_the_rates() {
        let mut cfg = SimImuConfig::perfect(100.0);
        cfg.vibration_accel_m_s2 = 0.3;
        cfg.vibration_gyro_deg_s = 0.1;
        let mut e = ImuErrors::new(cfg);
        let mut rng = Rng::new(5);
        let (dt, n) = (0.01, 50_000);
        let (mut sa, mut sg) = (0.0, 0.0);
        for _ in 0..n {
            let (dth, dv) = e.corrupt(&mut rng, &Vector3::zeros(), &Vector3::zeros(), dt);
            sa += dv.y * dv.y;
            sg += dth.z * dth.z;
        }
        // Per sample: the rate's RMS is the stated one.
        let acc_rms = (sa / n as f64).sqrt() / dt;
        let gyro_rms = (sg / n as f64).sqrt() / dt;
        assert!((acc_rms / 0.3 - 1.0).abs() < 0.02, "{acc_rms}");
        assert!(
            (gyro_rms / 0.1f64.to_radians() - 1.0).abs() < 0.02,
            "{gyro_rms}"
        );
        let mut bad = SimImuConfig::perfect(100.0);
        bad.vibration_accel_m_s2 = -1.0;
        let mut p = Problems::default();
        bad.validate(&mut p);
        assert!(
            p.list
                .iter()
                .any(|i| i.to_string().contains("vibration_accel_m_s2"))
        );
    }
}
