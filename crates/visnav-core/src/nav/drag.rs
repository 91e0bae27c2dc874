//! Multirotor drag: the horizontal body-frame velocity from the accelerometer alone.
//!
//! A multirotor's thrust acts along body -z, so in steady flight the accelerometer's body x / y
//! readings are the aerodynamic drag (rotor momentum drag and body drag): a function of the
//! air-relative velocity in body axes, `f_x = a_x v_x + b_x q_x(v)` (same for y), with `a < 0`
//! (momentum drag, linear) and `b <= 0` (body drag, quadratic). The quadratic term has two forms
//! in use ([`QuadForm`]): per axis, `q_x = v_x |v_x|` (ArduPilot SITL's `SIM_Frame`), or along
//! the velocity vector, `q_x = v_x |v_h|` with `|v_h|` the horizontal body speed (jMAVSim; PX4
//! EKF2's drag model). They agree when the aircraft flies along one body axis and differ by up
//! to 30 % across it (a copter flying diagonally, or holding its nose north on a westward leg).
//! Both are fitted; the one whose residual is clearly smaller is used, and while the flight has
//! not told them apart their difference at the current velocity is added to the measurement
//! noise ([`AMBIGUITY_RESIDUAL_RATIO`]). ArduPilot EKF3
//! (`EK3_DRAG_BCOEF_*`, `EK3_DRAG_MCOEF`) and PX4 EKF2 (`EKF2_BCOEF_*`, `EKF2_MCOEF`) fuse the
//! same physics to bound their velocity without GPS. Here the coefficients are not configured
//! but learned while the GPS aids the filter: a least-squares fit of the averaged specific force
//! against the GPS-aided body velocity ([`DragLearner`]). Once the GPS is gone, every averaged
//! specific force is a measurement of the body velocity ([`DragFix`], fused by the filter).
//!
//! Limits, stated where they act:
//! * the wind is not estimated: the fit and the measurement use the ground velocity, and the
//!   difference between the wind during learning and now enters the measurement noise as
//!   `[nav.drag] wind_sigma_m_s`;
//! * a fixed-wing aircraft's accelerometer x is thrust minus drag, close to zero at any speed:
//!   its fit explains nothing and never becomes ready ([`MIN_EXPLAINED`]).

use nalgebra::{Matrix2, Vector2};

/// Averaging window of the specific force for one learning sample or one measurement, s: long
/// enough to average a real airframe's vibration (tens of Hz), short enough that the velocity
/// changes little within it at a copter's 2-3 m/s^2.
pub const WINDOW_S: f64 = 0.2;

/// Samples an axis needs before its fit is used (at 5 per second: 40 s of GPS-aided flight).
pub const MIN_SAMPLES: f64 = 200.0;

/// Speed range an axis must have covered in the fit, m/s: a fit over hover alone cannot
/// separate drag from an accelerometer bias, nor extrapolate to cruise.
pub const MIN_SPEED_SPAN_M_S: f64 = 4.0;

/// Share of the specific force's variance the fit must explain (R^2): drag dominates a
/// multirotor's body x / y accelerations (0.99 in ArduCopter SITL), not a fixed-wing's.
pub const MIN_EXPLAINED: f64 = 0.8;

/// Learning forgets with this time constant, s (equivalent: older samples weigh less), so the
/// fit follows a payload change while keeping several minutes of flight.
pub const FORGET_TIME_S: f64 = 600.0;

/// The fit's residual scatter under-states the error of using it later (another attitude,
/// another speed): the measurement noise is this many times the residual RMS.
pub const RESIDUAL_INFLATION: f64 = 3.0;

/// A fitted linear coefficient up to this (1/s) above zero is taken as a purely quadratic law's
/// noise (a fit of jMAVSim's `-b |v| v` gave +1e-5); beyond, the law pushes the aircraft along
/// its motion and is not a drag. 0.01 / s is 1 % of the slope of a copter's drag at cruise.
pub const LINEAR_NOISE_PER_S: f64 = 0.01;

/// Floor of the measurement noise in velocity terms, m/s: no drag model is better than this
/// outside the flight it was fitted on.
pub const MIN_VELOCITY_SIGMA_M_S: f64 = 0.3;

/// Correlation time of the drag measurement's error, s: the wind and the law's mismatch change
/// over tens of seconds, not between two 0.2 s windows; fused as independent, 50 windows would
/// shrink the velocity covariance 50-fold while the error stays. Each measurement's covariance is
/// multiplied by `max(1, tau / dt)` like the vision fixes' (`vision_error_corr_time_s`).
pub const ERROR_CORR_TIME_S: f64 = 5.0;

/// Relative error of an axis's law borrowed from the other axis, when the flight so far gave
/// that axis too little speed to fit (a multirotor flies forward: its body y rarely sees more
/// than 1 m/s while the GPS aids). The rotor momentum drag, the linear term, is the same on both
/// axes (PX4 and ArduPilot model it with one coefficient); the body drag differs with the frame's
/// side area, taken here as up to 30 %.
pub const BORROWED_LAW_REL_ERR: f64 = 0.3;

/// The two forms' residuals must differ by this factor before one is taken as the law and the
/// other dismissed; below it the forms' difference is part of the noise, in proportion (1.5: a
/// form that fits the same flight 50 % worse is the wrong one; measured 1.0 on ArduCopter-like
/// nose-first learning and far above 1.5 on jMAVSim's diagonal first leg, docs/nav.md).
pub const AMBIGUITY_RESIDUAL_RATIO: f64 = 1.5;

/// Half-width of the velocity bracket [`AxisModel::inverse_at`] searches, m/s: beyond any
/// multirotor's airspeed error.
pub const INVERSE_SPAN_M_S: f64 = 40.0;

/// Form of the quadratic (body drag) term.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum QuadForm {
    /// `v_k |v_k|`: each axis on its own.
    PerAxis,
    /// `v_k |v_h|`: along the horizontal velocity vector.
    Vector,
}

impl QuadForm {
    /// The quadratic regressor of axis `k` at body velocity `v`.
    pub fn q(self, v: &Vector2<f64>, k: usize) -> f64 {
        match self {
            Self::PerAxis => v[k] * v[k].abs(),
            Self::Vector => v[k] * v.norm(),
        }
    }

    /// Its gradient with respect to `(v_x, v_y)`.
    pub fn dq(self, v: &Vector2<f64>, k: usize) -> Vector2<f64> {
        let mut g = Vector2::zeros();
        match self {
            Self::PerAxis => g[k] = 2.0 * v[k].abs(),
            Self::Vector => {
                let n = v.norm();
                g[k] = n;
                if n > 1e-9 {
                    g += v * (v[k] / n);
                }
            }
        }
        g
    }

    /// Both forms.
    pub const ALL: [QuadForm; 2] = [QuadForm::PerAxis, QuadForm::Vector];
}

/// One axis's drag law `f = a v + b q(v)` (specific force, m/s^2, for body velocity v, m/s; `q`
/// per [`QuadForm`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AxisModel {
    /// Linear coefficient, 1/s (negative).
    pub a: f64,
    /// Quadratic coefficient, 1/m (zero or negative).
    pub b: f64,
    /// RMS residual of the fit, m/s^2.
    pub resid_m_s2: f64,
    /// Relative error of the law when it is the other axis's ([`BORROWED_LAW_REL_ERR`]); 0 for
    /// the axis's own fit.
    pub borrowed_rel_err: f64,
    /// The quadratic term's form.
    pub form: QuadForm,
    /// The other form's fit `(a, b)` and the weight (0 to 1) of the two forms' difference in the
    /// noise: 1 while the flight has not told them apart ([`AMBIGUITY_RESIDUAL_RATIO`]).
    pub alternative: Option<(f64, f64, f64)>,
}

impl AxisModel {
    /// Specific force for body velocity `v` along this axis alone (the forms agree there),
    /// m/s^2.
    pub fn force(&self, v: f64) -> f64 {
        self.a * v + self.b * v * v.abs()
    }

    /// d force / d v along this axis alone, 1/s.
    pub fn slope(&self, v: f64) -> f64 {
        self.a + 2.0 * self.b * v.abs()
    }

    /// Specific force of axis `k` at horizontal body velocity `v`, m/s^2.
    pub fn force_at(&self, v: &Vector2<f64>, k: usize) -> f64 {
        self.a * v[k] + self.b * self.form.q(v, k)
    }

    /// Gradient of [`Self::force_at`] with respect to `(v_x, v_y)`, 1/s.
    pub fn gradient(&self, v: &Vector2<f64>, k: usize) -> Vector2<f64> {
        let mut g = self.form.dq(v, k) * self.b;
        g[k] += self.a;
        g
    }

    /// Measurement variance of the averaged specific force `f_meas` on axis `k` at the estimated
    /// body velocity `v`, (m/s^2)^2.
    ///
    /// The two forms' disagreement (while undecided) is judged on what each infers from the
    /// measurement: the axis velocity at which each form gives `f_meas` (the other axis kept),
    /// their difference turned into force by this law's slope. Judged at the estimate instead,
    /// a drifted estimate makes the forms disagree and so weakens the very measurement that
    /// would correct it: flown nose first, a copter's body y sees no speed while learning; its
    /// forms' slopes across the nose differ threefold at cruise, but a sideways force of zero
    /// means no sideways speed in both (ArduCopter flight f9: 2.4 m/s across track otherwise).
    pub fn variance_at(&self, v: &Vector2<f64>, k: usize, wind_sigma_m_s: f64, f_meas: f64) -> f64 {
        let g = self.gradient(v, k);
        let s = g.norm();
        let model = (RESIDUAL_INFLATION * self.resid_m_s2).powi(2);
        let floor = (s * MIN_VELOCITY_SIGMA_M_S).powi(2);
        let f = self.force_at(v, k);
        let borrowed = (self.borrowed_rel_err * f).powi(2);
        let ambiguity = self.alternative.map_or(0.0, |(a, b, w)| {
            let other = AxisModel {
                a,
                b,
                form: match self.form {
                    QuadForm::PerAxis => QuadForm::Vector,
                    QuadForm::Vector => QuadForm::PerAxis,
                },
                alternative: None,
                ..*self
            };
            let dv = self.inverse_at(v, k, f_meas) - other.inverse_at(v, k, f_meas);
            w * (g[k] * dv).powi(2)
        });
        model.max(floor) + (s * wind_sigma_m_s).powi(2) + borrowed + ambiguity
    }

    /// The axis-`k` velocity at which this law gives `f_meas`, the other axis at `v`'s value
    /// (bisection over +-[`INVERSE_SPAN_M_S`] about `v[k]`; the law decreases with `v[k]` over
    /// any flown range, and the bracket's end is returned when it does not reach `f_meas`).
    pub fn inverse_at(&self, v: &Vector2<f64>, k: usize, f_meas: f64) -> f64 {
        let at = |x: f64| {
            let mut w = *v;
            w[k] = x;
            self.force_at(&w, k)
        };
        let (mut lo, mut hi) = (v[k] - INVERSE_SPAN_M_S, v[k] + INVERSE_SPAN_M_S);
        if !f_meas.is_finite() || at(lo) <= f_meas {
            return lo;
        }
        if at(hi) >= f_meas {
            return hi;
        }
        for _ in 0..48 {
            let mid = 0.5 * (lo + hi);
            if at(mid) > f_meas {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        0.5 * (lo + hi)
    }

    /// [`Self::variance_at`] for a velocity along this axis alone.
    pub fn variance(&self, v: f64, wind_sigma_m_s: f64) -> f64 {
        let mut vv = Vector2::zeros();
        vv[0] = v;
        let m = AxisModel {
            alternative: None,
            ..*self
        };
        m.variance_at(&vv, 0, wind_sigma_m_s, m.force(v))
    }
}

/// A drag measurement: the averaged body-frame specific force (bias-corrected) over a window
/// centred on `t_capture_us`, and the learned law per axis (None: that axis is not fused).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DragFix {
    /// Window centre, microseconds.
    pub t_capture_us: u64,
    /// Measured specific force, body x / y, m/s^2.
    pub f_body_xy_m_s2: Vector2<f64>,
    /// Learned law, body x / y.
    pub model: [Option<AxisModel>; 2],
    /// Wind uncertainty added to the noise, m/s.
    pub wind_sigma_m_s: f64,
}

/// Least-squares fit of one axis with exponential forgetting.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct AxisFit {
    s: Matrix2<f64>,
    r: Vector2<f64>,
    sff: f64,
    sf: f64,
    n: f64,
    v_min: f64,
    v_max: f64,
}

impl AxisFit {
    fn add(&mut self, v: f64, q: f64, f: f64, keep: f64) {
        if self.n == 0.0 {
            self.v_min = v;
            self.v_max = v;
        }
        let x = Vector2::new(v, q);
        self.s = self.s * keep + x * x.transpose();
        self.r = self.r * keep + x * f;
        self.sff = self.sff * keep + f * f;
        self.sf = self.sf * keep + f;
        self.n = self.n * keep + 1.0;
        self.v_min = self.v_min.min(v);
        self.v_max = self.v_max.max(v);
    }

    fn model(&self, form: QuadForm) -> Result<AxisModel, NotLearned> {
        if self.n < MIN_SAMPLES {
            return Err(NotLearned::FewSamples { n: self.n });
        }
        let span = self.v_max - self.v_min;
        if span < MIN_SPEED_SPAN_M_S {
            return Err(NotLearned::NarrowSpeedSpan { span_m_s: span });
        }
        let inv = self.s.try_inverse().ok_or(NotLearned::SingularFit)?;
        let th = inv * self.r;
        let ssr =
            (self.sff - 2.0 * th.dot(&self.r) + (th.transpose() * self.s * th)[(0, 0)]).max(0.0);
        let sst = (self.sff - self.sf * self.sf / self.n).max(1e-12);
        let explained = 1.0 - ssr / sst;
        if explained < MIN_EXPLAINED {
            return Err(NotLearned::Unexplained { explained });
        }
        let m = AxisModel {
            a: th.x,
            b: th.y,
            resid_m_s2: (ssr / (self.n - 2.0).max(1.0)).sqrt(),
            borrowed_rel_err: 0.0,
            form,
            alternative: None,
        };
        // Drag opposes the motion over the whole fitted range. A purely quadratic law (jMAVSim)
        // fits a linear coefficient of zero give or take its noise: a slightly positive one is
        // that noise, not thrust.
        let vmax = self.v_min.abs().max(self.v_max.abs());
        if !(m.a.is_finite() && m.b.is_finite())
            || m.slope(0.0) > LINEAR_NOISE_PER_S
            || m.slope(vmax) >= 0.0
        {
            return Err(NotLearned::NotADrag { a: m.a, b: m.b });
        }
        Ok(m)
    }
}

/// Why an axis's drag law is not usable (yet).
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum NotLearned {
    /// Fewer samples than [`MIN_SAMPLES`].
    #[error("{n:.0} of {MIN_SAMPLES:.0} samples")]
    FewSamples {
        /// The fit's effective sample count (older samples weigh less).
        n: f64,
    },
    /// The samples cover a speed range narrower than [`MIN_SPEED_SPAN_M_S`].
    #[error("speed span {span_m_s:.1} m/s < {MIN_SPEED_SPAN_M_S} m/s")]
    NarrowSpeedSpan {
        /// Fastest minus slowest body velocity seen on the axis, m/s.
        span_m_s: f64,
    },
    /// The least-squares normal matrix cannot be inverted.
    #[error("singular fit")]
    SingularFit,
    /// The law explains less of the specific force's variance than [`MIN_EXPLAINED`].
    #[error(
        "the fit explains {:.0} % of the specific force (< {:.0} %)",
        explained * 100.0,
        MIN_EXPLAINED * 100.0
    )]
    Unexplained {
        /// Share of the variance explained (R^2, 0 to 1).
        explained: f64,
    },
    /// The fitted law does not oppose the motion over the fitted speeds (thrust, not drag).
    #[error("fitted law is not a drag (a {a:.3}, b {b:.4})")]
    NotADrag {
        /// Fitted linear coefficient, 1/s.
        a: f64,
        /// Fitted quadratic coefficient, 1/m.
        b: f64,
    },
}

/// Learns the drag law of both horizontal body axes from averaged specific forces and
/// GPS-aided body velocities, in both quadratic forms ([`QuadForm`]).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct DragLearner {
    /// `[form][axis]`, forms in [`QuadForm::ALL`]'s order.
    fits: [[AxisFit; 2]; 2],
}

impl DragLearner {
    /// Add one window: body velocity (x, y) and mean specific force (x, y).
    pub fn add(&mut self, v_body_xy: Vector2<f64>, f_body_xy: Vector2<f64>) {
        if !(v_body_xy.iter().all(|v| v.is_finite()) && f_body_xy.iter().all(|v| v.is_finite())) {
            return;
        }
        let keep = (-WINDOW_S / FORGET_TIME_S).exp();
        for (fits, form) in self.fits.iter_mut().zip(QuadForm::ALL) {
            for (k, fit) in fits.iter_mut().enumerate() {
                fit.add(v_body_xy[k], form.q(&v_body_xy, k), f_body_xy[k], keep);
            }
        }
    }

    /// The form whose axes fit better (summed squared residuals of the axes that are ready in
    /// both), and the weight of the other form in the noise: 1 when their residuals are equal,
    /// 0 from [`AMBIGUITY_RESIDUAL_RATIO`] apart.
    fn chosen_form(&self) -> (usize, f64) {
        let ss = |i: usize| -> Option<f64> {
            let r: Vec<f64> = (0..2)
                .filter_map(|k| self.fits[i][k].model(QuadForm::ALL[i]).ok())
                .map(|m| m.resid_m_s2.powi(2))
                .collect();
            (!r.is_empty()).then(|| r.iter().sum())
        };
        match (ss(0), ss(1)) {
            (Some(p), Some(v)) => {
                let (best, worse, i) = if v < p { (v, p, 1) } else { (p, v, 0) };
                let ratio = (worse / best.max(1e-18)).sqrt();
                let w = (1.0 - (ratio - 1.0) / (AMBIGUITY_RESIDUAL_RATIO - 1.0)).clamp(0.0, 1.0);
                (i, w)
            }
            _ => (0, 1.0),
        }
    }

    /// The law of axis `k` (0 = x, 1 = y) in the chosen form, or why it is not usable yet.
    pub fn axis(&self, k: usize) -> Result<AxisModel, NotLearned> {
        let (i, w) = self.chosen_form();
        let k = k.min(1);
        let mut m = self.fits[i][k].model(QuadForm::ALL[i])?;
        m.alternative = self.fits[1 - i][k]
            .model(QuadForm::ALL[1 - i])
            .ok()
            .filter(|_| w > 0.0)
            .map(|o| (o.a, o.b, w));
        Ok(m)
    }

    /// Both axes' laws: each axis's own fit, else the other axis's with
    /// [`BORROWED_LAW_REL_ERR`], else None.
    pub fn models(&self) -> [Option<AxisModel>; 2] {
        let own = [self.axis(0).ok(), self.axis(1).ok()];
        let borrow = |m: Option<AxisModel>| {
            m.map(|m| AxisModel {
                borrowed_rel_err: BORROWED_LAW_REL_ERR,
                ..m
            })
        };
        [own[0].or(borrow(own[1])), own[1].or(borrow(own[0]))]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Deterministic pseudo-noise in [-1, 1].
    fn wobble(i: usize) -> f64 {
        ((i as f64 * 12.9898).sin() * 43_758.545).rem_euclid(1.0) * 2.0 - 1.0
    }

    fn fly(learner: &mut DragLearner, n: usize, a: f64, b: f64, noise: f64) {
        for i in 0..n {
            // Hover, climb-out and cruise speeds, forward and sideways.
            let vx = 12.0 * ((i as f64) * 0.01).sin().abs();
            let vy = 6.0 * ((i as f64) * 0.013).sin();
            let f = |v: f64| a * v + b * v * v.abs();
            learner.add(
                Vector2::new(vx, vy),
                Vector2::new(f(vx) + noise * wobble(i), f(vy) + noise * wobble(i + 7)),
            );
        }
    }

    #[test]
    fn learns_arducopter_sitl_like_drag() {
        // ArduCopter SITL's quad, fitted from its log: a -0.215 / s, b -0.028 / m.
        let mut l = DragLearner::default();
        assert!(l.axis(0).is_err());
        fly(&mut l, 600, -0.215, -0.028, 0.05);
        for k in 0..2 {
            let m = l.axis(k).unwrap();
            assert!((m.a + 0.215).abs() < 0.02, "{m:?}");
            assert!((m.b + 0.028).abs() < 0.003, "{m:?}");
            assert!(m.resid_m_s2 < 0.06, "{m:?}");
            assert!((m.force(10.0) + 4.95).abs() < 0.1);
        }
    }

    #[test]
    fn a_fixed_wing_or_a_hover_never_becomes_ready() {
        // Thrust balances drag: the body x specific force is noise at every speed.
        let mut l = DragLearner::default();
        fly(&mut l, 600, 0.0, 0.0, 0.3);
        assert!(
            matches!(l.axis(0), Err(NotLearned::Unexplained { .. })),
            "{:?}",
            l.axis(0)
        );
        // Hover only: no speed span.
        let mut h = DragLearner::default();
        for i in 0..600 {
            let v = 0.5 * wobble(i);
            h.add(Vector2::new(v, v), Vector2::new(-0.3 * v, -0.3 * v));
        }
        assert!(
            matches!(h.axis(0), Err(NotLearned::NarrowSpeedSpan { .. })),
            "{:?}",
            h.axis(0)
        );
        // Too few samples.
        let mut s = DragLearner::default();
        fly(&mut s, 50, -0.2, -0.03, 0.0);
        let e = s.axis(1).unwrap_err();
        assert!(matches!(e, NotLearned::FewSamples { .. }), "{e:?}");
        assert!(e.to_string().ends_with(" of 200 samples"), "{e}");
    }

    #[test]
    fn a_thrust_like_law_is_refused() {
        let mut l = DragLearner::default();
        fly(&mut l, 600, 0.3, 0.0, 0.01);
        assert!(
            matches!(l.axis(0), Err(NotLearned::NotADrag { .. })),
            "{:?}",
            l.axis(0)
        );
    }

    #[test]
    fn noise_floor_and_wind_enter_the_variance() {
        let m = AxisModel {
            a: -0.2,
            b: -0.03,
            resid_m_s2: 0.001,
            borrowed_rel_err: 0.0,
            form: QuadForm::PerAxis,
            alternative: None,
        };
        let s = m.slope(10.0).abs();
        let calm = m.variance(10.0, 0.0);
        assert!((calm - (s * MIN_VELOCITY_SIGMA_M_S).powi(2)).abs() < 1e-12);
        let windy = m.variance(10.0, 2.0);
        assert!((windy - calm - (s * 2.0).powi(2)).abs() < 1e-12);
        let noisy = AxisModel {
            resid_m_s2: 0.5,
            ..m
        };
        assert!((noisy.variance(10.0, 0.0) - (RESIDUAL_INFLATION * 0.5).powi(2)).abs() < 1e-12);
        let lent = AxisModel {
            borrowed_rel_err: BORROWED_LAW_REL_ERR,
            ..m
        };
        let extra = (BORROWED_LAW_REL_ERR * m.force(10.0)).powi(2);
        assert!((lent.variance(10.0, 0.0) - calm - extra).abs() < 1e-12);
    }

    /// Flies a vector drag law (jMAVSim: `f = -b |v_h| v`) with the nose held while the
    /// velocity turns, like PX4's first leg north-west with the nose north.
    fn fly_vector(learner: &mut DragLearner, n: usize, a: f64, b: f64) {
        for i in 0..n {
            let speed = 14.0 * ((i as f64) * 0.01).sin().abs();
            let dir = 0.8 + 0.5 * (i as f64 * 0.003).sin(); // 17 to 75 deg off the nose
            let v = Vector2::new(speed * dir.cos(), speed * dir.sin());
            let f = v * a + v * (b * v.norm());
            learner.add(v, f + Vector2::new(0.02 * wobble(i), 0.02 * wobble(i + 3)));
        }
    }

    #[test]
    fn a_vector_drag_law_is_recognised_and_predicts_any_direction() {
        let (a, b) = (-0.02, -0.0133);
        let mut l = DragLearner::default();
        fly_vector(&mut l, 1500, a, b);
        let [x, y] = l.models();
        let (x, y) = (x.unwrap(), y.unwrap());
        assert_eq!(x.form, QuadForm::Vector, "{x:?}");
        assert!(x.alternative.is_none(), "the forms were told apart: {x:?}");
        // Along one axis at 14.8 m/s (a later leg flown nose first) and diagonally.
        for v in [
            Vector2::new(14.8, 0.0),
            Vector2::new(0.0, -14.8),
            Vector2::new(9.0, 9.0),
        ] {
            let truth = v * a + v * (b * v.norm());
            for (k, m) in [(0, x), (1, y)] {
                let f = m.force_at(&v, k);
                assert!(
                    (f - truth[k]).abs() < 0.03 * truth.norm(),
                    "{v:?} axis {k}: {f} vs {}",
                    truth[k]
                );
                // Gradient against a finite difference.
                let g = m.gradient(&v, k);
                for j in 0..2 {
                    let mut dv = v;
                    dv[j] += 1e-6;
                    let num = (m.force_at(&dv, k) - f) / 1e-6;
                    assert!((num - g[j]).abs() < 1e-4, "{num} vs {}", g[j]);
                }
            }
        }
        // The per-axis form fits this flight several times worse: the choice is not a tie.
        let per_axis = l.fits[0][0].model(QuadForm::PerAxis).unwrap();
        assert!(
            per_axis.resid_m_s2 > 3.0 * x.resid_m_s2,
            "{per_axis:?} vs {x:?}"
        );
    }

    #[test]
    fn forms_not_told_apart_put_their_difference_into_the_noise() {
        // Nose-first learning: v_y within +-0.5 m/s, so both forms fit the same.
        let mut l = DragLearner::default();
        for i in 0..800 {
            let vx = 12.0 * ((i as f64) * 0.01).sin().abs();
            let vy = 0.5 * wobble(i);
            let f = |v: f64| -0.21 * v - 0.028 * v * v.abs();
            let noise = Vector2::new(0.05 * wobble(i + 11), 0.05 * wobble(i + 5));
            l.add(Vector2::new(vx, vy), Vector2::new(f(vx), f(vy)) + noise);
        }
        let m = l.axis(0).unwrap();
        let (_, _, w) = m.alternative.expect("undecided forms carry the other one");
        assert!(w > 0.5, "weight {w}");
        // Along the axis the forms agree: no extra noise; diagonally they differ: extra noise.
        let along = Vector2::new(12.0, 0.0);
        let diag = Vector2::new(9.0, 9.0);
        let plain = AxisModel {
            alternative: None,
            ..m
        };
        let var = |m: &AxisModel, v: &Vector2<f64>, k: usize, f: f64| m.variance_at(v, k, 1.0, f);
        let f_along = m.force_at(&along, 0);
        let f_diag = m.force_at(&diag, 0);
        assert!((var(&m, &along, 0, f_along) - var(&plain, &along, 0, f_along)).abs() < 1e-3);
        assert!(var(&m, &diag, 0, f_diag) > var(&plain, &diag, 0, f_diag) + 0.1);
        // Across the nose at cruise with the estimate 2 m/s off sideways: the measured sideways
        // force of zero means no sideways speed in either form, so no extra noise (judged at the
        // estimate, the forms would differ by half a m/s^2 there).
        let my = l.models()[1].expect("the y law (its own or borrowed)");
        let plain_y = AxisModel {
            alternative: None,
            ..my
        };
        let drifted = Vector2::new(12.0, 2.0);
        assert!((var(&my, &drifted, 1, 0.0) - var(&plain_y, &drifted, 1, 0.0)).abs() < 1e-3);
        // A real sideways speed: the forms disagree on it, and the noise says so.
        let f_side = my.force_at(&drifted, 1);
        assert!(var(&my, &drifted, 1, f_side) > var(&plain_y, &drifted, 1, f_side) + 0.05);
    }

    #[test]
    fn the_inverse_gives_back_the_velocity_of_a_force() {
        for form in QuadForm::ALL {
            let m = AxisModel {
                a: -0.2,
                b: -0.03,
                resid_m_s2: 0.01,
                borrowed_rel_err: 0.0,
                form,
                alternative: None,
            };
            for (vx, vy) in [(12.0, 0.0), (-5.0, 3.0), (0.0, 8.0), (7.0, -7.0)] {
                let v = Vector2::new(vx, vy);
                for k in 0..2 {
                    let f = m.force_at(&v, k);
                    let start = Vector2::new(vx + 3.0, vy - 2.0);
                    let mut probe = start;
                    probe[1 - k] = v[1 - k];
                    let back = m.inverse_at(&probe, k, f);
                    assert!((back - v[k]).abs() < 1e-6, "{form:?} {v:?} {k}: {back}");
                }
            }
            // Out of reach: the bracket's end, never NaN.
            let v = Vector2::new(1.0, 0.0);
            assert_eq!(m.inverse_at(&v, 0, 1e9), 1.0 - INVERSE_SPAN_M_S);
            assert_eq!(m.inverse_at(&v, 0, f64::NAN), 1.0 - INVERSE_SPAN_M_S);
        }
    }

    #[test]
    fn an_axis_without_speed_borrows_the_other_axis_law() {
        // Forward flight only: body y stays within +-0.5 m/s.
        let mut l = DragLearner::default();
        for i in 0..600 {
            let vx = 12.0 * ((i as f64) * 0.01).sin().abs();
            let vy = 0.5 * wobble(i);
            let f = |v: f64| -0.21 * v - 0.028 * v * v.abs();
            l.add(Vector2::new(vx, vy), Vector2::new(f(vx), f(vy)));
        }
        assert!(l.axis(1).is_err());
        let [x, y] = l.models();
        let (x, y) = (x.unwrap(), y.unwrap());
        assert_eq!(x.borrowed_rel_err, 0.0);
        assert_eq!(y.borrowed_rel_err, BORROWED_LAW_REL_ERR);
        assert_eq!((x.a, x.b), (y.a, y.b));
        assert!(DragLearner::default().models().iter().all(|m| m.is_none()));
    }
}
