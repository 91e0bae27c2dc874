//! The vision fix, NAIP cross-date (see `visnav::sitl::fixeval`). Frames
//! rendered from the 2014 orthophoto are matched to a reference built from the 2009 orthophoto of
//! the same area (bundled in sitl/maps; the lake levels changed a lot between the two years).
//! Frames of other ground, of empty ground beyond the map, or with a prior far off must be
//! rejected.

use std::path::PathBuf;

use nalgebra::Vector3;
use visnav::camera::{Attitude, Mount};
use visnav::fix::{AreaMatching, FixParams};
use visnav::geo::dem::Dem;
use visnav::geo::geotiff::load_geotiff;
use visnav::geo::raster::{Raster, RasterData};
use visnav::sitl::fixeval::{Case, HeightSigmas, NAIP_GROUND_M, NaipEval, Summary};
use visnav::sitl::render::{ColourMode, RenderPose, Scene, grid_convergence_rad};
use visnav_core::rng::Rng;

fn eval() -> NaipEval {
    eval_with(FixParams::default())
}

fn eval_with(params: FixParams) -> NaipEval {
    let maps = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("sitl/maps");
    NaipEval::new(&maps, params).expect("NAIP evaluation set-up")
}

/// `frames` frames of `e` (seed 2024), each frame's line and the summary logged.
fn run_logged(e: &NaipEval, frames: usize) -> Summary {
    let s = e
        .run(frames, 2024, &mut |line| eprintln!("{line}"))
        .expect("run");
    eprintln!("{}", serde_json::to_string_pretty(&s).unwrap_or_default());
    s
}

fn area_only() -> FixParams {
    FixParams {
        area_matching: AreaMatching::Only,
        ..FixParams::default()
    }
}

/// The area correlation alone (`fix::area`, no features): fixes with the features' accuracy and
/// never a wrong one. Measured (100 frames, seed 2024): 59 % accepted, median 2.7 map px, 0
/// wrong, 3 beyond 3 sigma; as the features' fallback (the default) 75 -> 83 % accepted.
#[test]
fn naip_area_correlation_alone_fixes_honestly() {
    let e = eval_with(area_only());
    let s = run_logged(&e, 40);
    // Outside their own 3 sigma: at most 2 (measured 0). More than 50 m off (3-D) while inside
    // it: measured 2 of 24, their height 55-64 m off at 2.2 sigma; at 1200-2500 m over a 5 m
    // cross-date map a fix's height sigma is 20-30 m, so the 50 m bound is not met by the claims
    // themselves (docs/fix.md, "Wrong fixes"). Guarded at today's count.
    assert!(
        s.wrong_beyond_sigma <= 2,
        "{} area fixes outside 3 sigma",
        s.wrong_beyond_sigma
    );
    assert!(s.wrong_far <= 2, "{} area fixes over 50 m off", s.wrong_far);
    assert!(s.fix_rate >= 0.35, "area fix rate {}", s.fix_rate);
    assert!(
        s.median_err_map_px <= 4.0,
        "median error {} map px",
        s.median_err_map_px
    );
}

#[test]
fn naip_cross_date_fixes_with_prior() {
    let e = eval();
    let s = run_logged(&e, 40);
    // Integrity first: no accepted fix outside its 3-sigma bounds on any axis.
    assert_eq!(s.beyond_3_sigma, 0, "accepted fixes beyond 3 sigma");
    // The image-only pose ([nav] vision_attitude fuses it) is honest jointly, all six degrees of
    // freedom: measured NEES mean 6.6 (chi-square 6 dof: 6), none beyond the 99 % quantile.
    assert!(
        (3.0..=10.0).contains(&s.vision_only_nees6_mean),
        "image-only pose NEES mean {}",
        s.vision_only_nees6_mean
    );
    assert!(
        s.vision_only_beyond_chi2_99 * 10 <= s.accepted,
        "{} of {} image-only poses beyond the chi-square(6) 99 % quantile",
        s.vision_only_beyond_chi2_99,
        s.accepted
    );
    // Regression guards below today's measurement (22/40 accepted, median 4.7 map px); the
    // targets (90 %, 0.5 map px) are not met on this scene, see docs/fix.md.
    assert!(s.fix_rate >= 0.4, "fix rate {}", s.fix_rate);
    assert!(
        s.median_err_map_px <= 8.0,
        "median error {} map px",
        s.median_err_map_px
    );
}

/// The placement fix (docs/fix.md): at 1200-1600 m above ground, where the fewest features and
/// tie points are found, the area placement alone fixes the frames the tie points cannot, never
/// wrongly. Measured (100 frames, seed 2024): 70 -> 91 % accepted, 0 wrong, 0 beyond 3 sigma,
/// 21 placement fixes (horizontal error 1-24 m at sigma 13-20 m).
#[test]
fn naip_placement_fix_at_low_altitude_is_honest() {
    let mut e = eval();
    e.agl_range_m = (1200.0, 1600.0);
    let s = run_logged(&e, 40);
    // None outside its own 3 sigma; more than 50 m off (3-D) inside it: measured 4 of 36 (their
    // height 55-76 m off at 2.0-2.5 sigma of 20-31 m), guarded at today's count (docs/fix.md,
    // "Wrong fixes").
    assert_eq!(s.wrong_beyond_sigma, 0, "fixes outside 3 sigma");
    assert!(s.wrong_far <= 4, "{} fixes over 50 m off", s.wrong_far);
    assert_eq!(s.beyond_3_sigma, 0, "fixes beyond 3 sigma");
    assert!(s.fix_rate >= 0.8, "fix rate {}", s.fix_rate);
    assert!(
        s.median_err_map_px <= 4.0,
        "median error {} map px",
        s.median_err_map_px
    );
}

/// A frame that sees beyond the map's edge cannot be judged at its true place (too little of
/// the map under it), so an area placement elsewhere is not shown unique: without tie points
/// it must not become a placement fix. Same imagery and the area correlation alone, where
/// every other frame's tie points are found: 40 frames of seed 2024 give no wrong fix. The frame
/// the rule was made for is set here rather than left to the draws (about one frame in 100 of
/// the run is such a frame): seed 2024's frame 27 under the simulator's former generator, half
/// beyond the north edge, was placed 96 m off before the rule.
#[test]
fn naip_frames_beyond_the_map_edge_get_no_placement_fix() {
    let mut e = eval_with(area_only());
    e.same_imagery = true;
    let s = run_logged(&e, 40);
    assert_eq!(s.wrong_fixes, 0, "wrong fixes");
    assert!(s.fix_rate >= 0.85, "fix rate {}", s.fix_rate);
    // That frame: 858 m inside the north edge, 2233 m above ground, roll 12.2, pitch -5.6,
    // heading 83.2 deg; the prior 100 m x (-0.513, 0.997) off horizontally, 20 m x 1.207
    // vertically, its attitude 0.3 deg x (-1.490, 1.990, 1.262) off (the former draws).
    let map_scene = Scene::new(
        &e.map_raster,
        Dem::flat(NAIP_GROUND_M).expect("dem"),
        ColourMode::Grey,
    )
    .expect("scene of the map image");
    let (x, y) = (487_963.4, 5_208_388.8);
    let att = Attitude::from_deg(12.157, -5.611, 83.218);
    let gamma = grid_convergence_rad(&e.crs, x, y).expect("grid convergence");
    let body = Vector3::new(x, y, e.ground_m(x, y) + 2233.4);
    let case = Case {
        pose: RenderPose::from_body(body, &att, &Mount::nadir(), gamma),
        attitude: att,
        grid_convergence_rad: gamma,
    };
    let img = e.frame(&case, 27, Some(&map_scene)).expect("frame");
    let mut prior = e.prior(&mut Rng::new(27), &case, 27).expect("prior");
    let c = case.pose.centre_map_m;
    let (lat, lon) = e
        .crs
        .to_geodetic(c.x - 100.0 * 0.513, c.y + 100.0 * 0.997)
        .expect("geodetic");
    let p = prior.position.as_mut().expect("position prior");
    (p.lat_deg, p.lon_deg, p.alt_amsl_m) = (lat, lon, c.z + 20.0 * 1.207);
    let a = &mut prior.attitude.as_mut().expect("attitude prior").attitude;
    let n = 0.3f64.to_radians();
    *a = Attitude::new(
        att.roll_rad - 1.490 * n,
        att.pitch_rad + 1.990 * n,
        att.yaw_rad + 1.262 * n,
    );
    let r = e.engine.fix(&img, &prior);
    eprintln!(
        "frame beyond the north edge: {} method {:?} inliers {} matches {} x {:.0} y {:.0} yaw {:.1}",
        r.reason(),
        r.method,
        r.inliers,
        r.matches,
        r.x_m,
        r.y_m,
        r.yaw_deg
    );
    assert!(
        !r.accepted && r.reason().contains("could not judge"),
        "the frame beyond the map edge: accepted {}, {}",
        r.accepted,
        r.reason()
    );
}

/// A map from the same source as the camera's world (docs/fix.md, "A map from the same source
/// as the camera's world"): with the same-source weights the image, not the 0.5 deg attitude
/// prior, determines the attitude, and the covariance stays honest. Measured (100 frames, seed
/// 2024): 1.1 m median against 6.6 m with the cross-date defaults, image-only NEES 6.1.
#[test]
fn naip_same_source_weights_take_the_attitude_from_the_image() {
    let mut params = FixParams {
        area_matching: AreaMatching::First,
        ..FixParams::default()
    };
    params.pose.refine.sigma_inflation = 2.5;
    params.pose.refine.sigma0_floor = 0.1;
    // The frames' ground is flat at the map's height: stated so (no slope). A map slope left
    // open is indistinguishable from an attitude error, and the estimate between image and
    // prior then hands part of the prior's 0.5 deg to the map (8.5 m median measured).
    let maps = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("sitl/maps");
    let flat = HeightSigmas {
        offset_m: None,
        slope: Some(0.0),
        point_m: None,
    };
    let surf = visnav::vision::SurfParams {
        upright: true,
        ..visnav::vision::SurfParams::default()
    };
    let mut e = NaipEval::with_map_heights(
        &maps,
        &[maps.join("naip_nd_2009.tif")],
        1,
        params,
        surf,
        flat,
    )
    .expect("NAIP evaluation set-up");
    e.same_imagery = true;
    let s = run_logged(&e, 30);
    assert_eq!(s.wrong_fixes, 0, "wrong fixes");
    assert_eq!(s.beyond_3_sigma, 0, "fixes beyond 3 sigma");
    assert!(s.fix_rate >= 0.9, "fix rate {}", s.fix_rate);
    assert!(s.err_h_m.median <= 1.6, "median {} m", s.err_h_m.median);
    assert!(
        (2.5..=12.0).contains(&s.vision_only_nees6_mean),
        "image-only NEES mean {}",
        s.vision_only_nees6_mean
    );
}

#[test]
fn naip_frames_of_other_ground_are_rejected() {
    frames_of_other_ground_are_rejected(&eval());
}

/// The same with the area correlation alone: its uniqueness rule and tie points must refuse
/// other ground, empty ground and a far prior on their own.
#[test]
fn naip_frames_of_other_ground_are_rejected_by_the_area_correlation() {
    frames_of_other_ground_are_rejected(&eval_with(area_only()));
}

/// The same with the heading 25 deg off and a 30 deg sigma: a heading sweep, whose area pass
/// may end in a placement fix that must lead every other heading's correlation.
#[test]
fn naip_frames_of_other_ground_are_rejected_by_a_heading_sweep() {
    let mut e = eval();
    e.yaw_error_deg = 25.0;
    e.yaw_sigma_deg = 30.0;
    frames_of_other_ground_are_rejected(&e);
}

fn frames_of_other_ground_are_rejected(e: &NaipEval) {
    let b = e.map_raster.bounds();
    let mut rng = Rng::new(99);
    let uni = |rng: &mut Rng, lo: f64, hi: f64| lo + (hi - lo) * rng.uniform();
    // "Other ground": the 2014 image mirrored left-right and placed on the map's footprint, so
    // the frames are real textured farmland that is not the mapped area, while the prior claims
    // the mapped area. Nothing may be accepted.
    let maps = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("sitl/maps");
    let cam = load_geotiff(&maps.join("naip_nd_2014.tif"), None).expect("2014");
    let (w, h, nb) = (cam.width(), cam.height(), cam.bands());
    let src = cam.data().as_u8().expect("u8 NAIP");
    let mut mirrored = vec![0u8; src.len()];
    for row in 0..h {
        for col in 0..w {
            let (a, bi) = ((row * w + col) * nb, (row * w + (w - 1 - col)) * nb);
            mirrored[a..a + nb].copy_from_slice(&src[bi..bi + nb]);
        }
    }
    let other = Raster::new(
        w,
        h,
        nb,
        RasterData::U8(mirrored),
        *cam.transform(),
        cam.crs(),
        None,
    )
    .expect("mirrored raster");
    let other_scene = Scene::new(
        &other,
        Dem::flat(NAIP_GROUND_M).expect("dem"),
        ColourMode::Grey,
    )
    .expect("scene");
    for i in 0..12u64 {
        let x = uni(&mut rng, b.min_x_m + 1200.0, b.max_x_m - 1200.0);
        let y = uni(&mut rng, b.min_y_m + 1000.0, b.max_y_m - 1000.0);
        let case = e.random_case(&mut rng, x, y);
        let img = e.frame(&case, i, Some(&other_scene)).expect("frame");
        let prior = e.prior(&mut rng, &case, i).expect("prior");
        let r = e.engine.fix(&img, &prior);
        eprintln!(
            "other ground {i}: {} method {:?} inliers {} matches {} x {:.0} y {:.0} yaw {:.1} truth x {:.0} y {:.0}",
            r.reason(),
            r.method,
            r.inliers,
            r.matches,
            r.x_m,
            r.y_m,
            r.yaw_deg,
            case.pose.centre_map_m.x,
            case.pose.centre_map_m.y
        );
        assert!(!r.accepted, "a frame of other ground was accepted");
    }
    // Frames of empty ground beyond the map (the renderer's fill) are rejected.
    for (i, (x, y)) in [
        (b.min_x_m - 3000.0, 0.5 * (b.min_y_m + b.max_y_m)),
        (0.5 * (b.min_x_m + b.max_x_m), b.max_y_m + 5000.0),
    ]
    .into_iter()
    .enumerate()
    {
        let case = e.random_case(&mut rng, x, y);
        let img = e.frame(&case, i as u64, None).expect("frame");
        let prior = e.prior(&mut rng, &case, i as u64).expect("prior");
        let r = e.engine.fix(&img, &prior);
        eprintln!("beyond the map {i}: {}", r.reason());
        assert!(!r.accepted, "frame beyond the map accepted");
    }
    // A frame over the map whose prior is 1.5 km off (a lost filter claiming 150 m) is rejected,
    // not matched to the wrong place.
    for i in 0..8u64 {
        let x = uni(&mut rng, b.min_x_m + 1500.0, b.max_x_m - 1500.0);
        let y = uni(&mut rng, b.min_y_m + 1000.0, b.max_y_m - 1000.0);
        let case = e.random_case(&mut rng, x, y);
        let img = e.frame(&case, 20 + i, None).expect("frame");
        let mut prior = e.prior(&mut rng, &case, 20 + i).expect("prior");
        let dx = if x > 0.5 * (b.min_x_m + b.max_x_m) {
            -1500.0
        } else {
            1500.0
        };
        if let Some(p) = prior.position.as_mut() {
            let (lat, lon) = e.crs.to_geodetic(x + dx, y).expect("geodetic");
            p.lat_deg = lat;
            p.lon_deg = lon;
        }
        let r = e.engine.fix(&img, &prior);
        eprintln!("prior 1.5 km off {i}: {}", r.reason());
        assert!(!r.accepted, "fix accepted with a prior 1.5 km off");
    }
}

#[test]
fn naip_position_prior_without_attitude_stays_honest() {
    let e = eval();
    let b = e.map_raster.bounds();
    let mut rng = Rng::new(5);
    let (mut accepted, mut n) = (0, 0);
    for i in 0..8u64 {
        let x = b.min_x_m + 900.0 + (b.max_x_m - b.min_x_m - 1800.0) * rng.uniform();
        let y = b.min_y_m + 900.0 + (b.max_y_m - b.min_y_m - 1800.0) * rng.uniform();
        let mut case = e.random_case(&mut rng, x, y);
        // Near-nadir (what the headings search assumes), any heading.
        let heading = case.attitude.yaw_rad;
        case = {
            let att = visnav::camera::Attitude::new(0.01, -0.02, heading);
            let gamma = case.grid_convergence_rad;
            let body = case.pose.centre_map_m;
            visnav::sitl::fixeval::Case {
                pose: visnav::sitl::render::RenderPose::from_body(
                    body,
                    &att,
                    &visnav::camera::Mount::nadir(),
                    gamma,
                ),
                attitude: att,
                grid_convergence_rad: gamma,
            }
        };
        let img = e.frame(&case, i, None).expect("frame");
        let mut prior = e.prior(&mut rng, &case, i).expect("prior");
        prior.attitude = None;
        let r = e.engine.fix(&img, &prior);
        n += 1;
        if r.accepted {
            accepted += 1;
            let s = e.score(&r, &case);
            eprintln!(
                "no-attitude frame {i}: error h {:.1} m = {:.2} sigma",
                s.err_h_m, s.err_sigma
            );
            assert!(s.err_sigma <= 3.0, "beyond 3 sigma");
            // Never a wrong fix (> 50 m off): a fix whose 1-sigma exceeds 50 m is
            // not offered (MAX_FIX_HORIZONTAL_SIGMA_M).
            assert!(
                s.err_h_m <= 50.0,
                "a no-attitude fix {:.0} m off",
                s.err_h_m
            );
            // The heading comes out of the image.
            let dyaw = (r.yaw_deg.to_radians() - heading)
                .sin()
                .abs()
                .asin()
                .to_degrees();
            assert!(dyaw < 3.0, "yaw error {dyaw} deg");
        } else {
            eprintln!("no-attitude frame {i}: {}", r.reason());
            assert!(!r.reason().is_empty());
        }
    }
    // Without an attitude prior nothing bounds the position/tilt ambiguity of a 60 deg view over
    // flat ground: the solves are weak (1-sigma 120-180 m in trials) and honestly rejected by the
    // sigma limit; what must hold is integrity (checked above) and a reason for each rejection.
    eprintln!("position prior without attitude: {accepted} of {n} accepted");
}

/// `[fix] map_registration_sigma_px`: the map's registration shift is added to the horizontal
/// position covariance of the fix and of its image-only pose, whole (in metres of the map's
/// finest pixel), and nothing else changes.
#[test]
fn map_registration_sigma_widens_only_the_horizontal_position_covariance() {
    let maps = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("sitl/maps");
    let plain = eval();
    let with_reg = NaipEval::new(
        &maps,
        FixParams {
            map_registration_sigma_px: 0.8,
            ..FixParams::default()
        },
    )
    .expect("NAIP evaluation set-up");
    let reg_var = (0.8 * plain.map_gsd_m()).powi(2);
    let b = plain.map_raster.bounds();
    let mut rng = Rng::new(5);
    let mut compared = 0;
    for i in 0..12u64 {
        let x = b.min_x_m + 600.0 + (b.max_x_m - b.min_x_m - 1200.0) * rng.uniform();
        let y = b.min_y_m + 600.0 + (b.max_y_m - b.min_y_m - 1200.0) * rng.uniform();
        let case = plain.random_case(&mut rng, x, y);
        let img = plain.frame(&case, i, None).expect("render");
        let prior = plain.prior(&mut rng, &case, i).expect("prior");
        let a = plain.engine.fix(&img, &prior);
        let r = with_reg.engine.fix(&img, &prior);
        assert_eq!(
            a.accepted,
            r.accepted,
            "frame {i}: {} / {}",
            a.reason(),
            r.reason()
        );
        if !a.accepted {
            continue;
        }
        compared += 1;
        assert_eq!((a.x_m, a.y_m, a.z_m), (r.x_m, r.y_m, r.z_m), "frame {i}");
        for (k, l) in [(0, 0), (1, 1)] {
            let d = r.cov_ned_m2[k][l] - a.cov_ned_m2[k][l];
            assert!(
                (d - reg_var).abs() < 1e-6 * reg_var.max(1.0),
                "frame {i}: {d}"
            );
        }
        assert_eq!(r.cov_ned_m2[2][2], a.cov_ned_m2[2][2]);
        assert_eq!(r.cov_ned_m2[0][1], a.cov_ned_m2[0][1]);
        // A placement fix (the area correlation's place, no resection) has no image-only pose.
        let (va, vr) = match (a.vision_only, r.vision_only) {
            (Some(va), Some(vr)) => (va, vr),
            (None, None) => continue,
            (va, vr) => panic!("frame {i}: image-only pose {va:?} against {vr:?}"),
        };
        assert!((vr.cov6_ned[0][0] - va.cov6_ned[0][0] - reg_var).abs() < 1e-6 * reg_var);
        assert!((vr.cov6_ned[1][1] - va.cov6_ned[1][1] - reg_var).abs() < 1e-6 * reg_var);
        assert_eq!(vr.cov6_ned[2][2], va.cov6_ned[2][2]);
        assert_eq!(vr.cov6_ned[3][3], va.cov6_ned[3][3]);
    }
    assert!(compared >= 4, "only {compared} accepted fixes compared");
}

/// An upsampled map (`[map] upsample = 2`: level 0 at 2.5 m over the 5 m orthophoto) keeps
/// `map_registration_sigma_px` in orthophoto pixels, as `visnav map compare` measures it: 0.8 px
/// adds (0.8 x 5 m)^2, not (0.8 x 2.5 m)^2, on the frames that solve on the 2.5 m level.
#[test]
fn upsampled_map_keeps_the_registration_in_orthophoto_pixels() {
    let maps = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("sitl/maps");
    let map = [maps.join("naip_nd_2010.tif")];
    let surf = visnav::vision::SurfParams {
        upright: true,
        ..visnav::vision::SurfParams::default()
    };
    let build = |reg_px: f64| {
        let mut e = NaipEval::with_map(
            &maps,
            &map,
            2,
            FixParams {
                map_registration_sigma_px: reg_px,
                ..FixParams::default()
            },
            surf.clone(),
        )
        .expect("NAIP evaluation set-up");
        e.agl_range_m = (1000.0, 1100.0);
        e.max_tilt_deg = 3.0;
        e
    };
    let (plain, with_reg) = (build(0.0), build(0.8));
    let reference = plain.engine.reference();
    assert_eq!(reference.level_gsd_m()[0], 2.5);
    assert_eq!(reference.ortho_pixel_m(), 5.0);
    let reg_var = (0.8f64 * 5.0).powi(2);
    let b = plain.map_raster.bounds();
    let mut rng = Rng::new(11);
    let mut compared = 0;
    for i in 0..20u64 {
        let x = b.min_x_m + 600.0 + (b.max_x_m - b.min_x_m - 1200.0) * rng.uniform();
        let y = b.min_y_m + 600.0 + (b.max_y_m - b.min_y_m - 1200.0) * rng.uniform();
        let case = plain.random_case(&mut rng, x, y);
        let img = plain.frame(&case, i, None).expect("render");
        let prior = plain.prior(&mut rng, &case, i).expect("prior");
        let (a, at) = plain.engine.fix_with_attempt(&img, &prior);
        let r = with_reg.engine.fix(&img, &prior);
        assert_eq!(a.accepted, r.accepted, "frame {i}");
        if !a.accepted {
            continue;
        }
        assert_eq!(
            at.level, 0,
            "frame {i}: 1000-1100 m solves on the 2.5 m level"
        );
        compared += 1;
        let d = r.cov_ned_m2[0][0] - a.cov_ned_m2[0][0];
        assert!((d - reg_var).abs() < 1e-6 * reg_var, "frame {i}: {d}");
    }
    assert!(compared >= 3, "only {compared} accepted fixes compared");
}

/// "Yaw is not tilt": the prior's heading 25 deg off (a compass heading, or one drifted after a
/// GPS loss) while roll and pitch are good. Claimed as known (0.5 deg) with the widening off, the
/// frame is rectified at the wrong heading and nothing matches; with the widening (the default:
/// no fix at the stated heading, so the heading is searched again over +-90 deg) and claimed as
/// loose (20 deg), the engine searches headings and fixes as often as with a good heading, never
/// wrongly. Release bench: `visnav bench fix --yaw-error-deg 25` and `--yaw-error-deg 30
/// --yaw-sigma-deg 2` (docs/fix.md).
#[test]
fn naip_heading_25_deg_off_is_searched_when_its_sigma_says_so_or_no_fix_is_found() {
    let mut e = eval_with(FixParams {
        widen_heading_sigma_deg: 0.0,
        ..FixParams::default()
    });
    e.yaw_error_deg = 25.0;
    e.yaw_sigma_deg = 0.5;
    let tight = e
        .run(10, 2024, &mut |l| eprintln!("tight: {l}"))
        .expect("run");
    let mut e = eval();
    e.yaw_error_deg = 25.0;
    e.yaw_sigma_deg = 0.5;
    let widened = e
        .run(10, 2024, &mut |l| eprintln!("widened: {l}"))
        .expect("run");
    e.yaw_sigma_deg = 20.0;
    let loose = e
        .run(10, 2024, &mut |l| eprintln!("loose: {l}"))
        .expect("run");
    eprintln!(
        "heading 25 deg off: claimed 0.5 deg {} of 10 accepted without the widening, {} with it; \
         claimed 20 deg {} of 10 (measured 0, 8 and 8)",
        tight.accepted, widened.accepted, loose.accepted
    );
    assert_eq!(tight.wrong_fixes, 0, "wrong fixes with the tight heading");
    assert!(
        tight.accepted <= 2,
        "a 25 deg heading error claimed as 0.5 deg matched"
    );
    for (what, s) in [("widened", &widened), ("loose", &loose)] {
        assert_eq!(s.wrong_fixes, 0, "{what}: wrong fixes in the heading sweep");
        assert_eq!(s.beyond_3_sigma, 0, "{what}: sweep fixes beyond 3 sigma");
        assert!(s.accepted >= 6, "{what}: accepted {} of 10", s.accepted);
    }
}

/// A heading sweep in which no heading matches by features (here made impossible: a feature
/// match must lie within 0.01 px of its prediction) falls back to the area correlation at every heading, with the
/// same uniqueness rule and the fix redone at its own heading: fixes, and never wrongly.
/// Release bench with the features on: 80 -> 84 % at a 25 deg heading error (docs/fix.md).
#[test]
fn heading_sweep_falls_back_to_the_area_correlation() {
    let mut e = eval_with(FixParams {
        fine_radius_px: 0.01,
        ..FixParams::default()
    });
    e.yaw_error_deg = 25.0;
    e.yaw_sigma_deg = 30.0;
    let s = e
        .run(6, 2024, &mut |l| eprintln!("area sweep: {l}"))
        .expect("run");
    eprintln!(
        "heading sweep by area: {} of 6 accepted, wrong {}, beyond 3 sigma {} (measured 4)",
        s.accepted, s.wrong_fixes, s.beyond_3_sigma
    );
    // Outside their own 3 sigma: the allowance below; more than 50 m off (3-D) inside it: at
    // most one (this seed's frame 5: its height 56 m off at 2.8 sigma of 20 m; docs/fix.md,
    // "Wrong fixes").
    assert!(
        s.wrong_far <= 1,
        "{} area sweep fixes over 50 m off",
        s.wrong_far
    );
    // One fix beyond 3 sigma is allowed: in this mode about 2 % of the fixes are (release bench,
    // `--yaw-error-deg 25 --yaw-sigma-deg 30 --set 'fine_radius_px = 0.01'`, 100 frames, seed
    // 2024: 2 of 88 accepted with the simulator's former generator, 2 of 84 with this one), so
    // among five or six fixes one is a fluctuation of the noise realisation (this seed's frame 5
    // since the generator changed: 44 m, 3.46 sigma, not wrong), not a covariance regression.
    assert!(
        s.beyond_3_sigma <= 1,
        "area sweep fixes beyond 3 sigma: {}",
        s.beyond_3_sigma
    );
    assert!(s.accepted >= 3, "area sweep accepted {} of 6", s.accepted);
}

/// Relocalisation's budget counts work, not time: the same frame gives the same report (but for
/// the wall time) every time, and a budget too small for one level's hypotheses is a rejection
/// that says so, never a winner picked without its competitors.
#[test]
fn relocalisation_is_reproducible_and_its_budget_counts_work() {
    let e = eval();
    let b = e.map_raster.bounds();
    let mut rng = Rng::new(1);
    let x = 0.5 * (b.min_x_m + b.max_x_m);
    let y = 0.5 * (b.min_y_m + b.max_y_m);
    let case = e.random_case(&mut rng, x, y);
    let img = e.frame(&case, 0, None).expect("frame");
    let mut prior = e.prior(&mut rng, &case, 0).expect("prior");
    prior.position = None;
    let json = |mut r: visnav::fix::FixReport| {
        r.ms = 0.0;
        serde_json::to_string(&r).expect("json")
    };
    let first = e.engine.fix(&img, &prior);
    eprintln!("relocalisation: {}", first.reason());
    assert!(first.accepted, "{}", first.reason());
    assert!(e.score(&first, &case).err_h_m < 50.0);
    assert_eq!(
        json(first),
        json(e.engine.fix(&img, &prior)),
        "relocalisation is not reproducible"
    );
    // A budget of one unit: spent by the first hypothesis; a tilt-only prior has 24 of them.
    let params = FixParams {
        reloc_budget_mwork: 1e-6,
        ..FixParams::default()
    };
    let maps = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("sitl/maps");
    let small = NaipEval::new(&maps, params).expect("set-up");
    if let Some(a) = prior.attitude.as_mut() {
        a.sigma_yaw_rad = std::f64::consts::PI;
    }
    let r = small.engine.fix(&img, &prior);
    assert!(!r.accepted);
    assert!(r.reason().contains("work budget"), "{}", r.reason());
    // The heading hypotheses are tried in parallel and replayed in order against the budget:
    // the report is the one trying them one after another gives, on any number of threads,
    // with the budget cut in the middle of a level (5 million units: a few of the 24
    // hypotheses) and with the whole search (the fix found above, the heading now unknown).
    let on_threads = |engine: &visnav::fix::FixEngine, n: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build()
            .expect("thread pool");
        json(pool.install(|| engine.fix(&img, &prior)))
    };
    let mid = NaipEval::new(
        &maps,
        FixParams {
            reloc_budget_mwork: 5.0,
            ..FixParams::default()
        },
    )
    .expect("set-up");
    let cut = on_threads(&mid.engine, 1);
    assert!(cut.contains("work budget"), "{cut}");
    assert_eq!(
        cut,
        on_threads(&mid.engine, 2),
        "budget cut differs by threads"
    );
    assert_eq!(
        on_threads(&e.engine, 1),
        on_threads(&e.engine, 2),
        "heading search differs by threads"
    );
}

/// Relocalisation with the tilt and the altitude known and the heading unknown (the
/// restart after a GPS loss: gravity and the barometer still work): the area search over the
/// whole map image at every heading shortlists places, the prior pipeline verifies them, and
/// one confirmed place is the answer. Measured (release, seed 2024): 7 of 10 found, none
/// outside 3 sigma, one 75 m off (its height) inside it, about 0.4 s a frame on one core (100 frames: 75 %, p95 0.6-0.7 s; the
/// feature search without the altitude: 37 %, 3 s). `visnav bench fix --tilt-only --no-prior`.
#[test]
fn relocalisation_with_tilt_and_altitude_finds_the_place_at_any_heading() {
    let mut e = eval();
    e.attitude_mode = visnav::sitl::fixeval::AttitudeMode::TiltOnly;
    let s = e
        .run_with(10, 2024, false, &mut |l| eprintln!("reloc: {l}"))
        .expect("run");
    eprintln!(
        "tilt-only relocalisation with altitude: {} of 10 found, {} wrong, {} beyond 3 sigma",
        s.accepted, s.wrong_fixes, s.beyond_3_sigma
    );
    assert_eq!(s.wrong_beyond_sigma, 0, "relocalisations outside 3 sigma");
    // More than 50 m off (3-D) inside 3 sigma: one (frame 4: its height 70 m off at 1.9 sigma
    // of 36 m; docs/fix.md, "Wrong fixes").
    assert!(
        s.wrong_far <= 1,
        "{} relocalisations over 50 m off",
        s.wrong_far
    );
    assert_eq!(s.beyond_3_sigma, 0, "relocalisations beyond 3 sigma");
    assert!(s.accepted >= 5, "found {} of 10", s.accepted);
    // The same frame twice: the same answer (the search and its budget count work, not time).
    let b = e.map_raster.bounds();
    let mut rng = Rng::new(3);
    let case = e.random_case(
        &mut rng,
        0.5 * (b.min_x_m + b.max_x_m),
        0.5 * (b.min_y_m + b.max_y_m),
    );
    let img = e.frame(&case, 0, None).expect("frame");
    let mut prior = e.prior(&mut rng, &case, 0).expect("prior");
    prior.altitude = prior.position.map(|p| visnav::fix::AltitudePrior {
        alt_amsl_m: p.alt_amsl_m,
        sigma_m: p.sigma_v_m,
    });
    prior.position = None;
    let json = |mut r: visnav::fix::FixReport| {
        r.ms = 0.0;
        serde_json::to_string(&r).expect("json")
    };
    let first = e.engine.fix(&img, &prior);
    eprintln!("one frame: {}", first.reason());
    assert_eq!(json(first), json(e.engine.fix(&img, &prior)));
    // An altitude the search cannot use (not finite, or under the terrain): the feature search
    // runs instead, and its answer is as honest as ever.
    for alt in [f64::NAN, -5000.0] {
        let mut p = prior;
        p.altitude = Some(visnav::fix::AltitudePrior {
            alt_amsl_m: alt,
            sigma_m: 30.0,
        });
        let r = e.engine.fix(&img, &p);
        eprintln!("altitude {alt}: {}", r.reason());
        assert!(!r.reason().contains("area search"), "{}", r.reason());
        if r.accepted {
            assert!(e.score(&r, &case).err_h_m < 50.0);
        }
    }
}

/// The frames a run of `e` accepted (their indices, from the per-frame lines).
fn accepted_frames(e: &NaipEval, frames: usize, position_prior: bool) -> Vec<usize> {
    let mut accepted = Vec::new();
    e.run_with(frames, 2024, position_prior, &mut |l| {
        eprintln!("{}: {l}", if position_prior { "prior" } else { "no prior" });
        if let Some(rest) = l.strip_prefix("frame ")
            && let Some((i, what)) = rest.split_once(':')
            && what.trim_start().starts_with("accepted")
            && let Ok(i) = i.trim().parse()
        {
            accepted.push(i);
        }
    })
    .expect("run");
    accepted
}

/// A position prior never makes a heading search fail that succeeds without one: with the heading
/// 30 deg off (sigma 30 deg), every frame the search without a position prior fixes (the area
/// search of the whole map at the barometer's altitude) is fixed with the 100 m prior too, whose
/// last resort is the same area search over its own window. Measured (release, 40 frames): 30
/// without the prior, 34 with it, none lost.
#[test]
fn a_position_prior_never_loses_a_frame_the_search_without_one_fixes() {
    let mut e = eval();
    e.yaw_error_deg = 30.0;
    e.yaw_sigma_deg = 30.0;
    let frames = 12;
    let without = accepted_frames(&e, frames, false);
    let with = accepted_frames(&e, frames, true);
    eprintln!("accepted without a position prior {without:?}, with one {with:?}");
    assert!(
        without.len() >= 6,
        "the search without a prior fixed {without:?}"
    );
    let lost: Vec<_> = without.iter().filter(|i| !with.contains(i)).collect();
    assert!(
        lost.is_empty(),
        "frames lost to the position prior: {lost:?}"
    );
}

/// The detector seam with a second family: a `.vnm` map of ORB-like binary features
/// (`vision::orb`, matched by Hamming distance) built by the product's map build from the 2009
/// photo (`visnav map build --detector orb`), its header recording the family, and the 2014
/// frames fixed through the same `FixEngine` with features only (no area fallback, so every fix is
/// the detector's). SURF is the product's detector; this one shows that another family builds a
/// map and fixes through the engine's stages, its chance check and its resection unchanged, and
/// says what it measures.
#[test]
fn a_second_detector_builds_a_map_and_fixes_through_the_engine() {
    use std::sync::Arc;
    use visnav::fix::{FixEngine, MapReference};
    use visnav::map::{BuildSpec, HeightSource};
    use visnav::vision::OrbParams;
    let features_only = FixParams {
        area_matching: AreaMatching::Off,
        ..FixParams::default()
    };
    let mut e = eval_with(features_only.clone());
    let maps = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("sitl/maps");
    let mut spec = BuildSpec::new(
        vec![maps.join("naip_nd_2009.tif")],
        HeightSource::ConstantAmsl(NAIP_GROUND_M),
    );
    spec.orb = Some(OrbParams::default());
    let map = MapReference::build_temporary(&spec, None).expect("ORB map");
    let header = map.map().header();
    assert!(header.orb.is_some(), "the header records the family");
    assert_eq!(header.descriptor_kind().to_string(), "binary-256");
    assert!(
        header.n_features() > 1000,
        "{} features",
        header.n_features()
    );
    let camera = *e.engine().camera();
    *e.engine_mut() = FixEngine::new(Arc::new(map), camera, features_only).expect("engine");
    let s = run_logged(&e, 40);
    eprintln!(
        "ORB: {} of {} accepted, median {:.1} m, wrong {}",
        s.accepted, s.frames, s.err_h_m.median, s.wrong_fixes
    );
    // Measured (40 frames, seed 2024): 14 accepted (SURF alone: 75 % of 100), median 23.0 m
    // (4.6 map px), p90 35.6 m, 0 beyond 3 sigma, 0 more than 50 m off in 3-D.
    assert!(s.accepted >= 8, "{} ORB fixes", s.accepted);
    assert!(
        s.wrong_beyond_sigma <= 1,
        "{} ORB fixes outside 3 sigma",
        s.wrong_beyond_sigma
    );
}
