//! Robust initial pose: LO-RANSAC over the Lambda Twist P3P solver with SPRT model verification.
//!
//! * Hypotheses: three distinct correspondences drawn uniformly (seeded xoshiro256++, so results
//!   are reproducible), up to four P3P poses each ([`super::p3p`]).
//! * Scoring: MSAC (P. Torr and A. Zisserman, "MLESAC", CVIU 2000): cost `sum min(e^2, th^2)` of the
//!   2-D pixel reprojection error `e`; a point behind the camera (cheirality) costs `th^2` and is
//!   never an inlier.
//! * Verification: Wald's sequential probability ratio test (O. Chum and J. Matas, "Optimal
//!   Randomized RANSAC", PAMI 2008): points are checked in random order and a hypothesis is dropped
//!   as soon as the likelihood ratio of "bad model" over "good model" exceeds `A`, so a wrong pose
//!   costs a few dozen projections instead of `n`. `epsilon` is the inlier ratio of the best model so
//!   far (at least 0.05), `delta` the running mean of the inlier fraction seen by rejected models, and
//!   `A` solves `A = t_M C / m_S + 1 + ln A` (`t_M` = 200 point checks per P3P, `m_S` = 2 models
//!   per sample).
//! * Local optimisation (O. Chum, J. Matas, J. Kittler, "Locally optimized RANSAC", DAGM 2003): each
//!   new best hypothesis is refined by a few Levenberg-Marquardt iterations on its inliers and
//!   re-scored, repeated while the cost decreases.
//! * Adaptive stopping: `k = ln(1 - confidence) / ln(1 - epsilon^3 (1 - 1/A))`, clamped to
//!   `[min_iterations, max_iterations]`.

use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

use super::p3p::p3p_lambda_twist;
use super::refine::{RefineConfig, RobustLoss, refine_pose};
use super::{Correspondence, Pose, nearest_rotation};
use crate::rng::Rng;
use crate::validate::{Problems, Validate};

/// RANSAC settings (`[pose.ransac]`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RansacConfig {
    /// Inlier threshold on the 2-D pixel reprojection error.
    pub threshold_px: f64,
    /// Probability of drawing at least one all-inlier sample before stopping.
    pub confidence: f64,
    /// Hard cap on the number of samples.
    pub max_iterations: usize,
    /// Minimum number of samples.
    pub min_iterations: usize,
    /// Seed of the sampler (same input + same seed = same result).
    pub seed: u64,
    /// Local optimisation of each new best model.
    pub local_optimisation: bool,
    /// Sequential probability ratio test for early rejection of bad models.
    pub sprt: bool,
}

impl Default for RansacConfig {
    fn default() -> Self {
        Self {
            threshold_px: 3.0,
            confidence: 0.999,
            max_iterations: 20_000,
            min_iterations: 20,
            seed: 0x5EED,
            local_optimisation: true,
            sprt: true,
        }
    }
}

impl Validate for RansacConfig {
    fn validate(&self, p: &mut Problems) {
        p.range("threshold_px", self.threshold_px, 0.1, 100.0);
        if !(self.confidence > 0.5 && self.confidence < 1.0) {
            p.push(
                "confidence",
                format!("{} must be in (0.5, 1)", self.confidence),
            );
        }
        if !(1..=10_000_000).contains(&self.max_iterations) {
            p.push(
                "max_iterations",
                format!("{} is outside 1..=10000000", self.max_iterations),
            );
        }
        if self.min_iterations > self.max_iterations {
            p.push(
                "min_iterations",
                format!(
                    "{} exceeds max_iterations {}",
                    self.min_iterations, self.max_iterations
                ),
            );
        }
    }
}

/// Result of [`ransac_p3p`].
#[derive(Debug, Clone, PartialEq)]
pub struct RansacResult {
    /// Best pose (after local optimisation).
    pub pose: Pose,
    /// Indices (into the input slice) of its inliers.
    pub inliers: Vec<usize>,
    /// Samples drawn.
    pub iterations: usize,
    /// Hypotheses verified (P3P gives 0..4 per sample).
    pub models: usize,
    /// Local optimisations run.
    pub lo_runs: usize,
}

struct Model {
    r: Matrix3<f64>,
    t: Vector3<f64>,
}

impl Model {
    fn from_pose(p: &Pose) -> Self {
        let r = *p.r_world_cam.inverse().matrix();
        Model {
            t: -(r * p.c_world),
            r,
        }
    }
    #[inline]
    fn err2(&self, c: &Correspondence, fx: f64, fy: f64) -> f64 {
        let p = self.r * c.point_world + self.t;
        if p.z.is_nan() || p.z <= 0.0 {
            return f64::INFINITY;
        }
        let iz = 1.0 / p.z;
        let dx = fx * (p.x * iz - c.obs_norm.x);
        let dy = fy * (p.y * iz - c.obs_norm.y);
        dx * dx + dy * dy
    }
}

struct Sprt {
    epsilon: f64,
    a: f64,
    /// Likelihood-ratio factor for a consistent / inconsistent point.
    up_in: f64,
    up_out: f64,
}

impl Sprt {
    fn new(epsilon: f64, delta: f64) -> Self {
        let eps = epsilon.clamp(0.05, 0.99);
        let delta = delta.clamp(1e-4, 0.5 * eps);
        let c = (1.0 - delta) * ((1.0 - delta) / (1.0 - eps)).ln() + delta * (delta / eps).ln();
        let k = 200.0 * c / 2.0;
        let mut a = k + 1.0;
        for _ in 0..20 {
            a = k + 1.0 + a.ln();
        }
        let a = a.max(1.5);
        Sprt {
            epsilon: eps,
            a,
            up_in: delta / eps,
            up_out: (1.0 - delta) / (1.0 - eps),
        }
    }
}

/// Scores of a model over the valid correspondences: each costs its squared pixel error, capped
/// at the threshold's square (MSAC).
struct Scorer<'a> {
    corrs: &'a [Correspondence],
    valid: Vec<usize>,
    fx_px: f64,
    fy_px: f64,
    th2: f64,
}

impl Scorer<'_> {
    /// `(cost, inliers)` over every valid correspondence.
    fn full(&self, m: &Model) -> (f64, usize) {
        let (mut cost, mut inl) = (0.0, 0);
        for &i in &self.valid {
            let e2 = m.err2(&self.corrs[i], self.fx_px, self.fy_px);
            if e2 < self.th2 {
                cost += e2;
                inl += 1;
            } else {
                cost += self.th2;
            }
        }
        (cost, inl)
    }

    fn inliers_of(&self, m: &Model) -> Vec<usize> {
        self.valid
            .iter()
            .copied()
            .filter(|&i| m.err2(&self.corrs[i], self.fx_px, self.fy_px) < self.th2)
            .collect()
    }

    /// Sequential verification (Wald's SPRT, Chum & Matas 2008) in `order` from `start`:
    /// `None` when the likelihood ratio rejects the model (its inlier fraction so far updates
    /// the test's `delta`), else `(cost, inliers)`.
    fn sprt(
        &self,
        m: &Model,
        order: &[usize],
        start: usize,
        t: &mut SprtState,
    ) -> Option<(f64, usize)> {
        let n = order.len();
        let (mut lambda, mut cost, mut inl) = (1.0, 0.0, 0usize);
        for k in 0..n {
            let i = order[(start + k) % n];
            let e2 = m.err2(&self.corrs[i], self.fx_px, self.fy_px);
            if e2 < self.th2 {
                cost += e2;
                inl += 1;
                lambda *= t.test.up_in;
            } else {
                cost += self.th2;
                lambda *= t.test.up_out;
            }
            if lambda > t.test.a {
                t.rejected(inl as f64 / (k + 1) as f64);
                return None;
            }
        }
        Some((cost, inl))
    }
}

/// The SPRT and its running estimate of a bad model's inlier fraction `delta`.
struct SprtState {
    test: Sprt,
    delta_sum: f64,
    delta_cnt: usize,
}

impl SprtState {
    fn rejected(&mut self, fraction: f64) {
        self.delta_sum += fraction;
        self.delta_cnt += 1;
        if self.delta_cnt.is_multiple_of(16) {
            self.test = Sprt::new(self.test.epsilon, self.delta());
        }
    }

    fn delta(&self) -> f64 {
        if self.delta_cnt > 0 {
            self.delta_sum / self.delta_cnt as f64
        } else {
            0.01
        }
    }
}

/// The local optimisation's adjustment: a few robust LM steps, no prior.
const LO_REFINE: RefineConfig = RefineConfig {
    max_iterations: 8,
    loss: RobustLoss::Huber { k_sigma: 2.0 },
    use_attitude_prior: false,
    sigma_inflation: 1.0,
    sigma0_floor: 1.0,
    split_variance: false,
    prior_against_conservative: true,
};

/// Three distinct valid correspondences drawn at random.
fn draw_sample(rng: &mut Rng, valid: &[usize]) -> [usize; 3] {
    let n = valid.len();
    let i0 = valid[rng.below(n)];
    let mut i1 = valid[rng.below(n)];
    while i1 == i0 {
        i1 = valid[rng.below(n)];
    }
    let mut i2 = valid[rng.below(n)];
    while i2 == i0 || i2 == i1 {
        i2 = valid[rng.below(n)];
    }
    [i0, i1, i2]
}

/// LO-RANSAC (Chum, Matas & Kittler 2003): the new best model re-estimated by LM over its
/// inliers while that lowers the cost (at most 4 times); `lo_runs` counts the adjustments.
fn local_optimise(
    s: &Scorer,
    mut cur: (Model, f64, usize),
    lo_runs: &mut usize,
) -> (Model, f64, usize) {
    for _ in 0..4 {
        let inl_idx = s.inliers_of(&cur.0);
        if inl_idx.len() < 6 {
            break;
        }
        let Some(start_pose) = model_to_pose(&cur.0) else {
            break;
        };
        *lo_runs += 1;
        let Ok(r) = refine_pose(
            s.corrs,
            &inl_idx,
            &start_pose,
            [s.fx_px, s.fy_px],
            None,
            &LO_REFINE,
        ) else {
            break;
        };
        let m2 = Model::from_pose(&r.pose);
        let (c2, n2) = s.full(&m2);
        if c2 < cur.1 {
            cur = (m2, c2, n2);
        } else {
            break;
        }
    }
    cur
}

/// Samples needed for `confidence` when a sample is all-inlier with probability `eps^3`
/// (times the SPRT's acceptance of a good model, `1 - alpha`).
fn samples_needed(eps: f64, alpha: f64, cfg: &RansacConfig) -> usize {
    let p_good = eps.powi(3) * if cfg.sprt { 1.0 - alpha } else { 1.0 };
    if p_good >= 1.0 {
        cfg.min_iterations
    } else if p_good <= 1e-12 {
        cfg.max_iterations
    } else {
        let k = (1.0 - cfg.confidence).ln() / (-p_good).ln_1p();
        if k.is_finite() {
            k.ceil().min(cfg.max_iterations as f64) as usize
        } else {
            cfg.max_iterations
        }
    }
}

/// Robust P3P pose. Correspondences with non-finite values or a non-positive sigma are never
/// sampled nor counted. Returns `Err(iterations)` when no hypothesis had at least four inliers.
pub fn ransac_p3p(
    corrs: &[Correspondence],
    fx_px: f64,
    fy_px: f64,
    cfg: &RansacConfig,
) -> Result<RansacResult, usize> {
    let valid: Vec<usize> = (0..corrs.len()).filter(|&i| corrs[i].is_valid()).collect();
    let n = valid.len();
    if n < 4 || !(fx_px > 0.0 && fy_px > 0.0) {
        return Err(0);
    }
    let mut rng = Rng::new(cfg.seed);
    // Random verification order (Fisher-Yates), entered at a random offset for each model.
    let mut order = valid.clone();
    for i in (1..n).rev() {
        order.swap(i, rng.below(i + 1));
    }
    let bearings: Vec<Vector3<f64>> = corrs
        .iter()
        .map(|c| Vector3::new(c.obs_norm.x, c.obs_norm.y, 1.0).normalize())
        .collect();
    let s = Scorer {
        corrs,
        valid,
        fx_px,
        fy_px,
        th2: cfg.threshold_px * cfg.threshold_px,
    };
    let mut best: Option<(Model, f64, usize)> = None;
    let mut sprt = SprtState {
        test: Sprt::new(0.05, 0.01),
        delta_sum: 0.0,
        delta_cnt: 0,
    };
    let mut needed = cfg.max_iterations;
    let (mut iterations, mut models, mut lo_runs) = (0, 0, 0);
    while iterations < needed.max(cfg.min_iterations).min(cfg.max_iterations) {
        iterations += 1;
        let [i0, i1, i2] = draw_sample(&mut rng, &s.valid);
        let y = [bearings[i0], bearings[i1], bearings[i2]];
        let x = [
            corrs[i0].point_world,
            corrs[i1].point_world,
            corrs[i2].point_world,
        ];
        for sol in p3p_lambda_twist(&y, &x).as_slice() {
            models += 1;
            let m = Model {
                r: sol.r_cam_world,
                t: sol.t_cam,
            };
            let scored = if cfg.sprt {
                let start = rng.below(n);
                s.sprt(&m, &order, start, &mut sprt)
            } else {
                Some(s.full(&m))
            };
            let Some((cost, inl)) = scored else {
                continue;
            };
            if inl < 4 || best.as_ref().is_some_and(|b| cost >= b.1) {
                continue;
            }
            // New best: local optimisation, then the test and the sample count follow it.
            let mut cur = (m, cost, inl);
            if cfg.local_optimisation {
                cur = local_optimise(&s, cur, &mut lo_runs);
            }
            let eps = cur.2 as f64 / n as f64;
            let alpha = 1.0 / sprt.test.a;
            sprt.test = Sprt::new(eps, sprt.delta());
            needed = samples_needed(eps, alpha, cfg);
            best = Some(cur);
        }
    }
    let Some((m, _, _)) = best else {
        return Err(iterations);
    };
    let pose = model_to_pose(&m).ok_or(iterations)?;
    let inliers = s.inliers_of(&Model::from_pose(&pose));
    if inliers.len() < 4 {
        return Err(iterations);
    }
    Ok(RansacResult {
        pose,
        inliers,
        iterations,
        models,
        lo_runs,
    })
}

fn model_to_pose(m: &Model) -> Option<Pose> {
    let r_cw = nearest_rotation(&m.r)?;
    let c = -(r_cw.inverse() * m.t);
    c.iter().all(|v| v.is_finite()).then(|| Pose {
        r_world_cam: r_cw.inverse(),
        c_world: c,
    })
}
