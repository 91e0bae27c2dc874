//! Timing of the whole resection ([`visnav_core::pose::resect`]) on synthetic aerial scenes, for `visnav bench`.
//!
//! Only the solver is timed (scene generation is excluded), single-threaded, with the default
//! configuration. Reports median / 95th percentile / maximum wall time per call and how many fixes
//! were accepted and were within 3 sigma of the truth.

use std::fmt;
use std::time::Instant;

use visnav_core::pose::synth::{SceneConfig, make_scene};
use visnav_core::pose::{Priors, ResectionConfig, resect};
use visnav_core::rng::Rng;

/// Timing of one benchmark case.
#[derive(Debug, Clone, PartialEq)]
pub struct BenchResult {
    /// 2-D/3-D correspondences per scene.
    pub correspondences: usize,
    /// Fraction of them that are wrong.
    pub outlier_ratio: f64,
    /// Resections timed.
    pub trials: usize,
    /// Median wall time per resection, ms.
    pub median_ms: f64,
    /// 95th percentile of the wall time, ms.
    pub p95_ms: f64,
    /// Largest wall time, ms.
    pub max_ms: f64,
    /// Fixes accepted by the integrity checks.
    pub accepted: usize,
    /// Accepted fixes whose position error exceeds 3 sigma on any axis (should be 0).
    pub accepted_beyond_3_sigma: usize,
    /// Mean RANSAC iterations per trial (trials without a fix count as 0).
    pub mean_ransac_iterations: f64,
}

impl fmt::Display for BenchResult {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "resection n={:5} outliers={:3.0}%  median {:7.3} ms  p95 {:7.3} ms  max {:7.3} ms  accepted {}/{}  >3sigma {}  ransac it {:.0}",
            self.correspondences,
            self.outlier_ratio * 100.0,
            self.median_ms,
            self.p95_ms,
            self.max_ms,
            self.accepted,
            self.trials,
            self.accepted_beyond_3_sigma,
            self.mean_ransac_iterations
        )
    }
}

/// Time `trials` resections of random nadir/oblique scenes (1000-2500 m above ground, 640x480,
/// 60 deg FOV, 1 px noise) with `n` correspondences of which `outlier_ratio` are wrong.
pub fn bench_resection(n: usize, outlier_ratio: f64, trials: usize, seed: u64) -> BenchResult {
    let mut rng = Rng::new(seed);
    let mut cfg = ResectionConfig::default();
    let mut times = Vec::with_capacity(trials);
    let (mut accepted, mut bad, mut iters) = (0, 0, 0.0);
    for t in 0..trials {
        let scene_cfg = SceneConfig {
            height_agl_m: rng.range(1000.0, 2500.0),
            tilt_rad: if t % 2 == 0 { 0.0 } else { rng.range(0.2, 0.6) },
            yaw_rad: rng.range(-3.1, 3.1),
            n,
            outlier_ratio,
            ..SceneConfig::default()
        };
        let scene = make_scene(&scene_cfg, &mut rng);
        cfg.ransac.seed = seed.wrapping_add(t as u64);
        let start = Instant::now();
        let out = resect(&scene.corrs, &scene.image, &Priors::default(), &cfg);
        times.push(start.elapsed().as_secs_f64() * 1e3);
        if let Some(fix) = &out.fix {
            iters += fix.quality.ransac_iterations as f64;
        }
        if let Some(fix) = out.accepted() {
            accepted += 1;
            let cov = fix.covariance.position_world_m2();
            let err = fix.pose.c_world - scene.truth.c_world;
            if (0..3).any(|k| err[k].abs() > 3.0 * cov[(k, k)].sqrt()) {
                bad += 1;
            }
        }
    }
    times.sort_by(f64::total_cmp);
    let pick = |q: f64| {
        times
            .get(((times.len() as f64 - 1.0) * q).round() as usize)
            .copied()
            .unwrap_or(f64::NAN)
    };
    BenchResult {
        correspondences: n,
        outlier_ratio,
        trials,
        median_ms: pick(0.5),
        p95_ms: pick(0.95),
        max_ms: times.last().copied().unwrap_or(f64::NAN),
        accepted,
        accepted_beyond_3_sigma: bad,
        mean_ransac_iterations: iters / trials.max(1) as f64,
    }
}

/// The standard suite: 100, 300 and 1000 correspondences at 50 % outliers, plus 300 at 90 %.
pub fn bench_suite(trials: usize) -> Vec<BenchResult> {
    [(100, 0.5), (300, 0.5), (1000, 0.5), (300, 0.9)]
        .iter()
        .map(|&(n, r)| bench_resection(n, r, trials, 1234))
        .collect()
}

/// Mean wall time of one Lambda Twist P3P call in microseconds, over `calls` random aerial triples.
pub fn bench_p3p(calls: usize, seed: u64) -> f64 {
    use nalgebra::Vector3;
    let mut rng = Rng::new(seed);
    let scene = make_scene(
        &SceneConfig {
            n: 300,
            outlier_ratio: 0.0,
            ..SceneConfig::default()
        },
        &mut rng,
    );
    let m = scene.corrs.len();
    if m < 3 || calls == 0 {
        return f64::NAN;
    }
    type Triple = [Vector3<f64>; 3];
    let samples: Vec<(Triple, Triple)> = (0..calls)
        .map(|_| {
            let idx = [rng.below(m), rng.below(m), rng.below(m)];
            let y = idx
                .map(|i| Vector3::new(scene.corrs[i].obs_norm.x, scene.corrs[i].obs_norm.y, 1.0));
            let x = idx.map(|i| scene.corrs[i].point_world - scene.truth.c_world);
            (y, x)
        })
        .collect();
    let start = Instant::now();
    let mut found = 0usize;
    for (y, x) in &samples {
        found += visnav_core::pose::p3p::p3p_lambda_twist(y, x).len();
    }
    let us = start.elapsed().as_secs_f64() * 1e6 / calls as f64;
    // Keep the work observable so that it is not optimised away.
    if found == usize::MAX { f64::NAN } else { us }
}
