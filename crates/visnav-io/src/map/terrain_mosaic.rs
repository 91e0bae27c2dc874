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
/// 8 km square). Beyond it the caller joins fewer tiles.
pub const MAX_MOSAIC_CELLS: usize = 64 << 20;

/// The grids of `tiles` (gridded terrains of one DEM) as one terrain; `None` when there is none,
/// they are not north-up on one grid, or their union exceeds [`MAX_MOSAIC_CELLS`].
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
    // Each grid's offset from the first, whole samples (a rotated grid is not joined).
    let mut offsets = Vec::with_capacity(grids.len());
    for g in &grids {
        let k = g.transform().coeffs();
        if k[2] != 0.0 || k[4] != 0.0 || k[1] != px || k[5] != py || g.crs() != first.crs() {
            return None;
        }
        let (dc, dr) = ((k[0] - c[0]) / px, (k[3] - c[3]) / py);
        let (ic, ir) = (dc.round(), dr.round());
        if !(ic.is_finite() && ir.is_finite()) || (dc - ic).abs() > 1e-6 || (dr - ir).abs() > 1e-6 {
            return None;
        }
        offsets.push((ic as i64, ir as i64)); // ok: finite and checked whole
    }
    let c0 = offsets.iter().map(|o| o.0).min()?;
    let r0 = offsets.iter().map(|o| o.1).min()?;
    let c1 = grids
        .iter()
        .zip(&offsets)
        .map(|(g, o)| o.0 + g.width() as i64)
        .max()?;
    let r1 = grids
        .iter()
        .zip(&offsets)
        .map(|(g, o)| o.1 + g.height() as i64)
        .max()?;
    let (w, h) = ((c1 - c0) as usize, (r1 - r0) as usize);
    if w.checked_mul(h).is_none_or(|n| n > MAX_MOSAIC_CELLS) {
        return None;
    }
    let mut heights = vec![f32::NAN; w * h];
    for (g, (oc, or)) in grids.iter().zip(&offsets) {
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
    fn grids_off_each_other_or_too_large_are_not_joined() {
        let a = grid(1000.0, 2000.0, 3, 3, |_, _| 5.0);
        let b = grid(1005.0, 2000.0, 3, 3, |_, _| 5.0);
        assert!(join(&[a.clone(), b]).is_none());
        let far = grid(1.0e9, 2000.0, 3, 3, |_, _| 5.0);
        assert!(
            join(&[a, far]).is_none(),
            "a union of 1e8 x 3 samples is over the bound"
        );
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
