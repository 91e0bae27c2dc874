//! The terrain of a tiled map in flight: the heights its tiles carry (`tiled::TileHeights`, each
//! a window of one DEM on the DEM's own grid) joined into one grid over the tiles in memory, and
//! the terrain of no tile at all (no height anywhere, the map's height range).
//!
//! The windows are cut from one DEM at whole-sample offsets, so joining them is copying each
//! at its offset from the first; where windows overlap (their margins) they hold the same
//! samples. A missing sample (NaN) never overwrites a present one.

use std::sync::Arc;

use visnav_core::geo::Crs;
use visnav_core::geo::dem::Dem;
use visnav_core::geo::raster::{Bounds, GeoTransform, Raster, RasterData};

/// Most samples one joined terrain holds: 64 M (256 MB of f32; a 1 m surface model over an
/// 8 km square). A tile that would grow the union beyond it is left out.
pub const MAX_MOSAIC_CELLS: usize = 64 << 20;

/// Largest offset between two tiles' grids, samples: a tile farther from the first is not of the
/// same map (a damaged or hostile heights file) and is left out.
const MAX_OFFSET_CELLS: f64 = (1u64 << 31) as f64;

/// The grids of `tiles` (gridded terrains of one DEM, most needed first) as one terrain: each in
/// turn, left out when it is not north-up on the first's grid or would grow the union beyond
/// [`MAX_MOSAIC_CELLS`]; `None` when there is no grid (or the first is rotated).
pub fn join(tiles: &[Arc<Dem>]) -> Option<Dem> {
    let grids: Vec<_> = tiles
        .iter()
        .filter_map(|d| match d.as_ref() {
            Dem::Grid(g) => Some(g),
            Dem::Flat { .. } => None,
        })
        .collect();
    let first = grids.first()?;
    let c = first.transform().coeffs();
    if grids.len() == 1 {
        return Some(Dem::Grid((*first).clone()));
    }
    let (px, py) = (c[1], c[5]);
    if c[2] != 0.0 || c[4] != 0.0 {
        return None;
    }
    // Each grid's offset from the first, whole samples, and the union so far.
    let (mut c0, mut r0) = (0i64, 0i64);
    let (mut c1, mut r1) = (first.width() as i64, first.height() as i64);
    let mut kept = vec![(*first, (0i64, 0i64))];
    for g in &grids[1..] {
        let k = g.transform().coeffs();
        if k[2] != 0.0 || k[4] != 0.0 || k[1] != px || k[5] != py || g.crs() != first.crs() {
            continue;
        }
        let (dc, dr) = ((k[0] - c[0]) / px, (k[3] - c[3]) / py);
        let (ic, ir) = (dc.round(), dr.round());
        if !(ic.abs() <= MAX_OFFSET_CELLS && ir.abs() <= MAX_OFFSET_CELLS)
            || (dc - ic).abs() > 1e-6
            || (dr - ir).abs() > 1e-6
        {
            continue;
        }
        let (oc, or) = (ic as i64, ir as i64); // ok: finite, whole and bounded
        let (gw, gh) = (g.width() as i64, g.height() as i64);
        let (n0, m0, n1, m1) = (c0.min(oc), r0.min(or), c1.max(oc + gw), r1.max(or + gh));
        if (n1 - n0)
            .checked_mul(m1 - m0)
            .is_none_or(|n| n > MAX_MOSAIC_CELLS as i64)
        {
            continue;
        }
        (c0, r0, c1, r1) = (n0, m0, n1, m1);
        kept.push((*g, (oc, or)));
    }
    // ok: the union is bounded by MAX_MOSAIC_CELLS
    let (w, h) = ((c1 - c0) as usize, (r1 - r0) as usize);
    let mut heights = vec![f32::NAN; w * h];
    for (g, (oc, or)) in &kept {
        let (gw, src) = (g.width(), g.heights_m());
        for row in 0..g.height() {
            let dst = ((or - r0) as usize + row) * w + (oc - c0) as usize;
            for (d, s) in heights[dst..dst + gw]
                .iter_mut()
                .zip(&src[row * gw..(row + 1) * gw])
            {
                if !s.is_nan() {
                    *d = *s;
                }
            }
        }
    }
    let transform = GeoTransform::new([
        c[0] + c0 as f64 * px,
        px,
        0.0,
        c[3] + r0 as f64 * py,
        0.0,
        py,
    ])
    .ok()?;
    let raster = Raster::new(
        w,
        h,
        1,
        RasterData::F32(heights),
        transform,
        first.crs(),
        None,
    )
    .ok()?;
    Dem::from_raster(&raster).ok()
}

/// A terrain with no height anywhere (every query `None`, no ray hits it) whose height range is
/// `lo_m` to `hi_m`: what a tiled map lends before any of its heights is in memory. Two samples
/// at the map's corner, the other two missing, so its one cell is a hole.
pub fn none(bounds: &Bounds, crs: Crs, lo_m: f64, hi_m: f64) -> Option<Dem> {
    let (lo, hi) = (lo_m.min(hi_m) as f32, lo_m.max(hi_m) as f32);
    let transform =
        GeoTransform::new([bounds.min_x_m, 1.0, 0.0, bounds.max_y_m, 0.0, -1.0]).ok()?;
    let raster = Raster::new(
        2,
        2,
        1,
        RasterData::F32(vec![lo, f32::NAN, f32::NAN, hi]),
        transform,
        crs,
        None,
    )
    .ok()?;
    Dem::from_raster(&raster).ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid(x0: f64, y0: f64, w: usize, h: usize, f: impl Fn(usize, usize) -> f32) -> Arc<Dem> {
        let t = GeoTransform::new([x0, 10.0, 0.0, y0, 0.0, -10.0]).unwrap();
        let data = (0..h)
            .flat_map(|r| (0..w).map(move |c| (c, r)))
            .map(|(c, r)| f(c, r))
            .collect();
        let r = Raster::new(
            w,
            h,
            1,
            RasterData::F32(data),
            t,
            Crs::Utm {
                zone: 14,
                north: true,
            },
            None,
        )
        .unwrap();
        Arc::new(Dem::from_raster(&r).unwrap())
    }

    #[test]
    fn windows_of_one_grid_join_into_the_whole() {
        // The whole: 8 x 6 samples of a plane; two windows overlapping by two columns.
        let plane = |c: usize, r: usize| 100.0 + c as f32 * 2.0 + r as f32 * 3.0;
        let whole = grid(1000.0, 2000.0, 8, 6, plane);
        let west = grid(1000.0, 2000.0, 5, 6, plane);
        let east = grid(1030.0, 1990.0, 5, 5, |c, r| plane(c + 3, r + 1));
        let joined = join(&[east, west]).unwrap();
        for (x, y) in [
            (1005.0, 1995.0),
            (1042.0, 1981.0),
            (1074.0, 1946.0),
            (1031.0, 1960.0),
        ] {
            assert_eq!(joined.height_at(x, y), whole.height_at(x, y), "({x}, {y})");
        }
        assert_eq!(joined.height_range_m(), whole.height_range_m());
    }

    #[test]
    fn grids_off_the_first_or_too_far_are_left_out() {
        let a = grid(1000.0, 2000.0, 3, 3, |_, _| 5.0);
        let off_grid = grid(1005.0, 2000.0, 3, 3, |_, _| 7.0);
        let far = grid(1.0e9, 2000.0, 3, 3, |_, _| 9.0);
        let hostile = grid(1.0e20, -1.0e20, 3, 3, |_, _| 9.0);
        let joined = join(&[a.clone(), off_grid, far, hostile]).unwrap();
        assert_eq!(joined, *a, "only the first is left");
        assert!(join(&[]).is_none());
    }

    #[test]
    fn no_terrain_has_its_range_and_no_height() {
        let b = Bounds {
            min_x_m: 0.0,
            min_y_m: 0.0,
            max_x_m: 10.0,
            max_y_m: 10.0,
        };
        let d = none(
            &b,
            Crs::Utm {
                zone: 14,
                north: true,
            },
            300.0,
            900.0,
        )
        .unwrap();
        assert_eq!(d.height_range_m(), (300.0, 900.0));
        assert_eq!(d.height_at(0.5, 9.5), None);
        assert_eq!(d.height_at(1.0, 9.0), None);
        assert!(
            d.intersect_ray([0.5, 9.5, 2000.0], [0.0, 0.0, -1.0], 1e4)
                .is_none()
        );
    }
}
