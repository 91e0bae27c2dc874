//! Prints render timings (no assertion on them): the acceptance camera (VGA, 60 deg HFOV) over the
//! bundled NAIP 2014 map with a flat DEM, and over the NGI orthophoto with its gridded DEM (skipped
//! without the shared data). Meaningful numbers need a release build:
//! `cargo test --release --test integration render_timing:: -- --nocapture`.

use std::path::Path;
use visnav::geo::dem::Dem;
use visnav::geo::geotiff::load_geotiff;
use visnav::sitl::render::{
    BlurSpec, ColourMode, NoiseSpec, RenderSpec, RenderTiming, Scene, bench_vga,
};

fn spec() -> RenderSpec {
    RenderSpec {
        seed: 1,
        blur: BlurSpec {
            sigma_px: 0.7,
            motion_length_px: 0.0,
            motion_angle_deg: 0.0,
        },
        noise: NoiseSpec {
            read_dn: 1.5,
            conversion_gain_dn_per_e: 0.04,
        },
        ..RenderSpec::default()
    }
}

fn print(name: &str, t: &RenderTiming) {
    eprintln!(
        "{name}: {}x{} radiance min {:.1} / median {:.1} ms, photometric min {:.1} / median {:.1} ms \
         ({} runs, {:.1} % valid, {} rayon threads)",
        t.width,
        t.height,
        t.radiance_min_ms,
        t.radiance_median_ms,
        t.photometric_min_ms,
        t.photometric_median_ms,
        t.iterations,
        100.0 * t.valid_fraction,
        rayon::current_num_threads()
    );
}

/// Runs per configuration: 10 in release, 2 in the (slow) dev profile.
fn runs() -> usize {
    if cfg!(debug_assertions) { 2 } else { 10 }
}

#[test]
fn timing_flat_and_grid_dem() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let naip = load_geotiff(&root.join("sitl/maps/naip_nd_2014.tif"), None).expect("NAIP 2014");
    let scene = Scene::new(&naip, Dem::flat(580.0).unwrap(), ColourMode::Grey).unwrap();
    for agl in [1200.0, 2500.0] {
        let t = bench_vga(&scene, spec(), agl, runs()).unwrap();
        print(&format!("NAIP flat DEM, {agl} m AGL"), &t);
        assert!(t.valid_fraction > 0.9);
    }
    let ngi = root.join("../shared/data/ngi_3324c");
    if !ngi.join("dem.tif").is_file() {
        eprintln!("SKIP grid DEM timing: {} absent", ngi.display());
        return;
    }
    let dem = visnav::geo::dem::load_dem(&ngi.join("dem.tif"), None).expect("NGI DEM");
    let ortho = load_geotiff(&ngi.join("ngi_ortho_5m_tile1.tif"), None).expect("NGI ortho");
    let scene = Scene::new(&ortho, dem, ColourMode::Grey).unwrap();
    for agl in [1200.0, 2500.0] {
        let t = bench_vga(&scene, spec(), agl, runs()).unwrap();
        print(&format!("NGI grid DEM (24 m), {agl} m AGL"), &t);
        assert!(t.valid_fraction > 0.5);
    }
}
