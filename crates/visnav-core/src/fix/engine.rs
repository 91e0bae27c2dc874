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

use std::sync::Arc;

use nalgebra::{Point2, Rotation3, Vector2, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

mod area_stage;
mod placement;

use area_stage::AreaOutcome;

use super::rectify::Rectification;
use super::reference::{RefSelection, Reference};
use super::{AttitudePriorNed, FixMethod, FixPrior, FixReport, PositionPriorGeo};
use crate::camera::frames::{r_enu_ned, rot_z};
use crate::camera::{Attitude, Camera};
use crate::fix::{Rejection, Rival};
use crate::geo::geoid::geoid_undulation_m;
use crate::geo::{Crs, Geodetic, LocalFrame};
use crate::pose::{
    AttitudePrior, Correspondence, ImageGeometry, PositionPrior, Priors, ResectionConfig, Verdict,
    resect,
};
use crate::validate::{Problems, Validate};
use crate::vision::matcher::dist2;
use crate::vision::{
    CpuFeatures, FeatureBackend, Features, GrayImage, KeyPoint, MatchParams, Surf,
};

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
    /// ([`RELOC_COMPARISONS_PER_UNIT`]: one pixel through rectification and SURF, or 16 descriptor
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
/// +-90 deg, the 13 headings of [`HEADING_STEP_DEG`] around the prior's. A compass near motors
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
    #[error("fix settings: {0}")]
    Config(String),
    #[error("the reference map has no levels")]
    EmptyMap,
    #[error("SURF settings of the map: {0}")]
    Surf(crate::vision::VisionError),
}

// Not `#[from]`: that would also make the error its `source()`, and the message already has its
// text (an error chain printed with `{:#}` would say it twice).
impl From<crate::vision::VisionError> for FixError {
    fn from(e: crate::vision::VisionError) -> Self {
        Self::Surf(e)
    }
}

/// The vision fix engine: a reference map, a camera and settings. `fix` takes `&self` and may be
/// called from several threads at once.
pub struct FixEngine {
    reference: Arc<dyn Reference>,
    camera: Camera,
    params: FixParams,
    surf: Surf,
    /// Where the query frame's features are computed (default: the CPU).
    features: Arc<dyn FeatureBackend>,
    levels_gsd_m: Vec<f64>,
}

/// Diagnostics of one attempt (for tests and benchmarks).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Attempt {
    pub level: usize,
    pub query_features: usize,
    pub map_features: usize,
    pub coarse_matches: usize,
    pub vote_peak: usize,
    pub fine_matches: usize,
    /// Matches obtained with the predictions displaced to unrelated places (chance level).
    pub null_matches: usize,
    /// The fine matches: frame pixel (distorted) and map point (grid x, y, height AMSL).
    pub pairs: Vec<([f64; 2], [f64; 3])>,
    /// Area correlation: the placement's peak, also when it was too weak or not unique, and
    /// the best other place (0 when not run).
    pub area_ncc: f64,
    pub area_runner_up: f64,
    /// Area correlation: tie points found.
    pub area_ties: usize,
    /// Area correlation: tie points found with the predictions displaced (chance level).
    pub area_null_ties: usize,
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
}

impl Single {
    /// Features only, an independent attitude prior (searches).
    const FEATURES: Self = Self {
        att_from_filter: false,
        features: true,
        area: false,
        placement: false,
    };
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
        let mut sp = reference.surf_params();
        sp.max_features = None;
        let surf = Surf::new(sp)?;
        Ok(Self {
            reference,
            camera,
            params,
            surf,
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

    /// A position prior without attitude: near-nadir views at [`HEADINGS`] headings (upright
    /// SURF degrades quickly beyond about +-10 deg), no attitude prior in the resection; the
    /// unique best hypothesis wins ([`select_unique`]).
    fn fix_any_heading(
        &self,
        frame: &GrayImage,
        pos: &PositionPriorGeo,
        t_us: u64,
    ) -> (FixReport, Attempt) {
        self.fix_heading_sweep(frame, pos, &self.nadir_any_heading(), None, t_us, false)
    }

    /// A heading sigma too large for one rectification ([`YAW_SWEEP_ABOVE_DEG`]): the frame is
    /// rectified at heading hypotheses [`HEADING_STEP_DEG`] apart over the prior's +-3 sigma
    /// (tilt kept: roll and pitch come from gravity), each matched and solved with the caller's
    /// prior (its loose heading; `solve`, None for no attitude prior), and the unique best
    /// hypothesis wins ([`select_unique`]). With none accepted, the same by area correlation
    /// alone (unless `[fix] area_matching = "off"`). The winner is redone at its own heading
    /// ([`Self::refine_sweep_fix`]).
    fn fix_heading_sweep(
        &self,
        frame: &GrayImage,
        pos: &PositionPriorGeo,
        att: &AttitudePriorNed,
        solve: Option<&AttitudePriorNed>,
        t_us: u64,
        att_from_filter: bool,
    ) -> (FixReport, Attempt) {
        let hyps = heading_hypotheses(att);
        let sweep = |how: Single| -> Vec<Hypothesis> {
            hyps.iter()
                .map(|hyp| {
                    let (r, a) = self.fix_single(frame, pos, hyp, solve, t_us, how);
                    Hypothesis::new(hyp.attitude.yaw_rad, r, a)
                })
                .collect()
        };
        let features = Single {
            att_from_filter,
            features: true,
            area: false,
            placement: false,
        };
        let (r, a) = select_unique(sweep(features), t_us);
        if r.accepted {
            return self.refine_sweep_fix(frame, pos, att, solve, t_us, features, r, a);
        }
        // Without an attitude prior an area fix has the features' position-tilt ambiguity and
        // fails the sigma limit as theirs do (NAIP: 0 of 3 frames, 1.7 s each): not tried.
        if self.params.area_matching == AreaMatching::Off || solve.is_none() {
            return (r, a);
        }
        // No heading matched by features: the area correlation at every heading (its placement
        // covers +-3 hypothesis sigmas of rotation, more than half a step), with the same
        // uniqueness rule.
        let area = Single {
            att_from_filter,
            features: false,
            area: true,
            placement: true,
        };
        let (r2, a2) = select_unique(sweep(area), t_us);
        if !r2.accepted {
            let mut r = r;
            r.rejection = Some(Rejection::Methods(vec![
                (FixMethod::Features, rejection_of(r.rejection.take())),
                (FixMethod::Area, rejection_of(r2.rejection)),
            ]));
            return (r, a);
        }
        self.refine_sweep_fix(frame, pos, att, solve, t_us, area, r2, a2)
    }

    /// The sweep's fix `r` again, rectified at its own heading: a hypothesis is up to half a
    /// [`HEADING_STEP_DEG`] from the true heading, which costs upright SURF matches and lets a
    /// few chance matches into a weak consensus. The caller's attitude prior is kept for the
    /// resection (the heading found is the image's, not a prior). The second fix replaces the
    /// first when it is at the same place; at another place the answer is ambiguous; when it
    /// is rejected the first stands (the sweep's uniqueness test passed). NAIP cross-date with
    /// a 25 deg heading error: the one fix 54 m off (tilt 1.3 deg) becomes 48 m max, p90 30.7 ->
    /// 27.8 m, same acceptance (docs/fix.md).
    #[allow(clippy::too_many_arguments)]
    fn refine_sweep_fix(
        &self,
        frame: &GrayImage,
        pos: &PositionPriorGeo,
        att: &AttitudePriorNed,
        solve: Option<&AttitudePriorNed>,
        t_us: u64,
        how: Single,
        r: FixReport,
        a: Attempt,
    ) -> (FixReport, Attempt) {
        let rect = at_own_heading(att, &r);
        let (r2, a2) = self.fix_single(frame, pos, &rect, solve, t_us, how);
        if !r2.accepted {
            return (r, a);
        }
        let d = (r2.x_m - r.x_m).hypot(r2.y_m - r.y_m);
        if d > SAME_PLACE_SIGMAS * sigma_h_m(&r2).hypot(sigma_h_m(&r)) {
            let mut rej =
                FixReport::rejected(Rejection::MovesAtOwnHeading { moved_m: d }, t_us, 0.0);
            rej.matches = r.matches;
            rej.level = r.level;
            return (rej, a);
        }
        (r2, a2)
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

    /// The prior-driven fix: one rectification at the prior attitude, or a heading sweep when
    /// the prior's heading sigma is larger than one rectification tolerates. When that finds no
    /// fix and the caller asks for it (`widen`, [`FixPrior::widen_heading`]), the heading is
    /// searched wider ([`Self::widened_heading`]) and then the area search runs over the prior's
    /// window ([`Self::area_search_near`]) before the frame is given up.
    fn fix_prior(
        &self,
        frame: &GrayImage,
        pos: &PositionPriorGeo,
        att: &AttitudePriorNed,
        t_us: u64,
        att_from_filter: bool,
        widen: bool,
    ) -> (FixReport, Attempt) {
        let (r, a) = self.fix_prior_as_stated(frame, pos, att, t_us, att_from_filter);
        if r.accepted || !widen {
            return (r, a);
        }
        let mut why = WidenedWhy {
            stated: rejection_of(r.rejection),
            heading: None,
            near: None,
        };
        let wide = self.widened_heading(att);
        if let Some(wide) = &wide {
            let (r2, a2) =
                self.fix_heading_sweep(frame, pos, wide, Some(wide), t_us, att_from_filter);
            let verdict = if r2.accepted {
                self.confirm_widened(wide, (&r2, &a2))
            } else {
                Err(rejection_of(r2.rejection.clone()))
            };
            match verdict {
                Ok(()) => return (r2, a2),
                Err(e) => why.heading = Some((3.0 * wide.sigma_yaw_rad.to_degrees(), e)),
            }
        }
        let searched = wide.as_ref().unwrap_or(att);
        let near = self.area_search_near(frame, pos, searched, t_us);
        match near {
            // Its candidates are confirmed by features over many places and headings: the
            // widened chance bar applies to them too.
            Ok((r3, a3)) if r3.accepted => {
                match (r3.method == FixMethod::Features)
                    .then(|| self.widened_chance_bar(searched, &a3))
                {
                    None | Some(Ok(())) => return (r3, a3),
                    Some(Err(e)) => why.near = Some(e),
                }
            }
            Ok((r3, _)) => why.near = Some(rejection_of(r3.rejection)),
            Err(AreaRelocError::NotFound(e)) => why.near = Some(e),
            // It could not run (an old map, no level images, the budget): nothing to add.
            Err(AreaRelocError::CannotRun(e)) => {
                tracing::debug!("area search of the prior's window: {e}");
            }
        }
        let mut r = FixReport::rejected(why.into_rejection(), t_us, 0.0);
        r.prior_attitude_from_filter = att_from_filter;
        (r, a)
    }

    /// A fix the widened heading search found by features must beat the features' chance bar
    /// raised for the number of headings asked: the widened search runs the chance test at a
    /// dozen headings after the stated one failed, so chance gets that many tries. The most
    /// matches chance gives at any of H headings, each about Poisson with the mean `null` the
    /// a-contrario count measured, lies near `null + sqrt(2 null ln H)` (the maximum of H such
    /// draws), so that margin is added to the bar a single rectification uses (NAIP at
    /// 1200-1600 m: a fix 52 m off with 34 matches where chance gives 14 and the bar is 33).
    /// Area and placement fixes carry their own uniqueness rule and pass as they are.
    ///
    /// No area correlation is asked on top: over 400 NAIP cross-date frames with the heading
    /// 30 deg off it refused 15 correct fixes (its peak stays under 0.3 where the fields
    /// changed between the years) and not one wrong fix the raised bar let through; frames of
    /// other ground are refused by the bar alone (`tests/fix_naip.rs`).
    fn confirm_widened(
        &self,
        wide: &AttitudePriorNed,
        (r, a): (&FixReport, &Attempt),
    ) -> Result<(), Rejection> {
        if r.method != FixMethod::Features {
            return Ok(());
        }
        self.widened_chance_bar(wide, a)
    }

    /// The features' chance bar raised for a search over the widened heading's hypotheses
    /// ([`Self::confirm_widened`]): `Err` names the count when `a`'s matches fall short of it.
    fn widened_chance_bar(&self, wide: &AttitudePriorNed, a: &Attempt) -> Result<(), Rejection> {
        let headings = heading_hypotheses(wide).len().max(1);
        let null = a.null_matches as f64;
        let needed = self.params.min_matches
            + (self.params.null_factor * null).ceil() as usize
            + (2.0 * null * (headings as f64).ln()).sqrt().ceil() as usize;
        if a.fine_matches < needed {
            return Err(Rejection::BelowWidenedChance {
                matches: a.fine_matches,
                chance: a.null_matches,
                headings,
                needed,
            });
        }
        Ok(())
    }

    /// The area search (as relocalisation runs it without a position prior) restricted to the
    /// window the position prior allows: its +-3 sigma gate grown by the footprint's reach, the
    /// candidates' camera positions within the gate. So a position prior never makes a frame fail
    /// that the search without one would fix there; the search is also far cheaper than over the
    /// whole map. The altitude is the prior's.
    fn area_search_near(
        &self,
        frame: &GrayImage,
        pos: &PositionPriorGeo,
        att: &AttitudePriorNed,
        t_us: u64,
    ) -> Result<(FixReport, Attempt), AreaRelocError> {
        if self.params.area_matching == AreaMatching::Off {
            return Err(AreaRelocError::CannotRun(Rejection::AreaOff));
        }
        let g = self
            .prior_geom(pos, att)
            .map_err(AreaRelocError::CannotRun)?;
        let agl_m = g.c_map.z - self.ground_below(&g);
        if !(agl_m.is_finite() && agl_m > 1.0) {
            return Err(AreaRelocError::CannotRun(Rejection::PriorBelowTerrain {
                alt_amsl_m: g.c_map.z,
            }));
        }
        let k = &self.camera.intrinsics;
        let half_diag_rad = (0.5 * f64::from(k.width_px))
            .hypot(0.5 * f64::from(k.height_px))
            .atan2(k.fx_px.min(k.fy_px));
        let off_nadir = (half_diag_rad + 3.0 * att.sigma_rad + tilt_of(&att.attitude))
            .min(self.params.max_off_nadir_deg.to_radians());
        let gate_m = self.params.gate_sigmas * pos.sigma_h_m;
        let reach_m = gate_m + agl_m * off_nadir.tan();
        let window = SearchWindow {
            rect_m: [
                g.c_map.x - reach_m,
                g.c_map.y - reach_m,
                g.c_map.x + reach_m,
                g.c_map.y + reach_m,
            ],
            centre_m: [g.c_map.x, g.c_map.y],
            max_distance_m: gate_m,
        };
        let alt = super::AltitudePrior {
            alt_amsl_m: pos.alt_amsl_m,
            sigma_m: pos.sigma_v_m,
        };
        let mut work = 0u64;
        let (r, a) = self.relocalise_area(frame, &alt, att, t_us, &mut work, Some(&window))?;
        if !r.accepted {
            return Ok((r, a));
        }
        // The window bounds the candidates; the verified fix must still agree with the prior.
        let d = (r.x_m - g.c_map.x).hypot(r.y_m - g.c_map.y);
        let limit = self.params.gate_sigmas * pos.sigma_h_m.hypot(sigma_h_m(&r));
        if d > limit {
            return Err(AreaRelocError::NotFound(Rejection::FarFromPrior {
                distance_m: d,
                limit_m: limit,
            }));
        }
        Ok((r, a))
    }

    /// [`Self::fix_prior`] at the prior's heading sigma as stated.
    fn fix_prior_as_stated(
        &self,
        frame: &GrayImage,
        pos: &PositionPriorGeo,
        att: &AttitudePriorNed,
        t_us: u64,
        att_from_filter: bool,
    ) -> (FixReport, Attempt) {
        if att.sigma_yaw_rad > YAW_SWEEP_ABOVE_DEG.to_radians() {
            self.fix_heading_sweep(frame, pos, att, Some(att), t_us, att_from_filter)
        } else {
            self.fix_single(
                frame,
                pos,
                att,
                Some(att),
                t_us,
                Single {
                    att_from_filter,
                    features: true,
                    area: true,
                    placement: true,
                },
            )
        }
    }

    /// The prior with its heading sigma widened to `[fix] widen_heading_sigma_deg` (tilt kept:
    /// gravity fixes it), or None when that is not wider than the prior's own. The widened
    /// heading also enters the resection: the heading a fix reports then comes from the image,
    /// not from the prior that failed.
    fn widened_heading(&self, att: &AttitudePriorNed) -> Option<AttitudePriorNed> {
        let wide = self.params.widen_heading_sigma_deg.to_radians();
        (wide > att.sigma_yaw_rad).then_some(AttitudePriorNed {
            sigma_yaw_rad: wide,
            ..*att
        })
    }

    /// One rectification at `rect` (the attitude the frame is resampled with and the coarse gate
    /// assumes), the resection fusing `solve` (None: no attitude prior), with the methods `how`
    /// names: a heading sweep runs features at every hypothesis first and the area correlation
    /// alone only when none matched; the feature relocalisation uses features only.
    fn fix_single(
        &self,
        frame: &GrayImage,
        pos: &PositionPriorGeo,
        rect: &AttitudePriorNed,
        solve: Option<&AttitudePriorNed>,
        t_us: u64,
        how: Single,
    ) -> (FixReport, Attempt) {
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

    /// The resection's attitude prior from an NED attitude prior.
    fn solve_prior(&self, att: &AttitudePriorNed) -> Result<SolvePrior, Rejection> {
        let ok = |v: f64| v.is_finite() && v > 0.0;
        if !(ok(att.sigma_rad) && ok(att.sigma_yaw_rad)) {
            return Err(Rejection::PriorSigmas);
        }
        Ok(SolvePrior {
            r_enu_cam: r_enu_ned() * self.camera.mount.r_ned_cam(&att.attitude),
            sigma_tilt_rad: att.sigma_rad,
            sigma_yaw_rad: att.sigma_yaw_rad,
        })
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
            let r = match method {
                FixMethod::Features => match self.feature_pairs(&view, &mut a) {
                    Ok(p) => self.solve_pairs(&view, &p, method, t_us),
                    Err(e) => FixReport::rejected(e, t_us, 0.0),
                },
                _ => match self.area_pairs(&view, &mut a, how.placement) {
                    Ok(AreaOutcome::Ties(p)) => self.solve_pairs(&view, &p, FixMethod::Area, t_us),
                    Ok(AreaOutcome::Placement(p)) => self.placement_report(&view, &p, t_us),
                    Err(e) => FixReport::rejected(e, t_us, 0.0),
                },
            };
            if r.accepted {
                report = Some(r);
                break;
            }
            tried.push((method, rejection_of(r.rejection)));
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

    /// Feature correspondences: detect in the rectified frame, predict each keypoint's map
    /// position from the prior, gate, vote a similarity, match finely, and check the count
    /// against chance (module doc).
    fn feature_pairs(&self, v: &View, a: &mut Attempt) -> Result<Vec<Pair>, Rejection> {
        let (rect, level) = (v.rect, v.level);
        let gsd = self.levels_gsd_m[level];
        // Query features on valid ground, strongest first, capped.
        let feats = self.features.detect_and_describe(&self.surf, &rect.image);
        let keep = self.query_on_ground(v, &feats);
        a.query_features = keep.len();
        if keep.len() < self.params.min_matches {
            return Err(Rejection::FewFeatures { n: keep.len() });
        }
        // Selection: predicted footprint grown by the coarse gate.
        let gate_m = self.gate_m(v);
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for (_, p) in &keep {
            lo = [lo[0].min(p[0]), lo[1].min(p[1])];
            hi = [hi[0].max(p[0]), hi[1].max(p[1])];
        }
        let bounds = self.reference.bounds_m();
        if footprint_outside_map(lo, hi, gate_m, bounds) {
            return Err(Rejection::FootprintOutsideMap {
                footprint_m: [lo[0], hi[0], lo[1], hi[1]],
                map_m: [bounds[0], bounds[2], bounds[1], bounds[3]],
            });
        }
        let sel = self.reference.select(
            level,
            [
                lo[0] - gate_m,
                lo[1] - gate_m,
                hi[0] + gate_m,
                hi[1] + gate_m,
            ],
        );
        a.map_features = sel.features.len();
        if sel.features.len() < self.params.min_matches {
            return Err(Rejection::FewMapFeatures {
                n: sel.features.len(),
            });
        }
        // Level-pixel coordinates: origin at the selection's top-left, y down.
        let (ox, oy) = (lo[0] - gate_m, hi[1] + gate_m);
        let to_lp = |x: f64, y: f64| [((x - ox) / gsd) as f32, ((oy - y) / gsd) as f32];
        let train = train_features(&sel, gsd, to_lp)?;
        let query = subset(&feats, keep.iter().map(|(i, _)| *i))?;
        let pred: Vec<[f32; 2]> = keep.iter().map(|(_, p)| to_lp(p[0], p[1])).collect();

        // Coarse: gated nearest neighbours (no ratio test: the gate holds many look-alikes) and a
        // RANSAC 2-D similarity between predicted and map positions. The prior's position error
        // is a shift, its yaw error a rotation and its height error a scale of this map.
        let gate_px = (gate_m / gsd) as f32;
        let fine_r = self.params.fine_radius_px as f32;
        let sim = if gate_px > fine_r {
            self.coarse_similarity(v, [&query, &train], &pred, gate_px, a)?
        } else {
            Sim2::identity()
        };
        let pred_fine: Vec<[f32; 2]> = pred.iter().map(|p| sim.apply(*p)).collect();
        let wide = self.params.fine_wide_factor as f32 * fine_r;
        let matches = gated_match(&query, &train, &pred_fine, fine_r, wide, self.params.ratio);
        a.fine_matches = matches.len();
        for m in &matches {
            let (q, f) = (&query.keypoints[m.query], &sel.features[m.train]);
            if let Some(px) = rect.to_frame_px(f64::from(q.x), f64::from(q.y)) {
                a.pairs.push(([px.x, px.y], [f.x_m, f.y_m, f.z_amsl_m]));
            }
        }
        // A-contrario check (Moisan & Stival 2004 in spirit): the same gated matching with the
        // predictions displaced to unrelated map areas counts the matches chance alone produces
        // here (texture density, gate size, ratio test). A genuine view must beat that clearly.
        let null = self.chance_matches([&query, &train], &pred_fine, wide);
        a.null_matches = null;
        let needed =
            self.params.min_matches + (self.params.null_factor * null as f64).ceil() as usize;
        if matches.len() < needed {
            return Err(Rejection::BelowChance {
                matches: matches.len(),
                chance: null,
                needed,
            });
        }
        // SURF localises a keypoint to a fraction of its scale s (rectified pixels).
        let sigma_px = self.base_sigma_px(v);
        Ok(matches
            .iter()
            .filter_map(|m| {
                let (q, f) = (&query.keypoints[m.query], &sel.features[m.train]);
                let px = rect.to_frame_px(f64::from(q.x), f64::from(q.y))?;
                let s_rect = f64::from(q.scale.max(f.scale_m / gsd as f32));
                Some(Pair {
                    frame_px: px,
                    map: [f.x_m, f.y_m, f.z_amsl_m],
                    sigma_px: sigma_px * (s_rect / 2.0).max(1.0),
                })
            })
            .collect())
    }

    /// The frame's features (indices into `feats`, strongest first, at most `max_query_features`)
    /// on valid rectified ground, with the map position the prior puts each at.
    fn query_on_ground(&self, v: &View, feats: &Features) -> Vec<(usize, [f64; 2])> {
        let mut keep: Vec<(usize, [f64; 2])> = Vec::new();
        for (i, k) in feats.keypoints.iter().enumerate() {
            if keep.len() >= self.params.max_query_features {
                break;
            }
            if !v
                .rect
                .window_valid(f64::from(k.x), f64::from(k.y), 10.0 * f64::from(k.scale))
            {
                continue;
            }
            let Some(p) = self.ground_of(v, f64::from(k.x), f64::from(k.y)) else {
                continue;
            };
            keep.push((i, p));
        }
        keep
    }

    /// The coarse stage: gated nearest neighbours (no ratio test: the gate holds many
    /// look-alikes) and a RANSAC 2-D similarity from the predicted to the map positions (level
    /// pixels). `qt` = [query, train].
    fn coarse_similarity(
        &self,
        v: &View,
        qt: [&Features; 2],
        pred: &[[f32; 2]],
        gate_px: f32,
        a: &mut Attempt,
    ) -> Result<Sim2, Rejection> {
        let [query, train] = qt;
        let coarse = MatchParams {
            ratio: 1.0,
            laplacian_gate: true,
            mutual: false,
            spatial_radius_px: Some(gate_px),
        };
        let m = self
            .features
            .match_features(query, train, &coarse, Some(pred))
            .map_err(internal("matching"))?;
        a.coarse_matches = m.len();
        let src: Vec<[f32; 2]> = m.iter().map(|mm| pred[mm.query]).collect();
        let dst: Vec<[f32; 2]> = m
            .iter()
            .map(|mm| [train.keypoints[mm.train].x, train.keypoints[mm.train].y])
            .collect();
        let (max_rot, max_log_scale) = self.similarity_bounds(v);
        let fine_r = self.params.fine_radius_px as f32;
        let (sim, n) = ransac_similarity(&src, &dst, fine_r, max_rot, max_log_scale, 0x5EED)
            .ok_or(Rejection::NoCoarseConsensus { matches: m.len() })?;
        a.vote_peak = n;
        Ok(sim)
    }

    /// The a-contrario count: the most matches the fine gated matching finds with the
    /// predictions displaced by three wide gates to unrelated map areas (what chance alone gives
    /// here). `qt` = [query, train].
    fn chance_matches(&self, qt: [&Features; 2], pred_fine: &[[f32; 2]], wide: f32) -> usize {
        let [query, train] = qt;
        let fine_r = self.params.fine_radius_px as f32;
        let d = 3.0 * wide;
        [[d, 0.0], [-d, 0.0], [0.0, d], [0.0, -d]]
            .par_iter()
            .map(|o| {
                let shifted: Vec<[f32; 2]> = pred_fine
                    .iter()
                    .map(|p| [p[0] + o[0], p[1] + o[1]])
                    .collect();
                gated_match(query, train, &shifted, fine_r, wide, self.params.ratio).len()
            })
            .max()
            .unwrap_or(0)
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

    /// The coarse gate: the prior's position and tilt uncertainty on the ground, metres.
    fn gate_m(&self, v: &View) -> f64 {
        let g = v.g;
        (self.params.gate_sigmas
            * (g.sigma_h_m.powi(2) + (v.agl_m * g.sigma_tilt_rad.min(0.5)).powi(2)).sqrt())
        .max(self.params.min_gate_m)
    }

    /// Largest rotation (rad) and log scale between the predicted and the true map positions the
    /// prior allows.
    fn similarity_bounds(&self, v: &View) -> (f64, f64) {
        let g = v.g;
        let max_rot =
            (self.params.gate_sigmas * g.sigma_yaw_rad.max(g.sigma_tilt_rad)).min(0.5) + 0.02;
        let max_log_scale = (self.params.gate_sigmas * g.sigma_v_m / v.agl_m).min(0.7) + 0.05;
        (max_rot, max_log_scale)
    }

    /// A correspondence's localisation sigma in frame pixels before its scale: the rectified
    /// sigma, magnified when the frame is finer than the level.
    fn base_sigma_px(&self, v: &View) -> f64 {
        (self.params.sigma_rect_px / v.scale).max(0.5)
    }

    /// The resection of `pairs` in a local ENU frame about the footprint, with the prior fused.
    fn solve_pairs(&self, v: &View, pairs: &[Pair], method: FixMethod, t_us: u64) -> FixReport {
        let g = v.g;
        let rej = |reason: Rejection| FixReport::rejected(reason, t_us, 0.0);
        if pairs.len() < self.params.min_matches {
            return rej(Rejection::FewMatches {
                n: pairs.len(),
                min: self.params.min_matches,
            });
        }
        let crs = self.reference.crs();
        let mid = pairs[pairs.len() / 2].map;
        let origin = match crs
            .to_geodetic(mid[0], mid[1])
            .and_then(|(lat, lon)| Geodetic::new(lat, lon, mid[2] + geoid_undulation_m(lat, lon)?))
        {
            Ok(o) => o,
            Err(e) => return rej(geodesy("map geodesy")(e)),
        };
        let local = match LocalFrame::new(origin) {
            Ok(l) => l,
            Err(e) => return rej(geodesy("map geodesy")(e)),
        };
        let c_enu = match map_to_enu(&crs, &local, g.c_map.x, g.c_map.y, g.c_map.z) {
            Ok(c) => c,
            Err(e) => return rej(geodesy("prior geodesy")(e)),
        };
        let heights = self.reference.height_errors();
        // Pixel thresholds are in frame pixels; a frame finer than the map level sees its
        // localisation errors magnified by 1/scale.
        let mag = (1.0 / v.scale).max(1.0);
        // An inlier's residual stays within the consensus threshold, so the part of its height
        // error the image shows cannot exceed it (the points whose heights are further off, the
        // roofs and trees a constant height leaves out, fail the consensus): at most a uniform
        // spread over +-threshold.
        let height_cap_px = self.params.pose.ransac.threshold_px * mag / 3f64.sqrt();
        let corrs: Vec<Correspondence> = pairs
            .iter()
            .filter_map(|p| {
                let r = self.camera.unproject(&p.frame_px)?.into_inner();
                if r.z <= 0.0 {
                    return None;
                }
                let p_enu = map_to_enu(&crs, &local, p.map[0], p.map[1], p.map[2]).ok()?;
                let sigma_height_px = height_error_px(
                    &p_enu,
                    &c_enu,
                    heights.point_sigma_m,
                    self.camera.intrinsics.fx_px,
                )
                .min(height_cap_px);
                Some(Correspondence {
                    point_world: p_enu,
                    obs_norm: Vector2::new(r.x / r.z, r.y / r.z),
                    sigma_px: p.sigma_px.hypot(sigma_height_px),
                })
            })
            .collect();
        let image = ImageGeometry::from(&self.camera.intrinsics);
        let priors = Priors {
            // World = local ENU: tilt about east/north, heading about up. A loose heading (after
            // a GPS loss, or unknown) keeps the tilt: gravity still fixes it.
            attitude: g
                .solve
                .filter(|s| s.sigma_tilt_rad < MAX_PRIOR_TILT_SIGMA_RAD)
                .map(|s| AttitudePrior {
                    r_world_cam: s.r_enu_cam,
                    cov_rad2: nalgebra::Matrix3::from_diagonal(&Vector3::new(
                        s.sigma_tilt_rad.powi(2),
                        s.sigma_tilt_rad.powi(2),
                        s.sigma_yaw_rad.min(MAX_PRIOR_YAW_SIGMA_RAD).powi(2),
                    )),
                }),
            position: Some(PositionPrior {
                c_world: c_enu,
                cov_m2: nalgebra::Matrix3::from_diagonal(&Vector3::new(
                    g.sigma_h_m.powi(2),
                    g.sigma_h_m.powi(2),
                    g.sigma_v_m.powi(2),
                )),
            }),
            map_tilt_sigma_rad: heights.slope_sigma.atan(),
        };
        let mut cfg = self.params.pose.clone();
        // The filter's own attitude is not an independent prior: weigh it as before this
        // weighting became the information-weighted one (docs/fix.md, "The attitude prior").
        if g.att_from_filter {
            cfg.refine = cfg.refine.for_unscaled_prior();
        }
        cfg.ransac.threshold_px *= mag;
        cfg.integrity.max_reprojection_rms_px *= mag;
        let outcome = resect(&corrs, &image, &priors, &cfg);
        let verdict = match &outcome.verdict {
            Verdict::Accepted => None,
            Verdict::Rejected(r) => Some(Rejection::Pose(r.clone())),
        };
        let Some(fix) = outcome.fix.as_ref() else {
            let mut r = rej(rejection_of(verdict));
            r.matches = pairs.len();
            r.method = method;
            return r;
        };
        let mut report = match self.report_from(&crs, &local, fix, t_us, verdict) {
            Ok(r) => r,
            Err(e) => return rej(e),
        };
        report.matches = pairs.len();
        report.inliers = fix.quality.inliers;
        report.method = method;
        report
    }

    fn report_from(
        &self,
        crs: &Crs,
        local: &LocalFrame,
        fix: &crate::pose::Fix,
        t_us: u64,
        rejection: Option<Rejection>,
    ) -> Result<FixReport, Rejection> {
        let geo = local
            .enu_to_geodetic(&fix.pose.c_world)
            .map_err(geodesy("fix geodesy"))?;
        let n = geoid_undulation_m(geo.lat_deg, geo.lon_deg).map_err(geodesy("geoid"))?;
        let (x, y) = crs
            .from_geodetic(geo.lat_deg, geo.lon_deg)
            .map_err(geodesy("fix to map grid"))?;
        // Local ENU axes differ from the NED axes at the fix by the angle between the two
        // verticals (distance / Earth radius, < 0.01 deg over a footprint): ignored.
        let r_ned_enu = r_enu_ned().inverse();
        let r_ned_cam = r_ned_enu * fix.pose.r_world_cam;
        let att = self.camera.mount.attitude_from_r_ned_cam(&r_ned_cam);
        let mut cov = fix.covariance.position_ned_m2(&r_ned_enu);
        let reg_var = self.map_registration_var_m2();
        let height_var = self.map_height_var_m2();
        cov[(0, 0)] += reg_var;
        cov[(1, 1)] += reg_var;
        cov[(2, 2)] += height_var;
        let cov_att = fix.covariance.attitude_ned_rad2(&r_ned_enu);
        let to_arr = |m: &nalgebra::Matrix3<f64>| {
            [
                [m[(0, 0)], m[(0, 1)], m[(0, 2)]],
                [m[(1, 0)], m[(1, 1)], m[(1, 2)]],
                [m[(2, 0)], m[(2, 1)], m[(2, 2)]],
            ]
        };
        let r = FixReport {
            accepted: rejection.is_none(),
            rejection,
            t_capture_us: t_us,
            lat_deg: geo.lat_deg,
            lon_deg: geo.lon_deg,
            alt_amsl_m: geo.h_ellip_m - n,
            h_ellip_m: geo.h_ellip_m,
            x_m: x,
            y_m: y,
            z_m: geo.h_ellip_m - n,
            roll_deg: att.roll_rad.to_degrees(),
            pitch_deg: att.pitch_rad.to_degrees(),
            yaw_deg: att.yaw_rad.to_degrees(),
            cov_ned_m2: to_arr(&cov),
            cov_att_ned_rad2: to_arr(&cov_att),
            inliers: fix.quality.inliers,
            matches: 0,
            reproj_rms_px: fix.quality.reprojection_rms_px,
            sigma0: fix.quality.sigma0,
            cov_factor: fix.covariance.factor(),
            vision_only: self.vision_only_pose(local, fix, &r_ned_enu),
            // Position world = ENU, attitude errors as world rotation vectors: D_ned =
            // R_ned_enu G R_enu_ned (R_world_cam = R_enu_ned R_ned_body R_body_cam, so a body
            // error Exp(psi_ned) is the world error Exp(R_enu_ned psi_ned)).
            prior_dependence: fix
                .prior_dependence
                .map(|d| {
                    let r = r_ned_enu.matrix();
                    // The registration shift is part of the image's share (cov = image_cov +
                    // D P D^T holds with it).
                    let mut image_cov = r * d.image_position_cov_m2 * r.transpose();
                    image_cov[(0, 0)] += reg_var;
                    image_cov[(1, 1)] += reg_var;
                    image_cov[(2, 2)] += height_var;
                    crate::fix::PriorDependenceNed {
                        d_pos_d_att: to_arr(&(r * d.d_position_d_prior_att * r.transpose())),
                        image_cov_ned_m2: to_arr(&image_cov),
                    }
                })
                .filter(crate::fix::PriorDependenceNed::is_finite),
            prior_attitude_from_filter: false,
            level: 0,
            method: FixMethod::Features,
            ms: 0.0,
        };
        let finite = [
            r.lat_deg,
            r.lon_deg,
            r.alt_amsl_m,
            r.x_m,
            r.y_m,
            r.roll_deg,
            r.pitch_deg,
            r.yaw_deg,
        ]
        .iter()
        .chain(r.cov_ned_m2.iter().flatten())
        .all(|v| v.is_finite());
        if !finite {
            return Err(Rejection::NonFinite { what: "the fix" });
        }
        Ok(r)
    }

    /// Variance of the map's horizontal registration per axis, m^2
    /// (`FixParams::map_registration_sigma_px` in orthophoto pixels, whatever the map's upsampling).
    fn map_registration_var_m2(&self) -> f64 {
        (self.params.map_registration_sigma_px * self.reference.ortho_pixel_m()).powi(2)
    }

    /// Vertical variance a height error shared by the whole footprint adds, m^2: every map point
    /// raised by `dh` raises the solved camera by exactly `dh` and moves nothing else, so the
    /// map's height sigma ([`Reference::height_sigma_m`]) goes into the vertical in full (the
    /// per-point weighting of [`height_error_px`] covers the part that varies across the
    /// footprint, which the points' scatter would otherwise average away).
    fn map_height_var_m2(&self) -> f64 {
        self.reference.height_errors().offset_sigma_m.powi(2)
    }

    /// The image-only pose of `fix` in geodetic / NED terms, its 6x6 covariance reordered to
    /// `[position NED, attitude NED]` (the pose module orders `[phi, C]` in the local ENU frame
    /// and uses the same error signs as the filter: `tests/pose_resection.rs` checks them). None
    /// when a number is not finite.
    fn vision_only_pose(
        &self,
        local: &LocalFrame,
        fix: &crate::pose::Fix,
        r_ned_enu: &nalgebra::Rotation3<f64>,
    ) -> Option<super::VisionOnlyPose> {
        let geo = local.enu_to_geodetic(&fix.vision_pose.c_world).ok()?;
        let att = self
            .camera
            .mount
            .attitude_from_r_ned_cam(&(r_ned_enu * fix.vision_pose.r_world_cam));
        let c = fix.vision_covariance.conservative();
        let r = r_ned_enu.matrix();
        // Rotate both 3-blocks into NED and swap them: [phi, C] -> [C, phi].
        let mut t = nalgebra::Matrix6::<f64>::zeros();
        t.fixed_view_mut::<3, 3>(0, 3).copy_from(r);
        t.fixed_view_mut::<3, 3>(3, 0).copy_from(r);
        let cov = t * c * t.transpose();
        let mut cov = (cov + cov.transpose()) * 0.5;
        let reg_var = self.map_registration_var_m2();
        cov[(0, 0)] += reg_var;
        cov[(1, 1)] += reg_var;
        cov[(2, 2)] += self.map_height_var_m2();
        let v = super::VisionOnlyPose {
            lat_deg: geo.lat_deg,
            lon_deg: geo.lon_deg,
            h_ellip_m: geo.h_ellip_m,
            roll_deg: att.roll_rad.to_degrees(),
            pitch_deg: att.pitch_rad.to_degrees(),
            yaw_deg: att.yaw_rad.to_degrees(),
            cov6_ned: std::array::from_fn(|i| std::array::from_fn(|j| cov[(i, j)])),
        };
        v.is_finite().then_some(v)
    }

    /// Global relocalisation: no position prior. The altitude is unknown, so every level is tried
    /// (coarse to fine), each with the frame rectified to that level's scale at an assumed height
    /// chosen to make the virtual image about the frame's size; SURF's scale invariance absorbs the
    /// remaining scale error. Matches are voted in (log scale, translation) space like Lowe's
    /// Hough transform, the winning cluster's 3-D points seed a resection whose pose then serves
    /// as the prior of the normal pipeline. With a loose heading (or none) the headings are
    /// searched ([`heading_hypotheses`], tilt kept from the prior, or nadir without one); the
    /// first level with an accepted fix decides, by [`select_unique`] over all its hypotheses.
    /// The budget counts work (pixels through SURF, descriptor comparisons), so the same
    /// frame gives the same answer on any machine; when it runs out before a level's hypotheses
    /// are all tried, the fix is rejected (a winner without its competitors is not unique).
    fn relocalise(&self, frame: &GrayImage, prior: &FixPrior) -> (FixReport, Attempt) {
        let t_us = prior.t_capture_us;
        let budget = (self.params.reloc_budget_mwork * 1e6) as u64;
        if let (Some(alt), Some(att)) = (prior.altitude, prior.attitude)
            && self.params.area_matching != AreaMatching::Off
        {
            let mut work = 0u64;
            match self.relocalise_area(frame, &alt, &att, t_us, &mut work, None) {
                Ok(found) => return found,
                // The search ran and confirmed nothing: the frame does not match well enough
                // (the feature search would spend seconds to find little more).
                Err(AreaRelocError::NotFound(e)) => {
                    return (
                        FixReport::rejected(e.in_relocalisation(), t_us, 0.0),
                        Attempt::default(),
                    );
                }
                // It could not run (an old map, a budget too small, no ground in view): the
                // feature search below.
                Err(AreaRelocError::CannotRun(e)) => {
                    tracing::debug!("area relocalisation: {e}; the feature search instead");
                }
            }
        }
        let (hyps, solve) = match prior.attitude {
            Some(a) if a.sigma_yaw_rad <= YAW_SWEEP_ABOVE_DEG.to_radians() => (vec![a], Some(a)),
            Some(a) => (heading_hypotheses(&a), Some(a)),
            None => (heading_hypotheses(&self.nadir_any_heading()), None),
        };
        let mut work = 0u64;
        let mut last_reason = Rejection::NoLevelFix;
        // Each hypothesis' rectified view and features serve every level (rectified at the
        // frame's own scale); computed on first use.
        let mut views: Vec<Option<Result<RelocView, Rejection>>> =
            hyps.iter().map(|_| None).collect();
        for level in (0..self.levels_gsd_m.len()).rev() {
            let level_map = match self.reloc_level_map(level) {
                Ok(l) => l,
                Err(e) => {
                    last_reason = e;
                    continue;
                }
            };
            // The hypotheses are independent: each is tried on its own thread with its own
            // work count, then replayed in order against the budget. The replay stops where the
            // sequential search would have stopped, so the report is the same as trying them one
            // after another (what was computed past that point is discarded).
            let outcomes: Vec<HypothesisOutcome> = hyps
                .par_iter()
                .zip(views.par_iter_mut())
                .map(|(hyp, view)| {
                    let mut view_work = 0u64;
                    let view =
                        view.get_or_insert_with(|| self.reloc_view(frame, hyp, &mut view_work));
                    let mut level_work = 0u64;
                    let tried = match view {
                        Ok(v) => Some(self.reloc_level(
                            frame,
                            v,
                            &level_map,
                            solve.as_ref(),
                            t_us,
                            &mut level_work,
                        )),
                        Err(_) => None,
                    };
                    HypothesisOutcome {
                        view_work,
                        level_work,
                        tried,
                    }
                })
                .collect();
            let mut tries = Vec::new();
            for (outcome, view) in outcomes.into_iter().zip(&views) {
                if work >= budget {
                    let reason = Rejection::WorkBudget {
                        budget_mwork: self.params.reloc_budget_mwork,
                        level,
                        last: Box::new(last_reason),
                    };
                    let r = FixReport::rejected(reason.in_relocalisation(), t_us, 0.0);
                    return (r, Attempt::default());
                }
                work = work.saturating_add(outcome.view_work);
                let Some(tried) = outcome.tried else {
                    if let Some(Err(e)) = view {
                        last_reason = e.clone();
                    }
                    continue;
                };
                work = work.saturating_add(outcome.level_work);
                match tried {
                    Ok(h) => {
                        if let Some(r) = &h.report.rejection {
                            last_reason = r.clone().at_level(level);
                        }
                        tries.push(h);
                    }
                    Err(e) => last_reason = e,
                }
            }
            if tries.iter().any(|h| h.report.accepted) {
                let (mut r, a) = select_unique(tries, t_us);
                r.rejection = r
                    .rejection
                    .take()
                    .map(|why| why.at_level(level).in_relocalisation());
                return (r, a);
            }
        }
        let r = FixReport::rejected(last_reason.in_relocalisation(), t_us, 0.0);
        (r, Attempt::default())
    }

    /// Relocalisation by area when the altitude and the tilt are known (docs/fix.md,
    /// "Relocalisation"): [`Self::area_search`] shortlists places and headings over the whole
    /// map image; each candidate, best first, is verified by the prior pipeline (a position
    /// prior of one coarse pixel at the candidate, rectified at its heading) and confirmed from
    /// its own pose ([`Self::confirm_from_own_pose`]). After the first confirmed candidate only
    /// its rivals (a correlation within [`RELOC_AREA_RIVAL_MARGIN`] of its own) are verified,
    /// and one of them confirmed at another place makes the answer ambiguous. Err: no candidate
    /// confirmed.
    fn relocalise_area(
        &self,
        frame: &GrayImage,
        alt: &super::AltitudePrior,
        att: &AttitudePriorNed,
        t_us: u64,
        work: &mut u64,
        window: Option<&SearchWindow>,
    ) -> Result<(FixReport, Attempt), AreaRelocError> {
        let search = self
            .area_search(frame, alt, att, window, work)
            .map_err(AreaRelocError::CannotRun)?;
        let how = Single {
            att_from_filter: false,
            features: true,
            area: true,
            placement: false,
        };
        // The best candidate may be confirmed by its placement alone when it leads every other
        // place searched by the placement fix's margin (there no tie point confirms it), also
        // the places a window's distance rule left out.
        let lead = match search.candidates.first() {
            Some(first) => first.ncc - search.runner_up_ncc,
            None => f64::INFINITY,
        };
        let mut confirmed: Option<(f64, Hypothesis)> = None;
        let mut best_refused: Option<(f64, Box<Rejection>)> = None;
        for (i, c) in search.candidates.iter().enumerate() {
            if let Some((ncc, _)) = &confirmed
                && c.ncc < ncc - RELOC_AREA_RIVAL_MARGIN
            {
                break;
            }
            let how = Single {
                placement: i == 0 && lead >= area_stage::PLACEMENT_FIX_MARGIN,
                ..how
            };
            *work = work.saturating_add((frame.width() * frame.height()) as u64);
            let (r, a) = self.fix_single(frame, &c.position, &c.rect_att, Some(att), t_us, how);
            let h = if r.accepted {
                self.confirm_from_own_pose(
                    frame,
                    r,
                    a,
                    &c.rect_att,
                    Some(att),
                    t_us,
                    search.gsd_m,
                    how,
                    work,
                )
            } else {
                Hypothesis::new(c.rect_att.attitude.yaw_rad, r, a)
            };
            if !h.report.accepted {
                if best_refused.is_none() {
                    best_refused = Some((c.ncc, Box::new(rejection_of(h.report.rejection))));
                }
                continue;
            }
            match &confirmed {
                None => confirmed = Some((c.ncc, h)),
                Some((first_ncc, first)) => {
                    let d =
                        (h.report.x_m - first.report.x_m).hypot(h.report.y_m - first.report.y_m);
                    let same = SAME_PLACE_SIGMAS
                        * sigma_h_m(&first.report)
                            .hypot(sigma_h_m(&h.report))
                            .max(search.coarse_px_m);
                    if d > same {
                        let reason = Rejection::TwoPlaces {
                            distance_m: d,
                            ncc: [*first_ncc, c.ncc],
                        }
                        .in_relocalisation();
                        return Ok((FixReport::rejected(reason, t_us, 0.0), Attempt::default()));
                    }
                }
            }
        }
        match confirmed {
            Some((_, h)) => Ok((h.report, h.attempt)),
            None => Err(AreaRelocError::NotFound(Rejection::NoCandidateConfirmed {
                candidates: search.candidates.len(),
                best: best_refused,
            })),
        }
    }

    /// The area search over the whole map image: the frame rectified at the prior's tilt (its
    /// heading as given, however wrong) and at the scale the altitude gives over the map's
    /// middle height, in two channels ([`super::area::grey_and_gradient`]) block-averaged to
    /// at most [`RELOC_AREA_TEMPLATE_PX`] per side, correlated with the map image at every
    /// heading and over the scales the altitude's +-3 sigma and the map's height range allow,
    /// steps moving the template's corner by [`RELOC_AREA_EDGE_STEP_PX`]; the
    /// [`RELOC_AREA_CANDIDATES`] best distinct places with the camera position and heading each
    /// implies.
    fn area_search(
        &self,
        frame: &GrayImage,
        alt: &super::AltitudePrior,
        att: &AttitudePriorNed,
        window: Option<&SearchWindow>,
        work: &mut u64,
    ) -> Result<AreaSearch, Rejection> {
        use super::area::{candidates, grey_and_gradient};
        let (level, agl_m, img, budget) = self.area_level(alt, window, work)?;
        let gsd = self.levels_gsd_m[level];
        let (lo, hi) = self.reference.dem().height_range_m();
        let (rect, tc, f) = self.area_template(frame, att, agl_m / gsd, work)?;
        let crop = window.map_or([0, 0, img.width, img.height], |w| w.pixels(&img));
        let map = img
            .crop(crop[0] as i64, crop[1] as i64, crop[2], crop[3])
            .and_then(|m| grey_and_gradient(&m, f))
            .ok_or(Rejection::MapImageTooSmall)?;
        // The frame may see beyond the map's edge: the map inside a border of no data as wide
        // as the largest overhang the overlap rule allows.
        let (tw, th) = (tc[0].width, tc[0].height);
        let over = 1.0 - RELOC_AREA_MIN_OVERLAP;
        let (mx, my) = (
            (tw as f64 * over).ceil() as usize,
            (th as f64 * over).ceil() as usize,
        );
        let map = [map[0].padded(mx, my), map[1].padded(mx, my)];
        // The headings of the prior's +-3 sigma (every heading when that reaches round); the
        // scales the altitude and the terrain allow.
        let radius = 0.5 * (tw as f64).hypot(th as f64);
        let step = RELOC_AREA_EDGE_STEP_PX / radius.max(1.0);
        let half_log = ((3.0 * alt.sigma_m + 0.5 * (hi - lo)) / agl_m).min(0.7);
        let hyps = similarity_hypotheses(att.sigma_yaw_rad, half_log, step);
        // The budget counts work: the search's transforms, estimated before it runs.
        let points = (map[0].width * map[0].height) as u64;
        let estimate =
            (hyps.len() as u64 * 2 * 5 + 2 * 3).saturating_mul(points) / AREA_FFT_POINTS_PER_UNIT;
        if work.saturating_add(estimate) > budget {
            return Err(Rejection::AreaSearchBudget {
                needed_mwork: estimate as f64 / 1e6,
                budget_mwork: self.params.reloc_budget_mwork,
            });
        }
        let mut fft_points = 0u64;
        let shortlist = candidates(
            &[(&map[0], &tc[0]), (&map[1], &tc[1])],
            &hyps,
            RELOC_AREA_MIN_OVERLAP,
            super::area::UNIQUE_RADIUS_COARSE_PX,
            RELOC_AREA_CANDIDATES,
            &mut fft_points,
        );
        *work = work.saturating_add(fft_points / AREA_FFT_POINTS_PER_UNIT);
        // A candidate's camera: the virtual principal point (straight below the camera)
        // carried from the template's centre by the candidate's similarity.
        let fine = |c: f64| c * f as f64 + (f as f64 - 1.0) / 2.0;
        let (tcx, tcy) = (fine((tw as f64 - 1.0) / 2.0), fine((th as f64 - 1.0) / 2.0));
        let (dx, dy) = (rect.cx_px - tcx, rect.cy_px - tcy);
        let crs = self.reference.crs();
        let mut out: Vec<AreaCandidate> = Vec::new();
        let mut runner_up_ncc = f64::NEG_INFINITY;
        for c in &shortlist {
            let (s, co) = c.theta_rad.sin_cos();
            let px = [
                crop[0] as f64 + fine(c.centre[0] - mx as f64) + c.scale * (co * dx - s * dy),
                crop[1] as f64 + fine(c.centre[1] - my as f64) + c.scale * (s * dx + co * dy),
            ];
            let xy = img.to_map(px);
            // The shortlist is best first: every place after the first kept one is a rival, and
            // so is every place the window's distance rule leaves out.
            let admitted = window.is_none_or(|w| w.admits(xy));
            if !admitted || !out.is_empty() {
                runner_up_ncc = runner_up_ncc.max(c.ncc);
            }
            if !admitted {
                continue;
            }
            let Ok((lat, lon)) = crs.to_geodetic(xy[0], xy[1]) else {
                continue;
            };
            out.push(AreaCandidate {
                ncc: c.ncc,
                position: PositionPriorGeo {
                    lat_deg: lat,
                    lon_deg: lon,
                    alt_amsl_m: alt.alt_amsl_m,
                    sigma_h_m: f as f64 * gsd,
                    sigma_v_m: alt.sigma_m,
                },
                rect_att: AttitudePriorNed {
                    attitude: Attitude::new(
                        att.attitude.roll_rad,
                        att.attitude.pitch_rad,
                        wrap_pi(att.attitude.yaw_rad + c.theta_rad),
                    ),
                    sigma_rad: att.sigma_rad,
                    sigma_yaw_rad: (0.5 * step).max(MIN_HYPOTHESIS_YAW_SIGMA_RAD),
                },
            });
        }
        Ok(AreaSearch {
            candidates: out,
            runner_up_ncc,
            gsd_m: gsd,
            coarse_px_m: f as f64 * gsd,
        })
    }

    /// The area search's template: the frame rectified at `att` with `agl_px` (height above
    /// ground in map-level pixels) as its scale, in the two channels block-averaged by the factor
    /// `f` that brings its longer side to at most [`RELOC_AREA_TEMPLATE_PX`]; the rectification's
    /// pixels are counted as work.
    fn area_template(
        &self,
        frame: &GrayImage,
        att: &AttitudePriorNed,
        agl_px: f64,
        work: &mut u64,
    ) -> Result<(Rectification, [super::area::Plane; 2], usize), Rejection> {
        let r_map_cam = r_enu_ned() * self.camera.mount.r_ned_cam(&att.attitude);
        let rect = Rectification::new(
            frame,
            &self.camera,
            &r_map_cam,
            agl_px / self.camera.intrinsics.fx_px,
            self.params.max_rect_side_px,
            self.params.max_off_nadir_deg.to_radians(),
        )
        .ok_or(Rejection::NoGround)?;
        *work = work.saturating_add((rect.width() * rect.height()) as u64);
        let plane = rect.plane().ok_or(Rejection::NoGround)?;
        let f = rect
            .width()
            .max(rect.height())
            .div_ceil(RELOC_AREA_TEMPLATE_PX)
            .max(1);
        let tc = super::area::grey_and_gradient(&plane, f).ok_or(Rejection::ImagesTooSmall)?;
        Ok((rect, tc, f))
    }

    /// The area search's map level (the one whose ground sample matches the frame's at the
    /// altitude prior over the terrain's middle height), that height above ground, the level's
    /// image and the work budget; the image's pixels are counted as work (a map too large for the
    /// budget is left to the feature search before any is read).
    fn area_level(
        &self,
        alt: &super::AltitudePrior,
        window: Option<&SearchWindow>,
        work: &mut u64,
    ) -> Result<(usize, f64, super::reference::MapImage<'_>, u64), Rejection> {
        if !(alt.alt_amsl_m.is_finite() && alt.sigma_m.is_finite() && alt.sigma_m > 0.0) {
            return Err(Rejection::AltitudePrior);
        }
        let (lo, hi) = self.reference.dem().height_range_m();
        let agl_m = alt.alt_amsl_m - 0.5 * (lo + hi);
        if agl_m.is_nan() || agl_m <= 1.0 {
            return Err(Rejection::AltitudeBelowMap {
                alt_amsl_m: alt.alt_amsl_m,
            });
        }
        let level = self.pick_level(agl_m / self.camera.intrinsics.fx_px);
        let img = self
            .reference
            .level_image(level)
            .ok_or(Rejection::NoLevelImages)?;
        // Each pixel of the level image read (and held in the working planes) counts one unit:
        // a map too large for the budget is left to the feature search before any is read.
        let budget = (self.params.reloc_budget_mwork * 1e6) as u64;
        let [_, _, w, h] = window.map_or([0, 0, img.width, img.height], |w| w.pixels(&img));
        let map_px = (w * h) as u64;
        if work.saturating_add(map_px) > budget {
            return Err(Rejection::MapLevelBudget {
                mpixels: map_px as f64 / 1e6,
                budget_mwork: self.params.reloc_budget_mwork,
            });
        }
        *work = work.saturating_add(map_px);
        Ok((level, agl_m, img, budget))
    }

    /// The confirmation of a search's accepted fix `r`: the frame matched again from that fix's
    /// own pose (a tight position, rectified at the fix's attitude), the resection fusing the
    /// caller's `solve` prior again (not the first fix's attitude: the reported fix must not be
    /// checked against itself). A true view is confirmed (its matches come back with
    /// predictions accurate to a few pixels); a chance alignment found among many hypotheses
    /// is not (its matches came from the loose coarse gate), which the a-contrario count of one
    /// attempt cannot see after a search of dozens. The refined pass is kept only with more
    /// inliers.
    #[allow(clippy::too_many_arguments)]
    fn confirm_from_own_pose(
        &self,
        frame: &GrayImage,
        r: FixReport,
        a: Attempt,
        att: &AttitudePriorNed,
        solve: Option<&AttitudePriorNed>,
        t_us: u64,
        gsd: f64,
        how: Single,
        work: &mut u64,
    ) -> Hypothesis {
        let refined_pos = PositionPriorGeo {
            lat_deg: r.lat_deg,
            lon_deg: r.lon_deg,
            alt_amsl_m: r.alt_amsl_m,
            sigma_h_m: 3.0 * r.cov_ned_m2[0][0].max(r.cov_ned_m2[1][1]).sqrt().max(gsd),
            sigma_v_m: 3.0 * r.cov_ned_m2[2][2].sqrt().max(gsd),
        };
        let refined_rect = AttitudePriorNed::isotropic(
            Attitude::from_deg(r.roll_deg, r.pitch_deg, r.yaw_deg),
            1f64.to_radians(),
        );
        *work = work.saturating_add((frame.width() * frame.height()) as u64);
        let (r2, a2) = self.fix_single(frame, &refined_pos, &refined_rect, solve, t_us, how);
        if !r2.accepted {
            let mut rejected = FixReport::rejected(
                Rejection::NotConfirmed(Box::new(rejection_of(r2.rejection))),
                t_us,
                0.0,
            );
            rejected.matches = r.matches;
            rejected.level = r.level;
            return Hypothesis::new(att.attitude.yaw_rad, rejected, a);
        }
        if r2.inliers >= r.inliers {
            Hypothesis::new(att.attitude.yaw_rad, r2, a2)
        } else {
            Hypothesis::new(att.attitude.yaw_rad, r, a)
        }
    }

    /// Near nadir at an unknown heading: what relocalisation assumes without an attitude prior.
    fn nadir_any_heading(&self) -> AttitudePriorNed {
        AttitudePriorNed {
            attitude: Attitude::new(0.0, 0.0, 0.0),
            sigma_rad: self.params.reloc_tilt_sigma_deg.to_radians(),
            sigma_yaw_rad: std::f64::consts::PI,
        }
    }

    /// The frame rectified at `att` at its own scale (level-independent) with its query features;
    /// adds the pixels to `work`.
    fn reloc_view(
        &self,
        frame: &GrayImage,
        att: &AttitudePriorNed,
        work: &mut u64,
    ) -> Result<RelocView, Rejection> {
        let r_ned_cam = self.camera.mount.r_ned_cam(&att.attitude);
        let r_map_cam = r_enu_ned() * r_ned_cam; // grid convergence unknown yet: < 3 deg in a zone
        let Some(rect) = Rectification::new(
            frame,
            &self.camera,
            &r_map_cam,
            1.0,
            self.params.max_rect_side_px,
            self.params.max_off_nadir_deg.to_radians(),
        ) else {
            return Err(Rejection::NoGround);
        };
        *work = work.saturating_add((rect.width() * rect.height()) as u64);
        let feats = self.features.detect_and_describe(&self.surf, &rect.image);
        let idx: Vec<usize> = feats
            .keypoints
            .iter()
            .enumerate()
            .filter(|(_, k)| {
                rect.window_valid(f64::from(k.x), f64::from(k.y), 10.0 * f64::from(k.scale))
            })
            .map(|(i, _)| i)
            .take(self.params.max_query_features)
            .collect();
        if idx.len() < self.params.min_matches {
            return Err(Rejection::FewFeatures { n: idx.len() });
        }
        let query = subset(&feats, idx.iter().copied())?;
        Ok(RelocView {
            rect,
            query,
            att: *att,
        })
    }

    /// All of `level`'s features in level pixels (origin at the map's top-left corner).
    fn reloc_level_map(&self, level: usize) -> Result<RelocLevel, Rejection> {
        let gsd = self.levels_gsd_m[level];
        let sel = self.reference.select(level, self.reference.bounds_m());
        if sel.features.len() < self.params.min_matches {
            return Err(Rejection::FewLevelFeatures {
                level,
                n: sel.features.len(),
            });
        }
        let b = self.reference.bounds_m();
        let (ox, oy) = (b[0], b[3]);
        let to_lp = |x: f64, y: f64| [((x - ox) / gsd) as f32, ((oy - y) / gsd) as f32];
        let train = train_features(&sel, gsd, to_lp)?;
        Ok(RelocLevel {
            level,
            gsd,
            origin: (ox, oy),
            train,
        })
    }

    /// One relocalisation try at `level`, the frame rectified at `att` (one heading hypothesis),
    /// the resection fusing the caller's `solve` prior: the Hough cluster's position through the
    /// prior pipeline, refined once from its own fix. Err when no cluster was found; a rejected
    /// hypothesis is Ok (its evidence counts as a competitor in [`select_unique`]). Adds its work
    /// (pixels rectified and searched by SURF, descriptor comparisons / 16; each prior-pipeline
    /// pass counted as one frame's pixels) to `work`.
    fn reloc_level(
        &self,
        frame: &GrayImage,
        view: &RelocView,
        level_map: &RelocLevel,
        solve: Option<&AttitudePriorNed>,
        t_us: u64,
        work: &mut u64,
    ) -> Result<Hypothesis, Rejection> {
        let RelocView { rect, query, att } = view;
        let RelocLevel {
            level,
            gsd,
            origin: (ox, oy),
            train,
        } = level_map;
        let (level, gsd, ox, oy) = (*level, *gsd, *ox, *oy);
        *work = work.saturating_add(
            (query.len() as u64).saturating_mul(train.len() as u64) / RELOC_COMPARISONS_PER_UNIT,
        );
        let m = self
            .features
            .match_features(
                query,
                train,
                &MatchParams {
                    ratio: self.params.ratio,
                    laplacian_gate: true,
                    mutual: false,
                    spatial_radius_px: None,
                },
                None,
            )
            .map_err(internal("matching"))?;
        let at_level = |r: Rejection| r.at_level(level);
        if m.len() < self.params.min_matches {
            return Err(at_level(Rejection::FewMatches {
                n: m.len(),
                min: self.params.min_matches,
            }));
        }
        let size_px = rect.width().max(rect.height()) as f32;
        let centre_px = [rect.cx_px as f32, rect.cy_px as f32];
        let Some(cluster) = hough_cluster(&m, query, train, size_px, centre_px) else {
            return Err(at_level(Rejection::NoHoughCluster));
        };
        if cluster.len() < MIN_HOUGH_CLUSTER {
            return Err(at_level(Rejection::SmallHoughCluster {
                n: cluster.len(),
                min: MIN_HOUGH_CLUSTER,
            }));
        }
        // Scale and translation of the cluster: camera height and nadir point.
        let mut ss: Vec<f32> = cluster
            .iter()
            .map(|&j| train.keypoints[m[j].train].scale / query.keypoints[m[j].query].scale)
            .collect();
        ss.sort_by(f32::total_cmp);
        let s = f64::from(ss[ss.len() / 2]);
        let mut txs: Vec<f64> = Vec::new();
        let mut tys: Vec<f64> = Vec::new();
        for &j in &cluster {
            let q = &query.keypoints[m[j].query];
            let t = &train.keypoints[m[j].train];
            txs.push(f64::from(t.x) - s * (f64::from(q.x) - rect.cx_px));
            tys.push(f64::from(t.y) - s * (f64::from(q.y) - rect.cy_px));
        }
        txs.sort_by(f64::total_cmp);
        tys.sort_by(f64::total_cmp);
        let (nx, ny) = (txs[txs.len() / 2], tys[tys.len() / 2]);
        let x = ox + nx * gsd;
        let y = oy - ny * gsd;
        // One virtual pixel covers s level pixels: height above ground = f_v * s * gsd.
        let agl = rect.f_px * s * gsd;
        let ground = self.reference.height_amsl_m(x, y).unwrap_or_else(|| {
            let (lo, hi) = self.reference.dem().height_range_m();
            0.5 * (lo + hi)
        });
        let crs = self.reference.crs();
        let (lat, lon) = crs.to_geodetic(x, y).map_err(geodesy("map geodesy"))?;
        let pos = PositionPriorGeo {
            lat_deg: lat,
            lon_deg: lon,
            alt_amsl_m: ground + agl,
            // The cluster locates the nadir point to a few bins and the height to a scale bin.
            sigma_h_m: (0.2 * agl).max(3.0 * gsd),
            sigma_v_m: (0.3 * agl).max(3.0 * gsd),
        };
        let frame_px = (frame.width() * frame.height()) as u64;
        *work = work.saturating_add(frame_px);
        let (r, a) = self.fix_single(frame, &pos, att, solve, t_us, Single::FEATURES);
        if !r.accepted {
            return Ok(Hypothesis::new(att.attitude.yaw_rad, r, a));
        }
        Ok(self.confirm_from_own_pose(frame, r, a, att, solve, t_us, gsd, Single::FEATURES, work))
    }
}

/// Above this heading sigma (degrees) one rectification is not enough: upright SURF matches a
/// frame rotated by up to about 10 deg against the map (docs/surf.md) and the coarse similarity
/// searches +-3 sigma, so 3 x 3.5 deg is about the most one rectification covers.
const YAW_SWEEP_ABOVE_DEG: f64 = 3.5;
/// Number of heading hypotheses over a full turn.
const HEADINGS: u32 = 24;
/// Their spacing, degrees: every heading is within 7.5 deg of one, inside upright SURF's
/// tolerance.
const HEADING_STEP_DEG: f64 = 360.0 / HEADINGS as f64;
/// Heading sigma of one hypothesis for its rectification and coarse gate, degrees: the true
/// heading is within half a step of the nearest hypothesis, which 3 sigma covers.
const HYPOTHESIS_YAW_SIGMA_DEG: f64 = HEADING_STEP_DEG / 6.0;
/// A hypothesis search accepts its best fix only when its evidence (fine matches above its own
/// chance level, [`Attempt::evidence`]) is at least this many times its best competitor's (an
/// accepted fix at another place, or any hypothesis two or more heading steps away from the
/// fix's heading). The same margin as the a-contrario test's default `null_factor`: a genuine
/// view beats the alternatives clearly, a look-alike does not.
const UNIQUENESS_RATIO: f64 = 1.5;
/// Two accepted fixes are at the same place when their horizontal distance is within this many
/// of their combined horizontal sigmas.
const SAME_PLACE_SIGMAS: f64 = 3.0;
/// The resection fuses an attitude prior only when its tilt sigma is below this (rad, ~29 deg):
/// beyond, the prior carries nothing a linearised prior can use.
const MAX_PRIOR_TILT_SIGMA_RAD: f64 = 0.5;
/// A heading sigma beyond this (rad) is treated as this: no heading information, and the prior's
/// information matrix stays finite.
const MAX_PRIOR_YAW_SIGMA_RAD: f64 = std::f64::consts::PI;
/// Descriptor comparisons per relocalisation work unit: 16 comparisons of 64-float descriptors
/// took about as long as one pixel through rectification and SURF detection (release build,
/// one core; docs/fix.md), so the budget bounds both kinds of work alike.
pub const RELOC_COMPARISONS_PER_UNIT: u64 = 16;
/// Largest side of the coarse template of the area search over the whole map (coarse pixels).
/// The search's cost grows with its cube (pixels times headings); at 48 (about 1 700 valid
/// template pixels) fields and roads still span several coarse pixels and a search of a map of
/// a few km takes about 0.3 s on one core (docs/fix.md).
const RELOC_AREA_TEMPLATE_PX: usize = 48;
/// Heading and log-scale step of the area search: the template's corner moves by this many
/// coarse pixels per step (half of it at worst between steps, inside the correlation peak of
/// block-averaged images).
const RELOC_AREA_EDGE_STEP_PX: f64 = 1.5;
/// Share of the template's valid pixels that must lie on the map: a frame at 2 km above
/// ground sees 2-3 km, and near the map's edge much of it lies outside; below this the overlap
/// is too small for a correlation to mean anything.
const RELOC_AREA_MIN_OVERLAP: f64 = 0.45;
/// Distinct places of the area search shortlisted for verification (the true place is first
/// for most frames, and among the first four for nearly all).
const RELOC_AREA_CANDIDATES: usize = 4;
/// After a candidate is confirmed, the others whose correlation is within this of its own are
/// its rivals and verified too (lower ones are not alternatives to it).
const RELOC_AREA_RIVAL_MARGIN: f64 = 0.1;
/// FFT points per relocalisation work unit: a 2-D transform of 16 points took about as long as
/// one pixel through rectification and SURF detection (release build, one core), so the budget
/// bounds the area search and the feature search alike.
pub const AREA_FFT_POINTS_PER_UNIT: u64 = 16;
/// Smallest heading sigma of a verified candidate's rectification.
const MIN_HYPOTHESIS_YAW_SIGMA_RAD: f64 = 0.5 * std::f64::consts::PI / 180.0;

/// Why the area relocalisation gave no answer.
enum AreaRelocError {
    /// It could not run (no level images, budget, geometry).
    CannotRun(Rejection),
    /// It ran and confirmed no candidate.
    NotFound(Rejection),
}

/// Where the area search looks when a position prior bounds it ([`FixEngine::area_search_near`]):
/// the map rectangle searched (metres) and the largest distance of a candidate's camera from the
/// prior's centre.
struct SearchWindow {
    rect_m: [f64; 4],
    centre_m: [f64; 2],
    max_distance_m: f64,
}

impl SearchWindow {
    /// The rectangle in `img`'s pixels, clipped to the image: `[x0, y0, width, height]` (at
    /// least one pixel a side).
    fn pixels(&self, img: &super::reference::MapImage<'_>) -> [usize; 4] {
        let a = img.to_px(self.rect_m[0], self.rect_m[3]);
        let b = img.to_px(self.rect_m[2], self.rect_m[1]);
        let clip = |v: f64, n: usize| (v.max(0.0) as usize).min(n.saturating_sub(1));
        let (x0, y0) = (
            clip(a[0].floor(), img.width),
            clip(a[1].floor(), img.height),
        );
        let (x1, y1) = (clip(b[0].ceil(), img.width), clip(b[1].ceil(), img.height));
        [x0, y0, x1 - x0 + 1, y1 - y0 + 1]
    }

    /// A candidate camera at map `xy` is within the distance allowed.
    fn admits(&self, xy: [f64; 2]) -> bool {
        (xy[0] - self.centre_m[0]).hypot(xy[1] - self.centre_m[1]) <= self.max_distance_m
    }
}

/// The area search's shortlist ([`FixEngine::area_search`]).
struct AreaSearch {
    candidates: Vec<AreaCandidate>,
    /// The best correlation of any other place searched (a candidate or one the window's
    /// distance rule left out; -inf when there is none).
    runner_up_ncc: f64,
    /// Ground sample distance of the level searched and of its coarse grid, metres.
    gsd_m: f64,
    coarse_px_m: f64,
}

/// A place and heading of the area search, as the prior pipeline takes it.
struct AreaCandidate {
    /// The channels' mean correlation.
    ncc: f64,
    position: PositionPriorGeo,
    /// The attitude to rectify at: the prior's tilt and the candidate's heading.
    rect_att: AttitudePriorNed,
}

/// Fewest matches in the winning Hough bin of a relocalisation try (a similarity needs 2; 6
/// keeps chance clusters out, as the resection's own minimum then decides).
const MIN_HOUGH_CLUSTER: usize = 6;

/// One relocalisation hypothesis tried at one level, with the work it took (the view's only the
/// first time the view was made).
struct HypothesisOutcome {
    view_work: u64,
    level_work: u64,
    /// None when the hypothesis' view could not be made.
    tried: Option<Result<Hypothesis, Rejection>>,
}

/// A relocalisation hypothesis' rectified view (frame scale) and its query features.
struct RelocView {
    rect: Rectification,
    query: Features,
    /// The hypothesis it was rectified at.
    att: AttitudePriorNed,
}

/// One map level prepared for relocalisation: every feature, in level pixels from `origin`
/// (the map's top-left corner, grid metres).
struct RelocLevel {
    level: usize,
    gsd: f64,
    origin: (f64, f64),
    train: Features,
}

/// One hypothesis of a search: the heading the frame was rectified at and its outcome.
struct Hypothesis {
    rect_yaw_rad: f64,
    report: FixReport,
    attempt: Attempt,
}

impl Hypothesis {
    fn new(rect_yaw_rad: f64, report: FixReport, attempt: Attempt) -> Self {
        Self {
            rect_yaw_rad,
            report,
            attempt,
        }
    }
}

/// The strongest alternative to a search's best hypothesis.
struct Competitor {
    /// Its [`Attempt::evidence`].
    evidence: usize,
    /// Distance of its accepted fix from the best one, metres (None: not accepted).
    elsewhere_m: Option<f64>,
    rect_yaw_rad: f64,
}

/// The (scale, rotation) hypotheses of the area search, `step` apart (radians; a step moves the
/// template's corner by the edge step): the headings of +-3 `sigma_yaw_rad` (every heading when
/// that reaches round) at every log-scale step within +-`half_log`.
fn similarity_hypotheses(sigma_yaw_rad: f64, half_log: f64, step: f64) -> Vec<(f64, f64)> {
    let n_full = (std::f64::consts::TAU / step).ceil() as usize;
    let half_rot = 3.0 * sigma_yaw_rad + 0.5 * step;
    let rotations: Vec<f64> = if 2.0 * half_rot >= std::f64::consts::TAU {
        (0..n_full)
            .map(|r| r as f64 * std::f64::consts::TAU / n_full as f64)
            .collect()
    } else {
        let n = (half_rot / step).ceil() as i64;
        (-n..=n).map(|r| r as f64 * step).collect()
    };
    let n_scale = (half_log / step - 0.5).ceil().max(0.0) as i64;
    let mut hyps = Vec::new();
    for k in -n_scale..=n_scale {
        for &r in &rotations {
            hyps.push(((k as f64 * step).exp(), r));
        }
    }
    hyps
}

/// The largest Hough cluster of `m` (indices into it, sorted, distinct): each match votes for
/// the scale s = train.scale / query.scale (log2 bins of 0.5) and the translation of the virtual
/// principal point in level pixels (bins of 8 % of the image size at that scale), each vote
/// spread over the neighbouring bins. Ties go to the smallest key (HashMap order must not
/// decide). None without a vote.
fn hough_cluster(
    m: &[crate::vision::Match],
    query: &Features,
    train: &Features,
    size_px: f32,
    centre_px: [f32; 2],
) -> Option<Vec<usize>> {
    let mut votes: std::collections::HashMap<(i32, i32, i32), Vec<usize>> =
        std::collections::HashMap::new();
    let size = size_px;
    for (j, mm) in m.iter().enumerate() {
        let q = &query.keypoints[mm.query];
        let t = &train.keypoints[mm.train];
        let s = t.scale / q.scale;
        if !(s.is_finite() && s > 0.0) {
            continue;
        }
        let ls = s.log2() * 2.0;
        let tx = t.x - s * (q.x - centre_px[0]);
        let ty = t.y - s * (q.y - centre_px[1]);
        let bin = 0.08 * size * s;
        for ds in [0.0f32, 0.5] {
            let key = (
                (ls + ds).floor() as i32,
                (tx / bin).floor() as i32,
                (ty / bin).floor() as i32,
            );
            votes.entry(key).or_default().push(j);
            for (dx, dy) in [(1, 0), (0, 1), (1, 1)] {
                let key2 = (key.0, key.1 + dx, key.2 + dy);
                votes.entry(key2).or_default().push(j);
            }
        }
    }
    let (_, mut cluster) = votes
        .into_iter()
        .max_by(|(ka, va), (kb, vb)| va.len().cmp(&vb.len()).then(kb.cmp(ka)))?;
    cluster.sort_unstable();
    cluster.dedup();
    Some(cluster)
}

/// Heading hypotheses covering `att`'s heading +-3 sigma (all of them when that reaches round):
/// the prior heading first, then alternating outwards, [`HEADING_STEP_DEG`] apart, each with
/// the prior's roll, pitch and tilt sigma and [`HYPOTHESIS_YAW_SIGMA_DEG`].
fn heading_hypotheses(att: &AttitudePriorNed) -> Vec<AttitudePriorNed> {
    let step = HEADING_STEP_DEG.to_radians();
    let half_range = 3.0 * att.sigma_yaw_rad + 0.5 * step;
    let n_side = (half_range / step).floor() as i64;
    let full = 2 * n_side + 1 >= i64::from(HEADINGS);
    let mut ks = vec![0i64];
    let last = if full {
        i64::from(HEADINGS) / 2
    } else {
        n_side
    };
    for k in 1..=last {
        ks.push(k);
        if !(full && 2 * k == i64::from(HEADINGS)) {
            ks.push(-k);
        }
    }
    ks.into_iter()
        .map(|k| AttitudePriorNed {
            attitude: Attitude::new(
                att.attitude.roll_rad,
                att.attitude.pitch_rad,
                wrap_pi(att.attitude.yaw_rad + k as f64 * step),
            ),
            sigma_rad: att.sigma_rad,
            sigma_yaw_rad: HYPOTHESIS_YAW_SIGMA_DEG.to_radians(),
        })
        .collect()
}

/// Angle wrapped to (-pi, pi].
/// Image displacement (pixels, focal length `fx_px`) of a map point at `p` seen from `c` (same
/// local frame, z up) when its height is off by `height_sigma_m`: the component of a vertical
/// shift across the line of sight is `dh sin(alpha)` (alpha the ray's angle from the vertical),
/// seen at range `|p - c|`. 0 for a point straight below the camera, largest at the edge of a
/// tilted view: the same roof height misleads a point at the edge more than one at nadir.
fn height_error_px(p: &Vector3<f64>, c: &Vector3<f64>, height_sigma_m: f64, fx_px: f64) -> f64 {
    if height_sigma_m <= 0.0 {
        return 0.0;
    }
    let d = p - c;
    let range_m = d.norm();
    if !(range_m.is_finite() && range_m > 1e-6) {
        return 0.0;
    }
    let sin_alpha = d.xy().norm() / range_m;
    fx_px * height_sigma_m * sin_alpha / range_m
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

/// `att` turned to the heading a sweep's fix `r` found (tilt kept), at a hypothesis's heading
/// sigma: the rectification that fix is checked or redone at.
fn at_own_heading(att: &AttitudePriorNed, r: &FixReport) -> AttitudePriorNed {
    AttitudePriorNed {
        attitude: Attitude::new(
            att.attitude.roll_rad,
            att.attitude.pitch_rad,
            r.yaw_deg.to_radians(),
        ),
        sigma_rad: att.sigma_rad,
        sigma_yaw_rad: HYPOTHESIS_YAW_SIGMA_DEG.to_radians(),
    }
}

/// Horizontal 1-sigma of a report, metres (the larger of north and east).
fn sigma_h_m(r: &FixReport) -> f64 {
    r.cov_ned_m2[0][0].max(r.cov_ned_m2[1][1]).max(0.0).sqrt()
}

/// The search's answer: the accepted hypothesis with the most inliers, if it is unique (its
/// evidence at least [`UNIQUENESS_RATIO`] times its best competitor's: an accepted fix at
/// another place, or any hypothesis rectified two or more heading steps from the fix's heading);
/// otherwise a rejection that says what competed. With none accepted, the hypothesis that got
/// furthest (most evidence) explains the rejection.
fn select_unique(tries: Vec<Hypothesis>, t_us: u64) -> (FixReport, Attempt) {
    let n = tries.len();
    let best = tries
        .iter()
        .enumerate()
        .filter(|(_, h)| h.report.accepted)
        .max_by(|(ia, a), (ib, b)| {
            (a.report.inliers, a.attempt.fine_matches)
                .cmp(&(b.report.inliers, b.attempt.fine_matches))
                .then(a.attempt.area_ncc.total_cmp(&b.attempt.area_ncc))
                .then(ib.cmp(ia))
        })
        .map(|(i, _)| i);
    let Some(bi) = best else {
        let furthest = tries.into_iter().rev().max_by_key(|h| h.attempt.evidence());
        return match furthest {
            Some(h) => {
                let mut r = h.report;
                if n > 1 {
                    r.rejection = Some(Rejection::Headings {
                        tried: n,
                        best: Box::new(rejection_of(r.rejection.take())),
                    });
                }
                (r, h.attempt)
            }
            None => (
                FixReport::rejected(Rejection::NoHypothesis, t_us, 0.0),
                Attempt::default(),
            ),
        };
    };
    let b = &tries[bi];
    let far_heading = 1.5 * HEADING_STEP_DEG.to_radians();
    let best_yaw = b.report.yaw_deg.to_radians();
    if b.report.method == FixMethod::Placement {
        return placement_unique(tries, bi, far_heading, t_us);
    }
    let competitor = tries
        .iter()
        .enumerate()
        .filter(|(j, _)| *j != bi)
        .filter(|(_, h)| {
            if h.report.accepted {
                let d = (h.report.x_m - b.report.x_m).hypot(h.report.y_m - b.report.y_m);
                d > SAME_PLACE_SIGMAS * sigma_h_m(&h.report).hypot(sigma_h_m(&b.report))
            } else {
                wrap_pi(h.rect_yaw_rad - best_yaw).abs() > far_heading
            }
        })
        .max_by_key(|(_, h)| h.attempt.evidence())
        .map(|(_, h)| Competitor {
            evidence: h.attempt.evidence(),
            elsewhere_m: h
                .report
                .accepted
                .then(|| (h.report.x_m - b.report.x_m).hypot(h.report.y_m - b.report.y_m)),
            rect_yaw_rad: h.rect_yaw_rad,
        });
    let mut tries = tries;
    let Hypothesis {
        report, attempt, ..
    } = tries.swap_remove(bi);
    if let Some(c) = competitor
        && (attempt.evidence() as f64) < UNIQUENESS_RATIO * c.evidence as f64
    {
        let reason = Rejection::Ambiguous {
            evidence: attempt.evidence(),
            heading_deg: report.yaw_deg,
            rival_evidence: c.evidence,
            rival: match c.elsewhere_m {
                Some(distance_m) => Rival::Elsewhere { distance_m },
                None => Rival::Heading {
                    heading_deg: c.rect_yaw_rad.to_degrees(),
                },
            },
            ratio: UNIQUENESS_RATIO,
        };
        let mut r = FixReport::rejected(reason, t_us, 0.0);
        r.matches = report.matches;
        r.level = report.level;
        return (r, attempt);
    }
    (report, attempt)
}

/// [`select_unique`] for a placement fix (no tie points to weigh): every other hypothesis must
/// either be accepted at the same place, or (not accepted) lie within `far_heading` of its
/// heading, or correlate less than the winner by the placement fix's margin
/// ([`area_stage::PLACEMENT_FIX_MARGIN`]): the place and the heading are unique over the sweep as
/// the placement is within its own gate.
fn placement_unique(
    mut tries: Vec<Hypothesis>,
    bi: usize,
    far_heading: f64,
    t_us: u64,
) -> (FixReport, Attempt) {
    let b = &tries[bi];
    let best_yaw = b.report.yaw_deg.to_radians();
    let rival = tries.iter().enumerate().find(|&(j, h)| {
        if j == bi {
            return false;
        }
        if h.report.accepted {
            let d = (h.report.x_m - b.report.x_m).hypot(h.report.y_m - b.report.y_m);
            return d > SAME_PLACE_SIGMAS * sigma_h_m(&h.report).hypot(sigma_h_m(&b.report));
        }
        wrap_pi(h.rect_yaw_rad - best_yaw).abs() > far_heading
            && h.attempt.area_ncc > b.attempt.area_ncc - area_stage::PLACEMENT_FIX_MARGIN
    });
    if let Some((_, h)) = rival {
        let reason = Rejection::AmbiguousPlacement {
            ncc: b.attempt.area_ncc,
            heading_deg: b.report.yaw_deg,
            rival_ncc: h.attempt.area_ncc,
            rival_heading_deg: h.rect_yaw_rad.to_degrees(),
            margin: area_stage::PLACEMENT_FIX_MARGIN,
        };
        let mut r = FixReport::rejected(reason, t_us, 0.0);
        r.level = b.report.level;
        return (r, tries.swap_remove(bi).attempt);
    }
    let h = tries.swap_remove(bi);
    (h.report, h.attempt)
}

/// Map grid point (height AMSL) to the local ENU frame.
fn map_to_enu(
    crs: &Crs,
    local: &LocalFrame,
    x_m: f64,
    y_m: f64,
    z_amsl_m: f64,
) -> Result<Vector3<f64>, crate::geo::GeoError> {
    let (lat, lon) = crs.to_geodetic(x_m, y_m)?;
    let h = z_amsl_m + geoid_undulation_m(lat, lon)?;
    local.geodetic_to_enu(&Geodetic::new(lat, lon, h)?)
}

/// Train features in level-pixel coordinates.
fn train_features(
    sel: &RefSelection,
    gsd_m: f64,
    to_lp: impl Fn(f64, f64) -> [f32; 2],
) -> Result<Features, Rejection> {
    let kps = sel
        .features
        .iter()
        .map(|f| {
            let p = to_lp(f.x_m, f.y_m);
            KeyPoint {
                x: p[0],
                y: p[1],
                size: f.scale_m / gsd_m as f32 * 9.0 / 1.2,
                scale: f.scale_m / gsd_m as f32,
                response: 0.0,
                orientation_rad: 0.0,
                laplacian: f.laplacian,
                octave: 0,
            }
        })
        .collect();
    Features::new(kps, sel.descriptors.clone(), sel.kind).map_err(internal("map features"))
}

/// The features at `idx` (in that order).
fn subset(f: &Features, idx: impl Iterator<Item = usize>) -> Result<Features, Rejection> {
    let st = f.kind().stride();
    let mut kps = Vec::new();
    let mut desc = Vec::new();
    for i in idx {
        kps.push(f.keypoints[i]);
        desc.extend_from_slice(&f.descriptors_padded()[i * st..(i + 1) * st]);
    }
    Features::new(kps, desc, f.kind()).map_err(internal("query features"))
}

/// The rejection a report carries; a report rejected without one (which the engine never
/// makes) reads as the resection's numerical failure rather than being passed on as a fix.
fn rejection_of(r: Option<Rejection>) -> Rejection {
    r.unwrap_or(Rejection::Internal {
        stage: "fix",
        detail: "rejected without a reason".into(),
    })
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

/// The rejections of [`FixEngine::fix_prior`]'s searches, gathered as they fail.
struct WidenedWhy {
    stated: Rejection,
    /// The widened heading's +-3 sigma (degrees) and why it found nothing.
    heading: Option<(f64, Rejection)>,
    near: Option<Rejection>,
}

impl WidenedWhy {
    fn into_rejection(self) -> Rejection {
        if self.heading.is_none() && self.near.is_none() {
            return self.stated;
        }
        Rejection::Widened {
            stated: Box::new(self.stated),
            heading: self.heading.map(|(deg, r)| (deg, Box::new(r))),
            near: self.near.map(Box::new),
        }
    }
}

/// A match accepted by [`gated_match`]: query index, train index.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GatedMatch {
    pub query: usize,
    pub train: usize,
}

/// Spatially gated matching: for each query with a finite prediction, the nearest train descriptor
/// (same Laplacian sign) among the train keypoints within `r_wide` of the prediction is accepted when
/// it lies within `r_fine` of the prediction and passes Lowe's ratio test against the second nearest
/// in `r_wide` (a lone candidate passes). Brute force over a grid of `r_wide` cells.
pub fn gated_match(
    query: &Features,
    train: &Features,
    pred: &[[f32; 2]],
    r_fine: f32,
    r_wide: f32,
    ratio: f32,
) -> Vec<GatedMatch> {
    use std::collections::HashMap;
    let cell = r_wide.max(1.0);
    let key = |x: f32, y: f32| ((x / cell).floor() as i32, (y / cell).floor() as i32);
    let mut grid: HashMap<(i32, i32), Vec<usize>> = HashMap::new();
    for (j, k) in train.keypoints.iter().enumerate() {
        if k.x.is_finite() && k.y.is_finite() {
            grid.entry(key(k.x, k.y)).or_default().push(j);
        }
    }
    let st = query.kind().stride();
    let qd = query.descriptors_padded();
    let td = train.descriptors_padded();
    let mut out = Vec::new();
    for (i, q) in query.keypoints.iter().enumerate() {
        let Some(p) = pred.get(i) else {
            break;
        };
        if !(p[0].is_finite() && p[1].is_finite()) {
            continue;
        }
        let (cx, cy) = key(p[0], p[1]);
        let (mut d1, mut d2, mut b1) = (f32::INFINITY, f32::INFINITY, usize::MAX);
        for dx in -1..=1 {
            for dy in -1..=1 {
                let Some(c) = grid.get(&(cx + dx, cy + dy)) else {
                    continue;
                };
                for &j in c {
                    let t = &train.keypoints[j];
                    if t.laplacian != q.laplacian {
                        continue;
                    }
                    let (ex, ey) = (t.x - p[0], t.y - p[1]);
                    if ex * ex + ey * ey > r_wide * r_wide {
                        continue;
                    }
                    let d = dist2(&qd[i * st..(i + 1) * st], &td[j * st..(j + 1) * st]);
                    if d < d1 {
                        d2 = d1;
                        d1 = d;
                        b1 = j;
                    } else if d < d2 {
                        d2 = d;
                    }
                }
            }
        }
        if b1 == usize::MAX {
            continue;
        }
        let t = &train.keypoints[b1];
        let (ex, ey) = (t.x - p[0], t.y - p[1]);
        if ex * ex + ey * ey > r_fine * r_fine {
            continue;
        }
        if d2.is_finite() && d1.sqrt() >= ratio * d2.sqrt() {
            continue;
        }
        out.push(GatedMatch {
            query: i,
            train: b1,
        });
    }
    out
}

/// A 2-D similarity `p -> s R(theta) p + t`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sim2 {
    pub scale: f32,
    pub theta_rad: f32,
    pub t: [f32; 2],
}

impl Sim2 {
    /// The identity.
    pub fn identity() -> Self {
        Self {
            scale: 1.0,
            theta_rad: 0.0,
            t: [0.0, 0.0],
        }
    }
    /// Apply to a point.
    pub fn apply(&self, p: [f32; 2]) -> [f32; 2] {
        let (s, c) = self.theta_rad.sin_cos();
        [
            self.scale * (c * p[0] - s * p[1]) + self.t[0],
            self.scale * (s * p[0] + c * p[1]) + self.t[1],
        ]
    }
    /// Least-squares similarity from point pairs (Umeyama 1991, 2-D closed form); None when
    /// degenerate.
    pub fn fit(src: &[[f32; 2]], dst: &[[f32; 2]]) -> Option<Self> {
        let n = src.len().min(dst.len());
        if n < 2 {
            return None;
        }
        let nf = n as f64;
        let (mut ms, mut md) = ([0f64; 2], [0f64; 2]);
        for i in 0..n {
            for k in 0..2 {
                ms[k] += f64::from(src[i][k]) / nf;
                md[k] += f64::from(dst[i][k]) / nf;
            }
        }
        let (mut a, mut b, mut var) = (0f64, 0f64, 0f64);
        for i in 0..n {
            let (sx, sy) = (f64::from(src[i][0]) - ms[0], f64::from(src[i][1]) - ms[1]);
            let (dx, dy) = (f64::from(dst[i][0]) - md[0], f64::from(dst[i][1]) - md[1]);
            a += sx * dx + sy * dy;
            b += sx * dy - sy * dx;
            var += sx * sx + sy * sy;
        }
        if var.is_nan() || var <= 1e-9 {
            return None;
        }
        let theta = b.atan2(a);
        let scale = (a * a + b * b).sqrt() / var;
        let (s, c) = theta.sin_cos();
        let t = [
            md[0] - scale * (c * ms[0] - s * ms[1]),
            md[1] - scale * (s * ms[0] + c * ms[1]),
        ];
        let out = Self {
            scale: scale as f32,
            theta_rad: theta as f32,
            t: [t[0] as f32, t[1] as f32],
        };
        (out.scale.is_finite() && out.t.iter().all(|v| v.is_finite())).then_some(out)
    }
}

/// RANSAC over 2-point similarities between `src` and `dst` (pairs), with rotation and log-scale
/// limits (a similarity outside them is not a plausible prior error); the best model is refitted
/// to its inliers (distance <= `thresh`). Returns it with its inlier count (at least 3).
pub fn ransac_similarity(
    src: &[[f32; 2]],
    dst: &[[f32; 2]],
    thresh: f32,
    max_rot_rad: f64,
    max_abs_log_scale: f64,
    seed: u64,
) -> Option<(Sim2, usize)> {
    let n = src.len().min(dst.len());
    if n < 3 {
        return None;
    }
    let plausible = |s: &Sim2| {
        f64::from(s.theta_rad).abs() <= max_rot_rad
            && f64::from(s.scale).ln().abs() <= max_abs_log_scale
    };
    let count = |s: &Sim2| -> Vec<usize> {
        (0..n)
            .filter(|&i| {
                let p = s.apply(src[i]);
                let (dx, dy) = (p[0] - dst[i][0], p[1] - dst[i][1]);
                dx * dx + dy * dy <= thresh * thresh
            })
            .collect()
    };
    let mut state = seed | 1;
    let mut next = |m: usize| {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state % m as u64) as usize
    };
    let mut best: Vec<usize> = Vec::new();
    let iters = 2000.min(n * n);
    for _ in 0..iters {
        let (i, j) = (next(n), next(n));
        if i == j {
            continue;
        }
        let Some(s) = Sim2::fit(&[src[i], src[j]], &[dst[i], dst[j]]) else {
            continue;
        };
        if !plausible(&s) {
            continue;
        }
        let inl = count(&s);
        if inl.len() > best.len() {
            best = inl;
        }
    }
    if best.len() < 3 {
        return None;
    }
    // Refit on the inliers twice (inliers re-selected with the refined model).
    let mut model = None;
    for _ in 0..2 {
        let s: Vec<[f32; 2]> = best.iter().map(|&i| src[i]).collect();
        let d: Vec<[f32; 2]> = best.iter().map(|&i| dst[i]).collect();
        let Some(m) = Sim2::fit(&s, &d).filter(|m| plausible(m)) else {
            break;
        };
        let inl = count(&m);
        if inl.len() < 3 {
            break;
        }
        best = inl;
        model = Some(m);
    }
    model.map(|m| (m, best.len()))
}

/// Whether a footprint `[lo, hi]` (map metres), grown by the search gate, misses the map's
/// `bounds` `[min_x, min_y, max_x, max_y]` entirely: nothing there can match.
fn footprint_outside_map(lo: [f64; 2], hi: [f64; 2], gate_m: f64, bounds: [f64; 4]) -> bool {
    hi[0] + gate_m < bounds[0]
        || lo[0] - gate_m > bounds[2]
        || hi[1] + gate_m < bounds[1]
        || lo[1] - gate_m > bounds[3]
}

#[cfg(test)]
pub(crate) mod tests {
    #[test]
    fn a_footprint_beyond_the_map_is_outside_it() {
        let b = [1000.0, 2000.0, 3000.0, 4000.0];
        // Inside, overlapping an edge, and within the gate of it: not outside.
        assert!(!footprint_outside_map(
            [1500.0, 2500.0],
            [1800.0, 2800.0],
            50.0,
            b
        ));
        assert!(!footprint_outside_map(
            [2900.0, 3900.0],
            [3200.0, 4200.0],
            50.0,
            b
        ));
        assert!(!footprint_outside_map(
            [3020.0, 2500.0],
            [3300.0, 2800.0],
            50.0,
            b
        ));
        // Beyond each side.
        assert!(footprint_outside_map(
            [3100.0, 2500.0],
            [3300.0, 2800.0],
            50.0,
            b
        ));
        assert!(footprint_outside_map(
            [500.0, 2500.0],
            [900.0, 2800.0],
            50.0,
            b
        ));
        assert!(footprint_outside_map(
            [1500.0, 4100.0],
            [1800.0, 4300.0],
            50.0,
            b
        ));
        assert!(footprint_outside_map(
            [1500.0, 1000.0],
            [1800.0, 1900.0],
            50.0,
            b
        ));
    }

    use super::*;

    #[test]
    fn ransac_similarity_finds_the_prior_error_among_outliers() {
        let truth = Sim2 {
            scale: 1.05,
            theta_rad: 0.03,
            t: [37.0, -12.0],
        };
        let mut s = 12345u64;
        let mut rnd = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 33) as f32 / (1u64 << 31) as f32) - 0.5
        };
        let (mut src, mut dst) = (Vec::new(), Vec::new());
        for _ in 0..20 {
            let p = [300.0 * rnd() + 150.0, 300.0 * rnd() + 150.0];
            let q = truth.apply(p);
            src.push(p);
            dst.push([q[0] + 0.5 * rnd(), q[1] + 0.5 * rnd()]);
        }
        for _ in 0..150 {
            src.push([300.0 * rnd() + 150.0, 300.0 * rnd() + 150.0]);
            dst.push([400.0 * rnd() + 150.0, 400.0 * rnd() + 150.0]);
        }
        let (m, n) = ransac_similarity(&src, &dst, 3.0, 0.2, 0.2, 1).unwrap();
        assert!(n >= 20, "{n}");
        let p = m.apply([100.0, 200.0]);
        let q = truth.apply([100.0, 200.0]);
        assert!(
            (p[0] - q[0]).abs() < 1.0 && (p[1] - q[1]).abs() < 1.0,
            "{m:?}"
        );
        // Outside the rotation limit the true model is not accepted.
        let far = ransac_similarity(&src, &dst, 3.0, 0.001, 0.2, 1);
        assert!(far.is_none_or(|(_, n)| n < 20));
        assert!(ransac_similarity(&src[..2], &dst[..2], 3.0, 0.2, 0.2, 1).is_none());
    }

    fn prior_with_yaw_sigma(yaw_deg: f64, sigma_yaw_deg: f64) -> AttitudePriorNed {
        AttitudePriorNed {
            attitude: Attitude::from_deg(3.0, -4.0, yaw_deg),
            sigma_rad: 1f64.to_radians(),
            sigma_yaw_rad: sigma_yaw_deg.to_radians(),
        }
    }

    #[test]
    fn a_height_error_moves_a_point_in_the_image_by_its_viewing_angle() {
        let c = Vector3::new(0.0, 0.0, 100.0);
        let fx = 500.0;
        // Straight below: a height error moves the point along the ray, not across it.
        assert_eq!(height_error_px(&Vector3::zeros(), &c, 10.0, fx), 0.0);
        // 45 deg off the vertical at range 100 sqrt(2): 500 * 10 * sin 45 / 141.4 = 25 px.
        let p = Vector3::new(100.0, 0.0, 0.0);
        let px = height_error_px(&p, &c, 10.0, fx);
        assert!((px - 25.0).abs() < 1e-9, "{px}");
        // Proportional to the sigma; none without one; a degenerate geometry gives 0, not NaN.
        assert!((height_error_px(&p, &c, 5.0, fx) - 12.5).abs() < 1e-9);
        assert_eq!(height_error_px(&p, &c, 0.0, fx), 0.0);
        assert_eq!(height_error_px(&c, &c, 10.0, fx), 0.0);
    }

    #[test]
    fn heading_hypotheses_cover_three_sigma_and_keep_the_tilt() {
        let step = HEADING_STEP_DEG;
        for (sigma, yaw0) in [
            (4.0, 10.0),
            (10.0, 170.0),
            (30.0, -120.0),
            (60.0, 0.0),
            (180.0, 45.0),
        ] {
            let h = heading_hypotheses(&prior_with_yaw_sigma(yaw0, sigma));
            // The prior heading first; roll, pitch and tilt sigma kept; unique headings.
            assert!((h[0].attitude.yaw_rad.to_degrees() - yaw0).abs() < 1e-9);
            let mut yaws: Vec<f64> = h.iter().map(|a| a.attitude.yaw_rad.to_degrees()).collect();
            for a in &h {
                assert_eq!(a.attitude.roll_rad, 3f64.to_radians());
                assert_eq!(a.attitude.pitch_rad, (-4f64).to_radians());
                assert_eq!(a.sigma_rad, 1f64.to_radians());
                assert!(a.attitude.yaw_rad.abs() <= std::f64::consts::PI + 1e-12);
            }
            yaws.sort_by(f64::total_cmp);
            yaws.dedup_by(|a, b| (*a - *b).abs() < 1e-6);
            assert_eq!(yaws.len(), h.len(), "sigma {sigma}: duplicate headings");
            assert!(h.len() <= HEADINGS as usize);
            // Every heading within 3 sigma of the prior is within half a step of a hypothesis.
            let mut d = -3.0 * sigma.min(60.0);
            while d <= 3.0 * sigma.min(60.0) {
                let t = (yaw0 + d).to_radians();
                let near = h
                    .iter()
                    .map(|a| wrap_pi(a.attitude.yaw_rad - t).abs().to_degrees())
                    .fold(f64::INFINITY, f64::min);
                assert!(
                    near <= 0.5 * step + 1e-9,
                    "sigma {sigma}: {d} deg off is {near} from a hypothesis"
                );
                d += 0.5;
            }
        }
        assert_eq!(
            heading_hypotheses(&prior_with_yaw_sigma(0.0, 180.0)).len(),
            HEADINGS as usize
        );
        assert_eq!(heading_hypotheses(&prior_with_yaw_sigma(0.0, 4.0)).len(), 3);
        assert!((wrap_pi(3.5 * std::f64::consts::PI) + 0.5 * std::f64::consts::PI).abs() < 1e-12);
    }

    fn hypothesis(
        rect_yaw_deg: f64,
        accepted: bool,
        at: (f64, f64),
        fine: usize,
        null: usize,
    ) -> Hypothesis {
        let mut r = FixReport::rejected(Rejection::FewFeatures { n: 0 }, 7, 0.0);
        if accepted {
            r.accepted = true;
            r.rejection = None;
            r.x_m = at.0;
            r.y_m = at.1;
            r.yaw_deg = rect_yaw_deg + 2.0;
            r.cov_ned_m2 = [[100.0, 0.0, 0.0], [0.0, 100.0, 0.0], [0.0, 0.0, 100.0]];
            r.inliers = fine / 2;
        }
        let a = Attempt {
            fine_matches: fine,
            null_matches: null,
            ..Attempt::default()
        };
        Hypothesis::new(rect_yaw_deg.to_radians(), r, a)
    }

    #[test]
    fn select_unique_accepts_a_clear_winner_only() {
        // A clear winner: its neighbours in heading and a far heading at chance level.
        let (r, _) = select_unique(
            vec![
                hypothesis(0.0, false, (0.0, 0.0), 14, 10),
                hypothesis(15.0, true, (100.0, 50.0), 60, 10),
                hypothesis(30.0, true, (104.0, 52.0), 40, 10),
                hypothesis(90.0, false, (0.0, 0.0), 20, 10),
            ],
            7,
        );
        assert!(r.accepted, "{}", r.reason());
        assert_eq!((r.x_m, r.y_m), (100.0, 50.0));
        // A far heading with nearly as much evidence: ambiguous, rejected, saying so.
        let (r, a) = select_unique(
            vec![
                hypothesis(15.0, true, (100.0, 50.0), 60, 10),
                hypothesis(120.0, false, (0.0, 0.0), 45, 10),
            ],
            7,
        );
        assert!(!r.accepted);
        assert!(
            matches!(
                r.rejection,
                Some(Rejection::Ambiguous {
                    evidence: 50,
                    rival_evidence: 35,
                    rival: Rival::Heading { heading_deg },
                    ..
                }) if (heading_deg - 120.0).abs() < 1e-9
            ),
            "{}",
            r.reason()
        );
        assert_eq!(r.class(), "ambiguous");
        assert_eq!(a.fine_matches, 60);
        // An accepted fix at another place with nearly as much evidence: rejected.
        let (r, _) = select_unique(
            vec![
                hypothesis(15.0, true, (100.0, 50.0), 60, 10),
                hypothesis(30.0, true, (900.0, 50.0), 44, 10),
            ],
            7,
        );
        assert!(
            matches!(
                r.rejection,
                Some(Rejection::Ambiguous {
                    rival: Rival::Elsewhere { distance_m: 800.0 },
                    ..
                })
            ),
            "{}",
            r.reason()
        );
        assert!(!r.accepted && r.reason().contains("another place 800 m away"));
        // The same place twice is one answer, not a competitor.
        let (r, _) = select_unique(
            vec![
                hypothesis(15.0, true, (100.0, 50.0), 60, 10),
                hypothesis(90.0, true, (110.0, 45.0), 58, 10),
            ],
            7,
        );
        assert!(r.accepted, "{}", r.reason());
        // Nothing accepted: the rejection of the hypothesis that got furthest, with the count.
        let mut best = hypothesis(45.0, false, (0.0, 0.0), 30, 10);
        best.report.rejection = Some(Rejection::BelowChance {
            matches: 30,
            chance: 10,
            needed: 27,
        });
        let (r, _) = select_unique(vec![hypothesis(0.0, false, (0.0, 0.0), 12, 10), best], 7);
        assert!(!r.accepted);
        assert_eq!(
            r.reason(),
            "2 headings tried, best: only 30 matches where chance gives 10 (need 27)"
        );
        assert_eq!(r.class(), "below_chance");
    }

    /// An area-correlation hypothesis: no feature matches, `ties` tie points.
    fn area_hypothesis(
        rect_yaw_deg: f64,
        accepted: bool,
        at: (f64, f64),
        ties: usize,
    ) -> Hypothesis {
        let mut h = hypothesis(rect_yaw_deg, accepted, at, 0, 0);
        h.attempt.area_ties = ties;
        h.report.inliers = ties;
        h
    }

    #[test]
    fn select_unique_weighs_area_hypotheses_by_their_tie_points() {
        // Two area fixes at places 800 m apart with about the same tie points: ambiguous.
        let (r, _) = select_unique(
            vec![
                area_hypothesis(15.0, true, (100.0, 50.0), 40),
                area_hypothesis(60.0, true, (900.0, 50.0), 35),
            ],
            7,
        );
        assert!(
            !r.accepted && r.reason().contains("another place 800 m away"),
            "{}",
            r.reason()
        );
        // A clear winner against a far heading with a few ties.
        let (r, _) = select_unique(
            vec![
                area_hypothesis(15.0, true, (100.0, 50.0), 40),
                area_hypothesis(90.0, false, (0.0, 0.0), 12),
            ],
            7,
        );
        assert!(r.accepted, "{}", r.reason());
        // Features and area in one attempt: the larger evidence counts.
        let mut both = hypothesis(0.0, false, (0.0, 0.0), 30, 10).attempt;
        both.area_ties = 25;
        assert_eq!(both.evidence(), 25);
        both.area_ties = 5;
        assert_eq!(both.evidence(), 20);
        // Tie points count above their own chance level, as matches do.
        both.area_ties = 40;
        both.area_null_ties = 15;
        assert_eq!(both.evidence(), 25);
    }

    /// A hypothesis placed with correlation `ncc`; accepted as a placement fix at `at` or not.
    fn placement_hypothesis(rect_yaw_deg: f64, fix_at: Option<(f64, f64)>, ncc: f64) -> Hypothesis {
        let mut h = hypothesis(
            rect_yaw_deg,
            fix_at.is_some(),
            fix_at.unwrap_or_default(),
            0,
            0,
        );
        h.report.inliers = 0;
        if fix_at.is_some() {
            h.report.method = FixMethod::Placement;
        }
        h.attempt.area_ncc = ncc;
        h
    }

    #[test]
    fn select_unique_takes_a_placement_fix_only_when_its_correlation_leads() {
        // Headings within 1.5 steps (22.5 deg) of the fix's may correlate as well; farther ones
        // correlate 0.1 less or accept at the same place.
        let tries = || {
            vec![
                placement_hypothesis(0.0, None, 0.40),
                placement_hypothesis(15.0, Some((0.0, 0.0)), 0.45),
                placement_hypothesis(30.0, Some((5.0, 0.0)), 0.42),
                placement_hypothesis(45.0, None, 0.33),
                placement_hypothesis(180.0, None, 0.34),
            ]
        };
        let (r, a) = select_unique(tries(), 7);
        assert!(r.accepted, "{}", r.reason());
        assert_eq!(a.area_ncc, 0.45, "the best correlation wins");
        // A far heading within 0.1 of it: ambiguous.
        let mut t = tries();
        t[4].attempt.area_ncc = 0.36;
        let (r, _) = select_unique(t, 7);
        assert!(
            matches!(r.rejection, Some(Rejection::AmbiguousPlacement { .. })),
            "{}",
            r.reason()
        );
        // Another accepted placement fix at another place: ambiguous.
        let mut t = tries();
        t[4] = placement_hypothesis(180.0, Some((900.0, 0.0)), 0.30);
        let (r, _) = select_unique(t, 7);
        assert!(!r.accepted, "{}", r.reason());
        // A tie-point fix outranks a placement fix.
        let mut t = tries();
        t.push(area_hypothesis(90.0, true, (0.0, 3.0), 30));
        let (r, _) = select_unique(t, 7);
        assert!(r.accepted && r.inliers == 30, "{}", r.reason());
    }

    fn features(points: &[([f32; 2], i8, [f32; 8])]) -> Features {
        let kind = crate::vision::DescriptorKind::Surf64;
        let st = kind.stride();
        let mut desc = Vec::new();
        let kps = points
            .iter()
            .map(|(p, lap, d)| {
                let mut row = vec![0f32; st];
                row[..8].copy_from_slice(d);
                desc.extend(row);
                KeyPoint {
                    x: p[0],
                    y: p[1],
                    size: 9.0,
                    scale: 1.2,
                    response: 1.0,
                    orientation_rad: 0.0,
                    laplacian: *lap,
                    octave: 0,
                }
            })
            .collect();
        Features::new(kps, desc, kind).unwrap()
    }

    /// Key points at `pts` with scale `scale` (descriptors irrelevant here).
    fn keypoints_at(pts: &[[f32; 2]], scale: f32) -> Features {
        let kind = crate::vision::DescriptorKind::Surf64;
        let kps = pts
            .iter()
            .map(|p| KeyPoint {
                x: p[0],
                y: p[1],
                size: 9.0,
                scale,
                response: 1.0,
                orientation_rad: 0.0,
                laplacian: 1,
                octave: 0,
            })
            .collect();
        Features::new(kps, vec![0.0; pts.len() * kind.stride()], kind).unwrap()
    }

    #[test]
    fn the_hough_cluster_collects_the_matches_of_one_scale_and_shift() {
        // 12 matches agree on scale 2 and the virtual principal point at (400, 300); 6 others
        // scatter.
        let centre = [320.0f32, 240.0];
        let mut q = Vec::new();
        let mut t = Vec::new();
        for i in 0..12 {
            let p = [40.0 + 45.0 * i as f32, 30.0 + 33.0 * ((i * 7) % 12) as f32];
            q.push(p);
            t.push([
                400.0 + 2.0 * (p[0] - centre[0]),
                300.0 + 2.0 * (p[1] - centre[1]),
            ]);
        }
        for i in 0..6 {
            q.push([100.0 + 80.0 * i as f32, 200.0]);
            t.push([1500.0 - 230.0 * i as f32, 90.0 + 170.0 * i as f32]);
        }
        let query = keypoints_at(&q, 1.5);
        let train = keypoints_at(&t, 3.0);
        let m: Vec<crate::vision::Match> = (0..q.len())
            .map(|i| crate::vision::Match {
                query: i,
                train: i,
                distance: 0.1,
                second_distance: 0.5,
            })
            .collect();
        let c = hough_cluster(&m, &query, &train, 640.0, centre).unwrap();
        assert!((0..12).all(|i| c.contains(&i)), "{c:?}");
        assert!(c.iter().filter(|&&i| i >= 12).count() <= 1, "{c:?}");
        assert!(c.windows(2).all(|w| w[0] < w[1]), "sorted, distinct");
        assert!(hough_cluster(&[], &query, &train, 640.0, centre).is_none());
    }

    #[test]
    fn the_area_hypotheses_cover_the_heading_and_scale_bands() {
        let step = 0.05;
        // A tight heading: rotations within +-(3 sigma + a step), scales within the log band.
        let h = similarity_hypotheses(0.02, 0.12, step);
        let max_rot = h.iter().map(|(_, r)| r.abs()).fold(0.0, f64::max);
        assert!((0.06..=0.06 + 1.5 * step).contains(&max_rot), "{max_rot}");
        assert!(h.iter().any(|&(s, r)| s == 1.0 && r == 0.0));
        let max_log = h.iter().map(|(s, _)| s.ln().abs()).fold(0.0, f64::max);
        assert!((0.12 - step..=0.12 + step).contains(&max_log), "{max_log}");
        // An unknown heading: every heading, evenly.
        let h = similarity_hypotheses(2.0, 0.0, step);
        let n = (std::f64::consts::TAU / step).ceil() as usize;
        assert_eq!(h.len(), n);
        assert!(h.iter().all(|&(s, _)| s == 1.0));
        assert!((h[1].1 - h[0].1 - std::f64::consts::TAU / n as f64).abs() < 1e-12);
    }

    #[test]
    fn gated_match_rules() {
        let a = [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        let b = [0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        let a2 = [0.95, 0.05, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        let query = features(&[([0.0, 0.0], 1, a)]);
        // A lone candidate within the fine radius passes.
        let train = features(&[([102.0, 100.0], 1, a)]);
        let m = gated_match(&query, &train, &[[100.0, 100.0]], 4.0, 12.0, 0.9);
        assert_eq!(m, vec![GatedMatch { query: 0, train: 0 }]);
        // Outside the fine radius (but inside the wide one): no match.
        let m = gated_match(&query, &train, &[[95.0, 100.0]], 4.0, 12.0, 0.9);
        assert!(m.is_empty());
        // Other Laplacian sign: no candidate.
        let train_l = features(&[([100.0, 100.0], -1, a)]);
        assert!(gated_match(&query, &train_l, &[[100.0, 100.0]], 4.0, 12.0, 0.9).is_empty());
        // An ambiguous look-alike 8 px away fails the ratio test; a distinct one does not.
        let a3 = [0.95, -0.05, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        let amb = features(&[([100.0, 100.0], 1, a2), ([108.0, 100.0], 1, a3)]);
        assert!(gated_match(&query, &amb, &[[100.0, 100.0]], 4.0, 12.0, 0.9).is_empty());
        let dis = features(&[([100.0, 100.0], 1, a), ([108.0, 100.0], 1, b)]);
        assert_eq!(
            gated_match(&query, &dis, &[[100.0, 100.0]], 4.0, 12.0, 0.9).len(),
            1
        );
        // Non-finite predictions are skipped.
        assert!(gated_match(&query, &train, &[[f32::NAN, 0.0]], 4.0, 12.0, 0.9).is_empty());
    }

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
