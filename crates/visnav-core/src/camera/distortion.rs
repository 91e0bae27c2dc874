//! Brown-Conrady lens distortion (radial k1, k2, k3 and tangential p1, p2), OpenCV's model.
//!
//! On normalised image coordinates `(x, y) = (X/Z, Y/Z)` of the `_cam` frame, with `r^2 = x^2 + y^2`
//! (OpenCV `calib3d` documentation, same parameter names and meaning):
//!
//! ```text
//! x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)
//! y_d = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y^2) + 2 p2 x y
//! ```
//!
//! Undistortion inverts this by Newton's method on the 2x2 Jacobian (analytic), started at the exact
//! inverse of the radial part (bisection on the increasing branch), and reports failure instead of
//! returning an unconverged value.
//!
//! The radial polynomial is only one-to-one up to the radius where `d(r_d)/dr` first reaches zero
//! (e.g. `k1 = -0.3` folds over at r = 1.05). Beyond it a far off-axis point would be mapped back
//! into the image; [`Distortion::max_radius`] finds that radius so projection can refuse such points.

use nalgebra::{Matrix2, Vector2};
use serde::{Deserialize, Serialize};

/// Newton iterations allowed in [`Distortion::undistort`].
const MAX_ITERATIONS: usize = 30;
/// Convergence threshold on the residual in normalised units (1e-12 is ~1e-9 px at f = 1000 px).
const TOLERANCE: f64 = 1e-12;

/// Brown-Conrady coefficients (OpenCV order `k1, k2, p1, p2, k3`).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Distortion {
    /// Radial coefficient of r^2.
    pub k1: f64,
    /// Radial coefficient of r^4.
    pub k2: f64,
    /// Radial coefficient of r^6.
    pub k3: f64,
    /// First tangential coefficient.
    pub p1: f64,
    /// Second tangential coefficient.
    pub p2: f64,
}

impl Distortion {
    /// No distortion.
    pub fn none() -> Self {
        Self::default()
    }

    /// True when every coefficient is exactly zero (distort/undistort are the identity).
    pub fn is_zero(&self) -> bool {
        self.k1 == 0.0 && self.k2 == 0.0 && self.k3 == 0.0 && self.p1 == 0.0 && self.p2 == 0.0
    }

    /// The coefficients in the order `k1, k2, k3, p1, p2`.
    pub fn coefficients(&self) -> [f64; 5] {
        [self.k1, self.k2, self.k3, self.p1, self.p2]
    }

    /// All coefficients are finite.
    pub fn is_finite(&self) -> bool {
        self.coefficients().iter().all(|c| c.is_finite())
    }

    /// Apply the distortion to an ideal normalised point.
    pub fn distort(&self, p: &Vector2<f64>) -> Vector2<f64> {
        let (x, y) = (p.x, p.y);
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        Vector2::new(
            x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x),
            y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y,
        )
    }

    /// Jacobian of [`Self::distort`] with respect to the ideal point.
    pub fn jacobian(&self, p: &Vector2<f64>) -> Matrix2<f64> {
        let (x, y) = (p.x, p.y);
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        // d(radial)/d(r^2)
        let dradial = self.k1 + r2 * (2.0 * self.k2 + 3.0 * self.k3 * r2);
        let dxx = radial + 2.0 * x * x * dradial + 2.0 * self.p1 * y + 6.0 * self.p2 * x;
        let dxy = 2.0 * x * y * dradial + 2.0 * self.p1 * x + 2.0 * self.p2 * y;
        let dyx = 2.0 * x * y * dradial + 2.0 * self.p1 * x + 2.0 * self.p2 * y;
        let dyy = radial + 2.0 * y * y * dradial + 6.0 * self.p1 * y + 2.0 * self.p2 * x;
        Matrix2::new(dxx, dxy, dyx, dyy)
    }

    /// Invert the distortion: the ideal normalised point whose distortion is `pd`.
    ///
    /// Newton's method started at the exact inverse of the radial part; returns `None` if the input is not finite, the Jacobian becomes
    /// singular, the iteration does not reach a residual below 1e-12 (normalised units) within 30
    /// steps, or the solution lies beyond [`Self::max_radius`] (not the physically valid branch).
    /// Computes `max_radius` on each call; use [`Self::undistort_within`] with a cached value in loops.
    pub fn undistort(&self, pd: &Vector2<f64>) -> Option<Vector2<f64>> {
        self.undistort_within(pd, self.max_radius())
    }

    /// [`Self::undistort`] with the valid radius `r_max` (normally [`Self::max_radius`]) given.
    pub fn undistort_within(&self, pd: &Vector2<f64>, r_max: f64) -> Option<Vector2<f64>> {
        if !pd.x.is_finite() || !pd.y.is_finite() {
            return None;
        }
        if self.is_zero() {
            return Some(*pd);
        }
        // Start from the exact inverse of the radial part on the valid branch, then let Newton add
        // the tangential terms. Steps that would leave the valid disc are halved.
        let rd = pd.norm();
        let mut p = if rd > 0.0 {
            pd * (self.radial_inverse(rd, r_max) / rd)
        } else {
            *pd
        };
        for _ in 0..MAX_ITERATIONS {
            let residual = self.distort(&p) - pd;
            if residual.norm() < TOLERANCE {
                return (p.norm() <= r_max).then_some(p);
            }
            let mut step = self.jacobian(&p).lu().solve(&residual)?;
            let mut next = p - step;
            let mut halvings = 0;
            while next.norm() > r_max && halvings < 30 {
                step *= 0.5;
                next = p - step;
                halvings += 1;
            }
            p = next;
            if !p.x.is_finite() || !p.y.is_finite() {
                return None;
            }
        }
        let residual = self.distort(&p) - pd;
        (residual.norm() < TOLERANCE && p.norm() <= r_max).then_some(p)
    }

    /// Radius `r` in `[0, r_max]` with `r (1 + k1 r^2 + k2 r^4 + k3 r^6) = rd`, by bisection (the map is
    /// increasing there). Returns the end of the interval when `rd` is beyond its image.
    fn radial_inverse(&self, rd: f64, r_max: f64) -> f64 {
        let g = |r: f64| {
            let r2 = r * r;
            r * (1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3)))
        };
        let mut hi = if r_max.is_finite() {
            r_max
        } else {
            let mut h = rd.max(1e-3);
            while g(h) < rd && h < 1e6 {
                h *= 2.0;
            }
            h
        };
        if g(hi) <= rd {
            return hi;
        }
        let mut lo = 0.0;
        for _ in 0..64 {
            let mid = 0.5 * (lo + hi);
            if g(mid) < rd {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        0.5 * (lo + hi)
    }

    /// Largest ideal radius `r` up to which the radial map `r -> r (1 + k1 r^2 + k2 r^4 + k3 r^6)`
    /// is strictly increasing (`f64::INFINITY` if it never folds over). Found as the smallest positive
    /// root `s = r^2` of `1 + 3 k1 s + 5 k2 s^2 + 7 k3 s^3` by scanning and bisection, searched up to
    /// r = 20 (87 deg off-axis); beyond that the map is treated as valid.
    pub fn max_radius(&self) -> f64 {
        let deriv = |s: f64| 1.0 + s * (3.0 * self.k1 + s * (5.0 * self.k2 + s * 7.0 * self.k3));
        if self.k1 == 0.0 && self.k2 == 0.0 && self.k3 == 0.0 {
            return f64::INFINITY;
        }
        const STEPS: usize = 4_000; // r steps of 0.005
        let mut prev = 0.0;
        for i in 1..=STEPS {
            let r = 20.0 * i as f64 / STEPS as f64;
            let s = r * r;
            if deriv(s) <= 0.0 {
                let (mut lo, mut hi) = (prev, s);
                for _ in 0..60 {
                    let mid = 0.5 * (lo + hi);
                    if deriv(mid) > 0.0 {
                        lo = mid;
                    } else {
                        hi = mid;
                    }
                }
                return lo.sqrt();
            }
            prev = s;
        }
        f64::INFINITY
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// A strongly distorted but realistic wide-angle lens (OpenCV sample calibration magnitude).
    fn wide() -> Distortion {
        Distortion {
            k1: -0.28,
            k2: 0.07,
            k3: 0.0,
            p1: 0.0012,
            p2: -0.0008,
        }
    }

    #[test]
    fn zero_distortion_is_identity() {
        let d = Distortion::none();
        let p = Vector2::new(0.3, -0.2);
        assert_eq!(d.distort(&p), p);
        assert_eq!(d.undistort(&p), Some(p));
        assert_eq!(d.max_radius(), f64::INFINITY);
    }

    #[test]
    fn known_value_radial_and_tangential() {
        // Hand-computed: x=0.1, y=0.2, r2=0.05; radial = 1 + 0.1*0.05 + 0.01*0.0025 = 1.005025.
        let d = Distortion {
            k1: 0.1,
            k2: 0.01,
            k3: 0.0,
            p1: 0.001,
            p2: 0.002,
        };
        let q = d.distort(&Vector2::new(0.1, 0.2));
        let xd = 0.1 * 1.005025 + 2.0 * 0.001 * 0.02 + 0.002 * (0.05 + 0.02);
        let yd = 0.2 * 1.005025 + 0.001 * (0.05 + 0.08) + 2.0 * 0.002 * 0.02;
        assert!((q.x - xd).abs() < 1e-15 && (q.y - yd).abs() < 1e-15);
    }

    #[test]
    fn jacobian_matches_finite_differences() {
        let d = wide();
        let p = Vector2::new(0.35, -0.42);
        let j = d.jacobian(&p);
        let h = 1e-7;
        for c in 0..2 {
            let mut e = Vector2::zeros();
            e[c] = h;
            let num = (d.distort(&(p + e)) - d.distort(&(p - e))) / (2.0 * h);
            assert!((j.column(c) - num).amax() < 1e-7, "column {c}");
        }
    }

    #[test]
    fn fold_over_radius_of_pure_k1() {
        // r(1 + k1 r^2) has derivative 1 + 3 k1 r^2 = 0 at r = 1/sqrt(-3 k1).
        let d = Distortion {
            k1: -0.3,
            ..Distortion::none()
        };
        assert!((d.max_radius() - 1.0 / 0.9f64.sqrt()).abs() < 1e-9);
        // A point at r = 1.5 distorts to r_d = 1.5 * (1 - 0.675) = 0.4875, inside the valid range of
        // distorted radii, but it is on the folded branch: undistortion must give the r < 1.05 solution.
        let pd = d.distort(&Vector2::new(1.5, 0.0));
        let p = d.undistort(&pd).expect("valid branch exists");
        assert!(p.x < 1.05 && (d.distort(&p) - pd).norm() < 1e-12);
        // Beyond the largest distorted radius there is no solution at all.
        let r_d_max = d.distort(&Vector2::new(d.max_radius(), 0.0)).x;
        assert!(d.undistort(&Vector2::new(r_d_max + 0.01, 0.0)).is_none());
    }

    #[test]
    fn strong_pincushion_far_off_axis() {
        // Found by proptest: Newton started at the distorted point (r_d = 1.33) lies beyond the
        // fold-over radius and diverged; starting at the radial inverse converges.
        let d = Distortion {
            k1: 0.39236848175117567,
            k2: -0.11486116457299761,
            k3: -0.04178891438827657,
            p1: 0.0,
            p2: 0.0,
        };
        let p = Vector2::new(-0.7227100470973653, 0.7969682879797304);
        assert!(p.norm() < d.max_radius());
        let back = d
            .undistort(&d.distort(&p))
            .expect("inverse on the valid branch");
        assert!((back - p).norm() < 1e-9);
    }

    #[test]
    fn non_finite_input_is_rejected() {
        assert!(wide().undistort(&Vector2::new(f64::NAN, 0.0)).is_none());
        assert!(
            Distortion::none()
                .undistort(&Vector2::new(0.0, f64::INFINITY))
                .is_none()
        );
    }

    #[test]
    fn undistort_accuracy_over_a_wide_image() {
        // 1280x960 with fx = 900 px: corners at normalised radius ~0.89. Error must be < 1e-3 px.
        let d = wide();
        let fx = 900.0;
        let mut worst: f64 = 0.0;
        for iu in 0..=32 {
            for iv in 0..=24 {
                let pd = Vector2::new(
                    (iu as f64 * 40.0 - 639.5) / fx,
                    (iv as f64 * 40.0 - 479.5) / fx,
                );
                let p = d.undistort(&pd).expect("inside the image");
                worst = worst.max((d.distort(&p) - pd).norm() * fx);
            }
        }
        assert!(worst < 1e-3, "worst residual {worst} px");
    }

    proptest! {
        #[test]
        fn distort_undistort_round_trip(
            x in -0.8f64..0.8, y in -0.8f64..0.8,
            k1 in -0.4f64..0.4, k2 in -0.2f64..0.2, k3 in -0.05f64..0.05,
            p1 in -0.005f64..0.005, p2 in -0.005f64..0.005,
        ) {
            let d = Distortion { k1, k2, k3, p1, p2 };
            let p = Vector2::new(x, y);
            prop_assume!(p.norm() < 0.9 * d.max_radius());
            let pd = d.distort(&p);
            let back = d.undistort(&pd);
            prop_assert!(back.is_some(), "no inverse for {:?}", p);
            let back = back.unwrap();
            // 1e-3 px at f = 1000 px is 1e-6 normalised; demand far better.
            prop_assert!((back - p).norm() < 1e-9, "{:?} -> {:?}", p, back);
        }
    }
}
