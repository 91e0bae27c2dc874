//! Co-registration of two orthophotos of the same area (`visnav map compare`): how far the ground
//! seen in one image is displaced in the other, measured where both show the same structure.
//!
//! Why: a fix is registered to the reference map; when the map and the world the camera sees
//! (another year, another producer) disagree by a shift, every fix carries that shift, and no
//! matcher can remove it. This measures it before a map is trusted, and it is the bound behind
//! the accuracy figures in `docs/fix.md`.
//!
//! Method (area-based matching, the classic image-registration check, e.g. Zitová & Flusser 2003,
//! "Image registration methods: a survey", section 3.1):
//! 1. Image `b` is resampled onto the pixel grid of image `a` through both geotransforms
//!    (bilinear, grey = Rec. 601 luma of bands 1-3 or band 1), so the two grids agree exactly
//!    where the georeferencing says they should.
//! 2. On a regular grid of patch centres (every `step_px` pixels of `a`) a square template of
//!    side `2 patch_half_px` of `a` is compared with `b` at every integer shift within
//!    `+-search_px` by the normalised cross-correlation
//!    `ncc = sum (t - mean t)(s - mean s) / (n std t std s)`.
//! 3. A patch counts only where the ground is the same structure in both images: peak NCC at
//!    least `min_ncc`, the peak inside the search window (not on its border), and a sharp 2-D
//!    peak: the quadratic fitted to the 3 x 3 NCC values around it (central differences
//!    `g = (dx, dy)`, Hessian `H`) must curve down by at least `min_curvature` in every direction
//!    (both eigenvalues of `H` at most `-min_curvature`), which rejects straight edges (roads,
//!    field boundaries) whose position along the edge is undetermined (the aperture problem).
//!    The sub-pixel shift is the quadratic's peak, `integer shift - H^-1 g`.
//! 4. The shift `o` (pixels of `a`) is converted to map metres with the linear part of `a`'s
//!    geotransform: the ground at map position `p` in `a` lies at `p + d` in `b`.
//!
//! Besides the per-patch shifts, the mean shift over square windows of `window_m` (the size of
//! a camera footprint) is reported: that is the part of the misregistration a fix inherits as a
//! whole, where independent patch errors would average out.

use rayon::prelude::*;
use serde::Serialize;

use crate::geo::geotiff::crs_equivalent;
use visnav_core::geo::raster::{Bounds, Raster};

/// Settings of [`coregister`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CoregParams {
    /// Half side of the correlation template, pixels of image `a`.
    pub patch_half_px: usize,
    /// Distance between patch centres, pixels of image `a`.
    pub step_px: usize,
    /// Largest shift searched in each axis, pixels of image `a`.
    pub search_px: usize,
    /// Minimum peak normalised cross-correlation for a patch to count.
    pub min_ncc: f64,
    /// Minimum downward curvature of the NCC peak (per pixel squared) in every direction.
    pub min_curvature: f64,
    /// A template whose grey standard deviation is below this fraction of the whole image's is
    /// too flat to locate (water, bare field).
    pub min_rel_std: f64,
    /// Side of the windows over which the shift is averaged, map metres.
    pub window_m: f64,
    /// Windows with fewer counted patches are left out of the window statistics.
    pub min_patches_per_window: usize,
}

impl Default for CoregParams {
    fn default() -> Self {
        Self {
            patch_half_px: 24,
            step_px: 12,
            search_px: 4,
            min_ncc: 0.85,
            min_curvature: 0.01,
            min_rel_std: 0.15,
            window_m: 1500.0,
            min_patches_per_window: 10,
        }
    }
}

/// Errors of [`coregister`].
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum CoregError {
    /// The two images are in different CRSs.
    #[error("the two images are in different CRSs ({a} and {b}): reproject one first")]
    CrsMismatch {
        /// Image `a`'s CRS.
        a: String,
        /// Image `b`'s CRS.
        b: String,
    },
    /// The two images do not overlap.
    #[error("the two images do not overlap")]
    NoOverlap,
    /// A setting is out of its range.
    #[error("invalid setting {key} = {value}: {reason}")]
    BadParam {
        /// The setting.
        key: &'static str,
        /// The value given.
        value: f64,
        /// What is wrong, in words.
        reason: &'static str,
    },
    /// Image `a` has no grey variation to correlate.
    #[error("image a has no grey variation to correlate (standard deviation {std})")]
    Flat {
        /// The grey values' standard deviation.
        std: f64,
    },
    /// The overlap is too small for one patch and its search.
    #[error(
        "image a ({width} x {height} px) is too small for {side} px patches searched +-{search} px"
    )]
    TooSmall {
        /// The overlap's width, pixels of image `a`.
        width: usize,
        /// The overlap's height, pixels of image `a`.
        height: usize,
        /// The patch side, pixels.
        side: usize,
        /// The search radius, pixels.
        search: usize,
    },
}

/// The shift measured at one patch.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct PatchShift {
    /// Patch centre, map coordinates of image `a`'s CRS.
    pub x_m: f64,
    /// Patch centre, map northing (see `x_m`).
    pub y_m: f64,
    /// Where that ground lies in image `b`, relative to image `a`, map metres (CRS axes).
    pub dx_m: f64,
    /// The shift along the CRS's y axis, map metres (see `dx_m`).
    pub dy_m: f64,
    /// Peak normalised cross-correlation.
    pub ncc: f64,
}

/// Median / 90th percentile / maximum of a set of values.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Spread {
    /// Median.
    pub median: f64,
    /// 90th percentile.
    pub p90: f64,
    /// Maximum.
    pub max: f64,
}

impl Spread {
    fn of(values: &[f64]) -> Option<Self> {
        if values.is_empty() {
            return None;
        }
        let mut v = values.to_vec();
        v.sort_by(f64::total_cmp);
        let q = |p: f64| v[((v.len() - 1) as f64 * p).round() as usize];
        Some(Self {
            median: q(0.5),
            p90: q(0.9),
            max: v[v.len() - 1],
        })
    }
}

/// The mean shift over one window.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct WindowShift {
    /// Window centre, map coordinates.
    pub x_m: f64,
    /// Window centre, map northing.
    pub y_m: f64,
    /// Matched patches in the window.
    pub patches: usize,
    /// Mean shift along the CRS's x axis, map metres.
    pub dx_m: f64,
    /// Mean shift along the CRS's y axis, map metres.
    pub dy_m: f64,
}

/// Result of [`coregister`].
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CoregReport {
    /// Pixel size of image `a` (the unit of the `_px` figures), metres.
    pub pixel_m: f64,
    /// Patches on the grid inside the overlap with enough texture.
    pub patches_tried: usize,
    /// Patches whose correlation passed every test (same structure in both images).
    pub patches_matched: usize,
    /// Length of each matched patch's shift, metres (`None` when no patch matched).
    pub shift_m: Option<Spread>,
    /// The same in pixels of image `a`.
    pub shift_px: Option<Spread>,
    /// Median shift per axis over all matched patches, metres (a robust global offset).
    pub median_dx_m: Option<f64>,
    /// Median shift along the CRS's y axis, metres.
    pub median_dy_m: Option<f64>,
    /// Window side used for `window_shift_m`, metres.
    pub window_m: f64,
    /// Length of the mean shift over each window with enough patches, metres (`None` when no
    /// window has enough).
    pub window_shift_m: Option<Spread>,
    /// The same in pixels of image `a`.
    pub window_shift_px: Option<Spread>,
    /// Each window with enough patches.
    pub windows: Vec<WindowShift>,
    /// Each matched patch.
    pub patches: Vec<PatchShift>,
}

fn grey_at(r: &Raster, x_m: f64, y_m: f64, buf: &mut [f64]) -> f32 {
    if !r.bilinear_all_bands(x_m, y_m, buf) {
        return f32::NAN;
    }
    if buf.len() >= 3 {
        (0.299 * buf[0] + 0.587 * buf[1] + 0.114 * buf[2]) as f32
    } else {
        buf[0] as f32
    }
}

/// Grey of `a` at its pixel centres and of `b` resampled onto the same centres (NaN where a
/// sample is missing or outside).
fn grids(a: &Raster, b: &Raster) -> (Vec<f32>, Vec<f32>) {
    let (w, h) = (a.width(), a.height());
    let rows: Vec<(Vec<f32>, Vec<f32>)> = (0..h)
        .into_par_iter()
        .map(|row| {
            let mut ba = vec![0.0; a.bands()];
            let mut bb = vec![0.0; b.bands()];
            let mut ra = vec![f32::NAN; w];
            let mut rb = vec![f32::NAN; w];
            for col in 0..w {
                let (x, y) = a.pixel_centre_to_map(col, row);
                ra[col] = grey_at(a, x, y, &mut ba);
                rb[col] = grey_at(b, x, y, &mut bb);
            }
            (ra, rb)
        })
        .collect();
    let mut ga = Vec::with_capacity(w * h);
    let mut gb = Vec::with_capacity(w * h);
    for (ra, rb) in rows {
        ga.extend(ra);
        gb.extend(rb);
    }
    (ga, gb)
}

fn check(params: &CoregParams) -> Result<(), CoregError> {
    let bad = |key, value: f64, reason| Err(CoregError::BadParam { key, value, reason });
    if params.patch_half_px < 2 {
        return bad("patch_half_px", params.patch_half_px as f64, "at least 2");
    }
    if params.step_px == 0 {
        return bad("step_px", 0.0, "at least 1");
    }
    if params.search_px < 2 || params.search_px > params.patch_half_px {
        return bad(
            "search_px",
            params.search_px as f64,
            "at least 2 and at most patch_half_px",
        );
    }
    if params.patch_half_px > 1024 {
        return bad("patch_half_px", params.patch_half_px as f64, "at most 1024");
    }
    if !(params.min_ncc > -1.0 && params.min_ncc < 1.0) {
        return bad("min_ncc", params.min_ncc, "between -1 and 1");
    }
    if !(params.min_curvature.is_finite() && params.min_curvature >= 0.0) {
        return bad("min_curvature", params.min_curvature, "finite and >= 0");
    }
    if !(params.min_rel_std.is_finite() && params.min_rel_std >= 0.0) {
        return bad("min_rel_std", params.min_rel_std, "finite and >= 0");
    }
    if !(params.window_m.is_finite() && params.window_m > 0.0) {
        return bad("window_m", params.window_m, "finite and > 0");
    }
    Ok(())
}

/// Mean and standard deviation of a square block (`None` when a sample is missing).
fn block_stats(g: &[f32], w: usize, x0: usize, y0: usize, side: usize) -> Option<(f64, f64)> {
    let (mut s, mut s2) = (0.0f64, 0.0f64);
    for y in y0..y0 + side {
        for &v in &g[y * w + x0..y * w + x0 + side] {
            if v.is_nan() {
                return None;
            }
            let v = f64::from(v);
            s += v;
            s2 += v * v;
        }
    }
    let n = (side * side) as f64;
    let m = s / n;
    Some((m, (s2 / n - m * m).max(0.0).sqrt()))
}

/// One patch, given its template's mean and standard deviation: the sub-pixel shift `(ox, oy)`
/// in pixels of `a` and the peak NCC, or `None`.
fn match_patch(
    ga: &[f32],
    gb: &[f32],
    w: usize,
    cx: usize,
    cy: usize,
    (tm, ts): (f64, f64),
    p: &CoregParams,
) -> Option<(f64, f64, f64)> {
    let half = p.patch_half_px;
    let side = 2 * half;
    let r = p.search_px as isize;
    let (x0, y0) = (cx - half, cy - half);
    let n = (side * side) as f64;
    let dim = (2 * r + 1) as usize;
    let mut ncc = vec![f64::NAN; dim * dim];
    for dy in -r..=r {
        for dx in -r..=r {
            let bx = (x0 as isize + dx) as usize; // ok: the caller keeps search_px of margin
            let by = (y0 as isize + dy) as usize;
            let (bm, bs) = block_stats(gb, w, bx, by, side)?;
            if bs <= 0.0 {
                continue;
            }
            let mut c = 0.0f64;
            for k in 0..side {
                let ta = &ga[(y0 + k) * w + x0..(y0 + k) * w + x0 + side];
                let tb = &gb[(by + k) * w + bx..(by + k) * w + bx + side];
                for (a, b) in ta.iter().zip(tb) {
                    c += (f64::from(*a) - tm) * (f64::from(*b) - bm);
                }
            }
            ncc[(dy + r) as usize * dim + (dx + r) as usize] = c / (n * ts * bs);
        }
    }
    peak(&ncc, dim, p.min_ncc, p.min_curvature)
        .map(|(ox, oy, best)| (ox - r as f64, oy - r as f64, best))
}

/// The sub-pixel peak of a `dim x dim` correlation surface (row-major, `ncc[y * dim + x]`):
/// `(x, y, value)` in surface cells, or `None` when the maximum is below `min_ncc`, on the
/// border, or not curved down by at least `min_curvature` in every direction (module doc, 3).
fn peak(ncc: &[f64], dim: usize, min_ncc: f64, min_curvature: f64) -> Option<(f64, f64, f64)> {
    let (mut best, mut bi) = (f64::NEG_INFINITY, 0usize);
    for (i, &v) in ncc.iter().enumerate() {
        if v > best {
            best = v;
            bi = i;
        }
    }
    if best.is_nan() || best < min_ncc {
        return None;
    }
    let (iy, ix) = (bi / dim, bi % dim);
    if ix == 0 || iy == 0 || ix + 1 >= dim || iy + 1 >= dim {
        return None;
    }
    let at = |x: usize, y: usize| ncc[y * dim + x];
    let c = at(ix, iy);
    let (l, rr, t, b) = (
        at(ix - 1, iy),
        at(ix + 1, iy),
        at(ix, iy - 1),
        at(ix, iy + 1),
    );
    let gx = 0.5 * (rr - l);
    let gy = 0.5 * (b - t);
    let hxx = rr - 2.0 * c + l;
    let hyy = b - 2.0 * c + t;
    let hxy =
        0.25 * (at(ix + 1, iy + 1) - at(ix - 1, iy + 1) - at(ix + 1, iy - 1) + at(ix - 1, iy - 1));
    // Largest eigenvalue of the symmetric 2x2 Hessian must be <= -min_curvature.
    let tr = hxx + hyy;
    let det = hxx * hyy - hxy * hxy;
    let disc = (0.25 * tr * tr - det).max(0.0).sqrt();
    let lmax = 0.5 * tr + disc;
    if lmax.is_nan() || lmax > -min_curvature || !det.is_finite() || det <= 0.0 {
        return None;
    }
    // Peak of the quadratic: -H^-1 g.
    let sx = -(hyy * gx - hxy * gy) / det;
    let sy = -(-hxy * gx + hxx * gy) / det;
    if !(sx.abs() <= 1.0 && sy.abs() <= 1.0) {
        return None;
    }
    Some((ix as f64 + sx, iy as f64 + sy, best))
}

/// Measures how the ground of image `a` is displaced in image `b` (module doc). Both images
/// must be in the same CRS; `b` may have another pixel size and grid.
pub fn coregister(a: &Raster, b: &Raster, params: &CoregParams) -> Result<CoregReport, CoregError> {
    check(params)?;
    check_pair(a, b)?;
    let (ga, gb) = grids(a, b);
    let min_std = min_texture_std(&ga, params)?;
    let centres = patch_centres(a.width(), a.height(), params)?;
    let (patches_tried, patches) = match_patches(a, (&ga, &gb), &centres, min_std, params);
    let (pw, ph) = a.transform().pixel_size();
    let pixel_m = (pw.abs() * ph.abs()).sqrt();
    let lens: Vec<f64> = patches.iter().map(|p| p.dx_m.hypot(p.dy_m)).collect();
    let med = |mut v: Vec<f64>| {
        if v.is_empty() {
            return None;
        }
        v.sort_by(f64::total_cmp);
        Some(v[v.len() / 2])
    };
    let median_dx_m = med(patches.iter().map(|p| p.dx_m).collect());
    let median_dy_m = med(patches.iter().map(|p| p.dy_m).collect());
    let windows = window_shifts(&patches, &a.bounds(), params)?;
    let wl: Vec<f64> = windows.iter().map(|w| w.dx_m.hypot(w.dy_m)).collect();
    let px = |s: Spread| Spread {
        median: s.median / pixel_m,
        p90: s.p90 / pixel_m,
        max: s.max / pixel_m,
    };
    let shift_m = Spread::of(&lens);
    let window_shift_m = Spread::of(&wl);
    Ok(CoregReport {
        pixel_m,
        patches_tried,
        patches_matched: patches.len(),
        shift_m,
        shift_px: shift_m.map(px),
        median_dx_m,
        median_dy_m,
        window_m: params.window_m,
        window_shift_m,
        window_shift_px: window_shift_m.map(px),
        windows,
        patches,
    })
}

/// The two images share a CRS and overlap.
fn check_pair(a: &Raster, b: &Raster) -> Result<(), CoregError> {
    if !crs_equivalent(&a.crs(), &b.crs()) {
        return Err(CoregError::CrsMismatch {
            a: a.crs().to_string(),
            b: b.crs().to_string(),
        });
    }
    let (ab, bb) = (a.bounds(), b.bounds());
    if ab.max_x_m <= bb.min_x_m
        || bb.max_x_m <= ab.min_x_m
        || ab.max_y_m <= bb.min_y_m
        || bb.max_y_m <= ab.min_y_m
    {
        return Err(CoregError::NoOverlap);
    }
    Ok(())
}

/// The grey spread a patch needs to be matched: relative to the whole image's spread.
fn min_texture_std(ga: &[f32], params: &CoregParams) -> Result<f64, CoregError> {
    let (mut s, mut s2, mut n) = (0.0f64, 0.0f64, 0usize);
    for &v in ga {
        if !v.is_nan() {
            s += f64::from(v);
            s2 += f64::from(v) * f64::from(v);
            n += 1;
        }
    }
    let global_std = if n > 1 {
        let m = s / n as f64;
        (s2 / n as f64 - m * m).max(0.0).sqrt()
    } else {
        0.0
    };
    if global_std.is_nan() || global_std <= 0.0 {
        return Err(CoregError::Flat { std: global_std });
    }
    Ok((params.min_rel_std * global_std).max(1e-9))
}

/// The patch centres, pixels of `a`: every `step_px`, far enough from the edges for the patch
/// and its search.
fn patch_centres(
    w: usize,
    h: usize,
    params: &CoregParams,
) -> Result<Vec<(usize, usize)>, CoregError> {
    let margin = params.patch_half_px + params.search_px + 1;
    if w <= 2 * margin || h <= 2 * margin {
        return Err(CoregError::TooSmall {
            width: w,
            height: h,
            side: 2 * params.patch_half_px,
            search: params.search_px,
        });
    }
    Ok((margin..h - margin)
        .step_by(params.step_px)
        .flat_map(|cy| {
            (margin..w - margin)
                .step_by(params.step_px)
                .map(move |cx| (cx, cy))
        })
        .collect())
}

/// Matches the textured patches of `a` in `b` (the grey grids `g`): how many were tried, and the
/// shifts found.
fn match_patches(
    a: &Raster,
    g: (&[f32], &[f32]),
    centres: &[(usize, usize)],
    min_std: f64,
    params: &CoregParams,
) -> (usize, Vec<PatchShift>) {
    let (ga, gb) = g;
    let w = a.width();
    let tf = a.transform();
    let c = tf.coeffs();
    let results: Vec<(bool, Option<PatchShift>)> = centres
        .par_iter()
        .map(|&(cx, cy)| {
            let half = params.patch_half_px;
            // Textured in a and sampleable in b at zero shift.
            let template = block_stats(ga, w, cx - half, cy - half, 2 * half)
                .filter(|&(_, sd)| sd >= min_std)
                .filter(|_| block_stats(gb, w, cx - half, cy - half, 2 * half).is_some());
            let Some(template) = template else {
                return (false, None);
            };
            let shift = match_patch(ga, gb, w, cx, cy, template, params).map(|(ox, oy, ncc)| {
                // Patch centre: the corner between pixels cx-1 and cx (the template spans
                // [cx - half, cx + half)).
                let (x_m, y_m) = tf.pixel_to_map(cx as f64, cy as f64);
                PatchShift {
                    x_m,
                    y_m,
                    dx_m: c[1] * ox + c[2] * oy,
                    dy_m: c[4] * ox + c[5] * oy,
                    ncc,
                }
            });
            (true, shift)
        })
        .collect();
    let tried = results.iter().filter(|r| r.0).count();
    (tried, results.into_iter().filter_map(|r| r.1).collect())
}

/// The starts of the windows along one axis from `lo` to `hi`: a grid of side `window_m` with
/// half overlap, plus a last window flush with the far edge.
fn window_starts(lo: f64, hi: f64, params: &CoregParams) -> Result<Vec<f64>, CoregError> {
    let step = 0.5 * params.window_m;
    let extent = hi - lo;
    if extent < params.window_m {
        return Ok(Vec::new());
    }
    let n = ((extent - params.window_m) / step).floor() + 1.0;
    if n.is_nan() || n > MAX_WINDOWS_PER_AXIS {
        return Err(CoregError::BadParam {
            key: "window_m",
            value: params.window_m,
            reason: "too small for the image (more than 1000 windows per axis)",
        });
    }
    let mut v: Vec<f64> = (0..n as usize).map(|i| lo + i as f64 * step).collect();
    let last = hi - params.window_m;
    if v.last().is_some_and(|&x| last - x > 1e-6 * params.window_m) {
        v.push(last);
    }
    Ok(v)
}

/// The mean shift in each window over `ab` (a's bounds) that holds enough patches; each patch
/// counts in every window that contains it.
fn window_shifts(
    patches: &[PatchShift],
    ab: &Bounds,
    params: &CoregParams,
) -> Result<Vec<WindowShift>, CoregError> {
    let xs = window_starts(ab.min_x_m, ab.max_x_m, params)?;
    let ys = window_starts(ab.min_y_m, ab.max_y_m, params)?;
    // Indices of the sorted window starts whose window [s, s + window_m) contains v.
    let containing = |st: &[f64], v: f64| {
        st.partition_point(|&s| s + params.window_m <= v)..st.partition_point(|&s| s <= v)
    };
    let mut acc = vec![(0usize, 0.0f64, 0.0f64); xs.len() * ys.len()];
    for p in patches {
        for j in containing(&ys, p.y_m) {
            for i in containing(&xs, p.x_m) {
                let a = &mut acc[j * xs.len() + i];
                a.0 += 1;
                a.1 += p.dx_m;
                a.2 += p.dy_m;
            }
        }
    }
    let mut windows = Vec::new();
    for (j, &y0) in ys.iter().enumerate() {
        for (i, &x0) in xs.iter().enumerate() {
            let (n, sx, sy) = acc[j * xs.len() + i];
            if n >= params.min_patches_per_window.max(1) {
                windows.push(WindowShift {
                    x_m: x0 + 0.5 * params.window_m,
                    y_m: y0 + 0.5 * params.window_m,
                    patches: n,
                    dx_m: sx / n as f64,
                    dy_m: sy / n as f64,
                });
            }
        }
    }
    Ok(windows)
}

/// Upper bound on the number of windows along one axis.
const MAX_WINDOWS_PER_AXIS: f64 = 1000.0;

#[cfg(test)]
mod tests {
    use super::*;
    use visnav_core::geo::Crs;
    use visnav_core::geo::raster::{GeoTransform, RasterData};

    /// A smooth random texture (sum of blobs), 8-bit, north-up at `px_m` per pixel.
    fn texture(w: usize, h: usize, seed: u64) -> Vec<u8> {
        let mut state = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        let mut rnd = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((state >> 33) as f64) / ((1u64 << 31) as f64)
        };
        let blobs: Vec<(f64, f64, f64, f64)> = (0..(w * h / 60))
            .map(|_| {
                (
                    rnd() * w as f64,
                    rnd() * h as f64,
                    1.5 + 4.0 * rnd(),
                    rnd() - 0.5,
                )
            })
            .collect();
        let mut f = vec![0.0f64; w * h];
        for &(bx, by, s, a) in &blobs {
            let r = (3.0 * s).ceil() as isize;
            for y in (by as isize - r).max(0)..(by as isize + r).min(h as isize) {
                for x in (bx as isize - r).max(0)..(bx as isize + r).min(w as isize) {
                    let d2 = (x as f64 + 0.5 - bx).powi(2) + (y as f64 + 0.5 - by).powi(2);
                    f[y as usize * w + x as usize] += a * (-d2 / (2.0 * s * s)).exp();
                }
            }
        }
        f.iter()
            .map(|v| (128.0 + 120.0 * v).clamp(0.0, 255.0) as u8)
            .collect()
    }

    fn raster(data: Vec<u8>, w: usize, h: usize, x0: f64, y0: f64, px_m: f64) -> Raster {
        Raster::new(
            w,
            h,
            1,
            RasterData::U8(data),
            GeoTransform::north_up(x0, y0, px_m, -px_m).unwrap(),
            Crs::Utm {
                zone: 14,
                north: true,
            },
            None,
        )
        .unwrap()
    }

    #[test]
    fn a_georeferencing_shift_is_measured_in_map_metres_with_its_sign() {
        let (w, h) = (240, 200);
        let t = texture(w, h, 3);
        let a = raster(t.clone(), w, h, 500_000.0, 5_200_000.0, 5.0);
        // The same pixels, georeferenced 6.5 m further east and 3.5 m further south: the ground
        // of `a` at p lies at p + (6.5, -3.5) m in `b`.
        let b = raster(t, w, h, 500_006.5, 5_199_996.5, 5.0);
        let p = CoregParams {
            window_m: 600.0,
            ..CoregParams::default()
        };
        let r = coregister(&a, &b, &p).unwrap();
        assert!(r.windows.len() >= 4, "{} windows", r.windows.len());
        assert!(r.patches_matched > 50, "{} patches", r.patches_matched);
        let (dx, dy) = (r.median_dx_m.unwrap(), r.median_dy_m.unwrap());
        assert!((dx - 6.5).abs() < 0.25, "dx {dx}");
        assert!((dy + 3.5).abs() < 0.25, "dy {dy}");
        let want = 6.5f64.hypot(3.5);
        let ws = r.window_shift_m.unwrap();
        assert!((ws.median - want).abs() < 0.25, "{ws:?}");
        assert!((r.window_shift_px.unwrap().median - want / 5.0).abs() < 0.05);
        // Every patch lies in at least one window (the last one is flush with the far edges).
        let b = a.bounds();
        assert!(
            r.windows
                .iter()
                .any(|w| (w.x_m + 300.0 - b.max_x_m).abs() < 1e-6)
        );
        assert!(
            r.windows
                .iter()
                .any(|w| (w.y_m + 300.0 - b.max_y_m).abs() < 1e-6)
        );
    }

    #[test]
    fn identical_images_give_no_shift_and_unrelated_ones_no_matches() {
        let (w, h) = (200, 160);
        let t = texture(w, h, 5);
        let a = raster(t.clone(), w, h, 0.0, 1000.0, 2.0);
        let same = coregister(&a, &a, &CoregParams::default()).unwrap();
        assert!(same.patches_matched > 30);
        assert!(same.shift_m.unwrap().max < 0.05, "{:?}", same.shift_m);
        let other = raster(texture(w, h, 99), w, h, 0.0, 1000.0, 2.0);
        let r = coregister(&a, &other, &CoregParams::default()).unwrap();
        assert!(r.patches_tried > 30);
        assert_eq!(r.patches_matched, 0, "{:?}", r.shift_m);
        assert!(r.shift_m.is_none() && r.median_dx_m.is_none() && r.window_shift_m.is_none());
    }

    /// The peak analysis on synthetic correlation surfaces: a quadratic peak is found exactly;
    /// a ridge (a straight edge, located across itself only) is refused however high it is; a
    /// maximum on the border or below the threshold is refused.
    #[test]
    fn peak_is_subpixel_and_refuses_ridges_and_borders() {
        let dim = 9;
        let surf = |f: &dyn Fn(f64, f64) -> f64| -> Vec<f64> {
            (0..dim * dim)
                .map(|k| f((k % dim) as f64, (k / dim) as f64))
                .collect()
        };
        let sharp = surf(&|x, y| 0.95 - 0.1 * (x - 4.3).powi(2) - 0.08 * (y - 3.8).powi(2));
        let (x, y, v) = peak(&sharp, dim, 0.85, 0.01).unwrap();
        assert!((x - 4.3).abs() < 1e-9 && (y - 3.8).abs() < 1e-9, "{x} {y}");
        assert!((v - 0.95).abs() < 0.02);
        // Sharp across (x), nearly flat along (y): an edge.
        let ridge = surf(&|x, y| 0.97 - 0.1 * (x - 4.0).powi(2) - 0.001 * (y - 4.0).powi(2));
        assert!(peak(&ridge, dim, 0.85, 0.01).is_none());
        // The same ridge rotated by 45 degrees.
        let diag = surf(&|x, y| {
            let (u, w) = ((x - 4.0 + y - 4.0) / 2f64.sqrt(), (x - y) / 2f64.sqrt());
            0.97 - 0.1 * u * u - 0.001 * w * w
        });
        assert!(peak(&diag, dim, 0.85, 0.01).is_none());
        assert!(
            peak(&diag, dim, 0.85, 0.0).is_some(),
            "curved down a little: found"
        );
        let border = surf(&|x, _| 0.9 + 0.01 * x);
        assert!(peak(&border, dim, 0.85, 0.0).is_none());
        assert!(peak(&sharp, dim, 0.96, 0.01).is_none());
        let nan = vec![f64::NAN; dim * dim];
        assert!(peak(&nan, dim, 0.85, 0.01).is_none());
    }

    #[test]
    fn a_straight_edge_image_gives_no_shift() {
        // Vertical stripes only: every patch is an edge (aperture problem), none may count.
        let (w, h) = (160, 160);
        let t: Vec<u8> = (0..w * h)
            .map(|i| if (i % w) / 9 % 2 == 0 { 40 } else { 200 })
            .collect();
        let a = raster(t.clone(), w, h, 0.0, 1000.0, 1.0);
        let b = raster(t, w, h, 0.0, 1001.5, 1.0);
        let r = coregister(&a, &b, &CoregParams::default()).unwrap();
        assert!(r.patches_tried > 0);
        assert_eq!(r.patches_matched, 0, "{:?}", r.patches.first());
    }

    #[test]
    fn bad_inputs_are_refused_by_name() {
        let t = texture(100, 100, 1);
        let a = raster(t.clone(), 100, 100, 0.0, 1000.0, 1.0);
        let far = raster(t.clone(), 100, 100, 10_000.0, 1000.0, 1.0);
        assert_eq!(
            coregister(&a, &far, &CoregParams::default()),
            Err(CoregError::NoOverlap)
        );
        let mut other_crs = raster(t, 100, 100, 0.0, 1000.0, 1.0);
        other_crs = Raster::new(
            100,
            100,
            1,
            other_crs.into_data(),
            GeoTransform::north_up(0.0, 1000.0, 1.0, -1.0).unwrap(),
            Crs::Utm {
                zone: 15,
                north: true,
            },
            None,
        )
        .unwrap();
        assert!(matches!(
            coregister(&a, &other_crs, &CoregParams::default()),
            Err(CoregError::CrsMismatch { .. })
        ));
        let p = CoregParams {
            window_m: f64::NAN,
            ..CoregParams::default()
        };
        assert!(matches!(
            coregister(&a, &a, &p),
            Err(CoregError::BadParam {
                key: "window_m",
                ..
            })
        ));
        let p = CoregParams {
            search_px: 1000,
            ..CoregParams::default()
        };
        assert!(matches!(
            coregister(&a, &a, &p),
            Err(CoregError::BadParam {
                key: "search_px",
                ..
            })
        ));
        // A window so small that the grid would be huge is refused, not looped over.
        let p = CoregParams {
            window_m: 1e-9,
            ..CoregParams::default()
        };
        assert!(matches!(
            coregister(&a, &a, &p),
            Err(CoregError::BadParam {
                key: "window_m",
                ..
            })
        ));
        let tiny = raster(texture(40, 40, 2), 40, 40, 0.0, 1000.0, 1.0);
        assert!(matches!(
            coregister(&tiny, &tiny, &CoregParams::default()),
            Err(CoregError::TooSmall { .. })
        ));
        let flat = raster(vec![7; 100 * 100], 100, 100, 0.0, 1000.0, 1.0);
        assert!(matches!(
            coregister(&flat, &a, &CoregParams::default()),
            Err(CoregError::Flat { .. })
        ));
    }
}
