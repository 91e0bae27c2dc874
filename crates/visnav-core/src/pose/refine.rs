//! Levenberg-Marquardt refinement of the collinearity equations over the inliers, and the
//! covariance of the result.
//!
//! Model (the computer-vision form of the collinearity equations): a world point `X` is seen at
//! normalised image coordinates
//! `x = p_x / p_z`, `y = p_y / p_z` with `p = R_cam_world (X - C_world)` (camera frame x right, y
//! down, z forward). This is the photogrammetric `x = -f (r11 (X-X0) + r12 (Y-Y0) + r13 (Z-Z0)) /
//! (r31 (X-X0) + ...)` with the PATB camera frame flipped by `R_cv_pg = diag(1, -1, -1)`.
//! The residual of observation `i` is whitened: `e_i = [fx (x - x_obs), fy (y - y_obs)] / sigma_i`
//! (pixels over the pixel sigma), so `e^T e` is chi-square with `2n - 6` dof at the true pose.
//!
//! Parameters: `delta = [phi, dC]`, `phi` a rotation vector in the WORLD frame applied on the left,
//! `R_world_cam <- Exp(phi) R_world_cam`, and `C_world <- C_world + dC`. Analytic Jacobian:
//! `dp/dphi = R_cam_world [X - C]_x`, `dp/dC = -R_cam_world`,
//! `d(x, y)/dp = [[1/p_z, 0, -x/p_z], [0, 1/p_z, -y/p_z]]`.
//!
//! Optional attitude prior `R_prior` with covariance `P` (world-frame rotation vector, rad^2):
//! residual `L^-1 Log(R_world_cam R_prior^T)` with `P = L L^T`, Jacobian `L^-1 J_l^-1(Log(..))`.
//!
//! Robust loss (optional): Huber or Cauchy on the whitened residual norm, by iteratively reweighted
//! normal equations (weights `rho'(|e|^2)`).
//!
//! Covariance: `Q = (J^T W J)^-1` at the solution is the a-priori covariance (pixel sigmas taken at
//! face value); the a-posteriori variance factor `sigma0^2 = sum e^2 / (m - 6)` (m residual rows,
//! prior rows included; unweighted even with a robust loss, so that the loss cannot hide
//! residuals larger than the stated sigmas) scales it: `Cov = sigma0^2 Q`. Parameter order of both: `[phi (rad), C (m)]`.

use nalgebra::{Matrix3, Matrix6, Rotation3, SMatrix, Vector2, Vector3, Vector6};
use serde::{Deserialize, Serialize};

use super::{AttitudePrior, Correspondence, Pose};
use crate::validate::{Problems, Validate};

/// Robust loss on the whitened residual norm `s = |e|` (in sigmas).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum RobustLoss {
    /// Plain least squares.
    None,
    /// Huber: quadratic up to `k_sigma`, linear beyond.
    Huber {
        /// Threshold in sigmas of the whitened residual norm.
        k_sigma: f64,
    },
    /// Cauchy (Lorentzian) with scale `c_sigma`.
    Cauchy {
        /// Scale in sigmas of the whitened residual norm.
        c_sigma: f64,
    },
}

impl RobustLoss {
    /// `(rho(s2), rho'(s2))` for the squared whitened norm `s2`.
    fn eval(&self, s2: f64) -> (f64, f64) {
        match *self {
            RobustLoss::None => (s2, 1.0),
            RobustLoss::Huber { k_sigma: k } => {
                if s2 <= k * k {
                    (s2, 1.0)
                } else {
                    let s = s2.sqrt();
                    (2.0 * k * s - k * k, k / s)
                }
            }
            RobustLoss::Cauchy { c_sigma: c } => {
                let c2 = c * c;
                (c2 * (s2 / c2).ln_1p(), 1.0 / (1.0 + s2 / c2))
            }
        }
    }
}

/// Settings of the refinement (`[pose.refine]`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RefineConfig {
    /// Maximum LM iterations.
    pub max_iterations: usize,
    /// Robust loss.
    pub loss: RobustLoss,
    /// Fuse the attitude prior (if given) into the final estimate. Off by default: a navigation
    /// filter that already holds that attitude would count it twice. The consistency check with the
    /// prior is made on the vision-only solution either way.
    pub use_attitude_prior: bool,
    /// Factor (>= 1) on every reported standard deviation: the conservative covariance is
    /// `max(sigma0_floor^2, sigma0^2) * inflation^2 * Q`. 1 = the statistically honest covariance; a larger value
    /// buys margin against unmodelled errors (DEM, map registration, lens model).
    pub sigma_inflation: f64,
    /// Lower bound on the a-posteriori standard deviation of unit weight `sigma0` where it scales
    /// the covariance (`max(sigma0_floor^2, sigma0^2)`). 1 never lets the data claim better
    /// keypoints than the assumed sigmas; below 1 a fix whose residuals are smaller than assumed
    /// (same-source imagery) gets the smaller covariance they show, and the shared-error
    /// inflation then scales with the observed scatter rather than with the assumption.
    pub sigma0_floor: f64,
    /// Estimate a per-fix variance factor for errors shared by neighbouring observations (map
    /// registration, changed ground) from the disagreement of the poses solved from the four image
    /// quadrants' inliers alone (see [`super::split_variance_factor`]); the covariance is scaled by
    /// it when it exceeds 1. Off by default (independent pixel errors need no such factor).
    pub split_variance: bool,
    /// Fuse the attitude prior against the image's conservative covariance (`k Q`, the
    /// information-weighted combination; the default) rather than its a-priori one (`Q`, which
    /// weighs the prior `k` times less). The weaker weighting is for a prior that is not
    /// independent of what the fix will be fused with: a navigation filter's own attitude, whose
    /// errors would otherwise come back to it through the fix's position (see
    /// docs/fix.md, "The attitude prior").
    pub prior_against_conservative: bool,
}

impl RefineConfig {
    /// The settings for a fix whose attitude prior enters unscaled (a filter's own attitude,
    /// `prior_against_conservative = false`): the covariance factor
    /// `max(sigma0_floor^2, sigma0^2) max(1, split) sigma_inflation^2` must not fall below 1
    /// there, or it would shrink the prior's share of the fused covariance, so the floor is
    /// raised to `1 / sigma_inflation` where it is lower.
    pub fn for_unscaled_prior(&self) -> Self {
        Self {
            prior_against_conservative: false,
            sigma0_floor: self.sigma0_floor.max(1.0 / self.sigma_inflation),
            ..self.clone()
        }
    }
}

impl Default for RefineConfig {
    fn default() -> Self {
        Self {
            max_iterations: 30,
            loss: RobustLoss::Huber { k_sigma: 3.0 },
            use_attitude_prior: false,
            sigma_inflation: 1.0,
            sigma0_floor: 1.0,
            split_variance: false,
            prior_against_conservative: true,
        }
    }
}

impl Validate for RefineConfig {
    fn validate(&self, p: &mut Problems) {
        if !(1..=1000).contains(&self.max_iterations) {
            p.push(
                "max_iterations",
                format!("{} is outside 1..=1000", self.max_iterations),
            );
        }
        p.range("sigma_inflation", self.sigma_inflation, 1.0, 10.0);
        // `sigma0_floor x sigma_inflation` may be below 1 (a covariance below the a-priori one,
        // for same-source maps): a prior weighed against the image's covariance
        // (`prior_against_conservative`) keeps its share; a filter's own prior, entering
        // unscaled, gets the floor raised to `1 / sigma_inflation` for its fix
        // ([`RefineConfig::for_unscaled_prior`]).
        p.range("sigma0_floor", self.sigma0_floor, 0.05, 1.0);
        match self.loss {
            RobustLoss::None => {}
            RobustLoss::Huber { k_sigma } => p.range("loss.k_sigma", k_sigma, 0.5, 100.0),
            RobustLoss::Cauchy { c_sigma } => p.range("loss.c_sigma", c_sigma, 0.5, 100.0),
        }
    }
}

/// Why the refinement failed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RefineError {
    /// Fewer than 3 points, or no more residual rows than the 6 parameters.
    #[error("{n} observations cannot determine 6 pose parameters")]
    TooFewObservations {
        /// Points given.
        n: usize,
    },
    /// The normal matrix could not be factorised: degenerate geometry.
    #[error("the normal matrix is not positive definite (degenerate geometry)")]
    Singular,
    /// A NaN or infinity appeared in the residuals, the Jacobian or the step.
    #[error("non-finite value in the adjustment")]
    NonFinite,
    /// The attitude prior's covariance has no Cholesky factor.
    #[error("the attitude prior covariance is not positive definite")]
    BadPriorCovariance,
}

/// Result of [`refine_pose`].
#[derive(Debug, Clone, PartialEq)]
pub struct Refined {
    /// The adjusted pose.
    pub pose: Pose,
    /// A-priori covariance `(J^T W J)^-1`, order `[phi_world (rad), C_world (m)]`.
    pub cov_apriori: Matrix6<f64>,
    /// A-posteriori variance factor.
    pub sigma0_sq: f64,
    /// Redundancy `m - 6`.
    pub dof: usize,
    /// LM iterations done.
    pub iterations: usize,
    /// RMS of the 2-D pixel error over the observations used.
    pub rms_px: f64,
    /// Condition number of the Jacobi-scaled normal matrix.
    pub condition_number: f64,
}

/// The rotation vector of `r` (its logarithm, angle in `[0, pi]`), through the unit quaternion
/// (Shepperd's method) and `atan2`. nalgebra's `Rotation3::scaled_axis` takes the `acos` of
/// `(trace - 1) / 2`, which is NaN when a product of rotations that drifted from orthonormality by
/// rounding (1e-8 after a few dozen products) pushes it past 1 near the identity: found by the
/// visual odometry's chained attitude.
pub fn log_so3(r: &Rotation3<f64>) -> Vector3<f64> {
    let q = nalgebra::UnitQuaternion::from_rotation_matrix(r);
    let (w, v) = (q.w, q.imag());
    // The shorter way round: q and -q are the same rotation.
    let (w, v) = if w < 0.0 { (-w, -v) } else { (w, v) };
    let s = v.norm();
    if !(s.is_finite() && w.is_finite()) {
        return Vector3::repeat(f64::NAN);
    }
    if s <= 0.0 {
        return Vector3::zeros();
    }
    v * (2.0 * s.atan2(w) / s)
}

/// 3x3 skew-symmetric matrix `[v]_x`.
pub fn skew(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// Inverse of the left Jacobian of SO(3) at rotation vector `phi`.
pub fn so3_left_jacobian_inv(phi: &Vector3<f64>) -> Matrix3<f64> {
    let th = phi.norm();
    let k = skew(phi);
    if th < 1e-6 {
        return Matrix3::identity() - 0.5 * k + k * k / 12.0;
    }
    let coef = 1.0 / (th * th) - (1.0 + th.cos()) / (2.0 * th * th.sin());
    Matrix3::identity() - 0.5 * k + coef * k * k
}

/// Whitened residual (2) and its Jacobian (2x6) for one observation, or None when the point is
/// behind the camera or values are not finite.
#[inline]
pub(crate) fn residual_and_jacobian(
    r_cam_world: &Matrix3<f64>,
    c_world: &Vector3<f64>,
    corr: &Correspondence,
    fx_px: f64,
    fy_px: f64,
) -> Option<(Vector2<f64>, SMatrix<f64, 2, 6>)> {
    let d = corr.point_world - c_world;
    let p = r_cam_world * d;
    if p.z.is_nan() || p.z <= 0.0 {
        return None;
    }
    let iz = 1.0 / p.z;
    let (x, y) = (p.x * iz, p.y * iz);
    let w = 1.0 / corr.sigma_px;
    let e = Vector2::new(
        fx_px * w * (x - corr.obs_norm.x),
        fy_px * w * (y - corr.obs_norm.y),
    );
    // d(e)/dp
    let a = fx_px * w * iz;
    let b = fy_px * w * iz;
    let de_dp = SMatrix::<f64, 2, 3>::new(a, 0.0, -a * x, 0.0, b, -b * y);
    let dp_dphi = r_cam_world * skew(&d);
    let mut j = SMatrix::<f64, 2, 6>::zeros();
    j.fixed_view_mut::<2, 3>(0, 0).copy_from(&(de_dp * dp_dphi));
    j.fixed_view_mut::<2, 3>(0, 3)
        .copy_from(&(-(de_dp * r_cam_world)));
    if e.iter().chain(j.iter()).all(|v| v.is_finite()) {
        Some((e, j))
    } else {
        None
    }
}

struct PriorTerm {
    r_prior: Rotation3<f64>,
    l_inv: Matrix3<f64>,
}

impl PriorTerm {
    fn new(p: &AttitudePrior) -> Result<Self, RefineError> {
        let chol = nalgebra::Cholesky::new(p.cov_rad2).ok_or(RefineError::BadPriorCovariance)?;
        let l_inv = chol
            .l()
            .try_inverse()
            .ok_or(RefineError::BadPriorCovariance)?;
        if !l_inv.iter().all(|v| v.is_finite()) {
            return Err(RefineError::BadPriorCovariance);
        }
        Ok(Self {
            r_prior: p.r_world_cam,
            l_inv,
        })
    }
    fn residual(&self, r_world_cam: &Rotation3<f64>) -> (Vector3<f64>, Matrix3<f64>) {
        let phi = log_so3(&(r_world_cam * self.r_prior.inverse()));
        (self.l_inv * phi, self.l_inv * so3_left_jacobian_inv(&phi))
    }
}

struct Normal {
    h: Matrix6<f64>,
    g: Vector6<f64>,
    cost: f64,
    sum_sq: f64,
    px_sq: f64,
}

/// The normal equations of `pose` over the correspondences `idx` (pixels from normalised
/// residuals by `focal_px`), each weighed by `loss`, with the attitude prior's rows.
fn accumulate(
    corrs: &[Correspondence],
    idx: &[usize],
    pose: &Pose,
    [fx, fy]: [f64; 2],
    loss: &RobustLoss,
    prior: Option<&PriorTerm>,
) -> Option<Normal> {
    let r_cw = pose.r_world_cam.inverse();
    let r_cw = r_cw.matrix();
    let mut n = Normal {
        h: Matrix6::zeros(),
        g: Vector6::zeros(),
        cost: 0.0,
        sum_sq: 0.0,
        px_sq: 0.0,
    };
    for &i in idx {
        let c = &corrs[i];
        let (e, j) = residual_and_jacobian(r_cw, &pose.c_world, c, fx, fy)?;
        let s2 = e.norm_squared();
        let (rho, w) = loss.eval(s2);
        n.cost += rho;
        n.sum_sq += s2; // unweighted: a robust loss must not hide a wrong pixel sigma
        n.px_sq += s2 * c.sigma_px * c.sigma_px;
        let jt = j.transpose();
        n.h += jt * j * w;
        n.g += jt * e * w;
    }
    if let Some(p) = prior {
        let (r, j) = p.residual(&pose.r_world_cam);
        let s2 = r.norm_squared();
        n.cost += s2;
        n.sum_sq += s2;
        let jt = j.transpose();
        let mut hv = n.h.fixed_view_mut::<3, 3>(0, 0);
        hv += jt * j;
        let mut gv = n.g.fixed_view_mut::<3, 1>(0, 0);
        gv += jt * r;
    }
    (n.cost.is_finite() && n.h.iter().all(|v| v.is_finite())).then_some(n)
}

/// Apply the update `delta = [phi_world, dC]`.
pub fn apply_update(pose: &Pose, delta: &Vector6<f64>) -> Pose {
    let phi = Vector3::new(delta[0], delta[1], delta[2]);
    let mut r = Rotation3::from_scaled_axis(phi) * pose.r_world_cam;
    r.renormalize();
    Pose {
        r_world_cam: r,
        c_world: pose.c_world + Vector3::new(delta[3], delta[4], delta[5]),
    }
}

/// Condition number of the Jacobi-scaled symmetric positive matrix `h`.
fn scaled_condition(h: &Matrix6<f64>) -> f64 {
    let d = h
        .diagonal()
        .map(|v| if v > 0.0 { 1.0 / v.sqrt() } else { 0.0 });
    let hs = Matrix6::from_fn(|i, j| h[(i, j)] * d[i] * d[j]);
    let ev = hs.symmetric_eigenvalues();
    let (lo, hi) = (ev.min(), ev.max());
    if lo > 0.0 { hi / lo } else { f64::INFINITY }
}

/// Refine `initial` over the correspondences `idx` by Levenberg-Marquardt (see the module doc), and
/// compute the covariance at the solution. `focal_px` (`[fx, fy]`) converts normalised residuals
/// to pixels.
pub fn refine_pose(
    corrs: &[Correspondence],
    idx: &[usize],
    initial: &Pose,
    focal_px: [f64; 2],
    attitude_prior: Option<&AttitudePrior>,
    cfg: &RefineConfig,
) -> Result<Refined, RefineError> {
    let prior = attitude_prior.map(PriorTerm::new).transpose()?;
    let rows = 2 * idx.len() + if prior.is_some() { 3 } else { 0 };
    if rows <= 6 || idx.len() < 3 {
        return Err(RefineError::TooFewObservations { n: idx.len() });
    }
    let loss = cfg.loss;
    let mut pose = *initial;
    let mut cur = accumulate(corrs, idx, &pose, focal_px, &loss, prior.as_ref())
        .ok_or(RefineError::NonFinite)?;
    let mut mu = 1e-4;
    let mut iterations = 0;
    for _ in 0..cfg.max_iterations {
        iterations += 1;
        let mut accepted = false;
        let mut small_step = false;
        for _ in 0..12 {
            let mut a = cur.h;
            for k in 0..6 {
                a[(k, k)] += mu * cur.h[(k, k)].max(1e-12);
            }
            let Some(chol) = nalgebra::Cholesky::new(a) else {
                mu *= 10.0;
                continue;
            };
            let delta = -chol.solve(&cur.g);
            if !delta.iter().all(|v| v.is_finite()) {
                return Err(RefineError::NonFinite);
            }
            let cand = apply_update(&pose, &delta);
            match accumulate(corrs, idx, &cand, focal_px, &loss, prior.as_ref()) {
                Some(n) if n.cost <= cur.cost => {
                    let rot_step = delta.fixed_rows::<3>(0).norm();
                    let pos_step = delta.fixed_rows::<3>(3).norm();
                    small_step = rot_step < 1e-10 && pos_step < 1e-7
                        || cur.cost - n.cost <= 1e-12 * cur.cost;
                    pose = cand;
                    cur = n;
                    mu = (mu / 3.0).max(1e-12);
                    accepted = true;
                    break;
                }
                _ => mu *= 4.0,
            }
        }
        if !accepted || small_step {
            break;
        }
    }
    let h = cur.h;
    let chol = nalgebra::Cholesky::new(h).ok_or(RefineError::Singular)?;
    let cov_apriori = chol.inverse();
    if !cov_apriori.iter().all(|v| v.is_finite()) {
        return Err(RefineError::NonFinite);
    }
    let dof = rows - 6;
    let sigma0_sq = cur.sum_sq / dof as f64;
    let rms_px = (cur.px_sq / idx.len() as f64).sqrt();
    Ok(Refined {
        pose,
        cov_apriori,
        sigma0_sq,
        dof,
        iterations,
        rms_px,
        condition_number: scaled_condition(&h),
    })
}

/// Rotate a 3x3 covariance into another frame: `R_a_b * Cov_b * R_a_b^T`, e.g. the world-frame
/// position covariance into NED with `r_ned_world` (the caller knows the grid convergence).
pub fn rotate_cov3(cov_b: &Matrix3<f64>, r_a_b: &Rotation3<f64>) -> Matrix3<f64> {
    let r = r_a_b.matrix();
    r * cov_b * r.transpose()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_log_of_a_drifted_rotation_is_finite_and_right() {
        // A rotation 2e-4 rad from the identity whose matrix drifted from orthonormality by 1e-8
        // (what chaining a few dozen relative rotations does): nalgebra's scaled_axis gives NaN.
        let truth = Vector3::new(1e-4, -1.5e-4, 0.5e-4);
        let exact = Rotation3::from_scaled_axis(truth);
        let drifted: Rotation3<f64> =
            Rotation3::from_matrix_unchecked(exact.matrix() * (1.0 + 1.2e-8));
        // (nalgebra's scaled_axis gives NaN here as of 0.35; not asserted, it may clamp one day.)
        let phi = log_so3(&drifted);
        assert!((phi - truth).norm() < 1e-9, "{phi:?}");
        // Large angles, both signs of the quaternion, the identity.
        for v in [
            Vector3::new(0.0, 0.0, 3.0),
            Vector3::new(-2.0, 1.0, 0.5),
            Vector3::new(0.3, -0.2, 0.1),
        ] {
            let p = log_so3(&Rotation3::from_scaled_axis(v));
            assert!((p - v).norm() < 1e-12, "{v:?} -> {p:?}");
        }
        assert_eq!(log_so3(&Rotation3::identity()), Vector3::zeros());
        let nan: Rotation3<f64> = Rotation3::from_matrix_unchecked(Matrix3::repeat(f64::NAN));
        assert!(log_so3(&nan).iter().all(|v| v.is_nan()));
    }
    use crate::rng::Rng;
    use crate::validate::{Problems, Validate};

    /// A floor below the inflation's inverse is accepted (same-source maps), and a fix whose
    /// prior enters unscaled gets it raised so that its covariance factor stays at least 1.
    #[test]
    fn a_low_sigma0_floor_is_raised_for_an_unscaled_prior() {
        let cfg = |floor: f64, inflation: f64| RefineConfig {
            sigma0_floor: floor,
            sigma_inflation: inflation,
            ..RefineConfig::default()
        };
        let check = |c: RefineConfig| {
            let mut p = Problems::default();
            c.validate(&mut p);
            p.list.iter().map(|i| i.to_string()).collect::<Vec<_>>()
        };
        assert!(check(cfg(1.0, 1.0)).is_empty());
        assert!(check(cfg(0.1, 2.0)).is_empty());
        let e = check(cfg(0.01, 4.0));
        assert!(e.iter().any(|m| m.contains("sigma0_floor")), "{e:?}");
        for (floor, inflation) in [(0.1, 2.0), (0.25, 4.0), (1.0, 1.0), (0.05, 10.0)] {
            let u = cfg(floor, inflation).for_unscaled_prior();
            assert!(!u.prior_against_conservative);
            assert!(
                u.sigma0_floor * u.sigma_inflation >= 1.0 - 1e-12,
                "{floor} {inflation}"
            );
            assert!(u.sigma0_floor >= floor);
            // The factor's smallest value (sigma0 = 0, no split) is then at least 1.
            let cov = crate::pose::PoseCovariance {
                apriori: nalgebra::Matrix6::identity(),
                added: nalgebra::Matrix6::zeros(),
                sigma0_sq: 0.0,
                dof: 10,
                inflation: u.sigma_inflation,
                split_factor: 1.0,
                split_groups: 0,
                sigma0_floor: u.sigma0_floor,
            };
            assert!(cov.factor() >= 1.0 - 1e-12, "{}", cov.factor());
        }
        assert_eq!(cfg(1.0, 4.0).for_unscaled_prior().sigma0_floor, 1.0);
    }

    fn scene(rng: &mut Rng, n: usize) -> (Vec<Correspondence>, Pose) {
        let pose = Pose {
            r_world_cam: Rotation3::from_euler_angles(std::f64::consts::PI + 0.1, -0.05, 0.7),
            c_world: Vector3::new(10.0, -20.0, 1500.0),
        };
        let r_cw = pose.r_world_cam.inverse();
        let mut v = Vec::new();
        while v.len() < n {
            let x = Vector3::new(
                rng.range(-800.0, 800.0),
                rng.range(-800.0, 800.0),
                rng.range(-50.0, 200.0),
            );
            let p = r_cw * (x - pose.c_world);
            if p.z <= 0.0 {
                continue;
            }
            v.push(Correspondence {
                point_world: x,
                obs_norm: Vector2::new(p.x / p.z, p.y / p.z),
                sigma_px: rng.range(0.5, 2.0),
            });
        }
        (v, pose)
    }

    #[test]
    fn jacobian_matches_finite_differences() {
        let mut rng = Rng::new(11);
        let (mut corrs, pose) = scene(&mut rng, 20);
        for c in corrs.iter_mut() {
            c.obs_norm += Vector2::new(rng.normal(), rng.normal()) * 1e-3;
        }
        let (fx, fy) = (554.0, 560.0);
        for c in &corrs {
            let r_cw = pose.r_world_cam.inverse();
            let (e0, j) = residual_and_jacobian(r_cw.matrix(), &pose.c_world, c, fx, fy).unwrap();
            for k in 0..6 {
                let h = if k < 3 { 1e-7 } else { 1e-4 };
                let mut d = Vector6::zeros();
                d[k] = h;
                let pp = apply_update(&pose, &d);
                d[k] = -h;
                let pm = apply_update(&pose, &d);
                let (ep, _) = residual_and_jacobian(
                    pp.r_world_cam.inverse().matrix(),
                    &pp.c_world,
                    c,
                    fx,
                    fy,
                )
                .unwrap();
                let (em, _) = residual_and_jacobian(
                    pm.r_world_cam.inverse().matrix(),
                    &pm.c_world,
                    c,
                    fx,
                    fy,
                )
                .unwrap();
                let num = (ep - em) / (2.0 * h);
                let ana = j.column(k);
                let err = (num - ana).norm();
                assert!(
                    err < 1e-4 * (1.0 + ana.norm()),
                    "col {k}: num {num:?} ana {ana:?} (e0 {e0:?})"
                );
            }
        }
        // Prior term Jacobian.
        let prior = AttitudePrior {
            r_world_cam: Rotation3::from_scaled_axis(Vector3::new(0.02, -0.01, 0.03))
                * pose.r_world_cam,
            cov_rad2: Matrix3::from_diagonal(&Vector3::new(1e-4, 2e-4, 4e-4)),
        };
        let term = PriorTerm::new(&prior).unwrap();
        let (_, j) = term.residual(&pose.r_world_cam);
        for k in 0..3 {
            let h = 1e-7;
            let mut d = Vector6::zeros();
            d[k] = h;
            let (rp, _) = term.residual(&apply_update(&pose, &d).r_world_cam);
            d[k] = -h;
            let (rm, _) = term.residual(&apply_update(&pose, &d).r_world_cam);
            let num = (rp - rm) / (2.0 * h);
            assert!(
                (num - j.column(k)).norm() < 1e-5 * (1.0 + num.norm()),
                "prior col {k}"
            );
        }
    }

    #[test]
    fn converges_from_perturbed_start() {
        let mut rng = Rng::new(5);
        let (corrs, truth) = scene(&mut rng, 100);
        let idx: Vec<usize> = (0..corrs.len()).collect();
        let start = Pose {
            r_world_cam: Rotation3::from_scaled_axis(Vector3::new(0.03, -0.02, 0.05))
                * truth.r_world_cam,
            c_world: truth.c_world + Vector3::new(40.0, -30.0, 25.0),
        };
        let r = refine_pose(
            &corrs,
            &idx,
            &start,
            [554.0, 554.0],
            None,
            &RefineConfig::default(),
        )
        .unwrap();
        assert!(
            (r.pose.c_world - truth.c_world).norm() < 1e-6,
            "{:?}",
            r.pose.c_world - truth.c_world
        );
        assert!((r.pose.r_world_cam.inverse() * truth.r_world_cam).angle() < 1e-9);
        assert!(r.sigma0_sq < 1e-12);
        assert_eq!(r.dof, 194);
    }

    #[test]
    fn degenerate_is_an_error_not_nan() {
        let mut rng = Rng::new(6);
        let (mut corrs, truth) = scene(&mut rng, 3);
        let idx: Vec<usize> = (0..corrs.len()).collect();
        assert!(matches!(
            refine_pose(
                &corrs,
                &idx,
                &truth,
                [554.0, 554.0],
                None,
                &RefineConfig::default()
            ),
            Err(RefineError::TooFewObservations { .. })
        ));
        corrs[0].point_world.x = f64::NAN;
        let (more, _) = scene(&mut rng, 10);
        corrs.extend(more);
        let idx: Vec<usize> = (0..corrs.len()).collect();
        assert!(
            refine_pose(
                &corrs,
                &idx,
                &truth,
                [554.0, 554.0],
                None,
                &RefineConfig::default()
            )
            .is_err()
        );
    }
}
