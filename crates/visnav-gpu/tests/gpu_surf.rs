//! The GPU path against the CPU reference on real images: the bundled
//! NAIP 2014 quarter-quad (sitl/maps) and the bench frames (../shared/data/bench, skipped with a
//! printed SKIP when absent).
//!
//! * the integral table is the CPU's, cell for cell;
//! * every response layer equals the CPU's within 1e-5 of the layer's largest magnitude (a GPU
//!   may fuse a multiply-add: the last bit of a float);
//! * at least 98 % of the CPU's keypoints have a GPU keypoint within 0.5 px and 10 % scale whose
//!   descriptor is within 0.05 (Euclidean) of the CPU's, for every descriptor path (oriented and
//!   upright, SURF-36/64/128, with and without `max_features`).
//!
//! Needs a Vulkan (Metal, DX12) adapter; a software one (Mesa's lavapipe, installed by
//! scripts/setup.sh) is enough. Without any adapter the tests print SKIP, except under CI
//! (`CI` set), where they fail: CI must run them.

#![allow(clippy::expect_used)] // a test: a failed expect is a failed test

use std::path::{Path, PathBuf};

use visnav_core::vision::surf::response_layer;
use visnav_core::vision::{DescriptorKind, GrayImage, IntegralImage, Surf, SurfParams};
use visnav_gpu::{AdapterPolicy, GpuSurf};
use visnav_io::image_file::GrayImageFile;

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// The GPU, or None (SKIP) when this machine has no adapter outside CI.
fn gpu() -> Option<GpuSurf> {
    match GpuSurf::new(AdapterPolicy::AllowSoftware) {
        Ok(g) => {
            println!("adapter: {}", g.adapter());
            Some(g)
        }
        Err(e) if std::env::var_os("CI").is_none() => {
            println!("SKIP: {e}");
            None
        }
        Err(e) => panic!("CI must have a GPU adapter (lavapipe from scripts/setup.sh): {e}"),
    }
}

/// The test images: name and image.
fn images() -> Vec<(String, GrayImage)> {
    let mut out = Vec::new();
    let naip = repo().join("sitl/maps/naip_nd_2014.tif");
    out.push((
        "sitl/maps/naip_nd_2014.tif".to_string(),
        GrayImage::load(&naip).expect("the bundled NAIP map"),
    ));
    let bench = repo().join("../shared/data/bench");
    for name in ["naip2014_640x480.png", "naip2014_1280x960.png"] {
        let p = bench.join(name);
        if p.is_file() {
            out.push((name.to_string(), GrayImage::load(&p).expect("bench image")));
        } else {
            println!("SKIP: {} is absent", p.display());
        }
    }
    out
}

/// Every sampling path of the descriptor shader: oriented SURF-64 (rotated cells), upright
/// SURF-64 on the paper's step-2 sampling (upright grid), oriented SURF-36 capped by
/// `max_features` (the 18-sample grid, the spread selection), oriented SURF-128 (per sample),
/// upright SURF-128 (the grid's sign-split sums).
fn params() -> Vec<SurfParams> {
    let oriented = SurfParams::default();
    let upright = SurfParams {
        upright: true,
        n_octave_layers: 3,
        init_sample_step: 2,
        ..SurfParams::default()
    };
    let surf36 = SurfParams {
        descriptor: DescriptorKind::Surf36,
        max_features: Some(500),
        ..SurfParams::default()
    };
    let surf128 = SurfParams {
        descriptor: DescriptorKind::Surf128,
        hessian_threshold: 400.0,
        ..SurfParams::default()
    };
    let upright128 = SurfParams {
        upright: true,
        ..surf128.clone()
    };
    vec![oriented, upright, surf36, surf128, upright128]
}

#[test]
fn the_integral_table_and_every_response_layer_are_the_cpus() {
    let Some(g) = gpu() else { return };
    for (name, img) in images() {
        for p in params() {
            let surf = Surf::new(p.clone()).expect("params");
            let ii = IntegralImage::new(&img);
            let plan = surf.layer_plan(img.width(), img.height());
            let out = g.run(&img, &plan).expect("GPU run");
            assert_eq!(out.integral.as_slice(), ii.data(), "{name}: integral table");
            for (specs, dets) in plan.iter().zip(&out.layers) {
                for (s, det) in specs.iter().zip(dets) {
                    let cpu = response_layer(&ii, s);
                    let scale = cpu.iter().fold(0f32, |m, v| m.max(v.abs())).max(1.0);
                    let worst = cpu
                        .iter()
                        .zip(det)
                        .map(|(a, b)| (a - b).abs())
                        .fold(0f32, f32::max);
                    assert!(
                        worst <= 1e-5 * scale,
                        "{name}: layer {s:?}: worst difference {worst} of {scale}"
                    );
                }
            }
        }
    }
}

#[test]
fn keypoints_and_descriptors_match_the_cpu() {
    let Some(g) = gpu() else { return };
    for (name, img) in images() {
        for p in params() {
            let surf = Surf::new(p.clone()).expect("params");
            let cpu = surf.detect_and_describe(&img);
            let gpu = g.detect_and_describe(&surf, &img).expect("GPU detect");
            let mut matched = 0usize;
            let mut agree = 0usize;
            let mut dists = Vec::new();
            let mut worst_angle = 0f32;
            for (i, k) in cpu.keypoints.iter().enumerate() {
                // The nearest GPU keypoint in position and scale within the tolerances.
                let near = gpu
                    .keypoints
                    .iter()
                    .enumerate()
                    .filter(|(_, q)| {
                        (q.x - k.x).hypot(q.y - k.y) <= 0.5 && (q.size / k.size - 1.0).abs() <= 0.1
                    })
                    .min_by(|(_, a), (_, b)| {
                        let d = |q: &visnav_core::vision::KeyPoint| {
                            (q.x - k.x).hypot(q.y - k.y) + (q.size / k.size).ln().abs()
                        };
                        d(a).total_cmp(&d(b))
                    });
                let Some((j, q)) = near else { continue };
                matched += 1;
                let d = cpu
                    .descriptor(i)
                    .iter()
                    .zip(gpu.descriptor(j))
                    .map(|(x, y)| (x - y) * (x - y))
                    .sum::<f32>()
                    .sqrt();
                dists.push(d);
                if d <= 0.05 {
                    agree += 1;
                }
                let da = (q.orientation_rad - k.orientation_rad).sin().abs();
                worst_angle = worst_angle.max(da);
            }
            dists.sort_by(f32::total_cmp);
            let n = cpu.keypoints.len();
            let worst = dists.last().copied().unwrap_or(0.0);
            let p99 = dists.get(dists.len() * 99 / 100).copied().unwrap_or(0.0);
            println!(
                "{name} ({} upright {} max {:?}): CPU {n} keypoints, GPU {}, matched {matched}, \
                 descriptors within 0.05: {agree}; distance p99 {p99:.2e}, max {worst:.2e}; \
                 orientation max |sin d| {worst_angle:.2e}",
                p.descriptor,
                p.upright,
                p.max_features,
                gpu.keypoints.len()
            );
            assert!(n > 100, "{name}: too few keypoints to judge ({n})");
            assert!(
                agree as f64 >= 0.98 * n as f64,
                "{name} {}: {agree} of {n} keypoints matched with descriptors within 0.05",
                p.descriptor
            );
        }
    }
}

#[test]
fn frames_the_gpu_refuses_are_computed_on_the_cpu_and_counted() {
    let Some(g) = gpu() else { return };
    let surf = Surf::new(SurfParams::default()).expect("params");
    // Wider than the GPU path's 16384 px.
    let wide = GrayImage::from_fn(16_385, 40, |x, y| ((x * 7 + y * 13) % 256) as f32);
    let err = g
        .detect_and_describe(&surf, &wide)
        .expect_err("a side beyond 16384 px");
    assert!(err.to_string().contains("16385 x 40"), "{err}");
    let backend: &dyn visnav_core::vision::FeatureBackend = &g;
    let f = backend.detect_and_describe(&surf, &wide);
    assert_eq!(f.len(), surf.detect_and_describe(&wide).len());
    assert_eq!(g.fallbacks(), 1);
    // A flat frame: no features on either path, and nothing counted.
    let flat = GrayImage::from_fn(320, 240, |_, _| 128.0);
    let f = g
        .detect_and_describe(&surf, &flat)
        .expect("GPU on a flat frame");
    assert!(f.is_empty());
    assert_eq!(g.fallbacks(), 1);
}
