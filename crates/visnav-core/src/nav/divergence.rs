//! When may the filter give up its own position for the fixes it keeps rejecting?
//!
//! A run of position fixes rejected by the innovation gate means one of two things: the filter
//! has diverged (its position is off by more than it claims) or the fixes are wrong (a vision
//! relocalisation over repetitive ground, a jumping receiver). Resetting onto the fix is right only
//! in the first case. Then the rejected fixes agree with each other: their innovations
//! `d_i = z_i - h(x_i)` (fix minus the filter's prediction at the fix's capture time) follow the
//! filter's own error, which changes smoothly, `d(t) = a + b t` (an offset plus the drift of a
//! velocity error). Wrong fixes scatter instead (relocalisations without a prior land hundreds of
//! metres apart, issue 19).
//!
//! Test: a weighted least-squares line per horizontal axis through the window's innovations
//! (weights: each fix's own horizontal variance plus `DRIFT_ACCEL_M_S2`-driven curvature over the
//! window); the residual sum of squares is chi-square with `2 (n - 2)` degrees of freedom when the
//! fixes are consistent. The window is accepted for a reset when it is below the
//! `CONSISTENCY_PROB` quantile. With fewer than 3 fixes nothing can be tested and no reset is
//! allowed.

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

/// Why the held rejected fixes are not a position to reset onto.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum Inconsistent {
    #[error("{n} rejected fixes cannot be checked against each other")]
    TooFew { n: usize },
    #[error("a rejected fix has a non-finite value")]
    NonFinite,
    #[error("the {n} rejected fixes disagree with each other (chi-square {chi2:.1} > {gate:.1})")]
    Disagree { n: usize, chi2: f64, gate: f64 },
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

    /// Whether the held fixes agree with each other up to an offset and a drift of the filter
    /// (see the module doc): `Ok(chi2)` when they do, `Err(reason)` otherwise.
    pub fn consistent(&self) -> Result<f64, Inconsistent> {
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
        let mut chi2 = 0.0;
        for axis in 0..2 {
            let (mut sd, mut std) = (0.0, 0.0);
            for (f, wi) in self.fixes.iter().zip(&w) {
                let t = f.t_s - t_mid;
                sd += wi * f.innov_ne_m[axis];
                std += wi * t * f.innov_ne_m[axis];
            }
            let (a, b) = if det.abs() > 1e-12 * sw * stt.max(1e-12) {
                ((stt * sd - st * std) / det, (sw * std - st * sd) / det)
            } else {
                (sd / sw, 0.0) // all at one time: the mean
            };
            for (f, wi) in self.fixes.iter().zip(&w) {
                let r = f.innov_ne_m[axis] - a - b * (f.t_s - t_mid);
                chi2 += wi * r * r;
            }
        }
        let dof = 2.0 * (n as f64 - 2.0);
        let gate = chi2_quantile(dof, CONSISTENCY_PROB);
        if chi2 <= gate {
            Ok(chi2)
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
}
