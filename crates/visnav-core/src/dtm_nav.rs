//! DTM navigation: the camera's absolute pose from the optical flow between two frames and the
//! terrain model alone, no orthophoto (the "DTM navigator" of Kupervasser, Sarychev, Rubinstein,
//! Yavich 2018, "Robust positioning of drones for land use monitoring in strong terrain relief
//! using vision-based navigation").
//!
//! # The problem (the paper's)
//! Twelve unknowns: the first frame's position and attitude and the motion to the second frame.
//! Each flow vector, a pixel `p1` of the first frame seen at `p2` in the second, is one
//! constraint: the first frame's ray through `p1` meets the terrain at the ground point
//! `X(C1, R1, p1)` ([`Dem::intersect_ray`]); seen from the second pose it must project onto `p2`:
//!
//! ```text
//! r = pi(R2^T (X(C1, R1, p1) - C2)) - p2,    pi(q) = (fx q.x / q.z + cx, fy q.y / q.z + cy)
//! ```
//!
//! with `C2 = C1 + T`, `R2 = R1 dR` (`T`, `dR` the motion between the frames). The solution
//! minimises the stacked residuals. Over relief the flow field's pattern of parallax is the
//! terrain's shape seen from one place only: it fixes all twelve parameters. Over flat ground a
//! horizontal shift and a turn about the vertical change nothing: the normal equations are
//! singular there and the solver says so ([`DtmRejection::IllConditioned`],
//! [`DtmRejection::Unobservable`]).
//!
//! The solver iterates on the two poses (`R_i <- Exp(phi_i) R_i`, `C_i <- C_i + dC_i`, rotation
//! vectors in the world frame applied on the left): the same twelve degrees of freedom as the
//! paper's `(C1, angles1, T, dR)` (a one-to-one change of coordinates; [`DtmFix::motion`] gives
//! `T` and `dR` with their covariance), with simpler Jacobians.
//!
//! # Jacobians (analytic)
//! The ground point moves with the first pose along the terrain: with `X = C1 + t d`,
//! `d = R1 (x1, y1, 1)` and the surface normal `n = (-dh/dx, -dh/dy, 1)` at `X`
//! ([`Dem::gradient_at`]), the implicit function theorem on `n . dX = 0` gives
//! `dX = A (dC1 + t dd)`, `A = I - d n^T / (n . d)`, and `dd = -[d]x phi1`. The projection into
//! the second camera: `dq/dX = R2^T`, `dq/dC2 = -R2^T`, `dq/dphi2 = R2^T [X - C2]x`.
//!
//! # Estimation
//! Gauss-Newton on the whitened residuals (`sigma = sqrt(2) track_sigma_px`: both frames' noise),
//! with an M-estimator by iteratively reweighted least squares, in four stages:
//! 1. Huber (`huber_k_sigma`) with the first pose held at the guess: the second pose alone, the
//!    visual odometry's problem (a resection against the first guess's ground points), which
//!    converges from far. A guess's common heading error turns the baseline in the cameras'
//!    frames (2 deg of 2.6 km is 90 m, 16 px of flow on NGI), so the flow's first residuals are
//!    mostly the motion's.
//! 2. Huber with both frames' tilt (rotations about the world's horizontal axes) held at the
//!    guess's: a sideways shift and a tilt are nearly interchangeable to the flow, and Gauss-Newton
//!    from a guess hundreds of metres off can slide along that valley into another minimum
//!    (measured on NGI 0182/0184 from a guess 394 m and 2 deg off without these two stages: a
//!    solution 747 m and 11 deg wrong that fitted three quarters of the flow). An INS's roll and
//!    pitch stay good where its position and heading drift, so the guess's tilt is the safe thing
//!    to hold while position and heading find their basin.
//!
//!    These two stages only choose the basin: they may stop unconverged.
//! 3. Huber with everything free, from there.
//! 4. Tukey's biweight (`tukey_c_sigma`) from the Huber solution, which gives gross outliers
//!    (wrong flow vectors, moving objects) zero weight.
//!
//! Nothing of the guess is in the solution (no prior term), so it is an independent absolute
//! measurement; the guess only decides where the iterations start. A Gauss-Newton step that does not
//! lower the robust cost (or cannot be solved) switches to Levenberg-Marquardt (Marquardt's
//! diagonal damping) for the rest of that stage. The first guess is the navigation filter's two
//! poses.
//!
//! The covariance is `max(1, sigma0^2) k^2 (J^T J)^-1` over the inliers (whitened, unit
//! weights; `sigma0^2` the a-posteriori variance factor: never smaller than the a-priori; `k` the
//! `sigma_inflation`: the linearisation does not see the terrain model's kinks at its cell
//! edges, along which the minimum of the weakly determined direction wanders).
//!
//! # The terrain model's own error
//! The flow sees the cameras relative to the terrain model only: a model displaced by `b`
//! (misregistered horizontally, or its heights off by a common amount) gives the same flow as
//! both cameras displaced by `-b`. So the model's registration error (`dem_shift_sigma_cells` of
//! its cells, horizontally) and common height error (`dem_offset_sigma_m`) enter the covariance
//! exactly, as a common term of both positions: `Sigma_b` added to the `C1`, `C2` blocks and
//! their cross blocks. Its per-point errors (noise, trees on a terrain model) show in the fit's
//! residuals and `sigma0`.
//!
//! # Conditioning (what it refuses)
//! * Before solving, relief under the tracks: the standard deviation of the first guess's ground
//!   points' heights below `min_relief_agl_fraction` of the height above them
//!   ([`DtmRejection::FlatGround`]): a cheap screen, not the decision.
//! * After solving, the decision: the normal matrix scaled to unit diagonal (Jacobi) with a
//!   reciprocal condition number below [`MIN_RECIPROCAL_CONDITION`]
//!   ([`DtmRejection::IllConditioned`]), a horizontal 1-sigma of the first position given the
//!   attitudes over `max_sigma_agl_fraction` of the height above ground, or an attitude 1-sigma
//!   given the positions over `max_attitude_sigma_deg` ([`DtmRejection::Unobservable`]). The position is judged
//!   given the attitudes because a short baseline leaves a sideways shift and a tilt nearly
//!   interchangeable (at a 60 m baseline from 550 m, 31 m of marginal horizontal sigma but 7 m
//!   with the attitude known): the joint covariance carries that correlation to the filter, whose
//!   own roll and pitch resolve it. Flat ground leaves the position undetermined even with the
//!   attitude known: infinite.
//! * Too few tracks or tracks on the terrain, no convergence, too few inliers, a poor fit
//!   (`sigma0` over `max_sigma0`), non-finite numbers.
//! * When the caller says how good the guess's height and tilt are ([`DtmInput::guess_sigma`]):
//!   a solution whose height and tilt disagree with them ([`DtmRejection::InconsistentWithGuess`]):
//!   the flow can fit another minimum nearly as well, far from the truth in position, height and
//!   tilt; an INS's height and tilt are what stays good in a GPS outage. A check, not a prior.
//!   With the guess's horizontal sigma given, also a first position further from the guess's
//!   than the two sigmas together allow ([`DtmRejection::FarFromGuess`], [`GUESS_GATE_H_CHI2`]).
//!
//! # Conventions
//! World frame: the terrain model's map frame (x grid east, y grid north, z up, metres), as in
//! [`crate::pose`]. Camera frame `_cam`: x right, y down, z forward. Pixels: undistorted,
//! OpenCV's convention. Tracks are [`TrackPair`]s (the visual odometry's flow).

use nalgebra::{Matrix2x3, Matrix3, Matrix6, Rotation3, SMatrix, SVector, Vector2, Vector3};
use serde::{Deserialize, Serialize};

use crate::geo::dem::Dem;
use crate::pose::refine::skew;
use crate::pose::{ImageGeometry, Pose};
use crate::validate::{Problems, Validate};
use crate::vo::TrackPair;

pub mod flow;
pub mod navigator;

pub use navigator::{DTM_CLASSES, DtmNavigator, DtmObserver, DtmPoseFix, DtmRefusal, DtmStep};

type Vec12 = SVector<f64, 12>;
type Mat12 = SMatrix<f64, 12, 12>;
type Jac = SMatrix<f64, 2, 12>;

/// Offsets of the four 3-vectors in the parameter (and covariance) order
/// `[phi1, C1, phi2, C2]`.
const PHI1: usize = 0;
const C1: usize = 3;
const PHI2: usize = 6;
const C2: usize = 9;

/// Smallest accepted reciprocal condition number of the Jacobi-scaled normal matrix: with f64
/// (1e-16) and residuals of about 1e-1 px, 1e-10 still leaves every direction determined to
/// several digits; exactly flat ground gives 1e-15 or less.
pub const MIN_RECIPROCAL_CONDITION: f64 = 1e-10;

/// A step smaller than this moves the ground footprint by under a millimetre (rotations are
/// taken at the height above ground): converged.
const CONVERGED_STEP_M: f64 = 1e-3;

/// A drop of the robust cost (half a chi-square: moving any parameter by `x` of its own sigma
/// changes it by `x^2 / 2`) under which the iterations have converged: 1e-3 is 0.045 sigma. The
/// terrain's kinks (the bilinear surface's slope jumps at cell edges) make the cost rough at
/// about that level, so iterating further crawls along them.
const CONVERGED_COST_GAIN: f64 = 1e-3;

/// Levenberg-Marquardt damping (times each parameter's own diagonal entry, Marquardt 1963):
/// start, growth on a failed step,
/// shrink on a good one, and the damping at which the iterations stop (no step lowers the cost:
/// a minimum to working precision).
const LM_LAMBDA_START: f64 = 1e-4;
const LM_LAMBDA_UP: f64 = 10.0;
const LM_LAMBDA_DOWN: f64 = 0.3;
const LM_LAMBDA_MAX: f64 = 1e8;

/// The second camera must see a ground point at least this far in front, m (a point behind or at
/// the camera has no projection).
const MIN_DEPTH_M: f64 = 1e-3;

/// A ray meeting the terrain at a grazing angle: `|n . d|` below this (unit `d`, unnormalised
/// `n`) makes the ground point's derivative blow up; such a track is left out of that iteration.
const MIN_INCIDENCE: f64 = 1e-3;

/// DTM navigation settings (`[dtm_nav]`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DtmNavConfig {
    /// Run the DTM navigator (the daemon).
    pub enabled: bool,
    /// Fewest tracks on the terrain to try a solution.
    pub min_tracks: usize,
    /// 1-sigma position noise of a tracked feature in one frame, px.
    pub track_sigma_px: f64,
    /// Longest ray to the terrain, m.
    pub max_range_m: f64,
    /// Screen before solving: the ground points' height standard deviation must reach this
    /// fraction of the height above them.
    pub min_relief_agl_fraction: f64,
    /// Largest accepted horizontal 1-sigma of the first position, as a fraction of the height
    /// above ground.
    pub max_sigma_agl_fraction: f64,
    /// Largest accepted 1-sigma of the first attitude (any axis) given the positions, deg.
    pub max_attitude_sigma_deg: f64,
    /// Largest accepted a-posteriori sigma0 (the fit's residuals over their claimed noise).
    pub max_sigma0: f64,
    /// Fewest inliers as a fraction of the tracks on the terrain.
    pub min_inlier_fraction: f64,
    /// Iterations per stage (Huber, then Tukey).
    pub max_iterations: usize,
    /// Huber threshold, in sigmas.
    pub huber_k_sigma: f64,
    /// Tukey biweight cut-off, in sigmas (also the inlier threshold).
    pub tukey_c_sigma: f64,
    /// Factor on the standard deviations of the covariance (module doc).
    pub sigma_inflation: f64,
    /// The daemon pairs each frame with the newest earlier one at least this fraction of the
    /// height above ground away ([`navigator`]).
    pub min_baseline_agl_fraction: f64,
    /// ... and at most this much older, s.
    pub max_pair_span_s: f64,
    /// The terrain model's horizontal registration error, 1-sigma, in its cells (module doc,
    /// "The terrain model's own error").
    pub dem_shift_sigma_cells: f64,
    /// The terrain model's common height error, 1-sigma, m.
    pub dem_offset_sigma_m: f64,
}

/// Default fewest tracks: the twelve unknowns need six flow vectors; five times that leaves the
/// M-estimator a redundancy to find outliers with.
const DEFAULT_MIN_TRACKS: usize = 30;
/// Default track noise, as the visual odometry's (`vo::VoConfig::track_sigma_px`).
const DEFAULT_TRACK_SIGMA_PX: f64 = 0.5;
/// Default longest ray, m (as the visual odometry's).
const DEFAULT_MAX_RANGE_M: f64 = 20_000.0;
/// Default relief screen: 0.5 % of the height above ground (5 m of height spread at 1 km). Far
/// below what gives a usable fix; it only spares the solver ground that is flat to the eye.
const DEFAULT_MIN_RELIEF_AGL_FRACTION: f64 = 0.005;
/// Default horizontal sigma limit: 5 % of the height above ground (as the visual odometry's):
/// 25 m at 500 m. A larger sigma says little the filter does not know.
const DEFAULT_MAX_SIGMA_AGL_FRACTION: f64 = 0.05;
/// Default attitude sigma limit, deg (the absolute fix's `max_attitude_sigma_deg`).
const DEFAULT_MAX_ATTITUDE_SIGMA_DEG: f64 = 2.0;
/// Default sigma0 limit: residuals three times their claimed noise mean the model does not fit
/// (a terrain model far off, a wrong camera, a moving scene).
const DEFAULT_MAX_SIGMA0: f64 = 3.0;
/// Default inlier fraction: flow that passed the tracker's forward-backward check is nearly all
/// right (NGI 0182/0184: 99-100 % of the vectors agree with the solution from every guess it
/// solved correctly), while wrong minima leave more unexplained (NGI from guesses 200-600 m and
/// 2-10 deg off: 76-95 % for solutions 470-2300 m wrong; the guess check catches those above
/// 90 %). 90 % of the flow must agree. Over trees or buildings a terrain model (not a surface
/// model) leaves more flow unexplained: such pairs are refused, not guessed.
const DEFAULT_MIN_INLIER_FRACTION: f64 = 0.9;
/// Default iterations per stage: Gauss-Newton converges in 3-10 from an INS guess; a stage that
/// falls back to Levenberg-Marquardt crawls along the weakly determined direction for 20-35
/// (NGI 0182/0184: 20-93 iterations over all four stages).
const DEFAULT_MAX_ITERATIONS: usize = 50;
/// Huber's 95 % efficiency constant and Tukey's (Huber 1981; Beaton and Tukey 1974).
const DEFAULT_HUBER_K_SIGMA: f64 = 1.345;
const DEFAULT_TUKEY_C_SIGMA: f64 = 4.685;
/// Default covariance inflation: the linearised covariance does not see the terrain's kinks
/// (the bilinear surface's slope jumps at every cell edge), and along the weakly determined
/// direction the minimum wanders between them: over 24 noise draws of one synthetic pair with
/// the claimed noise (`tests::the_covariance_matches_the_scatter`) the errors scattered 1.6 times
/// the linear sigma (mean squared Mahalanobis distance 30 where 12 was due). 2 leaves a margin
/// for the terrain model's own error, which is not modelled otherwise.
const DEFAULT_SIGMA_INFLATION: f64 = 2.0;
/// Default pair baseline: 15 % of the height above ground (75 m at 500 m). One pair of synthetic
/// relief from 550 m above ground gave 77 / 38 / 31 m of horizontal sigma at 60 / 100 / 150 m
/// (14 / 10 / 8 m with the attitude known); the paper's 20 m between frames, 76 m: shorter
/// baselines say too little, longer ones lose overlap (a 38.7 deg field along track covers
/// 0.7 of the height above ground).
const DEFAULT_MIN_BASELINE_AGL_FRACTION: f64 = 0.15;
/// Default longest pair span, s: a pose guess older than this has drifted (an INS's tilt and
/// position errors grow with time) and a slow aircraft has other ways to measure.
const DEFAULT_MAX_PAIR_SPAN_S: f64 = 10.0;
/// Default horizontal registration sigma of the terrain model: a quarter of a cell. The global
/// elevation models' absolute geolocation is a fraction of their cell (SRTM: 12.6 m at 90 % for
/// 30 m cells (Rodriguez et al. 2006), about 6 m at one sigma per axis: a fifth of a cell), and a
/// model resampled to its grid adds up to half a cell of placement, uniform (0.29 cell at one
/// sigma) only where it was resampled coarser than its source.
const DEFAULT_DEM_SHIFT_SIGMA_CELLS: f64 = 0.25;
/// Default common height sigma of the terrain model, m: the global models' absolute vertical
/// error (SRTM: 5-9 m at 90 % over most terrain) at one sigma.
const DEFAULT_DEM_OFFSET_SIGMA_M: f64 = 5.0;

impl Default for DtmNavConfig {
    fn default() -> Self {
        Self {
            enabled: false,
            min_tracks: DEFAULT_MIN_TRACKS,
            track_sigma_px: DEFAULT_TRACK_SIGMA_PX,
            max_range_m: DEFAULT_MAX_RANGE_M,
            min_relief_agl_fraction: DEFAULT_MIN_RELIEF_AGL_FRACTION,
            max_sigma_agl_fraction: DEFAULT_MAX_SIGMA_AGL_FRACTION,
            max_attitude_sigma_deg: DEFAULT_MAX_ATTITUDE_SIGMA_DEG,
            max_sigma0: DEFAULT_MAX_SIGMA0,
            min_inlier_fraction: DEFAULT_MIN_INLIER_FRACTION,
            max_iterations: DEFAULT_MAX_ITERATIONS,
            huber_k_sigma: DEFAULT_HUBER_K_SIGMA,
            tukey_c_sigma: DEFAULT_TUKEY_C_SIGMA,
            sigma_inflation: DEFAULT_SIGMA_INFLATION,
            min_baseline_agl_fraction: DEFAULT_MIN_BASELINE_AGL_FRACTION,
            max_pair_span_s: DEFAULT_MAX_PAIR_SPAN_S,
            dem_shift_sigma_cells: DEFAULT_DEM_SHIFT_SIGMA_CELLS,
            dem_offset_sigma_m: DEFAULT_DEM_OFFSET_SIGMA_M,
        }
    }
}

impl Validate for DtmNavConfig {
    fn validate(&self, p: &mut Problems) {
        if self.min_tracks < 6 {
            p.push(
                "min_tracks",
                format!(
                    "{} is below 6 (twelve unknowns, two equations per track)",
                    self.min_tracks
                ),
            );
        }
        let positive = [
            ("track_sigma_px", self.track_sigma_px),
            ("max_range_m", self.max_range_m),
            ("max_sigma_agl_fraction", self.max_sigma_agl_fraction),
            ("max_attitude_sigma_deg", self.max_attitude_sigma_deg),
            ("max_sigma0", self.max_sigma0),
            ("huber_k_sigma", self.huber_k_sigma),
            ("tukey_c_sigma", self.tukey_c_sigma),
            ("min_baseline_agl_fraction", self.min_baseline_agl_fraction),
            ("max_pair_span_s", self.max_pair_span_s),
        ];
        if !(self.sigma_inflation.is_finite() && self.sigma_inflation >= 1.0) {
            p.push(
                "sigma_inflation",
                format!("{} must be finite and >= 1", self.sigma_inflation),
            );
        }
        for (key, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                p.push(key, format!("{v} must be finite and > 0"));
            }
        }
        for (key, v) in [
            ("dem_shift_sigma_cells", self.dem_shift_sigma_cells),
            ("dem_offset_sigma_m", self.dem_offset_sigma_m),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                p.push(key, format!("{v} must be finite and >= 0"));
            }
        }
        if !(self.min_relief_agl_fraction.is_finite() && self.min_relief_agl_fraction >= 0.0) {
            p.push(
                "min_relief_agl_fraction",
                format!("{} must be finite and >= 0", self.min_relief_agl_fraction),
            );
        }
        if !(self.min_inlier_fraction.is_finite()
            && (0.0..=1.0).contains(&self.min_inlier_fraction))
        {
            p.push(
                "min_inlier_fraction",
                format!("{} must be in 0..=1", self.min_inlier_fraction),
            );
        }
        if !(1..=1000).contains(&self.max_iterations) {
            p.push(
                "max_iterations",
                format!("{} must be in 1..=1000", self.max_iterations),
            );
        }
    }
}

/// Why no pose came out of a frame pair.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DtmRejection {
    /// Non-finite or non-rotation guesses, a bad camera or bad settings; says which.
    #[error("invalid input: {0}")]
    InvalidInput(String),
    /// The solution's first height and tilt disagree with the guess's beyond [`GUESS_GATE_CHI2`]
    /// (only with [`DtmInput::guess_sigma`]): a wrong minimum of the flow.
    #[error(
        "inconsistent with the navigation: height {dh_m:+.0} m and tilt {dtilt_deg:.2} deg from the guess's (squared Mahalanobis distance {m2:.1} over {max}): a wrong minimum"
    )]
    InconsistentWithGuess {
        /// Solution's first height minus the guess's, m.
        dh_m: f64,
        /// Tilt between the solution's first attitude and the guess's, deg.
        dtilt_deg: f64,
        /// Squared Mahalanobis distance (3 dof) with the summed covariances.
        m2: f64,
        /// The gate, [`GUESS_GATE_CHI2`].
        max: f64,
    },
    /// The solution's first horizontal position is beyond [`GUESS_GATE_H_CHI2`] from the guess's
    /// (only with a finite [`GuessSigma::horizontal_m`]).
    #[error(
        "{d_m:.0} m from the navigation's position (its 1-sigma {sigma_m:.0} m; squared Mahalanobis distance {m2:.1} over {max}): another minimum of the flow, or a navigation far more wrong than it says"
    )]
    FarFromGuess {
        /// Horizontal distance from the guess's first position, m.
        d_m: f64,
        /// The guess's horizontal 1-sigma per axis, m.
        sigma_m: f64,
        /// Squared Mahalanobis distance (2 dof) with the summed covariances.
        m2: f64,
        /// The gate, [`GUESS_GATE_H_CHI2`].
        max: f64,
    },
    /// Fewer flow vectors than [`DtmNavConfig::min_tracks`].
    #[error("{tracks} tracks, need {min}")]
    TooFewTracks {
        /// Flow vectors given.
        tracks: usize,
        /// [`DtmNavConfig::min_tracks`].
        min: usize,
    },
    /// Fewer flow vectors whose first-guess ray meets the terrain than
    /// [`DtmNavConfig::min_tracks`].
    #[error("{on_ground} of {tracks} tracks reach the terrain, need {min}")]
    TooFewOnGround {
        /// Vectors whose ray meets the terrain within [`DtmNavConfig::max_range_m`].
        on_ground: usize,
        /// Flow vectors given.
        tracks: usize,
        /// [`DtmNavConfig::min_tracks`].
        min: usize,
    },
    /// Relief screen before solving: the ground points' height spread is under
    /// [`DtmNavConfig::min_relief_agl_fraction`] of the height above them.
    #[error(
        "flat ground: the tracks' ground heights spread {relief_std_m:.1} m (1-sigma), under {min_fraction} of the {agl_m:.0} m above them; the terrain cannot fix the position"
    )]
    FlatGround {
        /// Standard deviation of the ground points' heights at the first guess, m.
        relief_std_m: f64,
        /// Height of the first guess above their mean, m.
        agl_m: f64,
        /// [`DtmNavConfig::min_relief_agl_fraction`].
        min_fraction: f64,
    },
    /// The Jacobi-scaled normal matrix (at the guess or at the solution) is near singular.
    #[error(
        "ill-conditioned: reciprocal condition number {rcond:.1e} of the normal equations (under {min:.0e}): flow and terrain do not determine the pose (flat ground, or tracks in a line)"
    )]
    IllConditioned {
        /// Its reciprocal condition number.
        rcond: f64,
        /// [`MIN_RECIPROCAL_CONDITION`].
        min: f64,
    },
    /// The first position's horizontal sigma given the attitudes, or the attitude sigma given
    /// the positions, is over its limit.
    #[error(
        "unobservable: {what} 1-sigma {sigma:.2} over the limit {limit:.2} (relief under the tracks {relief_std_m:.1} m 1-sigma, {agl_m:.0} m above ground)"
    )]
    Unobservable {
        /// "horizontal position given the attitude (m)" or "attitude given the position (deg)".
        what: &'static str,
        /// That 1-sigma, in the unit `what` names.
        sigma: f64,
        /// Its limit: [`DtmNavConfig::max_sigma_agl_fraction`] times `agl_m`, or
        /// [`DtmNavConfig::max_attitude_sigma_deg`].
        limit: f64,
        /// Standard deviation of the inliers' ground heights, m.
        relief_std_m: f64,
        /// Height of the first centre above their mean, m.
        agl_m: f64,
    },
    /// A free stage (Huber or Tukey) did not converge in [`DtmNavConfig::max_iterations`].
    #[error("no convergence in {iterations} iterations")]
    NotConverged {
        /// Iterations of all stages so far.
        iterations: usize,
    },
    /// Too little of the flow agrees with the solution.
    #[error("{inliers} of {on_ground} tracks agree with the solution, need {min}")]
    TooFewInliers {
        /// Vectors within the Tukey cut-off at the solution.
        inliers: usize,
        /// Vectors on the terrain at the first guess.
        on_ground: usize,
        /// [`DtmNavConfig::min_inlier_fraction`] of `on_ground`, at least 7.
        min: usize,
    },
    /// The residuals are too large for their claimed noise.
    #[error("poor fit: sigma0 {sigma0:.2} over {max} (residuals over their claimed noise)")]
    PoorFit {
        /// A-posteriori standard deviation of unit weight over the inliers.
        sigma0: f64,
        /// [`DtmNavConfig::max_sigma0`].
        max: f64,
    },
}

impl DtmRejection {
    /// The check's class for counting and metric labels (a name without numbers).
    pub fn class(&self) -> &'static str {
        match self {
            DtmRejection::InvalidInput(_) => "invalid_input",
            DtmRejection::InconsistentWithGuess { .. } => "inconsistent_with_guess",
            DtmRejection::FarFromGuess { .. } => "far_from_guess",
            DtmRejection::TooFewTracks { .. } => "few_tracks",
            DtmRejection::TooFewOnGround { .. } => "few_on_ground",
            DtmRejection::FlatGround { .. } => "flat_ground",
            DtmRejection::IllConditioned { .. } => "ill_conditioned",
            DtmRejection::Unobservable { .. } => "unobservable",
            DtmRejection::NotConverged { .. } => "not_converged",
            DtmRejection::TooFewInliers { .. } => "few_inliers",
            DtmRejection::PoorFit { .. } => "poor_fit",
        }
    }
}

/// The two frames' poses the navigation filter predicts: where the iterations start.
#[derive(Debug, Clone, Copy)]
pub struct DtmInput<'a> {
    /// Flow vectors: a pixel of the first frame and where it is in the second (undistorted).
    pub tracks: &'a [TrackPair],
    /// The camera's focal lengths, principal point and image size.
    pub image: &'a ImageGeometry,
    /// First guess of the first frame's camera pose (world frame).
    pub guess_first: Pose,
    /// First guess of the second frame's camera pose (world frame).
    pub guess_second: Pose,
    /// How good the guess's height and tilt are: when given, a solution whose first height and
    /// tilt disagree with the guess's beyond [`GUESS_GATE_CHI2`] is refused
    /// ([`DtmRejection::InconsistentWithGuess`]). A check only: nothing of the guess is fused.
    pub guess_sigma: Option<GuessSigma>,
}

/// 1-sigma of the guess's height and tilt (the navigation filter's: baro-aided height and
/// gravity-aided roll and pitch stay good where position and heading drift).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GuessSigma {
    /// The guess's height 1-sigma, m.
    pub height_m: f64,
    /// The guess's tilt 1-sigma per horizontal axis, rad.
    pub tilt_rad: f64,
    /// The guess's horizontal position 1-sigma per axis, m (infinite: unknown, no gate).
    pub horizontal_m: f64,
}

/// Chi-square 99.9 % point for 3 degrees of freedom: the gate on the solution's height and tilt
/// (two angles) against the guess's.
pub const GUESS_GATE_CHI2: f64 = 16.27;

/// Chi-square 99.9 % point for 2 degrees of freedom: the gate on the solution's horizontal
/// position against the guess's.
pub const GUESS_GATE_H_CHI2: f64 = 13.82;

/// Which minimiser finished a stage.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DtmMethod {
    /// Gauss-Newton: every step of the stage lowered the robust cost.
    GaussNewton,
    /// Levenberg-Marquardt: a Gauss-Newton step did not lower the cost (or could not be solved),
    /// so the stage switched to damped steps.
    LevenbergMarquardt,
}

/// `gauss_newton`, `levenberg_marquardt` (as serialised).
impl std::fmt::Display for DtmMethod {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            DtmMethod::GaussNewton => "gauss_newton",
            DtmMethod::LevenbergMarquardt => "levenberg_marquardt",
        })
    }
}

/// The twelve parameters solved.
#[derive(Debug, Clone, PartialEq)]
pub struct DtmFix {
    /// The first frame's camera pose (world frame).
    pub first: Pose,
    /// The second frame's camera pose (world frame).
    pub second: Pose,
    /// Covariance of `[phi1, C1, phi2, C2]` (rotation vectors in the world frame applied on the
    /// left, rad; positions, m): conservative (module doc).
    pub cov: Mat12,
    /// The minimiser that finished the final stage.
    pub method: DtmMethod,
    /// Iterations of all four stages together.
    pub iterations: usize,
    /// Flow vectors given.
    pub tracks: usize,
    /// Vectors on the terrain at the first guess.
    pub on_ground: usize,
    /// Inliers at the solution.
    pub inliers: usize,
    /// Reprojection RMS over the inliers, px.
    pub rms_px: f64,
    /// A-posteriori standard deviation of unit weight.
    pub sigma0: f64,
    /// Largest horizontal 1-sigma of the first position were both attitudes known, m: what the
    /// relief alone determines (the conditioning check's figure; the covariance itself is the
    /// joint one, where position and tilt are correlated).
    pub sigma_h_given_attitude_m: f64,
    /// Mean height of the first centre above the inliers' ground points, m.
    pub agl_m: f64,
    /// Standard deviation of those ground points' heights, m.
    pub relief_std_m: f64,
    /// Reciprocal condition number of the Jacobi-scaled normal matrix.
    pub rcond: f64,
}

/// The paper's last six parameters: the motion between the frames.
#[derive(Debug, Clone, PartialEq)]
pub struct DtmMotion {
    /// `T = C2 - C1`, world frame, m.
    pub t_world_m: Vector3<f64>,
    /// Covariance of `T`, world frame, m^2.
    pub cov_t_world_m2: Matrix3<f64>,
    /// `dR = R1^T R2`: second-camera vectors into the first camera frame.
    pub r_first_second: Rotation3<f64>,
    /// Covariance of the error of `dR` as a rotation vector in the first camera frame, on the
    /// left, rad^2.
    pub cov_rot_first_rad2: Matrix3<f64>,
}

impl DtmFix {
    /// The first frame's covariance in the resection's order `[phi_world, C_world]`.
    pub fn first_cov(&self) -> Matrix6<f64> {
        self.cov.fixed_view::<6, 6>(PHI1, PHI1).into_owned()
    }
    /// The second frame's covariance in the same order.
    pub fn second_cov(&self) -> Matrix6<f64> {
        self.cov.fixed_view::<6, 6>(PHI2, PHI2).into_owned()
    }
    /// The first position's covariance, world frame, m^2.
    pub fn position_cov_first_m2(&self) -> Matrix3<f64> {
        self.cov.fixed_view::<3, 3>(C1, C1).into_owned()
    }
    /// The first attitude's covariance (world-frame rotation vector on the left), rad^2.
    pub fn attitude_cov_first_rad2(&self) -> Matrix3<f64> {
        self.cov.fixed_view::<3, 3>(PHI1, PHI1).into_owned()
    }
    /// Largest horizontal 1-sigma of the first position, m.
    pub fn sigma_horizontal_first_m(&self) -> f64 {
        horizontal_sigma_m(&self.position_cov_first_m2())
    }
    /// The motion between the frames with its covariance (the paper's `T`, `dR`).
    pub fn motion(&self) -> DtmMotion {
        // T = C2 - C1: rows [0, -I, 0, I]; psi = R1^T (phi2 - phi1): rows [-R1^T, 0, R1^T, 0].
        let r1t = *self.first.r_world_cam.inverse().matrix();
        let mut jt = SMatrix::<f64, 3, 12>::zeros();
        jt.fixed_view_mut::<3, 3>(0, C1)
            .copy_from(&-Matrix3::identity());
        jt.fixed_view_mut::<3, 3>(0, C2)
            .copy_from(&Matrix3::identity());
        let mut jr = SMatrix::<f64, 3, 12>::zeros();
        jr.fixed_view_mut::<3, 3>(0, PHI1).copy_from(&-r1t);
        jr.fixed_view_mut::<3, 3>(0, PHI2).copy_from(&r1t);
        DtmMotion {
            t_world_m: self.second.c_world - self.first.c_world,
            cov_t_world_m2: jt * self.cov * jt.transpose(),
            r_first_second: self.first.r_world_cam.inverse() * self.second.r_world_cam,
            cov_rot_first_rad2: jr * self.cov * jr.transpose(),
        }
    }
}

/// Largest 1-sigma of the horizontal (x, y) block of a position covariance, m.
fn horizontal_sigma_m(cov: &Matrix3<f64>) -> f64 {
    let h = cov.fixed_view::<2, 2>(0, 0).into_owned();
    h.symmetric_eigenvalues().max().max(0.0).sqrt()
}

/// The robust loss of a stage, on the whitened residual norm `s`.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Loss {
    Huber(f64),
    Tukey(f64),
}

impl Loss {
    /// `rho(s)`: `s^2 / 2` near zero.
    fn rho(self, s: f64) -> f64 {
        match self {
            Loss::Huber(k) if s <= k => 0.5 * s * s,
            Loss::Huber(k) => k * s - 0.5 * k * k,
            Loss::Tukey(c) if s <= c => {
                let u = 1.0 - (s / c).powi(2);
                c * c / 6.0 * (1.0 - u * u * u)
            }
            Loss::Tukey(c) => c * c / 6.0,
        }
    }
    /// The IRLS weight `rho'(s) / s`.
    fn weight(self, s: f64) -> f64 {
        match self {
            Loss::Huber(k) if s <= k => 1.0,
            Loss::Huber(k) => k / s,
            Loss::Tukey(c) if s <= c => (1.0 - (s / c).powi(2)).powi(2),
            Loss::Tukey(_) => 0.0,
        }
    }
    /// The cost of a track whose ray misses the terrain at a trial pose: that of a residual at
    /// the Tukey cut-off (large, finite: the iterations may not gain by shooting rays off the
    /// model).
    fn missing(self, tukey_c: f64) -> f64 {
        self.rho(tukey_c)
    }
}

/// The first frame's pose: held at the guess in the first stage.
const FIRST_POSE: [usize; 6] = [PHI1, PHI1 + 1, PHI1 + 2, C1, C1 + 1, C1 + 2];

/// The tilt parameters (rotations about the world's east and north axes) of both frames: held
/// at the guess in the second stage.
const TILT: [usize; 4] = [PHI1, PHI1 + 1, PHI2, PHI2 + 1];

/// One stage of the minimisation: its loss and the parameters it holds.
#[derive(Debug, Clone, Copy)]
struct Stage {
    loss: Loss,
    held: &'static [usize],
}

/// A stage's outcome: where it stopped, after how many iterations, by which method, and whether
/// it converged.
struct Minimised {
    poses: PosePair,
    iterations: usize,
    method: DtmMethod,
    converged: bool,
}

impl Minimised {
    fn at(poses: PosePair, iterations: usize, method: DtmMethod, converged: bool) -> Self {
        Self {
            poses,
            iterations,
            method,
            converged,
        }
    }
}

/// The two poses being solved.
#[derive(Debug, Clone, Copy, PartialEq)]
struct PosePair {
    first: Pose,
    second: Pose,
}

impl PosePair {
    /// `R_i <- Exp(phi_i) R_i`, `C_i <- C_i + dC_i`.
    fn apply(&self, d: &Vec12) -> Self {
        let turn = |r: &Rotation3<f64>, phi: Vector3<f64>| {
            let mut out = Rotation3::new(phi) * r;
            out.renormalize();
            out
        };
        let v = |i: usize| Vector3::new(d[i], d[i + 1], d[i + 2]);
        PosePair {
            first: Pose {
                r_world_cam: turn(&self.first.r_world_cam, v(PHI1)),
                c_world: self.first.c_world + v(C1),
            },
            second: Pose {
                r_world_cam: turn(&self.second.r_world_cam, v(PHI2)),
                c_world: self.second.c_world + v(C2),
            },
        }
    }
}

/// One flow vector in the solver's terms: the first frame's normalised ray and the second
/// frame's pixel.
#[derive(Debug, Clone, Copy)]
struct Obs {
    ray_cam: Vector3<f64>,
    px2: Vector2<f64>,
}

/// One track evaluated at a pose pair: its residual (px) and Jacobian (px per parameter), and
/// the ground point.
struct TrackEval {
    r_px: Vector2<f64>,
    jac: Jac,
    ground: Vector3<f64>,
}

/// The residual of `obs` at `poses` with its Jacobian; `None` when the ray misses the terrain,
/// meets it grazing, or the point is not in front of the second camera.
fn eval_track(
    poses: &PosePair,
    obs: &Obs,
    image: &ImageGeometry,
    dem: &Dem,
    max_range_m: f64,
) -> Option<TrackEval> {
    let (p1, p2) = (&poses.first, &poses.second);
    let d = p1.r_world_cam * obs.ray_cam;
    let c1 = p1.c_world;
    let hit = dem.intersect_ray([c1.x, c1.y, c1.z], [d.x, d.y, d.z], max_range_m)?;
    let x = Vector3::new(hit[0], hit[1], hit[2]);
    let t = (x - c1).norm() / d.norm();
    let g = dem.gradient_at(x.x, x.y)?;
    let n = Vector3::new(-g[0], -g[1], 1.0);
    let nd = n.dot(&d);
    if nd.abs() < MIN_INCIDENCE * d.norm() {
        return None;
    }
    let a = Matrix3::identity() - d * n.transpose() / nd;
    let r2t = *p2.r_world_cam.inverse().matrix();
    let rel = x - p2.c_world;
    let q = r2t * rel;
    if q.z.is_nan() || q.z <= MIN_DEPTH_M {
        return None;
    }
    let pred = Vector2::new(
        image.fx_px * q.x / q.z + image.cx_px,
        image.fy_px * q.y / q.z + image.cy_px,
    );
    let proj = Matrix2x3::new(
        image.fx_px / q.z,
        0.0,
        -image.fx_px * q.x / (q.z * q.z),
        0.0,
        image.fy_px / q.z,
        -image.fy_px * q.y / (q.z * q.z),
    );
    let pr = proj * r2t;
    let mut jac = Jac::zeros();
    jac.fixed_view_mut::<2, 3>(0, PHI1)
        .copy_from(&(pr * a * (-t * skew(&d))));
    jac.fixed_view_mut::<2, 3>(0, C1).copy_from(&(pr * a));
    jac.fixed_view_mut::<2, 3>(0, PHI2)
        .copy_from(&(pr * skew(&rel)));
    jac.fixed_view_mut::<2, 3>(0, C2).copy_from(&(-pr));
    let r_px = pred - obs.px2;
    let finite = r_px.iter().chain(jac.iter()).all(|v| v.is_finite());
    finite.then_some(TrackEval {
        r_px,
        jac,
        ground: x,
    })
}

/// Everything the iterations need at one pose pair.
struct Linearised {
    cost: f64,
    /// `sum w J^T J`, `sum w J^T r` (whitened).
    h: Mat12,
    g: Vec12,
}

/// The problem: observations, camera, terrain, settings.
struct Problem<'a> {
    obs: Vec<Obs>,
    image: &'a ImageGeometry,
    dem: &'a Dem,
    cfg: &'a DtmNavConfig,
    sigma_px: f64,
}

impl Problem<'_> {
    /// Robust cost and normal equations at `poses` under `loss`.
    fn linearise(&self, poses: &PosePair, loss: Loss) -> Linearised {
        let mut out = Linearised {
            cost: 0.0,
            h: Mat12::zeros(),
            g: Vec12::zeros(),
        };
        for o in &self.obs {
            match eval_track(poses, o, self.image, self.dem, self.cfg.max_range_m) {
                Some(e) => {
                    let r = e.r_px / self.sigma_px;
                    let j = e.jac / self.sigma_px;
                    let s = r.norm();
                    out.cost += loss.rho(s);
                    let w = loss.weight(s);
                    if w > 0.0 {
                        out.h += j.transpose() * j * w;
                        out.g += j.transpose() * r * w;
                    }
                }
                None => out.cost += loss.missing(self.cfg.tukey_c_sigma),
            }
        }
        out
    }

    /// The robust cost alone.
    fn cost(&self, poses: &PosePair, loss: Loss) -> f64 {
        self.obs
            .iter()
            .map(
                |o| match eval_track(poses, o, self.image, self.dem, self.cfg.max_range_m) {
                    Some(e) => loss.rho((e.r_px / self.sigma_px).norm()),
                    None => loss.missing(self.cfg.tukey_c_sigma),
                },
            )
            .sum()
    }

    /// Size of a step on the ground: positions in metres, rotations times the range to the
    /// ground.
    fn step_m(d: &Vec12, agl_m: f64) -> f64 {
        let n = |i: usize| Vector3::new(d[i], d[i + 1], d[i + 2]).norm();
        (n(PHI1) * agl_m).max(n(PHI2) * agl_m).max(n(C1)).max(n(C2))
    }

    /// One stage: minimise the robust cost under `loss` from `start` by Gauss-Newton, switching
    /// to Levenberg-Marquardt when a Gauss-Newton step fails (or from the start when
    /// `lm_only`). Returns the solution, the iterations and the method that finished.
    fn minimise(
        &self,
        start: PosePair,
        stage: Stage,
        agl_m: f64,
        lm_only: bool,
    ) -> Result<Minimised, DtmRejection> {
        let loss = stage.loss;
        let mut x = start;
        let mut lin = self.linearise(&x, loss);
        let mut lambda: Option<f64> = lm_only.then_some(LM_LAMBDA_START);
        for it in 1..=self.cfg.max_iterations {
            let method = match lambda {
                None => DtmMethod::GaussNewton,
                Some(_) => DtmMethod::LevenbergMarquardt,
            };
            let (mut a, mut g) = (lin.h, lin.g);
            if let Some(l) = lambda {
                for i in 0..12 {
                    a[(i, i)] += l * lin.h[(i, i)].max(1e-12);
                }
            }
            for &i in stage.held {
                a.row_mut(i).fill(0.0);
                a.column_mut(i).fill(0.0);
                a[(i, i)] = 1.0;
                g[i] = 0.0;
            }
            let step = a.cholesky().map(|c| -c.solve(&g));
            let Some(delta) = step.filter(|d| d.iter().all(|v| v.is_finite())) else {
                // Singular normal equations: damp (Levenberg-Marquardt) or damp more.
                let up = lambda.map_or(LM_LAMBDA_START, |l| l * LM_LAMBDA_UP);
                if up > LM_LAMBDA_MAX {
                    return Err(DtmRejection::IllConditioned {
                        rcond: reciprocal_condition(&lin.h),
                        min: MIN_RECIPROCAL_CONDITION,
                    });
                }
                lambda = Some(up);
                continue;
            };
            let trial = x.apply(&delta);
            let trial_cost = self.cost(&trial, loss);
            let small = Self::step_m(&delta, agl_m) < CONVERGED_STEP_M;
            if trial_cost <= lin.cost {
                let gain = lin.cost - trial_cost;
                x = trial;
                lin = self.linearise(&x, loss);
                if let Some(l) = lambda.as_mut() {
                    *l *= LM_LAMBDA_DOWN;
                }
                if small || gain <= CONVERGED_COST_GAIN {
                    return Ok(Minimised::at(x, it, method, true));
                }
            } else if small {
                // A step too small to matter that does not lower the cost: at the minimum.
                return Ok(Minimised::at(x, it, method, true));
            } else {
                let up = lambda.map_or(LM_LAMBDA_START, |l| l * LM_LAMBDA_UP);
                if up > LM_LAMBDA_MAX {
                    // No damped step lowers the cost either: a minimum to working precision.
                    return Ok(Minimised::at(x, it, DtmMethod::LevenbergMarquardt, true));
                }
                lambda = Some(up);
            }
        }
        let method = match lambda {
            None => DtmMethod::GaussNewton,
            Some(_) => DtmMethod::LevenbergMarquardt,
        };
        Ok(Minimised::at(x, self.cfg.max_iterations, method, false))
    }
}

/// The first frame's pose (and the second's) from the flow and the terrain: see the module
/// documentation.
pub fn solve(input: &DtmInput<'_>, dem: &Dem, cfg: &DtmNavConfig) -> Result<DtmFix, DtmRejection> {
    solve_with(input, dem, cfg, false)
}

/// [`solve`], optionally with Levenberg-Marquardt from the first iteration (tests of the
/// fallback).
fn solve_with(
    input: &DtmInput<'_>,
    dem: &Dem,
    cfg: &DtmNavConfig,
    lm_only: bool,
) -> Result<DtmFix, DtmRejection> {
    check_inputs(input, cfg)?;
    let start = PosePair {
        first: input.guess_first,
        second: input.guess_second,
    };
    let problem = Problem {
        obs: observations(input),
        image: input.image,
        dem,
        cfg,
        sigma_px: std::f64::consts::SQRT_2 * cfg.track_sigma_px,
    };
    let (obs, agl0) = screen_tracks(&problem, &start, input.tracks.len())?;
    let problem = Problem { obs, ..problem };
    let (x, iterations, method) = run_stages(&problem, start, agl0, lm_only)?;
    let mut fix = assess(&problem, &x, input.tracks.len())?;
    add_dem_error(&mut fix, dem, cfg);
    if let Some(sigma) = input.guess_sigma {
        check_against_guess(&fix, &input.guess_first, &sigma)?;
    }
    fix.method = method;
    fix.iterations = iterations;
    Ok(fix)
}

/// The tracks on the terrain at the first guess (the ones solved with) and the guess's height
/// above them, after the count and relief screens.
fn screen_tracks(
    problem: &Problem<'_>,
    start: &PosePair,
    tracks: usize,
) -> Result<(Vec<Obs>, f64), DtmRejection> {
    let cfg = problem.cfg;
    let hits: Vec<(Obs, f64)> = problem
        .obs
        .iter()
        .filter_map(|o| {
            eval_track(start, o, problem.image, problem.dem, cfg.max_range_m)
                .map(|e| (*o, e.ground.z))
        })
        .collect();
    if hits.len() < cfg.min_tracks {
        return Err(DtmRejection::TooFewOnGround {
            on_ground: hits.len(),
            tracks,
            min: cfg.min_tracks,
        });
    }
    let heights: Vec<f64> = hits.iter().map(|(_, z)| *z).collect();
    let (agl_m, relief_std_m) = agl_and_relief(&heights, start.first.c_world.z);
    if agl_m.is_nan() || agl_m <= 0.0 {
        return Err(DtmRejection::InvalidInput(format!(
            "the first guess is {agl_m:.0} m above the ground it sees"
        )));
    }
    if relief_std_m < cfg.min_relief_agl_fraction * agl_m {
        return Err(DtmRejection::FlatGround {
            relief_std_m,
            agl_m,
            min_fraction: cfg.min_relief_agl_fraction,
        });
    }
    Ok((hits.into_iter().map(|(o, _)| o).collect(), agl_m))
}

/// The conditioning check at the first guess, then the four stages (module doc): the first pose
/// held, the tilt held (these two only choose the basin and may stop unconverged), everything
/// free with Huber, then Tukey (these must converge). The solution, the iterations of all
/// stages and the last stage's method.
fn run_stages(
    problem: &Problem<'_>,
    start: PosePair,
    agl_m: f64,
    lm_only: bool,
) -> Result<(PosePair, usize, DtmMethod), DtmRejection> {
    let cfg = problem.cfg;
    let huber = Loss::Huber(cfg.huber_k_sigma);
    // Singular normal equations (flat ground, tracks in a line) are refused before iterating.
    let rcond0 = reciprocal_condition(&problem.linearise(&start, huber).h);
    if rcond0.is_nan() || rcond0 < MIN_RECIPROCAL_CONDITION {
        return Err(DtmRejection::IllConditioned {
            rcond: rcond0,
            min: MIN_RECIPROCAL_CONDITION,
        });
    }
    let stage = |loss, held| Stage { loss, held };
    let stages = [
        stage(huber, &FIRST_POSE[..]),
        stage(huber, &TILT[..]),
        stage(huber, &[]),
        stage(Loss::Tukey(cfg.tukey_c_sigma), &[]),
    ];
    let (mut x, mut iterations, mut method) = (start, 0, DtmMethod::GaussNewton);
    for (i, stage) in stages.iter().enumerate() {
        let m = problem.minimise(x, *stage, agl_m, lm_only)?;
        iterations += m.iterations;
        if !m.converged && i >= 2 {
            return Err(DtmRejection::NotConverged { iterations });
        }
        (x, method) = (m.poses, m.method);
    }
    Ok((x, iterations, method))
}

/// The solution's first height and tilt against the guess's ([`DtmInput::guess_sigma`]): the
/// flow over relief can have other minima that fit it nearly as well (NGI 0182/0184 from guesses
/// 200-600 m and 10 deg off: solutions 470-2300 m wrong with 85-95 % of the flow agreeing,
/// their height 300-2000 m and their tilt up to 34 deg from the truth), while an INS's height
/// and tilt stay good.
fn check_against_guess(fix: &DtmFix, guess: &Pose, sigma: &GuessSigma) -> Result<(), DtmRejection> {
    check_horizontal_against_guess(fix, guess, sigma)?;
    let dh = fix.first.c_world.z - guess.c_world.z;
    let rot = crate::pose::refine::log_so3(&(fix.first.r_world_cam * guess.r_world_cam.inverse()));
    let z = Vector3::new(dh, rot.x, rot.y);
    let idx = [C1 + 2, PHI1, PHI1 + 1];
    let mut cov = Matrix3::from_fn(|i, j| fix.cov[(idx[i], idx[j])]);
    cov[(0, 0)] += sigma.height_m.powi(2);
    cov[(1, 1)] += sigma.tilt_rad.powi(2);
    cov[(2, 2)] += sigma.tilt_rad.powi(2);
    let m2 = cov
        .try_inverse()
        .map_or(f64::INFINITY, |inv| (z.transpose() * inv * z)[(0, 0)]);
    if m2.is_nan() || m2 > GUESS_GATE_CHI2 {
        return Err(DtmRejection::InconsistentWithGuess {
            dh_m: dh,
            dtilt_deg: rot.x.hypot(rot.y).to_degrees(),
            m2,
            max: GUESS_GATE_CHI2,
        });
    }
    Ok(())
}

/// The solution's first horizontal position against the guess's ([`GuessSigma::horizontal_m`]):
/// a pose far beyond what the navigation says of itself is more often another minimum of the
/// flow than a navigation that wrong (a guess 200 m off gave a pose 250 m wrong on an unseen
/// strip), and a navigation that wrong is the filter's integrity problem to raise, not this
/// measurement's to paper over.
fn check_horizontal_against_guess(
    fix: &DtmFix,
    guess: &Pose,
    sigma: &GuessSigma,
) -> Result<(), DtmRejection> {
    if sigma.horizontal_m.is_infinite() {
        return Ok(());
    }
    let d = (fix.first.c_world - guess.c_world).xy();
    let mut cov = fix.cov.fixed_view::<2, 2>(C1, C1).into_owned();
    cov[(0, 0)] += sigma.horizontal_m.powi(2);
    cov[(1, 1)] += sigma.horizontal_m.powi(2);
    let m2 = cov
        .try_inverse()
        .map_or(f64::INFINITY, |inv| (d.transpose() * inv * d)[(0, 0)]);
    if m2.is_nan() || m2 > GUESS_GATE_H_CHI2 {
        return Err(DtmRejection::FarFromGuess {
            d_m: d.norm(),
            sigma_m: sigma.horizontal_m,
            m2,
            max: GUESS_GATE_H_CHI2,
        });
    }
    Ok(())
}

/// The terrain model's own error in the covariance (module doc): a model displaced by `b` is
/// seen by the flow exactly as both cameras displaced by `-b`, so its registration and common
/// height errors add `diag(s_h^2, s_h^2, s_v^2)` to both positions' blocks and to their cross
/// blocks (the same `b` for both frames). The attitudes are untouched.
fn add_dem_error(fix: &mut DtmFix, dem: &Dem, cfg: &DtmNavConfig) {
    let s_h = cfg.dem_shift_sigma_cells * dem.cell_m().unwrap_or(0.0);
    let b = Matrix3::from_diagonal(&Vector3::new(
        s_h * s_h,
        s_h * s_h,
        cfg.dem_offset_sigma_m.powi(2),
    ));
    for (r, c) in [(C1, C1), (C1, C2), (C2, C1), (C2, C2)] {
        let mut blk = fix.cov.fixed_view_mut::<3, 3>(r, c);
        blk += b;
    }
}

/// Mean height of a camera at `z_m` above `heights` and their standard deviation, m.
fn agl_and_relief(heights: &[f64], z_m: f64) -> (f64, f64) {
    let n = heights.len().max(1) as f64;
    let mean = heights.iter().sum::<f64>() / n;
    let var = heights.iter().map(|h| (h - mean).powi(2)).sum::<f64>() / n;
    (z_m - mean, var.sqrt())
}

/// Inliers, covariance and the conditioning and fit checks at the solution.
fn assess(problem: &Problem<'_>, sol: &PosePair, tracks: usize) -> Result<DtmFix, DtmRejection> {
    let cfg = problem.cfg;
    let n = inlier_normals(problem, sol)?;
    let (agl_m, relief_std_m) = agl_and_relief(&n.heights, sol.first.c_world.z);
    let (cov, sigma0, factor, rcond) = covariance(&n, cfg)?;
    let sigma_h = check_observable(&n.h, factor, agl_m, relief_std_m, cfg)?;
    let inliers = n.heights.len();
    let fix = DtmFix {
        first: sol.first,
        second: sol.second,
        cov,
        method: DtmMethod::GaussNewton,
        iterations: 0,
        tracks,
        on_ground: problem.obs.len(),
        inliers,
        rms_px: (n.sum_px2 / inliers as f64).sqrt(),
        sigma0,
        sigma_h_given_attitude_m: sigma_h,
        agl_m,
        relief_std_m,
        rcond,
    };
    let finite = fix.cov.iter().all(|v| v.is_finite())
        && fix.first.c_world.iter().all(|v| v.is_finite())
        && fix.second.c_world.iter().all(|v| v.is_finite());
    if !finite {
        return Err(DtmRejection::InvalidInput(
            "the solution is not finite".into(),
        ));
    }
    Ok(fix)
}

/// The inliers' whitened normal matrix at the solution, their squared residuals (whitened and
/// in pixels) and ground heights.
struct InlierNormals {
    h: Mat12,
    sum_s2: f64,
    sum_px2: f64,
    heights: Vec<f64>,
}

/// The inliers (residual within `tukey_c_sigma`) at the solution; too few of the tracks on the
/// terrain refuses.
fn inlier_normals(problem: &Problem<'_>, sol: &PosePair) -> Result<InlierNormals, DtmRejection> {
    let cfg = problem.cfg;
    let mut n = InlierNormals {
        h: Mat12::zeros(),
        sum_s2: 0.0,
        sum_px2: 0.0,
        heights: Vec::new(),
    };
    for o in &problem.obs {
        let Some(e) = eval_track(sol, o, problem.image, problem.dem, cfg.max_range_m) else {
            continue;
        };
        let s = e.r_px.norm() / problem.sigma_px;
        if s <= cfg.tukey_c_sigma {
            let j = e.jac / problem.sigma_px;
            n.h += j.transpose() * j;
            n.sum_s2 += s * s;
            n.sum_px2 += e.r_px.norm_squared();
            n.heights.push(e.ground.z);
        }
    }
    let on_ground = problem.obs.len();
    let inliers = n.heights.len();
    let min_inliers = ((cfg.min_inlier_fraction * on_ground as f64).ceil() as usize).max(7);
    if inliers < min_inliers {
        return Err(DtmRejection::TooFewInliers {
            inliers,
            on_ground,
            min: min_inliers,
        });
    }
    Ok(n)
}

/// The solution's covariance `max(1, sigma0^2) k^2 H^-1` (module doc) with sigma0, the factor
/// on `H^-1` and the reciprocal condition number; ill-conditioned or poorly fitting refuses.
fn covariance(
    n: &InlierNormals,
    cfg: &DtmNavConfig,
) -> Result<(Mat12, f64, f64, f64), DtmRejection> {
    let rcond = reciprocal_condition(&n.h);
    let ill = DtmRejection::IllConditioned {
        rcond,
        min: MIN_RECIPROCAL_CONDITION,
    };
    if rcond.is_nan() || rcond < MIN_RECIPROCAL_CONDITION {
        return Err(ill);
    }
    let Some(h_inv) = n.h.try_inverse() else {
        return Err(ill);
    };
    // Redundancy: two equations per inlier, twelve unknowns (inliers >= 7).
    let dof = (2 * n.heights.len() - 12) as f64;
    let sigma0 = (n.sum_s2 / dof).sqrt();
    if sigma0.is_nan() || sigma0 > cfg.max_sigma0 {
        return Err(DtmRejection::PoorFit {
            sigma0,
            max: cfg.max_sigma0,
        });
    }
    let factor = sigma0.max(1.0).powi(2) * cfg.sigma_inflation.powi(2);
    let cov = h_inv * factor;
    Ok((0.5 * (cov + cov.transpose()), sigma0, factor, rcond))
}

/// The observability checks (module doc): the horizontal sigma of the first position given the
/// attitudes, and the attitude sigma given the positions; returns the former, m.
fn check_observable(
    h: &Mat12,
    factor: f64,
    agl_m: f64,
    relief_std_m: f64,
    cfg: &DtmNavConfig,
) -> Result<f64, DtmRejection> {
    let sigma_h = given_other_block_sigma(h, [C1, C2], factor);
    let limit_h = cfg.max_sigma_agl_fraction * agl_m;
    if sigma_h.is_nan() || sigma_h > limit_h {
        return Err(DtmRejection::Unobservable {
            what: "horizontal position given the attitude (m)",
            sigma: sigma_h,
            limit: limit_h,
            relief_std_m,
            agl_m,
        });
    }
    let sigma_att_deg = given_other_block_sigma(h, [PHI1, PHI2], factor).to_degrees();
    if sigma_att_deg.is_nan() || sigma_att_deg > cfg.max_attitude_sigma_deg {
        return Err(DtmRejection::Unobservable {
            what: "attitude given the position (deg)",
            sigma: sigma_att_deg,
            limit: cfg.max_attitude_sigma_deg,
            relief_std_m,
            agl_m,
        });
    }
    Ok(sigma_h)
}

/// Largest 1-sigma of the first frame's 3-vector at `blocks[0]` when the other kind of
/// parameter (attitudes for positions, positions for attitudes) is known: the information of
/// the two blocks `blocks` (the first and the second frame's), inverted, times `factor`.
/// Horizontal only for positions (the x, y part). Infinite when that information is singular.
fn given_other_block_sigma(h: &Mat12, blocks: [usize; 2], factor: f64) -> f64 {
    let idx = [
        blocks[0],
        blocks[0] + 1,
        blocks[0] + 2,
        blocks[1],
        blocks[1] + 1,
        blocks[1] + 2,
    ];
    let info = Matrix6::from_fn(|i, j| h[(idx[i], idx[j])]);
    let Some(cov) = info.try_inverse() else {
        return f64::INFINITY;
    };
    let first = cov.fixed_view::<3, 3>(0, 0).into_owned() * factor;
    if blocks[0] == C1 {
        horizontal_sigma_m(&first)
    } else {
        first.symmetric_eigenvalues().max().max(0.0).sqrt()
    }
}

/// Reciprocal condition number (smallest over largest eigenvalue) of `h` scaled to a unit
/// diagonal; 0 when a diagonal entry is not positive or anything is not finite.
fn reciprocal_condition(h: &Mat12) -> f64 {
    let d: Vec<f64> = (0..12).map(|i| h[(i, i)]).collect();
    if !d.iter().all(|v| v.is_finite() && *v > 0.0) {
        return 0.0;
    }
    let scaled = Mat12::from_fn(|i, j| h[(i, j)] / (d[i] * d[j]).sqrt());
    let eig = scaled.symmetric_eigenvalues();
    let (min, max) = (eig.min(), eig.max());
    if !(min.is_finite() && max.is_finite() && max > 0.0) {
        return 0.0;
    }
    (min / max).max(0.0)
}

/// The tracks as first-frame rays and second-frame pixels (non-finite ones dropped).
fn observations(input: &DtmInput<'_>) -> Vec<Obs> {
    let im = input.image;
    input
        .tracks
        .iter()
        .filter(|t| {
            t.prev_px
                .iter()
                .chain(t.next_px.iter())
                .all(|v| v.is_finite())
        })
        .map(|t| Obs {
            ray_cam: Vector3::new(
                (t.prev_px.x - im.cx_px) / im.fx_px,
                (t.prev_px.y - im.cy_px) / im.fy_px,
                1.0,
            ),
            px2: t.next_px,
        })
        .collect()
}

/// Settings, camera, guesses and the number of tracks are usable.
fn check_inputs(input: &DtmInput<'_>, cfg: &DtmNavConfig) -> Result<(), DtmRejection> {
    let mut problems = Problems::default();
    cfg.validate(&mut problems);
    if let Some(first) = problems.list.first() {
        return Err(DtmRejection::InvalidInput(format!("[dtm_nav] {first}")));
    }
    let invalid = |s: &str| Err(DtmRejection::InvalidInput(s.into()));
    for pose in [&input.guess_first, &input.guess_second] {
        let m = pose.r_world_cam.matrix();
        let finite = pose.c_world.iter().chain(m.iter()).all(|v| v.is_finite());
        if !finite {
            return invalid("a first-guess pose is not finite");
        }
        if (m * m.transpose() - Matrix3::identity()).amax() > 1e-6 || m.determinant() <= 0.0 {
            return invalid("a first-guess attitude is not a rotation");
        }
    }
    if let Some(g) = input.guess_sigma
        && !(g.height_m.is_finite()
            && g.height_m > 0.0
            && g.tilt_rad.is_finite()
            && g.tilt_rad > 0.0)
    {
        return invalid("the guess's height and tilt sigmas must be finite and > 0");
    }
    if let Some(g) = input.guess_sigma
        && (g.horizontal_m.is_nan() || g.horizontal_m <= 0.0)
    {
        return invalid("the guess's horizontal sigma must be > 0 (infinite: unknown)");
    }
    let im = input.image;
    let ok = |v: f64| v.is_finite() && v > 0.0;
    if !(ok(im.fx_px) && ok(im.fy_px) && im.cx_px.is_finite() && im.cy_px.is_finite()) {
        return invalid("the focal lengths must be finite and > 0, the principal point finite");
    }
    if input.tracks.len() < cfg.min_tracks {
        return Err(DtmRejection::TooFewTracks {
            tracks: input.tracks.len(),
            min: cfg.min_tracks,
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests;
