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

use std::sync::Arc;

use rayon::prelude::*;
use rustfft::num_complex::Complex;
use rustfft::{Fft, FftPlanner};

/// Smallest placement correlation accepted.
pub const MIN_PLACEMENT_NCC: f64 = 0.3;
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
    pub width: usize,
    pub height: usize,
    pub data: Vec<f32>,
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

/// Correlation values over a grid of shifts; `NaN` where undefined (too little overlap, flat).
#[derive(Debug, Clone)]
pub struct Surface {
    pub width: usize,
    pub height: usize,
    pub data: Vec<f64>,
    /// Shifts (indices into `data`, ascending) left undefined because the template overlapped
    /// too few of the window's valid pixels (the window's edge, a hole in the map): places that
    /// could not be judged, so a peak elsewhere is not shown to be unique against them.
    pub unjudged: Vec<usize>,
}

impl Surface {
    /// Fraction of the shifts that could not be judged ([`Self::unjudged`]).
    pub fn unjudged_fraction(&self) -> f64 {
        self.unjudged.len() as f64 / (self.width * self.height).max(1) as f64
    }
}

impl Surface {
    fn at(&self, x: i64, y: i64) -> f64 {
        if x < 0 || y < 0 || x >= self.width as i64 || y >= self.height as i64 {
            return f64::NAN;
        }
        self.data[y as usize * self.width + x as usize]
    }

    /// Local maxima (strictly above their defined 8 neighbours), best first.
    pub fn maxima(&self) -> Vec<(usize, usize, f64)> {
        let mut out = Vec::new();
        for y in 0..self.height {
            for x in 0..self.width {
                let c = self.data[y * self.width + x];
                if !c.is_finite() {
                    continue;
                }
                let is_max = (-1i64..=1).all(|dy| {
                    (-1i64..=1).all(|dx| {
                        let n = self.at(x as i64 + dx, y as i64 + dy);
                        (dx == 0 && dy == 0)
                            || n.partial_cmp(&c) == Some(std::cmp::Ordering::Less)
                            || n.is_nan()
                    })
                });
                if is_max {
                    out.push((x, y, c));
                }
            }
        }
        out.sort_by(|a, b| b.2.total_cmp(&a.2));
        out
    }

    /// Sub-pixel offset of the maximum at `(x, y)`: a parabola through the neighbours in each
    /// axis (0 where a neighbour is undefined or the fit is not a maximum), within +-0.5.
    pub fn subpixel(&self, x: usize, y: usize) -> (f64, f64) {
        let (xi, yi) = (x as i64, y as i64);
        let c = self.at(xi, yi);
        let fit = |a: f64, b: f64| {
            let d = a - 2.0 * c + b;
            if a.is_finite() && b.is_finite() && d < 0.0 {
                (0.5 * (a - b) / d).clamp(-0.5, 0.5)
            } else {
                0.0
            }
        };
        (
            fit(self.at(xi - 1, yi), self.at(xi + 1, yi)),
            fit(self.at(xi, yi - 1), self.at(xi, yi + 1)),
        )
    }

    /// How far the correlation stays within `delta` of its value at `(x, y)`: the shifts
    /// connected to `(x, y)` (8-neighbours, defined values only) whose value is at least
    /// `value(x, y) - delta`, as their second moment about `(x, y)` in cells squared
    /// (`[[xx, xy], [xy, yy]]`), with whether that region reaches the surface's edge or an
    /// undefined cell (then its true extent is unknown and the moment a lower bound).
    /// A textured place gives one cell or a few; an edge a ridge along it; a uniform area the
    /// whole surface.
    pub fn spread(&self, x: usize, y: usize, delta: f64) -> Spread {
        let c = self.at(x as i64, y as i64);
        let mut out = Spread {
            moment: [[0.0; 2]; 2],
            cells: 0,
            open: !c.is_finite(),
        };
        if !c.is_finite() {
            return out;
        }
        let floor = c - delta;
        let mut seen = vec![false; self.width * self.height];
        let mut stack = vec![(x, y)];
        seen[y * self.width + x] = true;
        let (mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0);
        while let Some((px, py)) = stack.pop() {
            out.cells += 1;
            let (dx, dy) = (px as f64 - x as f64, py as f64 - y as f64);
            sxx += dx * dx;
            sxy += dx * dy;
            syy += dy * dy;
            for (ox, oy) in NEIGHBOURS_8 {
                let (nx, ny) = (px as i64 + ox, py as i64 + oy);
                let v = self.at(nx, ny);
                if !v.is_finite() {
                    // Beyond the edge or unjudged: the region may go on there.
                    out.open = true;
                    continue;
                }
                let k = ny as usize * self.width + nx as usize;
                if v >= floor && !seen[k] {
                    seen[k] = true;
                    stack.push((nx as usize, ny as usize));
                }
            }
        }
        let n = out.cells as f64;
        out.moment = [[sxx / n, sxy / n], [sxy / n, syy / n]];
        out
    }

    /// Smaller over larger principal curvature of the surface at `(x, y)` (0 when undefined or
    /// not a maximum in every direction).
    pub fn curvature_ratio(&self, x: usize, y: usize) -> f64 {
        let (xi, yi) = (x as i64, y as i64);
        let c = self.at(xi, yi);
        let hxx = self.at(xi - 1, yi) + self.at(xi + 1, yi) - 2.0 * c;
        let hyy = self.at(xi, yi - 1) + self.at(xi, yi + 1) - 2.0 * c;
        let hxy = 0.25
            * (self.at(xi + 1, yi + 1) - self.at(xi + 1, yi - 1) - self.at(xi - 1, yi + 1)
                + self.at(xi - 1, yi - 1));
        if !(hxx.is_finite() && hyy.is_finite() && hxy.is_finite()) {
            return 0.0;
        }
        // Eigenvalues of the negated Hessian (both positive at a proper maximum).
        let (a, b, cc) = (-hxx, -hyy, -hxy);
        let mean = 0.5 * (a + b);
        let rad = (0.25 * (a - b).powi(2) + cc * cc).sqrt();
        let (lo, hi) = (mean - rad, mean + rad);
        if hi <= 0.0 || lo <= 0.0 {
            return 0.0;
        }
        lo / hi
    }
}

/// The FFTs' number type: single precision suffices for values normalised to zero mean and unit
/// variance (sums over at most a few 10^5 pixels; the correlations agree with a direct f64
/// computation to 1e-4, unit test) and halves the time of the placement.
type Real = f32;

/// Sizes FFTs are fast at: products of 2, 3 and 5, at least `n`.
fn fast_size(n: usize) -> usize {
    let mut m = n.max(1);
    loop {
        let mut r = m;
        for p in [2, 3, 5] {
            while r.is_multiple_of(p) {
                r /= p;
            }
        }
        if r == 1 {
            return m;
        }
        m += 1;
    }
}

/// A 2-D FFT of `sw x sh` (row-major, `sh` rows); the spectrum is kept transposed (`sw` rows of
/// `sh`), which every use here is indifferent to.
struct Fft2 {
    sw: usize,
    sh: usize,
    fwd_w: Arc<dyn Fft<Real>>,
    fwd_h: Arc<dyn Fft<Real>>,
    inv_w: Arc<dyn Fft<Real>>,
    inv_h: Arc<dyn Fft<Real>>,
}

/// `src` (`h` rows of `w`) transposed, in tiles that stay in cache.
fn transpose(src: &[Complex<Real>], w: usize, h: usize) -> Vec<Complex<Real>> {
    const TILE: usize = 16;
    let mut out = vec![Complex::new(0.0, 0.0); w * h];
    for y0 in (0..h).step_by(TILE) {
        for x0 in (0..w).step_by(TILE) {
            for y in y0..(y0 + TILE).min(h) {
                for x in x0..(x0 + TILE).min(w) {
                    out[x * h + y] = src[y * w + x];
                }
            }
        }
    }
    out
}

impl Fft2 {
    fn new(sw: usize, sh: usize) -> Self {
        let mut p = FftPlanner::new();
        Self {
            sw,
            sh,
            fwd_w: p.plan_fft_forward(sw),
            fwd_h: p.plan_fft_forward(sh),
            inv_w: p.plan_fft_inverse(sw),
            inv_h: p.plan_fft_inverse(sh),
        }
    }

    /// Row-major `sh x sw` in, transposed spectrum out.
    fn forward(&self, mut buf: Vec<Complex<Real>>) -> Vec<Complex<Real>> {
        self.fwd_w.process(&mut buf);
        let mut t = transpose(&buf, self.sw, self.sh);
        self.fwd_h.process(&mut t);
        t
    }

    /// Transposed spectrum in, row-major `sh x sw` out (normalised).
    fn inverse(&self, mut t: Vec<Complex<Real>>) -> Vec<Complex<Real>> {
        self.inv_h.process(&mut t);
        let mut buf = transpose(&t, self.sh, self.sw);
        self.inv_w.process(&mut buf);
        let k = 1.0 / (self.sw * self.sh) as Real;
        buf.iter_mut().for_each(|v| *v *= k);
        buf
    }

    /// Spectra of two real signals packed as `a + i b`: `(A, B)` from `Z = F(a + i b)` by the
    /// Hermitian symmetry of real signals' spectra.
    fn forward_pair(&self, z: Vec<Complex<Real>>) -> (Vec<Complex<Real>>, Vec<Complex<Real>>) {
        let zf = self.forward(z);
        let (sw, sh) = (self.sw, self.sh);
        let mut a = vec![Complex::new(0.0, 0.0); zf.len()];
        let mut b = a.clone();
        for kx in 0..sw {
            let jx = if kx == 0 { 0 } else { sw - kx };
            for ky in 0..sh {
                let i = kx * sh + ky;
                let j = jx * sh + if ky == 0 { 0 } else { sh - ky };
                let (zk, zm) = (zf[i], zf[j].conj());
                a[i] = (zk + zm) * 0.5;
                b[i] = (zk - zm) * Complex::new(0.0, -0.5);
            }
        }
        (a, b)
    }

    /// Spectrum of one real signal.
    fn forward_real(&self, a: &[Real]) -> Vec<Complex<Real>> {
        self.forward(a.iter().map(|&x| Complex::new(x, 0.0)).collect())
    }
}

/// A plane normalised over its valid pixels (zero mean, unit variance) and padded into an
/// `sw x sh` grid, with its mask: `(values * mask, mask)`.
fn normalised_padded(p: &Plane, sw: usize, sh: usize) -> (Vec<Real>, Vec<Real>) {
    let (mut s, mut s2, mut n) = (0f64, 0f64, 0usize);
    for (v, ok) in p.data.iter().zip(&p.valid) {
        if *ok {
            s += f64::from(*v);
            s2 += f64::from(*v).powi(2);
            n += 1;
        }
    }
    let mean = if n > 0 { s / n as f64 } else { 0.0 };
    let sd = if n > 1 {
        (s2 / n as f64 - mean * mean).max(0.0).sqrt()
    } else {
        0.0
    };
    let inv = if sd > 1e-9 { 1.0 / sd } else { 1.0 };
    let mut vals = vec![0.0; sw * sh];
    let mut mask = vec![0.0; sw * sh];
    for y in 0..p.height {
        for x in 0..p.width {
            let i = p.idx(x, y);
            if p.valid[i] {
                vals[y * sw + x] = ((f64::from(p.data[i]) - mean) * inv) as Real;
                mask[y * sw + x] = 1.0;
            }
        }
    }
    (vals, mask)
}

fn pack(a: &[Real], b: &[Real]) -> Vec<Complex<Real>> {
    a.iter().zip(b).map(|(x, y)| Complex::new(*x, *y)).collect()
}

/// The window side of a masked NCC: its spectra, computed once for many templates.
pub struct NccWindow {
    fft: Fft2,
    width: usize,
    height: usize,
    /// Spectra of the mask and the normalised masked values (packed as one transform) and of
    /// their squares.
    f_mi: Vec<Complex<Real>>,
    f_i: Vec<Complex<Real>>,
    f_i2: Vec<Complex<Real>>,
}

impl NccWindow {
    /// Spectra of `window` on FFT sizes of at least its own.
    pub fn new(window: &Plane) -> Self {
        let (sw, sh) = (fast_size(window.width), fast_size(window.height));
        let fft = Fft2::new(sw, sh);
        let (i, mi) = normalised_padded(window, sw, sh);
        let i2: Vec<Real> = i.iter().map(|v| v * v).collect();
        let (f_mi, f_i) = fft.forward_pair(pack(&mi, &i));
        let f_i2 = fft.forward_real(&i2);
        Self {
            fft,
            width: window.width,
            height: window.height,
            f_mi,
            f_i,
            f_i2,
        }
    }

    /// Points of one 2-D transform (the work unit of a correlation: each costs five transforms).
    pub fn transform_points(&self) -> u64 {
        (self.fft.sw * self.fft.sh) as u64
    }

    /// Masked NCC of `template` at every shift inside the window (Padfield 2012): entry
    /// `(dx, dy)` is the Pearson correlation over the pixels valid in both when the template's
    /// top-left pixel lies on window pixel `(dx, dy)`; `dx in 0..=Ww-Tw`, `dy in 0..=Wh-Th`.
    /// `NaN` where the overlap is under `min_overlap` of the template's valid pixels or either
    /// side is flat. `None` when the template does not fit or has no valid pixel.
    pub fn correlate(&self, template: &Plane, min_overlap: f64) -> Option<Surface> {
        if template.width > self.width || template.height > self.height {
            return None;
        }
        let n_t = template.valid_count();
        if n_t == 0 {
            return None;
        }
        let (sw, sh) = (self.fft.sw, self.fft.sh);
        let (t, mt) = normalised_padded(template, sw, sh);
        let t2: Vec<Real> = t.iter().map(|v| v * v).collect();
        let (f_mt, f_t) = self.fft.forward_pair(pack(&mt, &t));
        let f_t2 = self.fft.forward_real(&t2);
        // Correlation c(s) = sum_x a(x) b(x + s)  <->  conj(A) B; two real results per inverse.
        let corr2 = |a1: &[Complex<Real>],
                     b1: &[Complex<Real>],
                     a2: &[Complex<Real>],
                     b2: &[Complex<Real>]| {
            let z: Vec<Complex<Real>> = (0..a1.len())
                .map(|k| a1[k].conj() * b1[k] + Complex::new(0.0, 1.0) * (a2[k].conj() * b2[k]))
                .collect();
            self.fft.inverse(z)
        };
        let n_si = corr2(&f_mt, &self.f_mi, &f_mt, &self.f_i);
        let sii_st = corr2(&f_mt, &self.f_i2, &f_t, &self.f_mi);
        let stt_sit = corr2(&f_t2, &self.f_mi, &f_t, &self.f_i);
        let (w, h) = (
            self.width - template.width + 1,
            self.height - template.height + 1,
        );
        let mut data = vec![f64::NAN; w * h];
        let mut unjudged = Vec::new();
        let need = (min_overlap * n_t as f64).max(2.0);
        for dy in 0..h {
            for dx in 0..w {
                let k = dy * sw + dx;
                let n = f64::from(n_si[k].re).round();
                if n < need {
                    unjudged.push(dy * w + dx);
                    continue;
                }
                let (si, sii, st, stt, sit) = (
                    f64::from(n_si[k].im),
                    f64::from(sii_st[k].re),
                    f64::from(sii_st[k].im),
                    f64::from(stt_sit[k].re),
                    f64::from(stt_sit[k].im),
                );
                let vi = sii - si * si / n;
                let vt = stt - st * st / n;
                if vi < MIN_VARIANCE * n || vt < MIN_VARIANCE * n {
                    continue;
                }
                data[dy * w + dx] = ((sit - si * st / n) / (vi * vt).sqrt()).clamp(-1.0, 1.0);
            }
        }
        Some(Surface {
            width: w,
            height: h,
            data,
            unjudged,
        })
    }
}

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
const NEIGHBOURS_8: [(i64, i64); 8] = [
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
    /// The winning hypothesis: the window shows the template scaled and rotated by these.
    pub scale: f64,
    pub theta_rad: f64,
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
    /// The hypothesis: the window shows the template scaled and rotated by these.
    pub scale: f64,
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
    Weak { ncc: f64 },
    /// Another place correlates nearly as well.
    Ambiguous { ncc: f64, runner_up: f64 },
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

/// Summed-area tables of a plane's values, squares and valid count (`(w+1) x (h+1)`).
pub struct Integral {
    w1: usize,
    s: Vec<f64>,
    s2: Vec<f64>,
    n: Vec<u32>,
}

impl Integral {
    /// The tables of `p`.
    pub fn new(p: &Plane) -> Self {
        let w1 = p.width + 1;
        let mut s = vec![0f64; w1 * (p.height + 1)];
        let mut s2 = s.clone();
        let mut n = vec![0u32; s.len()];
        // Each row's running sums (rows in parallel)...
        s[w1..]
            .par_chunks_mut(w1)
            .zip(s2[w1..].par_chunks_mut(w1))
            .zip(n[w1..].par_chunks_mut(w1))
            .enumerate()
            .for_each(|(y, ((rs_row, rs2_row), rn_row))| {
                let (mut rs, mut rs2, mut rn) = (0f64, 0f64, 0u32);
                for x in 0..p.width {
                    let i = p.idx(x, y);
                    if p.valid[i] {
                        let v = f64::from(p.data[i]);
                        rs += v;
                        rs2 += v * v;
                        rn += 1;
                    }
                    rs_row[x + 1] = rs;
                    rs2_row[x + 1] = rs2;
                    rn_row[x + 1] = rn;
                }
            });
        // ...then accumulated down the columns, a row at a time (vectorised).
        accumulate_down(&mut s, w1);
        accumulate_down(&mut s2, w1);
        accumulate_down(&mut n, w1);
        Self { w1, s, s2, n }
    }

    /// Sums over the `w x h` box at `(x, y)` (inside the plane): `(sum, sum of squares, valid)`.
    fn sums(&self, x: usize, y: usize, w: usize, h: usize) -> (f64, f64, u32) {
        let (a, b) = (y * self.w1 + x, y * self.w1 + x + w);
        let (c, d) = ((y + h) * self.w1 + x, (y + h) * self.w1 + x + w);
        (
            self.s[d] - self.s[b] - self.s[c] + self.s[a],
            self.s2[d] - self.s2[b] - self.s2[c] + self.s2[a],
            self.n[d] + self.n[a] - self.n[b] - self.n[c],
        )
    }
}

/// Each row of `table` (rows of `w` values) plus the row above it, top to bottom: row sums
/// become the sums of the whole rectangle above and left.
fn accumulate_down<T: Copy + std::ops::AddAssign>(table: &mut [T], w: usize) {
    for y in 1..table.len() / w {
        let (above, row) = table.split_at_mut(y * w);
        let above = &above[(y - 1) * w..];
        row[..w].iter_mut().zip(above).for_each(|(r, a)| *r += *a);
    }
}

/// A square patch of a plane, zero-mean and unit-norm, ready for correlation.
#[derive(Debug, Clone)]
pub struct Patch {
    /// Centre in the source plane (pixel centres at integers; `side` odd).
    pub cx: usize,
    pub cy: usize,
    pub side: usize,
    /// Row-major, each row padded with zeros to `stride` values (a multiple of the dot
    /// product's 8 lanes, so the correlation's inner loop has no scalar tail).
    values: Vec<f32>,
    stride: usize,
}

impl Patch {
    /// The patch of odd `side` centred on `(cx, cy)`; `None` when it leaves the plane, touches an
    /// invalid pixel or is flat.
    pub fn new(p: &Plane, cx: usize, cy: usize, side: usize) -> Option<Self> {
        let r = side / 2;
        if side.is_multiple_of(2) || cx < r || cy < r || cx + r >= p.width || cy + r >= p.height {
            return None;
        }
        let mut values = Vec::with_capacity(side * side);
        for y in cy - r..=cy + r {
            for x in cx - r..=cx + r {
                let i = p.idx(x, y);
                if !p.valid[i] {
                    return None;
                }
                values.push(f64::from(p.data[i]));
            }
        }
        let mean = values.iter().sum::<f64>() / values.len() as f64;
        values.iter_mut().for_each(|v| *v -= mean);
        let norm = values.iter().map(|v| v * v).sum::<f64>().sqrt();
        if norm < 1e-6 {
            return None;
        }
        let stride = side.next_multiple_of(8);
        let mut padded = vec![0f32; side * stride];
        for (row, src) in padded
            .chunks_exact_mut(stride)
            .zip(values.chunks_exact(side))
        {
            for (d, v) in row.iter_mut().zip(src) {
                *d = (v / norm) as f32;
            }
        }
        Some(Self {
            cx,
            cy,
            side,
            values: padded,
            stride,
        })
    }
}

/// Shi-Tomasi corner strength of the odd `side` square centred on `(cx, cy)`: the smaller
/// eigenvalue of the structure tensor of central-difference gradients, per pixel (grey levels
/// squared). 0 when the square leaves the plane or touches an invalid pixel.
pub fn corner_strength(p: &Plane, cx: usize, cy: usize, side: usize) -> f64 {
    let r = side / 2 + 1;
    if cx < r || cy < r || cx + r >= p.width || cy + r >= p.height {
        return 0.0;
    }
    let (mut gxx, mut gyy, mut gxy) = (0f64, 0f64, 0f64);
    let r = side / 2;
    for y in cy - r..=cy + r {
        for x in cx - r..=cx + r {
            let ok = [
                p.idx(x - 1, y),
                p.idx(x + 1, y),
                p.idx(x, y - 1),
                p.idx(x, y + 1),
            ];
            if ok.iter().any(|&i| !p.valid[i]) {
                return 0.0;
            }
            let gx = 0.5 * f64::from(p.data[ok[1]] - p.data[ok[0]]);
            let gy = 0.5 * f64::from(p.data[ok[3]] - p.data[ok[2]]);
            gxx += gx * gx;
            gyy += gy * gy;
            gxy += gx * gy;
        }
    }
    let n = (side * side) as f64;
    let (a, b, c) = (gxx / n, gyy / n, gxy / n);
    0.5 * (a + b) - (0.25 * (a - b).powi(2) + c * c).sqrt()
}

/// Sum of the dot products of pairs of equal-length rows, with eight independent partial sums
/// over all rows and one reduction at the end (a float sum in one accumulator may not be
/// reordered, so it would not vectorise).
fn dot_rows_f32<'a>(rows: impl Iterator<Item = (&'a [f32], &'a [f32])>) -> f32 {
    let mut acc = [0f32; 8];
    let mut tail = 0f32;
    for (a, b) in rows {
        let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
        let (ra, rb) = (ca.remainder(), cb.remainder());
        for (x, y) in ca.zip(cb) {
            for k in 0..8 {
                acc[k] += x[k] * y[k];
            }
        }
        tail += ra.iter().zip(rb).map(|(x, y)| x * y).sum::<f32>();
    }
    acc.iter().sum::<f32>() + tail
}

/// A patch's match in a plane.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TieMatch {
    /// Patch centre in the searched plane (sub-pixel).
    pub x: f64,
    pub y: f64,
    pub ncc: f64,
}

/// Searches `patch` in `map` with its centre within `radius` pixels (Chebyshev) of the integer
/// pixel `(px, py)`; the match when the peak passes the module doc's rules.
pub fn match_patch(
    map: &Plane,
    sums: &Integral,
    patch: &Patch,
    px: i64,
    py: i64,
    radius: usize,
    min_ncc: f64,
) -> Option<TieMatch> {
    let side = patch.side;
    let r = side as i64 / 2;
    let n = (side * side) as f64;
    let w = 2 * radius + 1;
    let mut s = Surface {
        width: w,
        height: w,
        data: vec![f64::NAN; w * w],
        unjudged: Vec::new(),
    };
    for j in 0..w {
        for i in 0..w {
            let (x0, y0) = (
                px - radius as i64 + i as i64 - r,
                py - radius as i64 + j as i64 - r,
            );
            if x0 < 0 || y0 < 0 || x0 as usize + side > map.width || y0 as usize + side > map.height
            {
                s.unjudged.push(j * w + i);
                continue;
            }
            let (x0, y0) = (x0 as usize, y0 as usize);
            let (sm, sm2, cnt) = sums.sums(x0, y0, side, side);
            if cnt as usize != side * side {
                s.unjudged.push(j * w + i);
                continue;
            }
            let var = sm2 - sm * sm / n;
            if var < MIN_VARIANCE {
                continue;
            }
            // The patch is zero-mean, so the map's mean drops out of the numerator.
            // The padded rows when the map row is long enough (the padding is zero), the
            // patch's own width at the map's right edge.
            let len = if x0 + patch.stride <= map.width {
                patch.stride
            } else {
                side
            };
            let rows = (0..side).map(|y| {
                let start = (y0 + y) * map.width + x0;
                (
                    &map.data[start..start + len],
                    &patch.values[y * patch.stride..y * patch.stride + len],
                )
            });
            let dot = f64::from(dot_rows_f32(rows));
            s.data[j * w + i] = dot / var.sqrt();
        }
    }
    let maxima = s.maxima();
    let &(bx, by, best) = maxima.first()?;
    if best < min_ncc || bx == 0 || by == 0 || bx + 1 == w || by + 1 == w {
        return None;
    }
    let rival = maxima
        .iter()
        .skip(1)
        .find(|(x, y, _)| (*x as f64 - bx as f64).hypot(*y as f64 - by as f64) > 1.5)
        .map_or(-1.0, |m| m.2);
    if rival > best - TIE_MARGIN || s.curvature_ratio(bx, by) < MIN_PEAK_CURVATURE_RATIO {
        return None;
    }
    let (ox, oy) = s.subpixel(bx, by);
    Some(TieMatch {
        x: (px - radius as i64 + bx as i64) as f64 + ox,
        y: (py - radius as i64 + by as i64) as f64 + oy,
        ncc: best,
    })
}

/// Patch centres of a regular grid (step `side`) over `p`, strongest corners first, at most
/// `max`, each with a corner strength of at least `min_strength`.
pub fn select_patches(
    p: &Plane,
    side: usize,
    step: usize,
    min_strength: f64,
    max: usize,
) -> Vec<Patch> {
    let r = side / 2 + 1;
    let step = step.max(1);
    let ys: Vec<usize> = (r..p.height.saturating_sub(r)).step_by(step).collect();
    let xs: Vec<usize> = (r..p.width.saturating_sub(r)).step_by(step).collect();
    let mut cands: Vec<(f64, usize, usize)> = ys
        .par_iter()
        .flat_map_iter(|&y| {
            xs.iter().filter_map(move |&x| {
                let s = corner_strength(p, x, y, side);
                (s >= min_strength).then_some((s, x, y))
            })
        })
        .collect();
    cands.sort_by(|a, b| b.0.total_cmp(&a.0));
    // The strongest first, in chunks built in parallel until there are enough.
    let mut out = Vec::with_capacity(max);
    for chunk in cands.chunks(64) {
        if out.len() >= max {
            break;
        }
        let built: Vec<Patch> = chunk
            .par_iter()
            .filter_map(|&(_, x, y)| Patch::new(p, x, y, side))
            .collect();
        out.extend(built);
    }
    out.truncate(max);
    out
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
            let m = match_patch(&map, &sums, p, p.cx as i64, p.cy as i64, 4, MIN_TIE_NCC);
            if let Some(m) = m {
                assert!((m.x - (p.cx as f64 + 2.0)).abs() < 0.15, "{m:?}");
                assert!((m.y - (p.cy as f64 - 1.0)).abs() < 0.15, "{m:?}");
            }
        }
        let found = patches
            .iter()
            .filter(|p| {
                match_patch(&map, &sums, p, p.cx as i64, p.cy as i64, 4, MIN_TIE_NCC).is_some()
            })
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
        assert!(match_patch(&edge, &sums, &p, 20, 20, 4, MIN_TIE_NCC).is_none());
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
