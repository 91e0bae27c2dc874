//! The correlation surface over a grid of shifts: its local maxima, the sub-pixel peak from a
//! parabola through the neighbours in each axis, and the peak's principal curvatures (an edge's
//! ridge against a corner's point).

use super::*;

/// Correlation values over a grid of shifts; `NaN` where undefined (too little overlap, flat).
#[derive(Debug, Clone)]
pub struct Surface {
    /// Shifts along x.
    pub width: usize,
    /// Shifts along y.
    pub height: usize,
    /// Correlation per shift, row-major `width * height` (`NaN` where undefined).
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
