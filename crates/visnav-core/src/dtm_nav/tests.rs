//! The DTM navigator on synthetic relief: exact flow from known poses (plus noise and outliers),
//! a first guess drifted as an INS drifts, the solution against the truth and its own covariance.

use super::*;
use crate::geo::Crs;
use crate::geo::raster::{GeoTransform, Raster, RasterData};
use crate::rng::Rng;

const CELL_M: f64 = 24.0;
const SIZE: usize = 500;
const X0_M: f64 = 400_000.0;
const Y0_M: f64 = 6_000_000.0;

/// Hills and valleys of about 600 m relief on a 24 m grid (12 km square), heights 150-750 m:
/// the NGI valley's scale.
fn relief(x: f64, y: f64) -> f64 {
    450.0
        + 180.0 * (x / 900.0).sin() * (y / 1300.0).cos()
        + 90.0 * ((x - y) / 420.0).sin()
        + 40.0 * (x / 260.0).cos() * (y / 310.0).sin()
}

fn grid_dem(h: impl Fn(f64, f64) -> f64) -> Dem {
    let mut v = Vec::with_capacity(SIZE * SIZE);
    for r in 0..SIZE {
        for c in 0..SIZE {
            let (x, y) = (
                X0_M + (c as f64 + 0.5) * CELL_M,
                Y0_M - (r as f64 + 0.5) * CELL_M,
            );
            v.push(h(x - X0_M, Y0_M - y) as f32);
        }
    }
    let gt = GeoTransform::north_up(X0_M, Y0_M, CELL_M, CELL_M).unwrap();
    let utm = Crs::Utm {
        zone: 33,
        north: false,
    };
    let r = Raster::new(SIZE, SIZE, 1, RasterData::F32(v), gt, utm, None).unwrap();
    Dem::from_raster(&r).unwrap()
}

fn vga() -> ImageGeometry {
    ImageGeometry {
        fx_px: 554.256,
        fy_px: 554.256,
        cx_px: 319.5,
        cy_px: 239.5,
        width_px: 640,
        height_px: 480,
    }
}

/// The middle of the DEM at 1000 m above sea level, looking down 3 deg forward of nadir, and
/// the second frame `baseline_m` along the heading, turned 0.5 deg.
fn truth(baseline_m: f64) -> PosePair {
    let c = Vector3::new(X0_M + 6000.0, Y0_M - 6000.0, 1000.0);
    let yaw = 0.4_f64;
    let first = Pose::nadir(c, yaw, 3f64.to_radians());
    // Pose::nadir's image top points along yaw + 90 deg (north at yaw 0).
    let fwd = Vector3::new(-yaw.sin(), yaw.cos(), 0.0);
    let second = Pose::nadir(
        c + fwd * baseline_m + Vector3::new(0.0, 0.0, 2.0),
        yaw + 0.5f64.to_radians(),
        3.3f64.to_radians(),
    );
    PosePair { first, second }
}

/// Flow on a 20 x 15 grid of the first frame: each pixel's ground point (true first pose)
/// projected into the second, with `noise_px` of Gaussian noise on both ends; the ones that
/// land inside the second frame.
fn flow(poses: &PosePair, dem: &Dem, noise_px: f64, seed: u64) -> Vec<TrackPair> {
    let im = vga();
    let mut rng = Rng::new(seed);
    let mut out = Vec::new();
    for gy in 0..15 {
        for gx in 0..20 {
            let p1 = Vector2::new(16.0 + gx as f64 * 32.0, 16.0 + gy as f64 * 32.0);
            let ray = Vector3::new(
                (p1.x - im.cx_px) / im.fx_px,
                (p1.y - im.cy_px) / im.fy_px,
                1.0,
            );
            let d = poses.first.r_world_cam * ray;
            let c = poses.first.c_world;
            let Some(x) = dem.intersect_ray([c.x, c.y, c.z], [d.x, d.y, d.z], 1e5) else {
                continue;
            };
            let Some(n) = poses.second.project(&Vector3::new(x[0], x[1], x[2])) else {
                continue;
            };
            let p2 = Vector2::new(im.fx_px * n.x + im.cx_px, im.fy_px * n.y + im.cy_px);
            if !(0.0..640.0).contains(&p2.x) || !(0.0..480.0).contains(&p2.y) {
                continue;
            }
            let jitter = |rng: &mut Rng| Vector2::new(rng.normal(), rng.normal()) * noise_px;
            out.push(TrackPair {
                prev_px: p1 + jitter(&mut rng),
                next_px: p2 + jitter(&mut rng),
            });
        }
    }
    out
}

/// An INS-like first guess: both poses shifted by the same position error and turned by the
/// same attitude error (a filter's error is common to frames 0.4-2 s apart), plus a small
/// error of the motion.
fn drifted(t: &PosePair) -> PosePair {
    let dp = Vector3::new(60.0, -40.0, 15.0);
    let turn = Rotation3::from_euler_angles(0.5f64.to_radians(), -0.4f64.to_radians(), 0.0)
        * Rotation3::from_axis_angle(&Vector3::z_axis(), 3f64.to_radians());
    let off = |p: &Pose, extra: Vector3<f64>| Pose {
        r_world_cam: turn * p.r_world_cam,
        c_world: p.c_world + dp + extra,
    };
    PosePair {
        first: off(&t.first, Vector3::zeros()),
        second: off(&t.second, Vector3::new(1.5, -1.0, 0.5)),
    }
}

fn input<'a>(tracks: &'a [TrackPair], im: &'a ImageGeometry, guess: &PosePair) -> DtmInput<'a> {
    DtmInput {
        tracks,
        image: im,
        guess_first: guess.first,
        guess_second: guess.second,
        guess_sigma: None,
    }
}

/// The solution's error as the parameter vector `[phi1, C1, phi2, C2]` (truth to estimate).
fn error12(fix: &DtmFix, t: &PosePair) -> Vec12 {
    let rot = |est: &Pose, tru: &Pose| {
        crate::pose::refine::log_so3(&(est.r_world_cam * tru.r_world_cam.inverse()))
    };
    let mut e = Vec12::zeros();
    e.fixed_rows_mut::<3>(PHI1)
        .copy_from(&rot(&fix.first, &t.first));
    e.fixed_rows_mut::<3>(C1)
        .copy_from(&(fix.first.c_world - t.first.c_world));
    e.fixed_rows_mut::<3>(PHI2)
        .copy_from(&rot(&fix.second, &t.second));
    e.fixed_rows_mut::<3>(C2)
        .copy_from(&(fix.second.c_world - t.second.c_world));
    e
}

fn mahalanobis2(e: &Vec12, cov: &Mat12) -> f64 {
    (e.transpose() * cov.try_inverse().unwrap() * e)[(0, 0)]
}

/// Chi-square 99.9 % point for 12 degrees of freedom.
const CHI2_12_999: f64 = 32.91;

#[test]
fn the_analytic_jacobian_matches_central_differences() {
    let dem = grid_dem(relief);
    let t = truth(60.0);
    let im = vga();
    let tracks = flow(&t, &dem, 0.0, 1);
    let obs = observations(&input(&tracks, &im, &t));
    let mut checked = 0;
    for o in obs.iter().step_by(7) {
        let Some(e) = eval_track(&t, o, &im, &dem, 1e5) else {
            continue;
        };
        for k in 0..12 {
            let h = if k % 6 < 3 { 1e-6 } else { 1e-3 };
            let mut d = Vec12::zeros();
            d[k] = h;
            let (Some(plus), Some(minus)) = (
                eval_track(&t.apply(&d), o, &im, &dem, 1e5),
                eval_track(&t.apply(&(-d)), o, &im, &dem, 1e5),
            ) else {
                continue;
            };
            let fd = (plus.r_px - minus.r_px) / (2.0 * h);
            let an = e.jac.column(k);
            let tol = 1e-2 * an.norm().max(fd.norm()) + 1e-3;
            assert!(
                (fd - an).norm() <= tol,
                "parameter {k}: analytic {an:?} vs differences {fd:?}"
            );
        }
        checked += 1;
    }
    assert!(checked >= 20, "{checked} tracks checked");
}

#[test]
fn a_relief_pair_is_solved_from_a_drifted_guess_within_its_sigma() {
    let dem = grid_dem(relief);
    let im = vga();
    let cfg = DtmNavConfig::default();
    for (baseline_m, seed) in [(60.0, 3), (100.0, 4), (150.0, 2)] {
        let t = truth(baseline_m);
        let tracks = flow(&t, &dem, 0.3, seed);
        let guess = drifted(&t);
        let fix = solve(&input(&tracks, &im, &guess), &dem, &cfg).unwrap();
        let e = error12(&fix, &t);
        let err_h = e[C1].hypot(e[C1 + 1]);
        let err_att_deg = e.fixed_rows::<3>(PHI1).norm().to_degrees();
        let m2 = mahalanobis2(&e, &fix.cov);
        eprintln!(
            "baseline {baseline_m} m: {} tracks, {} inliers, {:?} in {} it, horizontal error {err_h:.2} m (sigma {:.2}, given the attitude {:.2}), height {:.2} m, attitude {err_att_deg:.4} deg, sigma0 {:.2}, rcond {:.1e}, mahalanobis^2 {m2:.1}",
            fix.on_ground,
            fix.inliers,
            fix.method,
            fix.iterations,
            fix.sigma_horizontal_first_m(),
            fix.sigma_h_given_attitude_m,
            e[C1 + 2],
            fix.sigma0,
            fix.rcond
        );
        assert_eq!(fix.inliers, fix.on_ground, "no outliers were made");
        assert!(m2 <= CHI2_12_999, "mahalanobis^2 {m2}");
        // Inside its own 3 sigma (a single pair at these baselines: sigma 15-40 m).
        assert!(
            err_h <= 3.0 * fix.sigma_horizontal_first_m(),
            "horizontal error {err_h} m"
        );
        assert!(err_h <= 60.0, "horizontal error {err_h} m");
        assert!(err_att_deg <= 2.0, "attitude error {err_att_deg} deg");
        // The paper's motion parameters: consistent with the truth.
        let m = fix.motion();
        let te = m.t_world_m - (t.second.c_world - t.first.c_world);
        let tm2 = (te.transpose() * m.cov_t_world_m2.try_inverse().unwrap() * te)[(0, 0)];
        assert!(tm2 <= 16.27, "motion mahalanobis^2 {tm2} (3 dof, 99.9 %)");
    }
}

#[test]
fn levenberg_marquardt_alone_reaches_the_same_solution() {
    let dem = grid_dem(relief);
    let im = vga();
    let t = truth(60.0);
    let tracks = flow(&t, &dem, 0.3, 5);
    let guess = drifted(&t);
    let cfg = DtmNavConfig::default();
    let gn = solve(&input(&tracks, &im, &guess), &dem, &cfg).unwrap();
    let lm = solve_with(&input(&tracks, &im, &guess), &dem, &cfg, true).unwrap();
    assert_eq!(lm.method, DtmMethod::LevenbergMarquardt);
    // The cost is nearly flat along the weakly determined direction (a sideways shift traded for
    // a tilt): the two minimisers stop within a small fraction of a sigma of each other.
    let mut d = Vec12::zeros();
    let rot = |a: &Pose, b: &Pose| {
        crate::pose::refine::log_so3(&(a.r_world_cam * b.r_world_cam.inverse()))
    };
    d.fixed_rows_mut::<3>(PHI1)
        .copy_from(&rot(&lm.first, &gn.first));
    d.fixed_rows_mut::<3>(C1)
        .copy_from(&(lm.first.c_world - gn.first.c_world));
    d.fixed_rows_mut::<3>(PHI2)
        .copy_from(&rot(&lm.second, &gn.second));
    d.fixed_rows_mut::<3>(C2)
        .copy_from(&(lm.second.c_world - gn.second.c_world));
    let m = mahalanobis2(&d, &gn.cov).sqrt();
    // Each stage stops when its cost drops by less than CONVERGED_COST_GAIN (0.045 sigma).
    assert!(m < 0.25, "GN and LM solutions {m} sigma apart");
}

#[test]
fn gross_flow_outliers_get_no_weight() {
    let dem = grid_dem(relief);
    let im = vga();
    let t = truth(60.0);
    let mut tracks = flow(&t, &dem, 0.3, 6);
    let mut rng = Rng::new(7);
    let n = tracks.len();
    // One in twelve (8 %): under the default 10 % the inlier check allows.
    for tr in tracks.iter_mut().step_by(12) {
        let a = rng.range(0.0, std::f64::consts::TAU);
        let r = rng.range(8.0, 40.0);
        tr.next_px += Vector2::new(a.cos(), a.sin()) * r;
    }
    let cfg = DtmNavConfig::default();
    let fix = solve(&input(&tracks, &im, &drifted(&t)), &dem, &cfg).unwrap();
    let e = error12(&fix, &t);
    let err_h = e[C1].hypot(e[C1 + 1]);
    eprintln!(
        "{} of {n} tracks inliers, horizontal error {err_h:.2} m, sigma {:.2} m",
        fix.inliers,
        fix.sigma_horizontal_first_m()
    );
    let outliers = n.div_ceil(12);
    assert!(fix.inliers <= n - outliers + 2, "{} inliers", fix.inliers);
    assert!(fix.inliers >= n - outliers - 5, "{} inliers", fix.inliers);
    assert!(mahalanobis2(&e, &fix.cov) <= CHI2_12_999);
    assert!(
        err_h <= 3.0 * fix.sigma_horizontal_first_m(),
        "horizontal error {err_h} m"
    );
}

#[test]
fn flat_ground_is_refused_with_a_conditioning_reason() {
    let im = vga();
    let cfg = DtmNavConfig::default();
    // Exactly flat: the relief screen refuses first...
    let flat = Dem::flat(450.0).unwrap();
    let t = truth(60.0);
    let tracks = flow(&t, &flat, 0.3, 8);
    let guess = drifted(&t);
    let r = solve(&input(&tracks, &im, &guess), &flat, &cfg).unwrap_err();
    assert!(matches!(r, DtmRejection::FlatGround { .. }), "{r}");
    // ... and without the screen the normal equations do: singular.
    let unscreened = DtmNavConfig {
        min_relief_agl_fraction: 0.0,
        ..DtmNavConfig::default()
    };
    let r = solve(&input(&tracks, &im, &guess), &flat, &unscreened).unwrap_err();
    assert!(
        matches!(
            r,
            DtmRejection::IllConditioned { .. } | DtmRejection::Unobservable { .. }
        ),
        "{r}"
    );
    // Gentle undulation (2 m over 550 m of height): solvable equations, but the position is
    // not determined to the limit: unobservable, said with the sigma.
    let gentle = grid_dem(|x, y| 450.0 + 2.0 * (x / 700.0).sin() * (y / 900.0).cos());
    let tracks = flow(&t, &gentle, 0.3, 9);
    let r = solve(&input(&tracks, &im, &guess), &gentle, &unscreened).unwrap_err();
    assert!(
        matches!(
            r,
            DtmRejection::Unobservable { .. } | DtmRejection::IllConditioned { .. }
        ),
        "{r}"
    );
    eprintln!("gentle undulation: {r}");
    let r = solve(&input(&tracks, &im, &guess), &gentle, &cfg).unwrap_err();
    assert!(matches!(r, DtmRejection::FlatGround { .. }), "{r}");
}

#[test]
fn bad_inputs_are_refused_without_a_panic() {
    let dem = grid_dem(relief);
    let im = vga();
    let t = truth(60.0);
    let tracks = flow(&t, &dem, 0.3, 10);
    let cfg = DtmNavConfig::default();
    let mut g = drifted(&t);
    g.first.c_world.x = f64::NAN;
    let r = solve(&input(&tracks, &im, &g), &dem, &cfg).unwrap_err();
    assert!(matches!(r, DtmRejection::InvalidInput(_)), "{r}");
    let mut g = drifted(&t);
    g.second.r_world_cam = Rotation3::from_matrix_unchecked(Matrix3::identity() * 2.0);
    let r = solve(&input(&tracks, &im, &g), &dem, &cfg).unwrap_err();
    assert!(matches!(r, DtmRejection::InvalidInput(_)), "{r}");
    let r = solve(&input(&tracks[..10], &im, &drifted(&t)), &dem, &cfg).unwrap_err();
    assert!(matches!(r, DtmRejection::TooFewTracks { .. }), "{r}");
    let bad_cfg = DtmNavConfig {
        tukey_c_sigma: f64::NAN,
        ..DtmNavConfig::default()
    };
    let r = solve(&input(&tracks, &im, &drifted(&t)), &dem, &bad_cfg).unwrap_err();
    assert!(r.to_string().contains("tukey_c_sigma"), "{r}");
    // Non-finite flow vectors are dropped, the rest solved.
    let mut some_nan = tracks.clone();
    for tr in some_nan.iter_mut().step_by(9) {
        tr.next_px.x = f64::NAN;
    }
    let fix = solve(&input(&some_nan, &im, &drifted(&t)), &dem, &cfg).unwrap();
    assert!(fix.on_ground < tracks.len());
    // A guess below the terrain sees no ground.
    let mut g = drifted(&t);
    g.first.c_world.z = 0.0;
    let r = solve(&input(&tracks, &im, &g), &dem, &cfg).unwrap_err();
    assert!(matches!(r, DtmRejection::TooFewOnGround { .. }), "{r}");
}

/// The covariance against the scatter: 24 noise draws (the claimed 0.5 px on both ends) of the
/// same pair; the squared Mahalanobis distance of the twelve-parameter error is chi-square with
/// 12 degrees of freedom when the covariance is right. Measured: mean 30 without the inflation
/// (the errors scatter 1.6 times the linear sigma: the default inflation's reason), 7.5 with the
/// default 2. The mean must stay at most 12 (not over-confident) and not far under (not
/// uselessly loose), no draw beyond the 99.9 % point.
#[test]
fn the_covariance_matches_the_scatter() {
    let dem = grid_dem(relief);
    let im = vga();
    let t = truth(60.0);
    let cfg = DtmNavConfig::default();
    let mut m2s = Vec::new();
    for seed in 1..=24 {
        let tracks = flow(&t, &dem, 0.5, 100 + seed);
        let fix = solve(&input(&tracks, &im, &drifted(&t)), &dem, &cfg).unwrap();
        let e = error12(&fix, &t);
        let err_h = e[C1].hypot(e[C1 + 1]);
        assert!(err_h <= 3.0 * fix.sigma_horizontal_first_m(), "{err_h} m");
        m2s.push(mahalanobis2(&e, &fix.cov));
    }
    let mean = m2s.iter().sum::<f64>() / m2s.len() as f64;
    let max = m2s.iter().cloned().fold(0.0, f64::max);
    eprintln!("mahalanobis^2 over 24 draws: mean {mean:.2}, max {max:.2}");
    assert!((3.0..=12.0).contains(&mean), "mean {mean}");
    assert!(max <= CHI2_12_999, "max {max}");
}

/// The guess check: a right solution agrees with a guess whose height and tilt are as good as
/// said; a guess 120 m too high that claims 10 m of height sigma makes the (right) solution
/// disagree with it: refused with the numbers.
#[test]
fn a_solution_is_checked_against_the_guess_height_and_tilt() {
    let dem = grid_dem(relief);
    let im = vga();
    let t = truth(100.0);
    let tracks = flow(&t, &dem, 0.3, 11);
    let cfg = DtmNavConfig::default();
    let guess = drifted(&t);
    let sigma = GuessSigma {
        height_m: 30.0,
        tilt_rad: 1f64.to_radians(),
        horizontal_m: f64::INFINITY,
    };
    let with = |g: &PosePair, s: GuessSigma| DtmInput {
        guess_sigma: Some(s),
        ..input(&tracks, &im, g)
    };
    solve(&with(&guess, sigma), &dem, &cfg).unwrap();
    let mut high = guess;
    high.first.c_world.z += 120.0;
    high.second.c_world.z += 120.0;
    let tight = GuessSigma {
        height_m: 10.0,
        ..sigma
    };
    let r = solve(&with(&high, tight), &dem, &cfg).unwrap_err();
    assert!(
        matches!(r, DtmRejection::InconsistentWithGuess { dh_m, .. } if dh_m < -100.0),
        "{r}"
    );
    let bad = GuessSigma {
        height_m: -1.0,
        ..sigma
    };
    let r = solve(&with(&guess, bad), &dem, &cfg).unwrap_err();
    assert!(matches!(r, DtmRejection::InvalidInput(_)), "{r}");
}

/// The terrain model's registration error: flow seen over the true relief, solved over a model
/// displaced by `b`, gives both cameras displaced by `b`; the covariance's DEM term is exactly
/// `Sigma_b` on both positions and their cross blocks (the attitudes' untouched).
#[test]
fn a_displaced_terrain_model_moves_the_poses_and_its_sigma_covers_it() {
    // World axes (x east, y north, z up); `grid_dem`'s closure takes y southward.
    let b = Vector3::new(40.0, -30.0, 10.0);
    let true_dem = grid_dem(relief);
    let model = grid_dem(|x, y| relief(x - b.x, y + b.y) + b.z);
    let im = vga();
    let t = truth(100.0);
    let tracks = flow(&t, &true_dem, 0.3, 5);
    let guess = drifted(&t);
    let exact = DtmNavConfig {
        dem_shift_sigma_cells: 0.0,
        dem_offset_sigma_m: 0.0,
        ..DtmNavConfig::default()
    };
    let stated = DtmNavConfig {
        dem_shift_sigma_cells: 2.0,
        dem_offset_sigma_m: 10.0,
        ..DtmNavConfig::default()
    };
    let on_truth = solve(&input(&tracks, &im, &guess), &true_dem, &exact).unwrap();
    let fix0 = solve(&input(&tracks, &im, &guess), &model, &exact).unwrap();
    let fix1 = solve(&input(&tracks, &im, &guess), &model, &stated).unwrap();
    for (a, b_) in [
        (fix0.first.c_world, on_truth.first.c_world),
        (fix0.second.c_world, on_truth.second.c_world),
    ] {
        // Within a few metres: the displaced function sampled on the same grid is not exactly
        // the displaced bilinear surface.
        assert!(
            ((a - b_) - b).norm() < 3.0,
            "moved {:?}, displacement {b:?}",
            a - b_
        );
    }
    let s_h = 2.0 * CELL_M;
    let want = Matrix3::from_diagonal(&Vector3::new(s_h * s_h, s_h * s_h, 100.0));
    for (r, c) in [(C1, C1), (C1, C2), (C2, C1), (C2, C2)] {
        let d = fix1.cov.fixed_view::<3, 3>(r, c) - fix0.cov.fixed_view::<3, 3>(r, c);
        assert!((d - want).amax() < 1e-6, "block ({r}, {c}): {d}");
    }
    assert_eq!(
        fix1.cov.fixed_view::<3, 3>(PHI1, PHI1),
        fix0.cov.fixed_view::<3, 3>(PHI1, PHI1)
    );
}

/// A solution further from the guess than the guess's horizontal sigma and its own allow is
/// refused (another minimum, or a navigation more wrong than it says); the same solution from a
/// guess that says it may be that far off is accepted.
#[test]
fn a_solution_far_from_a_confident_guess_is_refused() {
    let dem = grid_dem(relief);
    let im = vga();
    let t = truth(100.0);
    let tracks = flow(&t, &dem, 0.3, 13);
    let cfg = DtmNavConfig::default();
    // The guess 250 m off horizontally: the solution's own horizontal sigma here is about 30 m.
    let mut guess = drifted(&t);
    let far = Vector3::new(150.0, 150.0, 0.0);
    guess.first.c_world += far;
    guess.second.c_world += far;
    let with = |h: f64| DtmInput {
        guess_sigma: Some(GuessSigma {
            height_m: 30.0,
            tilt_rad: 1f64.to_radians(),
            horizontal_m: h,
        }),
        ..input(&tracks, &im, &guess)
    };
    let fix = solve(&with(150.0), &dem, &cfg).unwrap();
    assert!((fix.first.c_world - t.first.c_world).norm() < 30.0);
    solve(&with(f64::INFINITY), &dem, &cfg).unwrap();
    let r = solve(&with(20.0), &dem, &cfg).unwrap_err();
    let d = (guess.first.c_world - t.first.c_world).xy().norm();
    assert!(
        matches!(r, DtmRejection::FarFromGuess { d_m, .. } if (d_m - d).abs() < 30.0),
        "{r}"
    );
    let r = solve(&with(0.0), &dem, &cfg).unwrap_err();
    assert!(matches!(r, DtmRejection::InvalidInput(_)), "{r}");
}
