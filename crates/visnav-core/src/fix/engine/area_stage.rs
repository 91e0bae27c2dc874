//! The area stage of a fix with a position prior (docs/fix.md, "Area correlation"): the rectified
//! frame is placed in the map level's image by the masked correlation of [`crate::fix::area`]
//! over the prior's gate, then tie points of small patches are found in two passes (first near
//! the frame's centre, where a similarity fitted to them absorbs the prior's rotation and scale
//! errors, then everywhere around the final similarity's prediction) and counted against the
//! ties chance gives with the predictions displaced (the features' a-contrario rule).
//!
//! Every stage that runs in parallel takes its results in a fixed order, so the tie points do not
//! depend on the number of threads.

use nalgebra::Point2;
use rayon::prelude::*;

use super::{Attempt, FixEngine, Pair, View};
use crate::fix::Rejection;
use crate::fix::area::{
    Integral, MIN_TIE_NCC, MIN_TIE_NCC_NEAR, Patch, PlaceError, Plane, TieMatch, TieSearch,
    TwoChannels, UNIQUE_MARGIN, UNIQUE_RADIUS_COARSE_PX, best_similar, match_patch, place_similar,
    rank_hypotheses, select_patches, similar_surface, unjudged_places,
};
use crate::fix::reference::LevelWindow;
use crate::pose::similarity::{Sim2, ransac_similarity};

/// The area placement runs on block means bringing the rectified frame's longer side to at most
/// this many pixels: enough pattern for a unique peak, and FFTs of a few hundred pixels a side.
const AREA_COARSE_TEMPLATE_PX: usize = 128;
/// Tie-point patch side, level pixels (odd): large enough to correlate across dates, small
/// enough that relief and the prior's rotation barely distort it.
const AREA_PATCH_PX: usize = 31;
/// Smallest Shi-Tomasi corner strength of a patch (grey levels^2 per pixel): below it the patch
/// is too flat or one-directional to localise (sensor noise alone gives about 1).
const AREA_MIN_CORNER_STRENGTH: f64 = 4.0;
/// Patch grid step, level pixels.
const AREA_PATCH_STEP_PX: usize = 16;
/// At most this many patches per frame (the strongest corners).
const AREA_MAX_PATCHES: usize = 400;
/// Pass 1 searches a patch only when its search radius (placement uncertainty + the rotation
/// and scale still possible at its distance) stays within this many pixels.
const AREA_PASS1_MAX_RADIUS_PX: f64 = 12.0;
/// The placement fix needs its placement ahead of every other place by this correlation margin
/// (twice the placement's [`crate::fix::area::UNIQUE_MARGIN`]): no tie point confirms it. On
/// the NAIP cross-date bench the placements of the frames the tie points miss lead by
/// 0.15-0.41 (all at the true place).
pub(super) const PLACEMENT_FIX_MARGIN: f64 = 0.1;
/// The placement fix needs the places of the prior's gate judged: where the frame overlaps too
/// little of the map (it sees beyond the map's edge) the correlation is undefined, so the true
/// place may be one of those and the runner-up says nothing about it (NAIP same-imagery, a
/// frame half beyond the map's north edge: 71 % of the gate unjudged, the peak 0.32 ahead of
/// the judged places by 0.19 and 96 m from the truth). The unjudged places may hold at most
/// this much of the position prior's probability: about what the gate itself leaves out (+-3
/// sigma per axis holds 99.46 % of a 2-D Gaussian). The tie points' count against chance
/// still confirms a placement there; only the unconfirmed placement fix is refused.
const PLACEMENT_MAX_UNJUDGED_MASS: f64 = 0.005;
/// The placement fix refines the placement down to the grid on which the rectified frame's
/// longer side has at most this many pixels: a few hundred pixels of pattern localise the
/// peak to a fraction of a block, and the FFTs stay small.
const PLACEMENT_REFINE_MAX_TEMPLATE_PX: usize = 256;
/// A refinement step searches this far (finer blocks) around the coarser place: the coarser
/// peak is within one coarse block (two finer ones) of the true place.
const PLACEMENT_REFINE_MARGIN_PX: f64 = 3.0;
/// Farthest a refinement step may move the place, finer blocks along each grid axis: the
/// coarser peak's cell and its sub-block offset put the true place within one coarser block
/// (two finer) per axis, because the grid quantises each axis apart; a place one coarser block
/// off along both axes lies 2.8 finer blocks away. Bounded by the straight-line distance
/// instead, the step refused 76 of the 401 frames one `drone_naip` flight refused, nearly all moved 2.0-2.5 finer
/// blocks (changed ground, where the coarse peak is broad).
const PLACEMENT_REFINE_MAX_MOVE_PX: f64 = PLACEMENT_REFINE_MARGIN_PX - 1.0;
/// Localisation sigma of the refined placement's peak, in blocks of its finest grid (a
/// sub-pixel parabola peak on a correlation surface a block or two wide), to which the spread
/// of the places it cannot tell from the peak is added ([`PLACEMENT_SPREAD_DELTA`]).
const PLACEMENT_SIGMA_PX: f64 = 0.5;
/// Places whose correlation lies within this of the refined peak's are places the correlation
/// cannot tell apart from it: the same margin by which a placement must beat every distinct
/// place ([`UNIQUE_MARGIN`]). Where the ground changed between the map's date and the frame's,
/// or the frame sees one straight field edge, the peak is a plateau or a ridge, and the
/// placement is uncertain over all of it, not over the peak's parabola.
const PLACEMENT_SPREAD_DELTA: f64 = UNIQUE_MARGIN;
/// The plateau is traced this many finest blocks around the peak; one that reaches further
/// (an edge, a uniform area) leaves the place unsettled and the placement fix is refused.
const PLACEMENT_SPREAD_RADIUS_PX: f64 = 8.0;
/// The observations: a grid of this many points per side over the rectified frame.
const PLACEMENT_GRID: usize = 5;
/// At least this many grid points must see valid ground.
const PLACEMENT_MIN_OBS: usize = 6;

/// Placement hypotheses: log-scale and rotation steps (about one coarse pixel at the edge of a
/// template of [`AREA_COARSE_TEMPLATE_PX`]) and the largest errors searched.
const AREA_LOG_SCALE_STEP: f64 = 0.03;
const AREA_ROT_STEP_RAD: f64 = 0.035;
const AREA_MAX_LOG_SCALE: f64 = 0.15;
const AREA_MAX_ROT_RAD: f64 = 0.2;
/// At most this many hypotheses are placed on the full coarse grid; more are first ranked by their
/// correlation peak on a grid twice as coarse (a competitor that matters there ranks high too)...
const AREA_PLACEMENT_HYPOTHESES: usize = 4;
/// ...when the frame still has this many pixels along its longer side on that grid.
const AREA_RANKING_TEMPLATE_MIN_PX: usize = 40;
/// Pass 1 stops once this many tie points have fixed the similarity (a least-squares fit over
/// 40 points spread over the frame's centre predicts the rest to a fraction of a pixel).
const AREA_PASS1_ENOUGH_TIES: usize = 40;
/// Pass 1 must give at least this many tie points consistent with one similarity.
const AREA_PASS1_MIN_TIES: usize = 6;
/// Pass-1 patches searched together (in parallel, speculatively) with one similarity: a refit
/// discards the rest of its batch, so a batch is kept small against the refits' spacing.
const AREA_PASS1_BATCH: usize = 8;
/// Consistency tolerance of the pass-1 similarity, pixels.
const AREA_TIE_TOLERANCE_PX: f64 = 1.5;
/// Pass 2 search radius around the similarity's prediction, pixels.
const AREA_PASS2_RADIUS_PX: usize = 2;
/// Displacement of the tie points' predictions for their chance count (rectified pixels): three
/// times the widest pass-1 search radius, so the displaced searches look at ground the placement
/// did not choose (the features' check displaces by three times their widest gate likewise).
const AREA_NULL_SHIFT_PX: f32 = 3.0 * AREA_PASS1_MAX_RADIUS_PX as f32;

/// Placement hypotheses `(scale, rotation)` covering `+-max_log_scale` and `+-max_rot_rad` in
/// steps of [`AREA_LOG_SCALE_STEP`] and [`AREA_ROT_STEP_RAD`] (the identity first).
fn similarity_hypotheses(max_log_scale: f64, max_rot_rad: f64) -> Vec<(f64, f64)> {
    let ns = (max_log_scale / AREA_LOG_SCALE_STEP).round() as i64;
    let nr = (max_rot_rad / AREA_ROT_STEP_RAD).round() as i64;
    let mut out = Vec::new();
    for i in -ns..=ns {
        for j in -nr..=nr {
            out.push((
                (i as f64 * AREA_LOG_SCALE_STEP).exp(),
                j as f64 * AREA_ROT_STEP_RAD,
            ));
        }
    }
    out.sort_by(|a, b| (a.0.ln().abs() + a.1.abs()).total_cmp(&(b.0.ln().abs() + b.1.abs())));
    out
}

/// The pixel at the centre of block coordinate `c` on the grid of `f x f` blocks (block `c`
/// covers pixels `c f ..= c f + f - 1`).
fn block_to_px(c: f64, f: usize) -> f64 {
    c * f as f64 + (f as f64 - 1.0) / 2.0
}

/// The block coordinate of pixel `u` on the grid of `f x f` blocks ([`block_to_px`]'s inverse).
fn px_to_block(u: f64, f: usize) -> f64 {
    (u - (f as f64 - 1.0) / 2.0) / f as f64
}

/// A template and the window's crop around its current place ([`AreaSearch::crop_about`]).
struct Crop {
    /// The template's two channels on the block grid.
    t: [Plane; 2],
    /// The window's two channels, cropped.
    c: [Plane; 2],
    /// Where the current place puts the template's centre, window blocks.
    expected: [f64; 2],
    /// The crop's top-left, window blocks.
    x0: i64,
    y0: i64,
}

/// What the stages share: the map window searched and the prior's prediction into it.
struct AreaSearch<'a> {
    engine: &'a FixEngine,
    v: &'a View<'a>,
    img: LevelWindow<'a>,
    /// The level image inside the prior's gate around the frame's footprint, and its sums.
    window: Plane,
    sums: Integral,
    /// The window's top-left pixel in the level image.
    x0: i64,
    y0: i64,
}

/// A tie-point patch and the window pixel the prior predicts for its centre (computed once:
/// each pass and each chance count searches around it).
struct TiePatch {
    patch: Patch,
    q: [f64; 2],
}

impl TiePatch {
    fn q_f32(&self) -> [f32; 2] {
        [self.q[0] as f32, self.q[1] as f32]
    }
}

/// The placement as a similarity from predicted window pixels to found ones.
#[derive(Clone, Copy)]
struct Placed {
    sim: Sim2,
    /// Block size of the coarse grid the placement ran on, rectified pixels.
    f: usize,
    /// The template's centre, rectified pixels.
    centre: [f64; 2],
    ncc: f64,
    /// The best other place's correlation on the placement grid.
    runner_up: f64,
    /// The prior's probability that the frame lies where the placement could not judge it (it
    /// overlapped too little of the map there, [`crate::fix::area::Surface::unjudged`]).
    unjudged_prior_mass: f64,
}

/// What the area stage found: tie points for the resection, or, when too few tie points were
/// found but the placement was clearly unique, the refined placement for the placement fix.
pub(super) enum AreaOutcome {
    Ties(Vec<Pair>),
    Placement(PlacementObs),
}

/// The refined placement as observations: the map ground (grid x, y) that a grid of frame
/// pixels sees through it, with the placement's resolution.
pub(super) struct PlacementObs {
    /// (distorted frame pixel, map grid x and y of the ground it sees).
    pub obs: Vec<(Point2<f64>, [f64; 2])>,
    /// Localisation covariance of the placement on the ground, map grid (x, y), m^2.
    pub cov_h_m2: [[f64; 2]; 2],
    /// Sigmas of its rotation (rad, the finest hypothesis step: the peak is not interpolated
    /// between hypotheses) and log scale (the placement's step, 0.03: the scale is not refined;
    /// NAIP 1200-1600 m, 21 placement fixes: 0.017 RMS off).
    pub sigma_rot_rad: f64,
    pub sigma_log_scale: f64,
    /// Why the tie points failed (kept for the report when the placement fix fails too).
    pub ties_rejection: Rejection,
}

impl FixEngine {
    /// Area correspondences (module doc); with `placement_fix`, a unique placement whose tie
    /// points fail becomes a [`PlacementObs`].
    pub(super) fn area_pairs(
        &self,
        v: &View,
        a: &mut Attempt,
        placement_fix: bool,
    ) -> Result<AreaOutcome, Rejection> {
        let frame = v.rect.plane().ok_or(Rejection::NoGround)?;
        let s = AreaSearch::new(self, v)?;
        let (tc, wc) = rayon::join(|| TwoChannels::new(&frame), || TwoChannels::new(&s.window));
        let placed = s.place(&tc, &wc, a)?;
        match s.ties(&frame, &placed, a) {
            Ok(pairs) => Ok(AreaOutcome::Ties(pairs)),
            Err(e) if placement_fix => match s.placement(&frame, &tc, &wc, &placed, e.clone()) {
                Ok(obs) => Ok(AreaOutcome::Placement(obs)),
                Err(p) => Err(Rejection::NoPlacementFix {
                    ties: Box::new(e),
                    placement: Box::new(p),
                }),
            },
            Err(e) => Err(e),
        }
    }
}

impl<'a> AreaSearch<'a> {
    /// The window: the rectified grid is the map's (north-up, the level's pixel) up to the
    /// prior's errors, so the frame's centre's ground point anchors it, grown by the gate.
    fn new(engine: &'a FixEngine, v: &'a View<'a>) -> Result<Self, Rejection> {
        let rect = v.rect;
        let (uc, vc) = (rect.width() as f64 / 2.0, rect.height() as f64 / 2.0);
        let centre = engine
            .ground_of(v, uc, vc)
            .ok_or(Rejection::CentreOffGround)?;
        let gsd_m = engine.levels_gsd_m[v.level];
        let gate_px = (engine.gate_m(v) / gsd_m).ceil();
        // The map under the window below, a pixel beyond it on every side.
        let (half_w_m, half_h_m) = ((uc + gate_px + 2.0) * gsd_m, (vc + gate_px + 2.0) * gsd_m);
        let held = engine
            .reference
            .level_window(
                v.level,
                [
                    centre[0] - half_w_m,
                    centre[1] - half_h_m,
                    centre[0] + half_w_m,
                    centre[1] + half_h_m,
                ],
            )
            .ok_or(Rejection::NoLevelImages)?;
        let img = held.image();
        let c_px = img.to_px(centre[0], centre[1]);
        let x0 = (c_px[0] - uc - gate_px).floor() as i64;
        let y0 = (c_px[1] - vc - gate_px).floor() as i64;
        let (ww, wh) = (
            rect.width() + 2 * gate_px as usize + 2,
            rect.height() + 2 * gate_px as usize + 2,
        );
        let window = img.crop(x0, y0, ww, wh).ok_or(Rejection::EmptyWindow)?;
        let sums = Integral::new(&window);
        Ok(Self {
            engine,
            v,
            img: held,
            window,
            sums,
            x0,
            y0,
        })
    }

    /// The tie points of the placement (two passes) and their count against chance.
    fn ties(
        &self,
        frame: &Plane,
        placed: &Placed,
        a: &mut Attempt,
    ) -> Result<Vec<Pair>, Rejection> {
        let engine = self.engine;
        let patches: Vec<TiePatch> = select_patches(
            frame,
            AREA_PATCH_PX,
            AREA_PATCH_STEP_PX,
            AREA_MIN_CORNER_STRENGTH,
            AREA_MAX_PATCHES,
        )
        .into_par_iter()
        .filter_map(|patch| {
            let q = self.predict(patch.cx as f64, patch.cy as f64)?;
            Some(TiePatch { patch, q })
        })
        .collect();
        let (sim, found) = self.pass1(placed, &patches)?;
        let pairs = self.pass2(&sim, &patches, &found);
        a.area_ties = pairs.len();
        a.pairs
            .extend(pairs.iter().map(|p| ([p.frame_px.x, p.frame_px.y], p.map)));
        let min = engine.params.min_matches;
        if pairs.len() < min {
            return Err(Rejection::FewTies {
                ncc: placed.ncc,
                ties: pairs.len(),
                min,
            });
        }
        let null = self.chance(&sim, &patches);
        a.area_null_ties = null;
        let needed = min + (engine.params.null_factor * null as f64).ceil() as usize;
        if pairs.len() < needed {
            return Err(Rejection::TiesBelowChance {
                ncc: placed.ncc,
                ties: pairs.len(),
                chance: null,
                needed,
            });
        }
        Ok(pairs)
    }

    /// Window pixel of the ground seen at rectified pixel `(u, vv)`, predicted from the prior.
    fn predict(&self, u: f64, vv: f64) -> Option<[f64; 2]> {
        let p = self.engine.ground_of(self.v, u, vv)?;
        let m = self.img.image().to_px(p[0], p[1]);
        Some([m[0] - self.x0 as f64, m[1] - self.y0 as f64])
    }

    /// Patch `t` searched within `radius` of `sim`'s prediction displaced by `offset` (window
    /// pixels).
    fn search(
        &self,
        t: &TiePatch,
        sim: &Sim2,
        offset: [f32; 2],
        radius: usize,
        min_ncc: f64,
    ) -> Option<TieMatch> {
        let s = sim.apply(t.q_f32());
        let search = TieSearch {
            centre_px: [
                (s[0] + offset[0]).round() as i64,
                (s[1] + offset[1]).round() as i64,
            ],
            radius_px: radius,
            min_ncc,
        };
        match_patch(&self.window, &self.sums, &t.patch, search)
    }

    /// Placement on a coarse grid (block means of f x f pixels, grey values and gradients)
    /// over the prior's scale (height) and rotation (heading, tilt) errors; with many
    /// hypotheses, a first look on a grid twice as coarse keeps the most promising few.
    fn place(
        &self,
        frame2: &TwoChannels,
        window2: &TwoChannels,
        a: &mut Attempt,
    ) -> Result<Placed, Rejection> {
        let (rect, v) = (self.v.rect, self.v);
        let mut f = 1usize;
        while rect.width().max(rect.height()) / f > AREA_COARSE_TEMPLATE_PX {
            f *= 2;
        }
        let (Some(tc), Some(wc)) = (frame2.at(f), window2.at(f)) else {
            return Err(Rejection::ImagesTooSmall);
        };
        let g = v.g;
        let hyps = similarity_hypotheses(
            (3.0 * g.sigma_v_m / v.agl_m).min(AREA_MAX_LOG_SCALE),
            (3.0 * g.sigma_yaw_rad.max(g.sigma_tilt_rad)).min(AREA_MAX_ROT_RAD),
        );
        let hyps = match (frame2.at(2 * f), window2.at(2 * f)) {
            (Some(t1), Some(w1))
                if hyps.len() > AREA_PLACEMENT_HYPOTHESES
                    && rect.width().max(rect.height()) / (2 * f)
                        >= AREA_RANKING_TEMPLATE_MIN_PX =>
            {
                rank_hypotheses(&[(&w1[0], &t1[0]), (&w1[1], &t1[1])], &hyps)
                    .into_iter()
                    .take(AREA_PLACEMENT_HYPOTHESES)
                    .map(|(i, _)| hyps[i])
                    .collect()
            }
            _ => hyps,
        };
        let channels = [(&wc[0], &tc[0]), (&wc[1], &tc[1])];
        let placed = place_similar(&channels, &hyps, UNIQUE_RADIUS_COARSE_PX).map_err(|e| {
            // A failed placement still says how well the frame correlates here (a heading
            // sweep weighs it against a placement fix at another heading).
            if let PlaceError::Weak { ncc } | PlaceError::Ambiguous { ncc, .. } = e {
                a.area_ncc = ncc;
            }
            Rejection::Place(e)
        })?;
        a.area_ncc = placed.ncc;
        a.area_runner_up = placed.runner_up;
        let at = self.placed_at(
            f,
            [tc[0].width, tc[0].height],
            placed.centre,
            (placed.scale, placed.theta_rad),
            placed.ncc,
            placed.runner_up,
        )?;
        // Undefined (not at a peak just found) counts as all of the prior: no placement fix,
        // the tie points still tried.
        let unjudged_prior_mass = if placed.unjudged_fraction > 0.0 {
            unjudged_places(&channels, (placed.scale, placed.theta_rad))
                .and_then(|p| self.prior_mass(f, [tc[0].width, tc[0].height], &p).ok())
                .unwrap_or(1.0)
        } else {
            0.0
        };
        Ok(Placed {
            unjudged_prior_mass,
            ..at
        })
    }

    /// The position prior's probability of the template centres `places` (cells of the grid of
    /// `f x f` blocks, the template `size` blocks): its Gaussian density at each cell's centre
    /// times the cell's area, summed (at most 1).
    fn prior_mass(
        &self,
        f: usize,
        size: [usize; 2],
        places: &[[f64; 2]],
    ) -> Result<f64, Rejection> {
        let (_, q) = self.predicted_centre(f, size)?;
        let (qx, qy) = (px_to_block(q[0], f), px_to_block(q[1], f));
        let sigma = (self.v.g.sigma_h_m / (self.img.image().gsd_m * f as f64)).max(1e-6);
        let norm = 1.0 / (std::f64::consts::TAU * sigma * sigma);
        let mass: f64 = places
            .iter()
            .map(|p| {
                let d2 = (p[0] - qx).powi(2) + (p[1] - qy).powi(2);
                norm * (-0.5 * d2 / (sigma * sigma)).exp()
            })
            .sum();
        Ok(mass.min(1.0))
    }

    /// The centre of a template of `size` blocks of `f x f` pixels, in rectified pixels, and the
    /// window pixel the prior predicts for the ground it sees.
    fn predicted_centre(
        &self,
        f: usize,
        size: [usize; 2],
    ) -> Result<([f64; 2], [f64; 2]), Rejection> {
        let t_c = [
            block_to_px((size[0] as f64 - 1.0) / 2.0, f),
            block_to_px((size[1] as f64 - 1.0) / 2.0, f),
        ];
        let q = self
            .predict(t_c[0], t_c[1])
            .ok_or(Rejection::CentreOffGround)?;
        Ok((t_c, q))
    }

    /// The placement of a template of `size` pixels on the grid of `f x f` blocks whose centre
    /// lies at window pixel `centre` of that grid, the template scaled and rotated by
    /// `(scale, theta)`, as a similarity from predicted to found window pixels.
    fn placed_at(
        &self,
        f: usize,
        size: [usize; 2],
        centre: [f64; 2],
        (scale, theta): (f64, f64),
        ncc: f64,
        runner_up: f64,
    ) -> Result<Placed, Rejection> {
        let (t_c, q_c) = self.predicted_centre(f, size)?;
        let w_c = [block_to_px(centre[0], f), block_to_px(centre[1], f)];
        let mut sim = Sim2 {
            scale: scale as f32,
            theta_rad: theta as f32,
            t: [0.0, 0.0],
        };
        let r_qc = sim.apply([q_c[0] as f32, q_c[1] as f32]);
        sim.t = [w_c[0] as f32 - r_qc[0], w_c[1] as f32 - r_qc[1]];
        Ok(Placed {
            sim,
            f,
            centre: t_c,
            ncc,
            runner_up,
            unjudged_prior_mass: 0.0,
        })
    }

    /// The placement fix's observations: the placement refined on grids twice as fine down to
    /// [`PLACEMENT_REFINE_MAX_TEMPLATE_PX`], each around the coarser one's place, scale and
    /// rotation; then the ground a grid of the frame's valid pixels sees through it. Only a
    /// placement unique by [`PLACEMENT_FIX_MARGIN`] qualifies (no tie point confirms it).
    fn placement(
        &self,
        frame: &Plane,
        tc: &TwoChannels,
        wc: &TwoChannels,
        placed: &Placed,
        ties_rejection: Rejection,
    ) -> Result<PlacementObs, Rejection> {
        if placed.ncc - placed.runner_up < PLACEMENT_FIX_MARGIN {
            return Err(Rejection::PlacementMargin {
                ncc: placed.ncc,
                lead: placed.ncc - placed.runner_up,
                margin: PLACEMENT_FIX_MARGIN,
            });
        }
        if placed.unjudged_prior_mass > PLACEMENT_MAX_UNJUDGED_MASS {
            return Err(Rejection::PlacementUnjudged {
                percent: 100.0 * placed.unjudged_prior_mass,
            });
        }
        let longer = self.v.rect.width().max(self.v.rect.height());
        let (mut cur, mut rot_step) = (*placed, AREA_ROT_STEP_RAD);
        while cur.f > 1 && longer / (cur.f / 2) <= PLACEMENT_REFINE_MAX_TEMPLATE_PX {
            rot_step /= 2.0;
            cur = self.refine(tc, wc, &cur, rot_step)?;
        }
        let mut obs = Vec::new();
        let n = PLACEMENT_GRID;
        for i in 0..n {
            for j in 0..n {
                let u = (i as f64 + 0.5) / n as f64 * frame.width as f64;
                let vv = (j as f64 + 0.5) / n as f64 * frame.height as f64;
                if !frame.valid[frame.idx(u as usize, vv as usize)] {
                    continue;
                }
                let (Some(q), Some(px)) = (self.predict(u, vv), self.v.rect.to_frame_px(u, vv))
                else {
                    continue;
                };
                let w = cur.sim.apply([q[0] as f32, q[1] as f32]);
                let xy = self.img.image().to_map([
                    f64::from(w[0]) + self.x0 as f64,
                    f64::from(w[1]) + self.y0 as f64,
                ]);
                obs.push((px, xy));
            }
        }
        if obs.len() < PLACEMENT_MIN_OBS {
            return Err(Rejection::FewGridPoints { n: obs.len() });
        }
        let cov_h_m2 = self.placement_spread(tc, wc, &cur)?;
        Ok(PlacementObs {
            obs,
            cov_h_m2,
            sigma_rot_rad: rot_step,
            sigma_log_scale: AREA_LOG_SCALE_STEP,
            ties_rejection,
        })
    }

    /// The refined placement's horizontal covariance, map grid (x, y), m^2: the peak's own
    /// localisation plus the second moment of the places around it whose correlation is
    /// within [`PLACEMENT_SPREAD_DELTA`] of it (the plateau, [`Surface::spread`]); refused when
    /// that plateau reaches [`PLACEMENT_SPREAD_RADIUS_PX`] blocks or the window's edge.
    fn placement_spread(
        &self,
        tc: &TwoChannels,
        wc: &TwoChannels,
        cur: &Placed,
    ) -> Result<[[f64; 2]; 2], Rejection> {
        let f = cur.f;
        let Crop {
            t,
            c: [c0, c1],
            expected: at,
            x0,
            y0,
        } = self
            .crop_about(tc, wc, cur, f, PLACEMENT_SPREAD_RADIUS_PX)
            .map_err(|e| e.in_step("placement spread"))?;
        let (scale, theta) = (f64::from(cur.sim.scale), f64::from(cur.sim.theta_rad));
        let (surface, cx, cy) = similar_surface(&[(&c0, &t[0]), (&c1, &t[1])], (scale, theta))
            .ok_or_else(|| Rejection::CorrelationUndefined.in_step("placement spread"))?;
        // The shift that puts the template's centre at the refined place, and the best cell
        // next to it (the refined centre is sub-pixel).
        let sx = (at[0] - x0 as f64 - cx).round() as i64;
        let sy = (at[1] - y0 as f64 - cy).round() as i64;
        let mut peak: Option<(usize, usize, f64)> = None;
        for (ox, oy) in (-1..=1).flat_map(|oy| (-1..=1).map(move |ox| (ox, oy))) {
            let (x, y) = (sx + ox, sy + oy);
            if x < 0 || y < 0 || x >= surface.width as i64 || y >= surface.height as i64 {
                continue;
            }
            let v = surface.data[y as usize * surface.width + x as usize];
            if v.is_finite() && peak.is_none_or(|p| v > p.2) {
                peak = Some((x as usize, y as usize, v));
            }
        }
        let (px, py, _) =
            peak.ok_or_else(|| Rejection::CorrelationUndefined.in_step("placement spread"))?;
        let spread = surface.spread(px, py, PLACEMENT_SPREAD_DELTA);
        let moment = spread.moment;
        if spread.open {
            return Err(Rejection::PlacementOpen {
                delta: PLACEMENT_SPREAD_DELTA,
                radius_blocks: PLACEMENT_SPREAD_RADIUS_PX,
            });
        }
        // Blocks -> metres; window rows run south, the grid's y north.
        let m = f as f64 * self.img.image().gsd_m;
        let base = (PLACEMENT_SIGMA_PX * m).powi(2);
        Ok([
            [moment[0][0] * m * m + base, -moment[0][1] * m * m],
            [-moment[0][1] * m * m, moment[1][1] * m * m + base],
        ])
    }

    /// The template's channels on the grid of `f x f` blocks and the window's crop around the
    /// place `cur` puts it (block coordinates): the template turned and scaled as `cur` says,
    /// plus `margin` blocks each side.
    fn crop_about(
        &self,
        tc: &TwoChannels,
        wc: &TwoChannels,
        cur: &Placed,
        f: usize,
        margin: f64,
    ) -> Result<Crop, Rejection> {
        let (Some(t), Some(w)) = (tc.at(f), wc.at(f)) else {
            return Err(Rejection::ImagesTooSmall);
        };
        let (_, q) = self.predicted_centre(f, [t[0].width, t[0].height])?;
        let e = cur.sim.apply([q[0] as f32, q[1] as f32]);
        let expected = [
            px_to_block(f64::from(e[0]), f),
            px_to_block(f64::from(e[1]), f),
        ];
        let (scale, theta) = (f64::from(cur.sim.scale), f64::from(cur.sim.theta_rad));
        let (sn, cs) = theta.sin_cos();
        let (tw, th) = (t[0].width as f64 * scale, t[0].height as f64 * scale);
        let half = [
            0.5 * (tw * cs.abs() + th * sn.abs()) + margin + 1.0,
            0.5 * (tw * sn.abs() + th * cs.abs()) + margin + 1.0,
        ];
        let x0 = (expected[0] - half[0]).floor() as i64;
        let y0 = (expected[1] - half[1]).floor() as i64;
        let (cw, ch) = (
            (2.0 * half[0]).ceil() as usize + 1,
            (2.0 * half[1]).ceil() as usize + 1,
        );
        let (Some(c0), Some(c1)) = (w[0].crop(x0, y0, cw, ch), w[1].crop(x0, y0, cw, ch)) else {
            return Err(Rejection::EmptyWindow);
        };
        Ok(Crop {
            t,
            c: [c0, c1],
            expected,
            x0,
            y0,
        })
    }

    /// One refinement step of [`Self::placement`]: the grid twice as fine, the window cropped
    /// around the current place, rotations `rot_step` either side of the current one.
    fn refine(
        &self,
        tc: &TwoChannels,
        wc: &TwoChannels,
        cur: &Placed,
        rot_step: f64,
    ) -> Result<Placed, Rejection> {
        let f = cur.f / 2;
        let Crop {
            t,
            c: [c0, c1],
            expected,
            x0,
            y0,
        } = self
            .crop_about(tc, wc, cur, f, PLACEMENT_REFINE_MARGIN_PX)
            .map_err(|e| e.in_step("refinement"))?;
        let (scale, theta) = (f64::from(cur.sim.scale), f64::from(cur.sim.theta_rad));
        // The rotation refined, the scale kept: the peak's place hardly depends on the scale
        // (it stretches the template about its centre), which the fix does not use (its
        // height is the prior's) beyond the lever term.
        let hyps: Vec<(f64, f64)> = (-1..=1)
            .map(|j| (scale, theta + f64::from(j) * rot_step))
            .collect();
        let best = best_similar(&[(&c0, &t[0]), (&c1, &t[1])], &hyps)
            .ok_or_else(|| Rejection::CorrelationUndefined.in_step("refinement"))?;
        let centre = [best.centre[0] + x0 as f64, best.centre[1] + y0 as f64];
        let moved = refinement_move([centre[0] - expected[0], centre[1] - expected[1]]);
        if moved > PLACEMENT_REFINE_MAX_MOVE_PX {
            return Err(Rejection::RefinementMoved {
                block_px: f,
                moved_blocks: moved,
            });
        }
        self.placed_at(
            f,
            [t[0].width, t[0].height],
            centre,
            (best.scale, best.theta_rad),
            best.ncc,
            cur.runner_up,
        )
    }

    /// Pass 1, growing from the centre: each patch is searched around the current similarity's
    /// prediction, over the placement's uncertainty plus the rotation and scale still possible
    /// at its distance (half a hypothesis step); the similarity is refitted as tie points
    /// accumulate, which shrinks both (a fit over ties spanning D pixels leaves about
    /// tolerance / D). Returns the final similarity and each patch's match.
    fn pass1(
        &self,
        placed: &Placed,
        patches: &[TiePatch],
    ) -> Result<(Sim2, Vec<Option<TieMatch>>), Rejection> {
        let (max_rot, max_log_scale) = self.engine.similarity_bounds(self.v);
        let fit = |src: &[[f32; 2]], dst: &[[f32; 2]]| {
            ransac_similarity(
                src,
                dst,
                AREA_TIE_TOLERANCE_PX as f32,
                max_rot,
                max_log_scale,
                0x5EED,
            )
            .filter(|(_, n)| *n >= AREA_PASS1_MIN_TIES)
        };
        let mut sim = placed.sim;
        let mut spread = 0.5 * (AREA_LOG_SCALE_STEP + AREA_ROT_STEP_RAD);
        let mut base = 0.5 * placed.f as f64 + 2.0;
        let [tcx, tcy] = placed.centre;
        let mut near: Vec<(f64, usize)> = patches
            .iter()
            .enumerate()
            .map(|(i, t)| ((t.patch.cx as f64 - tcx).hypot(t.patch.cy as f64 - tcy), i))
            .collect();
        near.sort_by(|x, y| x.0.total_cmp(&y.0));
        let (mut src, mut dst) = (Vec::new(), Vec::new());
        let mut found = vec![None; patches.len()];
        let mut refit_at = AREA_PASS1_MIN_TIES;
        // Speculatively in parallel: the next batch of patches is searched with the current
        // similarity and the results are taken in order; after a refit the rest of the batch is
        // searched again with the new similarity, so the ties are those of the one-by-one
        // search whatever the thread count.
        let mut next = 0;
        'search: while next < near.len() {
            let batch = &near[next..(next + AREA_PASS1_BATCH).min(near.len())];
            let searched: Vec<Option<TieMatch>> = batch
                .par_iter()
                .map(|&(dist, i)| {
                    let r = (base + dist * spread).ceil();
                    (r <= AREA_PASS1_MAX_RADIUS_PX).then_some(())?;
                    self.search(&patches[i], &sim, [0.0; 2], r as usize, MIN_TIE_NCC)
                })
                .collect();
            for (&(dist, i), hit) in batch.iter().zip(searched) {
                if src.len() >= AREA_PASS1_ENOUGH_TIES && base <= 2.0 {
                    break 'search; // the similarity is determined; pass 2 does the rest cheaply
                }
                next += 1;
                let Some(m) = hit else {
                    continue;
                };
                src.push(patches[i].q_f32());
                dst.push([m.x as f32, m.y as f32]);
                found[i] = Some(m);
                if src.len() >= refit_at {
                    refit_at = src.len() + src.len() / 2;
                    if let Some((s_fit, _)) = fit(&src, &dst) {
                        sim = s_fit;
                        base = 2.0;
                        spread = AREA_TIE_TOLERANCE_PX / dist.max(1.0);
                        continue 'search; // the rest of the batch again, with the new fit
                    }
                }
            }
        }
        let (sim, _) = fit(&src, &dst).ok_or(Rejection::PatchesDisagree {
            ncc: placed.ncc,
            agree: src.len(),
        })?;
        Ok((sim, found))
    }

    /// Pass 2: every patch close to the final similarity's prediction (a pass-1 match that
    /// agrees with it is kept as found), as correspondences for the resection.
    fn pass2(&self, sim: &Sim2, patches: &[TiePatch], found: &[Option<TieMatch>]) -> Vec<Pair> {
        let sigma_px = self.engine.base_sigma_px(self.v);
        let matched: Vec<Option<TieMatch>> = patches
            .par_iter()
            .zip(found)
            .map(|(t, prev)| {
                let s = sim.apply(t.q_f32());
                let agrees = |m: &&TieMatch| {
                    (m.x - f64::from(s[0])).hypot(m.y - f64::from(s[1])) <= AREA_TIE_TOLERANCE_PX
                };
                match prev.as_ref().filter(agrees) {
                    Some(m) => Some(*m),
                    None => self.search(t, sim, [0.0; 2], AREA_PASS2_RADIUS_PX, MIN_TIE_NCC_NEAR),
                }
            })
            .collect();
        patches
            .iter()
            .zip(matched)
            .filter_map(|(t, m)| {
                let (p, m) = (&t.patch, m?);
                let xy = self
                    .img
                    .image()
                    .to_map([m.x + self.x0 as f64, m.y + self.y0 as f64]);
                let z = self.engine.reference.height_amsl_m(xy[0], xy[1])?;
                let px = self.v.rect.to_frame_px(p.cx as f64, p.cy as f64)?;
                Some(Pair {
                    frame_px: px,
                    map: [xy[0], xy[1], z],
                    sigma_px,
                })
            })
            .collect()
    }

    /// The ties chance gives: the pass-2 search with the similarity's predictions displaced
    /// beyond anything pass 1 searched, in four directions, the most found (a periodic
    /// pattern, rows of a crop, gives many).
    fn chance(&self, sim: &Sim2, patches: &[TiePatch]) -> usize {
        let d = AREA_NULL_SHIFT_PX;
        [[d, 0.0], [-d, 0.0], [0.0, d], [0.0, -d]]
            .iter()
            .map(|&o| {
                patches
                    .par_iter()
                    .filter(|t| {
                        self.search(t, sim, o, AREA_PASS2_RADIUS_PX, MIN_TIE_NCC_NEAR)
                            .is_some()
                    })
                    .count()
            })
            .max()
            .unwrap_or(0)
    }
}

/// How far a refinement step moved the place, blocks: the larger of its moves along the grid's
/// axes ([`PLACEMENT_REFINE_MAX_MOVE_PX`]).
fn refinement_move(d: [f64; 2]) -> f64 {
    d[0].abs().max(d[1].abs())
}

#[cfg(test)]
mod tests {
    use super::super::tests::checkerboard_engine;
    use super::*;
    use crate::camera::Attitude;
    use crate::fix::rectify::Rectification;
    use crate::fix::{AttitudePriorNed, PositionPriorGeo};
    use crate::vision::gray::GrayImage;

    /// The prior's probability of unjudged places is its Gaussian around the place it
    /// predicts for the template's centre: every cell around it holds all of it, the cells on
    /// one side of it half, cells 5 sigma away none.
    #[test]
    fn the_unjudged_places_are_weighed_by_the_prior_around_its_prediction() {
        let (engine, crs) = checkerboard_engine();
        let (x, y) = (500_640.0, 5_199_360.0);
        let (lat, lon) = crs.to_geodetic(x, y).unwrap();
        let pos = PositionPriorGeo {
            lat_deg: lat,
            lon_deg: lon,
            alt_amsl_m: 1300.0,
            sigma_h_m: 50.0,
            sigma_v_m: 10.0,
        };
        let att = AttitudePriorNed::isotropic(Attitude::new(0.0, 0.0, 0.0), 0.005);
        let g = engine.prior_geom(&pos, &att).unwrap();
        let frame = GrayImage::from_fn(320, 240, |_, _| 100.0);
        let level = 0;
        let scale = 1000.0 / engine.levels_gsd_m[level] / engine.camera.intrinsics.fx_px;
        let rect =
            Rectification::new(&frame, &engine.camera, &g.r_map_cam, scale, 512, 1.0).unwrap();
        let v = View {
            rect: &rect,
            g: &g,
            level,
            agl_m: 1000.0,
            scale,
        };
        let s = AreaSearch::new(&engine, &v).unwrap();
        // Nadir: the template's centre sees the prior's own ground point.
        let (f, size) = (2usize, [rect.width() / 2, rect.height() / 2]);
        let c_px = s.img.image().to_px(x, y);
        // Block k covers pixels k f ..= k f + f - 1 (computed here, not with the stage's helper).
        let coarse = |u: f64| (u - (f as f64 - 1.0) / 2.0) / f as f64;
        let (qx, qy) = (coarse(c_px[0] - s.x0 as f64), coarse(c_px[1] - s.y0 as f64));
        let sigma_cells = 50.0 / (s.img.image().gsd_m * f as f64);
        let grid = |keep: &dyn Fn(f64, f64) -> bool| -> Vec<[f64; 2]> {
            let r = (8.0 * sigma_cells).ceil() as i64;
            let mut out = Vec::new();
            for j in -r..=r {
                for i in -r..=r {
                    let p = [qx.round() + i as f64, qy.round() + j as f64];
                    if keep(p[0], p[1]) {
                        out.push(p);
                    }
                }
            }
            out
        };
        let mass = |places: &[[f64; 2]]| s.prior_mass(f, size, places).unwrap();
        let all = mass(&grid(&|_, _| true));
        assert!((all - 1.0).abs() < 0.01, "all cells: {all}");
        let east = mass(&grid(&|px, _| px > qx));
        let south = mass(&grid(&|_, py| py > qy));
        for half in [east, south] {
            assert!((half - 0.5).abs() < 0.1, "one side: {east} {south}");
        }
        let far = mass(&grid(&|px, _| px > qx + 5.0 * sigma_cells));
        assert!(far < 1e-5, "beyond 5 sigma: {far}");
        assert_eq!(mass(&[]), 0.0);
    }

    /// A refinement step is bounded per grid axis: one coarser block off along both axes is as
    /// far as along one, and a step beyond two finer blocks along either axis is refused.
    #[test]
    fn a_refinement_step_is_bounded_per_axis() {
        let within = |d: [f64; 2]| refinement_move(d) <= PLACEMENT_REFINE_MAX_MOVE_PX;
        assert!(within([1.9, 0.0]));
        assert!(within([1.8, -1.8]), "diagonal, 2.5 blocks away");
        assert!(within([-2.0, 2.0]));
        assert!(!within([2.1, 0.0]));
        assert!(!within([0.3, -2.2]));
        assert!(!within([2.5, 2.5]));
        assert_eq!(refinement_move([-1.5, 0.5]), 1.5);
    }
}
