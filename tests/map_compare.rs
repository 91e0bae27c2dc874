//! `visnav map compare` / `map::coreg` on real imagery: how well the NAIP years are registered to
//! each other. These figures bound the cross-date fix accuracy (docs/fix.md, "What the data
//! allow"): a fix is registered to the map's year, the truth to the camera's.

use std::path::PathBuf;
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
    let (sp, wp) = (
        r.shift_px.expect("patches"),
        r.window_shift_px.expect("windows"),
    );
    eprintln!(
        "2009 -> 2014: {} of {} patches, shift median {:.2} px, windows {} median {:.2} px max {:.2} px, median shift ({:?}, {:?}) m",
        r.patches_matched,
        r.patches_tried,
        sp.median,
        r.windows.len(),
        wp.median,
        wp.max,
        r.median_dx_m,
        r.median_dy_m
    );
    // Measured: 35 of 3626 patches (the lakes and fields changed), per patch 1.33 px median,
    // over 1.5 km windows 1.27 px (4 windows), median shift (+1.73, -3.02) m.
    assert!(r.patches_matched >= 20, "{} patches", r.patches_matched);
    assert!(!r.windows.is_empty());
    assert!((0.6..=2.0).contains(&wp.median), "window shift {wp:?} px");
    // The same image against itself: no shift.
    let same = coregister(&b, &b, &CoregParams::default()).expect("self");
    assert!(same.patches_matched > 1000);
    assert!(
        same.shift_px.expect("patches").p90 < 0.05,
        "{:?}",
        same.shift_px
    );
    assert!(same.window_shift_px.expect("windows").max < 0.02);
}

/// The bundled 2010 image, the seed experiment's map year, is registered to the 2014 camera
/// image better than 2009 is (the reason the scenario uses it).
#[test]
fn naip_2010_is_registered_to_2014_better_than_2009() {
    let load = |f: &str| load_geotiff(&repo(f), None).expect(f);
    let (m2009, m2010, m2014) = (
        load("sitl/maps/naip_nd_2009.tif"),
        load("sitl/maps/naip_nd_2010.tif"),
        load("sitl/maps/naip_nd_2014.tif"),
    );
    let p = CoregParams::default();
    let r = coregister(&m2010, &m2014, &p).expect("coregister");
    let w = r.window_shift_px.expect("windows");
    eprintln!(
        "2010 -> 2014: {} patches, windows {} median {:.2} px",
        r.patches_matched,
        r.windows.len(),
        w.median
    );
    // Measured: 149 patches, 0.35 px over 1.5 km windows (2009 -> 2014: 35, 1.27 px).
    assert!(r.patches_matched >= 100, "{} patches", r.patches_matched);
    assert!(w.median < 0.6, "window shift {w:?} px");
    let r = coregister(&m2009, &m2010, &p).expect("coregister");
    // Measured: 372 patches (ten times 2014's: less changed), 0.49 px.
    assert!(r.patches_matched >= 200, "{} patches", r.patches_matched);
    assert!(r.window_shift_px.expect("windows").median < 0.85);
}

/// `visnav map compare ARGS...`: (success, stdout, stderr).
fn map_compare(args: &[&std::ffi::OsStr]) -> (bool, Vec<u8>, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_visnav"))
        .args(["map", "compare"])
        .args(args)
        .output()
        .expect("run visnav");
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    (out.status.success(), out.stdout, err)
}

#[test]
fn map_compare_cli_reports_json_and_names_a_bad_file() {
    let m2009 = repo("sitl/maps/naip_nd_2009.tif");
    let m2014 = repo("sitl/maps/naip_nd_2014.tif");
    let (ok, stdout, err) = map_compare(&["--json".as_ref(), m2009.as_os_str(), m2014.as_os_str()]);
    assert!(ok, "{err}");
    let v: serde_json::Value = serde_json::from_slice(&stdout).expect("JSON");
    assert!(v["patches_matched"].as_u64().unwrap_or(0) >= 20, "{v}");
    assert!(v["window_shift_px"]["median"].as_f64().is_some(), "{v}");
    assert_eq!(v["patches"].as_array().map(Vec::len), Some(0));

    let bad = repo("Cargo.toml");
    let (ok, _, err) = map_compare(&[m2009.as_os_str(), bad.as_os_str()]);
    assert!(!ok);
    assert!(err.contains("Cargo.toml"), "{err}");
    assert!(!err.contains("panicked"), "{err}");
}
