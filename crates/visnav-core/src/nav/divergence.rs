//! When may the filter give up its own position for the fixes it keeps rejecting?
//!
//! A run of position fixes rejected by the innovation gate means one of two things: the filter
//! has diverged (its position is off by more than it claims) or the fixes are wrong (a vision
//! relocalisation over repetitive ground, a jumping receiver). Resetting onto the fix is right only
//! in the first case. Then the rejected fixes agree with each other: their innovations
//! `d_i = z_i - h(x_i)` (fix minus the filter's prediction at the fix's capture time) follow the
//! filter's own error, which changes smoothly, `d(t) = a + b t` (an offset plus the drift of a
//! velocity error). Wrong fixes scatter instead (relocalisations without a prior land hundreds of
//! metres apart).
//!
//! Test: a weighted least-squares line per horizontal axis through the window's innovations
//! (weights: each fix's own horizontal variance plus `DRIFT_ACCEL_M_S2`-driven curvature over the
//! window); the residual sum of squares is chi-square with `2 (n - 2)` degrees of freedom when the
//! fixes are consistent. The window is accepted for a reset when it is below the
//! `CONSISTENCY_PROB` quantile. With fewer than 3 fixes nothing can be tested and no reset is
//! allowed.
//!
//! # Steps
//! Consistent fixes can still be wrong together: a receiver that jumps (10 km for 4 s) or is
//! spoofed, a relocalisation repeated on the same wrong place. What tells a drifting filter from
//! a stepping source is how fast the disagreement appeared. Since the last accepted position fix
//! (`dt` seconds before the window's middle) the filter's error can have grown by at most
//! [`plausible_drift_m`]`(dt)`: a velocity error of [`DRIFT_VEL_M_S`] plus the
//! [`DRIFT_ACCEL_M_S2`] acceleration error, `v dt + a dt^2 / 2`. A fitted offset beyond that is a
//! step, and the filter resets onto it at once only when its own velocity is contradicted as
//! well (a velocity measurement was rejected since the last accepted position fix: the IMU or
//! the filter went wrong, not the position source). Otherwise the fixes must keep being rejected
//! for `nav.health.step_reset_s` before the filter follows them; a short jump never moves it.
//!
//! The reset also takes the fitted drift: `b` is the rate of the innovation, i.e. the filter's
//! horizontal velocity error with the sign of a correction (`v <- v + b`), with its variance
//! from the same weighted fit.

use std::collections::VecDeque;

use nalgebra::Vector2;

use crate::stats::chi2_quantile;

/// Probability of the chi-square quantile that accepts a window as consistent: 99.9 %, so a
/// truly diverged filter with honest fixes is refused only once in a thousand windows, while
/// fixes scattered by several sigmas are refused.
pub const CONSISTENCY_PROB: f64 = 0.999;

/// Unmodelled change of the filter's error over the window beyond a constant velocity error
/// (an acceleration error: a tilt error of about 1 deg gives 0.17 m/s^2; 0.5 m/s^2 covers 3 deg),
/// m/s^2. Enters each fix's variance as `(0.5 a (t - t_mid)^2)^2`.
pub const DRIFT_ACCEL_M_S2: f64 = 0.5;

/// Velocity error a filter can carry beyond what it claims (after a minute unaided, or an IMU
/// fault below the clip), m/s: the first term of [`plausible_drift_m`].
pub const DRIFT_VEL_M_S: f64 = 10.0;

/// How far the filter's position error can have grown in `dt_s` seconds without any fix being
/// accepted: `DRIFT_VEL_M_S dt + DRIFT_ACCEL_M_S2 dt^2 / 2`, m (see "Steps").
pub fn plausible_drift_m(dt_s: f64) -> f64 {
    let dt = dt_s.max(0.0);
    DRIFT_VEL_M_S * dt + 0.5 * DRIFT_ACCEL_M_S2 * dt * dt
}

/// The weighted line through the window's innovations (see the module doc).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WindowFit {
    /// Residual chi-square of the fit.
    pub chi2: f64,
    /// Middle of the window (mean capture time), s.
    pub t_mid_s: f64,
    /// Fitted innovation at `t_mid_s` (north, east), m.
    pub offset_ne_m: Vector2<f64>,
    /// Fitted rate of the innovation (north, east), m/s: the filter's velocity error with the
    /// sign of a correction.
    pub rate_ne_m_s: Vector2<f64>,
    /// Variance of each rate component, (m/s)^2 (infinite when the window has no time span).
    pub rate_var_m2_s2: f64,
    /// Mean horizontal variance of the fixes themselves, m^2.
    pub fix_var_mean_m2: f64,
}

/// The run of rejected fixes a consistent window belongs to, for the step rule.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RejectRun {
    /// Capture time of the last accepted position fix, s (`None`: none since the start).
    pub last_accepted_s: Option<f64>,
    /// Capture time of the first rejected fix of the run, s.
    pub first_rejected_s: f64,
    /// Capture time of the latest rejected fix, s.
    pub latest_s: f64,
    /// A velocity measurement was rejected since the last accepted position fix.
    pub velocity_contradicted: bool,
}

/// Whether a consistent window may reset the filter now (module doc, "Steps"): at once when the
/// filter could have drifted that far (its fitted offset within [`plausible_drift_m`] of the
/// time since the last accepted fix, plus 3 sigma of the fixes' own noise) or its velocity is
/// contradicted too; else once the run has lasted `step_reset_s`.
pub fn reset_allowed(
    fit: &WindowFit,
    run: &RejectRun,
    step_reset_s: f64,
) -> Result<(), Inconsistent> {
    let Some(last) = run.last_accepted_s else {
        return Ok(());
    };
    if run.velocity_contradicted {
        return Ok(());
    }
    let since_s = (fit.t_mid_s - last).max(0.0);
    let offset_m = fit.offset_ne_m.norm();
    let allowed_m = plausible_drift_m(since_s) + 3.0 * fit.fix_var_mean_m2.max(0.0).sqrt();
    let lasted_s = run.latest_s - run.first_rejected_s;
    if offset_m <= allowed_m || lasted_s >= step_reset_s {
        return Ok(());
    }
    Err(Inconsistent::Step {
        offset_m,
        since_s,
        wait_s: step_reset_s,
    })
}

/// Why the held rejected fixes are not a position to reset onto.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum Inconsistent {
    /// The fixes agree with each other but lie further from the filter than it could have
    /// drifted since the last accepted fix: a reset waits until the run has lasted `wait_s`.
    #[error(
        "the rejected fixes stepped {offset_m:.0} m away in {since_s:.1} s (the filter's error \
         cannot grow that fast): waiting for {wait_s:.0} s of them before a reset"
    )]
    Step {
        /// Size of the fixes' fitted horizontal offset from the filter's prediction, metres.
        offset_m: f64,
        /// Time from the last accepted fix to the window's middle, seconds.
        since_s: f64,
        /// How long the run must last before a reset (`step_reset_s`), seconds.
        wait_s: f64,
    },
    /// Fewer than 3 fixes held: an offset and a drift leave nothing to test.
    #[error("{n} rejected fixes cannot be checked against each other")]
    TooFew {
        /// Fixes held.
        n: usize,
    },
    /// A held fix has a time, innovation or variance that is not finite (or a variance not
    /// positive).
    #[error("a rejected fix has a non-finite value")]
    NonFinite,
    /// The fixes' residuals about the fitted offset and drift fail the chi-square test.
    #[error("the {n} rejected fixes disagree with each other (chi-square {chi2:.1} > {gate:.1})")]
    Disagree {
        /// Fixes held.
        n: usize,
        /// Weighted residual sum of squares of the fit.
        chi2: f64,
        /// The chi-square quantile it must not exceed (`2 (n - 2)` degrees of freedom).
        gate: f64,
    },
}

/// One rejected fix: capture time, horizontal innovation (north, east; fix minus prediction) and
/// the fix's own horizontal variance (largest eigenvalue of its north/east block).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RejectedFix {
    /// Capture time, s (any epoch, the same for the whole window).
    pub t_s: f64,
    /// Innovation north / east, m.
    pub innov_ne_m: Vector2<f64>,
    /// Horizontal variance of the fix, m^2.
    pub var_h_m2: f64,
}

/// The window of the latest consecutive rejected position fixes.
#[derive(Debug, Clone, Default)]
pub struct RejectedWindow {
    fixes: VecDeque<RejectedFix>,
}

impl RejectedWindow {
    /// Add a rejected fix, keeping the newest `cap`.
    pub fn push(&mut self, f: RejectedFix, cap: usize) {
        self.fixes.push_back(f);
        while self.fixes.len() > cap.max(1) {
            self.fixes.pop_front();
        }
    }

    /// Forget the window (a fix was accepted, or the filter was reset).
    pub fn clear(&mut self) {
        self.fixes.clear();
    }

    /// Number of fixes held.
    pub fn len(&self) -> usize {
        self.fixes.len()
    }

    /// Whether the window is empty.
    pub fn is_empty(&self) -> bool {
        self.fixes.is_empty()
    }

    /// Capture time of the oldest held fix, s.
    pub fn first_t_s(&self) -> Option<f64> {
        self.fixes.front().map(|f| f.t_s)
    }

    /// Whether the held fixes agree with each other up to an offset and a drift of the filter
    /// (see the module doc): the fit when they do, the reason otherwise.
    pub fn consistent(&self) -> Result<WindowFit, Inconsistent> {
        let n = self.fixes.len();
        if n < 3 {
            return Err(Inconsistent::TooFew { n });
        }
        if self.fixes.iter().any(|f| {
            !(f.t_s.is_finite() && f.var_h_m2 > 0.0 && f.innov_ne_m.iter().all(|v| v.is_finite()))
        }) {
            return Err(Inconsistent::NonFinite);
        }
        let t_mid = self.fixes.iter().map(|f| f.t_s).sum::<f64>() / n as f64;
        let w: Vec<f64> = self
            .fixes
            .iter()
            .map(|f| {
                let c = 0.5 * DRIFT_ACCEL_M_S2 * (f.t_s - t_mid).powi(2);
                1.0 / (f.var_h_m2 + c * c)
            })
            .collect();
        // Weighted least squares of d = a + b (t - t_mid), per axis.
        let (mut sw, mut st, mut stt) = (0.0, 0.0, 0.0);
        for (f, wi) in self.fixes.iter().zip(&w) {
            let t = f.t_s - t_mid;
            sw += wi;
            st += wi * t;
            stt += wi * t * t;
        }
        let det = sw * stt - st * st;
        let spans = det.abs() > 1e-12 * sw * stt.max(1e-12);
        let mut chi2 = 0.0;
        let (mut offset, mut rate) = (Vector2::zeros(), Vector2::zeros());
        for axis in 0..2 {
            let (mut sd, mut std) = (0.0, 0.0);
            for (f, wi) in self.fixes.iter().zip(&w) {
                let t = f.t_s - t_mid;
                sd += wi * f.innov_ne_m[axis];
                std += wi * t * f.innov_ne_m[axis];
            }
            let (a, b) = if spans {
                ((stt * sd - st * std) / det, (sw * std - st * sd) / det)
            } else {
                (sd / sw, 0.0) // all at one time: the mean
            };
            offset[axis] = a;
            rate[axis] = b;
            for (f, wi) in self.fixes.iter().zip(&w) {
                let r = f.innov_ne_m[axis] - a - b * (f.t_s - t_mid);
                chi2 += wi * r * r;
            }
        }
        let dof = 2.0 * (n as f64 - 2.0);
        let gate = chi2_quantile(dof, CONSISTENCY_PROB);
        if chi2 <= gate {
            Ok(WindowFit {
                chi2,
                t_mid_s: t_mid,
                offset_ne_m: offset,
                rate_ne_m_s: rate,
                rate_var_m2_s2: if spans { sw / det } else { f64::INFINITY },
                fix_var_mean_m2: self.fixes.iter().map(|f| f.var_h_m2).sum::<f64>() / n as f64,
            })
        } else {
            Err(Inconsistent::Disagree { n, chi2, gate })
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fix(t_s: f64, n: f64, e: f64, sigma: f64) -> RejectedFix {
        RejectedFix {
            t_s,
            innov_ne_m: Vector2::new(n, e),
            var_h_m2: sigma * sigma,
        }
    }

    fn window(f: &[RejectedFix]) -> RejectedWindow {
        let mut w = RejectedWindow::default();
        for x in f {
            w.push(*x, 5);
        }
        w
    }

    #[test]
    fn a_diverged_filter_with_honest_fixes_is_consistent() {
        // The filter is 300 m off and drifting 8 m/s east; the fixes scatter by their 20 m sigma.
        let noise = [
            (12.0, -8.0),
            (-15.0, 4.0),
            (3.0, 18.0),
            (-6.0, -20.0),
            (9.0, 7.0),
        ];
        let f: Vec<_> = noise
            .iter()
            .enumerate()
            .map(|(i, (dn, de))| {
                let t = i as f64 * 0.5;
                fix(t, 300.0 + dn, -100.0 + 8.0 * t + de, 20.0)
            })
            .collect();
        let w = window(&f);
        assert!(w.consistent().is_ok(), "{:?}", w.consistent());
    }

    #[test]
    fn scattered_relocalisations_are_refused() {
        // Fixes 300-600 m apart, each claiming 40 m.
        let f = [
            fix(0.0, 310.0, -40.0, 40.0),
            fix(0.5, -250.0, 380.0, 40.0),
            fix(1.0, 20.0, 600.0, 40.0),
            fix(1.5, 500.0, 90.0, 40.0),
            fix(2.0, -330.0, -280.0, 40.0),
        ];
        let w = window(&f);
        let e = w.consistent().unwrap_err();
        assert!(matches!(e, Inconsistent::Disagree { n: 5, .. }), "{e:?}");
        assert!(
            e.to_string().contains("the 5 rejected fixes disagree"),
            "{e}"
        );
    }

    #[test]
    fn one_wild_fix_among_consistent_ones_is_refused() {
        let mut f: Vec<_> = (0..5).map(|i| fix(i as f64, 200.0, 50.0, 15.0)).collect();
        f[2].innov_ne_m.x += 250.0;
        assert!(window(&f).consistent().is_err());
    }

    #[test]
    fn too_few_or_non_finite_fixes_never_allow_a_reset() {
        let w = window(&[fix(0.0, 100.0, 0.0, 10.0), fix(1.0, 100.0, 0.0, 10.0)]);
        assert!(w.consistent().is_err());
        let w = window(&[
            fix(0.0, 100.0, 0.0, 10.0),
            fix(1.0, f64::NAN, 0.0, 10.0),
            fix(2.0, 100.0, 0.0, 10.0),
        ]);
        assert!(w.consistent().is_err());
    }

    #[test]
    fn the_window_keeps_the_newest() {
        let mut w = RejectedWindow::default();
        for i in 0..8 {
            w.push(fix(i as f64, 0.0, 0.0, 1.0), 5);
        }
        assert_eq!(w.len(), 5);
        w.clear();
        assert!(w.is_empty());
    }

    fn fit_of(offset_n: f64, t_mid: f64, sigma: f64) -> WindowFit {
        WindowFit {
            chi2: 1.0,
            t_mid_s: t_mid,
            offset_ne_m: Vector2::new(offset_n, 0.0),
            rate_ne_m_s: Vector2::zeros(),
            rate_var_m2_s2: 1.0,
            fix_var_mean_m2: sigma * sigma,
        }
    }

    #[test]
    fn a_step_the_filter_cannot_have_drifted_waits_for_step_reset_s() {
        let run = |last: f64, first: f64, latest: f64, vel: bool| RejectRun {
            last_accepted_s: Some(last),
            first_rejected_s: first,
            latest_s: latest,
            velocity_contradicted: vel,
        };
        // A 10 km jump 0.6 s after the last accepted GPS fix: a step.
        let f = fit_of(10_000.0, 100.6, 1.5);
        let e = reset_allowed(&f, &run(100.0, 100.2, 101.0, false), 10.0);
        assert!(matches!(e, Err(Inconsistent::Step { .. })), "{e:?}");
        // ... unless the filter's velocity is contradicted too (an IMU fault), or it lasted.
        assert_eq!(
            reset_allowed(&f, &run(100.0, 100.2, 101.0, true), 10.0),
            Ok(())
        );
        assert_eq!(
            reset_allowed(&f, &run(100.0, 100.2, 110.2, false), 10.0),
            Ok(())
        );
        assert!(reset_allowed(&f, &run(100.0, 100.2, 110.1, false), 10.0).is_err());
        // 300 m after a minute unaided: a drift (10 m/s x 60 s + 0.25 x 3600 = 1500 m allowed).
        let f = fit_of(300.0, 160.0, 3.0);
        assert_eq!(
            reset_allowed(&f, &run(100.0, 158.0, 162.0, false), 10.0),
            Ok(())
        );
        // The fixes' own noise widens the allowance: 40 m after 1 s with 10 m fixes is a drift.
        assert_eq!(
            reset_allowed(
                &fit_of(40.0, 101.0, 10.0),
                &run(100.0, 100.5, 101.5, false),
                10.0
            ),
            Ok(())
        );
        assert!(
            reset_allowed(
                &fit_of(40.0, 101.0, 1.0),
                &run(100.0, 100.5, 101.5, false),
                10.0
            )
            .is_err()
        );
        // Never an accepted fix: nothing to step from.
        let none = RejectRun {
            last_accepted_s: None,
            ..run(0.0, 100.0, 101.0, false)
        };
        assert_eq!(reset_allowed(&fit_of(1e4, 100.5, 1.0), &none, 10.0), Ok(()));
    }

    #[test]
    fn the_fit_returns_the_drift_of_a_diverging_filter() {
        // Innovations 20 m + 3 m/s x t north, -2 m/s x t east.
        let f: Vec<_> = (0..5)
            .map(|k| {
                let t = k as f64;
                fix(t, 20.0 + 3.0 * t, -2.0 * t, 1.0)
            })
            .collect();
        let fit = window(&f).consistent().expect("consistent");
        assert!(
            (fit.rate_ne_m_s - Vector2::new(3.0, -2.0)).norm() < 1e-9,
            "{fit:?}"
        );
        assert!(
            (fit.offset_ne_m - Vector2::new(26.0, -4.0)).norm() < 1e-9,
            "{fit:?}"
        );
        assert!((fit.t_mid_s - 2.0).abs() < 1e-12);
        assert!(
            fit.rate_var_m2_s2 > 0.0 && fit.rate_var_m2_s2 < 1.0,
            "{fit:?}"
        );
        assert!((fit.fix_var_mean_m2 - 1.0).abs() < 1e-12);
    }
}
