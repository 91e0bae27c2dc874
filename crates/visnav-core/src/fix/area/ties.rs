//! The tie-point stage: textured patches of the rectified frame (Shi-Tomasi corner strength),
//! each searched for a few pixels around its predicted place with the correlation computed
//! directly (window sums from summed-area tables), kept when the peak passes the module rules of
//! [`super`].

use rayon::prelude::*;

use super::*;

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
    /// Centre column in the source plane (pixel centres at integers).
    pub cx: usize,
    /// Centre row in the source plane.
    pub cy: usize,
    /// Side length, pixels (odd).
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
    /// Patch centre in the searched plane, column (sub-pixel).
    pub x: f64,
    /// Patch centre in the searched plane, row (sub-pixel).
    pub y: f64,
    /// The correlation (NCC) at the match.
    pub ncc: f64,
}

/// Where and how hard one patch is searched ([`match_patch`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TieSearch {
    /// The predicted centre, integer pixels of the searched plane.
    pub centre_px: [i64; 2],
    /// Search radius, pixels (Chebyshev).
    pub radius_px: usize,
    /// Smallest correlation accepted ([`MIN_TIE_NCC`], [`MIN_TIE_NCC_NEAR`]).
    pub min_ncc: f64,
}

/// Searches `patch` in `map` with its centre within `search.radius_px` pixels (Chebyshev) of
/// `search.centre_px`; the match when the peak passes the module doc's rules.
pub fn match_patch(
    map: &Plane,
    sums: &Integral,
    patch: &Patch,
    search: TieSearch,
) -> Option<TieMatch> {
    let TieSearch {
        centre_px: [px, py],
        radius_px: radius,
        min_ncc,
    } = search;
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
