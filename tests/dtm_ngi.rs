//! DTM navigation on real frames with measured poses: NGI 3324C frame 0182's pose from
//! its Lucas-Kanade flow to frame 0184 and the 24 m DEM alone, no orthophoto
//! (`visnav::sitl::dtm_eval::ngi_dtm`), from first guesses some hundreds of metres and degrees
//! off: from the bench's guess (183 m, 1 deg) the error inside 3 sigma of the solution's own
//! covariance and far below the guess's; from guesses up to 1 km and 10 deg off the same or a
//! refusal, never a wrong pose accepted. And flat ground (a real NAIP photo laid flat): every pair refused, by the relief
//! screen and, with it off, by the conditioning check. Skipped with a SKIP line when
//! ../shared/data is absent.

use std::path::Path;

use visnav::sitl::dtm_eval::{
    GuessError, NGI_GUESS, NgiOrder, WRONG_POSE_CHI2_3D, flat_dtm, ngi_dtm, ngi_sweep,
};

fn data(rel: &str) -> Option<std::path::PathBuf> {
    let p = Path::new(env!("CARGO_MANIFEST_DIR")).join(rel);
    if p.exists() {
        Some(p)
    } else {
        eprintln!("SKIP: {} not found (shared test data absent)", p.display());
        None
    }
}

#[test]
fn ngi_first_pose_from_flow_and_the_dem_is_inside_its_sigma() {
    let Some(dir) = data("../shared/data/ngi_3324c") else {
        return;
    };
    let r = ngi_dtm(&dir, &NGI_GUESS, NgiOrder::Forward)
        .expect("NGI DTM navigation from the bench's guess");
    eprintln!(
        "guess {:.0} m off: error {:.1} m ({:.2} sigma, claimed {:.1} m along it), sigma0 {:.2}, attitude {:.3} deg (sigma {:.3}), {} flow vectors, {} inliers, {} in {} iterations",
        r.guess_err_m,
        r.err_norm_m,
        r.err_over_sigma,
        r.sigma_along_err_m,
        r.sigma0,
        r.att_err_deg,
        r.att_sigma_deg,
        r.tracks,
        r.inliers,
        r.method,
        r.iterations
    );
    assert!(r.inliers >= 100, "{} inliers", r.inliers);
    assert!(r.err_over_sigma <= 3.0, "{} sigma", r.err_over_sigma);
    assert!(
        r.err_norm_m <= 0.2 * r.guess_err_m,
        "error {} m from a guess {} m off",
        r.err_norm_m,
        r.guess_err_m
    );
    assert!(
        r.att_err_deg <= 3.0 * r.att_sigma_deg,
        "attitude {} deg",
        r.att_err_deg
    );
}

/// Guesses 200, 600 and 1000 m off in four directions, with heading errors of 0, 5 and -10 deg
/// (and 0.3 deg of tilt, 8 % of the distance in height): every solution accepted is inside its
/// 3 sigma; from 200 m and up to 5 deg every guess is solved. (Measured over 280 guesses of
/// 100-1000 m and 0-10 deg: none accepted wrong; all solved up to 200 m and 5 deg; all refused
/// from 1000 m.)
#[test]
fn no_guess_gives_a_wrong_pose() {
    let Some(dir) = data("../shared/data/ngi_3324c") else {
        return;
    };
    let (mut solved, mut refused) = (0, 0);
    for dist in [200.0, 600.0, 1000.0] {
        for yaw in [0.0, 5.0, -10.0] {
            for k in 0..4 {
                let a = f64::from(k) * std::f64::consts::FRAC_PI_2 + 0.4;
                let sign = if k % 2 == 0 { 1.0 } else { -1.0 };
                let g = GuessError {
                    offset_m: [dist * a.cos(), dist * a.sin(), 0.08 * dist * sign],
                    turn_deg: [0.3, -0.3, yaw],
                    motion_err_m: [0.03 * dist, -0.02 * dist, 0.01 * dist],
                };
                match ngi_dtm(&dir, &g, NgiOrder::Forward) {
                    Ok(r) => {
                        solved += 1;
                        assert!(
                            r.err_over_sigma <= 3.0,
                            "guess {dist} m, {yaw} deg, direction {k}: accepted {:.0} m wrong ({:.1} sigma)",
                            r.err_norm_m,
                            r.err_over_sigma
                        );
                    }
                    Err(e) => {
                        refused += 1;
                        assert!(
                            !(dist <= 200.0 && yaw.abs() <= 5.0),
                            "guess {dist} m, {yaw} deg, direction {k} refused: {e}"
                        );
                    }
                }
            }
        }
    }
    eprintln!("{solved} solved within 3 sigma, {refused} refused, none wrong");
}

/// Both frame orders (0182 from its flow to 0184, and 0184 from its flow back to 0182): the
/// bench's guess gives a pose inside 3 sigma on every axis and jointly, and guesses 200, 400 and
/// 600 m off in 8 directions give either such a pose or a refusal. (Measured: 39 of 48 solved,
/// the reverse order's errors 7-30 m at up to 2.55 sigma along the error, squared Mahalanobis
/// distance at most 6.9; the 9 refusals are guesses 400-600 m off whose flow the solution does
/// not explain.)
#[test]
fn both_frame_orders_give_no_pose_beyond_3_sigma() {
    let Some(dir) = data("../shared/data/ngi_3324c") else {
        return;
    };
    for order in [NgiOrder::Forward, NgiOrder::Reverse] {
        let r =
            ngi_dtm(&dir, &NGI_GUESS, order).expect("NGI DTM navigation from the bench's guess");
        eprintln!(
            "{}: error {:.1} m, {:.2} sigma along it, squared Mahalanobis {:.1}, largest axis {:.2} sigma",
            order.label(),
            r.err_norm_m,
            r.err_over_sigma,
            r.err_mahalanobis2,
            r.err_axis_sigmas
        );
        assert!(r.err_axis_sigmas <= 3.0, "{}: {r:?}", order.label());
        assert!(
            r.err_mahalanobis2 <= WRONG_POSE_CHI2_3D,
            "{}: {r:?}",
            order.label()
        );
        let cases = ngi_sweep(&dir, order, &[200.0, 400.0, 600.0], 8).expect("sweep");
        let solved = cases.iter().filter(|c| c.solved.is_some()).count();
        for c in &cases {
            assert!(
                !c.wrong(),
                "{} guess {} m at {:.0} deg accepted outside 3 sigma: {:?}",
                order.label(),
                c.offset_m,
                c.direction_deg,
                c.solved
            );
        }
        let near = cases
            .iter()
            .filter(|c| c.offset_m <= 200.0 && c.solved.is_some())
            .count();
        eprintln!(
            "{}: {solved} of {} guesses solved inside 3 sigma, the rest refused",
            order.label(),
            cases.len()
        );
        assert_eq!(
            near,
            8,
            "{}: every guess 200 m off is solved",
            order.label()
        );
    }
}

#[test]
fn flat_ground_is_never_accepted() {
    let Some(photo) = data("../shared/data/bench/naip2014_1280x960.png") else {
        return;
    };
    let f = flat_dtm(&photo, 6).expect("flat pairs");
    eprintln!("{f:?}");
    assert!(f.tracks_mean >= 100.0, "{} flow vectors", f.tracks_mean);
    assert_eq!(f.accepted, 0, "{:?}", f.reasons);
    assert_eq!(f.accepted_unscreened, 0, "{:?}", f.reasons);
    assert!(f.reasons.iter().any(|r| r.contains("flat ground")));
    assert!(
        f.reasons
            .iter()
            .any(|r| r.contains("ill-conditioned") || r.contains("unobservable"))
    );
}
