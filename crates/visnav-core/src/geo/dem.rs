//! Terrain model: heights and ray/terrain intersection (in memory; `visnav_io::geo::dem` loads
//! one from a GeoTIFF).
//!
//! [`Dem`] is either a gridded model ([`GridDem`], a one-band raster of heights, metres,
//! orthometric/AMSL unless the source says otherwise) or a constant height ([`Dem::Flat`], for maps
//! without a DEM such as NAIP North Dakota, ground about 580 m AMSL).
//!
//! Coordinates are the DEM's map coordinates: `x_m`, `y_m` projected (easting, northing, metres)
//! and `z` height in metres. Ray intersection needs x, y and z in the same unit, so it refuses
//! (returns `None`) for a DEM in a geographic CRS.
//!
//! # Surface
//!
//! The surface is the bilinear interpolant of the height samples placed at the pixel centres
//! (see `raster`): over each "dual cell" spanned by four neighbouring pixel centres
//! `h(a, b) = h00 + (h10 - h00) a + (h01 - h00) b + (h00 - h10 - h01 + h11) a b`, `a, b in [0, 1]`.
//! A cell with any missing corner (nodata/NaN) is a hole. `height_at` is `None` in holes and in the
//! outer half-pixel margin.
//!
//! # Ray intersection (exact, no tunnelling)
//!
//! The ray `p(t) = o + t d` (`d` normalised, so `t` is the range in metres) is clipped to the height
//! band `[min_h - 1, max_h + 1]` of the whole DEM (above `max_h` nothing can be hit), then the cells
//! under its horizontal projection are visited in order with the Amanatides–Woo grid traversal
//! ("A fast voxel traversal algorithm for ray tracing", Eurographics 1987) done in continuous
//! pixel-centre index space (the geotransform is affine, so the ray stays a straight line there).
//! Inside a cell, `a(t)` and `b(t)` are linear in `t`, so `f(t) = z(t) - h(t)` is a quadratic.
//! The first root is found exactly: if `f` changes sign between the cell entry and exit it is
//! bracketed there; otherwise, if `f` is convex with an interior minimum `f(t*) <= 0` (a ray
//! grazing a ridge or peak inside one cell), it is bracketed in `[t_entry, t*]`. The bracket is
//! refined by bisection to 1e-6 m of range. No step size is involved, so thin ridges cannot be
//! tunnelled through; the hit is the first crossing of the bilinear surface.
//!
//! The result is `None` when the first hit cannot be established with integrity:
//! the origin is below the terrain (`z < h` at the origin), the ray points up out of the height
//! band, it leaves the DEM, it crosses a hole or passes outside the DEM while at or below
//! `max_h + 1`, or the hit is beyond `max_range_m`.

use super::Crs;
use super::raster::{GeoTransform, Raster, bilerp};

/// Errors building a DEM.
#[derive(Debug, thiserror::Error)]
pub enum DemError {
    /// A DEM has exactly one band.
    #[error("DEM raster has {bands} bands, expected 1 (heights)")]
    NotOneBand {
        /// Bands in the raster.
        bands: usize,
    },
    /// Bilinear cells need at least 2 x 2 samples.
    #[error("DEM raster is {width} x {height} px, need at least 2 x 2")]
    TooSmall {
        /// Raster width, samples.
        width: usize,
        /// Raster height, samples.
        height: usize,
    },
    /// Every sample is nodata.
    #[error("DEM raster has no valid height sample")]
    NoValidHeights,
    /// A constant height must be finite.
    #[error("flat DEM height {0} m is not finite")]
    BadFlatHeight(f64),
}

/// A gridded height model (bilinear surface over the pixel centres).
#[derive(Debug, Clone, PartialEq)]
pub struct GridDem {
    width: usize,
    height: usize,
    /// Row-major heights, metres; NaN marks missing samples (nodata already mapped to NaN).
    heights_m: Vec<f32>,
    transform: GeoTransform,
    crs: Crs,
    min_h_m: f64,
    max_h_m: f64,
}

/// Terrain: gridded or constant height, behind one interface.
#[derive(Debug, Clone, PartialEq)]
pub enum Dem {
    /// Gridded DEM/DSM.
    Grid(GridDem),
    /// Constant height everywhere, metres (valid in any CRS, unbounded).
    Flat {
        /// The height, metres.
        height_m: f64,
    },
}

impl Dem {
    /// Wraps a one-band raster of heights (metres).
    pub fn from_raster(raster: &Raster) -> Result<Self, DemError> {
        Ok(Dem::Grid(GridDem::from_raster(raster)?))
    }

    /// Constant-height terrain.
    pub fn flat(height_m: f64) -> Result<Self, DemError> {
        if height_m.is_finite() {
            Ok(Dem::Flat { height_m })
        } else {
            Err(DemError::BadFlatHeight(height_m))
        }
    }

    /// CRS of the grid; `None` for flat terrain (valid in any CRS).
    pub fn crs(&self) -> Option<Crs> {
        match self {
            Dem::Grid(g) => Some(g.crs),
            Dem::Flat { .. } => None,
        }
    }

    /// The grid's cell size (the larger of its two spacings), metres; `None` for flat terrain.
    pub fn cell_m(&self) -> Option<f64> {
        match self {
            Dem::Grid(g) => {
                let (dx, dy) = g.transform.pixel_size();
                Some(dx.max(dy))
            }
            Dem::Flat { .. } => None,
        }
    }

    /// `(min, max)` height over all valid samples, metres.
    pub fn height_range_m(&self) -> (f64, f64) {
        match self {
            Dem::Grid(g) => g.height_range_m(),
            Dem::Flat { height_m } => (*height_m, *height_m),
        }
    }

    /// Terrain height at map coordinates (bilinear), metres; `None` outside the grid or in holes.
    pub fn height_at(&self, x_m: f64, y_m: f64) -> Option<f64> {
        match self {
            Dem::Grid(g) => g.height_at(x_m, y_m),
            Dem::Flat { height_m } => (x_m.is_finite() && y_m.is_finite()).then_some(*height_m),
        }
    }

    /// Slope of the terrain at map coordinates, `[dh/dx, dh/dy]` (metres per metre): the derivative
    /// of the bilinear surface inside its cell (on a cell edge, the cell `height_at` uses); `None`
    /// where `height_at` is `None`. Zero for flat terrain.
    pub fn gradient_at(&self, x_m: f64, y_m: f64) -> Option<[f64; 2]> {
        match self {
            Dem::Grid(g) => g.gradient_at(x_m, y_m),
            Dem::Flat { .. } => (x_m.is_finite() && y_m.is_finite()).then_some([0.0, 0.0]),
        }
    }

    /// First intersection of the ray `origin + t dir` (`t >= 0`, map coordinates with z = height,
    /// `dir` need not be normalised) with the terrain, within `max_range_m` of the origin (pass
    /// `f64::INFINITY` for no limit). Returns the point on the ray (within 1e-6 m of range of the
    /// surface crossing). `None` rules: see the module doc.
    pub fn intersect_ray(
        &self,
        origin_xyz: [f64; 3],
        dir_xyz: [f64; 3],
        max_range_m: f64,
    ) -> Option<[f64; 3]> {
        let (o, d) = normalise_ray(origin_xyz, dir_xyz, max_range_m)?;
        match self {
            Dem::Grid(g) => g.intersect_normalised(o, d, max_range_m),
            Dem::Flat { height_m } => {
                let f0 = o[2] - height_m;
                if f0 < 0.0 {
                    return None;
                }
                if f0 == 0.0 {
                    return Some(o);
                }
                if d[2] >= 0.0 {
                    return None;
                }
                let t = f0 / -d[2];
                (t <= max_range_m).then(|| [o[0] + t * d[0], o[1] + t * d[1], *height_m])
            }
        }
    }
}

/// Validates a ray and normalises its direction.
fn normalise_ray(o: [f64; 3], d: [f64; 3], max_range_m: f64) -> Option<([f64; 3], [f64; 3])> {
    if o.iter().chain(d.iter()).any(|v| !v.is_finite()) || max_range_m.is_nan() || max_range_m < 0.0
    {
        return None;
    }
    let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    if !(n > 0.0 && n.is_finite()) {
        return None;
    }
    Some((o, [d[0] / n, d[1] / n, d[2] / n]))
}

impl GridDem {
    /// Builds the grid from a one-band raster; nodata and NaN samples become holes.
    pub fn from_raster(raster: &Raster) -> Result<Self, DemError> {
        if raster.bands() != 1 {
            return Err(DemError::NotOneBand {
                bands: raster.bands(),
            });
        }
        let (width, height) = (raster.width(), raster.height());
        if width < 2 || height < 2 {
            return Err(DemError::TooSmall { width, height });
        }
        let mut heights_m = Vec::with_capacity(width * height);
        let (mut min_h_m, mut max_h_m) = (f64::INFINITY, f64::NEG_INFINITY);
        for row in 0..height {
            for col in 0..width {
                match raster.value(col, row, 0).filter(|v| v.is_finite()) {
                    Some(v) => {
                        let h = v as f32;
                        min_h_m = min_h_m.min(f64::from(h));
                        max_h_m = max_h_m.max(f64::from(h));
                        heights_m.push(h);
                    }
                    None => heights_m.push(f32::NAN),
                }
            }
        }
        if min_h_m > max_h_m {
            return Err(DemError::NoValidHeights);
        }
        Ok(Self {
            width,
            height,
            heights_m,
            transform: *raster.transform(),
            crs: raster.crs(),
            min_h_m,
            max_h_m,
        })
    }

    /// Width in samples.
    pub fn width(&self) -> usize {
        self.width
    }
    /// Height in samples.
    pub fn height(&self) -> usize {
        self.height
    }
    /// Pixel <-> map transform (corner convention, see `raster`).
    pub fn transform(&self) -> &GeoTransform {
        &self.transform
    }
    /// Horizontal CRS.
    pub fn crs(&self) -> Crs {
        self.crs
    }
    /// The grid as a one-band float raster (NaN where missing), the inverse of
    /// [`Self::from_raster`].
    pub fn to_raster(&self) -> Result<Raster, super::raster::RasterError> {
        Raster::new(
            self.width,
            self.height,
            1,
            super::raster::RasterData::F32(self.heights_m.clone()),
            self.transform,
            self.crs,
            None,
        )
    }
    /// `(min, max)` height over all valid samples, metres.
    pub fn height_range_m(&self) -> (f64, f64) {
        (self.min_h_m, self.max_h_m)
    }
    /// The height samples, row-major (`width * height`), metres; NaN where missing.
    pub fn heights_m(&self) -> &[f32] {
        &self.heights_m
    }

    #[inline]
    fn h(&self, i: usize, j: usize) -> f64 {
        f64::from(self.heights_m[j * self.width + i])
    }

    /// Bilinear height at map coordinates; `None` outside the pixel-centre grid or in holes.
    pub fn height_at(&self, x_m: f64, y_m: f64) -> Option<f64> {
        let (corners, a, b) = self.locate(x_m, y_m)?;
        Some(eval_cell(&corners, a, b))
    }

    /// See [`Dem::gradient_at`]: `dh/da` and `dh/db` of the cell's bilinear form, taken into map
    /// coordinates through the geotransform's linear part (`a` follows columns, `b` rows).
    pub fn gradient_at(&self, x_m: f64, y_m: f64) -> Option<[f64; 2]> {
        let (c, a, b) = self.locate(x_m, y_m)?;
        let cross = c[0] - c[1] - c[2] + c[3];
        let dh_da = c[1] - c[0] + cross * b;
        let dh_db = c[2] - c[0] + cross * a;
        let (da_dx, db_dx) = self.transform.map_delta_to_pixel(1.0, 0.0);
        let (da_dy, db_dy) = self.transform.map_delta_to_pixel(0.0, 1.0);
        Some([dh_da * da_dx + dh_db * db_dx, dh_da * da_dy + dh_db * db_dy])
    }

    /// The dual cell holding map point `(x_m, y_m)` and the point's position `(a, b)` in it;
    /// `None` outside the pixel-centre grid or in a hole.
    fn locate(&self, x_m: f64, y_m: f64) -> Option<([f64; 4], f64, f64)> {
        let (col, row) = self.transform.map_to_pixel(x_m, y_m);
        let (fx, fy) = (col - 0.5, row - 0.5);
        if !(fx >= 0.0 && fy >= 0.0) {
            return None; // also rejects NaN
        }
        let (wm1, hm1) = ((self.width - 1) as f64, (self.height - 1) as f64);
        if fx > wm1 || fy > hm1 {
            return None;
        }
        // Cell index clamped so the last row/column of centres belongs to the last cell.
        let i = (fx.floor() as usize).min(self.width - 2); // ok: fx in [0, w-1]
        let j = (fy.floor() as usize).min(self.height - 2); // ok: fy in [0, h-1]
        let (a, b) = (fx - i as f64, fy - j as f64);
        Some((self.cell(i, j)?, a, b))
    }

    /// The four corner heights `[h00, h10, h01, h11]` of dual cell `(i, j)`, `None` for a hole.
    #[inline]
    fn cell(&self, i: usize, j: usize) -> Option<[f64; 4]> {
        let c = [
            self.h(i, j),
            self.h(i + 1, j),
            self.h(i, j + 1),
            self.h(i + 1, j + 1),
        ];
        c.iter().all(|v| !v.is_nan()).then_some(c)
    }

    /// See [`Dem::intersect_ray`].
    pub fn intersect_ray(
        &self,
        origin_xyz: [f64; 3],
        dir_xyz: [f64; 3],
        max_range_m: f64,
    ) -> Option<[f64; 3]> {
        let (o, d) = normalise_ray(origin_xyz, dir_xyz, max_range_m)?;
        self.intersect_normalised(o, d, max_range_m)
    }

    fn intersect_normalised(&self, o: [f64; 3], d: [f64; 3], max_range_m: f64) -> Option<[f64; 3]> {
        if self.crs == Crs::Geographic {
            return None; // x, y in degrees, z in metres: no straight rays
        }
        const MARGIN_M: f64 = 1.0;
        let z_top = self.max_h_m + MARGIN_M;
        let z_bottom = self.min_h_m - MARGIN_M;
        // Range interval where the ray is inside the height band [z_bottom, z_top].
        let t_lo = if o[2] <= z_top {
            0.0
        } else if d[2] < 0.0 {
            (z_top - o[2]) / d[2]
        } else {
            return None; // above all terrain and not descending
        };
        let t_band_end = if d[2] < 0.0 {
            ((z_bottom - o[2]) / d[2]).max(0.0)
        } else if d[2] > 0.0 {
            ((z_top - o[2]) / d[2]).max(0.0)
        } else {
            f64::INFINITY
        };
        let t_hi = t_band_end.min(max_range_m);
        if t_lo > t_hi {
            return None;
        }

        // Horizontal part in pixel-centre index space (fx = col - 0.5, fy = row - 0.5).
        let (c0, r0) = self.transform.map_to_pixel(o[0], o[1]);
        let (ox, oy) = (c0 - 0.5, r0 - 0.5);
        let (dx, dy) = self.transform.map_delta_to_pixel(d[0], d[1]);
        let (wm1, hm1) = ((self.width - 1) as f64, (self.height - 1) as f64);
        let (t_in, t_out) = clip_slab(ox, dx, wm1, 0.0, f64::INFINITY)
            .and_then(|(a, b)| clip_slab(oy, dy, hm1, a, b))?;
        // Over unknown terrain while low enough to hit something: the first hit is unknowable.
        let slack = 1e-9 * (1.0 + t_lo.abs());
        if t_in > t_lo + slack || t_out < t_lo {
            return None;
        }
        let t_end = t_hi.min(t_out);

        let f = |t: f64, i: usize, j: usize, c: &[f64; 4]| -> f64 {
            let a = (ox + t * dx - i as f64).clamp(0.0, 1.0);
            let b = (oy + t * dy - j as f64).clamp(0.0, 1.0);
            o[2] + t * d[2] - eval_cell(c, a, b)
        };
        let point = |t: f64| [o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]];

        // Amanatides–Woo set-up at t_lo.
        let (px, py) = (ox + t_lo * dx, oy + t_lo * dy);
        let mut i = cell_index(px, dx, self.width);
        let mut j = cell_index(py, dy, self.height);
        let axis = |p0: f64, dp: f64, idx: usize| -> (i64, f64, f64) {
            if dp > 0.0 {
                (1, (idx as f64 + 1.0 - p0) / dp, 1.0 / dp)
            } else if dp < 0.0 {
                (-1, (idx as f64 - p0) / dp, -1.0 / dp)
            } else {
                (0, f64::INFINITY, f64::INFINITY)
            }
        };
        let (step_i, mut next_i, delta_i) = axis(ox, dx, i);
        let (step_j, mut next_j, delta_j) = axis(oy, dy, j);

        let mut t0 = t_lo;
        let mut first = true;
        let max_cells = self.width + self.height + 4;
        for _ in 0..max_cells {
            let t1 = next_i.min(next_j).min(t_end).max(t0);
            let c = self.cell(i, j)?; // a hole on the path: unknowable
            let f0 = f(t0, i, j, &c);
            if first {
                first = false;
                if f0 < 0.0 {
                    return None; // origin (t_lo = 0 here) below the terrain
                }
            }
            if f0 <= 0.0 {
                return Some(point(t0));
            }
            let f1 = f(t1, i, j, &c);
            if f1 <= 0.0 {
                return Some(point(bisect(&|t| f(t, i, j, &c), t0, t1)));
            }
            // No sign change: look for an interior minimum of the quadratic (grazing hit).
            let [h00, h10, h01, h11] = c;
            let k = h00 - h10 - h01 + h11;
            let f2 = -2.0 * k * dx * dy; // f''(t)
            if f2 > 0.0 {
                let a0 = ox + t0 * dx - i as f64;
                let b0 = oy + t0 * dy - j as f64;
                let fp0 = d[2] - (h10 - h00) * dx - (h01 - h00) * dy - k * (dx * b0 + dy * a0);
                let ts = t0 - fp0 / f2;
                if ts > t0 && ts < t1 && f(ts, i, j, &c) <= 0.0 {
                    return Some(point(bisect(&|t| f(t, i, j, &c), t0, ts)));
                }
            }
            if t1 >= t_end {
                return None; // out of range, out of the height band, or out of the DEM
            }
            // Step to the next cell.
            if next_i <= next_j {
                i = step(i, step_i, self.width)?;
                t0 = next_i;
                next_i += delta_i;
            } else {
                j = step(j, step_j, self.height)?;
                t0 = next_j;
                next_j += delta_j;
            }
        }
        None
    }
}

/// Bilinear height of a cell `[h00, h10, h01, h11]` at fractions `(a, b)`.
#[inline]
fn eval_cell(c: &[f64; 4], a: f64, b: f64) -> f64 {
    bilerp(c[0], c[1], c[2], c[3], a, b)
}

/// Intersects `p0 + t dp in [0, max]` with the running interval `[t_a, t_b]`.
fn clip_slab(p0: f64, dp: f64, max: f64, t_a: f64, t_b: f64) -> Option<(f64, f64)> {
    if dp == 0.0 {
        return (p0 >= 0.0 && p0 <= max).then_some((t_a, t_b));
    }
    let (ta, tb) = ((0.0 - p0) / dp, (max - p0) / dp);
    let (lo, hi) = if ta <= tb { (ta, tb) } else { (tb, ta) };
    let (lo, hi) = (lo.max(t_a), hi.min(t_b));
    (lo <= hi).then_some((lo, hi))
}

/// Dual-cell index containing coordinate `p` (in `[0, n-1]` up to rounding) for travel direction
/// `dp`: on a cell boundary the cell ahead is chosen; clamped to `[0, n-2]`.
fn cell_index(p: f64, dp: f64, n: usize) -> usize {
    let f = p.floor();
    let mut idx = if f <= 0.0 { 0.0 } else { f };
    if dp < 0.0 && p == f && idx > 0.0 {
        idx -= 1.0; // on a boundary moving towards lower indices: the cell behind the boundary
    }
    (idx as usize).min(n - 2) // ok: idx >= 0 and finite
}

/// Advances a cell index by `s` (+1/-1), `None` when it leaves `[0, n-2]`.
fn step(idx: usize, s: i64, n: usize) -> Option<usize> {
    let next = idx as i64 + s;
    (next >= 0 && next <= n as i64 - 2).then_some(next as usize)
}

/// Bisection on `[lo, hi]` with `f(lo) > 0 >= f(hi)`, to 1e-6 (range metres); returns the
/// midpoint of the final bracket.
fn bisect(f: &dyn Fn(f64) -> f64, mut lo: f64, mut hi: f64) -> f64 {
    for _ in 0..200 {
        if hi - lo <= 1e-6 {
            break;
        }
        let mid = 0.5 * (lo + hi);
        if f(mid) > 0.0 {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    0.5 * (lo + hi)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geo::raster::RasterData;
    use proptest::prelude::*;

    const UTM: Crs = Crs::Utm {
        zone: 33,
        north: true,
    };

    /// DEM with `cell_m` spacing, top-left corner at (x0, y0), heights from `h(col, row)`.
    fn grid(
        w: usize,
        hgt: usize,
        cell_m: f64,
        nodata: Option<f64>,
        h: impl Fn(usize, usize) -> f32,
    ) -> Dem {
        let mut v = Vec::with_capacity(w * hgt);
        for r in 0..hgt {
            for c in 0..w {
                v.push(h(c, r));
            }
        }
        let gt = GeoTransform::north_up(500_000.0, 4_000_000.0, cell_m, cell_m).unwrap();
        let r = Raster::new(w, hgt, 1, RasterData::F32(v), gt, UTM, nodata).unwrap();
        Dem::from_raster(&r).unwrap()
    }

    #[test]
    fn the_gradient_is_the_bilinear_surfaces_slope() {
        // Heights 2 col + 3 row + 0.5 col row on 4 m cells (rows run south).
        let dem = grid(6, 6, 4.0, None, |c, r| {
            (2.0 * c as f64 + 3.0 * r as f64 + 0.5 * (c * r) as f64) as f32
        });
        for &(c, r) in &[(1.3, 2.6), (0.1, 0.2), (3.9, 4.5), (2.0, 2.0)] {
            let (x, y) = centre(c, r, 4.0);
            let g = dem.gradient_at(x, y).unwrap();
            // The surface is linear along x and along y inside a cell: differences are exact up to
            // the rounding of map coordinates near 4e6 m (5e-10 m), hence a centimetre step.
            let step = 1e-2;
            let h = |x: f64, y: f64| dem.height_at(x, y).unwrap();
            let fd = [
                (h(x + step, y) - h(x - step, y)) / (2.0 * step),
                (h(x, y + step) - h(x, y - step)) / (2.0 * step),
            ];
            // The samples lie on one bilinear function, so every cell's surface is that function.
            assert!((g[0] - fd[0]).abs() < 1e-6, "{c} {r}: {g:?} vs {fd:?}");
            assert!((g[1] - fd[1]).abs() < 1e-6, "{c} {r}: {g:?} vs {fd:?}");
            // Analytic: dh/dcol over 4 m east; rows run south, so dh/dy = -dh/drow / 4 m.
            let expect_x = (2.0 + 0.5 * r) / 4.0;
            let expect_y = -(3.0 + 0.5 * c) / 4.0;
            assert!((g[0] - expect_x).abs() < 1e-9, "{c} {r}: {g:?}");
            assert!((g[1] - expect_y).abs() < 1e-9, "{c} {r}: {g:?}");
        }
        assert_eq!(
            Dem::flat(3.0).unwrap().gradient_at(1.0, 2.0),
            Some([0.0, 0.0])
        );
        assert_eq!(dem.gradient_at(f64::NAN, 0.0), None);
    }

    /// Map coordinates of pixel centre (c, r) for the grids above.
    fn centre(c: f64, r: f64, cell_m: f64) -> (f64, f64) {
        (
            500_000.0 + (c + 0.5) * cell_m,
            4_000_000.0 - (r + 0.5) * cell_m,
        )
    }

    /// Plane h = 100 + 0.3 x' - 0.2 y' in local metres (x' = x - 500000, y' = y - 4000000), which
    /// the bilinear surface reproduces exactly.
    fn plane_dem() -> (Dem, impl Fn(f64, f64) -> f64) {
        let cell = 10.0;
        let hf = |x: f64, y: f64| 100.0 + 0.3 * (x - 500_000.0) - 0.2 * (y - 4_000_000.0);
        let dem = grid(60, 50, cell, None, |c, r| {
            let (x, y) = centre(c as f64, r as f64, cell);
            hf(x, y) as f32
        });
        (dem, hf)
    }

    #[test]
    fn vertical_ray_hits_the_height_below() {
        let (dem, hf) = plane_dem();
        let (x, y) = (500_123.4, 3_999_777.7);
        let p = dem
            .intersect_ray([x, y, 2000.0], [0.0, 0.0, -1.0], f64::INFINITY)
            .unwrap();
        assert!((p[0] - x).abs() < 1e-9 && (p[1] - y).abs() < 1e-9);
        assert!((p[2] - hf(x, y)).abs() < 1e-5, "{p:?} vs {}", hf(x, y));
        assert!((dem.height_at(x, y).unwrap() - hf(x, y)).abs() < 1e-4);
        // Near-vertical ray (horizontal component 1e-12).
        let q = dem
            .intersect_ray([x, y, 2000.0], [1e-12, -1e-12, -1.0], f64::INFINITY)
            .unwrap();
        assert!((q[2] - p[2]).abs() < 1e-5);
        // Upward ray, ray starting below ground, zero direction: None.
        assert_eq!(
            dem.intersect_ray([x, y, 2000.0], [0.0, 0.0, 1.0], 1e9),
            None
        );
        assert_eq!(
            dem.intersect_ray([x, y, hf(x, y) - 1.0], [0.0, 0.1, -1.0], 1e9),
            None
        );
        assert_eq!(dem.intersect_ray([x, y, 2000.0], [0.0; 3], 1e9), None);
        assert_eq!(
            dem.intersect_ray([x, y, f64::NAN], [0.0, 0.0, -1.0], 1e9),
            None
        );
        // Out of range.
        let range = 2000.0 - hf(x, y);
        assert!(
            dem.intersect_ray([x, y, 2000.0], [0.0, 0.0, -1.0], range - 0.01)
                .is_none()
        );
        assert!(
            dem.intersect_ray([x, y, 2000.0], [0.0, 0.0, -1.0], range + 0.01)
                .is_some()
        );
    }

    proptest! {
        #[test]
        fn oblique_ray_matches_analytic_plane(
            x in 500_050.0f64..500_550.0, y in 3_999_550.0f64..3_999_950.0,
            alt in 5.0f64..1500.0, az in 0.0f64..std::f64::consts::TAU, dip_deg in 20.0f64..90.0,
        ) {
            let (dem, hf) = plane_dem();
            let o = [x, y, hf(x, y) + alt];
            let dip = dip_deg.to_radians();
            let d = [dip.cos() * az.cos(), dip.cos() * az.sin(), -dip.sin()];
            // Analytic: o_z + t d_z = 100 + 0.3 (o_x + t d_x - x0) - 0.2 (o_y + t d_y - y0).
            let den = d[2] - 0.3 * d[0] + 0.2 * d[1];
            let t = (hf(o[0], o[1]) - o[2]) / den;
            // Heights are stored as f32 (~3e-5 m here); a shallow crossing stretches that by 1/|den|.
            let tol = 1e-4 + 3e-5 / den.abs();
            let expect = [o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]];
            let inside = dem.height_at(expect[0], expect[1]).is_some();
            match dem.intersect_ray(o, d, f64::INFINITY) {
                Some(p) => {
                    prop_assert!(inside);
                    for k in 0..3 {
                        prop_assert!((p[k] - expect[k]).abs() < tol, "{:?} vs {:?}", p, expect);
                    }
                }
                None => prop_assert!(!inside, "missed an in-grid hit at {:?}", expect),
            }
        }
    }

    /// A 1-sample-wide ridge 50 m high on flat ground at 0 m, 10 m cells. The bilinear ridge is a
    /// tent 20 m wide at the base; a ray skimming just below its crest crosses it over a range of
    /// a few centimetres, which any fixed-step marcher with steps >= 0.5 cell would tunnel through.
    #[test]
    fn sharp_ridge_is_not_tunnelled() {
        let cell = 10.0;
        let ridge_col = 20usize;
        let dem = grid(
            40,
            40,
            cell,
            None,
            |c, _| if c == ridge_col { 50.0 } else { 0.0 },
        );
        let (xr, y) = centre(ridge_col as f64, 20.0, cell);
        // Horizontal ray 1 cm below the crest, coming from the west.
        let o = [xr - 150.0, y, 49.99];
        let p = dem
            .intersect_ray(o, [1.0, 0.0, 0.0], f64::INFINITY)
            .expect("ray must hit the ridge");
        // Tent flank: h = 50 (1 - |x - xr| / 10) = 49.99 at x = xr - 0.002.
        assert!((p[0] - (xr - 0.002)).abs() < 1e-4, "{p:?}");
        // Slightly descending ray that, sampled every half cell, is above the terrain at every
        // sample west and east of the ridge's crest.
        let o2 = [xr - 102.5, y, 60.0];
        let d2 = [1.0, 0.0, -0.1];
        let p2 = dem.intersect_ray(o2, d2, f64::INFINITY).unwrap();
        let h_at = |x: f64| dem.height_at(x, y).unwrap();
        // A coarse marcher (samples every half cell, 5 m) never sees the ray below the ground
        // anywhere on the grid, so it would report no hit at all.
        let mut coarse_samples = 0;
        for k in 0.. {
            let s = k as f64 * 5.0;
            let Some(h) = dem.height_at(o2[0] + s, y) else {
                break;
            };
            coarse_samples += 1;
            assert!(60.0 - 0.1 * s > h, "coarse sample {k} is below ground");
        }
        assert!(coarse_samples > 50);
        assert!(
            p2[0] < xr && p2[0] > xr - cell,
            "hit must be on the west flank: {p2:?}"
        );
        assert!((p2[2] - h_at(p2[0])).abs() < 1e-4);
        // Grazing inside one cell: a ray crossing a peak cell diagonally, whose minimum clearance
        // is inside the cell and whose ends are above ground (interior-minimum case).
        let dem3 = grid(
            4,
            4,
            cell,
            None,
            |c, r| if (c, r) == (1, 1) { 10.0 } else { 0.0 },
        );
        // Cell (1,1)-(2,2) has h00 = 10, others 0: h = 10 (1-a)(1-b). Along a = b = s the
        // height is 10 (1-s)^2; a horizontal ray at z = 2.5 along the anti-diagonal a + b = 1
        // (h = 10 a (1-a), max 2.5 at a = 0.5) touches it; at z = 2.4 it crosses twice inside.
        let (xa, ya) = centre(1.0, 2.0, cell); // a = 0, b = 1
        let (xb, yb) = centre(2.0, 1.0, cell); // a = 1, b = 0
        let d3 = [xb - xa, yb - ya, 0.0];
        let o3 = [xa, ya, 2.4];
        let p3 = dem3
            .intersect_ray(o3, d3, f64::INFINITY)
            .expect("graze hit");
        let a = (p3[0] - xa) / (xb - xa);
        let expect_a = (1.0 - (1.0f64 - 4.0 * 0.24).sqrt()) / 2.0; // 10 a (1-a) = 2.4
        assert!((a - expect_a).abs() < 1e-6, "{a} vs {expect_a}");
        assert!(
            dem3.intersect_ray([xa, ya, 2.6], d3, f64::INFINITY)
                .is_none()
        );
    }

    #[test]
    fn holes_and_edges() {
        let cell = 10.0;
        let nod = -9999.0;
        let dem = grid(30, 30, cell, Some(nod), |c, r| {
            if (10..12).contains(&c) && (10..12).contains(&r) {
                nod as f32
            } else {
                100.0
            }
        });
        let (xh, yh) = centre(10.5, 10.5, cell);
        assert_eq!(dem.height_at(xh, yh), None);
        assert_eq!(dem.height_range_m(), (100.0, 100.0));
        // Vertical ray into the hole: None. Next to it: hit.
        assert_eq!(
            dem.intersect_ray([xh, yh, 500.0], [0.0, 0.0, -1.0], 1e9),
            None
        );
        let (xg, yg) = centre(20.0, 20.0, cell);
        let p = dem
            .intersect_ray([xg, yg, 500.0], [0.0, 0.0, -1.0], 1e9)
            .unwrap();
        assert!(
            p[0] == xg && p[1] == yg && (p[2] - 100.0).abs() < 1e-6,
            "{p:?}"
        );
        // Low oblique ray passing over the hole at 100.5 m (below max_h + 1): None, because the
        // hole could hide a hit.
        let o = [xh - 50.0, yh, 100.5];
        assert_eq!(dem.intersect_ray(o, [1.0, 0.0, -0.001], 1e9), None);
        // The same ray passing high over the hole: fine.
        let o = [xh - 50.0, yh, 200.0];
        let p = dem.intersect_ray(o, [1.0, 0.0, -1.0], 1e9).unwrap();
        assert!((p[0] - (xh + 50.0)).abs() < 1e-5 && (p[2] - 100.0).abs() < 1e-5);
        // A ray leaving the DEM above ground: None.
        let (xe, ye) = centre(28.0, 5.0, cell);
        assert_eq!(
            dem.intersect_ray([xe, ye, 100.5], [1.0, 0.0, -0.001], 1e9),
            None
        );
        // A ray coming from outside the DEM high above it and descending inside: hit.
        let p = dem
            .intersect_ray([499_900.0, ye, 400.0], [1.0, 0.0, -1.0], 1e9)
            .unwrap();
        assert!((p[0] - 500_200.0).abs() < 1e-5, "{p:?}");
        // From outside, low: None (unknown terrain before the DEM).
        assert_eq!(
            dem.intersect_ray([499_900.0, ye, 100.5], [1.0, 0.0, -0.01], 1e9),
            None
        );
    }

    #[test]
    fn flat_dem_behaves_like_a_plane() {
        let dem = Dem::flat(580.0).unwrap();
        assert_eq!(dem.height_at(1.0, 2.0), Some(580.0));
        assert_eq!(dem.crs(), None);
        let p = dem
            .intersect_ray([100.0, 200.0, 1080.0], [3.0, 4.0, -5.0], f64::INFINITY)
            .unwrap();
        assert!((p[0] - 400.0).abs() < 1e-9 && (p[1] - 600.0).abs() < 1e-9 && p[2] == 580.0);
        assert_eq!(
            dem.intersect_ray([0.0, 0.0, 1080.0], [3.0, 4.0, -5.0], 700.0),
            None
        );
        assert_eq!(
            dem.intersect_ray([0.0, 0.0, 1080.0], [0.0, 0.0, 1.0], 1e9),
            None
        );
        assert_eq!(
            dem.intersect_ray([0.0, 0.0, 570.0], [0.0, 0.0, -1.0], 1e9),
            None
        );
        assert!(Dem::flat(f64::NAN).is_err());
        // Same interface as a gridded constant DEM.
        let g = grid(50, 50, 10.0, None, |_, _| 580.0);
        let o = [500_100.0, 3_999_800.0, 1080.0];
        let d = [0.3, -0.2, -1.0];
        let pg = g.intersect_ray(o, d, 1e9).unwrap();
        let pf = dem.intersect_ray(o, d, 1e9).unwrap();
        for k in 0..3 {
            assert!((pg[k] - pf[k]).abs() < 1e-5);
        }
    }

    #[test]
    fn rejects_bad_rasters() {
        let gt = GeoTransform::north_up(0.0, 0.0, 1.0, 1.0).unwrap();
        let r = Raster::new(1, 5, 1, RasterData::F32(vec![0.0; 5]), gt, UTM, None).unwrap();
        assert!(matches!(
            Dem::from_raster(&r),
            Err(DemError::TooSmall { .. })
        ));
        let r = Raster::new(2, 2, 2, RasterData::F32(vec![0.0; 8]), gt, UTM, None).unwrap();
        assert!(matches!(
            Dem::from_raster(&r),
            Err(DemError::NotOneBand { .. })
        ));
        let r = Raster::new(2, 2, 1, RasterData::F32(vec![f32::NAN; 4]), gt, UTM, None).unwrap();
        assert!(matches!(
            Dem::from_raster(&r),
            Err(DemError::NoValidHeights)
        ));
    }
}
