//! Brute-force descriptor matching: 2-nearest-neighbour search in the descriptor family's distance
//! (L2 for SURF's float vectors, Hamming for binary strings: [`row_distance2`]), Lowe's ratio test
//! (Lowe 2004, sec. 7.1), the Laplacian-sign gate of SURF (Bay et al. 2008, sec. 4.3: only
//! keypoints with the same sign of the trace are compared), an optional mutual (cross) check and an
//! optional spatial gate (only train keypoints within a radius of a predicted location).
//!
//! Layout: descriptors are stored row-major with a stride that is a multiple of 8 floats (see
//! `Features`), and the squared distance accumulates into 8 independent lanes, which the compiler
//! turns into SIMD adds and multiplies (a plain `sum()` would be serial because float addition is
//! not associative); on x86-64 with AVX (detected at run time) the 8 lanes sit in one register,
//! with the same bits. Queries run in parallel (rayon).

use rayon::prelude::*;

use super::surf::Family;
use super::{DescriptorKind, Features, VisionError};

/// Matching options.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct MatchParams {
    /// Accept when `d1 < ratio * d2` (distances, not squared); 1.0 disables the test. With the test
    /// on, a query with a single candidate is rejected.
    pub ratio: f32,
    /// Compare only keypoints with the same Laplacian sign.
    pub laplacian_gate: bool,
    /// Keep a match only when the query is also the train keypoint's nearest neighbour (among
    /// the candidates that pass the same gates).
    pub mutual: bool,
    /// When set, a train keypoint is a candidate only if it lies within this many pixels of the
    /// query's predicted location (passed to [`match_features`]).
    pub spatial_radius_px: Option<f32>,
}

impl Default for MatchParams {
    fn default() -> Self {
        Self {
            ratio: 0.8,
            laplacian_gate: true,
            mutual: false,
            spatial_radius_px: None,
        }
    }
}

/// A match from query keypoint `query` to train keypoint `train`.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Match {
    /// Index of the query keypoint.
    pub query: usize,
    /// Index of its nearest train keypoint.
    pub train: usize,
    /// Distance to the nearest train descriptor: Euclidean for float descriptors, bits that
    /// differ for binary ones.
    pub distance: f32,
    /// Distance to the second nearest, in the same measure (infinite when there was only one
    /// candidate).
    pub second_distance: f32,
}

/// Squared L2 distance of two equally long rows whose length is a multiple of 8.
#[inline(always)]
pub fn dist2(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0f32; 8];
    for (ca, cb) in a.chunks_exact(8).zip(b.chunks_exact(8)) {
        for k in 0..8 {
            let d = ca[k] - cb[k];
            acc[k] += d * d;
        }
    }
    ((acc[0] + acc[4]) + (acc[1] + acc[5])) + ((acc[2] + acc[6]) + (acc[3] + acc[7]))
}

/// Squared Hamming distance of two binary rows (32-bit words kept as float bits,
/// [`Features::binary_descriptor`]): squared so that the matcher's square roots give bits.
pub fn hamming2(a: &[f32], b: &[f32]) -> f32 {
    let bits: u32 = a
        .iter()
        .zip(b)
        .map(|(x, y)| (x.to_bits() ^ y.to_bits()).count_ones())
        .sum();
    (bits * bits) as f32
}

/// The squared distance of two descriptor rows of `kind`: Euclidean ([`dist2`]) for float
/// descriptors, Hamming ([`hamming2`]) for binary ones.
pub fn row_distance2(kind: DescriptorKind) -> fn(&[f32], &[f32]) -> f32 {
    match kind.family() {
        Family::Float => dist2,
        Family::Binary => hamming2,
    }
}

/// Nearest and second nearest `(index, d1^2, d2^2)` of row `qi` of `q` among rows of `t` that pass
/// `accept`.
///
/// On x86-64 with AVX the distance runs in one 256-bit register ([`dist2_avx`]; baseline x86-64
/// has SSE2 only, and the compiler left [`dist2`] in shuffled 128-bit halves): every lane sums
/// the same products in the same order, so the distances are bit for bit the baseline's (no FMA:
/// a fused multiply-add would round differently). Brute-force matching is about 40 % of a
/// relocalisation's time.
fn two_nn(
    q: &Features,
    qi: usize,
    t: &Features,
    accept: &impl Fn(usize) -> bool,
) -> Option<(usize, f32, f32)> {
    if q.kind().family() == Family::Binary {
        return two_nn_with(q, qi, t, accept, hamming2);
    }
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx") {
        // SAFETY: the CPU was just found to support AVX, the only feature `two_nn_avx` enables.
        return unsafe { two_nn_avx(q, qi, t, accept) };
    }
    two_nn_with(q, qi, t, accept, dist2)
}

/// [`two_nn_with`] with the distance in AVX registers.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
fn two_nn_avx(
    q: &Features,
    qi: usize,
    t: &Features,
    accept: &impl Fn(usize) -> bool,
) -> Option<(usize, f32, f32)> {
    two_nn_with(q, qi, t, accept, |a, b| dist2_avx(a, b))
}

/// [`dist2`] with the 8 lanes in one AVX register: the same products summed in the same order,
/// so the same bits.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
fn dist2_avx(a: &[f32], b: &[f32]) -> f32 {
    use std::arch::x86_64::*;
    let mut acc = _mm256_setzero_ps();
    for (ca, cb) in a.chunks_exact(8).zip(b.chunks_exact(8)) {
        // SAFETY: both chunks are exactly 8 f32 long (chunks_exact), what an unaligned
        // 256-bit load reads.
        let (va, vb) = unsafe { (_mm256_loadu_ps(ca.as_ptr()), _mm256_loadu_ps(cb.as_ptr())) };
        let d = _mm256_sub_ps(va, vb);
        acc = _mm256_add_ps(acc, _mm256_mul_ps(d, d));
    }
    // (acc0 + acc4, acc1 + acc5, acc2 + acc6, acc3 + acc7), then its pairs, then their sum:
    // dist2's order.
    let s = _mm_add_ps(_mm256_castps256_ps128(acc), _mm256_extractf128_ps(acc, 1));
    let pairs = _mm_hadd_ps(s, s);
    _mm_cvtss_f32(_mm_hadd_ps(pairs, pairs))
}

/// The search itself, with the squared distance `dist`.
#[inline(always)]
fn two_nn_with(
    q: &Features,
    qi: usize,
    t: &Features,
    accept: &impl Fn(usize) -> bool,
    dist: impl Fn(&[f32], &[f32]) -> f32,
) -> Option<(usize, f32, f32)> {
    let st = q.kind().stride();
    let qd = &q.descriptors_padded()[qi * st..(qi + 1) * st];
    let td = t.descriptors_padded();
    let (mut best, mut b1, mut b2) = (usize::MAX, f32::INFINITY, f32::INFINITY);
    for (ti, row) in td.chunks_exact(st).enumerate() {
        if !accept(ti) {
            continue;
        }
        let d = dist(qd, row);
        if d < b1 {
            b2 = b1;
            b1 = d;
            best = ti;
        } else if d < b2 {
            b2 = d;
        }
    }
    (best != usize::MAX).then_some((best, b1, b2))
}

/// Match every query feature against the train features.
///
/// `predicted_in_train`: with `params.spatial_radius_px`, the predicted train-image location of
/// each query keypoint (one per query; a non-finite prediction excludes that query). The mutual
/// check uses the same gates in reverse (a train keypoint's candidates are the queries whose
/// prediction lies within the radius of it). Returns matches ordered by query index.
pub fn match_features(
    query: &Features,
    train: &Features,
    params: &MatchParams,
    predicted_in_train: Option<&[[f32; 2]]>,
) -> Result<Vec<Match>, VisionError> {
    if query.kind() != train.kind() {
        return Err(VisionError::Matcher(format!(
            "descriptor kinds differ: query {}, train {}",
            query.kind(),
            train.kind()
        )));
    }
    if !(params.ratio.is_finite() && params.ratio > 0.0 && params.ratio <= 1.0) {
        return Err(VisionError::Matcher(format!(
            "ratio {} must be in (0, 1]",
            params.ratio
        )));
    }
    let gate = match params.spatial_radius_px {
        None => None,
        Some(r) => {
            if !(r.is_finite() && r > 0.0) {
                return Err(VisionError::Matcher(format!(
                    "spatial_radius_px {r} must be positive"
                )));
            }
            let pred = predicted_in_train.ok_or_else(|| {
                VisionError::Matcher("spatial gate set but no predicted locations given".into())
            })?;
            if pred.len() != query.len() {
                return Err(VisionError::Matcher(format!(
                    "{} predicted locations for {} query keypoints",
                    pred.len(),
                    query.len()
                )));
            }
            Some((pred, r * r))
        }
    };
    let compatible = |qi: usize, ti: usize| -> bool {
        let (qk, tk) = (&query.keypoints[qi], &train.keypoints[ti]);
        if params.laplacian_gate && qk.laplacian != tk.laplacian {
            return false;
        }
        if let Some((pred, r2)) = gate {
            let [px, py] = pred[qi];
            let (dx, dy) = (tk.x - px, tk.y - py);
            // NaN predictions fail this comparison and exclude the pair.
            let within = dx * dx + dy * dy <= r2;
            if !within {
                return false;
            }
        }
        true
    };
    let ratio2 = params.ratio * params.ratio;
    let forward: Vec<Option<Match>> = (0..query.len())
        .into_par_iter()
        .with_min_len(32)
        .map(|qi| {
            let (ti, d1, d2) = two_nn(query, qi, train, &|ti| compatible(qi, ti))?;
            // A lone candidate (d2 infinite) gives no evidence of distinctiveness: rejected.
            if params.ratio < 1.0 && !(d2.is_finite() && d1 < ratio2 * d2) {
                return None;
            }
            Some(Match {
                query: qi,
                train: ti,
                distance: d1.max(0.0).sqrt(),
                second_distance: d2.max(0.0).sqrt(),
            })
        })
        .collect();
    let mut out: Vec<Match> = forward.into_iter().flatten().collect();
    if params.mutual {
        out = out
            .into_par_iter()
            .with_min_len(32)
            .filter(|m| {
                two_nn(train, m.train, query, &|qi| compatible(qi, m.train))
                    .is_some_and(|(qi, _, _)| qi == m.query)
            })
            .collect();
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vision::{DescriptorKind, KeyPoint};

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn the_avx_distance_has_the_baselines_bits() {
        if !std::arch::is_x86_feature_detected!("avx") {
            eprintln!("SKIP: this CPU has no AVX");
            return;
        }
        let mut rng = crate::rng::Rng::new(5);
        for len in [8, 64, 128] {
            for _ in 0..2000 {
                let a: Vec<f32> = (0..len).map(|_| rng.normal() as f32 * 0.2).collect();
                let b: Vec<f32> = (0..len).map(|_| rng.normal() as f32 * 0.2).collect();
                // SAFETY: AVX was detected above.
                let avx = unsafe { dist2_avx(&a, &b) };
                assert_eq!(avx.to_bits(), dist2(&a, &b).to_bits(), "length {len}");
            }
        }
    }

    fn kp(x: f32, y: f32, lap: i8) -> KeyPoint {
        KeyPoint {
            x,
            y,
            size: 9.0,
            scale: 1.2,
            response: 1.0,
            orientation_rad: 0.0,
            laplacian: lap,
            octave: 0,
        }
    }

    fn features(rows: &[(KeyPoint, Vec<f32>)]) -> Features {
        let kind = DescriptorKind::Surf36;
        let mut d = Vec::new();
        for (_, v) in rows {
            let mut r = v.clone();
            r.resize(kind.stride(), 0.0);
            d.extend(r);
        }
        Features::new(rows.iter().map(|r| r.0).collect(), d, kind).unwrap()
    }

    fn unit(i: usize, eps: f32) -> Vec<f32> {
        let mut v = vec![0.0; 36];
        v[i] = 1.0;
        v[(i + 1) % 36] = eps;
        v
    }

    #[test]
    fn dist2_matches_naive() {
        let a: Vec<f32> = (0..64).map(|i| (i as f32 * 0.37).sin()).collect();
        let b: Vec<f32> = (0..64).map(|i| (i as f32 * 0.11).cos()).collect();
        let naive: f32 = a.iter().zip(&b).map(|(x, y)| (x - y) * (x - y)).sum();
        assert!((dist2(&a, &b) - naive).abs() < 1e-4);
    }

    #[test]
    fn ratio_laplacian_mutual_and_spatial_gates() {
        let q = features(&[
            (kp(10.0, 10.0, 1), unit(0, 0.0)),
            (kp(20.0, 20.0, 1), unit(5, 0.0)),
            (kp(30.0, 30.0, -1), unit(9, 0.0)),
        ]);
        let t = features(&[
            (kp(11.0, 10.0, 1), unit(0, 0.1)),  // good match of q0
            (kp(90.0, 90.0, 1), unit(5, 0.05)), // q1 ambiguous with t2
            (kp(21.0, 20.0, 1), unit(5, 0.06)),
            (kp(31.0, 30.0, 1), unit(9, 0.0)), // q2's twin but opposite Laplacian sign
            (kp(50.0, 50.0, -1), unit(20, 0.0)), // unrelated, same sign as q2
            (kp(22.0, 21.0, 1), unit(30, 0.0)), // unrelated, near q1's prediction
        ]);
        let m = match_features(&q, &t, &MatchParams::default(), None).unwrap();
        assert_eq!(m.len(), 1, "{m:?}");
        assert_eq!((m[0].query, m[0].train), (0, 0));

        // Without the Laplacian gate q2 matches t3.
        let p = MatchParams {
            laplacian_gate: false,
            ..Default::default()
        };
        let m = match_features(&q, &t, &p, None).unwrap();
        assert!(m.iter().any(|m| (m.query, m.train) == (2, 3)));

        // Spatial gate resolves the ambiguity of q1 (t1 is far from the prediction).
        let pred = [[10.0, 10.0], [20.0, 20.0], [30.0, 30.0]];
        let p = MatchParams {
            spatial_radius_px: Some(5.0),
            ..Default::default()
        };
        let m = match_features(&q, &t, &p, Some(&pred)).unwrap();
        assert!(m.iter().any(|m| (m.query, m.train) == (1, 2)), "{m:?}");
        assert!(m.iter().all(|m| m.train != 1));

        // Mutual: two queries wanting the same train keypoint, only the closer survives.
        let q2 = features(&[
            (kp(0.0, 0.0, 1), unit(0, 0.0)),
            (kp(1.0, 0.0, 1), unit(0, 0.3)),
        ]);
        let t2 = features(&[
            (kp(0.0, 0.0, 1), unit(0, 0.0)),
            (kp(5.0, 5.0, 1), unit(30, 0.0)),
        ]);
        let p = MatchParams {
            ratio: 1.0,
            mutual: true,
            ..Default::default()
        };
        let m = match_features(&q2, &t2, &p, None).unwrap();
        assert_eq!(m.len(), 1);
        assert_eq!((m[0].query, m[0].train), (0, 0));
        let p = MatchParams {
            ratio: 1.0,
            ..Default::default()
        };
        assert_eq!(match_features(&q2, &t2, &p, None).unwrap().len(), 2);
    }

    #[test]
    fn bad_inputs_are_errors() {
        let q = features(&[(kp(0.0, 0.0, 1), unit(0, 0.0))]);
        let p = MatchParams {
            spatial_radius_px: Some(3.0),
            ..Default::default()
        };
        assert!(match_features(&q, &q, &p, None).is_err());
        assert!(match_features(&q, &q, &p, Some(&[])).is_err());
        let p = MatchParams {
            ratio: 0.0,
            ..Default::default()
        };
        assert!(match_features(&q, &q, &p, None).is_err());
        // NaN prediction excludes the query instead of panicking.
        let p = MatchParams {
            spatial_radius_px: Some(3.0),
            ..Default::default()
        };
        assert!(
            match_features(&q, &q, &p, Some(&[[f32::NAN, 0.0]]))
                .unwrap()
                .is_empty()
        );
    }
}
