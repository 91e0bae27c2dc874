//! Restoring the raw IMU from an autopilot's bias-corrected HIGHRES_IMU (PX4), with the
//! uncorrected but quantised SCALED_IMU of the same samples (pure, no I/O; unit-tested here).
//!
//! PX4 v1.14 sends HIGHRES_IMU as its `vehicle_imu` sample minus the primary EKF2's gyro and
//! accelerometer bias estimates (`src/modules/mavlink/streams/HIGHRES_IMU.hpp`), and SCALED_IMU
//! as the same `vehicle_imu` sample without them, cast (truncated toward zero) to int16 mrad/s
//! and mG (`SCALED_IMU.hpp`). EKF2's estimates swing by 100-220 deg/h once it loses the GPS
//! (docs/real-sitl.md, PX4 section): an input error visnav's filter does not model. Neither
//! message alone is the raw IMU; together they give it.
//!
//! Model, per channel `c` (three gyro axes in mrad/s, three accelerometer axes in mG, the SCALED
//! unit; one unit = one LSB):
//!
//! ```text
//! h_c = x_c - b_c          HIGHRES_IMU (float), converted to LSB
//! s_c = trunc(x_c)         SCALED_IMU (int16)
//! ```
//!
//! with `x` the raw sample and `b` EKF2's bias estimate. So `b_c = s_c - h_c + u_c` where
//! `u_c` lies in `[0, 1)` when `s_c > 0`, in `(-1, 0]` when `s_c < 0` and in `(-1, 1)` when
//! `s_c = 0`: every matched pair of messages bounds the bias in an interval (midpoint, half
//! width). When the signal moves by more than about half an LSB from sample to sample (sensor
//! noise, vibration, manoeuvres: jMAVSim's gyro noise is 6 LSB per sample) the fractional part
//! of `x` is uniform and the midpoint is an unbiased estimate of `b` with a standard deviation
//! of `1/sqrt(12)` LSB; a critically damped level + trend tracker (time constant
//! [`AVERAGE_TAU_S`]) brings it to a few deg/h and hundredths of a mG at 250 Hz and follows
//! EKF2's swings (up to about 13 deg/h per second measured) without a lag. Midpoints from `s_c = 0` (a wider, possibly
//! asymmetric interval) and from saturated values are used only to check the pairing.
//!
//! Pairing. The two messages come from separate PX4 streams: usually one after the other for the
//! same sample, but either may be skipped or come first, and their time stamps differ
//! (HIGHRES_IMU `time_usec` is the sample time, SCALED_IMU `time_boot_ms` the publication time
//! in whole ms). So a SCALED_IMU is paired, once [`LOOK_AHEAD`] later HIGHRES_IMU have arrived,
//! with whichever of the HIGHRES_IMU received around it (within [`CANDIDATE_WINDOW_US`]) is
//! consistent with the current bias estimate on all six channels. A wrong candidate differs by
//! a sample-to-sample change on each channel and is rejected; where the signal is so quiet that
//! neighbours agree to an LSB the choice does not matter. Without an estimate (at start, or after
//! [`REBOOTSTRAP_AFTER`] unpaired messages in a row: an EKF2 bias reset) the estimate is
//! bootstrapped from [`BOOT_MESSAGES`] SCALED_IMU: the bias hypothesis consistent with a
//! candidate of at least 80 % of them, and no competing hypothesis as well supported.
//!
//! Gyro scale. PX4's SCALED_IMU divides the gyro's delta angle by the *accelerometer's*
//! integration interval, HIGHRES_IMU by the gyro's. They are equal where one chip samples both at
//! one rate (SITL, ICM-42688-class), but can differ by several percent where the accelerometer and
//! gyro run at different rates (BMI088-class: 6.25 % at 1.6 / 2 kHz), and then `s` is off by that
//! fraction of the rate. Pairs then fail the consistency check when the vehicle rotates, and a
//! bootstrap during a steady turn would take `(k - 1) x rate` for the bias: so a bootstrap uses
//! only gyro midpoints of samples below [`BOOT_GYRO_MAX_LSB`] (at most 1.3 LSB off at 6.25 %) and
//! needs [`BOOT_MIN_PER_CHANNEL`] of them on every channel.
//!
//! A wrong IMU is worse than a biased one: until the bias is known the HIGHRES_IMU sample is
//! passed on unchanged and reported as [`Restored::NotYet`]; a known estimate is held when pairs
//! stop (EKF2's bias moves slowly) for at most [`MAX_HOLD_S`], then the samples pass as sent again
//! ([`Restored::Stale`]); the estimate's age and every unpaired SCALED_IMU are reported.

use std::collections::VecDeque;

/// Standard gravity PX4 uses for mG (`CONSTANTS_ONE_G`), m/s^2.
pub(crate) const G0_M_S2: f64 = 9.806_65;
/// Later HIGHRES_IMU messages awaited before a SCALED_IMU is paired.
pub const LOOK_AHEAD: u64 = 3;
/// HIGHRES_IMU messages received before a SCALED_IMU that are still candidates for it.
pub const LOOK_BEHIND: u64 = 4;
/// Largest difference between a SCALED_IMU's and a candidate HIGHRES_IMU's time stamps, µs.
pub const CANDIDATE_WINDOW_US: u64 = 50_000;
/// SCALED_IMU messages used to bootstrap the estimate.
pub const BOOT_MESSAGES: usize = 40;
/// Unpaired SCALED_IMU in a row after which the estimate is bootstrapped again.
pub const REBOOTSTRAP_AFTER: u32 = 50;
/// Time constant of the bias tracker, s.
pub const AVERAGE_TAU_S: f64 = 0.7;
/// Longest an estimate is applied without a new pair, s.
pub const MAX_HOLD_S: f64 = 5.0;
/// A bootstrap takes gyro midpoints only from samples whose |SCALED_IMU gyro| is at most this,
/// LSB (mrad/s): bounds the error of a gyro scale mismatch between the two messages.
pub const BOOT_GYRO_MAX_LSB: i16 = 20;
/// Usable midpoints a bootstrap needs on every channel.
pub const BOOT_MIN_PER_CHANNEL: u32 = 10;
/// HIGHRES_IMU messages kept for pairing.
const RING: usize = 16;
/// SCALED_IMU messages waiting for later HIGHRES_IMU (beyond: the oldest is dropped, unpaired).
const PENDING_MAX: usize = 64;
/// Consistency tolerance beyond the interval, LSB: float rounding, the estimate's own error.
const TOL_LSB: f64 = 0.3;
/// Tolerance proportional to the value (float rounding; PX4 divides SCALED_IMU's gyro by the
/// accelerometer's integration interval, HIGHRES_IMU's by the gyro's: equal in SITL and where one
/// chip samples both at one rate, several percent apart otherwise, see the module doc).
const TOL_REL: f64 = 1e-3;
/// Bootstrap hypotheses are tested with this much more tolerance (a hypothesis is one midpoint,
/// itself up to half an LSB off), LSB.
const BOOT_TOL_LSB: f64 = 0.6;

/// What [`ImuBiasRestorer::on_highres`] did to a sample.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Restored {
    /// The autopilot's bias estimate was added back.
    Yes,
    /// No estimate yet: the sample is passed on as the autopilot sent it.
    NotYet,
    /// The estimate is older than [`MAX_HOLD_S`]: the sample is passed on as sent.
    Stale,
}

/// Counters and the current estimate, for metrics and logs.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct RestoreStatus {
    /// SCALED_IMU paired with a HIGHRES_IMU.
    pub paired: u64,
    /// SCALED_IMU that no HIGHRES_IMU matched (inconsistent with the estimate, or left over
    /// from a bootstrap that found none).
    pub unpaired: u64,
    /// Times the estimate was bootstrapped (1 after a normal start).
    pub bootstraps: u64,
    /// HIGHRES_IMU samples passed on without the estimate (none yet, or stale).
    pub not_restored: u64,
    /// The autopilot's bias estimate now: gyro rad/s (body FRD), accelerometer m/s^2.
    pub bias: Option<([f64; 3], [f64; 3])>,
    /// HIGHRES_IMU time of the newest pair behind the estimate, µs.
    pub bias_t_us: Option<u64>,
    /// HIGHRES_IMU time of the newest sample, µs.
    pub last_sample_t_us: Option<u64>,
    /// The newest sample had the estimate added back.
    pub restoring: bool,
}

impl RestoreStatus {
    /// Age of the estimate at the newest sample, s.
    pub fn age_s(&self) -> Option<f64> {
        match (self.bias_t_us, self.last_sample_t_us) {
            (Some(b), Some(t)) => Some(t.saturating_sub(b) as f64 * 1e-6),
            _ => None,
        }
    }
}

#[derive(Debug, Clone, Copy)]
struct Hi {
    seq: u64,
    t_us: u64,
    /// Gyro mrad/s, accelerometer mG.
    lsb: [f64; 6],
}

#[derive(Debug, Clone, Copy)]
struct Sc {
    /// HIGHRES_IMU messages received before this one.
    after: u64,
    t_us: u64,
    lsb: [i16; 6],
}

/// The bias interval one (SCALED, HIGHRES) pair gives, per channel: (midpoint, half width).
type Intervals = [(f64, f64); 6];

/// A SCALED_IMU kept for the bootstrap: tolerances, SCALED gyro, candidates.
type BootMsg = ([f64; 6], [i16; 3], Vec<(Intervals, u64)>);

fn intervals(s: &Sc, h: &Hi) -> Intervals {
    std::array::from_fn(|c| {
        let sv = s.lsb[c];
        let r = f64::from(sv) - h.lsb[c];
        if sv == i16::MAX || sv == i16::MIN {
            // Saturated by a saturating cast: no information. (PX4's C cast of an out-of-range
            // float is undefined and wraps on ARM: such a value fails the consistency check.)
            (r, f64::INFINITY)
        } else if sv > 0 {
            (r + 0.5, 0.5)
        } else if sv < 0 {
            (r - 0.5, 0.5)
        } else {
            (r, 1.0)
        }
    })
}

fn tolerances(s: &Sc) -> [f64; 6] {
    std::array::from_fn(|c| TOL_LSB + TOL_REL * f64::from(s.lsb[c]).abs())
}

/// Squared normalised distance of `iv` from `b`, or `None` when a channel is inconsistent
/// (`tol`: the message's [`tolerances`]).
fn score(iv: &Intervals, tol: &[f64; 6], b: &[f64; 6], extra: f64) -> Option<f64> {
    let mut sum = 0.0;
    for c in 0..6 {
        let (mid, hw) = iv[c];
        if !hw.is_finite() {
            continue;
        }
        let lim = hw + tol[c] + extra;
        let d = (mid - b[c]).abs();
        if d.is_nan() || d > lim {
            return None;
        }
        sum += (d / lim).powi(2);
    }
    Some(sum)
}

#[derive(Debug, Clone, Copy)]
struct Estimate {
    /// Bias, LSB.
    b: [f64; 6],
    /// Its rate of change, LSB/s.
    rate: [f64; 6],
    /// SCALED_IMU time of the newest pair (the tracker's clock), µs.
    t_us: u64,
    /// HIGHRES_IMU time of the newest pair, µs.
    t_hi_us: u64,
}

/// Pairs HIGHRES_IMU with SCALED_IMU and adds the autopilot's bias estimate back.
#[derive(Debug, Clone, Default)]
pub struct ImuBiasRestorer {
    ring: VecDeque<Hi>,
    next_seq: u64,
    pending: VecDeque<Sc>,
    /// Bootstrap messages: each one's tolerances, SCALED_IMU gyro and candidate intervals (with
    /// the candidate's HIGHRES_IMU time).
    boot: VecDeque<BootMsg>,
    est: Option<Estimate>,
    /// Bootstrapping again (the held estimate stays applied meanwhile).
    rebootstrap: bool,
    unpaired_run: u32,
    /// Counters; `bias` and `bias_t_us` stay `None` here ([`Self::status`] derives them from
    /// `est`).
    status: RestoreStatus,
}

fn to_lsb(gyro_rad_s: [f64; 3], acc_m_s2: [f64; 3]) -> [f64; 6] {
    [
        gyro_rad_s[0] * 1e3,
        gyro_rad_s[1] * 1e3,
        gyro_rad_s[2] * 1e3,
        acc_m_s2[0] / G0_M_S2 * 1e3,
        acc_m_s2[1] / G0_M_S2 * 1e3,
        acc_m_s2[2] / G0_M_S2 * 1e3,
    ]
}

fn from_lsb(b: &[f64; 6]) -> ([f64; 3], [f64; 3]) {
    (
        [b[0] * 1e-3, b[1] * 1e-3, b[2] * 1e-3],
        [
            b[3] * 1e-3 * G0_M_S2,
            b[4] * 1e-3 * G0_M_S2,
            b[5] * 1e-3 * G0_M_S2,
        ],
    )
}

impl ImuBiasRestorer {
    /// A restorer without an estimate.
    pub fn new() -> Self {
        Self::default()
    }

    /// Forget everything but the counters (autopilot reboot).
    pub fn reset(&mut self) {
        *self = Self {
            status: self.status,
            ..Self::default()
        };
    }

    /// Counters and the current estimate.
    pub fn status(&self) -> RestoreStatus {
        RestoreStatus {
            bias: self.est.map(|e| from_lsb(&e.b)),
            bias_t_us: self.est.map(|e| e.t_hi_us),
            ..self.status
        }
    }

    /// One SCALED_IMU: its time (µs, from `time_boot_ms`), gyro (mrad/s) and accelerometer (mG)
    /// as sent. It is paired once later HIGHRES_IMU have arrived.
    pub fn on_scaled(&mut self, t_us: u64, gyro_mrad_s: [i16; 3], acc_mg: [i16; 3]) {
        if self.pending.len() >= PENDING_MAX {
            self.pending.pop_front();
            self.unpaired();
        }
        self.pending.push_back(Sc {
            after: self.next_seq,
            t_us,
            lsb: [
                gyro_mrad_s[0],
                gyro_mrad_s[1],
                gyro_mrad_s[2],
                acc_mg[0],
                acc_mg[1],
                acc_mg[2],
            ],
        });
    }

    /// One HIGHRES_IMU sample (time µs, gyro rad/s, accelerometer m/s^2, body FRD as sent):
    /// the sample with the autopilot's bias estimate added back, or unchanged before there is
    /// one.
    pub fn on_highres(
        &mut self,
        t_us: u64,
        gyro_rad_s: [f64; 3],
        acc_m_s2: [f64; 3],
    ) -> ([f64; 3], [f64; 3], Restored) {
        let lsb = to_lsb(gyro_rad_s, acc_m_s2);
        if lsb.iter().all(|v| v.is_finite()) {
            self.ring.push_back(Hi {
                seq: self.next_seq,
                t_us,
                lsb,
            });
            self.next_seq += 1;
            while self.ring.len() > RING {
                self.ring.pop_front();
            }
            while self
                .pending
                .front()
                .is_some_and(|s| s.after + LOOK_AHEAD <= self.next_seq)
            {
                if let Some(s) = self.pending.pop_front() {
                    self.pair(&s);
                }
            }
        }
        self.status.last_sample_t_us = Some(t_us);
        let out = match self.est {
            Some(e) if t_us.saturating_sub(e.t_hi_us) as f64 * 1e-6 <= MAX_HOLD_S => {
                let (bg, ba) = from_lsb(&e.b);
                (
                    std::array::from_fn(|i| gyro_rad_s[i] + bg[i]),
                    std::array::from_fn(|i| acc_m_s2[i] + ba[i]),
                    Restored::Yes,
                )
            }
            Some(_) => (gyro_rad_s, acc_m_s2, Restored::Stale),
            None => (gyro_rad_s, acc_m_s2, Restored::NotYet),
        };
        self.status.restoring = out.2 == Restored::Yes;
        if !self.status.restoring {
            self.status.not_restored += 1;
        }
        out
    }

    fn candidates(&self, s: &Sc) -> Vec<(Intervals, u64)> {
        self.ring
            .iter()
            .filter(|h| {
                h.seq + LOOK_BEHIND >= s.after
                    && h.seq < s.after + LOOK_AHEAD
                    && h.t_us.abs_diff(s.t_us) <= CANDIDATE_WINDOW_US
            })
            .map(|h| (intervals(s, h), h.t_us))
            .collect()
    }

    fn unpaired(&mut self) {
        self.status.unpaired += 1;
        self.unpaired_run += 1;
        if self.unpaired_run >= REBOOTSTRAP_AFTER && !self.rebootstrap {
            // The autopilot's estimate jumped (an EKF reset) or the streams changed: bootstrap
            // again, holding the old estimate (for at most MAX_HOLD_S) until a new one is found.
            self.boot.clear();
            self.rebootstrap = true;
        }
    }

    fn pair(&mut self, s: &Sc) {
        let cands = self.candidates(s);
        let tol = tolerances(s);
        if let Some(est) = self.est {
            let best = cands
                .iter()
                .filter_map(|(iv, t)| score(iv, &tol, &est.b, 0.0).map(|q| (q, iv, *t)))
                .min_by(|a, b| a.0.total_cmp(&b.0));
            if let Some((_, iv, t_hi)) = best {
                self.track(s, iv, t_hi, est);
                return;
            }
            self.unpaired();
            if !self.rebootstrap {
                return;
            }
        }
        self.bootstrap_step(s, tol, cands);
    }

    /// One consistent pair: the critically damped level + trend tracker (alpha-beta, time
    /// constant AVERAGE_TAU_S) follows a steady swing of the autopilot's estimate without lag.
    fn track(&mut self, s: &Sc, iv: &Intervals, t_hi_us: u64, est: Estimate) {
        self.unpaired_run = 0;
        if self.rebootstrap {
            self.rebootstrap = false;
            self.boot.clear();
        }
        self.status.paired += 1;
        let dt_s = (s.t_us.saturating_sub(est.t_us) as f64 * 1e-6).clamp(0.0, 0.1);
        let k_level = (2.0 * dt_s / AVERAGE_TAU_S).min(1.0);
        let k_trend = dt_s / (AVERAGE_TAU_S * AVERAGE_TAU_S);
        let mut b = est.b;
        let mut rate = est.rate;
        for c in 0..6 {
            let pred = b[c] + rate[c] * dt_s;
            let (mid, hw) = iv[c];
            if hw <= 0.5 {
                let e = mid - pred;
                b[c] = pred + k_level * e;
                rate[c] += k_trend * e;
            } else {
                b[c] = pred;
            }
        }
        self.set_estimate(b, rate, s.t_us.max(est.t_us), t_hi_us.max(est.t_hi_us));
    }

    fn set_estimate(&mut self, b: [f64; 6], rate: [f64; 6], t_us: u64, t_hi_us: u64) {
        self.est = Some(Estimate {
            b,
            rate,
            t_us,
            t_hi_us,
        });
    }

    fn bootstrap_step(&mut self, s: &Sc, tol: [f64; 6], cands: Vec<(Intervals, u64)>) {
        let gyro_s = [s.lsb[0], s.lsb[1], s.lsb[2]];
        self.boot.push_back((tol, gyro_s, cands));
        if self.boot.len() > BOOT_MESSAGES {
            self.boot.pop_front();
            if self.est.is_none() {
                // Left the window without a bootstrap (with an estimate it was counted already).
                self.status.unpaired += 1;
            }
        }
        if self.boot.len() < BOOT_MESSAGES {
            return;
        }
        // Hypotheses: every candidate midpoint of the newest few messages.
        let hyps: Vec<[f64; 6]> = self
            .boot
            .iter()
            .rev()
            .take(6)
            .flat_map(|(_, _, c)| c)
            .map(|(iv, _)| std::array::from_fn(|c| iv[c].0))
            .collect();
        // (support, hypothesis, sum of usable midpoints, their count per channel, newest HIGHRES
        // time of the supporting pairs).
        type Scored = (usize, [f64; 6], [f64; 6], [u32; 6], u64);
        let support = |h: &[f64; 6]| -> Scored {
            let (mut n, mut sum, mut k, mut t_hi) = (0, [0.0; 6], [0u32; 6], 0u64);
            for (tol, gyro_s, msg) in &self.boot {
                let best = msg
                    .iter()
                    .filter_map(|(iv, t)| score(iv, tol, h, BOOT_TOL_LSB).map(|q| (q, iv, *t)))
                    .min_by(|a, b| a.0.total_cmp(&b.0));
                if let Some((_, iv, t)) = best {
                    n += 1;
                    t_hi = t_hi.max(t);
                    for c in 0..6 {
                        // Gyro channels only from slow samples (a scale mismatch between the
                        // two messages grows with the rate: module doc).
                        let slow = c >= 3 || gyro_s[c].unsigned_abs() <= BOOT_GYRO_MAX_LSB as u16;
                        if iv[c].1 <= 0.5 && slow {
                            sum[c] += iv[c].0;
                            k[c] += 1;
                        }
                    }
                }
            }
            (n, *h, sum, k, t_hi)
        };
        let mut scored: Vec<Scored> = hyps.iter().map(support).collect();
        scored.sort_by_key(|h| std::cmp::Reverse(h.0));
        let need = BOOT_MESSAGES * 4 / 5;
        let Some(&(n, h, sum, k, t_hi)) = scored.first() else {
            return;
        };
        // Well supported, with usable midpoints on every channel (a gyro axis that read 0 in
        // every sample, or only fast samples, bounds nothing).
        if n < need || k.iter().any(|&kc| kc < BOOT_MIN_PER_CHANNEL) {
            return;
        }
        // A competing hypothesis as well supported but more than 2 LSB away: ambiguous.
        let rival = scored.iter().skip(1).any(|(m, g, _, _, _)| {
            *m >= need && (0..6).any(|c| (g[c] - h[c]).abs() > 2.0 + tol[c])
        });
        if rival {
            return;
        }
        let b: [f64; 6] = std::array::from_fn(|c| sum[c] / f64::from(k[c]));
        self.boot.clear();
        self.rebootstrap = false;
        self.unpaired_run = 0;
        self.status.bootstraps += 1;
        self.set_estimate(b, [0.0; 6], s.t_us, t_hi);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use visnav_core::rng::Rng;

    const DEG_H: f64 = std::f64::consts::PI / 180.0 / 3600.0; // rad/s per deg/h

    /// A PX4-like pair of streams at 250 Hz: `raw(t)` the sample, `bias(t)` EKF2's estimate.
    /// HIGHRES_IMU = raw - bias (f32), SCALED_IMU = trunc(raw) (int16 mrad/s, mG), sent in
    /// random order, each skipped now and then.
    struct Px4Streams {
        rng: Rng,
        gyro_noise_rad_s: f64,
        acc_noise_m_s2: f64,
        skip: f64,
        /// SCALED_IMU from another IMU instance (independent noise) than HIGHRES_IMU.
        other_instance: bool,
        /// Manoeuvre amplitude (1: turns up to 0.3 rad/s; 0: still).
        motion: f64,
        /// SCALED_IMU's gyro scale against HIGHRES_IMU's (PX4 divides by the accelerometer's
        /// interval: 1.0625 for a 1.6 / 2 kHz accelerometer / gyro).
        scaled_gyro_scale: f64,
        /// SCALED_IMU stops after this time, s.
        scaled_until_s: f64,
    }

    #[derive(Debug, Clone, Copy)]
    struct Out {
        raw: ([f64; 3], [f64; 3]),
        sent: ([f64; 3], [f64; 3]),
        restored: ([f64; 3], [f64; 3], Restored),
    }

    fn f32r(v: f64) -> f64 {
        f64::from(v as f32)
    }

    impl Px4Streams {
        fn new(seed: u64) -> Self {
            Self {
                rng: Rng::new(seed),
                gyro_noise_rad_s: 0.006,
                acc_noise_m_s2: 0.03,
                skip: 0.03,
                other_instance: false,
                motion: 1.0,
                scaled_gyro_scale: 1.0,
                scaled_until_s: f64::INFINITY,
            }
        }

        fn sample(&mut self, t: f64) -> ([f64; 3], [f64; 3]) {
            let w = self.motion * 0.3 * (0.4 * t).sin(); // manoeuvres
            let g = [
                w + self.gyro_noise_rad_s * self.rng.normal(),
                0.5 * w + self.gyro_noise_rad_s * self.rng.normal(),
                self.motion * 0.08 * (0.25 * t).sin() + self.gyro_noise_rad_s * self.rng.normal(),
            ];
            let a = [
                0.8 * w + self.acc_noise_m_s2 * self.rng.normal(),
                -0.3 + self.acc_noise_m_s2 * self.rng.normal(),
                -G0_M_S2 + self.acc_noise_m_s2 * self.rng.normal(),
            ];
            (g, a)
        }

        /// Run `dur_s` through `r`; `bias(t)` gives (gyro rad/s, accel m/s^2).
        fn run(
            &mut self,
            r: &mut ImuBiasRestorer,
            dur_s: f64,
            bias: impl Fn(f64) -> ([f64; 3], [f64; 3]),
        ) -> Vec<(f64, Out)> {
            let mut out = Vec::new();
            let n = (dur_s * 250.0) as usize;
            for k in 0..n {
                let t = k as f64 / 250.0;
                let t_us = (t * 1e6) as u64;
                let (g, a) = self.sample(t);
                let (bg, ba) = bias(t);
                let hg: [f64; 3] = std::array::from_fn(|i| f32r(g[i] - bg[i]));
                let ha: [f64; 3] = std::array::from_fn(|i| f32r(a[i] - ba[i]));
                let (sg, sa) = if self.other_instance {
                    self.sample(t)
                } else {
                    (g, a)
                };
                let sgi = sg.map(|v| (f32r(v * self.scaled_gyro_scale) * 1000.0) as i16);
                let sai = sa.map(|v| (f32r(v) * 1000.0 / G0_M_S2) as i16);
                let t_pub_us = t_us + 300;
                let scaled_first = self.rng.uniform() < 0.5;
                let skip_h = self.rng.uniform() < self.skip;
                let skip_s = self.rng.uniform() < self.skip || t >= self.scaled_until_s;
                if scaled_first && !skip_s {
                    r.on_scaled(t_pub_us / 1000 * 1000, sgi, sai);
                }
                if !skip_h {
                    let restored = r.on_highres(t_us, hg, ha);
                    out.push((
                        t,
                        Out {
                            raw: (g, a),
                            sent: (hg, ha),
                            restored,
                        },
                    ));
                }
                if !scaled_first && !skip_s {
                    r.on_scaled(t_pub_us / 1000 * 1000, sgi, sai);
                }
            }
            out
        }
    }

    /// (RMS, max) over samples after `t0` of the gyro error (deg/h) and accel error (mG) of
    /// the restored sample against the raw one (restored samples only), and the same for the
    /// sample as sent.
    fn errors(out: &[(f64, Out)], t0: f64) -> ((f64, f64, f64, f64), (f64, f64)) {
        let (mut sg, mut mg, mut sa, mut ma, mut n) = (0.0, 0.0f64, 0.0, 0.0f64, 0.0);
        let (mut sent_sg, mut sent_n) = (0.0, 0.0);
        for (t, o) in out.iter().filter(|(t, _)| *t >= t0) {
            let _ = t;
            for i in 0..3 {
                let e = (o.sent.0[i] - o.raw.0[i]) / DEG_H;
                sent_sg += e * e;
                sent_n += 1.0;
            }
            if o.restored.2 != Restored::Yes {
                continue;
            }
            for i in 0..3 {
                let eg = (o.restored.0[i] - o.raw.0[i]) / DEG_H;
                let ea = (o.restored.1[i] - o.raw.1[i]) / G0_M_S2 * 1e3;
                sg += eg * eg;
                sa += ea * ea;
                mg = mg.max(eg.abs());
                ma = ma.max(ea.abs());
                n += 1.0;
            }
        }
        assert!(n > 0.0, "no restored sample after {t0} s");
        (
            ((sg / n).sqrt(), mg, (sa / n).sqrt(), ma),
            ((sent_sg / sent_n).sqrt(), n / 3.0),
        )
    }

    /// EKF2's estimate swinging as measured in jMAVSim flight jm-v2 (x: -14, -125, -189, -55
    /// deg/h at +0 / 10 / 20 / 30 s: up to 13 deg/h per second) and SIH's accelerometer
    /// (-5 to -14 mg): 200 deg/h, 10 mg, up to 14 deg/h per second.
    fn swing(t: f64) -> ([f64; 3], [f64; 3]) {
        let s = (2.0 * std::f64::consts::PI * t / 90.0).sin();
        let c = (2.0 * std::f64::consts::PI * t / 60.0).cos();
        (
            [200.0 * DEG_H * s, -150.0 * DEG_H * c, 80.0 * DEG_H * s],
            [0.1 * s, -0.08 * c, 0.05 * c],
        )
    }

    #[test]
    fn restores_a_swinging_bias_from_shuffled_streams() {
        let mut r = ImuBiasRestorer::new();
        let out = Px4Streams::new(1).run(&mut r, 60.0, swing);
        let ((g_rms, g_max, a_rms, a_max), (sent_rms, n)) = errors(&out, 1.0);
        eprintln!(
            "restored: gyro RMS {g_rms:.2} max {g_max:.1} deg/h, accel RMS {a_rms:.3} max {a_max:.3} mG; \
             as sent: gyro RMS {sent_rms:.1} deg/h; {:?}",
            r.status()
        );
        // What visnav integrated before: the swing itself.
        assert!(sent_rms > 100.0, "sent error {sent_rms} deg/h");
        assert!(g_rms < 8.0 && g_max < 30.0, "gyro {g_rms} / {g_max} deg/h");
        assert!(a_rms < 0.1 && a_max < 0.4, "accel {a_rms} / {a_max} mG");
        let st = r.status();
        assert_eq!(st.bootstraps, 1);
        // Almost every SCALED_IMU whose HIGHRES_IMU was not skipped is paired.
        assert!(st.paired > 14_000 && st.unpaired < 600, "{st:?}");
        assert!(n > 14_000.0);
        // Restored within the first half second.
        let first = out.iter().find(|(_, o)| o.restored.2 == Restored::Yes);
        assert!(
            first.is_some_and(|(t, _)| *t < 0.5),
            "{:?}",
            first.map(|f| f.0)
        );
    }

    #[test]
    fn imu_at_rest_with_little_noise_is_still_bounded() {
        // Noise of 0.4 LSB: the fractional part is no longer uniform, yet every pair's interval
        // holds the bias, so the estimate stays within about half an LSB (103 deg/h, 0.5 mG).
        let mut s = Px4Streams::new(2);
        s.gyro_noise_rad_s = 0.0004;
        s.acc_noise_m_s2 = 0.004;
        let mut r = ImuBiasRestorer::new();
        let out = s.run(&mut r, 20.0, |_| {
            ([0.0004, -0.0012, 0.0021], [0.05, -0.02, 0.1])
        });
        let ((g_rms, g_max, a_rms, a_max), _) = errors(&out, 2.0);
        assert!(
            g_max < 110.0 && g_rms < 60.0,
            "gyro {g_rms} / {g_max} deg/h"
        );
        assert!(a_max < 0.6 && a_rms < 0.4, "accel {a_rms} / {a_max} mG");
    }

    #[test]
    fn scaled_imu_of_another_imu_is_never_paired() {
        // PX4's SCALED_IMU is instance 0; HIGHRES_IMU the selected IMU. If they differ nothing
        // may be restored: the samples pass unchanged and are counted.
        let mut s = Px4Streams::new(3);
        s.other_instance = true;
        let mut r = ImuBiasRestorer::new();
        let out = s.run(&mut r, 20.0, swing);
        assert!(out.iter().all(|(_, o)| o.restored.2 == Restored::NotYet));
        assert!(
            out.iter()
                .all(|(_, o)| o.restored.0 == o.sent.0 && o.restored.1 == o.sent.1)
        );
        let st = r.status();
        assert_eq!((st.paired, st.bootstraps), (0, 0), "{st:?}");
        assert_eq!(st.bias, None);
        assert!(st.not_restored as usize == out.len());
    }

    #[test]
    fn a_jump_of_the_autopilot_estimate_is_found_again() {
        // An EKF reset moves the estimate by 1000 deg/h at once in cruise (slow manoeuvres):
        // the pairing fails, the held estimate stays applied, and a new one is bootstrapped
        // within a second. (While the vehicle turns faster than BOOT_GYRO_MAX_LSB a bootstrap
        // waits: `a_gyro_scale_mismatch_between_the_messages_never_adds_a_large_error`.)
        let mut r = ImuBiasRestorer::new();
        let mut streams = Px4Streams::new(4);
        streams.motion = 0.05;
        let jump = |t: f64| {
            let (mut g, a) = swing(t);
            if t >= 20.0 {
                g[1] += 1000.0 * DEG_H;
            }
            (g, a)
        };
        let out = streams.run(&mut r, 30.0, jump);
        let ((g_rms, g_max, _, _), _) = errors(&out[..out.len() * 19 / 30], 1.0);
        assert!(g_rms < 8.0 && g_max < 30.0, "before: {g_rms} / {g_max}");
        let after: Vec<_> = out.iter().copied().filter(|(t, _)| *t >= 21.0).collect();
        let ((g_rms, g_max, _, _), _) = errors(&after, 21.0);
        assert!(g_rms < 8.0 && g_max < 30.0, "after: {g_rms} / {g_max}");
        assert_eq!(r.status().bootstraps, 2);
    }

    #[test]
    fn hostile_values_do_not_panic_or_poison() {
        let mut r = ImuBiasRestorer::new();
        let mut s = Px4Streams::new(5);
        let _ = s.run(&mut r, 2.0, swing);
        let before = r.status().bias;
        r.on_scaled(0, [i16::MIN, i16::MAX, 0], [i16::MAX, i16::MIN, 0]);
        let (g, _, _) = r.on_highres(2_000_000, [f64::NAN, 0.0, 0.0], [0.0, 0.0, f64::INFINITY]);
        assert!(g[0].is_nan()); // passed on as sent: the caller drops non-finite samples
        for k in 0..10 {
            r.on_highres(2_004_000 + k * 4000, [1e9, -1e9, 0.0], [1e9, 0.0, -1e9]);
        }
        let st = r.status();
        assert!(
            st.bias
                .is_some_and(|b| b.0.iter().chain(&b.1).all(|v| v.is_finite()))
        );
        let moved = |b: ([f64; 3], [f64; 3])| {
            let a = before.unwrap_or(b);
            (0..3).map(|i| (b.0[i] - a.0[i]).abs()).fold(0.0, f64::max)
        };
        assert!(
            st.bias.is_some_and(|b| moved(b) < 1e-4),
            "{st:?} {before:?}"
        );
        r.reset();
        assert_eq!(r.status().bias, None);
        assert!(r.status().paired > 0);
    }

    #[test]
    fn a_still_scaled_imu_of_another_imu_is_not_taken_either() {
        // Both IMUs quiet on the ground (noise 0.3 LSB): the gyro reads 0 in almost every
        // sample and bounds nothing, so no bootstrap can be made of it.
        let mut s = Px4Streams::new(6);
        s.other_instance = true;
        s.motion = 0.0;
        s.gyro_noise_rad_s = 0.0003;
        s.acc_noise_m_s2 = 0.002;
        let mut r = ImuBiasRestorer::new();
        let out = s.run(&mut r, 20.0, |_| ([0.0; 3], [0.0; 3]));
        assert!(out.iter().all(|(_, o)| o.restored.2 == Restored::NotYet));
        let st = r.status();
        assert_eq!((st.paired, st.bootstraps), (0, 0), "{st:?}");
        assert!(st.unpaired > 4000, "{st:?}");
    }

    #[test]
    fn the_estimate_is_held_five_seconds_then_samples_pass_as_sent() {
        let mut s = Px4Streams::new(7);
        s.scaled_until_s = 10.0;
        let mut r = ImuBiasRestorer::new();
        let out = s.run(&mut r, 20.0, swing);
        for (t, o) in &out {
            let want = if *t < 10.0 + MAX_HOLD_S - 0.05 && *t > 2.0 {
                Restored::Yes
            } else if *t > 10.0 + MAX_HOLD_S + 0.05 {
                Restored::Stale
            } else {
                continue;
            };
            assert_eq!(o.restored.2, want, "at {t} s");
            if want == Restored::Stale {
                assert_eq!((o.restored.0, o.restored.1), o.sent);
            }
        }
        let st = r.status();
        assert!(
            !st.restoring && st.age_s().is_some_and(|a| a > 9.0),
            "{st:?}"
        );
    }

    #[test]
    fn a_gyro_scale_mismatch_between_the_messages_never_adds_a_large_error() {
        // SCALED_IMU's gyro 6.25 % larger (a 1.6 kHz accelerometer beside a 2 kHz gyro). Pairs
        // fail while the vehicle turns, and a bootstrap in a turn must not take the scale error
        // for a bias: the restored gyro may be biased a little, never by the turn rate's 6 %.
        let mut s = Px4Streams::new(8);
        s.scaled_gyro_scale = 1.0625;
        let mut r = ImuBiasRestorer::new();
        let out = s.run(&mut r, 60.0, swing);
        let worst = out
            .iter()
            .filter(|(_, o)| o.restored.2 == Restored::Yes)
            .flat_map(|(_, o)| (0..3).map(move |i| ((o.restored.0[i] - o.raw.0[i]) / DEG_H).abs()))
            .fold(0.0, f64::max);
        let st = r.status();
        eprintln!("gyro scale mismatch 6.25 %: worst restored gyro error {worst:.0} deg/h; {st:?}");
        // The bias swing as sent reaches 200 deg/h; 6.25 % of the 0.3 rad/s turns is 3900 deg/h.
        // The little bias that remains is the scale mismatch of the slow samples a bootstrap
        // averages (below 20 LSB: up to 1.25 LSB, 258 deg/h) and of the pairs that pass the
        // consistency check while the estimate is held, so it depends on the noise realisation:
        // over seeds 1-200 the worst error has median 143 deg/h, maximum 338 (this seed 300; the
        // former generator: median 145, maximum 276). 450 deg/h (2.2 LSB) bounds that
        // distribution and stays a ninth of the turn-rate error the test guards against.
        assert!(worst < 450.0, "worst restored gyro error {worst} deg/h");
    }
}
