//! The placement stage: the rectified frame, block-averaged to a coarse grid in two channels
//! (grey values and gradient magnitude), correlated with the map window at a few scales and
//! rotations; the unique peak, the ranked hypotheses and the places left unjudged.

use rayon::prelude::*;

use super::*;

/// `p` scaled by `scale` and rotated by `theta_rad` (image axes, x right, y down: positive
/// turns x towards y) about its centre, bilinear; the output's centre is the input's. A pixel
/// is valid when its four source pixels are.
pub fn warp_similar(p: &Plane, scale: f64, theta_rad: f64) -> Option<Plane> {
    if (scale - 1.0).abs() < 1e-9 && theta_rad.abs() < 1e-9 {
        return Some(p.clone());
    }
    let (s, c) = theta_rad.sin_cos();
    let (hw, hh) = (0.5 * p.width as f64 * scale, 0.5 * p.height as f64 * scale);
    let out_w = (2.0 * (hw * c.abs() + hh * s.abs())).ceil() as usize;
    let out_h = (2.0 * (hw * s.abs() + hh * c.abs())).ceil() as usize;
    let (ci, cj) = ((p.width as f64 - 1.0) / 2.0, (p.height as f64 - 1.0) / 2.0);
    let (co, cp) = ((out_w as f64 - 1.0) / 2.0, (out_h as f64 - 1.0) / 2.0);
    let mut data = vec![0f32; out_w * out_h];
    let mut valid = vec![false; out_w * out_h];
    for y in 0..out_h {
        for x in 0..out_w {
            let (dx, dy) = ((x as f64 - co) / scale, (y as f64 - cp) / scale);
            // Inverse rotation.
            let (sx, sy) = (ci + c * dx + s * dy, cj - s * dx + c * dy);
            if sx < 0.0 || sy < 0.0 {
                continue;
            }
            let (x0, y0) = (sx.floor() as usize, sy.floor() as usize);
            if x0 + 1 >= p.width || y0 + 1 >= p.height {
                continue;
            }
            let idx = [
                p.idx(x0, y0),
                p.idx(x0 + 1, y0),
                p.idx(x0, y0 + 1),
                p.idx(x0 + 1, y0 + 1),
            ];
            if idx.iter().any(|&i| !p.valid[i]) {
                continue;
            }
            let (fx, fy) = ((sx - x0 as f64) as f32, (sy - y0 as f64) as f32);
            let v = (1.0 - fy) * ((1.0 - fx) * p.data[idx[0]] + fx * p.data[idx[1]])
                + fy * ((1.0 - fx) * p.data[idx[2]] + fx * p.data[idx[3]]);
            data[y * out_w + x] = v;
            valid[y * out_w + x] = true;
        }
    }
    Plane::new(out_w, out_h, data, valid)
}

/// A window and a template in one or more representations ("channels") of the same two
/// images: `(window, template)` pairs, every window of one size and every template of one size.
pub type Channels<'a> = [(&'a Plane, &'a Plane)];

/// The two channels the area stages correlate: block means of the grey values and of their
/// gradient magnitude ([`Plane::gradient_magnitude`]) over `f x f` pixels. Their failures
/// differ: a field's grey value changes with the season and the crop, even its sign against
/// its neighbour's, while its edges and the roads between fields stay where they are; and
/// where edges are few, the grey pattern still correlates.
pub fn grey_and_gradient(p: &Plane, f: usize) -> Option<[Plane; 2]> {
    TwoChannels::new(p).at(f)
}

/// A plane and its gradient magnitude at full resolution, for [`grey_and_gradient`] at
/// several block sizes without computing the gradient again.
pub struct TwoChannels<'a> {
    grey: &'a Plane,
    gradient: Plane,
}

impl<'a> TwoChannels<'a> {
    /// `p` and its gradient magnitude, computed once.
    pub fn new(p: &'a Plane) -> Self {
        Self {
            grey: p,
            gradient: p.gradient_magnitude(),
        }
    }

    /// Both channels block-averaged over `f x f` pixels.
    pub fn at(&self, f: usize) -> Option<[Plane; 2]> {
        Some([self.grey.block_mean(f)?, self.gradient.block_mean(f)?])
    }
}

/// The 8-neighbourhood of a cell.
pub(super) const NEIGHBOURS_8: [(i64, i64); 8] = [
    (-1, -1),
    (0, -1),
    (1, -1),
    (-1, 0),
    (1, 0),
    (-1, 1),
    (0, 1),
    (1, 1),
];

/// The region of a correlation surface near its peak ([`Surface::spread`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Spread {
    /// Second moment of the region's cells about the peak, cells squared, `[[xx, xy], [xy, yy]]`.
    pub moment: [[f64; 2]; 2],
    /// Cells in the region (the peak included).
    pub cells: usize,
    /// The region reaches the surface's edge or an undefined cell.
    pub open: bool,
}

/// The masked NCC surface of the template warped by `(scale, theta_rad)` over the window,
/// averaged over the channels, and the template centre's offset `(cx, cy)` from a shift (the
/// centre of the template at shift `(x, y)` lies at window pixel `(x + cx, y + cy)`); `None`
/// when undefined.
pub fn similar_surface(
    channels: &Channels,
    (scale, theta_rad): (f64, f64),
) -> Option<(Surface, f64, f64)> {
    let mut work = 0;
    let nccs = prepare(channels, &mut work);
    hypothesis_surface(&nccs, scale, theta_rad, MIN_OVERLAP, &mut work)
}

/// The masked NCC surface of one hypothesis, averaged over the channels (`None` when a
/// channel's is undefined), and the template centre's offset `(cx, cy)` from a shift.
fn hypothesis_surface(
    nccs: &[(NccWindow, &Plane)],
    scale: f64,
    theta: f64,
    min_overlap: f64,
    work: &mut u64,
) -> Option<(Surface, f64, f64)> {
    let mut sum: Option<(Surface, f64, f64)> = None;
    for (ncc, template) in nccs {
        let t = warp_similar(template, scale, theta)?;
        *work = work.saturating_add(ncc.transform_points() * 5);
        let s = ncc.correlate(&t, min_overlap)?;
        let (cx, cy) = ((t.width as f64 - 1.0) / 2.0, (t.height as f64 - 1.0) / 2.0);
        sum = Some(match sum {
            None => (s, cx, cy),
            Some((mut acc, ax, ay)) => {
                if acc.width != s.width || acc.height != s.height {
                    return None;
                }
                acc.data.iter_mut().zip(&s.data).for_each(|(a, b)| *a += b);
                // A place is judged only where every channel judged it.
                acc.unjudged.extend(&s.unjudged);
                acc.unjudged.sort_unstable();
                acc.unjudged.dedup();
                (acc, ax, ay)
            }
        });
    }
    let (mut s, cx, cy) = sum?;
    let n = nccs.len() as f64;
    s.data.iter_mut().for_each(|v| *v /= n);
    Some((s, cx, cy))
}

/// The window sides' spectra, once for every hypothesis.
fn prepare<'a>(channels: &Channels<'a>, work: &mut u64) -> Vec<(NccWindow, &'a Plane)> {
    let nccs: Vec<(NccWindow, &'a Plane)> = channels
        .par_iter()
        .map(|(w, t)| (NccWindow::new(w), *t))
        .collect();
    for (n, _) in &nccs {
        *work = work.saturating_add(n.transform_points() * 3);
    }
    nccs
}

/// `f` of every hypothesis, in parallel, in the hypotheses' order (`None` where the surface
/// is undefined); `work` grows by every hypothesis's count, so the total does not depend on
/// the thread count.
fn per_hypothesis<T: Send>(
    nccs: &[(NccWindow, &Plane)],
    hypotheses: &[(f64, f64)],
    min_overlap: f64,
    work: &mut u64,
    f: impl Fn(Surface, f64, f64) -> T + Sync,
) -> Vec<Option<T>> {
    let out: Vec<(u64, Option<T>)> = hypotheses
        .par_iter()
        .map(|&(scale, theta)| {
            let mut w = 0u64;
            let r = hypothesis_surface(nccs, scale, theta, min_overlap, &mut w)
                .map(|(s, cx, cy)| f(s, cx, cy));
            (w, r)
        })
        .collect();
    out.into_iter()
        .map(|(w, r)| {
            *work = work.saturating_add(w);
            r
        })
        .collect()
}

/// Every hypothesis's local maxima (at most `cap` each, its best), as candidates, best first.
fn scored_maxima(
    channels: &Channels,
    hypotheses: &[(f64, f64)],
    min_overlap: f64,
    cap: usize,
    work: &mut u64,
) -> Vec<Candidate> {
    let nccs = prepare(channels, work);
    let per = per_hypothesis(&nccs, hypotheses, min_overlap, work, |s, cx, cy| {
        let maxima = s
            .maxima()
            .into_iter()
            .take(cap)
            .map(|(x, y, v)| {
                let (ox, oy) = s.subpixel(x, y);
                (x as f64 + cx + ox, y as f64 + cy + oy, v)
            })
            .collect::<Vec<_>>();
        (maxima, s.unjudged_fraction())
    });
    let mut all: Vec<Candidate> = Vec::new();
    for (&(scale, theta), found) in hypotheses.iter().zip(per) {
        let Some((maxima, unjudged)) = found else {
            continue;
        };
        all.extend(maxima.into_iter().map(|(x, y, ncc)| Candidate {
            centre: [x, y],
            scale,
            theta_rad: theta,
            ncc,
            unjudged_fraction: unjudged,
        }));
    }
    all.sort_by(|a, b| b.ncc.total_cmp(&a.ncc));
    all
}

/// Each hypothesis's best correlation peak, best first: `(index into hypotheses, peak)`
/// (hypotheses without a defined correlation are left out). A cheap first look on a coarser
/// grid, to pick the hypotheses [`place_similar`] examines.
pub fn rank_hypotheses(channels: &Channels, hypotheses: &[(f64, f64)]) -> Vec<(usize, f64)> {
    let mut work = 0;
    let nccs = prepare(channels, &mut work);
    let peaks = per_hypothesis(&nccs, hypotheses, MIN_OVERLAP, &mut work, |s, _, _| {
        s.data
            .iter()
            .copied()
            .filter(|v| v.is_finite())
            .max_by(f64::total_cmp)
    });
    let mut out: Vec<(usize, f64)> = peaks
        .into_iter()
        .enumerate()
        .filter_map(|(h, v)| Some((h, v.flatten()?)))
        .collect();
    out.sort_by(|a, b| b.1.total_cmp(&a.1));
    out
}

/// The best placement of a template over similarity hypotheses ([`place_similar`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SimilarPlacement {
    /// Where the template's centre `((w-1)/2, (h-1)/2)` lies in the window, pixels.
    pub centre: [f64; 2],
    /// The winning hypothesis's scale: the window shows the template scaled by this.
    pub scale: f64,
    /// The winning hypothesis's rotation of the template (image axes: positive turns x towards
    /// y), radians.
    pub theta_rad: f64,
    /// The channels' mean correlation (NCC) at the peak.
    pub ncc: f64,
    /// Best correlation of a local maximum (any hypothesis) whose centre lies beyond the
    /// exclusion radius (-1 when none).
    pub runner_up: f64,
    /// Fraction of the winning hypothesis's shifts that could not be judged
    /// ([`Surface::unjudged`]): the runner-up says nothing about those places.
    pub unjudged_fraction: f64,
}

/// The unique best placement of the template in the window over the similarity hypotheses
/// `(scale, theta_rad)` (each a warp of the template, [`warp_similar`], and a masked NCC over
/// the window, averaged over the channels); the peak rules of the module doc, the competitors
/// being every hypothesis's local maxima whose template centre lies more than `exclusion_px`
/// from the winner's.
pub fn place_similar(
    channels: &Channels,
    hypotheses: &[(f64, f64)],
    exclusion_px: f64,
) -> Result<SimilarPlacement, PlaceError> {
    let mut work = 0;
    let all = scored_maxima(channels, hypotheses, MIN_OVERLAP, usize::MAX, &mut work);
    let best = *all.first().ok_or(PlaceError::Undefined)?;
    let runner_up = all
        .iter()
        .filter(|c| {
            (c.centre[0] - best.centre[0]).hypot(c.centre[1] - best.centre[1]) > exclusion_px
        })
        .map(|c| c.ncc)
        .fold(-1.0, f64::max);
    if best.ncc < MIN_PLACEMENT_NCC {
        return Err(PlaceError::Weak { ncc: best.ncc });
    }
    if runner_up > best.ncc - UNIQUE_MARGIN {
        return Err(PlaceError::Ambiguous {
            ncc: best.ncc,
            runner_up,
        });
    }
    Ok(SimilarPlacement {
        centre: best.centre,
        scale: best.scale,
        theta_rad: best.theta_rad,
        ncc: best.ncc,
        runner_up,
        unjudged_fraction: best.unjudged_fraction,
    })
}

/// The best placement of the template in the window over the hypotheses, without the
/// uniqueness rule: the refinement of a place already found unique on a coarser grid (`None`
/// when no correlation is defined).
pub fn best_similar(channels: &Channels, hypotheses: &[(f64, f64)]) -> Option<Candidate> {
    let mut work = 0;
    scored_maxima(channels, hypotheses, MIN_OVERLAP, 1, &mut work)
        .into_iter()
        .next()
}

/// Where the template's centre lies (window pixels) at each place the hypothesis `(scale,
/// theta_rad)` could not judge ([`Surface::unjudged`]); `None` when its correlation is
/// undefined. For weighing those places against a prior after [`place_similar`].
pub fn unjudged_places(
    channels: &Channels,
    (scale, theta_rad): (f64, f64),
) -> Option<Vec<[f64; 2]>> {
    let mut work = 0;
    let nccs = prepare(channels, &mut work);
    let (s, cx, cy) = hypothesis_surface(&nccs, scale, theta_rad, MIN_OVERLAP, &mut work)?;
    Some(
        s.unjudged
            .iter()
            .map(|&k| [(k % s.width) as f64 + cx, (k / s.width) as f64 + cy])
            .collect(),
    )
}

/// One place a template correlates well at ([`candidates`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Candidate {
    /// Where the template's centre `((w-1)/2, (h-1)/2)` lies in the window, pixels.
    pub centre: [f64; 2],
    /// The hypothesis's scale: the window shows the template scaled by this.
    pub scale: f64,
    /// The hypothesis's rotation of the template (image axes: positive turns x towards y),
    /// radians.
    pub theta_rad: f64,
    /// The channels' mean correlation.
    pub ncc: f64,
    /// Fraction of its hypothesis's shifts that could not be judged ([`Surface::unjudged`]).
    pub unjudged_fraction: f64,
}

/// The `k` best distinct placements of the template in the window over the similarity
/// hypotheses, best first (the channels' mean masked NCC, a template overlapping the window's
/// valid pixels by at least `min_overlap` of its own). Every hypothesis's local maxima compete;
/// one is kept when its template centre lies more than `exclusion_px` from every better kept
/// one (greedy non-maximum suppression across hypotheses: the rotations and scales of one
/// place collapse into its best). A global search's shortlist; [`place_similar`] is the
/// unique-peak rule for a prior's window. `work` grows by the FFT points transformed (a count,
/// never a clock).
pub fn candidates(
    channels: &Channels,
    hypotheses: &[(f64, f64)],
    min_overlap: f64,
    exclusion_px: f64,
    k: usize,
    work: &mut u64,
) -> Vec<Candidate> {
    // A hypothesis contributes at most 4k maxima: more cannot survive the suppression among
    // its own (they are distinct places, and k are kept overall).
    let all = scored_maxima(channels, hypotheses, min_overlap, 4 * k.max(1), work);
    let mut kept: Vec<Candidate> = Vec::new();
    for c in all {
        if kept.len() >= k {
            break;
        }
        let far = |o: &Candidate| {
            (o.centre[0] - c.centre[0]).hypot(o.centre[1] - c.centre[1]) > exclusion_px
        };
        if kept.iter().all(far) {
            kept.push(c);
        }
    }
    kept
}

/// Why a placement failed.
#[derive(Debug, Clone, PartialEq)]
pub enum PlaceError {
    /// Nothing to correlate (no overlap, flat images).
    Undefined,
    /// The best peak is too weak.
    Weak {
        /// The peak's correlation (NCC), below [`MIN_PLACEMENT_NCC`].
        ncc: f64,
    },
    /// Another place correlates nearly as well.
    Ambiguous {
        /// The peak's correlation (NCC).
        ncc: f64,
        /// The best other place's correlation, within [`UNIQUE_MARGIN`] of the peak.
        runner_up: f64,
    },
}

impl std::fmt::Display for PlaceError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            PlaceError::Undefined => write!(f, "area correlation undefined (no textured overlap)"),
            PlaceError::Weak { ncc } => {
                write!(f, "area correlation peak {ncc:.2} < {MIN_PLACEMENT_NCC}")
            }
            PlaceError::Ambiguous { ncc, runner_up } => write!(
                f,
                "area correlation peak {ncc:.2} not unique (another place {runner_up:.2}, margin {UNIQUE_MARGIN})"
            ),
        }
    }
}
