//! The fix through the GPU path against the fix through the CPU (the target: fix results identical
//! within 0.1 map px on the fix bench): the NAIP cross-date fix bench (`visnav_sim::fixeval`:
//! frames rendered from the 2014 photo, the map built from 2009, priors with errors), each frame
//! fixed twice by the same engine, once with the CPU's features and once with the GPU's
//! (`FixEngine::set_feature_backend`). Both must accept or reject the same frames, and the
//! accepted positions must agree within 0.1 map px. Needs an adapter (see gpu_surf.rs: SKIP
//! outside CI without one).
#![allow(clippy::expect_used)] // a test: a failed expect is a failed test

use std::path::Path;
use std::sync::Arc;

use visnav_core::fix::FixParams;
use visnav_core::rng::Rng;
use visnav_core::vision::CpuFeatures;
use visnav_gpu::{AdapterPolicy, GpuSurf};
use visnav_sim::fixeval::NaipEval;

/// Frames fixed (each twice); about 1 s each on lavapipe.
const FRAMES: u64 = 16;

#[test]
fn fixes_through_the_gpu_path_equal_the_cpus() {
    let gpu = match GpuSurf::new(AdapterPolicy::AllowSoftware) {
        Ok(g) => Arc::new(g),
        Err(e) if std::env::var_os("CI").is_none() => {
            println!("SKIP: {e}");
            return;
        }
        Err(e) => panic!("CI must have a GPU adapter (lavapipe from scripts/setup.sh): {e}"),
    };
    println!("adapter: {}", gpu.adapter());
    let maps = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../sitl/maps");
    let mut e = NaipEval::new(&maps, FixParams::default()).expect("the NAIP fix bench");
    let gsd_m = e.map_gsd_m();
    let ([x0, y0, x1, y1], margin) = e.frame_area_m();
    let mut rng = Rng::new(2024);
    let (mut both, mut differ, mut worst_px) = (0, 0, 0f64);
    for i in 0..FRAMES {
        let x = x0 + margin + (x1 - x0 - 2.0 * margin) * rng.uniform();
        let y = y0 + margin + (y1 - y0 - 2.0 * margin) * rng.uniform();
        let case = e.random_case(&mut rng, x, y);
        let img = e.frame(&case, i, None).expect("frame");
        let prior = e.prior(&mut rng, &case, i).expect("prior");
        e.engine_mut().set_feature_backend(Arc::new(CpuFeatures));
        let cpu = e.engine().fix(&img, &prior);
        e.engine_mut().set_feature_backend(gpu.clone());
        assert!(e.engine().feature_backend().name().starts_with("gpu: "));
        let g = e.engine().fix(&img, &prior);
        if cpu.accepted != g.accepted {
            differ += 1;
            println!(
                "frame {i}: CPU {} ({}), GPU {} ({})",
                cpu.accepted,
                cpu.reason(),
                g.accepted,
                g.reason()
            );
            continue;
        }
        if cpu.accepted {
            both += 1;
            let m_per_deg = 111_320.0;
            let dn = (g.lat_deg - cpu.lat_deg) * m_per_deg;
            let de = (g.lon_deg - cpu.lon_deg) * m_per_deg * cpu.lat_deg.to_radians().cos();
            worst_px = worst_px.max(dn.hypot(de) / gsd_m);
        }
    }
    println!(
        "{FRAMES} frames: {both} accepted by both, {differ} decided differently, worst position difference {worst_px:.4} map px, GPU fallbacks {}",
        gpu.fallbacks()
    );
    assert_eq!(differ, 0, "frames decided differently");
    assert!(both >= 4, "too few accepted fixes to compare ({both})");
    assert!(worst_px <= 0.1, "positions differ by {worst_px} map px");
    assert_eq!(gpu.fallbacks(), 0);
}
