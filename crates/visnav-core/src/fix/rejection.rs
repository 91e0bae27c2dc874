//! Why a fix attempt produced no fix: a typed outcome with its numbers as fields.
//!
//! Every stage of the fix (prior geometry, features, matching, area correlation, placement,
//! solve, relocalisation, the heading search) refuses with a [`Rejection`]. People read its
//! [`Display`](std::fmt::Display) (the check and its values: "only 24 matches where chance gives
//! 10 (need 27)"); counters and metric labels use [`Rejection::class`], a closed set of short
//! names ([`CLASSES`]) that never carries a number. A rejection that wraps others (a heading
//! sweep's best try, the area fallback after the features, the wider heading search after the
//! stated one) is counted by the first check that refused: the class of the attempt tried first.

use std::fmt;

use super::FixMethod;
use super::area::PlaceError;

/// Why a fix attempt produced no fix (module doc).
#[derive(Debug, Clone, PartialEq)]
pub enum Rejection {
    // --- Input and prior ---
    /// The frame's size is not the camera's.
    FrameSize {
        /// The frame's `[width, height]`, pixels.
        frame: [usize; 2],
        /// The camera's `[width, height]`, pixels.
        camera: [u32; 2],
    },
    /// A prior sigma is not finite and positive, or the prior altitude not finite.
    PriorSigmas,
    /// The altitude prior (no position prior) is not finite or has no positive sigma.
    AltitudePrior,
    /// A geodetic conversion failed (`stage` names which; `detail` is the geodesy's message).
    Geodesy {
        /// The conversion that failed.
        stage: &'static str,
        /// The geodesy library's error message.
        detail: String,
    },
    /// The prior altitude is not above the terrain below the camera.
    PriorBelowTerrain {
        /// The prior's camera altitude, metres above mean sea level.
        alt_amsl_m: f64,
    },
    /// The altitude prior is not above the map's terrain (area relocalisation).
    AltitudeBelowMap {
        /// The altitude prior, metres above mean sea level.
        alt_amsl_m: f64,
    },
    /// The frame's rays miss the ground (rectification empty).
    NoGround,
    /// The frame's centre does not see the ground.
    CentreOffGround,
    /// The configuration enables no matching method for this attempt.
    NoMethod,
    /// Area matching is off (`[fix] area_matching = "off"`).
    AreaOff,
    /// The map was built without level images (an older visnav).
    NoLevelImages,
    /// A computed pose or report holds a number that is not finite (`what` names it).
    NonFinite {
        /// The quantity that is not finite.
        what: &'static str,
    },
    /// An internal step failed on data it was given (`stage` names it; `detail` its message).
    Internal {
        /// The step that failed.
        stage: &'static str,
        /// Its error message.
        detail: String,
    },
    /// Refused before the engine ran, by a rule outside it (a simulator's scripted fault).
    Withheld {
        /// The words shown for the refusal.
        reason: &'static str,
    },
    /// A rejection read back from a record (the daemon's fix log): its words and its class as
    /// written ([`Rejection::recorded`]).
    Recorded {
        /// Its class: one of [`CLASSES`], "recorded" when the record's is not.
        class: &'static str,
        /// Its words as recorded.
        reason: String,
    },

    // --- Features ---
    /// Too few frame features on valid ground.
    FewFeatures {
        /// Frame features kept.
        n: usize,
    },
    /// The footprint the prior predicts lies outside the map: `[x0, x1, y0, y1]`, metres.
    FootprintOutsideMap {
        /// The predicted footprint grown by the coarse gate, map grid `[x0, x1, y0, y1]`, metres.
        footprint_m: [f64; 4],
        /// The map's bounds, map grid `[x0, x1, y0, y1]`, metres.
        map_m: [f64; 4],
    },
    /// Too few map features under the footprint.
    FewMapFeatures {
        /// Map features selected under the footprint.
        n: usize,
    },
    /// A relocalisation level holds too few features.
    FewLevelFeatures {
        /// The map level (0 the finest).
        level: usize,
        /// Its features.
        n: usize,
    },
    /// The coarse matches agree on no similarity.
    NoCoarseConsensus {
        /// Coarse matches the similarity was sought among.
        matches: usize,
    },
    /// Fewer fine matches than chance gives plus the margin (the a-contrario count).
    BelowChance {
        /// Fine matches found.
        matches: usize,
        /// Matches the same matching gives against unrelated map areas.
        chance: usize,
        /// The bar: `min_matches` plus `null_factor` times `chance`.
        needed: usize,
    },
    /// A fix of the widened heading search below the chance bar raised for its headings.
    BelowWidenedChance {
        /// Fine matches of the fix.
        matches: usize,
        /// Matches chance gives (as in [`Rejection::BelowChance`]).
        chance: usize,
        /// Heading hypotheses the widened search tried.
        headings: usize,
        /// The bar: the plain chance bar raised by `sqrt(2 chance ln(headings))`.
        needed: usize,
    },
    /// Too few correspondences for the resection.
    FewMatches {
        /// Correspondences found.
        n: usize,
        /// The least the resection takes (`min_matches`).
        min: usize,
    },
    /// Relocalisation: no Hough cluster among the matches.
    NoHoughCluster,
    /// Relocalisation: the largest Hough cluster is too small.
    SmallHoughCluster {
        /// Matches in the largest cluster.
        n: usize,
        /// The least a cluster must hold.
        min: usize,
    },
    /// The resection's checks refused the pose.
    Pose(crate::pose::Rejection),

    // --- Area correlation and the placement fix ---
    /// The rectified frame is too small to correlate.
    ImagesTooSmall,
    /// The map window around the prediction is empty.
    EmptyWindow,
    /// The map image is too small for the area search.
    MapImageTooSmall,
    /// The placement of the frame on the map failed.
    Place(PlaceError),
    /// The correlation surface is undefined at the place.
    CorrelationUndefined,
    /// The placement stands but its patches do not agree on a similarity.
    PatchesDisagree {
        /// The placement's correlation (NCC).
        ncc: f64,
        /// Patches matched before the similarity fit failed.
        agree: usize,
    },
    /// Too few tie points.
    FewTies {
        /// The placement's correlation (NCC).
        ncc: f64,
        /// Tie points found.
        ties: usize,
        /// The least the resection takes (`min_matches`).
        min: usize,
    },
    /// Fewer tie points than chance gives plus the margin.
    TiesBelowChance {
        /// The placement's correlation (NCC).
        ncc: f64,
        /// Tie points found.
        ties: usize,
        /// Tie points chance gives.
        chance: usize,
        /// The bar: `min_matches` plus `null_factor` times `chance`.
        needed: usize,
    },
    /// The placement leads the next place by less than the placement fix's margin.
    PlacementMargin {
        /// The placement's correlation (NCC).
        ncc: f64,
        /// Its lead over the best other place, in NCC.
        lead: f64,
        /// The lead the placement fix needs, in NCC.
        margin: f64,
    },
    /// The places the correlation could not judge hold too much of the prior.
    PlacementUnjudged {
        /// The prior's probability on the unjudged places, percent.
        percent: f64,
    },
    /// Too few of the placement's grid points see the ground.
    FewGridPoints {
        /// Grid points on valid ground.
        n: usize,
    },
    /// The correlation's plateau does not close around the place.
    PlacementOpen {
        /// The plateau's depth below the peak, in NCC.
        delta: f64,
        /// How far the plateau was traced, finest blocks.
        radius_blocks: f64,
    },
    /// A refinement step moved the place too far.
    RefinementMoved {
        /// The refinement grid's block size, pixels.
        block_px: usize,
        /// How far the place moved along the grid axis it moved most, blocks of that grid.
        moved_blocks: f64,
    },
    /// The placement grid's rays miss the terrain.
    RaysMissTerrain,
    /// The tie points failed and so did the placement fix.
    NoPlacementFix {
        /// Why the tie points failed.
        ties: Box<Rejection>,
        /// Why the placement fix failed.
        placement: Box<Rejection>,
    },
    /// A step of the placement failed (`step`: which).
    Step {
        /// The step's name.
        step: &'static str,
        /// Why it failed.
        inner: Box<Rejection>,
    },

    // --- Uniqueness ---
    /// Rectified at its own heading the fix moves to another place.
    MovesAtOwnHeading {
        /// Horizontal distance between the two fixes, metres.
        moved_m: f64,
    },
    /// A competitor has nearly as much evidence.
    Ambiguous {
        /// The fix's matches above chance ([`crate::fix::engine::Attempt::evidence`]).
        evidence: usize,
        /// The fix's heading, degrees.
        heading_deg: f64,
        /// The competitor's matches above chance.
        rival_evidence: usize,
        /// What the competitor is.
        rival: Rival,
        /// How many times the rival's evidence the fix needs.
        ratio: f64,
    },
    /// A placement at another heading correlates nearly as well.
    AmbiguousPlacement {
        /// The placement's correlation (NCC).
        ncc: f64,
        /// The placement's heading, degrees.
        heading_deg: f64,
        /// The rival placement's correlation (NCC).
        rival_ncc: f64,
        /// The heading the rival was rectified at, degrees.
        rival_heading_deg: f64,
        /// The lead the placement needs, in NCC.
        margin: f64,
    },
    /// The area search confirmed two places.
    TwoPlaces {
        /// Horizontal distance between them, metres.
        distance_m: f64,
        /// Their area-search correlations (NCC), the first confirmed first.
        ncc: [f64; 2],
    },
    /// The fix was not confirmed when matched again from its own pose.
    NotConfirmed(Box<Rejection>),
    /// A feature fix too weak to check its own covariance and the area method's fix of the same
    /// frame disagree: the area fix lies outside the feature fix's 3-sigma ellipse.
    MethodsDisagree {
        /// Horizontal distance between the two fixes, metres.
        distance_m: f64,
        /// The area fix's squared Mahalanobis distance in the feature fix's horizontal
        /// covariance.
        d2: f64,
        /// The gate: the chi-square(2) quantile of the 3-sigma probability.
        gate: f64,
    },
    /// A feature fix too weak to check its own covariance that the area method found nothing to
    /// compare with, and that the widened heading search did not confirm (or was not asked).
    Unconfirmed {
        /// Inliers of the feature fix.
        inliers: usize,
        /// Its fine matches.
        matches: usize,
        /// Matches chance gives there.
        chance: usize,
        /// What the widened heading search found instead (None: widening is off,
        /// `widen_heading_sigma_deg = 0`).
        search: Option<Box<Rejection>>,
    },
    /// The area search's fix lies beyond the prior's gate.
    FarFromPrior {
        /// Horizontal distance from the prior, metres.
        distance_m: f64,
        /// The gate: `gate_sigmas` times the combined horizontal sigmas, metres.
        limit_m: f64,
    },
    /// No area-search candidate was confirmed; the best with its correlation.
    NoCandidateConfirmed {
        /// Candidates the search found.
        candidates: usize,
        /// The best refused candidate: its correlation (NCC) and why it was refused.
        best: Option<(f64, Box<Rejection>)>,
    },

    // --- Budgets ---
    /// The area search would need more work than the budget.
    AreaSearchBudget {
        /// The search's estimated work, millions of units.
        needed_mwork: f64,
        /// The budget left, millions of units (`reloc_budget_mwork`).
        budget_mwork: f64,
    },
    /// The map level's pixels exceed the budget.
    MapLevelBudget {
        /// The map level's size, millions of pixels.
        mpixels: f64,
        /// The budget, millions of units (`reloc_budget_mwork`).
        budget_mwork: f64,
    },
    /// The relocalisation budget ran out before a level's hypotheses were all tried.
    WorkBudget {
        /// The budget, millions of units (`reloc_budget_mwork`).
        budget_mwork: f64,
        /// The level being searched.
        level: usize,
        /// The rejection of the last hypothesis tried.
        last: Box<Rejection>,
    },

    // --- Searches over hypotheses ---
    /// No hypothesis was tried.
    NoHypothesis,
    /// No relocalisation level produced a fix.
    NoLevelFix,
    /// At relocalisation level `level`.
    AtLevel {
        /// The map level.
        level: usize,
        /// The rejection there.
        inner: Box<Rejection>,
    },
    /// Relocalisation (no position prior).
    Relocalisation(Box<Rejection>),
    /// A heading sweep: `tried` headings, the rejection of the one that got furthest.
    Headings {
        /// Headings tried.
        tried: usize,
        /// The rejection of the heading that got furthest.
        best: Box<Rejection>,
    },
    /// Each matching method's rejection, in the order tried.
    Methods(Vec<(FixMethod, Rejection)>),
    /// The stated heading failed, then the widened heading (`heading`: its +-3 sigma, degrees)
    /// and the area search of the prior's window (`near`), each when it ran.
    Widened {
        /// The rejection at the heading prior as stated.
        stated: Box<Rejection>,
        /// The widened heading search: its half-width (+-3 sigma, degrees) and rejection.
        heading: Option<(f64, Box<Rejection>)>,
        /// The area search of the prior's window, when it ran.
        near: Option<Box<Rejection>>,
    },
}

/// What a fix competed with in [`Rejection::Ambiguous`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Rival {
    /// An accepted fix at another place, metres away.
    Elsewhere {
        /// Horizontal distance from the fix, metres.
        distance_m: f64,
    },
    /// A hypothesis rectified at another heading, degrees.
    Heading {
        /// The heading it was rectified at, degrees.
        heading_deg: f64,
    },
}

/// Every value [`Rejection::class`] returns: the label set of the rejection metrics.
pub const CLASSES: &[&str] = &[
    "frame_size",
    "invalid_prior",
    "geodesy",
    "below_terrain",
    "no_ground",
    "no_method",
    "old_map",
    "non_finite",
    "internal",
    "few_features",
    "outside_map",
    "few_map_features",
    "no_coarse_consensus",
    "below_chance",
    "below_widened_chance",
    "few_matches",
    "no_hough_cluster",
    "pose_invalid_input",
    "pose_few_correspondences",
    "pose_no_consensus",
    "pose_numerical",
    "pose_few_inliers",
    "pose_inlier_ratio",
    "pose_reprojection",
    "pose_variance_factor",
    "pose_spread",
    "pose_conditioning",
    "pose_horizontal_sigma",
    "pose_vertical_sigma",
    "pose_attitude_sigma",
    "pose_prior_position",
    "pose_prior_attitude",
    "area_too_small",
    "area_undefined",
    "area_weak",
    "area_not_unique",
    "few_ties",
    "ties_below_chance",
    "placement_not_unique",
    "placement_unjudged",
    "placement_off_ground",
    "placement_open",
    "placement_refinement",
    "ambiguous",
    "not_confirmed",
    "far_from_prior",
    "methods_disagree",
    "unconfirmed",
    "no_candidate_confirmed",
    "budget",
    "no_hypothesis",
    "no_level_fix",
    "withheld",
    "recorded",
];

impl Rejection {
    /// The class for counting and metric labels: one of [`CLASSES`]. A rejection wrapping
    /// others has the class of the check that refused first.
    pub fn class(&self) -> &'static str {
        use Rejection::*;
        match self {
            FrameSize { .. } => "frame_size",
            PriorSigmas | AltitudePrior => "invalid_prior",
            Geodesy { .. } => "geodesy",
            PriorBelowTerrain { .. } | AltitudeBelowMap { .. } => "below_terrain",
            NoGround | CentreOffGround => "no_ground",
            NoMethod | AreaOff => "no_method",
            NoLevelImages => "old_map",
            NonFinite { .. } => "non_finite",
            Internal { .. } => "internal",
            Recorded { class, .. } => class,
            Withheld { .. } => "withheld",
            FewFeatures { .. } => "few_features",
            FootprintOutsideMap { .. } => "outside_map",
            FewMapFeatures { .. } | FewLevelFeatures { .. } => "few_map_features",
            NoCoarseConsensus { .. } => "no_coarse_consensus",
            BelowChance { .. } => "below_chance",
            BelowWidenedChance { .. } => "below_widened_chance",
            FewMatches { .. } => "few_matches",
            NoHoughCluster | SmallHoughCluster { .. } => "no_hough_cluster",
            Pose(r) => r.class(),
            ImagesTooSmall | EmptyWindow | MapImageTooSmall => "area_too_small",
            Place(PlaceError::Undefined) | CorrelationUndefined => "area_undefined",
            Place(PlaceError::Weak { .. }) => "area_weak",
            Place(PlaceError::Ambiguous { .. }) => "area_not_unique",
            PatchesDisagree { .. } | FewTies { .. } => "few_ties",
            TiesBelowChance { .. } => "ties_below_chance",
            PlacementMargin { .. } => "placement_not_unique",
            PlacementUnjudged { .. } => "placement_unjudged",
            FewGridPoints { .. } | RaysMissTerrain => "placement_off_ground",
            PlacementOpen { .. } => "placement_open",
            RefinementMoved { .. } => "placement_refinement",
            NoPlacementFix { ties, .. } => ties.class(),
            Step { inner, .. } => inner.class(),
            MovesAtOwnHeading { .. }
            | Ambiguous { .. }
            | AmbiguousPlacement { .. }
            | TwoPlaces { .. } => "ambiguous",
            NotConfirmed(_) => "not_confirmed",
            FarFromPrior { .. } => "far_from_prior",
            MethodsDisagree { .. } => "methods_disagree",
            Unconfirmed { .. } => "unconfirmed",
            NoCandidateConfirmed { .. } => "no_candidate_confirmed",
            AreaSearchBudget { .. } | MapLevelBudget { .. } | WorkBudget { .. } => "budget",
            NoHypothesis => "no_hypothesis",
            NoLevelFix => "no_level_fix",
            AtLevel { inner, .. } | Relocalisation(inner) => inner.class(),
            Headings { best, .. } => best.class(),
            Methods(tried) => tried.first().map_or("no_method", |(_, r)| r.class()),
            Widened { stated, .. } => stated.class(),
        }
    }

    /// A rejection read back from a record: `reason` as written, `class` one of [`CLASSES`]
    /// (anything else, from an older or foreign record, counts as "recorded").
    pub fn recorded(class: &str, reason: &str) -> Self {
        Rejection::Recorded {
            class: CLASSES
                .iter()
                .find(|c| **c == class)
                .copied()
                .unwrap_or("recorded"),
            reason: reason.to_string(),
        }
    }

    /// The rejection `r` a rejected report carries; a report rejected without one (which the
    /// engine never makes) reads as an internal failure, never as a fix.
    pub fn or_unexplained(r: Option<Rejection>) -> Rejection {
        r.unwrap_or(Rejection::Internal {
            stage: "fix report",
            detail: "rejected without a reason".into(),
        })
    }

    /// `self` at relocalisation level `level` ("level 2: ...").
    pub fn at_level(self, level: usize) -> Self {
        Rejection::AtLevel {
            level,
            inner: Box::new(self),
        }
    }

    /// `self` as relocalisation's ("relocalisation: ...").
    pub fn in_relocalisation(self) -> Self {
        Rejection::Relocalisation(Box::new(self))
    }

    /// `self` wrapped as a failed step named `step` ("placement spread: ...").
    pub fn in_step(self, step: &'static str) -> Self {
        Rejection::Step {
            step,
            inner: Box::new(self),
        }
    }
}

impl fmt::Display for Rival {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Rival::Elsewhere { distance_m } => write!(f, "another place {distance_m:.0} m away"),
            Rival::Heading { heading_deg } => write!(f, "heading {heading_deg:.0} deg"),
        }
    }
}

impl fmt::Display for Rejection {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        // Each group writes its own variants and leaves the others to the next.
        self.fmt_input(f)
            .or_else(|| self.fmt_features(f))
            .or_else(|| self.fmt_area(f))
            .or_else(|| self.fmt_search(f))
            .unwrap_or(Ok(()))
    }
}

impl Rejection {
    /// The input, prior and internal rejections' words. None for a variant of another group.
    fn fmt_input(&self, f: &mut fmt::Formatter<'_>) -> Option<fmt::Result> {
        use Rejection::*;
        Some(match self {
            FrameSize { frame, camera } => write!(
                f,
                "frame is {}x{} but the camera is {}x{}",
                frame[0], frame[1], camera[0], camera[1]
            ),
            PriorSigmas => f.write_str("prior sigmas must be finite and positive"),
            AltitudePrior => f.write_str("the altitude prior must be finite with a positive sigma"),
            Geodesy { stage, detail } => write!(f, "{stage}: {detail}"),
            PriorBelowTerrain { alt_amsl_m } => write!(
                f,
                "prior altitude {alt_amsl_m:.1} m AMSL is not above the terrain"
            ),
            AltitudeBelowMap { alt_amsl_m } => write!(
                f,
                "altitude {alt_amsl_m:.1} m AMSL is not above the map's terrain"
            ),
            NoGround => f.write_str("the frame does not see the ground"),
            CentreOffGround => f.write_str("the frame's centre does not see the ground"),
            NoMethod => f.write_str("no matching method enabled"),
            AreaOff => f.write_str("area matching is off"),
            NoLevelImages => {
                f.write_str("the map has no level images (built by an older visnav: rebuild it)")
            }
            NonFinite { what } => write!(f, "{what} has non-finite values"),
            Internal { stage, detail } => write!(f, "{stage}: {detail}"),
            Recorded { reason, .. } => f.write_str(reason),
            Withheld { reason } => f.write_str(reason),
            _ => return None,
        })
    }

    /// The feature path's words. None for a variant of another group.
    fn fmt_features(&self, f: &mut fmt::Formatter<'_>) -> Option<fmt::Result> {
        use Rejection::*;
        Some(match self {
            FewFeatures { n } => write!(f, "only {n} features in the frame"),
            FootprintOutsideMap {
                footprint_m: p,
                map_m: m,
            } => write!(
                f,
                "the frame's footprint (x {:.0}..{:.0}, y {:.0}..{:.0} m, where the prior puts \
                 it) lies outside the map (x {:.0}..{:.0}, y {:.0}..{:.0} m)",
                p[0], p[1], p[2], p[3], m[0], m[1], m[2], m[3]
            ),
            FewMapFeatures { n } => write!(
                f,
                "only {n} map features under the footprint (outside the map?)"
            ),
            FewLevelFeatures { level, n } => write!(f, "level {level} has {n} features"),
            NoCoarseConsensus { matches } => {
                write!(f, "no consistent coarse matches among {matches}")
            }
            BelowChance {
                matches,
                chance,
                needed,
            } => write!(
                f,
                "only {matches} matches where chance gives {chance} (need {needed})"
            ),
            BelowWidenedChance {
                matches,
                chance,
                headings,
                needed,
            } => write!(
                f,
                "its feature fix has {matches} matches where chance gives {chance} at one of \
                 {headings} headings (need {needed})"
            ),
            FewMatches { n, min } => write!(f, "only {n} matches (min {min})"),
            NoHoughCluster => f.write_str("no Hough cluster"),
            SmallHoughCluster { n, min } => {
                write!(f, "largest Hough cluster has {n} matches (min {min})")
            }
            Pose(r) => write!(f, "resection: {r}"),
            _ => return None,
        })
    }

    /// The area correlation's and the placement fix's words. None for a variant of another group.
    fn fmt_area(&self, f: &mut fmt::Formatter<'_>) -> Option<fmt::Result> {
        use Rejection::*;
        Some(match self {
            ImagesTooSmall => f.write_str("area correlation: images too small"),
            EmptyWindow => f.write_str("empty map window"),
            MapImageTooSmall => f.write_str("the map image is too small"),
            Place(e) => write!(f, "{e}"),
            CorrelationUndefined => f.write_str("correlation undefined"),
            PatchesDisagree { ncc, agree } => write!(
                f,
                "area correlation {ncc:.2} placed the frame but only {agree} patches agree"
            ),
            FewTies { ncc, ties, min } => write!(
                f,
                "area correlation {ncc:.2}: only {ties} tie points (min {min})"
            ),
            TiesBelowChance {
                ncc,
                ties,
                chance,
                needed,
            } => write!(
                f,
                "area correlation {ncc:.2}: only {ties} tie points where chance gives {chance} \
                 (need {needed})"
            ),
            PlacementMargin { ncc, lead, margin } => write!(
                f,
                "peak {ncc:.2} ahead of another place by {lead:.2} < {margin}"
            ),
            PlacementUnjudged { percent } => write!(
                f,
                "the places the correlation could not judge (the frame sees beyond the map \
                 there) hold {percent:.1} % of the prior's probability"
            ),
            FewGridPoints { n } => write!(f, "only {n} grid points see the ground"),
            PlacementOpen {
                delta,
                radius_blocks,
            } => write!(
                f,
                "the correlation does not settle the place: it stays within {delta} of its peak \
                 {radius_blocks} blocks away (an edge or uniform ground)"
            ),
            RefinementMoved {
                block_px,
                moved_blocks,
            } => write!(
                f,
                "refinement on {block_px} px blocks moved the place by {moved_blocks:.1} blocks"
            ),
            RaysMissTerrain => f.write_str("the grid's rays miss the terrain"),
            NoPlacementFix { ties, placement } => {
                write!(f, "{ties}; no placement fix: {placement}")
            }
            Step { step, inner } => write!(f, "{step}: {inner}"),
            _ => return None,
        })
    }

    /// The uniqueness, budget and search rejections' words. None for a variant of another group.
    fn fmt_search(&self, f: &mut fmt::Formatter<'_>) -> Option<fmt::Result> {
        use Rejection::*;
        Some(match self {
            MovesAtOwnHeading { moved_m } => write!(
                f,
                "ambiguous: rectified at its own heading the fix moves {moved_m:.0} m"
            ),
            Ambiguous {
                evidence,
                heading_deg,
                rival_evidence,
                rival,
                ratio,
            } => write!(
                f,
                "ambiguous: {evidence} matches above chance at heading {heading_deg:.0} deg \
                 against {rival_evidence} at {rival} (need {ratio:.1} times)"
            ),
            AmbiguousPlacement {
                ncc,
                heading_deg,
                rival_ncc,
                rival_heading_deg,
                margin,
            } => write!(
                f,
                "ambiguous: placement {ncc:.2} at heading {heading_deg:.0} deg against \
                 {rival_ncc:.2} at heading {rival_heading_deg:.0} deg (need a lead of {margin})"
            ),
            TwoPlaces { distance_m, ncc } => write!(
                f,
                "ambiguous: the area search confirmed two places {distance_m:.0} m apart \
                 (correlations {:.2} and {:.2})",
                ncc[0], ncc[1]
            ),
            NotConfirmed(inner) => write!(f, "not confirmed from its own pose: {inner}"),
            MethodsDisagree {
                distance_m,
                d2,
                gate,
            } => write!(
                f,
                "the feature fix (too few inliers to check its covariance) and the area fix lie \
                 {distance_m:.1} m apart, outside the feature fix's 3 sigma (d^2 {d2:.1} > \
                 {gate:.1})"
            ),
            Unconfirmed {
                inliers,
                matches,
                chance,
                search,
            } => {
                let head = format!(
                    "a feature fix too weak to check ({inliers} inliers, {matches} matches where \
                     chance gives {chance}) with no area fix to hold it against"
                );
                match search {
                    Some(r) => write!(f, "{head}; the widened heading search: {r}"),
                    None => write!(f, "{head}; the heading search is off"),
                }
            }
            FarFromPrior {
                distance_m,
                limit_m,
            } => write!(
                f,
                "its fix lies {distance_m:.0} m from the prior, beyond {limit_m:.0} m (3 sigma)"
            ),
            NoCandidateConfirmed { candidates, best } => match best {
                Some((ncc, r)) => write!(
                    f,
                    "area search: none of {candidates} candidates confirmed (best, correlation \
                     {ncc:.2}: {r})"
                ),
                None => write!(f, "area search: none of {candidates} candidates confirmed"),
            },
            AreaSearchBudget {
                needed_mwork,
                budget_mwork,
            } => write!(
                f,
                "the area search needs about {needed_mwork:.0} million work units, more than \
                 the budget (reloc_budget_mwork = {budget_mwork})"
            ),
            MapLevelBudget {
                mpixels,
                budget_mwork,
            } => write!(
                f,
                "the map level's {mpixels:.0} million pixels exceed the budget \
                 (reloc_budget_mwork = {budget_mwork})"
            ),
            WorkBudget {
                budget_mwork,
                level,
                last,
            } => write!(
                f,
                "work budget of {budget_mwork} million units spent before every hypothesis at \
                 level {level} was tried (last: {last})"
            ),
            NoHypothesis => f.write_str("no hypothesis tried"),
            NoLevelFix => f.write_str("no level produced a fix"),
            AtLevel { level, inner } => write!(f, "level {level}: {inner}"),
            Relocalisation(inner) => write!(f, "relocalisation: {inner}"),
            Headings { tried, best } => write!(f, "{tried} headings tried, best: {best}"),
            Methods(tried) => fmt_methods(tried, f),
            Widened {
                stated,
                heading,
                near,
            } => fmt_widened(stated, heading.as_ref(), near.as_deref(), f),
            _ => return None,
        })
    }
}

/// Each method's rejection in the order tried; with two, the area's labelled as such.
fn fmt_methods(tried: &[(FixMethod, Rejection)], f: &mut fmt::Formatter<'_>) -> fmt::Result {
    for (i, (method, r)) in tried.iter().enumerate() {
        if i > 0 {
            f.write_str("; ")?;
        }
        if tried.len() > 1 && *method != FixMethod::Features {
            write!(f, "{method}: ")?;
        }
        write!(f, "{r}")?;
    }
    Ok(())
}

/// The stated heading's rejection, then the widened searches' that ran.
fn fmt_widened(
    stated: &Rejection,
    heading: Option<&(f64, Box<Rejection>)>,
    near: Option<&Rejection>,
    f: &mut fmt::Formatter<'_>,
) -> fmt::Result {
    write!(f, "{stated}")?;
    if let Some((deg, why)) = heading {
        write!(f, "; heading widened to +-{deg:.0} deg: {why}")?;
    }
    if let Some(why) = near {
        write!(f, "; area search of the prior's window: {why}")?;
    }
    Ok(())
}

impl std::error::Error for Rejection {}

impl From<crate::pose::Rejection> for Rejection {
    fn from(r: crate::pose::Rejection) -> Self {
        Rejection::Pose(r)
    }
}

impl From<PlaceError> for Rejection {
    fn from(e: PlaceError) -> Self {
        Rejection::Place(e)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn examples() -> Vec<Rejection> {
        use Rejection::*;
        let chance = BelowChance {
            matches: 24,
            chance: 10,
            needed: 27,
        };
        vec![
            FrameSize {
                frame: [100, 100],
                camera: [640, 480],
            },
            PriorSigmas,
            PriorBelowTerrain { alt_amsl_m: 580.1 },
            FewFeatures { n: 3 },
            chance.clone(),
            Pose(crate::pose::Rejection::TooFewInliers {
                inliers: 9,
                min: 12,
            }),
            Place(PlaceError::Weak { ncc: 0.11 }),
            NoPlacementFix {
                ties: Box::new(FewTies {
                    ncc: 0.45,
                    ties: 5,
                    min: 12,
                }),
                placement: Box::new(PlacementOpen {
                    delta: 0.05,
                    radius_blocks: 8.0,
                }),
            },
            Widened {
                stated: Box::new(Methods(vec![
                    (FixMethod::Features, chance.clone()),
                    (FixMethod::Area, Place(PlaceError::Undefined)),
                ])),
                heading: Some((
                    90.0,
                    Box::new(Headings {
                        tried: 13,
                        best: Box::new(FewFeatures { n: 4 }),
                    }),
                )),
                near: Some(Box::new(NoCandidateConfirmed {
                    candidates: 4,
                    best: None,
                })),
            },
            Relocalisation(Box::new(WorkBudget {
                budget_mwork: 400.0,
                level: 2,
                last: Box::new(AtLevel {
                    level: 2,
                    inner: Box::new(NoHoughCluster),
                }),
            })),
            MethodsDisagree {
                distance_m: 24.96,
                d2: 17.3,
                gate: 11.83,
            },
            Unconfirmed {
                inliers: 12,
                matches: 37,
                chance: 14,
                search: Some(Box::new(Ambiguous {
                    evidence: 23,
                    heading_deg: 312.0,
                    rival_evidence: 20,
                    rival: Rival::Heading { heading_deg: 340.0 },
                    ratio: 1.5,
                })),
            },
        ]
    }

    /// Every class is in the closed label set and has no digit; a wrapper counts as the check
    /// that refused first.
    #[test]
    fn classes_are_closed_and_numberless() {
        for r in examples() {
            let c = r.class();
            assert!(CLASSES.contains(&c), "{c} of {r}");
            assert!(!c.chars().any(|ch| ch.is_ascii_digit()), "{c}");
        }
        for c in CLASSES {
            assert!(
                c.chars().all(|ch| ch.is_ascii_lowercase() || ch == '_'),
                "{c}"
            );
        }
        let e = examples();
        assert_eq!(e[7].class(), "few_ties");
        assert_eq!(e[8].class(), "below_chance");
        assert_eq!(e[9].class(), "budget");
        assert_eq!(e[5].class(), "pose_few_inliers");
        assert_eq!(e[10].class(), "methods_disagree");
        assert_eq!(e[11].class(), "unconfirmed");
        // Read back from a record: its class when it is one, otherwise "recorded".
        let back = Rejection::recorded(e[4].class(), &e[4].to_string());
        assert_eq!(
            (back.class(), back.to_string()),
            (e[4].class(), e[4].to_string())
        );
        assert_eq!(Rejection::recorded("made up", "x").class(), "recorded");
    }

    /// What people read names the check and its numbers, each wrapper with its own words.
    #[test]
    fn display_names_the_check_and_its_numbers() {
        let e = examples();
        assert_eq!(
            e[10].to_string(),
            "the feature fix (too few inliers to check its covariance) and the area fix lie 25.0 \
             m apart, outside the feature fix's 3 sigma (d^2 17.3 > 11.8)"
        );
        assert_eq!(
            e[4].to_string(),
            "only 24 matches where chance gives 10 (need 27)"
        );
        assert_eq!(
            e[5].to_string(),
            "resection: inlier count check failed: 9 inliers < minimum 12"
        );
        assert_eq!(
            e[8].to_string(),
            "only 24 matches where chance gives 10 (need 27); area: area correlation undefined \
             (no textured overlap); heading widened to +-90 deg: 13 headings tried, best: only 4 \
             features in the frame; area search of the prior's window: area search: none of 4 \
             candidates confirmed"
        );
        assert!(
            e[9].to_string().starts_with(
                "relocalisation: work budget of 400 million units spent before every hypothesis \
                 at level 2 was tried (last: level 2: no Hough cluster)"
            ),
            "{}",
            e[9]
        );
    }
}
