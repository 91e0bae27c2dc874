//! Quality guards for SURF on real imagery (the bundled NAIP maps, sitl/maps): the repeatability and
//! matching-score protocol of Mikolajczyk & Schmid (src/vision/eval.rs) under rotation, scale,
//! blur, noise, photometric change and across years (2009 vs 2014). Thresholds are conservative
//! (well below the values in docs/surf.md) so that only a real regression fails.

use std::path::PathBuf;

use visnav::vision::eval::{self, Change, ImagePair, PairScore};
use visnav::vision::{
    DescriptorKind, GrayImage, GrayImageFile, MatchParams, Surf, SurfParams, match_features,
};

fn map(year: u32) -> GrayImage {
    let p = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(format!("sitl/maps/naip_nd_{year}.tif"));
    GrayImage::load(&p).expect("bundled NAIP map readable")
}

const WINDOW: (usize, usize, usize, usize) = (307, 202, 320, 320);

fn surf(upright: bool, descriptor: DescriptorKind) -> Surf {
    Surf::new(SurfParams {
        upright,
        descriptor,
        ..SurfParams::default()
    })
    .unwrap()
}

fn score(s: &Surf, pair: &ImagePair) -> PairScore {
    let f1 = s.detect_and_describe(&pair.img1);
    let f2 = s.detect_and_describe(&pair.img2);
    let sc = eval::score_pair(
        &f1,
        &f2,
        &pair.h12,
        (pair.img1.width(), pair.img1.height()),
        (pair.img2.width(), pair.img2.height()),
    )
    .unwrap();
    eprintln!(
        "{:<28} n1 {:>4} n2 {:>4} rep {:.3} ms {:.3}",
        pair.label, sc.n1, sc.n2, sc.repeatability, sc.matching_score
    );
    sc
}

fn check(changes: &[(Change, f64, f64)], s: &Surf) {
    let m14 = map(2014);
    let mut failures = Vec::new();
    for &(c, min_rep, min_ms) in changes {
        let pair = eval::make_pair(&m14, WINDOW, c).unwrap();
        let sc = score(s, &pair);
        assert!(
            sc.n1 >= 50 && sc.n2 >= 50,
            "{}: too few features {sc:?}",
            pair.label
        );
        if sc.repeatability < min_rep || sc.matching_score < min_ms {
            failures.push(format!(
                "{}: repeatability {:.3} (min {min_rep}), matching score {:.3} (min {min_ms})",
                pair.label, sc.repeatability, sc.matching_score
            ));
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
}

#[test]
fn rotation_invariant_surf64_under_rotation() {
    let r = |deg| Change::Rotation { deg };
    check(
        &[
            (r(0.0), 0.95, 0.90),
            (r(15.0), 0.50, 0.30),
            (r(45.0), 0.50, 0.30),
            (r(90.0), 0.60, 0.40),
            (r(135.0), 0.50, 0.30),
            (r(180.0), 0.60, 0.40),
        ],
        &surf(false, DescriptorKind::Surf64),
    );
}

#[test]
fn rotation_invariant_surf64_under_scale() {
    let z = |factor| Change::Zoom { factor };
    check(
        &[
            (z(0.5), 0.30, 0.15),
            (z(0.7), 0.40, 0.20),
            (z(1.4), 0.40, 0.20),
            (z(2.0), 0.30, 0.15),
        ],
        &surf(false, DescriptorKind::Surf64),
    );
}

#[test]
fn upright_surf64_under_blur_noise_and_light() {
    check(
        &[
            (Change::Blur { sigma: 1.0 }, 0.50, 0.35),
            (Change::Blur { sigma: 2.0 }, 0.30, 0.15),
            (Change::Noise { sigma: 5.0 }, 0.50, 0.35),
            (Change::Noise { sigma: 10.0 }, 0.35, 0.20),
            (
                Change::Photometric {
                    gain: 0.6,
                    bias: 0.0,
                },
                0.50,
                0.40,
            ),
            (
                Change::Photometric {
                    gain: 1.3,
                    bias: -20.0,
                },
                0.60,
                0.50,
            ),
        ],
        &surf(true, DescriptorKind::Surf64),
    );
}

#[test]
fn surf36_and_surf128_under_rotation_and_blur() {
    for kind in [DescriptorKind::Surf36, DescriptorKind::Surf128] {
        check(
            &[
                (Change::Rotation { deg: 30.0 }, 0.50, 0.25),
                (Change::Blur { sigma: 1.0 }, 0.50, 0.30),
            ],
            &surf(false, kind),
        );
    }
}

/// 2009 map against 2014 imagery, identity geometry: the cross-date condition of map matching.
#[test]
fn cross_year_repeatability_and_gated_matching() {
    let (x0, y0, w, h) = WINDOW;
    let pair = ImagePair {
        label: "2009 vs 2014".into(),
        img1: map(2009).crop(x0, y0, w, h).unwrap(),
        img2: map(2014).crop(x0, y0, w, h).unwrap(),
        h12: nalgebra::Matrix3::identity(),
    };
    let s = surf(true, DescriptorKind::Surf64);
    let sc = score(&s, &pair);
    // Measured 0.154 / 0.024 (docs/surf.md): the cross-date change is hard for every detector
    // (OpenCV SIFT: repeatability 0.040 on the same pair).
    assert!(sc.repeatability >= 0.10, "{sc:?}");
    assert!(sc.matching_score >= 0.01, "{sc:?}");

    // Unconstrained ratio-test matching finds almost nothing right across years (measured 2 of
    // 33, and OpenCV SIFT 0 of 6 on the same pair): the navigator gates the search around the
    // INS prediction. With a 15 px gate around a prediction 4 px off, measured 16 correct
    // (within 3 px) of 79; a random candidate of the gate would be correct with probability
    // about (3/15)^2 = 0.04, so at least 10 % correct shows the descriptor still carries signal.
    let f1 = s.detect_and_describe(&pair.img1);
    let f2 = s.detect_and_describe(&pair.img2);
    let pred: Vec<[f32; 2]> = f1
        .keypoints
        .iter()
        .map(|k| [k.x + 3.0, k.y - 2.5])
        .collect();
    let params = MatchParams {
        spatial_radius_px: Some(15.0),
        ..MatchParams::default()
    };
    let m = match_features(&f1, &f2, &params, Some(&pred)).unwrap();
    let good = m
        .iter()
        .filter(|m| {
            let (a, b) = (&f1.keypoints[m.query], &f2.keypoints[m.train]);
            (a.x - b.x).hypot(a.y - b.y) < 3.0
        })
        .count();
    eprintln!(
        "cross-year gated ratio matches {} correct {}",
        m.len(),
        good
    );
    assert!(good >= 8, "{good} correct of {}", m.len());
    assert!(
        good as f64 >= 0.10 * m.len() as f64,
        "{good} correct of {}",
        m.len()
    );
}

/// The spatial gate and mutual check keep or improve precision on a rotated pair.
#[test]
fn gated_matching_on_rotated_pair() {
    let pair = eval::make_pair(&map(2014), WINDOW, Change::Rotation { deg: 60.0 }).unwrap();
    let s = surf(false, DescriptorKind::Surf64);
    let f1 = s.detect_and_describe(&pair.img1);
    let f2 = s.detect_and_describe(&pair.img2);
    let truth = |i: usize| {
        let k = &f1.keypoints[i];
        let (u, v) = eval::project(&pair.h12, f64::from(k.x), f64::from(k.y)).unwrap();
        [u as f32, v as f32]
    };
    let correct = |ms: &[visnav::vision::Match]| {
        ms.iter()
            .filter(|m| {
                let p = truth(m.query);
                let k = &f2.keypoints[m.train];
                (k.x - p[0]).hypot(k.y - p[1]) < 3.0
            })
            .count()
    };
    let plain = match_features(&f1, &f2, &MatchParams::default(), None).unwrap();
    let mutual = match_features(
        &f1,
        &f2,
        &MatchParams {
            mutual: true,
            ..Default::default()
        },
        None,
    )
    .unwrap();
    // Predictions off by 10 px, gate radius 25 px.
    let pred: Vec<[f32; 2]> = (0..f1.len())
        .map(|i| {
            let p = truth(i);
            [p[0] + 10.0, p[1] - 5.0]
        })
        .collect();
    let gated = match_features(
        &f1,
        &f2,
        &MatchParams {
            spatial_radius_px: Some(25.0),
            ..Default::default()
        },
        Some(&pred),
    )
    .unwrap();
    let (cp, cm, cg) = (correct(&plain), correct(&mutual), correct(&gated));
    eprintln!(
        "plain {}/{}, mutual {}/{}, gated {}/{}",
        cp,
        plain.len(),
        cm,
        mutual.len(),
        cg,
        gated.len()
    );
    assert!(cp >= 100 && cp as f64 >= 0.85 * plain.len() as f64);
    assert!(cm as f64 >= 0.9 * mutual.len() as f64 && cm >= cp / 2);
    assert!(cg >= cp, "gating must not lose correct matches");
    // The ratio test inside a small gate has fewer competitors, so it accepts more (and a few
    // more wrong) matches; measured 244 of 307.
    assert!(cg as f64 >= 0.7 * gated.len() as f64);
}

/// Upright SURF is more distinctive than rotation-invariant SURF on unrotated imagery, and
/// rotation-invariant SURF is the one that survives rotation.
#[test]
fn upright_versus_oriented() {
    let m14 = map(2014);
    let blur = eval::make_pair(&m14, WINDOW, Change::Blur { sigma: 1.5 }).unwrap();
    let up = score(&surf(true, DescriptorKind::Surf64), &blur);
    let or = score(&surf(false, DescriptorKind::Surf64), &blur);
    assert!(up.matching_score >= or.matching_score, "{up:?} vs {or:?}");
    let rot = eval::make_pair(&m14, WINDOW, Change::Rotation { deg: 90.0 }).unwrap();
    let up = score(&surf(true, DescriptorKind::Surf64), &rot);
    let or = score(&surf(false, DescriptorKind::Surf64), &rot);
    assert!(
        or.matching_score > 2.0 * up.matching_score,
        "{up:?} vs {or:?}"
    );
}

/// The feature cap keeps the strongest keypoints spread over the image.
#[test]
fn feature_cap_spreads_keypoints() {
    let (x0, y0, w, h) = WINDOW;
    let img = map(2014).crop(x0, y0, w, h).unwrap();
    let s = Surf::new(SurfParams {
        upright: true,
        max_features: Some(100),
        ..SurfParams::default()
    })
    .unwrap();
    let f = s.detect_and_describe(&img);
    assert_eq!(f.len(), 100);
    // Every quadrant of the image holds some of them.
    for (qx, qy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
        let n = f
            .keypoints
            .iter()
            .filter(|k| (k.x >= 160.0) as usize == qx && (k.y >= 160.0) as usize == qy)
            .count();
        assert!(n >= 10, "quadrant {qx},{qy}: {n}");
    }
}
