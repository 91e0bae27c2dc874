//! Matching with predicted positions: the spatially gated matcher (each query keypoint's nearest
//! train descriptor among those near where a prior puts it, with Lowe's ratio test against the
//! gate's second best) and the Hough clustering of matches by scale and shift (Lowe 2004, 7.3),
//! the vote relocalisation runs without a position prior.

use super::Features;

/// A match accepted by [`gated_match`]: query index, train index.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GatedMatch {
    /// Index of the query keypoint.
    pub query: usize,
    /// Index of the matched train keypoint.
    pub train: usize,
}

/// Spatially gated matching: for each query with a finite prediction, the nearest train descriptor
/// (same Laplacian sign) among the train keypoints within `r_wide` of the prediction is accepted when
/// it lies within `r_fine` of the prediction and passes Lowe's ratio test against the second nearest
/// in `r_wide` (a lone candidate passes). Brute force over a grid of `r_wide` cells.
pub fn gated_match(
    query: &Features,
    train: &Features,
    pred: &[[f32; 2]],
    r_fine: f32,
    r_wide: f32,
    ratio: f32,
) -> Vec<GatedMatch> {
    use std::collections::HashMap;
    let cell = r_wide.max(1.0);
    let key = |x: f32, y: f32| ((x / cell).floor() as i32, (y / cell).floor() as i32);
    let mut grid: HashMap<(i32, i32), Vec<usize>> = HashMap::new();
    for (j, k) in train.keypoints.iter().enumerate() {
        if k.x.is_finite() && k.y.is_finite() {
            grid.entry(key(k.x, k.y)).or_default().push(j);
        }
    }
    let st = query.kind().stride();
    let dist = super::matcher::row_distance2(query.kind());
    let qd = query.descriptors_padded();
    let td = train.descriptors_padded();
    let mut out = Vec::new();
    for (i, q) in query.keypoints.iter().enumerate() {
        let Some(p) = pred.get(i) else {
            break;
        };
        if !(p[0].is_finite() && p[1].is_finite()) {
            continue;
        }
        let (cx, cy) = key(p[0], p[1]);
        let (mut d1, mut d2, mut b1) = (f32::INFINITY, f32::INFINITY, usize::MAX);
        for dx in -1..=1 {
            for dy in -1..=1 {
                let Some(c) = grid.get(&(cx + dx, cy + dy)) else {
                    continue;
                };
                for &j in c {
                    let t = &train.keypoints[j];
                    if t.laplacian != q.laplacian {
                        continue;
                    }
                    let (ex, ey) = (t.x - p[0], t.y - p[1]);
                    if ex * ex + ey * ey > r_wide * r_wide {
                        continue;
                    }
                    let d = dist(&qd[i * st..(i + 1) * st], &td[j * st..(j + 1) * st]);
                    if d < d1 {
                        d2 = d1;
                        d1 = d;
                        b1 = j;
                    } else if d < d2 {
                        d2 = d;
                    }
                }
            }
        }
        if b1 == usize::MAX {
            continue;
        }
        let t = &train.keypoints[b1];
        let (ex, ey) = (t.x - p[0], t.y - p[1]);
        if ex * ex + ey * ey > r_fine * r_fine {
            continue;
        }
        if d2.is_finite() && d1.sqrt() >= ratio * d2.sqrt() {
            continue;
        }
        out.push(GatedMatch {
            query: i,
            train: b1,
        });
    }
    out
}

/// The largest Hough cluster of `m` (indices into it, sorted, distinct): each match votes for
/// the scale s = train.scale / query.scale (log2 bins of 0.5) and the translation of the virtual
/// principal point in level pixels (bins of 8 % of the image size at that scale), each vote
/// spread over the neighbouring bins. Ties go to the smallest key (HashMap order must not
/// decide). None without a vote.
pub fn hough_cluster(
    m: &[crate::vision::Match],
    query: &Features,
    train: &Features,
    size_px: f32,
    centre_px: [f32; 2],
) -> Option<Vec<usize>> {
    let mut votes: std::collections::HashMap<(i32, i32, i32), Vec<usize>> =
        std::collections::HashMap::new();
    let size = size_px;
    for (j, mm) in m.iter().enumerate() {
        let q = &query.keypoints[mm.query];
        let t = &train.keypoints[mm.train];
        let s = t.scale / q.scale;
        if !(s.is_finite() && s > 0.0) {
            continue;
        }
        let ls = s.log2() * 2.0;
        let tx = t.x - s * (q.x - centre_px[0]);
        let ty = t.y - s * (q.y - centre_px[1]);
        let bin = 0.08 * size * s;
        for ds in [0.0f32, 0.5] {
            let key = (
                (ls + ds).floor() as i32,
                (tx / bin).floor() as i32,
                (ty / bin).floor() as i32,
            );
            votes.entry(key).or_default().push(j);
            for (dx, dy) in [(1, 0), (0, 1), (1, 1)] {
                let key2 = (key.0, key.1 + dx, key.2 + dy);
                votes.entry(key2).or_default().push(j);
            }
        }
    }
    let (_, mut cluster) = votes
        .into_iter()
        .max_by(|(ka, va), (kb, vb)| va.len().cmp(&vb.len()).then(kb.cmp(ka)))?;
    cluster.sort_unstable();
    cluster.dedup();
    Some(cluster)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vision::KeyPoint;

    /// Key points at `pts` with scale `scale` (descriptors irrelevant here).
    fn keypoints_at(pts: &[[f32; 2]], scale: f32) -> Features {
        let kind = crate::vision::DescriptorKind::Surf64;
        let kps = pts
            .iter()
            .map(|p| KeyPoint {
                x: p[0],
                y: p[1],
                size: 9.0,
                scale,
                response: 1.0,
                orientation_rad: 0.0,
                laplacian: 1,
                octave: 0,
            })
            .collect();
        Features::new(kps, vec![0.0; pts.len() * kind.stride()], kind).unwrap()
    }

    fn features(points: &[([f32; 2], i8, [f32; 8])]) -> Features {
        let kind = crate::vision::DescriptorKind::Surf64;
        let st = kind.stride();
        let mut desc = Vec::new();
        let kps = points
            .iter()
            .map(|(p, lap, d)| {
                let mut row = vec![0f32; st];
                row[..8].copy_from_slice(d);
                desc.extend(row);
                KeyPoint {
                    x: p[0],
                    y: p[1],
                    size: 9.0,
                    scale: 1.2,
                    response: 1.0,
                    orientation_rad: 0.0,
                    laplacian: *lap,
                    octave: 0,
                }
            })
            .collect();
        Features::new(kps, desc, kind).unwrap()
    }

    #[test]
    fn the_hough_cluster_collects_the_matches_of_one_scale_and_shift() {
        // 12 matches agree on scale 2 and the virtual principal point at (400, 300); 6 others
        // scatter.
        let centre = [320.0f32, 240.0];
        let mut q = Vec::new();
        let mut t = Vec::new();
        for i in 0..12 {
            let p = [40.0 + 45.0 * i as f32, 30.0 + 33.0 * ((i * 7) % 12) as f32];
            q.push(p);
            t.push([
                400.0 + 2.0 * (p[0] - centre[0]),
                300.0 + 2.0 * (p[1] - centre[1]),
            ]);
        }
        for i in 0..6 {
            q.push([100.0 + 80.0 * i as f32, 200.0]);
            t.push([1500.0 - 230.0 * i as f32, 90.0 + 170.0 * i as f32]);
        }
        let query = keypoints_at(&q, 1.5);
        let train = keypoints_at(&t, 3.0);
        let m: Vec<crate::vision::Match> = (0..q.len())
            .map(|i| crate::vision::Match {
                query: i,
                train: i,
                distance: 0.1,
                second_distance: 0.5,
            })
            .collect();
        let c = hough_cluster(&m, &query, &train, 640.0, centre).unwrap();
        assert!((0..12).all(|i| c.contains(&i)), "{c:?}");
        assert!(c.iter().filter(|&&i| i >= 12).count() <= 1, "{c:?}");
        assert!(c.windows(2).all(|w| w[0] < w[1]), "sorted, distinct");
        assert!(hough_cluster(&[], &query, &train, 640.0, centre).is_none());
    }

    #[test]
    fn gated_match_rules() {
        let a = [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        let b = [0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        let a2 = [0.95, 0.05, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        let query = features(&[([0.0, 0.0], 1, a)]);
        // A lone candidate within the fine radius passes.
        let train = features(&[([102.0, 100.0], 1, a)]);
        let m = gated_match(&query, &train, &[[100.0, 100.0]], 4.0, 12.0, 0.9);
        assert_eq!(m, vec![GatedMatch { query: 0, train: 0 }]);
        // Outside the fine radius (but inside the wide one): no match.
        let m = gated_match(&query, &train, &[[95.0, 100.0]], 4.0, 12.0, 0.9);
        assert!(m.is_empty());
        // Other Laplacian sign: no candidate.
        let train_l = features(&[([100.0, 100.0], -1, a)]);
        assert!(gated_match(&query, &train_l, &[[100.0, 100.0]], 4.0, 12.0, 0.9).is_empty());
        // An ambiguous look-alike 8 px away fails the ratio test; a distinct one does not.
        let a3 = [0.95, -0.05, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        let amb = features(&[([100.0, 100.0], 1, a2), ([108.0, 100.0], 1, a3)]);
        assert!(gated_match(&query, &amb, &[[100.0, 100.0]], 4.0, 12.0, 0.9).is_empty());
        let dis = features(&[([100.0, 100.0], 1, a), ([108.0, 100.0], 1, b)]);
        assert_eq!(
            gated_match(&query, &dis, &[[100.0, 100.0]], 4.0, 12.0, 0.9).len(),
            1
        );
        // Non-finite predictions are skipped.
        assert!(gated_match(&query, &train, &[[f32::NAN, 0.0]], 4.0, 12.0, 0.9).is_empty());
    }
}
