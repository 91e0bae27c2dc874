//! `visnav map compare` / `map::coreg` on real imagery: how well the NAIP years are registered to
//! each other. These figures bound the cross-date fix accuracy (docs/fix.md, "What the data
//! allow"): a fix is registered to the map's year, the truth to the camera's.

use std::path::{Path, PathBuf};
use std::process::Command;

use visnav::geo::geotiff::load_geotiff;
use visnav::map::coreg::{CoregParams, coregister};

fn repo(p: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(p)
}

#[test]
fn naip_2009_and_2014_disagree_by_about_a_pixel_over_a_footprint() {
    let a = load_geotiff(&repo("sitl/maps/naip_nd_2009.tif"), None).expect("2009");
    let b = load_geotiff(&repo("sitl/maps/naip_nd_2014.tif"), None).expect("2014");
    let r = coregister(&a, &b, &CoregParams::default()).expect("coregister");
    eprintln!(
        "2009 -> 2014: {} of {} patches, shift median {:.2} px, windows {} median {:.2} px max {:.2} px, median shift ({:+.2}, {:+.2}) m",
        r.patches_matched,
        r.patches_tried,
        r.shift_px.median,
        r.windows.len(),
        r.window_shift_px.median,
        r.window_shift_px.max,
        r.median_dx_m,
        r.median_dy_m
    );
    // Measured: 35 of 3626 patches (the lakes and fields changed), per patch 1.33 px median,
    // over 1.5 km windows 0.92 px median, 1.27 px max.
    assert!(r.patches_matched >= 20, "{} patches", r.patches_matched);
    assert!(!r.windows.is_empty());
    assert!(
        (0.6..=2.0).contains(&r.window_shift_px.median),
        "window shift {:?} px",
        r.window_shift_px
    );
    // The same image against itself: no shift.
    let same = coregister(&b, &b, &CoregParams::default()).expect("self");
    assert!(same.patches_matched > 1000);
    assert!(same.shift_px.p90 < 0.05, "{:?}", same.shift_px);
    assert!(
        same.window_shift_px.max < 0.02,
        "{:?}",
        same.window_shift_px
    );
}

#[test]
fn naip_2009_and_2010_agree_better_than_2009_and_2014() {
    let dir = repo("../shared/data/naip_nd");
    let f2010 = dir.join("m_4709963_se_14_1_20100629.tif");
    if !f2010.exists() {
        eprintln!("skipped: {} is absent", f2010.display());
        return;
    }
    let a = load_geotiff(&repo("sitl/maps/naip_nd_2009.tif"), None).expect("2009");
    let b = load_geotiff(&f2010, None).expect("2010");
    let r = coregister(&a, &b, &CoregParams::default()).expect("coregister");
    eprintln!(
        "2009 -> 2010: {} patches, windows {} median {:.2} px",
        r.patches_matched,
        r.windows.len(),
        r.window_shift_px.median
    );
    // Measured: 372 patches (ten times 2014's: less changed), 0.64 px over 1.5 km windows.
    assert!(r.patches_matched >= 200, "{} patches", r.patches_matched);
    assert!(
        r.window_shift_px.median < 0.85,
        "window shift {:?} px",
        r.window_shift_px
    );
}

fn visnav(args: &[&Path]) -> std::process::Output {
    let mut c = Command::new(env!("CARGO_BIN_EXE_visnav"));
    c.args(["map", "compare"]);
    for a in args {
        c.arg(a);
    }
    c.output().expect("run visnav")
}

#[test]
fn map_compare_cli_reports_json_and_names_a_bad_file() {
    let m2009 = repo("sitl/maps/naip_nd_2009.tif");
    let m2014 = repo("sitl/maps/naip_nd_2014.tif");
    let out = Command::new(env!("CARGO_BIN_EXE_visnav"))
        .args(["map", "compare", "--json"])
        .arg(&m2009)
        .arg(&m2014)
        .output()
        .expect("run visnav");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).expect("JSON");
    assert!(v["patches_matched"].as_u64().unwrap_or(0) >= 20, "{v}");
    assert!(v["window_shift_px"]["median"].as_f64().is_some(), "{v}");
    assert_eq!(v["patches"].as_array().map(Vec::len), Some(0));

    let bad = repo("Cargo.toml");
    let out = visnav(&[&m2009, &bad]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("Cargo.toml"), "{err}");
    assert!(!err.contains("panicked"), "{err}");
}
