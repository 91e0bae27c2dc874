//! GPU matching against the CPU matcher (`visnav_core::vision::match_features`) on real features:
//! the bench's 640x480 NAIP frame against its 1280x960 one (SKIP when ../shared/data is absent)
//! and the bundled NAIP 2014 map against itself shifted; brute force with the ratio test, with the
//! spatial gate (some predictions not finite), with the mutual check, and without the Laplacian
//! gate; SURF-64 and SURF-128. The matches must be the CPU's: the same pairs, distances within
//! 1e-5.
//!
//! Needs a GPU adapter (lavapipe is enough); without one the test prints SKIP, except under CI.

#![allow(clippy::expect_used)] // a test: a failed expect is a failed test

use std::path::{Path, PathBuf};

use visnav_core::vision::{
    DescriptorKind, Features, GrayImage, Match, MatchParams, Surf, SurfParams, match_features,
};
use visnav_gpu::{AdapterPolicy, GpuSurf};
use visnav_io::image_file::GrayImageFile;

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn gpu() -> Option<GpuSurf> {
    match GpuSurf::new(AdapterPolicy::AllowSoftware) {
        Ok(g) => Some(g),
        Err(e) if std::env::var_os("CI").is_none() => {
            println!("SKIP: {e}");
            None
        }
        Err(e) => panic!("CI must have a GPU adapter (lavapipe from scripts/setup.sh): {e}"),
    }
}

/// (name, query, train, the query's predicted train positions: the true ones, every 7th
/// not finite).
fn pairs(surf: &Surf) -> Vec<(String, Features, Features, Vec<[f32; 2]>)> {
    let mut out = Vec::new();
    let map = GrayImage::load(&repo().join("sitl/maps/naip_nd_2014.tif")).expect("NAIP map");
    let (w, h) = (map.width(), map.height());
    // The map's lower right part against its upper left part, 40 px apart.
    let a = map.crop(0, 0, w - 40, h - 40).expect("crop");
    let b = map.crop(40, 40, w - 40, h - 40).expect("crop");
    let (fa, fb) = (surf.detect_and_describe(&a), surf.detect_and_describe(&b));
    let pred = fa
        .keypoints
        .iter()
        .enumerate()
        .map(|(i, k)| {
            if i % 7 == 3 {
                [f32::NAN, 0.0]
            } else {
                [k.x - 40.0, k.y - 40.0]
            }
        })
        .collect();
    out.push(("NAIP map, shifted 40 px".to_string(), fa, fb, pred));
    let bench = repo().join("../shared/data/bench");
    let (p640, p1280) = (
        bench.join("naip2014_640x480.png"),
        bench.join("naip2014_1280x960.png"),
    );
    if p640.is_file() && p1280.is_file() {
        let q = surf.detect_and_describe(&GrayImage::load(&p640).expect("bench"));
        let t = surf.detect_and_describe(&GrayImage::load(&p1280).expect("bench"));
        // No known relation between the frames: predictions at the query's own position scaled.
        let pred = q.keypoints.iter().map(|k| [k.x * 2.0, k.y * 2.0]).collect();
        out.push(("bench 640x480 against 1280x960".to_string(), q, t, pred));
    } else {
        println!("SKIP: the bench frames in {} are absent", bench.display());
    }
    out
}

fn same(name: &str, cpu: &[Match], gpu: &[Match]) {
    assert_eq!(
        cpu.len(),
        gpu.len(),
        "{name}: {} CPU matches, {} GPU",
        cpu.len(),
        gpu.len()
    );
    for (a, b) in cpu.iter().zip(gpu) {
        assert_eq!((a.query, a.train), (b.query, b.train), "{name}");
        assert!(
            (a.distance - b.distance).abs() <= 1e-5,
            "{name}: {a:?} {b:?}"
        );
        let second = if a.second_distance.is_finite() {
            (a.second_distance - b.second_distance).abs() <= 1e-5
        } else {
            !b.second_distance.is_finite()
        };
        assert!(second, "{name}: {a:?} {b:?}");
    }
}

#[test]
fn gpu_matches_are_the_cpus() {
    let Some(g) = gpu() else { return };
    // SURF-128 too: its longer rows once hit llvmpipe's loop limit beyond 3495 train rows.
    let mut all = pairs(&Surf::new(SurfParams::default()).expect("params"));
    let surf128 = Surf::new(SurfParams {
        descriptor: DescriptorKind::Surf128,
        ..SurfParams::default()
    })
    .expect("params");
    all.extend(
        pairs(&surf128)
            .into_iter()
            .take(1)
            .map(|(n, q, t, p)| (format!("{n}, SURF-128"), q, t, p)),
    );
    for (name, q, t, pred) in all {
        let cases = [
            ("ratio 0.8", MatchParams::default(), None),
            (
                "gate 30 px, ratio 1",
                MatchParams {
                    ratio: 1.0,
                    spatial_radius_px: Some(30.0),
                    ..MatchParams::default()
                },
                Some(pred.as_slice()),
            ),
            (
                "gate 100 px, mutual",
                MatchParams {
                    spatial_radius_px: Some(100.0),
                    mutual: true,
                    ..MatchParams::default()
                },
                Some(pred.as_slice()),
            ),
            (
                "no Laplacian gate, mutual",
                MatchParams {
                    laplacian_gate: false,
                    mutual: true,
                    ..MatchParams::default()
                },
                None,
            ),
        ];
        for (case, p, pr) in cases {
            let cpu = match_features(&q, &t, &p, pr).expect("CPU matching");
            let gpu = g.match_features(&q, &t, &p, pr).expect("GPU matching");
            println!(
                "{name}, {case}: {} x {} features, {} matches on both",
                q.len(),
                t.len(),
                cpu.len()
            );
            assert!(!cpu.is_empty(), "{name}, {case}: no matches to compare");
            same(&format!("{name}, {case}"), &cpu, &gpu);
        }
    }
}

#[test]
fn inputs_the_cpu_refuses_are_refused() {
    let Some(g) = gpu() else { return };
    let surf = Surf::new(SurfParams::default()).expect("params");
    let (_, q, t, _) = pairs(&surf).into_iter().next().expect("the NAIP pair");
    let gated = MatchParams {
        spatial_radius_px: Some(10.0),
        ..MatchParams::default()
    };
    assert!(g.match_features(&q, &t, &gated, None).is_err());
    let bad_ratio = MatchParams {
        ratio: 0.0,
        ..MatchParams::default()
    };
    assert!(g.match_features(&q, &t, &bad_ratio, None).is_err());
}
