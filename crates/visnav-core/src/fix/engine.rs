//! The fix pipeline (see the module doc of `fix`): rectify, detect, predict, gate, vote, match,
//! resect, convert.
//!
//! Frames used here:
//! * map grid: the reference's CRS, x grid east, y grid north, z up = height AMSL (the DEM's datum).
//!   Used for rectification, prediction and selection (all approximate, prior-driven steps).
//! * `_enu`: a local east-north-up frame (true north, ellipsoidal heights, exact geodesy through
//!   ECEF) about the footprint; the resection runs in it, so neither the projection's scale factor
//!   nor the Earth's curvature biases the fix.
//! * `R_map_cam = Rz(gamma) R_enu_ned R_ned_body R_body_cam`, `gamma` the grid convergence (bearing
//!   of grid north clockwise from true north), as in `sitl::render::RenderPose::from_body`.
//!
//! Matching with a prior, in "level pixels" (map metres / level gsd, y down):
//! 1. each query keypoint's ray (from the prior pose) is cast onto the DEM: its predicted map position;
//! 2. coarse: nearest neighbours within the prior's 3-sigma gate (ratio 0.9) vote for the offset
//!    between prediction and map (a 2-D histogram; the prior's position error and most of its attitude
//!    error are such a common shift);
//! 3. fine: matching again with the predictions shifted by the voted offset, a tight gate and the
//!    ratio test, which is where cross-date matches survive (a raw ratio test over the whole footprint
//!    keeps few correct ones, see docs/surf.md).
//!
//! This file is the orchestrator (the engine, one rectification's match-and-solve, the prior's
//! geometry); each stage has its file: `heading` (the prior's heading, its sweep and the widened
//! search), `features` (the feature correspondences), `area_stage` (the area correlation's tie
//! points and placement), `placement` (the placement fix's pose), `solve` (the resection and the
//! report), `select` (the uniqueness rule over hypotheses), `reloc` (relocalisation without a
//! position prior). General algorithms live with their kind: the 2-D similarity and its RANSAC in
//! `pose::similarity`, the gated matcher and the Hough clustering in `vision::gated`.

use std::sync::Arc;

use nalgebra::{Point2, Rotation3, Vector2, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

mod area_stage;
mod corroborate;
mod features;
mod heading;
mod placement;
mod reloc;
mod select;
mod solve;

use area_stage::AreaOutcome;
use features::*;
use heading::*;
use reloc::*;
use select::*;

use super::rectify::Rectification;
use super::reference::{RefSelection, Reference};
use super::{AttitudePriorNed, FixMethod, FixPrior, FixReport, PositionPriorGeo};
use crate::camera::frames::{r_enu_ned, rot_z};
use crate::camera::{Attitude, Camera};
use crate::fix::{Rejection, Rival};
use crate::geo::geoid::geoid_undulation_m;
use crate::geo::{Crs, Geodetic, LocalFrame};
use crate::pose::similarity::{Sim2, ransac_similarity};
use crate::pose::{
    AttitudePrior, Correspondence, ImageGeometry, PositionPrior, Priors, ResectionConfig, Verdict,
    resect,
};
use crate::validate::{Problems, Validate};
use crate::vision::{
    CpuFeatures, Detector, FeatureBackend, Features, GrayImage, KeyPoint, MatchParams,
};
use crate::vision::{gated_match, hough_cluster};

/// Settings of the fix pipeline (`[fix]`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FixParams {
    /// Keep at most this many query keypoints (strongest, evenly spread).
    pub max_query_features: usize,
    /// Largest side of the rectified image, pixels.
    pub max_rect_side_px: usize,
    /// Rays further than this from the vertical are not rectified, degrees.
    pub max_off_nadir_deg: f64,
    /// Lowe ratio of the fine matching.
    pub ratio: f32,
    /// Gate of the coarse matching in prior standard deviations.
    pub gate_sigmas: f64,
    /// Smallest coarse gate, metres (covers DEM and map registration errors).
    pub min_gate_m: f64,
    /// Radius of the fine gate around the similarity-corrected prediction, level pixels.
    pub fine_radius_px: f64,
    /// The fine ratio test compares with the second-best candidate within this many fine radii.
    pub fine_wide_factor: f64,
    /// Keypoint localisation 1-sigma in rectified pixels (converted to frame pixels for the solve).
    pub sigma_rect_px: f64,
    /// 1-sigma per horizontal axis of the map's registration against the world the camera sees,
    /// in pixels of the orthophoto the map was built from (0 = none; not of an upsampled map's
    /// finer level 0): a shift every fix over that map inherits
    /// whole, however well its keypoints fit, so it is added to the fix's horizontal position
    /// covariance (and the image-only pose's) rather than scaled by sigma0. `visnav map compare`
    /// measures it against another image of the area (docs/map-format.md).
    pub map_registration_sigma_px: f64,
    /// Below this many fine matches the fix is rejected before the solve.
    pub min_matches: usize,
    /// The fine matches must number at least `min_matches + null_factor * chance`, where chance is
    /// the count obtained with the predictions displaced to unrelated places.
    pub null_factor: f64,
    /// Work budget of a global relocalisation (no position prior), millions of work units
    /// (`RELOC_COMPARISONS_PER_UNIT`: one pixel through rectification and SURF, or 16 descriptor
    /// comparisons of the brute-force matching, which cost about the same). Counted, not timed:
    /// the same inputs give the same answer on any machine.
    pub reloc_budget_mwork: f64,
    /// Attitude 1-sigma assumed when the prior gives none, degrees (nadir, any heading is searched).
    pub reloc_tilt_sigma_deg: f64,
    /// Area correlation of the rectified frame with the map's image (`fix::area`) beside the
    /// features: `fallback` (features first, area when they fail), `first`, `only` or `off`.
    pub area_matching: AreaMatching,
    /// When a frame finds no fix at the prior's heading, the heading is searched again with this
    /// sigma (degrees; the sweep covers +-3 sigma) before the frame is given up: after a GPS loss a
    /// compass or a drifted filter can be tens of degrees off while claiming a few
    /// (docs/fix.md, "A heading that is wrong"). 0: never widened.
    pub widen_heading_sigma_deg: f64,
    /// Resection, RANSAC and integrity settings.
    pub pose: ResectionConfig,
}

/// When the area correlation runs (`[fix] area_matching`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AreaMatching {
    /// Features only.
    Off,
    /// Features first; the area correlation when they give no accepted fix.
    Fallback,
    /// The area correlation first; features when it gives no accepted fix.
    First,
    /// The area correlation only.
    Only,
}

impl Default for FixParams {
    fn default() -> Self {
        Self {
            max_query_features: 1500,
            max_rect_side_px: 1024,
            max_off_nadir_deg: 60.0,
            ratio: 0.9,
            gate_sigmas: 3.0,
            min_gate_m: 30.0,
            fine_radius_px: 4.0,
            fine_wide_factor: 3.0,
            sigma_rect_px: 0.7,
            map_registration_sigma_px: 0.0,
            min_matches: 12,
            null_factor: 1.5,
            reloc_budget_mwork: 60.0,
            reloc_tilt_sigma_deg: 5.0,
            area_matching: AreaMatching::Fallback,
            widen_heading_sigma_deg: WIDEN_HEADING_SIGMA_DEG,
            pose: default_pose_config(),
        }
    }
}

/// The heading sigma a failed frame is searched again with, degrees (`widen_heading_sigma_deg`):
/// +-90 deg, the 13 headings of `HEADING_STEP_DEG` around the prior's. A compass near motors
/// and power leads, or a filter's heading drifting without the GPS, errs by tens of degrees;
/// errors beyond 90 deg (a camera mounted backwards) are a configuration fault, not a drift.
pub const WIDEN_HEADING_SIGMA_DEG: f64 = 30.0;

/// Largest horizontal 1-sigma of an accepted fix, metres. A fix more than 50 m off counts as
/// wrong whatever its sigma (`visnav bench fix`'s `wrong_fixes`), so a fix that cannot
/// promise that at one sigma is not offered. Only a resection without any attitude prior gets
/// near it (the position-tilt ambiguity of a narrow view over flat ground: NAIP cross-date at
/// 2000 m, 58-75 m, 76-130 m off); with an attitude prior (tight, tilt only, or a heading 25 deg
/// off) no accepted fix exceeded 28.5 m over 600 bench frames.
pub const MAX_FIX_HORIZONTAL_SIGMA_M: f64 = 50.0;

/// Resection settings of the fix pipeline: the autopilot's attitude is fused (it bounds the
/// position-tilt ambiguity of a narrow field of view over flat ground), and the covariance is
/// inflated by 4 on `max(1, sigma0)` (calibrated on 200 NAIP cross-date frames, see docs/fix.md:
/// cross-date keypoints are displaced by a few pixels in a spatially correlated way that sigma0
/// alone does not capture, and the map itself can be shifted against the world the camera sees).
/// `[fix.pose.refine] sigma0_floor` below 1 lets the covariance follow keypoints better than
/// assumed (same-source imagery: 0.69 -> 0.27 map px on a same-year control with 0.25), but it
/// is not the default: a map's registration shift does not shrink with sigma0, and in the closed
/// loop it made cross-date fixes over-confident (docs/fix.md, "The covariance factor").
/// Fixes up to [`MAX_FIX_HORIZONTAL_SIGMA_M`] horizontal, 80 m vertical and 3 deg (1 sigma) are
/// accepted: the navigation filter weighs them.
pub fn default_pose_config() -> ResectionConfig {
    let mut c = ResectionConfig::default();
    // Cross-date keypoints scatter by 2-3 px; a 3 px consensus admits near-miss wrong matches
    // that bias the pose (NAIP cross-date: 2 px halves the fixes beyond 3 sigma).
    c.ransac.threshold_px = 2.0;
    c.refine.use_attitude_prior = true;
    c.refine.sigma_inflation = 4.0;
    // Per-fix evidence of shared errors (a displaced or changed map area) on top of the floor.
    c.refine.split_variance = true;
    c.integrity.max_horizontal_sigma_m = MAX_FIX_HORIZONTAL_SIGMA_M;
    c.integrity.max_vertical_sigma_m = 80.0;
    c.integrity.max_attitude_sigma_deg = 3.0;
    c
}

impl Validate for FixParams {
    fn validate(&self, p: &mut Problems) {
        if self.max_query_features < 10 {
            p.push("max_query_features", "must be at least 10");
        }
        if self.max_rect_side_px < 64 {
            p.push("max_rect_side_px", "must be at least 64");
        }
        p.range("max_off_nadir_deg", self.max_off_nadir_deg, 1.0, 85.0);
        p.range("ratio", f64::from(self.ratio), 0.1, 1.0);
        p.positive("gate_sigmas", self.gate_sigmas);
        p.positive("min_gate_m", self.min_gate_m);
        p.positive("fine_radius_px", self.fine_radius_px);
        p.range("fine_wide_factor", self.fine_wide_factor, 1.0, 20.0);
        p.positive("sigma_rect_px", self.sigma_rect_px);
        p.range(
            "map_registration_sigma_px",
            self.map_registration_sigma_px,
            0.0,
            20.0,
        );
        if self.min_matches < 4 {
            p.push("min_matches", "must be at least 4");
        }
        p.range("null_factor", self.null_factor, 0.0, 100.0);
        p.positive("reloc_budget_mwork", self.reloc_budget_mwork);
        p.range(
            "reloc_tilt_sigma_deg",
            self.reloc_tilt_sigma_deg,
            0.01,
            45.0,
        );
        p.range(
            "widen_heading_sigma_deg",
            self.widen_heading_sigma_deg,
            0.0,
            180.0,
        );
        p.section("pose", |p| self.pose.validate(p));
    }
}

/// Why an engine could not be built.
#[derive(Debug, thiserror::Error)]
pub enum FixError {
    /// A fix setting is out of range (the first problem found, in words).
    #[error("fix settings: {0}")]
    Config(String),
    /// The reference map has no pyramid levels.
    #[error("the reference map has no levels")]
    EmptyMap,
    /// The map's feature settings cannot build its detector.
    #[error("the map's feature settings: {0}")]
    Detector(crate::vision::VisionError),
}

// Not `#[from]`: that would also make the error its `source()`, and the message already has its
// text (an error chain printed with `{:#}` would say it twice).
impl From<crate::vision::VisionError> for FixError {
    fn from(e: crate::vision::VisionError) -> Self {
        Self::Detector(e)
    }
}

/// The vision fix engine: a reference map, a camera and settings. `fix` takes `&self` and may be
/// called from several threads at once.
pub struct FixEngine {
    reference: Arc<dyn Reference>,
    camera: Camera,
    params: FixParams,
    detector: Arc<dyn Detector>,
    /// Where the query frame's features are computed (default: the CPU).
    features: Arc<dyn FeatureBackend>,
    levels_gsd_m: Vec<f64>,
}

/// Diagnostics of one attempt (for tests and benchmarks).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Attempt {
    /// Map pyramid level matched against (0 the finest).
    pub level: usize,
    /// Frame features kept on valid ground of the rectified frame.
    pub query_features: usize,
    /// Map features selected under the predicted footprint.
    pub map_features: usize,
    /// Coarse (gated nearest-neighbour) matches.
    pub coarse_matches: usize,
    /// Coarse matches that agree with the coarse similarity (its RANSAC consensus).
    pub vote_peak: usize,
    /// Fine matches around the coarse similarity's predictions.
    pub fine_matches: usize,
    /// Matches obtained with the predictions displaced to unrelated places (chance level).
    pub null_matches: usize,
    /// The fine matches: frame pixel (distorted) and map point (grid x, y, height AMSL).
    pub pairs: Vec<([f64; 2], [f64; 3])>,
    /// Area correlation: the placement's peak NCC, also when it was too weak or not unique
    /// (0 when not run).
    pub area_ncc: f64,
    /// Area correlation: the best other place's NCC (0 when not run).
    pub area_runner_up: f64,
    /// Area correlation: tie points found.
    pub area_ties: usize,
    /// Area correlation: tie points found with the predictions displaced (chance level).
    pub area_null_ties: usize,
    /// The accepted fix is a feature fix the split-sample factor could not check and the area
    /// method, asked to corroborate it, found no fix to hold it against (docs/fix.md,
    /// "Integrity", *Corroboration*).
    pub uncorroborated: bool,
}

impl Attempt {
    /// Fine matches above the chance level measured for this attempt (the a-contrario count):
    /// what a hypothesis has that an unrelated place would not; for an area correlation, its
    /// tie points above their own chance level. The larger of the two when both ran.
    pub fn evidence(&self) -> usize {
        self.fine_matches
            .saturating_sub(self.null_matches)
            .max(self.area_ties.saturating_sub(self.area_null_ties))
    }
}

/// The prior in the map grid and in the local ENU frame.
struct PriorGeom {
    c_map: Vector3<f64>,
    /// Camera attitude the frame is rectified with (a heading hypothesis during a sweep).
    r_map_cam: Rotation3<f64>,
    sigma_h_m: f64,
    sigma_v_m: f64,
    /// Tilt (about north/east) and heading sigmas, rad.
    sigma_tilt_rad: f64,
    sigma_yaw_rad: f64,
    /// The attitude is the navigation filter's own (FixPrior::attitude_from_filter).
    att_from_filter: bool,
    /// The attitude prior the resection fuses: the caller's (its heading sigma may be large),
    /// not the heading hypothesis the frame was rectified with; None: no attitude prior.
    solve: Option<SolvePrior>,
}

/// How one rectification is matched ([`FixEngine::fix_single`]).
#[derive(Debug, Clone, Copy)]
struct Single {
    /// The attitude prior is the navigation filter's own.
    att_from_filter: bool,
    /// The features run.
    features: bool,
    /// The area correlation may run (as `[fix] area_matching` says; alone when `features` is
    /// false).
    area: bool,
    /// A unique area placement without enough tie points may still give a fix (the placement
    /// fix; a search that allows it must weigh it by its correlation, [`placement_unique`], as
    /// it has no tie points).
    placement: bool,
    /// A feature fix the split-sample factor could not check is put to the area correlation
    /// (`corroborate`): the attempt at the prior as stated. A search's hypotheses are weighed
    /// against each other by their own rules instead.
    corroborate: bool,
}

impl Single {
    /// Features only, an independent attitude prior (searches).
    const FEATURES: Self = Self {
        att_from_filter: false,
        features: true,
        area: false,
        placement: false,
        corroborate: false,
    };
}

/// One attempt's plan, what every stage that re-enters [`FixEngine::fix_single`] passes on:
/// the attitude the frame is rectified at (and the coarse gate assumes), the attitude prior the
/// resection fuses (None: none) and the methods that may run.
#[derive(Debug, Clone, Copy)]
struct Plan<'a> {
    rect: &'a AttitudePriorNed,
    solve: Option<&'a AttitudePriorNed>,
    how: Single,
}

impl<'a> Plan<'a> {
    /// Rectified at `rect`, `solve` fused, the methods of `how`.
    fn new(rect: &'a AttitudePriorNed, solve: Option<&'a AttitudePriorNed>, how: Single) -> Self {
        Self { rect, solve, how }
    }
    /// The same plan rectified at `rect` instead.
    fn at(self, rect: &'a AttitudePriorNed) -> Self {
        Self { rect, ..self }
    }
}

/// One rectified view of a frame, as the correspondence stages see it.
struct View<'a> {
    rect: &'a Rectification,
    g: &'a PriorGeom,
    level: usize,
    agl_m: f64,
    /// Rectified pixels per frame pixel.
    scale: f64,
}

/// A correspondence before the resection: frame pixel (distorted), map point (grid x, y,
/// height AMSL) and the localisation sigma in frame pixels.
struct Pair {
    frame_px: Point2<f64>,
    map: [f64; 3],
    sigma_px: f64,
}

/// Rays are cast at most this many times the height above ground (a ray that grazes the terrain
/// further away is not a usable prediction).
const MAX_RAY_RANGE_AGL: f64 = 20.0;

/// An attitude prior for the resection (world = local ENU).
#[derive(Debug, Clone, Copy)]
struct SolvePrior {
    r_enu_cam: Rotation3<f64>,
    sigma_tilt_rad: f64,
    sigma_yaw_rad: f64,
}

impl FixEngine {
    /// An engine over `reference`; the query SURF uses the map's settings (upright recommended).
    pub fn new(
        reference: Arc<dyn Reference>,
        camera: Camera,
        params: FixParams,
    ) -> Result<Self, FixError> {
        let mut problems = Problems::default();
        params.validate(&mut problems);
        if let Some(first) = problems.list.first() {
            return Err(FixError::Config(first.to_string()));
        }
        let levels_gsd_m = reference.level_gsd_m();
        if levels_gsd_m.is_empty() {
            return Err(FixError::EmptyMap);
        }
        let detector = reference
            .feature_spec()
            .with_max_features(None)
            .detector()?;
        Ok(Self {
            reference,
            camera,
            params,
            detector,
            features: Arc::new(CpuFeatures),
            levels_gsd_m,
        })
    }

    /// Compute the query frames' features with `backend` (the GPU path) instead of the CPU; the
    /// SURF parameters stay the map's.
    pub fn set_feature_backend(&mut self, backend: Arc<dyn FeatureBackend>) {
        self.features = backend;
    }

    /// Where the query frames' features are computed.
    pub fn feature_backend(&self) -> &Arc<dyn FeatureBackend> {
        &self.features
    }

    /// The settings.
    pub fn params(&self) -> &FixParams {
        &self.params
    }
    /// The camera.
    pub fn camera(&self) -> &Camera {
        &self.camera
    }
    /// The reference.
    pub fn reference(&self) -> &Arc<dyn Reference> {
        &self.reference
    }

    /// One fix. With a position prior: the prior-driven pipeline; without: global relocalisation.
    pub fn fix(&self, frame: &GrayImage, prior: &FixPrior) -> FixReport {
        self.fix_with_attempt(frame, prior).0
    }

    /// [`Self::fix`] with diagnostics.
    pub fn fix_with_attempt(&self, frame: &GrayImage, prior: &FixPrior) -> (FixReport, Attempt) {
        if frame.width() != self.camera.width_px() as usize
            || frame.height() != self.camera.height_px() as usize
        {
            let reason = Rejection::FrameSize {
                frame: [frame.width(), frame.height()],
                camera: [self.camera.width_px(), self.camera.height_px()],
            };
            return (
                FixReport::rejected(reason, prior.t_capture_us, 0.0),
                Attempt::default(),
            );
        }
        match prior.position {
            Some(pos) => {
                let (r, a) = match prior.attitude {
                    Some(att) => {
                        let (mut r, a) = self.fix_prior(
                            frame,
                            &pos,
                            &att,
                            prior.t_capture_us,
                            prior.attitude_from_filter,
                            prior.widen_heading,
                        );
                        r.prior_attitude_from_filter = prior.attitude_from_filter;
                        (r, a)
                    }
                    None => self.fix_any_heading(frame, &pos, prior.t_capture_us),
                };
                (r, a)
            }
            None => self.relocalise(frame, prior),
        }
    }

    fn prior_geom(
        &self,
        pos: &PositionPriorGeo,
        att: &AttitudePriorNed,
    ) -> Result<PriorGeom, Rejection> {
        let crs: Crs = self.reference.crs();
        let (x, y) = crs
            .from_geodetic(pos.lat_deg, pos.lon_deg)
            .map_err(geodesy("prior position"))?;
        let gamma = crs
            .grid_convergence_deg(pos.lat_deg, pos.lon_deg)
            .map_err(geodesy("prior position"))?
            .to_radians();
        let r_ned_cam = self.camera.mount.r_ned_cam(&att.attitude);
        let r_enu_cam = r_enu_ned() * r_ned_cam;
        let ok = |v: f64| v.is_finite() && v > 0.0;
        if !(ok(pos.sigma_h_m)
            && ok(pos.sigma_v_m)
            && ok(att.sigma_rad)
            && ok(att.sigma_yaw_rad)
            && pos.alt_amsl_m.is_finite())
        {
            return Err(Rejection::PriorSigmas);
        }
        Ok(PriorGeom {
            c_map: Vector3::new(x, y, pos.alt_amsl_m),
            r_map_cam: rot_z(gamma) * r_enu_cam,
            sigma_h_m: pos.sigma_h_m,
            sigma_v_m: pos.sigma_v_m,
            sigma_tilt_rad: att.sigma_rad,
            sigma_yaw_rad: att.sigma_yaw_rad,
            att_from_filter: false,
            solve: None,
        })
    }

    /// Ground height below the camera's principal ray (or straight below, or the DEM's middle).
    fn ground_below(&self, g: &PriorGeom) -> f64 {
        let dem = self.reference.dem();
        let axis = g.r_map_cam * Vector3::z();
        let o = [g.c_map.x, g.c_map.y, g.c_map.z];
        if let Some(p) = dem.intersect_ray(o, [axis.x, axis.y, axis.z], 1e6) {
            return p[2];
        }
        if let Some(h) = dem.height_at(g.c_map.x, g.c_map.y) {
            return h;
        }
        let (lo, hi) = dem.height_range_m();
        0.5 * (lo + hi)
    }

    /// The level whose gsd is the smallest not finer than 0.8 x the camera's nadir gsd.
    fn pick_level(&self, cam_gsd_m: f64) -> usize {
        self.levels_gsd_m
            .iter()
            .position(|&g| g >= 0.8 * cam_gsd_m)
            .unwrap_or(self.levels_gsd_m.len() - 1)
    }

    /// One rectification at `plan.rect` (the attitude the frame is resampled with and the
    /// coarse gate assumes), the resection fusing `plan.solve` (None: no attitude prior), with
    /// the methods `plan.how` names: a heading sweep runs features at every hypothesis first and
    /// the area correlation alone only when none matched; the feature relocalisation uses
    /// features only.
    fn fix_single(
        &self,
        frame: &GrayImage,
        pos: &PositionPriorGeo,
        plan: Plan,
        t_us: u64,
    ) -> (FixReport, Attempt) {
        let Plan { rect, solve, how } = plan;
        let rej = |reason: Rejection, a: Attempt| (FixReport::rejected(reason, t_us, 0.0), a);
        let solve = match solve.map(|s| self.solve_prior(s)) {
            None => None,
            Some(Ok(s)) => Some(s),
            Some(Err(e)) => return rej(e, Attempt::default()),
        };
        let g = match self.prior_geom(pos, rect) {
            Ok(g) => PriorGeom {
                att_from_filter: how.att_from_filter,
                solve,
                ..g
            },
            Err(e) => return rej(e, Attempt::default()),
        };
        let agl_m = g.c_map.z - self.ground_below(&g);
        if agl_m.is_nan() || agl_m <= 1.0 {
            return rej(
                Rejection::PriorBelowTerrain {
                    alt_amsl_m: g.c_map.z,
                },
                Attempt::default(),
            );
        }
        let cam_gsd_m = agl_m / self.camera.intrinsics.fx_px;
        let level = self.pick_level(cam_gsd_m);
        self.match_and_solve(frame, &g, level, agl_m, t_us, how)
    }

    /// Rectify at `level`, find correspondences (features, or the map image's area correlation
    /// as `[fix] area_matching` says) and resect.
    fn match_and_solve(
        &self,
        frame: &GrayImage,
        g: &PriorGeom,
        level: usize,
        agl_m: f64,
        t_us: u64,
        how: Single,
    ) -> (FixReport, Attempt) {
        let mut a = Attempt {
            level,
            ..Attempt::default()
        };
        let rej = |reason: Rejection, a: Attempt| (FixReport::rejected(reason, t_us, 0.0), a);
        let gsd = self.levels_gsd_m[level];
        let scale = agl_m / gsd / self.camera.intrinsics.fx_px;
        let Some(rect) = Rectification::new(
            frame,
            &self.camera,
            &g.r_map_cam,
            scale,
            self.params.max_rect_side_px,
            self.params.max_off_nadir_deg.to_radians(),
        ) else {
            return rej(Rejection::NoGround, a);
        };
        let view = View {
            rect: &rect,
            g,
            level,
            agl_m,
            scale,
        };
        // The methods in the order `[fix] area_matching` tries them; the first accepted wins.
        // `only` measures the area correlation alone: a pass that asks for features only (a
        // sweep's feature hypotheses, a candidate's confirmation) finds nothing there.
        let order: &[FixMethod] = match (how.features, how.area, self.params.area_matching) {
            (false, false, _)
            | (false, true, AreaMatching::Off)
            | (_, false, AreaMatching::Only) => {
                return rej(Rejection::NoMethod, a);
            }
            (_, true, AreaMatching::Only) | (false, true, _) => &[FixMethod::Area],
            (_, false, _) | (_, true, AreaMatching::Off) => &[FixMethod::Features],
            (true, true, AreaMatching::Fallback) => &[FixMethod::Features, FixMethod::Area],
            (true, true, AreaMatching::First) => &[FixMethod::Area, FixMethod::Features],
        };
        let mut tried = Vec::new();
        let mut report = None;
        for &method in order {
            let r = self.run_method(&view, &mut a, method, how, t_us);
            if r.accepted {
                report = Some(r);
                break;
            }
            tried.push((method, Rejection::or_unexplained(r.rejection)));
        }
        // A feature fix the split-sample factor could not check is put to the area method
        // when it would run after features anyway (`corroborate`), at the prior as stated.
        if how.corroborate
            && order == [FixMethod::Features, FixMethod::Area]
            && let Some(feature_fix) = report.take_if(|r| corroborate::unchecked(r))
        {
            report = Some(self.corroborate(&view, &mut a, feature_fix, how, t_us));
        }
        let report = report.unwrap_or_else(|| {
            let why = if tried.len() == 1 {
                tried.remove(0).1
            } else {
                Rejection::Methods(tried)
            };
            FixReport::rejected(why, t_us, 0.0)
        });
        (FixReport { level, ..report }, a)
    }

    /// One method's correspondences and its fix (or the reason there is none).
    fn run_method(
        &self,
        view: &View,
        a: &mut Attempt,
        method: FixMethod,
        how: Single,
        t_us: u64,
    ) -> FixReport {
        match method {
            FixMethod::Features => match self.feature_pairs(view, a) {
                Ok(p) => self.solve_pairs(view, &p, method, t_us),
                Err(e) => FixReport::rejected(e, t_us, 0.0),
            },
            _ => match self.area_pairs(view, a, how.placement) {
                Ok(AreaOutcome::Ties(p)) => self.solve_pairs(view, &p, FixMethod::Area, t_us),
                Ok(AreaOutcome::Placement(p)) => self.placement_report(view, &p, t_us),
                Err(e) => FixReport::rejected(e, t_us, 0.0),
            },
        }
    }

    /// Map position (grid x, y) of the ground seen at rectified pixel `(u, v)` from the prior.
    fn ground_of(&self, v: &View, u: f64, vv: f64) -> Option<[f64; 2]> {
        let ray = v.rect.ray_map(u, vv);
        let c = v.g.c_map;
        self.reference
            .dem()
            .intersect_ray(
                [c.x, c.y, c.z],
                [ray.x, ray.y, ray.z],
                MAX_RAY_RANGE_AGL * v.agl_m.max(100.0),
            )
            .map(|p| [p[0], p[1]])
    }

    /// A correspondence's localisation sigma in frame pixels before its scale: the rectified
    /// sigma, magnified when the frame is finer than the level.
    fn base_sigma_px(&self, v: &View) -> f64 {
        (self.params.sigma_rect_px / v.scale).max(0.5)
    }
}

/// Angle of the body's z axis from the vertical, radians.
fn tilt_of(a: &Attitude) -> f64 {
    (a.r_ned_body() * Vector3::z()).z.clamp(-1.0, 1.0).acos()
}

fn wrap_pi(a: f64) -> f64 {
    let t = std::f64::consts::TAU;
    let w = a - t * (a / t).round();
    if w <= -std::f64::consts::PI { w + t } else { w }
}

/// `map_err` helper: a geodesy error at `stage`.
fn geodesy(stage: &'static str) -> impl Fn(crate::geo::GeoError) -> Rejection {
    move |e| Rejection::Geodesy {
        stage,
        detail: e.to_string(),
    }
}

/// `map_err` helper: an internal step's error at `stage`.
fn internal<E: std::fmt::Display>(stage: &'static str) -> impl Fn(E) -> Rejection {
    move |e| Rejection::Internal {
        stage,
        detail: e.to_string(),
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// An engine over a 1.28 km checkerboard ortho (5 m pixels, UTM 14N, easting 500 000,
    /// northing 5 200 000 at its top left) on flat ground at 300 m, with a 320 x 240 camera of
    /// 60 deg field of view.
    pub(crate) fn checkerboard_engine() -> (FixEngine, Crs) {
        use crate::fix::reference::MemoryReference;
        use crate::geo::raster::{GeoTransform, Raster, RasterData};
        let (w, h) = (256usize, 256usize);
        let data: Vec<u8> = (0..w * h)
            .map(|i| (((i % w) / 8 + (i / w) / 8) % 2 * 200 + 20) as u8)
            .collect();
        let gt = GeoTransform::north_up(500_000.0, 5_200_000.0, 5.0, 5.0).unwrap();
        let crs = Crs::Utm {
            zone: 14,
            north: true,
        };
        let raster = Raster::new(w, h, 1, RasterData::U8(data), gt, crs, None).unwrap();
        let surf = crate::vision::SurfParams {
            upright: true,
            ..Default::default()
        };
        let dem = crate::geo::dem::Dem::flat(300.0).unwrap();
        let reference = MemoryReference::from_raster(&raster, dem, surf, 2).unwrap();
        let camera = Camera::pinhole(
            crate::camera::Intrinsics::from_hfov(60f64.to_radians(), 320, 240).unwrap(),
        )
        .unwrap();
        let engine = FixEngine::new(Arc::new(reference), camera, FixParams::default()).unwrap();
        (engine, crs)
    }

    #[test]
    fn bad_frames_and_priors_are_rejected_with_a_reason() {
        let (engine, crs) = checkerboard_engine();
        let (lat, lon) = crs.to_geodetic(500_640.0, 5_199_360.0).unwrap();
        let att = Some(AttitudePriorNed::isotropic(
            Attitude::new(0.0, 0.0, 0.0),
            0.01,
        ));
        let pos = |alt: f64, s: f64| {
            Some(PositionPriorGeo {
                lat_deg: lat,
                lon_deg: lon,
                alt_amsl_m: alt,
                sigma_h_m: s,
                sigma_v_m: s,
            })
        };
        // Wrong frame size.
        let small = GrayImage::from_fn(100, 100, |_, _| 0.0);
        let r = engine.fix(
            &small,
            &FixPrior {
                t_capture_us: 7,
                position: pos(1300.0, 50.0),
                attitude: att,
                altitude: None,
                attitude_from_filter: false,
                widen_heading: true,
            },
        );
        assert!(
            matches!(
                r.rejection,
                Some(Rejection::FrameSize {
                    frame: [100, 100],
                    ..
                })
            ),
            "{}",
            r.reason()
        );
        assert_eq!(r.t_capture_us, 7);
        let frame = GrayImage::from_fn(320, 240, |x, y| ((x / 8 + y / 8) % 2 * 200) as f32);
        // Prior below the terrain, non-finite prior, zero sigma: rejected, never a panic.
        for (p, what) in [
            (pos(100.0, 50.0), "terrain"),
            (pos(f64::NAN, 50.0), ""),
            (pos(1300.0, 0.0), "sigma"),
        ] {
            let r = engine.fix(
                &frame,
                &FixPrior {
                    t_capture_us: 1,
                    position: p,
                    attitude: att,
                    altitude: None,
                    attitude_from_filter: false,
                    widen_heading: true,
                },
            );
            assert!(!r.accepted, "{what}");
            assert!(r.reason().contains(what), "{what}: {}", r.reason());
            assert!(r.lat_deg.is_nan());
        }
        // A blank frame: no features.
        let blank = GrayImage::from_fn(320, 240, |_, _| 90.0);
        let r = engine.fix(
            &blank,
            &FixPrior {
                t_capture_us: 1,
                position: pos(1300.0, 50.0),
                attitude: att,
                altitude: None,
                attitude_from_filter: false,
                widen_heading: true,
            },
        );
        assert_eq!(r.class(), "few_features", "{}", r.reason());
    }

    #[test]
    fn params_validate() {
        let mut p = Problems::default();
        FixParams::default().validate(&mut p);
        assert!(p.list.is_empty(), "{:?}", p.list);
        let bad = FixParams {
            ratio: 0.0,
            ..FixParams::default()
        };
        let mut p = Problems::default();
        bad.validate(&mut p);
        assert!(p.list.iter().any(|i| i.key == "ratio"), "{:?}", p.list);
    }
}
