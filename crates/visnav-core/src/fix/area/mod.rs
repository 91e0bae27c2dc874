//! Area-based matching: the rectified frame correlated with the map's own grey image.
//!
//! Features fail where the map and the frame differ in their small details (another season or
//! year, another sensor) while the larger pattern of fields, roads and water still agrees. Area
//! correlation uses every pixel of that pattern. Two stages, both normalised cross-correlation
//! (NCC) with validity masks (map nodata, rectified pixels outside the frame's footprint):
//!
//! 1. **Placement**: the whole rectified frame, block-averaged to a coarse grid, is
//!    correlated with the map window the prior allows, at a few scales and rotations
//!    ([`place_similar`]: the prior's height and heading errors). Masked NCC with FFTs after Padfield,
//!    "Masked object registration in the Fourier domain", IEEE TIP 21(5), 2012, eqs. 9-12: six
//!    correlations of masks, masked images and masked squares give, for every shift, the overlap
//!    count and the sums that the Pearson correlation over the overlap needs. The peak must be
//!    unique: at least [`MIN_PLACEMENT_NCC`] and ahead of every other local maximum more than
//!    [`UNIQUE_RADIUS_COARSE_PX`] away by [`UNIQUE_MARGIN`].
//! 2. **Tie points** ([`match_patch`]): small textured patches of the rectified frame (Shi-Tomasi
//!    corner strength, so edges and flat ground are skipped), each searched for a few pixels
//!    around its predicted place (NCC computed directly, window sums from integral images); the
//!    sub-pixel peak from a parabola through the neighbours in each axis. A patch is kept when its
//!    peak is an interior maximum, at least [`MIN_TIE_NCC`], curved in both directions (not an
//!    edge: [`MIN_PEAK_CURVATURE_RATIO`]) and ahead of any other maximum of its search window by
//!    [`TIE_MARGIN`]. The tie points enter the resection like matched features.
//!
//! Coordinates: pixel centres at integers, x right, y down, in the plane's own grid. Pure: no I/O.

use rayon::prelude::*;

mod ncc;
mod placement;
mod surface;
mod ties;

pub use ncc::*;
pub use placement::*;
pub use surface::*;
pub use ties::*;

/// Smallest placement correlation accepted. Not the guard against unrelated ground (the
/// uniqueness margin, the tie points' chance count and the placement fix's rules are): frames of
/// other farmland placed over the NAIP map peak at 0.05-0.25 (median 0.13, nine in ten below
/// 0.2), and with no floor at all every one of them is still refused. It keeps most of those
/// peaks from the later stages while letting through the true place on ground that changed
/// between the map's year and the frame's, which peaks at 0.2-0.3 (a lake that rose, fields
/// replanted): on the `drone_naip` flight 0.3 refused every frame of such a stretch.
pub const MIN_PLACEMENT_NCC: f64 = 0.2;
/// The placement peak must beat every other local maximum this far away (coarse pixels: the
/// correlation peak of block-averaged images is 1-2 coarse pixels wide) by [`UNIQUE_MARGIN`].
pub const UNIQUE_RADIUS_COARSE_PX: f64 = 3.0;
/// Correlation margin of a unique placement.
pub const UNIQUE_MARGIN: f64 = 0.05;
/// A placement needs the template to overlap valid map pixels over this share of its own valid
/// pixels (a frame hanging over the map's edge by more is not placed).
pub const MIN_OVERLAP: f64 = 0.6;
/// Smallest correlation of a tie point (cross-date patches of 16 px correlate 0.5-0.9 where
/// they truly match).
pub const MIN_TIE_NCC: f64 = 0.5;
/// Smallest correlation of a tie point searched within a couple of pixels of a place already
/// fixed by others (the area stage's second pass): there the correlation only has to say "the
/// same ground", not find it, and a chance peak cannot lie further off than the search radius.
/// Measured on NAIP cross-date (100 frames): 0.5 -> 0.4 lifts the area stage alone from 67 to
/// 74 % and the features' fallback from 85 to 88 %, 0 wrong; 0.3 gave the first wrong fix.
pub const MIN_TIE_NCC_NEAR: f64 = 0.4;
/// A tie point's peak must beat other maxima of its search window (beyond 1.5 px) by this much.
pub const TIE_MARGIN: f64 = 0.1;
/// Ratio of the smaller to the larger principal curvature of a tie point's correlation peak:
/// below it the peak is a ridge (an edge), localised along one direction only.
pub const MIN_PEAK_CURVATURE_RATIO: f64 = 0.2;
/// Per-pixel variance (normalised units) below which an overlap is treated as flat.
const MIN_VARIANCE: f64 = 1e-3;

/// A grey image with a validity mask.
#[derive(Debug, Clone, PartialEq)]
pub struct Plane {
    /// Width, pixels.
    pub width: usize,
    /// Height, pixels.
    pub height: usize,
    /// Values, row-major `width * height`; always finite (0 where invalid).
    pub data: Vec<f32>,
    /// Row-major: true where the pixel holds data.
    pub valid: Vec<bool>,
}

impl Plane {
    /// A plane from its parts; `None` when the sizes disagree or a side is zero. A value that
    /// is not finite is invalid, and every value is stored finite (0 there), so that sums over
    /// windows may include invalid pixels with a zero weight.
    pub fn new(
        width: usize,
        height: usize,
        mut data: Vec<f32>,
        mut valid: Vec<bool>,
    ) -> Option<Self> {
        if !(width > 0 && height > 0 && data.len() == width * height && valid.len() == data.len()) {
            return None;
        }
        for (d, ok) in data.iter_mut().zip(valid.iter_mut()) {
            if !d.is_finite() {
                *d = 0.0;
                *ok = false;
            }
        }
        Some(Self {
            width,
            height,
            data,
            valid,
        })
    }

    /// Index of pixel `(x, y)` in `data`.
    pub fn idx(&self, x: usize, y: usize) -> usize {
        y * self.width + x
    }

    /// Block means over `f x f` pixels (trailing partial blocks dropped); a block is valid when
    /// at least 3/4 of its pixels are (the rule of the map's own pyramid), its mean over those.
    pub fn block_mean(&self, f: usize) -> Option<Plane> {
        if f <= 1 {
            return Some(self.clone());
        }
        let (w, h) = (self.width / f, self.height / f);
        if w == 0 || h == 0 {
            return None;
        }
        let mut data = vec![0f32; w * h];
        let mut valid = vec![false; w * h];
        data.par_chunks_mut(w)
            .zip(valid.par_chunks_mut(w))
            .enumerate()
            .for_each(|(by, (drow, vrow))| {
                for (bx, (d, ok)) in drow.iter_mut().zip(vrow.iter_mut()).enumerate() {
                    let (mut s, mut n) = (0f64, 0usize);
                    for y in by * f..(by + 1) * f {
                        for x in bx * f..(bx + 1) * f {
                            let i = self.idx(x, y);
                            if self.valid[i] {
                                s += f64::from(self.data[i]);
                                n += 1;
                            }
                        }
                    }
                    if 4 * n >= 3 * f * f {
                        *d = (s / n as f64) as f32;
                        *ok = true;
                    }
                }
            });
        Plane::new(w, h, data, valid)
    }

    /// The `w x h` pixels from `(x0, y0)` on; pixels outside the plane are invalid. `None` when
    /// a side is zero.
    pub fn crop(&self, x0: i64, y0: i64, w: usize, h: usize) -> Option<Plane> {
        Plane::window([self.width, self.height], x0, y0, w, h, |x, y| {
            let i = self.idx(x, y);
            self.valid[i].then_some(self.data[i])
        })
    }

    /// The `w x h` window from `(x0, y0)` on of a `size` grid whose pixel `(x, y)` is `at(x, y)`
    /// (`None`: invalid); pixels outside the grid are invalid. `None` when a side is zero.
    pub fn window(
        size: [usize; 2],
        x0: i64,
        y0: i64,
        w: usize,
        h: usize,
        at: impl Fn(usize, usize) -> Option<f32>,
    ) -> Option<Plane> {
        let mut data = vec![0f32; w * h];
        let mut valid = vec![false; w * h];
        for y in 0..h {
            let sy = y0 + y as i64;
            if sy < 0 || sy >= size[1] as i64 {
                continue;
            }
            for x in 0..w {
                let sx = x0 + x as i64;
                if sx < 0 || sx >= size[0] as i64 {
                    continue;
                }
                if let Some(v) = at(sx as usize, sy as usize) {
                    data[y * w + x] = v;
                    valid[y * w + x] = true;
                }
            }
        }
        Plane::new(w, h, data, valid)
    }

    /// The plane inside a border of `mx` invalid pixels left and right and `my` above and
    /// below (so a template may hang over the edge, its overlap counted by the masked NCC).
    pub fn padded(&self, mx: usize, my: usize) -> Plane {
        let (w, h) = (self.width + 2 * mx, self.height + 2 * my);
        let mut data = vec![0f32; w * h];
        let mut valid = vec![false; w * h];
        for y in 0..self.height {
            let (src, dst) = (self.idx(0, y), (y + my) * w + mx);
            data[dst..dst + self.width].copy_from_slice(&self.data[src..src + self.width]);
            valid[dst..dst + self.width].copy_from_slice(&self.valid[src..src + self.width]);
        }
        Plane {
            width: w,
            height: h,
            data,
            valid,
        }
    }

    /// Gradient magnitude (central differences, `|dx| + |dy|`), valid where the four neighbours
    /// are; the border invalid. Edges of fields, roads and buildings keep their place between
    /// seasons while the fields' own brightness does not (a crop's colour changes every year,
    /// even its sign against the neighbour's), so a coarse search correlates these.
    pub fn gradient_magnitude(&self) -> Plane {
        let (w, h) = (self.width, self.height);
        let mut data = vec![0f32; w * h];
        let mut valid = vec![false; w * h];
        data.par_chunks_mut(w.max(1))
            .zip(valid.par_chunks_mut(w.max(1)))
            .enumerate()
            .filter(|(y, _)| *y >= 1 && *y + 1 < h)
            .for_each(|(y, (drow, vrow))| {
                for x in 1..w.saturating_sub(1) {
                    let (l, r, u, d) = (
                        self.idx(x - 1, y),
                        self.idx(x + 1, y),
                        self.idx(x, y - 1),
                        self.idx(x, y + 1),
                    );
                    if self.valid[l] && self.valid[r] && self.valid[u] && self.valid[d] {
                        drow[x] = (self.data[r] - self.data[l]).abs()
                            + (self.data[d] - self.data[u]).abs();
                        vrow[x] = true;
                    }
                }
            });
        Plane {
            width: w,
            height: h,
            data,
            valid,
        }
    }

    /// Number of valid pixels.
    pub fn valid_count(&self) -> usize {
        self.valid.iter().filter(|v| **v).count()
    }
}

#[cfg(test)]
mod tests_support {
    use super::*;
    /// A textured test image (sum of incommensurate sines and a few blobs), deterministic.
    pub fn texture(w: usize, h: usize, seed: f64) -> Plane {
        let data = (0..w * h)
            .map(|k| {
                let (x, y) = ((k % w) as f64, (k / w) as f64);
                let v = 100.0
                    + 30.0 * (0.31 * x + seed).sin() * (0.23 * y - seed).cos()
                    + 20.0 * (0.071 * x + 0.113 * y + 2.0 * seed).sin()
                    + 25.0 * ((0.05 * x * y / (w as f64)).sin() + (0.17 * (x - y)).cos());
                v as f32
            })
            .collect();
        Plane::new(w, h, data, vec![true; w * h]).unwrap()
    }

    pub fn crop(p: &Plane, x0: usize, y0: usize, w: usize, h: usize) -> Plane {
        p.crop(x0 as i64, y0 as i64, w, h).unwrap()
    }
}

#[cfg(test)]
mod tests {
    use super::tests_support::{crop, texture};
    use super::*;

    /// A search of radius 4 at the tie points' first-pass bar.
    fn tie_search(x: i64, y: i64) -> TieSearch {
        TieSearch {
            centre_px: [x, y],
            radius_px: 4,
            min_ncc: MIN_TIE_NCC,
        }
    }

    /// The FFT masked NCC equals the direct Pearson correlation over the common valid pixels.
    #[test]
    fn masked_ncc_equals_the_direct_correlation() {
        let win = {
            let mut p = texture(47, 39, 0.3);
            for k in (0..p.valid.len()).step_by(7) {
                p.valid[k] = false;
            }
            p
        };
        let mut tpl = crop(&texture(60, 60, 1.1), 5, 9, 21, 17);
        for k in (0..tpl.valid.len()).step_by(5) {
            tpl.valid[k] = false;
        }
        let s = NccWindow::new(&win).correlate(&tpl, 0.5).unwrap();
        assert_eq!((s.width, s.height), (27, 23));
        for (dx, dy) in [(0, 0), (3, 11), (26, 22), (13, 5)] {
            let (mut a, mut b) = (Vec::new(), Vec::new());
            for y in 0..tpl.height {
                for x in 0..tpl.width {
                    let (ti, wi) = (y * tpl.width + x, (y + dy) * win.width + x + dx);
                    if tpl.valid[ti] && win.valid[wi] {
                        a.push(f64::from(tpl.data[ti]));
                        b.push(f64::from(win.data[wi]));
                    }
                }
            }
            let n = a.len() as f64;
            let (ma, mb) = (a.iter().sum::<f64>() / n, b.iter().sum::<f64>() / n);
            let cov: f64 = a.iter().zip(&b).map(|(x, y)| (x - ma) * (y - mb)).sum();
            let va: f64 = a.iter().map(|x| (x - ma).powi(2)).sum();
            let vb: f64 = b.iter().map(|y| (y - mb).powi(2)).sum();
            let direct = cov / (va * vb).sqrt();
            let got = s.data[dy * s.width + dx];
            assert!(
                (got - direct).abs() < 1e-4,
                "({dx},{dy}): {got} vs {direct}"
            );
        }
    }

    /// The plateau around a correlation peak: a textured crop correlates within the margin
    /// over a cell or a few (a small moment, closed); a crop of one straight edge along the
    /// whole of it (a ridge: the moment along the edge large, or open); a flat-ish gradient
    /// plane everywhere (open). The moment is about the peak, in cells squared.
    #[test]
    fn the_plateau_of_a_peak_is_small_on_texture_and_runs_along_an_edge() {
        let surface = |win: &Plane, tpl: &Plane| {
            let (s, _, _) = similar_surface(&[(win, tpl)], (1.0, 0.0)).unwrap();
            let (x, y, _) = s.maxima()[0];
            (s.spread(x, y, UNIQUE_MARGIN), x, y)
        };
        let big = texture(80, 80, 0.4);
        let (sp, x, y) = surface(&big, &crop(&big, 20, 24, 40, 32));
        assert_eq!((x, y), (20, 24));
        assert!(!sp.open, "{sp:?}");
        assert!(sp.moment[0][0] < 1.0 && sp.moment[1][1] < 1.0, "{sp:?}");
        // A vertical edge (a field boundary running north-south) with a little texture on each
        // side: along it (y) the correlation hardly changes, across it (x) it falls at once.
        let edge = {
            let t = texture(80, 80, 1.3);
            let data = (0..80 * 80)
                .map(|k| {
                    let side = if k % 80 < 40 { 60.0 } else { 160.0 };
                    side + 0.02 * (t.data[k] - 100.0)
                })
                .collect();
            Plane::new(80, 80, data, vec![true; 80 * 80]).unwrap()
        };
        let (sp, _, _) = surface(&edge, &crop(&edge, 20, 24, 40, 32));
        assert!(sp.moment[0][0] < 1.0, "{sp:?}");
        assert!(sp.open || sp.moment[1][1] > 25.0, "{sp:?}");
        assert!(sp.moment[1][1] > 25.0 * sp.moment[0][0].max(0.04), "{sp:?}");
        // A smooth ramp: every shift along the ramp's contours correlates alike.
        let ramp = {
            let data = (0..80 * 80)
                .map(|k| (k % 80) as f32 + 0.5 * (k / 80) as f32)
                .collect();
            Plane::new(80, 80, data, vec![true; 80 * 80]).unwrap()
        };
        let (sp, _, _) = surface(&ramp, &crop(&ramp, 20, 24, 40, 32));
        assert!(sp.open, "{sp:?}");
    }

    /// Ground whose texture is random (white noise box-blurred over 3 x 3 pixels), and a crop of
    /// it buried in independent noise so that it correlates about `ncc` with its true place:
    /// changed ground between a map's year and the frame's still places where it clears the
    /// floor and stays unique, and a correlation near unrelated ground's typical peak does not.
    #[test]
    fn a_weak_but_unique_peak_above_the_floor_is_placed() {
        let (w, h) = (200usize, 170usize);
        let mut rng = crate::rng::Rng::new(11);
        let white: Vec<f64> = (0..w * h).map(|_| rng.normal()).collect();
        let data = (0..w * h)
            .map(|k| {
                let (x, y) = ((k % w) as i64, (k / w) as i64);
                let mut sum = 0.0;
                for (dx, dy) in (-1..=1).flat_map(|dy| (-1..=1).map(move |dx| (dx, dy))) {
                    let (u, v) = (
                        (x + dx).clamp(0, w as i64 - 1),
                        (y + dy).clamp(0, h as i64 - 1),
                    );
                    sum += white[v as usize * w + u as usize];
                }
                (100.0 + 10.0 * sum) as f32
            })
            .collect();
        let big = Plane::new(w, h, data, vec![true; w * h]).unwrap();
        let tpl = crop(&big, 61, 47, 96, 72);
        let n = tpl.data.len() as f64;
        let mean = tpl.data.iter().map(|&v| f64::from(v)).sum::<f64>() / n;
        let sd = (tpl
            .data
            .iter()
            .map(|&v| (f64::from(v) - mean).powi(2))
            .sum::<f64>()
            / n)
            .sqrt();
        let buried = |ncc: f64| {
            let mut rng = crate::rng::Rng::new(7);
            let k = sd * (1.0 / (ncc * ncc) - 1.0).sqrt();
            let data = tpl
                .data
                .iter()
                .map(|&v| v + (k * rng.normal()) as f32)
                .collect();
            Plane::new(96, 72, data, vec![true; 96 * 72]).unwrap()
        };
        let id = [(1.0, 0.0)];
        let place = |t: &Plane| place_similar(&[(&big, t)], &id, UNIQUE_RADIUS_COARSE_PX);
        let p = place(&buried(0.26)).unwrap();
        assert!(p.ncc > MIN_PLACEMENT_NCC && p.ncc < 0.3, "{p:?}");
        // Template centre (47.5, 35.5) + top-left (61, 47).
        assert!(
            (p.centre[0] - 108.5).abs() < 1.0 && (p.centre[1] - 82.5).abs() < 1.0,
            "{p:?}"
        );
        assert!(p.ncc - p.runner_up >= UNIQUE_MARGIN, "{p:?}");
        assert!(place(&buried(0.12)).is_err());
    }

    #[test]
    fn place_finds_a_crop_and_refuses_a_stranger() {
        let big = texture(160, 140, 0.7);
        let tpl = crop(&big, 57, 33, 64, 48);
        let id = [(1.0, 0.0)];
        let place = |w: &Plane, t: &Plane| place_similar(&[(w, t)], &id, UNIQUE_RADIUS_COARSE_PX);
        let p = place(&big, &tpl).unwrap();
        // Template centre (31.5, 23.5) + top-left (57, 33).
        assert!(
            (p.centre[0] - 88.5).abs() < 0.05 && (p.centre[1] - 56.5).abs() < 0.05,
            "{p:?}"
        );
        assert!(p.ncc > 0.999);
        // An unrelated template: weak or ambiguous, never placed.
        let other = crop(&texture(100, 100, 4.2), 10, 10, 64, 48);
        let noise = Plane::new(
            64,
            48,
            (0..64 * 48)
                .map(|k| ((k as u64 * 2654435761) % 251) as f32)
                .collect(),
            vec![true; 64 * 48],
        )
        .unwrap();
        assert!(place(&big, &noise).is_err());
        let _ = place(&big, &other); // defined either way
        // A periodic scene is ambiguous.
        let stripes = Plane::new(
            120,
            120,
            (0..120 * 120)
                .map(|k| {
                    (100.0
                        + 50.0 * ((k % 120) as f64 * std::f64::consts::TAU / 10.0).sin()
                        + 30.0 * ((k / 120) as f64 * std::f64::consts::TAU / 12.0).cos())
                        as f32
                })
                .collect(),
            vec![true; 120 * 120],
        )
        .unwrap();
        let t = crop(&stripes, 30, 30, 40, 40);
        assert!(matches!(
            place(&stripes, &t),
            Err(PlaceError::Ambiguous { .. })
        ));
    }

    /// A window that is map only in its lower part (the map's edge): shifts where the
    /// template overlaps too little of the map are counted as unjudged, and a fully valid
    /// window has none.
    #[test]
    fn places_over_the_maps_edge_are_counted_unjudged() {
        let big = texture(160, 140, 0.7);
        let tpl = crop(&big, 57, 33, 64, 48);
        let id = [(1.0, 0.0)];
        let full = place_similar(&[(&big, &tpl)], &id, UNIQUE_RADIUS_COARSE_PX).unwrap();
        assert_eq!(full.unjudged_fraction, 0.0);
        // Rows above 60 are beyond the map: the template's true place (rows 33..81) overlaps
        // the map by 21 of its 48 rows, under the minimum overlap.
        let mut edge = big.clone();
        for y in 0..60 {
            for x in 0..edge.width {
                let i = edge.idx(x, y);
                edge.valid[i] = false;
            }
        }
        let s = NccWindow::new(&edge).correlate(&tpl, MIN_OVERLAP).unwrap();
        assert_eq!((s.width, s.height), (97, 93));
        // At shift row dy the template has dy - 12 of its 48 rows on the map; 0.6 x 48 = 28.8
        // rows are needed, so rows dy = 0..=40 are unjudged, the true place (dy = 33) among them.
        assert_eq!(s.unjudged.len(), 41 * 97);
        assert_eq!(s.unjudged, (0..41 * 97).collect::<Vec<_>>());
        assert!(
            s.data[33 * s.width + 57].is_nan(),
            "the true place is unjudged"
        );
        assert!(s.data[41 * s.width + 57].is_finite());
        let frac = s.unjudged_fraction();
        assert!(
            (frac - 41.0 / 93.0).abs() < 1e-12,
            "unjudged fraction {frac}"
        );
        if let Ok(p) = place_similar(&[(&edge, &tpl)], &id, UNIQUE_RADIUS_COARSE_PX) {
            assert!((p.unjudged_fraction - frac).abs() < 1e-12, "{p:?}");
        }
        // The places as template centres (31.5, 23.5) + shift, the true one among them.
        let places = unjudged_places(&[(&edge, &tpl)], (1.0, 0.0)).unwrap();
        assert_eq!(places.len(), 41 * 97);
        assert!(places.contains(&[88.5, 56.5]));
        assert!(places.iter().all(|p| p[1] <= 40.0 + 23.5));
    }

    /// The global search's shortlist: a crop turned by an unknown heading and hanging over the
    /// window's edge is found at its place and heading among every heading, first; the
    /// shortlist's places are distinct.
    #[test]
    fn candidates_find_a_turned_crop_at_any_heading() {
        let big = texture(150, 130, 0.4);
        let turn = 2.2f64; // rad: the window shows the template turned by this
        let cut = crop(&big, 70, 50, 48, 40);
        let tpl = warp_similar(&cut, 1.0, -turn).unwrap();
        // The window: the image with its left part missing, and a border of no data around it
        // wide enough for the template to hang over the edge.
        let mut w = big.clone();
        for y in 0..w.height {
            for x in 0..80 {
                let i = w.idx(x, y);
                w.valid[i] = false;
            }
        }
        let w = w.padded(20, 20);
        let steps = 120;
        let hyps: Vec<(f64, f64)> = (0..steps)
            .map(|k| (1.0, k as f64 * std::f64::consts::TAU / steps as f64))
            .collect();
        let mut work = 0;
        let c = candidates(&[(&w, &tpl)], &hyps, 0.4, 3.0, 4, &mut work);
        assert_eq!(c.len(), 4, "{c:?}");
        assert!(work > 0);
        // Crop centre (70 + 23.5, 50 + 19.5) in the padded window.
        let (ex, ey) = (93.5 + 20.0, 69.5 + 20.0);
        let d_theta = (c[0].theta_rad - turn).rem_euclid(std::f64::consts::TAU);
        assert!(
            d_theta.min(std::f64::consts::TAU - d_theta) < 0.03,
            "heading {} vs {turn}",
            c[0].theta_rad
        );
        assert!(
            (c[0].centre[0] - ex).hypot(c[0].centre[1] - ey) < 1.0,
            "{:?} vs ({ex}, {ey})",
            c[0]
        );
        assert!(c[0].ncc > 0.9 && c[1].ncc < c[0].ncc);
        for (i, a) in c.iter().enumerate() {
            for b in &c[i + 1..] {
                assert!((a.centre[0] - b.centre[0]).hypot(a.centre[1] - b.centre[1]) > 3.0);
            }
        }
    }

    #[test]
    fn gradient_magnitude_and_padding() {
        let ramp = Plane::new(
            6,
            5,
            (0..30)
                .map(|k| (2 * (k % 6) + 3 * (k / 6)) as f32)
                .collect(),
            vec![true; 30],
        )
        .unwrap();
        let g = ramp.gradient_magnitude();
        // Central differences: |2 * 2| + |2 * 3| inside, the border invalid.
        for y in 0..5 {
            for x in 0..6 {
                let inside = x > 0 && x < 5 && y > 0 && y < 4;
                assert_eq!(g.valid[g.idx(x, y)], inside, "({x}, {y})");
                if inside {
                    assert_eq!(g.data[g.idx(x, y)], 10.0);
                }
            }
        }
        let p = ramp.padded(2, 1);
        assert_eq!((p.width, p.height), (10, 7));
        assert_eq!(p.valid_count(), 30);
        assert_eq!(p.data[p.idx(2 + 3, 1 + 2)], ramp.data[ramp.idx(3, 2)]);
        assert!(!p.valid[p.idx(1, 3)] && !p.valid[p.idx(4, 0)]);
    }

    #[test]
    fn patches_match_to_a_fraction_of_a_pixel_and_edges_are_refused() {
        let big = texture(120, 120, 0.2);
        // The map is the image shifted by (2.0, -1.0) px.
        let map = crop(&big, 10, 20, 90, 90);
        let frame = crop(&big, 12, 19, 90, 90);
        let sums = Integral::new(&map);
        let patches = select_patches(&frame, 15, 15, 1.0, 50);
        assert!(patches.len() >= 10, "{}", patches.len());
        for p in &patches {
            let m = match_patch(&map, &sums, p, tie_search(p.cx as i64, p.cy as i64));
            if let Some(m) = m {
                assert!((m.x - (p.cx as f64 + 2.0)).abs() < 0.15, "{m:?}");
                assert!((m.y - (p.cy as f64 - 1.0)).abs() < 0.15, "{m:?}");
            }
        }
        let found = patches
            .iter()
            .filter(|p| match_patch(&map, &sums, p, tie_search(p.cx as i64, p.cy as i64)).is_some())
            .count();
        // Patches whose true place touches the map's edge (row 7 of 90 here) have no curvature
        // on that side and are refused; almost all the others are found.
        assert!(
            found * 10 >= patches.len() * 7,
            "{found} of {}",
            patches.len()
        );
        // A vertical edge: corner strength 0 and no match.
        let edge = Plane::new(
            40,
            40,
            (0..1600)
                .map(|k| if k % 40 < 20 { 50.0 } else { 150.0 })
                .collect(),
            vec![true; 1600],
        )
        .unwrap();
        assert!(corner_strength(&edge, 20, 20, 15) < 1e-9);
        let p = Patch::new(&edge, 20, 20, 15).unwrap();
        let sums = Integral::new(&edge);
        assert!(match_patch(&edge, &sums, &p, tie_search(20, 20)).is_none());
    }

    #[test]
    fn crop_marks_pixels_outside_the_plane_invalid() {
        let p = texture(10, 8, 0.4);
        let c = p.crop(-2, 5, 6, 5).unwrap();
        for y in 0..5 {
            for x in 0..6 {
                let (sx, sy) = (x as i64 - 2, y as i64 + 5);
                let inside = sx >= 0 && sy < 8;
                assert_eq!(c.valid[c.idx(x, y)], inside, "({x}, {y})");
                if inside {
                    assert_eq!(c.data[c.idx(x, y)], p.data[p.idx(sx as usize, sy as usize)]);
                }
            }
        }
        assert!(p.crop(20, 0, 3, 3).unwrap().valid.iter().all(|v| !v));
        assert!(p.crop(0, 0, 0, 3).is_none());
    }

    #[test]
    fn block_mean_follows_the_three_quarter_rule() {
        let mut p = Plane::new(
            4,
            2,
            vec![1.0, 3.0, 5.0, 7.0, 1.0, 3.0, 5.0, 7.0],
            vec![true; 8],
        )
        .unwrap();
        p.valid[0] = false;
        p.valid[2] = false;
        p.valid[3] = false;
        let b = p.block_mean(2).unwrap();
        assert_eq!((b.width, b.height), (2, 1));
        assert!(b.valid[0] && !b.valid[1]);
        assert!((b.data[0] - 7.0 / 3.0).abs() < 1e-6);
        assert_eq!(fast_size(97), 100);
        assert_eq!(fast_size(128), 128);
    }
}
