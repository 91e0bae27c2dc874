//! A 2-D similarity (`p -> s R(theta) p + t`) and its robust fit: RANSAC over pairs of point
//! correspondences with bounds on the rotation and the scale, refitted to the consensus by least
//! squares (Umeyama's closed form in 2-D). The fix engine fits it between the positions its prior
//! predicts and the map's (the prior's position error a shift, its heading error a rotation,
//! its height error a scale).

/// A 2-D similarity `p -> s R(theta) p + t`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sim2 {
    /// Scale factor `s` (1 = same size).
    pub scale: f32,
    /// Rotation angle, radians, from +x towards +y.
    pub theta_rad: f32,
    /// Translation, added after scaling and rotating, in the target's units.
    pub t: [f32; 2],
}

impl Sim2 {
    /// The identity.
    pub fn identity() -> Self {
        Self {
            scale: 1.0,
            theta_rad: 0.0,
            t: [0.0, 0.0],
        }
    }
    /// Apply to a point.
    pub fn apply(&self, p: [f32; 2]) -> [f32; 2] {
        let (s, c) = self.theta_rad.sin_cos();
        [
            self.scale * (c * p[0] - s * p[1]) + self.t[0],
            self.scale * (s * p[0] + c * p[1]) + self.t[1],
        ]
    }
    /// Least-squares similarity from point pairs (Umeyama 1991, 2-D closed form); None when
    /// degenerate.
    pub fn fit(src: &[[f32; 2]], dst: &[[f32; 2]]) -> Option<Self> {
        let n = src.len().min(dst.len());
        if n < 2 {
            return None;
        }
        let nf = n as f64;
        let (mut ms, mut md) = ([0f64; 2], [0f64; 2]);
        for i in 0..n {
            for k in 0..2 {
                ms[k] += f64::from(src[i][k]) / nf;
                md[k] += f64::from(dst[i][k]) / nf;
            }
        }
        let (mut a, mut b, mut var) = (0f64, 0f64, 0f64);
        for i in 0..n {
            let (sx, sy) = (f64::from(src[i][0]) - ms[0], f64::from(src[i][1]) - ms[1]);
            let (dx, dy) = (f64::from(dst[i][0]) - md[0], f64::from(dst[i][1]) - md[1]);
            a += sx * dx + sy * dy;
            b += sx * dy - sy * dx;
            var += sx * sx + sy * sy;
        }
        if var.is_nan() || var <= 1e-9 {
            return None;
        }
        let theta = b.atan2(a);
        let scale = (a * a + b * b).sqrt() / var;
        let (s, c) = theta.sin_cos();
        let t = [
            md[0] - scale * (c * ms[0] - s * ms[1]),
            md[1] - scale * (s * ms[0] + c * ms[1]),
        ];
        let out = Self {
            scale: scale as f32,
            theta_rad: theta as f32,
            t: [t[0] as f32, t[1] as f32],
        };
        (out.scale.is_finite() && out.t.iter().all(|v| v.is_finite())).then_some(out)
    }
}

/// RANSAC over 2-point similarities between `src` and `dst` (pairs), with rotation and log-scale
/// limits (a similarity outside them is not a plausible prior error); the best model is refitted
/// to its inliers (distance <= `thresh`). Returns it with its inlier count (at least 3).
pub fn ransac_similarity(
    src: &[[f32; 2]],
    dst: &[[f32; 2]],
    thresh: f32,
    max_rot_rad: f64,
    max_abs_log_scale: f64,
    seed: u64,
) -> Option<(Sim2, usize)> {
    let n = src.len().min(dst.len());
    if n < 3 {
        return None;
    }
    let plausible = |s: &Sim2| {
        f64::from(s.theta_rad).abs() <= max_rot_rad
            && f64::from(s.scale).ln().abs() <= max_abs_log_scale
    };
    let count = |s: &Sim2| -> Vec<usize> {
        (0..n)
            .filter(|&i| {
                let p = s.apply(src[i]);
                let (dx, dy) = (p[0] - dst[i][0], p[1] - dst[i][1]);
                dx * dx + dy * dy <= thresh * thresh
            })
            .collect()
    };
    let mut state = seed | 1;
    let mut next = |m: usize| {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state % m as u64) as usize
    };
    let mut best: Vec<usize> = Vec::new();
    let iters = 2000.min(n * n);
    for _ in 0..iters {
        let (i, j) = (next(n), next(n));
        if i == j {
            continue;
        }
        let Some(s) = Sim2::fit(&[src[i], src[j]], &[dst[i], dst[j]]) else {
            continue;
        };
        if !plausible(&s) {
            continue;
        }
        let inl = count(&s);
        if inl.len() > best.len() {
            best = inl;
        }
    }
    if best.len() < 3 {
        return None;
    }
    // Refit on the inliers twice (inliers re-selected with the refined model).
    let mut model = None;
    for _ in 0..2 {
        let s: Vec<[f32; 2]> = best.iter().map(|&i| src[i]).collect();
        let d: Vec<[f32; 2]> = best.iter().map(|&i| dst[i]).collect();
        let Some(m) = Sim2::fit(&s, &d).filter(|m| plausible(m)) else {
            break;
        };
        let inl = count(&m);
        if inl.len() < 3 {
            break;
        }
        best = inl;
        model = Some(m);
    }
    model.map(|m| (m, best.len()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ransac_similarity_finds_the_prior_error_among_outliers() {
        let truth = Sim2 {
            scale: 1.05,
            theta_rad: 0.03,
            t: [37.0, -12.0],
        };
        let mut s = 12345u64;
        let mut rnd = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 33) as f32 / (1u64 << 31) as f32) - 0.5
        };
        let (mut src, mut dst) = (Vec::new(), Vec::new());
        for _ in 0..20 {
            let p = [300.0 * rnd() + 150.0, 300.0 * rnd() + 150.0];
            let q = truth.apply(p);
            src.push(p);
            dst.push([q[0] + 0.5 * rnd(), q[1] + 0.5 * rnd()]);
        }
        for _ in 0..150 {
            src.push([300.0 * rnd() + 150.0, 300.0 * rnd() + 150.0]);
            dst.push([400.0 * rnd() + 150.0, 400.0 * rnd() + 150.0]);
        }
        let (m, n) = ransac_similarity(&src, &dst, 3.0, 0.2, 0.2, 1).unwrap();
        assert!(n >= 20, "{n}");
        let p = m.apply([100.0, 200.0]);
        let q = truth.apply([100.0, 200.0]);
        assert!(
            (p[0] - q[0]).abs() < 1.0 && (p[1] - q[1]).abs() < 1.0,
            "{m:?}"
        );
        // Outside the rotation limit the true model is not accepted.
        let far = ransac_similarity(&src, &dst, 3.0, 0.001, 0.2, 1);
        assert!(far.is_none_or(|(_, n)| n < 20));
        assert!(ransac_similarity(&src[..2], &dst[..2], 3.0, 0.2, 0.2, 1).is_none());
    }
}
