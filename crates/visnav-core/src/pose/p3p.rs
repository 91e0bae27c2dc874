//! Minimal absolute-pose solver: Lambda Twist P3P.
//!
//! Follows M. Persson and K. Nordberg, "Lambda Twist: An Accurate Fast Robust Perspective Three
//! Point (P3P) Solver", ECCV 2018 (Algorithm 1), with the two sign/ordering corrections to the
//! paper's printed equations that later implementations (e.g. PoseLib) point out: the cubic's
//! `c1`/`c2` are `<D2, cof(D1)>` and `<D1, cof(D2)>`, and the first coefficient of the
//! characteristic polynomial in the known-zero eigen-decomposition is `-trace(D0)`.
//!
//! Problem: find `R`, `t` with `lambda_i * y_i = R * x_i + t`, `lambda_i > 0`, for three unit bearing
//! vectors `y_i` (camera frame) and three world points `x_i`. Here `R = R_cam_world` and
//! `t = -R_cam_world * C_world`. The squared distances `a_ij = |x_i - x_j|^2` and cosines
//! `b_ij = y_i . y_j` give three quadratics in the depths `lambda`; two of them are combined into a
//! degenerate conic `D0 = D1 + gamma * D2` (gamma a real root of the cubic `det(D1 + gamma D2) = 0`),
//! which factors into two lines through the origin; intersecting each line with one quadratic gives up
//! to four depth triples, which are polished by Gauss-Newton on the three distance equations and
//! turned into a rotation by aligning the triangle edges.
//!
//! Degenerate input (coincident or collinear world points, parallel bearings, non-finite values)
//! yields zero solutions, never NaN: every returned solution is checked finite.

use nalgebra::{Matrix3, Vector3};

/// One P3P solution: `lambda * y = r_cam_world * x + t_cam`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct P3pSolution {
    /// Rotation world -> camera (not exactly orthonormal under noise; orthonormalise before
    /// publishing it).
    pub r_cam_world: Matrix3<f64>,
    /// Translation: the world origin in camera coordinates, `-R_cam_world * C_world`.
    pub t_cam: Vector3<f64>,
}

/// Up to four solutions without heap allocation.
#[derive(Debug, Clone, Copy)]
pub struct P3pSolutions {
    len: usize,
    items: [P3pSolution; 4],
}

impl P3pSolutions {
    fn new() -> Self {
        let z = P3pSolution {
            r_cam_world: Matrix3::zeros(),
            t_cam: Vector3::zeros(),
        };
        Self {
            len: 0,
            items: [z; 4],
        }
    }
    fn push(&mut self, s: P3pSolution) {
        if self.len < 4 {
            self.items[self.len] = s;
            self.len += 1;
        }
    }
    /// The solutions found (0..=4).
    pub fn as_slice(&self) -> &[P3pSolution] {
        &self.items[..self.len]
    }
    /// Number of solutions.
    pub fn len(&self) -> usize {
        self.len
    }
    /// No solution.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }
}

/// Eigen-decomposition of a symmetric 3x3 matrix known to be singular: returns the eigenvectors of
/// the two non-zero eigenvalues (largest magnitude first) and those eigenvalues.
fn eig3x3_known0(m: &Matrix3<f64>) -> Option<(Vector3<f64>, Vector3<f64>, f64, f64)> {
    let p1 = -m[(0, 0)] - m[(1, 1)] - m[(2, 2)];
    let p0 = -m[(0, 1)] * m[(0, 1)] - m[(0, 2)] * m[(0, 2)] - m[(1, 2)] * m[(1, 2)]
        + m[(0, 0)] * (m[(1, 1)] + m[(2, 2)])
        + m[(1, 1)] * m[(2, 2)];
    let disc = (p1 * p1 / 4.0 - p0).max(0.0).sqrt();
    let tmp = -p1 / 2.0;
    let (mut sig1, mut sig2) = (tmp + disc, tmp - disc);
    if sig1.abs() < sig2.abs() {
        std::mem::swap(&mut sig1, &mut sig2);
    }
    let vec_for = |sig: f64| -> Option<Vector3<f64>> {
        let c = sig * sig + m[(0, 0)] * m[(1, 1)]
            - sig * (m[(0, 0)] + m[(1, 1)])
            - m[(0, 1)] * m[(0, 1)];
        let a1 = (sig * m[(0, 2)] + m[(0, 1)] * m[(1, 2)] - m[(0, 2)] * m[(1, 1)]) / c;
        let a2 = (sig * m[(1, 2)] + m[(0, 1)] * m[(0, 2)] - m[(0, 0)] * m[(1, 2)]) / c;
        let n = 1.0 / (1.0 + a1 * a1 + a2 * a2).sqrt();
        let v = Vector3::new(a1 * n, a2 * n, n);
        v.iter().all(|x| x.is_finite()).then_some(v)
    };
    Some((vec_for(sig1)?, vec_for(sig2)?, sig1, sig2))
}

/// A real root of the monic cubic `g^3 + c2 g^2 + c1 g + c0` (the largest one when all three are
/// real), polished by Newton steps.
fn cubic_root(c2: f64, c1: f64, c0: f64) -> Option<f64> {
    let a = c1 - c2 * c2 / 3.0;
    let b = (2.0 * c2 * c2 * c2 - 9.0 * c2 * c1) / 27.0 + c0;
    let disc = b * b / 4.0 + a * a * a / 27.0;
    let mut g = if disc > 0.0 {
        let s = disc.sqrt();
        let h = -0.5 * b;
        (h + s).cbrt() + (h - s).cbrt() - c2 / 3.0
    } else if a < 0.0 {
        let c = (3.0 * b / (2.0 * a) * (-3.0 / a).sqrt()).clamp(-1.0, 1.0);
        2.0 * (-a / 3.0).sqrt() * (c.acos() / 3.0).cos() - c2 / 3.0
    } else {
        // a == 0 and b == 0: triple root.
        -c2 / 3.0
    };
    for _ in 0..2 {
        let f = ((g + c2) * g + c1) * g + c0;
        let df = (3.0 * g + 2.0 * c2) * g + c1;
        if df.abs() > 1e-300 {
            let step = f / df;
            if step.is_finite() {
                g -= step;
            }
        }
    }
    g.is_finite().then_some(g)
}

/// Gauss-Newton on the three distance equations
/// `l_i^2 - 2 l_i l_j b_ij + l_j^2 = a_ij`.
/// `a = [a12, a13, a23]`, `b = [b12, b13, b23]`.
fn refine_lambda(l: &mut [f64; 3], [a12, a13, a23]: [f64; 3], [b12, b13, b23]: [f64; 3]) {
    for _ in 0..5 {
        let [l1, l2, l3] = *l;
        let r1 = l1 * l1 - 2.0 * l1 * l2 * b12 + l2 * l2 - a12;
        let r2 = l1 * l1 - 2.0 * l1 * l3 * b13 + l3 * l3 - a13;
        let r3 = l2 * l2 - 2.0 * l2 * l3 * b23 + l3 * l3 - a23;
        if r1.abs() + r2.abs() + r3.abs() < 1e-10 * (a12 + a13 + a23) {
            return;
        }
        let x11 = l1 - l2 * b12;
        let x12 = l2 - l1 * b12;
        let x21 = l1 - l3 * b13;
        let x23 = l3 - l1 * b13;
        let x32 = l2 - l3 * b23;
        let x33 = l3 - l2 * b23;
        let det = x11 * x23 * x32 + x12 * x21 * x33;
        if det.abs() < 1e-300 {
            return;
        }
        let h = 0.5 / det;
        let d1 = (-x23 * x32 * r1 - x12 * x33 * r2 + x12 * x23 * r3) * h;
        let d2 = (-x21 * x33 * r1 + x11 * x33 * r2 - x11 * x23 * r3) * h;
        let d3 = (x21 * x32 * r1 - x11 * x32 * r2 - x12 * x21 * r3) * h;
        if !(d1.is_finite() && d2.is_finite() && d3.is_finite()) {
            return;
        }
        *l = [l1 + d1, l2 + d2, l3 + d3];
    }
}

/// The three correspondences as Lambda Twist sees them: unit bearings, the world triangle's
/// sides `dx`, their squared lengths `a` and the bearings' cosines `b`.
struct Triangle {
    yn: [Vector3<f64>; 3],
    dx12: Vector3<f64>,
    dx13: Vector3<f64>,
    /// `dx12 x dx13`: the triangle's normal.
    cross: Vector3<f64>,
    a12: f64,
    a13: f64,
    a23: f64,
    b12: f64,
    b13: f64,
    b23: f64,
}

impl Triangle {
    /// `None` for non-finite input, zero bearings, coincident or collinear world points and
    /// parallel bearings.
    fn new(y: &[Vector3<f64>; 3], x: &[Vector3<f64>; 3]) -> Option<Self> {
        let mut yn = [Vector3::zeros(); 3];
        for i in 0..3 {
            let n = y[i].norm();
            if !(n.is_finite() && n > 0.0 && x[i].iter().all(|v| v.is_finite())) {
                return None;
            }
            yn[i] = y[i] / n;
        }
        let dx12 = x[0] - x[1];
        let dx13 = x[0] - x[2];
        let dx23 = x[1] - x[2];
        let (a12, a13, a23) = (
            dx12.norm_squared(),
            dx13.norm_squared(),
            dx23.norm_squared(),
        );
        let (b12, b13, b23) = (yn[0].dot(&yn[1]), yn[0].dot(&yn[2]), yn[1].dot(&yn[2]));
        let scale = a12.max(a13).max(a23);
        if scale.is_nan() || scale <= 0.0 || a12.min(a13).min(a23) < 1e-12 * scale {
            return None; // coincident points
        }
        // Collinear world points: the triangle has no area and the rotation is undetermined.
        let cross = dx12.cross(&dx13);
        if cross.norm_squared() < 1e-14 * a12 * a13 {
            return None;
        }
        if b12.abs() > 1.0 - 1e-15 || b13.abs() > 1.0 - 1e-15 || b23.abs() > 1.0 - 1e-15 {
            return None; // parallel bearings
        }
        Some(Self {
            yn,
            dx12,
            dx13,
            cross,
            a12,
            a13,
            a23,
            b12,
            b13,
            b23,
        })
    }

    /// The paper's steps 1-3: the cubic's root `gamma` of `det(D1 + gamma D2) = 0` and the
    /// eigen-decomposition of the degenerate `D0 = D1 + gamma D2` (eigenvectors `e0`, `e1` and
    /// `s = sqrt(-sigma2 / sigma1)`): the two lines the lambdas lie on are `e0 -+ s e1`.
    fn lines(&self) -> Option<(Vector3<f64>, Vector3<f64>, f64)> {
        let (a12, a13, a23) = (self.a12, self.a13, self.a23);
        let a23b12 = a23 * self.b12;
        let a12b23 = a12 * self.b23;
        let a23b13 = a23 * self.b13;
        let a13b23 = a13 * self.b23;
        #[rustfmt::skip]
        let d1 = Matrix3::new(
            a23, -a23b12, 0.0,
            -a23b12, a23 - a12, a12b23,
            0.0, a12b23, -a12,
        );
        #[rustfmt::skip]
        let d2 = Matrix3::new(
            a23, 0.0, -a23b13,
            0.0, -a13, a13b23,
            -a23b13, a13b23, a23 - a13,
        );
        let cof = |d: &Matrix3<f64>| -> Matrix3<f64> {
            Matrix3::from_columns(&[
                d.column(1).cross(&d.column(2)),
                d.column(2).cross(&d.column(0)),
                d.column(0).cross(&d.column(1)),
            ])
        };
        let (dx1, dx2) = (cof(&d1), cof(&d2));
        let c3 = d2.column(0).dot(&dx2.column(0));
        let c2 = d1.component_mul(&dx2).sum();
        let c1 = d2.component_mul(&dx1).sum();
        let c0 = d1.column(0).dot(&dx1.column(0));
        let cscale = c3.abs().max(c2.abs()).max(c1.abs()).max(c0.abs());
        if !(cscale.is_finite() && c3.abs() > 1e-14 * cscale) {
            return None;
        }
        let gamma = cubic_root(c2 / c3, c1 / c3, c0 / c3)?;
        let d0 = d1 + d2 * gamma;
        let (e0, e1, sig1, sig2) = eig3x3_known0(&d0)?;
        let ratio = -sig2 / sig1;
        if !(ratio.is_finite() && ratio >= 0.0) {
            return None;
        }
        Some((e0, e1, ratio.sqrt()))
    }

    /// Step 4 on the line `u`: the lambdas where it meets the quadratic of the side with the
    /// larger coefficient (lambda1's, or lambda2's when `u1` is small), at most two, all
    /// positive and finite.
    fn lambdas_on(&self, u: [f64; 3]) -> Vec<[f64; 3]> {
        const TOL_DOUBLE_ROOT: f64 = 1e-12;
        let (a12, a13, a23) = (self.a12, self.a13, self.a23);
        let (b12, b13, b23) = (self.b12, self.b13, self.b23);
        let (a13b23, a23b13) = (a13 * b23, a23 * b13);
        let [u1, u2, u3] = u;
        let switch12 = u1.abs() < u2.abs();
        let (a, b, c, w0, w1);
        if switch12 {
            w0 = -u1 / u2;
            w1 = -u3 / u2;
            a = -a13 * w1 * w1 + 2.0 * a13b23 * w1 - a13 + a23;
            b = 2.0 * a13b23 * w0 - 2.0 * a23b13 - 2.0 * a13 * w0 * w1;
            c = -a13 * w0 * w0 + a23;
        } else {
            w0 = -u2 / u1;
            w1 = -u3 / u1;
            a = (a13 - a12) * w1 * w1 + 2.0 * a12 * b13 * w1 - a12;
            b = -2.0 * a13 * b12 * w1 + 2.0 * a12 * b13 * w0 - 2.0 * w0 * w1 * (a12 - a13);
            c = (a13 - a12) * w0 * w0 - 2.0 * a13 * b12 * w0 + a13;
        }
        let mut out = Vec::new();
        if !(w0.is_finite() && w1.is_finite() && a.is_finite() && b.is_finite() && c.is_finite()) {
            return out;
        }
        let b2m4ac = b * b - 4.0 * a * c;
        if b2m4ac < -TOL_DOUBLE_ROOT * (b * b).max(1e-300) {
            return out;
        }
        let sq = b2m4ac.max(0.0).sqrt();
        let mut tau = if b > 0.0 {
            2.0 * c / (-b - sq)
        } else {
            2.0 * c / (-b + sq)
        };
        for k in 0..2 {
            if k == 1 {
                if b2m4ac <= TOL_DOUBLE_ROOT * (b * b).max(1e-300) {
                    break; // double root
                }
                tau = c / (a * tau);
            }
            if !(tau.is_finite() && tau > 0.0) {
                continue;
            }
            let l = if switch12 {
                let l1 = (a13 / (tau * (tau - 2.0 * b13) + 1.0)).sqrt();
                let l3 = tau * l1;
                [l1, w0 * l1 + w1 * l3, l3]
            } else {
                let l2 = (a23 / (tau * (tau - 2.0 * b23) + 1.0)).sqrt();
                let l3 = tau * l2;
                [w0 * l2 + w1 * l3, l2, l3]
            };
            if l.iter().all(|v| v.is_finite() && *v > 0.0) {
                out.push(l);
            }
        }
        out
    }

    /// Step 5: the pose from the depths `l` (refined by Gauss-Newton first), through the
    /// camera-side triangle frame and the inverse world-side one `xx_inv`.
    fn pose(
        &self,
        mut l: [f64; 3],
        xx_inv: &Matrix3<f64>,
        x0: &Vector3<f64>,
    ) -> Option<P3pSolution> {
        refine_lambda(
            &mut l,
            [self.a12, self.a13, self.a23],
            [self.b12, self.b13, self.b23],
        );
        if !l.iter().all(|v| v.is_finite() && *v > 0.0) {
            return None;
        }
        let yn = &self.yn;
        let v1 = yn[0] * l[0] - yn[1] * l[1];
        let v2 = yn[0] * l[0] - yn[2] * l[2];
        let yy = Matrix3::from_columns(&[v1, v2, v1.cross(&v2)]);
        let r = yy * xx_inv;
        let t = yn[0] * l[0] - r * x0;
        (r.iter().all(|v| v.is_finite()) && t.iter().all(|v| v.is_finite())).then_some(
            P3pSolution {
                r_cam_world: r,
                t_cam: t,
            },
        )
    }
}

/// Lambda Twist P3P. `y` are bearing vectors in the camera frame (need not be unit length; they are
/// normalised here), `x` the corresponding world points. Returns up to four poses with all three
/// depths positive.
pub fn p3p_lambda_twist(y: &[Vector3<f64>; 3], x: &[Vector3<f64>; 3]) -> P3pSolutions {
    let mut out = P3pSolutions::new();
    let Some(t) = Triangle::new(y, x) else {
        return out;
    };
    let Some((e0, e1, s)) = t.lines() else {
        return out;
    };
    // Inverse of the world-side triangle frame [dx12, dx13, dx12 x dx13].
    let Some(xx_inv) = Matrix3::from_columns(&[t.dx12, t.dx13, t.cross]).try_inverse() else {
        return out;
    };
    for s in [s, -s] {
        let u = [e0[0] - s * e1[0], e0[1] - s * e1[1], e0[2] - s * e1[2]];
        for l in t.lambdas_on(u) {
            if let Some(sol) = t.pose(l, &xx_inv, &x[0]) {
                out.push(sol);
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Rotation3;
    use proptest::prelude::*;

    fn check_recovers(
        r: Rotation3<f64>,
        c: Vector3<f64>,
        pts: [Vector3<f64>; 3],
    ) -> Result<(), TestCaseError> {
        let rm = *r.matrix();
        let t = -rm * c;
        let y = pts.map(|p| rm * p + t);
        prop_assume!(y.iter().all(|v| v.z > 0.1 * v.norm()));
        // Reject near-degenerate random triangles (tiny area relative to their size).
        let area = (pts[0] - pts[1]).cross(&(pts[0] - pts[2])).norm();
        prop_assume!(area > 1e-2 * (pts[0] - pts[1]).norm_squared().max(1e-9));
        let sols = p3p_lambda_twist(&y, &pts);
        prop_assert!(!sols.is_empty(), "no solution");
        let best = sols
            .as_slice()
            .iter()
            .map(|s| (s.r_cam_world - rm).norm() + (s.t_cam - t).norm() / (1.0 + t.norm()))
            .fold(f64::INFINITY, f64::min);
        prop_assert!(best < 1e-6, "best error {best}");
        for s in sols.as_slice() {
            // Every solution reprojects the three points exactly.
            for i in 0..3 {
                let p = s.r_cam_world * pts[i] + s.t_cam;
                prop_assert!(p.z > 0.0);
                let e = (p / p.norm() - y[i] / y[i].norm()).norm();
                prop_assert!(e < 1e-6, "solution reprojection {e}");
            }
        }
        Ok(())
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(500))]
        #[test]
        fn recovers_true_pose(
            rx in -3.1f64..3.1, ry in -3.1f64..3.1, rz in -3.1f64..3.1,
            c in prop::array::uniform3(-50.0f64..50.0),
            p in prop::array::uniform3(prop::array::uniform3(-10.0f64..10.0)),
        ) {
            let r = Rotation3::from_euler_angles(rx, ry, rz);
            let c = Vector3::from(c);
            // Put the points in front of the camera: shift them along the optical axis.
            let axis = r.inverse() * Vector3::z();
            let pts = p.map(|q| c + axis * 30.0 + Vector3::from(q));
            check_recovers(r, c, pts)?;
        }

        #[test]
        fn aerial_geometry(
            yaw in -3.1f64..3.1, tilt in 0.0f64..0.6,
            h in 1000.0f64..2500.0,
            p in prop::array::uniform3(prop::array::uniform3(-600.0f64..600.0)),
        ) {
            // Nadir-ish camera at height h above ground points with relief.
            let r_world_cam = Rotation3::from_axis_angle(&Vector3::z_axis(), yaw)
                * Rotation3::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI + tilt);
            let c = Vector3::new(1000.0, -500.0, h);
            let pts = p.map(|q| Vector3::new(c.x + q[0], c.y + q[1], q[2] * 0.2));
            check_recovers(r_world_cam.inverse(), c, pts)?;
        }
    }

    #[test]
    fn degenerate_inputs_give_no_nan() {
        let y = [
            Vector3::new(0.0, 0.0, 1.0),
            Vector3::new(0.1, 0.0, 1.0),
            Vector3::new(0.0, 0.1, 1.0),
        ];
        let collinear = [
            Vector3::new(0.0, 0.0, 10.0),
            Vector3::new(1.0, 0.0, 10.0),
            Vector3::new(2.0, 0.0, 10.0),
        ];
        assert!(p3p_lambda_twist(&y, &collinear).is_empty());
        let dup = [
            Vector3::new(0.0, 0.0, 10.0),
            Vector3::new(0.0, 0.0, 10.0),
            Vector3::new(2.0, 0.0, 10.0),
        ];
        assert!(p3p_lambda_twist(&y, &dup).is_empty());
        let nan = [
            Vector3::new(f64::NAN, 0.0, 10.0),
            Vector3::new(1.0, 0.0, 10.0),
            Vector3::new(0.0, 1.0, 10.0),
        ];
        assert!(p3p_lambda_twist(&y, &nan).is_empty());
        let yp = [
            Vector3::new(0.0, 0.0, 1.0),
            Vector3::new(0.0, 0.0, 1.0),
            Vector3::new(0.0, 0.1, 1.0),
        ];
        let ok = [
            Vector3::new(0.0, 0.0, 10.0),
            Vector3::new(1.0, 0.0, 10.0),
            Vector3::new(0.0, 1.0, 10.0),
        ];
        assert!(p3p_lambda_twist(&yp, &ok).is_empty());
        let zero = [Vector3::zeros(), y[1], y[2]];
        assert!(p3p_lambda_twist(&zero, &ok).is_empty());
        // Nearly collinear bearings and points: whatever comes out is finite.
        let mut rng = crate::rng::Rng::new(3);
        for _ in 0..10_000 {
            let pts =
                [0, 1, 2].map(|_| Vector3::new(rng.range(-1.0, 1.0), rng.range(-1e-9, 1e-9), 10.0));
            let ys =
                [0, 1, 2].map(|_| Vector3::new(rng.range(-0.1, 0.1), rng.range(-1e-9, 1e-9), 1.0));
            for s in p3p_lambda_twist(&ys, &pts).as_slice() {
                assert!(
                    s.r_cam_world
                        .iter()
                        .chain(s.t_cam.iter())
                        .all(|v| v.is_finite())
                );
            }
        }
    }
}
