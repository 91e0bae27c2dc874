//! Integrity of a resection fix: quality figures, thresholds and the accept/reject decision.
//!
//! A fix is accepted only when every check passes; otherwise it is rejected with the first failing
//! check, named with its value and its limit. The checks, in order:
//!
//! 1. inlier count and inlier ratio (of the valid correspondences);
//! 2. reprojection RMS over the inliers, in pixels (root mean square of the 2-D pixel error norm);
//! 3. a-posteriori standard deviation of unit weight `sigma0` (residuals larger than the stated pixel
//!    sigmas mean a wrong model or wrong sigmas, so the covariance cannot be trusted);
//! 4. spatial spread of the inliers in the image: `sqrt(lambda_min / lambda_max)` of the inliers'
//!    pixel scatter matrix (near 0 = points on a line, the classic critical configuration), occupied
//!    cells of a 3x3 grid, and the convex-hull area as a fraction of the image;
//! 5. conditioning: the condition number of the Jacobi-scaled normal matrix (unit-free);
//! 6. the size of the covariance: horizontal 1-sigma semi-major axis, vertical 1-sigma, largest
//!    attitude 1-sigma;
//! 7. consistency with the priors: the squared Mahalanobis distance of the vision-only fix from the
//!    prior position (3 dof) and attitude (3 dof) with the summed covariances, against the
//!    chi-square quantile of `prior_gate_probability`.
//!
//! The chi-square quantile is computed from the regularised lower incomplete gamma function
//! (series / continued fraction, Numerical Recipes 3rd ed. section 6.2) by bisection.

use std::fmt;

use nalgebra::{Matrix2, Vector2};
use serde::{Deserialize, Serialize};

use crate::validate::{Problems, Validate};

/// Quality figures of one fix (all computed over the inliers of the final solution).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FixQuality {
    /// Correspondences with finite values and a positive sigma.
    pub valid_correspondences: usize,
    /// Inliers of the final solution.
    pub inliers: usize,
    /// `inliers / valid_correspondences`.
    pub inlier_ratio: f64,
    /// RMS of the 2-D pixel reprojection error over the inliers.
    pub reprojection_rms_px: f64,
    /// A-posteriori standard deviation of unit weight (1 when the pixel sigmas are right).
    pub sigma0: f64,
    /// Redundancy of the adjustment (observations minus 6).
    pub dof: usize,
    /// Occupied cells of a 3x3 grid over the image (0..=9).
    pub grid_cells_3x3: usize,
    /// Convex-hull area of the inliers divided by the image area (0..=1).
    pub hull_area_fraction: f64,
    /// `sqrt(lambda_min / lambda_max)` of the inliers' pixel scatter (0 = collinear, 1 = isotropic).
    pub spread_eig_ratio: f64,
    /// Condition number of the Jacobi-scaled 6x6 normal matrix.
    pub condition_number: f64,
    /// Horizontal position 1-sigma semi-major axis (world x/y plane), metres.
    pub horizontal_sigma_m: f64,
    /// Vertical position 1-sigma (world z), metres.
    pub vertical_sigma_m: f64,
    /// Largest attitude 1-sigma (any axis), radians.
    pub attitude_sigma_rad: f64,
    /// Squared Mahalanobis distance of the vision-only position from the position prior.
    pub prior_position_d2: Option<f64>,
    /// Squared Mahalanobis distance of the vision-only attitude from the attitude prior.
    pub prior_attitude_d2: Option<f64>,
    /// RANSAC hypotheses drawn.
    pub ransac_iterations: usize,
    /// Levenberg-Marquardt iterations (all stages).
    pub lm_iterations: usize,
}

/// Thresholds of the integrity checks (`[pose.integrity]`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct IntegrityConfig {
    /// Minimum number of inliers.
    pub min_inliers: usize,
    /// Minimum inlier ratio.
    pub min_inlier_ratio: f64,
    /// Maximum reprojection RMS over the inliers, pixels.
    pub max_reprojection_rms_px: f64,
    /// Maximum a-posteriori sigma0 (residuals vs stated pixel sigmas).
    pub max_sigma0: f64,
    /// Minimum occupied cells of the 3x3 image grid.
    pub min_grid_cells: usize,
    /// Minimum convex-hull area fraction of the image.
    pub min_hull_area_fraction: f64,
    /// Minimum `sqrt(lambda_min / lambda_max)` of the inlier pixel scatter.
    pub min_spread_eig_ratio: f64,
    /// Maximum condition number of the scaled normal matrix.
    pub max_condition_number: f64,
    /// Maximum horizontal 1-sigma, metres.
    pub max_horizontal_sigma_m: f64,
    /// Maximum vertical 1-sigma, metres.
    pub max_vertical_sigma_m: f64,
    /// Maximum attitude 1-sigma, degrees.
    pub max_attitude_sigma_deg: f64,
    /// Probability of the chi-square gate for the prior consistency checks (e.g. 0.999).
    pub prior_gate_probability: f64,
}

impl Default for IntegrityConfig {
    fn default() -> Self {
        Self {
            min_inliers: 12,
            min_inlier_ratio: 0.08,
            max_reprojection_rms_px: 3.0,
            max_sigma0: 2.5,
            min_grid_cells: 4,
            min_hull_area_fraction: 0.1,
            min_spread_eig_ratio: 0.15,
            max_condition_number: 1e10,
            max_horizontal_sigma_m: 30.0,
            max_vertical_sigma_m: 30.0,
            max_attitude_sigma_deg: 1.0,
            prior_gate_probability: 0.999,
        }
    }
}

impl Validate for IntegrityConfig {
    fn validate(&self, p: &mut Problems) {
        if self.min_inliers < 4 {
            p.push(
                "min_inliers",
                format!(
                    "{} is below 4, the fewest points that fix a pose uniquely",
                    self.min_inliers
                ),
            );
        }
        p.range("min_inlier_ratio", self.min_inlier_ratio, 0.0, 1.0);
        p.positive("max_reprojection_rms_px", self.max_reprojection_rms_px);
        p.positive("max_sigma0", self.max_sigma0);
        if self.min_grid_cells > 9 {
            p.push(
                "min_grid_cells",
                format!(
                    "{} is more than the 9 cells of a 3x3 grid",
                    self.min_grid_cells
                ),
            );
        }
        p.range(
            "min_hull_area_fraction",
            self.min_hull_area_fraction,
            0.0,
            1.0,
        );
        p.range("min_spread_eig_ratio", self.min_spread_eig_ratio, 0.0, 1.0);
        p.positive("max_condition_number", self.max_condition_number);
        p.positive("max_horizontal_sigma_m", self.max_horizontal_sigma_m);
        p.positive("max_vertical_sigma_m", self.max_vertical_sigma_m);
        p.positive("max_attitude_sigma_deg", self.max_attitude_sigma_deg);
        if !(self.prior_gate_probability > 0.5 && self.prior_gate_probability < 1.0) {
            p.push(
                "prior_gate_probability",
                format!("{} must be in (0.5, 1)", self.prior_gate_probability),
            );
        }
    }
}

/// Why a fix was not produced or not accepted. The message names the check and its values.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum Rejection {
    /// The input or the configuration is unusable (non-finite, out of range); `reason` says which.
    #[error("invalid input: {reason}")]
    InvalidInput {
        /// What is wrong, naming the value.
        reason: String,
    },
    /// Fewer valid correspondences than a pose needs.
    #[error("too few valid correspondences: {valid} (need at least {required})")]
    TooFewCorrespondences {
        /// Correspondences with finite values and a positive sigma.
        valid: usize,
        /// The fewest the solver accepts (4).
        required: usize,
    },
    /// RANSAC found no hypothesis with enough support.
    #[error("no consensus: RANSAC found no pose with enough support in {iterations} iterations")]
    NoConsensus {
        /// Hypotheses drawn.
        iterations: usize,
    },
    /// A numerical step (refinement, covariance inversion) failed.
    #[error("numerical failure in {stage}: {detail}")]
    NumericalFailure {
        /// The pipeline stage that failed.
        stage: &'static str,
        /// What went wrong there.
        detail: String,
    },
    /// Inlier count check: fewer inliers than `IntegrityConfig::min_inliers`.
    #[error("inlier count check failed: {inliers} inliers < minimum {min}")]
    TooFewInliers {
        /// Inliers of the solution.
        inliers: usize,
        /// The configured minimum.
        min: usize,
    },
    /// Inlier ratio check: inliers over valid correspondences below the minimum.
    #[error("inlier ratio check failed: {ratio:.3} < minimum {min:.3}")]
    LowInlierRatio {
        /// Inliers / valid correspondences.
        ratio: f64,
        /// The configured minimum.
        min: f64,
    },
    /// Reprojection check: the inliers' RMS pixel error above the maximum.
    #[error("reprojection check failed: RMS {rms_px:.2} px > maximum {max_px:.2} px")]
    ReprojectionRms {
        /// RMS of the 2-D reprojection error over the inliers, pixels.
        rms_px: f64,
        /// The configured maximum, pixels.
        max_px: f64,
    },
    /// Variance factor check: residuals larger than the stated pixel sigmas.
    #[error(
        "variance factor check failed: sigma0 {sigma0:.2} > maximum {max:.2} (residuals exceed the stated pixel sigmas)"
    )]
    Sigma0 {
        /// A-posteriori standard deviation of unit weight.
        sigma0: f64,
        /// The configured maximum.
        max: f64,
    },
    /// Spread check: the inliers occupy too few cells of the 3x3 image grid.
    #[error("spread check failed: inliers occupy {cells} of 9 grid cells < minimum {min}")]
    GridCoverage {
        /// Occupied cells (0..=9).
        cells: usize,
        /// The configured minimum.
        min: usize,
    },
    /// Spread check: the inliers' convex hull covers too little of the image.
    #[error(
        "spread check failed: inlier convex hull covers {fraction:.3} of the image < minimum {min:.3}"
    )]
    HullArea {
        /// Hull area / image area.
        fraction: f64,
        /// The configured minimum.
        min: f64,
    },
    /// Spread check: the inliers lie nearly on a line (a critical configuration).
    #[error(
        "spread check failed: inliers nearly collinear (eigenvalue ratio {ratio:.3} < minimum {min:.3})"
    )]
    Collinear {
        /// `sqrt(lambda_min / lambda_max)` of the inliers' pixel scatter.
        ratio: f64,
        /// The configured minimum.
        min: f64,
    },
    /// Conditioning check: the Jacobi-scaled normal matrix is near singular.
    #[error("conditioning check failed: condition number {condition:.3e} > maximum {max:.3e}")]
    IllConditioned {
        /// Its condition number.
        condition: f64,
        /// The configured maximum.
        max: f64,
    },
    /// Horizontal position 1-sigma (semi-major axis) above the maximum.
    #[error(
        "position sigma check failed: horizontal 1-sigma {sigma_m:.1} m > maximum {max_m:.1} m"
    )]
    HorizontalSigma {
        /// The fix's horizontal 1-sigma, metres.
        sigma_m: f64,
        /// The configured maximum, metres.
        max_m: f64,
    },
    /// Vertical position 1-sigma above the maximum.
    #[error("position sigma check failed: vertical 1-sigma {sigma_m:.1} m > maximum {max_m:.1} m")]
    VerticalSigma {
        /// The fix's vertical 1-sigma, metres.
        sigma_m: f64,
        /// The configured maximum, metres.
        max_m: f64,
    },
    /// Largest attitude 1-sigma above the maximum.
    #[error("attitude sigma check failed: 1-sigma {sigma_deg:.3} deg > maximum {max_deg:.3} deg")]
    AttitudeSigma {
        /// The fix's largest attitude 1-sigma, degrees.
        sigma_deg: f64,
        /// The configured maximum, degrees.
        max_deg: f64,
    },
    /// The vision-only position disagrees with the position prior beyond the chi-square gate.
    #[error(
        "prior consistency check failed: position Mahalanobis d^2 {d2:.1} > chi-square({dof}) gate {gate:.1} (p = {probability})"
    )]
    PriorPositionInconsistent {
        /// Squared Mahalanobis distance with the summed covariances.
        d2: f64,
        /// Chi-square quantile of `probability` for `dof`.
        gate: f64,
        /// Degrees of freedom (3).
        dof: usize,
        /// The gate's probability (`IntegrityConfig::prior_gate_probability`).
        probability: f64,
    },
    /// The vision-only attitude disagrees with the attitude prior beyond the chi-square gate.
    #[error(
        "prior consistency check failed: attitude Mahalanobis d^2 {d2:.1} > chi-square({dof}) gate {gate:.1} (p = {probability})"
    )]
    PriorAttitudeInconsistent {
        /// Squared Mahalanobis distance with the summed covariances.
        d2: f64,
        /// Chi-square quantile of `probability` for `dof`.
        gate: f64,
        /// Degrees of freedom (3).
        dof: usize,
        /// The gate's probability (`IntegrityConfig::prior_gate_probability`).
        probability: f64,
    },
}

impl Rejection {
    /// The check's class for counting and metric labels (`fix::rejection::CLASSES` lists them):
    /// its name without its numbers.
    pub fn class(&self) -> &'static str {
        use Rejection::*;
        match self {
            InvalidInput { .. } => "pose_invalid_input",
            TooFewCorrespondences { .. } => "pose_few_correspondences",
            NoConsensus { .. } => "pose_no_consensus",
            NumericalFailure { .. } => "pose_numerical",
            TooFewInliers { .. } => "pose_few_inliers",
            LowInlierRatio { .. } => "pose_inlier_ratio",
            ReprojectionRms { .. } => "pose_reprojection",
            Sigma0 { .. } => "pose_variance_factor",
            GridCoverage { .. } | HullArea { .. } | Collinear { .. } => "pose_spread",
            IllConditioned { .. } => "pose_conditioning",
            HorizontalSigma { .. } => "pose_horizontal_sigma",
            VerticalSigma { .. } => "pose_vertical_sigma",
            AttitudeSigma { .. } => "pose_attitude_sigma",
            PriorPositionInconsistent { .. } => "pose_prior_position",
            PriorAttitudeInconsistent { .. } => "pose_prior_attitude",
        }
    }
}

/// The decision on a fix.
#[derive(Debug, Clone, PartialEq)]
pub enum Verdict {
    /// Every check passed.
    Accepted,
    /// The first check that failed, or why no fix could be computed.
    Rejected(Rejection),
}

impl Verdict {
    /// True when accepted.
    pub fn is_accepted(&self) -> bool {
        matches!(self, Verdict::Accepted)
    }
}

impl fmt::Display for Verdict {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Verdict::Accepted => write!(f, "accepted"),
            Verdict::Rejected(r) => write!(f, "rejected: {r}"),
        }
    }
}

/// Apply every check of `cfg` to `q`. Non-finite figures fail their check.
pub fn check(q: &FixQuality, cfg: &IntegrityConfig) -> Verdict {
    match first_failure(q, cfg) {
        None => Verdict::Accepted,
        Some(r) => Verdict::Rejected(r),
    }
}

// `!(x <= max)` is deliberate throughout: a NaN figure fails.
#[allow(clippy::neg_cmp_op_on_partial_ord)]
fn first_failure(q: &FixQuality, cfg: &IntegrityConfig) -> Option<Rejection> {
    use Rejection::*;
    if q.inliers < cfg.min_inliers {
        return Some(TooFewInliers {
            inliers: q.inliers,
            min: cfg.min_inliers,
        });
    }
    if !(q.inlier_ratio >= cfg.min_inlier_ratio) {
        return Some(LowInlierRatio {
            ratio: q.inlier_ratio,
            min: cfg.min_inlier_ratio,
        });
    }
    if !(q.reprojection_rms_px <= cfg.max_reprojection_rms_px) {
        return Some(ReprojectionRms {
            rms_px: q.reprojection_rms_px,
            max_px: cfg.max_reprojection_rms_px,
        });
    }
    if !(q.sigma0 <= cfg.max_sigma0) {
        return Some(Sigma0 {
            sigma0: q.sigma0,
            max: cfg.max_sigma0,
        });
    }
    if !(q.spread_eig_ratio >= cfg.min_spread_eig_ratio) {
        return Some(Collinear {
            ratio: q.spread_eig_ratio,
            min: cfg.min_spread_eig_ratio,
        });
    }
    if q.grid_cells_3x3 < cfg.min_grid_cells {
        return Some(GridCoverage {
            cells: q.grid_cells_3x3,
            min: cfg.min_grid_cells,
        });
    }
    if !(q.hull_area_fraction >= cfg.min_hull_area_fraction) {
        return Some(HullArea {
            fraction: q.hull_area_fraction,
            min: cfg.min_hull_area_fraction,
        });
    }
    if !(q.condition_number <= cfg.max_condition_number) {
        return Some(IllConditioned {
            condition: q.condition_number,
            max: cfg.max_condition_number,
        });
    }
    if !(q.horizontal_sigma_m <= cfg.max_horizontal_sigma_m) {
        return Some(HorizontalSigma {
            sigma_m: q.horizontal_sigma_m,
            max_m: cfg.max_horizontal_sigma_m,
        });
    }
    if !(q.vertical_sigma_m <= cfg.max_vertical_sigma_m) {
        return Some(VerticalSigma {
            sigma_m: q.vertical_sigma_m,
            max_m: cfg.max_vertical_sigma_m,
        });
    }
    let att_deg = q.attitude_sigma_rad.to_degrees();
    if !(att_deg <= cfg.max_attitude_sigma_deg) {
        return Some(AttitudeSigma {
            sigma_deg: att_deg,
            max_deg: cfg.max_attitude_sigma_deg,
        });
    }
    let p = cfg.prior_gate_probability;
    let gate = chi2_quantile(p, 3);
    if let Some(d2) = q.prior_position_d2
        && !(d2 <= gate)
    {
        return Some(PriorPositionInconsistent {
            d2,
            gate,
            dof: 3,
            probability: p,
        });
    }
    if let Some(d2) = q.prior_attitude_d2
        && !(d2 <= gate)
    {
        return Some(PriorAttitudeInconsistent {
            d2,
            gate,
            dof: 3,
            probability: p,
        });
    }
    None
}

/// Spread figures of pixel positions in a `width_px` x `height_px` image:
/// (occupied 3x3 grid cells, convex-hull area fraction, sqrt eigenvalue ratio of the scatter).
pub fn spread(points_px: &[Vector2<f64>], width_px: f64, height_px: f64) -> (usize, f64, f64) {
    let pts: Vec<Vector2<f64>> = points_px
        .iter()
        .copied()
        .filter(|p| p.x.is_finite() && p.y.is_finite())
        .collect();
    if pts.is_empty() || !(width_px > 0.0 && height_px > 0.0) {
        return (0, 0.0, 0.0);
    }
    let mut cells = [false; 9];
    for p in &pts {
        let cx = ((p.x + 0.5) / width_px * 3.0).floor().clamp(0.0, 2.0) as usize;
        let cy = ((p.y + 0.5) / height_px * 3.0).floor().clamp(0.0, 2.0) as usize;
        cells[cy * 3 + cx] = true;
    }
    let n_cells = cells.iter().filter(|c| **c).count();
    let hull = convex_hull_area(&pts) / (width_px * height_px);
    let mean = pts.iter().fold(Vector2::zeros(), |a, p| a + p) / pts.len() as f64;
    let scatter = pts.iter().fold(Matrix2::zeros(), |a, p| {
        let d = p - mean;
        a + d * d.transpose()
    });
    let eig = scatter.symmetric_eigenvalues();
    let (lo, hi) = (eig.min().max(0.0), eig.max());
    let ratio = if hi > 0.0 { (lo / hi).sqrt() } else { 0.0 };
    (
        n_cells,
        hull.clamp(0.0, 1.0),
        if ratio.is_finite() { ratio } else { 0.0 },
    )
}

/// Area of the convex hull (Andrew's monotone chain).
pub fn convex_hull_area(points: &[Vector2<f64>]) -> f64 {
    let mut p: Vec<Vector2<f64>> = points.to_vec();
    if p.len() < 3 {
        return 0.0;
    }
    p.sort_by(|a, b| a.x.total_cmp(&b.x).then(a.y.total_cmp(&b.y)));
    let cross = |o: &Vector2<f64>, a: &Vector2<f64>, b: &Vector2<f64>| {
        (a.x - o.x) * (b.y - o.y) - (a.y - o.y) * (b.x - o.x)
    };
    let mut hull: Vec<Vector2<f64>> = Vec::with_capacity(2 * p.len());
    for pass in 0..2 {
        let start = hull.len();
        for q in p.iter() {
            while hull.len() >= start + 2
                && cross(&hull[hull.len() - 2], &hull[hull.len() - 1], q) <= 0.0
            {
                hull.pop();
            }
            hull.push(*q);
        }
        hull.pop();
        if pass == 0 {
            p.reverse();
        }
    }
    let n = hull.len();
    let mut area2 = 0.0;
    for i in 0..n {
        let (a, b) = (hull[i], hull[(i + 1) % n]);
        area2 += a.x * b.y - b.x * a.y;
    }
    (0.5 * area2).abs()
}

/// Chi-square quantile for `dof` degrees of freedom at probability `p` (NaN for invalid input);
/// see [`crate::stats::chi2_quantile`].
pub fn chi2_quantile(p: f64, dof: usize) -> f64 {
    crate::stats::chi2_quantile(dof as f64, p)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn chi2_reference_values() {
        // Reference quantiles (standard tables).
        let cases = [
            (0.95, 1, 3.841_459),
            (0.95, 2, 5.991_465),
            (0.95, 3, 7.814_728),
            (0.999, 3, 16.266_24),
            (0.99, 6, 16.811_89),
            (0.5, 3, 2.365_974),
        ];
        for (p, k, x) in cases {
            let q = chi2_quantile(p, k);
            assert!((q - x).abs() < 1e-4, "chi2({k}) at {p}: {q} vs {x}");
        }
        assert!(chi2_quantile(f64::NAN, 3).is_nan());
    }

    #[test]
    fn hull_and_spread() {
        let sq = [
            Vector2::new(0.0, 0.0),
            Vector2::new(10.0, 0.0),
            Vector2::new(10.0, 10.0),
            Vector2::new(0.0, 10.0),
            Vector2::new(5.0, 5.0),
        ];
        assert!((convex_hull_area(&sq) - 100.0).abs() < 1e-12);
        let line: Vec<_> = (0..20)
            .map(|i| Vector2::new(i as f64 * 30.0, 240.0))
            .collect();
        let (cells, hull, eig) = spread(&line, 640.0, 480.0);
        assert_eq!(cells, 3);
        assert!(hull < 1e-12);
        assert!(eig < 1e-9);
        let grid: Vec<_> = (0..100)
            .map(|i| Vector2::new((i % 10) as f64 * 70.0, (i / 10) as f64 * 53.0))
            .collect();
        let (cells, hull, eig) = spread(&grid, 640.0, 480.0);
        assert_eq!(cells, 9);
        assert!(hull > 0.9, "{hull}");
        assert!(eig > 0.7, "{eig}");
    }

    fn good() -> FixQuality {
        FixQuality {
            valid_correspondences: 100,
            inliers: 60,
            inlier_ratio: 0.6,
            reprojection_rms_px: 1.4,
            sigma0: 1.0,
            dof: 114,
            grid_cells_3x3: 9,
            hull_area_fraction: 0.8,
            spread_eig_ratio: 0.7,
            condition_number: 1e4,
            horizontal_sigma_m: 3.0,
            vertical_sigma_m: 2.0,
            attitude_sigma_rad: 1e-3,
            prior_position_d2: Some(2.0),
            prior_attitude_d2: Some(2.0),
            ransac_iterations: 50,
            lm_iterations: 5,
        }
    }

    #[test]
    fn each_check_rejects_with_its_reason() {
        let cfg = IntegrityConfig::default();
        assert_eq!(check(&good(), &cfg), Verdict::Accepted);
        type Case = (Box<dyn Fn(&mut FixQuality)>, &'static str);
        let cases: Vec<Case> = vec![
            (Box::new(|q| q.inliers = 5), "inlier count"),
            (Box::new(|q| q.inlier_ratio = 0.01), "inlier ratio"),
            (
                Box::new(|q| q.reprojection_rms_px = f64::NAN),
                "reprojection",
            ),
            (Box::new(|q| q.sigma0 = 9.0), "sigma0"),
            (Box::new(|q| q.spread_eig_ratio = 0.01), "collinear"),
            (Box::new(|q| q.grid_cells_3x3 = 1), "grid cells"),
            (Box::new(|q| q.hull_area_fraction = 0.01), "convex hull"),
            (
                Box::new(|q| q.condition_number = f64::INFINITY),
                "condition number",
            ),
            (Box::new(|q| q.horizontal_sigma_m = 100.0), "horizontal"),
            (Box::new(|q| q.vertical_sigma_m = 100.0), "vertical"),
            (Box::new(|q| q.attitude_sigma_rad = 0.1), "attitude sigma"),
            (
                Box::new(|q| q.prior_position_d2 = Some(40.0)),
                "position Mahalanobis",
            ),
            (
                Box::new(|q| q.prior_attitude_d2 = Some(f64::NAN)),
                "attitude Mahalanobis",
            ),
        ];
        for (modify, needle) in cases {
            let mut q = good();
            modify(&mut q);
            match check(&q, &cfg) {
                Verdict::Rejected(r) => {
                    let msg = r.to_string();
                    assert!(msg.contains(needle), "{msg:?} should mention {needle:?}");
                }
                Verdict::Accepted => panic!("{needle}: accepted"),
            }
        }
    }

    #[test]
    fn config_validation_and_unknown_keys() {
        let mut p = Problems::default();
        IntegrityConfig::default().validate(&mut p);
        assert!(p.list.is_empty(), "{:?}", p.list);
        let bad = IntegrityConfig {
            min_inlier_ratio: 1.5,
            prior_gate_probability: 1.0,
            min_inliers: 2,
            ..Default::default()
        };
        let mut p = Problems::default();
        bad.validate(&mut p);
        let keys: Vec<_> = p.list.iter().map(|i| i.key.as_str()).collect();
        assert_eq!(
            keys,
            ["min_inliers", "min_inlier_ratio", "prior_gate_probability"]
        );
        let e = toml::from_str::<IntegrityConfig>("min_inlier = 3")
            .unwrap_err()
            .to_string();
        assert!(e.contains("min_inlier"), "{e}");
        let c: IntegrityConfig = toml::from_str("min_inliers = 20").unwrap();
        assert_eq!(c.min_inliers, 20);
    }
}
