//! Photogrammetric space resection: the camera pose from 2-D/3-D correspondences, its covariance
//! and its integrity.
//!
//! Pipeline of [`resect`]:
//! 1. drop invalid correspondences (non-finite or absurd values, sigma <= 0) and centre the 3-D
//!    points on their coordinate-wise median (numbers stay well conditioned with map grid coordinates of 10^6 m);
//! 2. LO-RANSAC + SPRT over Lambda Twist P3P ([`ransac`], [`p3p`]) with a pixel threshold;
//! 3. Levenberg-Marquardt on the collinearity equations over the inliers ([`refine`]), inliers
//!    re-selected with the refined pose and the adjustment repeated until the set is stable;
//! 4. covariance `sigma0^2 (J^T W J)^-1` (and the a-priori `(J^T W J)^-1`);
//! 5. quality figures and the integrity decision ([`integrity`]), including chi-square consistency
//!    of the vision-only fix with the position and attitude priors;
//! 6. optionally the attitude prior is fused into the final estimate (weighted by its covariance).
//!
//! # Conventions
//! * World frame: any right-handed local Cartesian metric frame with z vertical (up), e.g. the map
//!   grid (x grid east, y grid north, z up, metres). Absolute map coordinates are fine: the solver
//!   centres them itself. "Horizontal" / "vertical" sigmas refer to world x/y and z.
//! * Camera frame `_cam`: x right, y down, z forward (optical axis).
//! * Observations: NORMALISED UNDISTORTED image coordinates `x = (u - cx) / fx`, `y = (v - cy) / fy`
//!   (the caller removes lens distortion), each with a 1-sigma pixel noise `sigma_px` (isotropic). The
//!   sigma should include the pixel-space effect of the 3-D point error (DEM, orthophoto
//!   registration); the a-posteriori sigma0 inflates the covariance when it is too small.
//! * Pose: `R_world_cam` (takes camera-frame vectors to the world frame) and the projection centre
//!   `C_world`. Projection: `p_cam = R_world_cam^T (X_world - C_world)`, `x = p_x / p_z`,
//!   `y = p_y / p_z` — the collinearity equations in computer-vision form (see [`refine`]).
//! * Attitude errors and attitude covariances are rotation vectors in the WORLD frame applied on the
//!   left: `R_true = Exp(phi_world) R_estimate`, radians. Priors use the same convention.
//! * 6x6 covariances are ordered `[phi_world (rad, 3), C_world (m, 3)]`.
//! * To express covariances in NED use [`rotate_cov3`] with `R_ned_world` (for the map grid frame
//!   this includes the swap of axes and the meridian convergence, which the caller knows).

pub mod integrity;
pub mod p3p;
pub mod ransac;
pub mod refine;
pub mod similarity;
pub mod synth;

use std::ops::AddAssign;

use nalgebra::{Matrix3, Matrix6, Rotation3, Vector2, Vector3, Vector6};
use serde::{Deserialize, Serialize};

use crate::validate::{Problems, Validate};
pub use integrity::{FixQuality, IntegrityConfig, Rejection, Verdict, check, chi2_quantile};
pub use p3p::{P3pSolution, P3pSolutions, p3p_lambda_twist};
pub use ransac::{RansacConfig, RansacResult, ransac_p3p};
pub use refine::{
    RefineConfig, RefineError, Refined, RobustLoss, log_so3, refine_pose, rotate_cov3,
};

/// One 2-D/3-D correspondence.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Correspondence {
    /// The 3-D point in the world frame, metres.
    pub point_world: Vector3<f64>,
    /// Its observation in normalised undistorted image coordinates.
    pub obs_norm: Vector2<f64>,
    /// 1-sigma noise of the observation, pixels (isotropic).
    pub sigma_px: f64,
}

impl Correspondence {
    /// Largest accepted world coordinate magnitude, metres (beyond any map grid on Earth).
    pub const MAX_COORD_M: f64 = 1e8;
    /// Largest accepted normalised image coordinate (89.9 deg off the optical axis).
    pub const MAX_NORM: f64 = 500.0;

    /// Finite values of plausible magnitude and a finite positive sigma.
    pub fn is_valid(&self) -> bool {
        self.point_world
            .iter()
            .all(|v| v.abs() <= Self::MAX_COORD_M)
            && self.obs_norm.iter().all(|v| v.abs() <= Self::MAX_NORM)
            && self.sigma_px.is_finite()
            && self.sigma_px > 0.0
    }
}

/// What the solver needs of the camera: focal lengths and principal point in pixels (to convert
/// normalised residuals to pixels and to place the inliers in the image for the spread checks) and
/// the image size.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImageGeometry {
    /// Focal length along u, pixels.
    pub fx_px: f64,
    /// Focal length along v, pixels.
    pub fy_px: f64,
    /// Principal point u, pixels (top-left pixel centre at 0).
    pub cx_px: f64,
    /// Principal point v, pixels.
    pub cy_px: f64,
    /// Image width, pixels.
    pub width_px: u32,
    /// Image height, pixels.
    pub height_px: u32,
}

impl From<&crate::camera::Intrinsics> for ImageGeometry {
    fn from(k: &crate::camera::Intrinsics) -> Self {
        Self {
            fx_px: k.fx_px,
            fy_px: k.fy_px,
            cx_px: k.cx_px,
            cy_px: k.cy_px,
            width_px: k.width_px,
            height_px: k.height_px,
        }
    }
}

impl ImageGeometry {
    /// Pixel position of a normalised point.
    pub fn to_pixel(&self, n: &Vector2<f64>) -> Vector2<f64> {
        Vector2::new(self.cx_px + self.fx_px * n.x, self.cy_px + self.fy_px * n.y)
    }
    /// The focal lengths, principal point and size are usable.
    fn check(&self) -> Result<(), Rejection> {
        let invalid = |reason: String| Err(Rejection::InvalidInput { reason });
        let ok = |v: f64| v.is_finite() && v > 0.0;
        if !(ok(self.fx_px) && ok(self.fy_px)) {
            return invalid(format!(
                "focal lengths fx_px={} fy_px={} must be finite and > 0",
                self.fx_px, self.fy_px
            ));
        }
        if !(self.cx_px.is_finite() && self.cy_px.is_finite()) {
            return invalid(format!(
                "principal point ({}, {}) must be finite",
                self.cx_px, self.cy_px
            ));
        }
        if self.width_px == 0 || self.height_px == 0 {
            return invalid(format!(
                "image size {}x{} is empty",
                self.width_px, self.height_px
            ));
        }
        Ok(())
    }
}

/// A camera pose: `R_world_cam` and the projection centre `C_world`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    /// Rotation taking camera-frame vectors (`_cam`: x right, y down, z forward) to the world frame.
    pub r_world_cam: Rotation3<f64>,
    /// Projection centre in the world frame, metres.
    pub c_world: Vector3<f64>,
}

impl Pose {
    /// A camera looking straight down from `c_world` (world x east, y north, z up): camera x east,
    /// y south, z down at `yaw_rad = 0`; turned by `yaw_rad` about the vertical (counter-clockwise
    /// seen from above), then tilted by `tilt_rad` about its own x axis (a positive tilt turns the
    /// optical axis towards the image's top edge: north at `yaw_rad = 0`). For synthetic scenes and
    /// benchmarks.
    pub fn nadir(c_world: Vector3<f64>, yaw_rad: f64, tilt_rad: f64) -> Self {
        let down = Rotation3::from_matrix_unchecked(Matrix3::new(
            1.0, 0.0, 0.0, //
            0.0, -1.0, 0.0, //
            0.0, 0.0, -1.0,
        ));
        Pose {
            r_world_cam: Rotation3::from_axis_angle(&Vector3::z_axis(), yaw_rad)
                * down
                * Rotation3::from_axis_angle(&Vector3::x_axis(), tilt_rad),
            c_world,
        }
    }

    /// Camera-frame coordinates of a world point: `R_world_cam^T (X - C)`.
    pub fn to_cam(&self, p_world: &Vector3<f64>) -> Vector3<f64> {
        self.r_world_cam.inverse() * (p_world - self.c_world)
    }
    /// Normalised image coordinates of a world point, None when it is not in front of the camera.
    pub fn project(&self, p_world: &Vector3<f64>) -> Option<Vector2<f64>> {
        let p = self.to_cam(p_world);
        (p.z > 0.0).then(|| Vector2::new(p.x / p.z, p.y / p.z))
    }
}

/// Prior attitude: `R_world_cam` with a 3x3 covariance of the world-frame rotation-vector error, rad^2.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AttitudePrior {
    /// The prior's camera attitude, camera to world.
    pub r_world_cam: Rotation3<f64>,
    /// Covariance of its world-frame rotation-vector error, rad^2.
    pub cov_rad2: Matrix3<f64>,
}

/// Prior position of the projection centre with its covariance, world frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PositionPrior {
    /// The prior projection centre, world frame, metres.
    pub c_world: Vector3<f64>,
    /// Its covariance, world frame, m^2.
    pub cov_m2: Matrix3<f64>,
}

/// Optional priors (from the navigation filter), and what the world points may be off by as a
/// whole.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Priors {
    /// Attitude prior: checked for consistency, and fused when `refine.use_attitude_prior` is on.
    pub attitude: Option<AttitudePrior>,
    /// Position prior: used only for the consistency check, never fused.
    pub position: Option<PositionPrior>,
    /// How far the world points as a whole may be tilted against the true world, radians per
    /// horizontal axis (1 sigma; 0: not at all). A map's height error that changes linearly across
    /// the footprint (a constant height over sloping ground, a DEM's tilt) tilts the points about
    /// their centre: the image pins the pose against the points, which then stands turned by that
    /// tilt against the world (attitude) and displaced by it times the camera's height above them
    /// (position). See `MapTilt`; with an attitude prior the tilt is estimated between the
    /// image and the prior (`fuse_attitude_prior`).
    pub map_tilt_sigma_rad: f64,
}

/// All resection settings (`[pose]`).
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ResectionConfig {
    /// Hypothesis search (`[pose.ransac]`).
    pub ransac: RansacConfig,
    /// Least-squares adjustment and covariance scaling (`[pose.refine]`).
    pub refine: RefineConfig,
    /// Accept/reject thresholds (`[pose.integrity]`).
    pub integrity: IntegrityConfig,
}

impl Validate for ResectionConfig {
    fn validate(&self, p: &mut Problems) {
        p.section("ransac", |p| self.ransac.validate(p));
        p.section("refine", |p| self.refine.validate(p));
        p.section("integrity", |p| self.integrity.validate(p));
    }
}

/// Covariance of a fix, parameter order `[phi_world (rad), C_world (m)]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseCovariance {
    /// `(J^T W J)^-1`: the pixel sigmas taken at face value.
    pub apriori: Matrix6<f64>,
    /// Added to the scaled covariance whatever the image's scatter: the world points' tilt as a
    /// whole ([`Priors::map_tilt_sigma_rad`], `MapTilt`), which no factor on the pixel
    /// residuals can see (zero without one).
    pub added: Matrix6<f64>,
    /// A-posteriori variance factor `sigma0^2`.
    pub sigma0_sq: f64,
    /// Redundancy of the adjustment.
    pub dof: usize,
    /// Factor on the standard deviations of [`Self::conservative`] (`refine.sigma_inflation`).
    pub inflation: f64,
    /// Split-sample variance factor (1 when not estimated; see [`split_variance_factor`]).
    pub split_factor: f64,
    /// How many image quadrants' poses measured [`Self::split_factor`]: 0 when it was not
    /// estimated (too few inliers, or off), otherwise 2-4. Without it the covariance has not
    /// been checked for errors the inliers share.
    pub split_groups: usize,
    /// Lower bound on `sigma0` where it scales the covariance (`refine.sigma0_floor`).
    pub sigma0_floor: f64,
}

impl PoseCovariance {
    /// `sigma0^2 (J^T W J)^-1`.
    pub fn aposteriori(&self) -> Matrix6<f64> {
        self.apriori * self.sigma0_sq
    }
    /// The factor of [`Self::conservative`]:
    /// `max(sigma0_floor^2, sigma0^2) max(1, split_factor) inflation^2`.
    pub fn factor(&self) -> f64 {
        self.sigma0_sq.max(self.sigma0_floor * self.sigma0_floor)
            * self.split_factor.max(1.0)
            * self.inflation
            * self.inflation
    }
    /// `max(sigma0_floor^2, sigma0^2) max(1, split_factor) inflation^2 (J^T W J)^-1 + added`:
    /// never smaller than the a-priori covariance when `sigma0_floor * inflation >= 1`. This is
    /// the one used for the integrity checks and the one to hand to a filter.
    pub fn conservative(&self) -> Matrix6<f64> {
        self.apriori * self.factor() + self.added
    }
    /// Conservative position covariance, world frame, m^2.
    pub fn position_world_m2(&self) -> Matrix3<f64> {
        self.conservative().fixed_view::<3, 3>(3, 3).into_owned()
    }
    /// Conservative attitude covariance (world-frame rotation vector), rad^2.
    pub fn attitude_world_rad2(&self) -> Matrix3<f64> {
        self.conservative().fixed_view::<3, 3>(0, 0).into_owned()
    }
    /// Position covariance in NED, given `R_ned_world`.
    pub fn position_ned_m2(&self, r_ned_world: &Rotation3<f64>) -> Matrix3<f64> {
        rotate_cov3(&self.position_world_m2(), r_ned_world)
    }
    /// Attitude covariance as an NED-frame rotation vector, given `R_ned_world`.
    pub fn attitude_ned_rad2(&self, r_ned_world: &Rotation3<f64>) -> Matrix3<f64> {
        rotate_cov3(&self.attitude_world_rad2(), r_ned_world)
    }
}

/// A resection result.
#[derive(Debug, Clone, PartialEq)]
pub struct Fix {
    /// Final pose (world frame).
    pub pose: Pose,
    /// Its covariance.
    pub covariance: PoseCovariance,
    /// The vision-only pose (equal to `pose` unless the attitude prior was fused).
    pub vision_pose: Pose,
    /// The covariance of `vision_pose` (the image alone: no prior in it). A navigation filter
    /// that holds the attitude the prior came from fuses this pose and covariance, all six
    /// degrees of freedom with their correlation, rather than `pose`, whose position already
    /// carries the filter's own attitude (fused twice, and its errors then look confirmed).
    pub vision_covariance: PoseCovariance,
    /// Quality figures.
    pub quality: FixQuality,
    /// Indices into the input slice of the inliers used by the final adjustment.
    pub inliers: Vec<usize>,
    /// Whether the attitude prior was fused into `pose`.
    pub attitude_prior_fused: bool,
    /// With the attitude prior fused: how the fused position depends on the prior's attitude,
    /// `d C_world / d phi_prior` (m/rad, world frame; `phi_prior` the world-frame rotation vector of
    /// the prior's error, `R_prior = Exp(phi_prior) R_true`), and the part of the position
    /// covariance that comes from the image alone (m^2, world). The fused position is, to first
    /// order, `C_true + G phi_prior + e_img` with `Cov(e_img)` this part; a filter that supplied
    /// the prior models `G phi` as a dependence on its own attitude error instead of noise, so its
    /// attitude is not fused a second time through the position (`Cov = e_img + G P G^T`).
    pub prior_dependence: Option<PriorDependence>,
}

/// See [`Fix::prior_dependence`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PriorDependence {
    /// `d C_world / d phi_prior`, m/rad, world frame.
    pub d_position_d_prior_att: Matrix3<f64>,
    /// Position covariance from the image alone, world frame, m^2.
    pub image_position_cov_m2: Matrix3<f64>,
}

/// The fused estimate is `x_f = C (I_img x_img + I_P x_P)` with `C = (I_img + I_P)^-1`,
/// `I_img = (k Q_img)^-1` and `I_P` the prior's information on the attitude block, so
/// `d x_f / d x_P = C I_P` and the image's share of the covariance is `C I_img C`.
fn prior_dependence(
    fused: &PoseCovariance,
    image: &PoseCovariance,
    prior: &AttitudePrior,
) -> Option<PriorDependence> {
    let c = fused.conservative();
    let i_img = image.conservative().try_inverse()?;
    let p_inv = prior.cov_rad2.try_inverse()?;
    let g = c.fixed_view::<3, 3>(3, 0) * p_inv;
    let img = c * i_img * c;
    let cov = img.fixed_view::<3, 3>(3, 3).into_owned();
    let cov = 0.5 * (cov + cov.transpose());
    (g.iter().chain(cov.iter()).all(|v| v.is_finite())).then_some(PriorDependence {
        d_position_d_prior_att: g,
        image_position_cov_m2: cov,
    })
}

/// Outcome of [`resect`]: the fix when one could be computed, and the decision.
#[derive(Debug, Clone, PartialEq)]
pub struct Outcome {
    /// The fix, also when rejected (for diagnostics); None when none could be computed.
    pub fix: Option<Fix>,
    /// Accepted, or the first failing check.
    pub verdict: Verdict,
}

impl Outcome {
    /// The fix, only if it passed every integrity check.
    pub fn accepted(&self) -> Option<&Fix> {
        if self.verdict.is_accepted() {
            self.fix.as_ref()
        } else {
            None
        }
    }
    /// The rejection reason, if rejected.
    pub fn rejection(&self) -> Option<&Rejection> {
        match &self.verdict {
            Verdict::Rejected(r) => Some(r),
            Verdict::Accepted => None,
        }
    }
    fn rejected(r: Rejection) -> Self {
        Outcome {
            fix: None,
            verdict: Verdict::Rejected(r),
        }
    }
}

/// Closest rotation (Frobenius norm) to a 3x3 matrix, by SVD.
pub fn nearest_rotation(m: &Matrix3<f64>) -> Option<Rotation3<f64>> {
    if !m.iter().all(|v| v.is_finite()) {
        return None;
    }
    let svd = m.svd(true, true);
    let (u, v_t) = (svd.u?, svd.v_t?);
    let d = (u * v_t).determinant().signum();
    let r = u * Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, d)) * v_t;
    r.iter()
        .all(|v| v.is_finite())
        .then(|| Rotation3::from_matrix_unchecked(r))
}

fn inv3(m: &Matrix3<f64>) -> Option<Matrix3<f64>> {
    let c = nalgebra::Cholesky::new(*m)?;
    let i = c.inverse();
    i.iter().all(|v| v.is_finite()).then_some(i)
}

/// Largest square-root eigenvalue of a symmetric 2x2 / 3x3 block.
fn max_sigma3(m: &Matrix3<f64>) -> f64 {
    m.symmetric_eigenvalues().max().max(0.0).sqrt()
}

/// Solve the resection; see the module documentation for the pipeline and conventions.
///
/// Never panics and never returns non-finite numbers in an accepted fix: bad input is rejected
/// with a reason ([`Rejection::InvalidInput`], [`Rejection::TooFewCorrespondences`], ...).
pub fn resect(
    corrs: &[Correspondence],
    image: &ImageGeometry,
    priors: &Priors,
    cfg: &ResectionConfig,
) -> Outcome {
    match resect_stages(corrs, image, priors, cfg) {
        Ok(outcome) => outcome,
        Err(r) => Outcome::rejected(r),
    }
}

/// The pipeline of [`resect`] as stages; a stage's rejection ends it.
fn resect_stages(
    corrs: &[Correspondence],
    image: &ImageGeometry,
    priors: &Priors,
    cfg: &ResectionConfig,
) -> Result<Outcome, Rejection> {
    check_inputs(image, priors, cfg)?;
    // 1. Valid correspondences, centred.
    let c = Centred::new(corrs)?;
    let (fx, fy) = (image.fx_px, image.fy_px);
    // 2. RANSAC.
    let rs = ransac_p3p(&c.local, fx, fy, &cfg.ransac)
        .map_err(|iterations| Rejection::NoConsensus { iterations })?;
    // 3. Vision-only LM, inliers re-selected until stable.
    let (vision, inliers, lm_vision) = refine_reselecting(&c.local, &rs, fx, fy, cfg)?;
    let split = if cfg.refine.split_variance {
        split_variance_factor(&c.local, &inliers, &vision, image, &cfg.refine)
    } else {
        None
    };
    let tilt = map_tilt_response(
        &c.local,
        &inliers,
        &vision,
        fx,
        fy,
        priors.map_tilt_sigma_rad,
    );
    let vision_cov = PoseCovariance {
        apriori: vision.cov_apriori,
        added: tilt.as_ref().map_or_else(Matrix6::zeros, MapTilt::cov),
        sigma0_sq: vision.sigma0_sq,
        dof: vision.dof,
        inflation: cfg.refine.sigma_inflation,
        split_factor: split.map_or(1.0, |s| s.factor),
        split_groups: split.map_or(0, |s| s.groups),
        sigma0_floor: cfg.refine.sigma0_floor,
    };
    // 5a. Prior consistency on the vision-only solution (in the centred frame).
    let prior_d2 = prior_consistency(&vision.pose, &vision_cov, priors, &c.origin);
    // 6. Optional fusion of the attitude prior.
    let fusion = fuse_attitude_prior(
        (&c.local, &inliers),
        (&vision, &vision_cov),
        priors,
        tilt.as_ref(),
        image,
        cfg,
    )?;
    let final_r = fusion.as_ref().map_or(&vision, |(r, _)| r);
    // The fused covariance scales with the image's variance factor (see `fuse_attitude_prior`):
    // the prior rows' residuals say nothing about the pixel sigmas. The map's tilt is already in
    // a fused covariance.
    let covariance = PoseCovariance {
        apriori: final_r.cov_apriori,
        dof: final_r.dof,
        added: if fusion.is_some() {
            Matrix6::zeros()
        } else {
            vision_cov.added
        },
        ..vision_cov
    };
    // 5b. Quality figures.
    let quality = quality_figures(QualityInputs {
        local: &c.local,
        inliers: &inliers,
        vision: &vision,
        covariance: &covariance,
        image,
        prior_d2,
        ransac_iterations: rs.iterations,
        lm_iterations: lm_vision + fusion.as_ref().map_or(0, |(r, _)| r.iterations),
    });
    let uncentre = |p: &Pose| Pose {
        r_world_cam: p.r_world_cam,
        c_world: p.c_world + c.origin,
    };
    let fix = Fix {
        pose: uncentre(&final_r.pose),
        covariance,
        vision_pose: uncentre(&vision.pose),
        vision_covariance: vision_cov,
        quality,
        inliers: inliers.iter().map(|&i| c.valid_idx[i]).collect(),
        attitude_prior_fused: fusion.is_some(),
        prior_dependence: fusion
            .as_ref()
            .and_then(|(_, effective)| prior_dependence(&covariance, &vision_cov, effective)),
    };
    Ok(Outcome {
        verdict: verdict_of(&fix, cfg),
        fix: Some(fix),
    })
}

/// The image geometry, the configuration and the priors are usable.
fn check_inputs(
    image: &ImageGeometry,
    priors: &Priors,
    cfg: &ResectionConfig,
) -> Result<(), Rejection> {
    image.check()?;
    let mut problems = Problems::default();
    cfg.validate(&mut problems);
    if let Some(first) = problems.list.first() {
        return Err(Rejection::InvalidInput {
            reason: format!("configuration {first}"),
        });
    }
    for (what, ok) in [
        (
            "attitude prior",
            priors.attitude.is_none_or(|a| {
                a.cov_rad2.iter().all(|v| v.is_finite()) && inv3(&a.cov_rad2).is_some()
            }),
        ),
        (
            "position prior",
            priors.position.is_none_or(|p| {
                p.c_world.iter().all(|v| v.is_finite()) && inv3(&p.cov_m2).is_some()
            }),
        ),
    ] {
        if !ok {
            return Err(Rejection::InvalidInput {
                reason: format!("{what}: non-finite value or covariance not positive definite"),
            });
        }
    }
    Ok(())
}

/// The valid correspondences with their world points centred on their mean (numbers stay well
/// conditioned with map grid coordinates of 10^6 m).
struct Centred {
    /// Index of each into the caller's slice.
    valid_idx: Vec<usize>,
    origin: Vector3<f64>,
    local: Vec<Correspondence>,
}

impl Centred {
    fn new(corrs: &[Correspondence]) -> Result<Self, Rejection> {
        let valid_idx: Vec<usize> = (0..corrs.len()).filter(|&i| corrs[i].is_valid()).collect();
        if valid_idx.len() < 4 {
            return Err(Rejection::TooFewCorrespondences {
                valid: valid_idx.len(),
                required: 4,
            });
        }
        let origin = valid_idx
            .iter()
            .fold(Vector3::zeros(), |a, &i| a + corrs[i].point_world)
            / valid_idx.len() as f64;
        let local = valid_idx
            .iter()
            .map(|&i| Correspondence {
                point_world: corrs[i].point_world - origin,
                ..corrs[i]
            })
            .collect();
        Ok(Self {
            valid_idx,
            origin,
            local,
        })
    }
}

/// Vision-only LM from the RANSAC pose, the inliers re-selected with the refined pose and the
/// adjustment repeated until the set is stable (at most 4 times): the solution, its inliers and
/// the LM iterations spent.
fn refine_reselecting(
    local: &[Correspondence],
    rs: &RansacResult,
    fx: f64,
    fy: f64,
    cfg: &ResectionConfig,
) -> Result<(Refined, Vec<usize>, usize), Rejection> {
    let th2 = cfg.ransac.threshold_px * cfg.ransac.threshold_px;
    let mut inliers = rs.inliers.clone();
    let mut lm_iterations = 0;
    let mut pose = rs.pose;
    let mut refined = None;
    for _ in 0..4 {
        let r =
            refine_pose(local, &inliers, &pose, [fx, fy], None, &cfg.refine).map_err(
                |e| match e {
                    RefineError::Singular => Rejection::IllConditioned {
                        condition: f64::INFINITY,
                        max: cfg.integrity.max_condition_number,
                    },
                    e => Rejection::NumericalFailure {
                        stage: "refinement",
                        detail: e.to_string(),
                    },
                },
            )?;
        lm_iterations += r.iterations;
        pose = r.pose;
        let new_inl: Vec<usize> = (0..local.len())
            .filter(|&i| {
                let c = &local[i];
                pose.project(&c.point_world).is_some_and(|p| {
                    let d = p - c.obs_norm;
                    (fx * d.x).powi(2) + (fy * d.y).powi(2) < th2
                })
            })
            .collect();
        let stable = new_inl == inliers;
        refined = Some(r);
        if stable || new_inl.len() < 4 {
            break;
        }
        inliers = new_inl;
    }
    let vision = refined.ok_or_else(|| Rejection::NumericalFailure {
        stage: "refinement",
        detail: "no iteration".into(),
    })?;
    Ok((vision, inliers, lm_iterations))
}

/// Squared Mahalanobis distances of the vision-only pose from the position and attitude priors
/// (`origin`: the centring of the solution's frame), each against the sum of the conservative
/// covariance and the prior's.
fn prior_consistency(
    vision: &Pose,
    vision_cov: &PoseCovariance,
    priors: &Priors,
    origin: &Vector3<f64>,
) -> (Option<f64>, Option<f64>) {
    let cons = vision_cov.conservative();
    let position = priors.position.map(|p| {
        let d = vision.c_world - (p.c_world - origin);
        let s = cons.fixed_view::<3, 3>(3, 3) + p.cov_m2;
        inv3(&s).map_or(f64::INFINITY, |si| (d.transpose() * si * d)[0])
    });
    let attitude = priors.attitude.map(|a| {
        let phi = log_so3(&(vision.r_world_cam * a.r_world_cam.inverse()));
        let s = cons.fixed_view::<3, 3>(0, 0) + a.cov_rad2;
        inv3(&s).map_or(f64::INFINITY, |si| (phi.transpose() * si * phi)[0])
    });
    (position, attitude)
}

/// Step 6, when configured and an attitude prior is given: the solution with the prior fused, and
/// the prior as the fusion weighed it (for [`prior_dependence`]).
///
/// The image's real covariance is `k Q_img` with `k = PoseCovariance::factor()` (the
/// conservative covariance's factor), so the prior enters the whitened least squares with
/// `P / k`: the fused normal matrix is then `Q_img^-1 + k P^-1` and
/// `k (Q_img^-1 + k P^-1)^-1 = ((k Q_img)^-1 + P^-1)^-1`, the information-weighted combination of
/// the image and the prior. Without the scaling the prior is under-weighted by `k` (16 with the
/// fix pipeline's inflation of 4) and the image's correlated errors leak into the tilt along the
/// position/tilt ambiguity. The prior as weighed is `P k / k_image`.
fn fuse_attitude_prior(
    (local, inliers): (&[Correspondence], &[usize]),
    (vision, vision_cov): (&Refined, &PoseCovariance),
    priors: &Priors,
    tilt: Option<&MapTilt>,
    image: &ImageGeometry,
    cfg: &ResectionConfig,
) -> Result<Option<(Refined, AttitudePrior)>, Rejection> {
    let Some(a) = priors
        .attitude
        .as_ref()
        .filter(|_| cfg.refine.use_attitude_prior)
    else {
        return Ok(None);
    };
    let k_image = if cfg.refine.prior_against_conservative {
        vision_cov.factor()
    } else {
        1.0
    };
    let factor = vision_cov.factor();
    // The image pins the pose against the points; a tilt of the points against the world widens
    // the prior as the image sees it (the map frame) by the tilt's attitude covariance.
    let tilt_att = tilt.map_or_else(Matrix3::zeros, |t| {
        t.cov().fixed_view::<3, 3>(0, 0).into_owned()
    });
    let scaled = AttitudePrior {
        r_world_cam: a.r_world_cam,
        cov_rad2: a.cov_rad2 / k_image + tilt_att / factor,
    };
    let (fx, fy) = (image.fx_px, image.fy_px);
    let mut fused = refine_pose(
        local,
        inliers,
        &vision.pose,
        [fx, fy],
        Some(&scaled),
        &cfg.refine,
    )
    .map_err(|e| Rejection::NumericalFailure {
        stage: "attitude prior fusion",
        detail: e.to_string(),
    })?;
    let effective = AttitudePrior {
        r_world_cam: a.r_world_cam,
        cov_rad2: a.cov_rad2 * (factor / k_image),
    };
    if let Some(t) = tilt {
        world_from_map_frame(&mut fused, vision, vision_cov, &effective, t, factor)?;
    }
    Ok(Some((fused, effective)))
}

/// The fused pose of [`fuse_attitude_prior`], solved against the points (the map frame), moved
/// into the world by the points' most likely tilt, with the world covariance.
///
/// Linear model (conservative units): the image gives the map-frame pose `y ~ N(y_img, Y)`
/// (`Y` the image's conservative covariance without the tilt); the tilt `g ~ N(0, T)` (slope per
/// horizontal axis) makes it differ from the world pose by `y = x + D g` ([`MapTilt`]); the prior
/// observes the world attitude, `a = H x + e`, `e ~ N(0, P)`. With `S = H (Y + D T D^T) H^T + P`
/// and the innovation `v = Log(R_prior R_img^T)`, the tilt's posterior mean is
/// `g = -T D^T H^T S^-1 v`; the map-frame part of the posterior is what the refinement found with
/// the prior widened to `P + H D T D^T H^T`, and `x = y - D g`. The world covariance is the
/// image-only world pose `N(y_img, Y + D T D^T)` fused with the prior:
/// `((Y + D T D^T)^-1 + H^T P^-1 H)^-1`.
fn world_from_map_frame(
    fused: &mut Refined,
    vision: &Refined,
    vision_cov: &PoseCovariance,
    prior: &AttitudePrior,
    tilt: &MapTilt,
    factor: f64,
) -> Result<(), Rejection> {
    let fail = |detail: &str| Rejection::NumericalFailure {
        stage: "map tilt",
        detail: detail.to_string(),
    };
    let y = vision_cov.apriori * factor;
    let image_world = y + tilt.cov();
    let s = image_world.fixed_view::<3, 3>(0, 0) + prior.cov_rad2;
    let s_inv = inv3(&s).ok_or_else(|| fail("singular innovation covariance"))?;
    let v = log_so3(&(prior.r_world_cam * vision.pose.r_world_cam.inverse()));
    let dh = tilt.d.fixed_view::<3, 2>(0, 0).into_owned();
    let g = -(tilt.sigma * tilt.sigma) * dh.transpose() * s_inv * v;
    let dx = -(tilt.d * g);
    let phi = Vector3::new(dx[0], dx[1], dx[2]);
    fused.pose = Pose {
        r_world_cam: Rotation3::new(phi) * fused.pose.r_world_cam,
        c_world: fused.pose.c_world + Vector3::new(dx[3], dx[4], dx[5]),
    };
    let mut info = image_world
        .try_inverse()
        .ok_or_else(|| fail("singular image covariance"))?;
    let p_inv = inv3(&prior.cov_rad2).ok_or_else(|| fail("singular prior covariance"))?;
    info.fixed_view_mut::<3, 3>(0, 0).add_assign(&p_inv);
    let cov = info
        .try_inverse()
        .ok_or_else(|| fail("singular fused information"))?;
    let cov = (cov + cov.transpose()) * 0.5;
    if !cov.iter().chain(phi.iter()).all(|v| v.is_finite()) {
        return Err(fail("non-finite result"));
    }
    fused.cov_apriori = cov / factor;
    Ok(())
}

/// How a tilt of the world points moves the solved pose ([`Priors::map_tilt_sigma_rad`]): the
/// points' heights off by `g . (X - X_mid)` (slope `g` per horizontal axis, `X_mid` the points'
/// centre) move the least-squares pose by `D g`, `D = -(A^T A)^-1 A^T B` with `A` the whitened
/// Jacobian of the inliers' residuals in the pose and `B` in the slope (each point's height
/// Jacobian times its horizontal offset). Over flat ground this is the rigid turn of the frame
/// about the centre (the attitude turns by the slope, the camera moves by it times its height);
/// over relief it is not quite, which the least-squares response includes.
struct MapTilt {
    /// `D`, rows `[phi, C]`, columns the slope along world x and y.
    d: nalgebra::SMatrix<f64, 6, 2>,
    /// The slope's sigma per axis.
    sigma: f64,
}

impl MapTilt {
    /// The pose covariance the tilt adds: `D T D^T`.
    fn cov(&self) -> Matrix6<f64> {
        self.d * self.d.transpose() * (self.sigma * self.sigma)
    }
}

/// [`MapTilt`] of the inliers at the vision-only solution; None without a tilt (or when a value
/// is not finite).
fn map_tilt_response(
    local: &[Correspondence],
    inliers: &[usize],
    vision: &Refined,
    fx: f64,
    fy: f64,
    sigma: f64,
) -> Option<MapTilt> {
    if !(sigma.is_finite() && sigma > 0.0) {
        return None;
    }
    let r_cw = vision.pose.r_world_cam.inverse();
    let r_cw = r_cw.matrix();
    let mut atb = nalgebra::SMatrix::<f64, 6, 2>::zeros();
    for &i in inliers {
        let c = &local[i];
        let (_, a) = refine::residual_and_jacobian(r_cw, &vision.pose.c_world, c, fx, fy)?;
        // d e / d X = -(d e / d C): the point moves against the camera.
        let de_dz = -(a.fixed_view::<2, 3>(0, 3) * Vector3::z());
        let b = de_dz * nalgebra::RowVector2::new(c.point_world.x, c.point_world.y);
        atb += a.transpose() * b;
    }
    let d = -(vision.cov_apriori * atb);
    d.iter()
        .all(|v| v.is_finite())
        .then_some(MapTilt { d, sigma })
}

/// What the quality figures of a fix are computed from.
struct QualityInputs<'a> {
    local: &'a [Correspondence],
    inliers: &'a [usize],
    vision: &'a Refined,
    covariance: &'a PoseCovariance,
    image: &'a ImageGeometry,
    /// Squared distances from the position and attitude priors ([`prior_consistency`]).
    prior_d2: (Option<f64>, Option<f64>),
    ransac_iterations: usize,
    lm_iterations: usize,
}

/// Step 5b: the figures the integrity check judges.
fn quality_figures(q: QualityInputs) -> FixQuality {
    let px: Vec<Vector2<f64>> = q
        .inliers
        .iter()
        .map(|&i| q.image.to_pixel(&q.local[i].obs_norm))
        .collect();
    let (cells, hull, eig) =
        integrity::spread(&px, q.image.width_px as f64, q.image.height_px as f64);
    let pos = q.covariance.position_world_m2();
    let horiz = pos
        .fixed_view::<2, 2>(0, 0)
        .into_owned()
        .symmetric_eigenvalues()
        .max()
        .max(0.0)
        .sqrt();
    let n_valid = q.local.len();
    FixQuality {
        valid_correspondences: n_valid,
        inliers: q.inliers.len(),
        inlier_ratio: q.inliers.len() as f64 / n_valid as f64,
        reprojection_rms_px: q.vision.rms_px,
        sigma0: q.vision.sigma0_sq.sqrt(),
        dof: q.vision.dof,
        grid_cells_3x3: cells,
        hull_area_fraction: hull,
        spread_eig_ratio: eig,
        condition_number: q.vision.condition_number,
        horizontal_sigma_m: horiz,
        vertical_sigma_m: pos[(2, 2)].max(0.0).sqrt(),
        attitude_sigma_rad: max_sigma3(&q.covariance.attitude_world_rad2()),
        prior_position_d2: q.prior_d2.0,
        prior_attitude_d2: q.prior_d2.1,
        ransac_iterations: q.ransac_iterations,
        lm_iterations: q.lm_iterations,
    }
}

/// The integrity verdict; a non-finite pose or covariance is a numerical failure.
fn verdict_of(fix: &Fix, cfg: &ResectionConfig) -> Verdict {
    let finite = fix.pose.c_world.iter().all(|v| v.is_finite())
        && fix.pose.r_world_cam.matrix().iter().all(|v| v.is_finite())
        && fix.covariance.apriori.iter().all(|v| v.is_finite())
        && fix.covariance.sigma0_sq.is_finite();
    if finite {
        check(&fix.quality, &cfg.integrity)
    } else {
        Verdict::Rejected(Rejection::NumericalFailure {
            stage: "result",
            detail: "non-finite pose or covariance".into(),
        })
    }
}

/// Split-sample variance factor of a vision-only solution: the inliers are split into the four
/// quadrants about their median pixel position, the pose is re-solved from each quadrant alone
/// (LM from the full solution, no prior), and each quadrant's pose difference `d_g` to the full
/// solution is compared with its covariance. For disjoint subsets of equally informative data the
/// full solution is the information-weighted mean, so `Cov(d_g) = Cov_g - Cov_full ~ (1 - n_g/n)
/// Cov_g` with `Cov_g = max(f^2, sigma0_g^2) Q_g` (`f` = `refine.sigma0_floor`). The factor is the mean of
/// `d_g^T Cov_g^-1 d_g / (1 - n_g/n)` over the quadrants, divided by 6: about 1 when the pixel
/// errors are independent, larger when neighbouring observations share an error (a displaced map
/// area, changed ground), which the residual scatter `sigma0` cannot see because a shared error is
/// absorbed by the pose. A quadrant with fewer than [`MIN_SPLIT_GROUP_INLIERS`] inliers or a
/// failed solve is skipped; with fewer than two quadrants there is no evidence (`None`). This is
/// a delete-a-group jackknife in spirit (Efron 1982), on spatial blocks as for correlated data
/// (Kunsch 1989).
pub fn split_variance_factor(
    corrs: &[Correspondence],
    inliers: &[usize],
    full: &Refined,
    image: &ImageGeometry,
    cfg: &RefineConfig,
) -> Option<SplitFactor> {
    let n = inliers.len();
    if n < 2 * MIN_SPLIT_GROUP_INLIERS {
        return None;
    }
    let px: Vec<Vector2<f64>> = inliers
        .iter()
        .map(|&i| image.to_pixel(&corrs[i].obs_norm))
        .collect();
    let median = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let mx = median(px.iter().map(|p| p.x).collect());
    let my = median(px.iter().map(|p| p.y).collect());
    let mut groups: [Vec<usize>; 4] = Default::default();
    for (k, p) in px.iter().enumerate() {
        let q = usize::from(p.x >= mx) + 2 * usize::from(p.y >= my);
        groups[q].push(inliers[k]);
    }
    let mut sum = 0.0;
    let mut used = 0usize;
    for g in groups.iter().filter(|g| g.len() >= MIN_SPLIT_GROUP_INLIERS) {
        let Ok(r) = refine_pose(corrs, g, &full.pose, [image.fx_px, image.fy_px], None, cfg) else {
            continue;
        };
        let cov_g = r.cov_apriori * r.sigma0_sq.max(cfg.sigma0_floor * cfg.sigma0_floor);
        let Some(inv) = cov_g.try_inverse() else {
            continue;
        };
        let phi = log_so3(&(r.pose.r_world_cam * full.pose.r_world_cam.inverse()));
        let dc = r.pose.c_world - full.pose.c_world;
        let d = Vector6::new(phi.x, phi.y, phi.z, dc.x, dc.y, dc.z);
        let shrink = 1.0 - g.len() as f64 / n as f64;
        let d2 = (d.transpose() * inv * d)[0] / shrink.max(0.1);
        if d2.is_finite() {
            sum += d2;
            used += 1;
        }
    }
    (used >= 2).then(|| SplitFactor {
        factor: sum / (6.0 * used as f64),
        groups: used,
    })
}

/// Fewest inliers in a quadrant whose own pose enters the split-sample factor: a 6-parameter
/// pose from fewer points has a redundancy of a few residuals, too noisy to compare.
pub const MIN_SPLIT_GROUP_INLIERS: usize = 8;

/// A measured split-sample variance factor ([`split_variance_factor`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SplitFactor {
    /// The factor (about 1 for independent pixel errors).
    pub factor: f64,
    /// The quadrants whose poses measured it (2-4).
    pub groups: usize,
}
