//! The closed loop over a tiled map flown paged (`[closed_loop] mosaic`, `map_tile_m`): a short
//! leg of the long-range scenario (sitl/scenarios/long_range.toml) over a 3 x 2 mosaic of the
//! NAIP tile cut into 4 km squares, eastward across two square edges and a mirror seam. In
//! lock-step the tiles load inline, so the run is the same twice; no tile fails, none is missed by
//! a select, only the first frame meets tiles not yet in memory (nothing is at the start), and
//! fixes are made at the seams.

use std::path::Path;
use std::process::Command;

/// The long-range scenario cut to 150 s east (the GPS off from 30 s), over a 3 x 2 mosaic in
/// 4 km squares, its paths absolute.
fn short_long_range(root: &Path) -> String {
    let text = std::fs::read_to_string(root.join("sitl/scenarios/long_range.toml")).unwrap();
    let head = text.split("[[segments]]").next().unwrap();
    let tail = &text[text.find("[imu]").unwrap()..];
    let abs = |p: &str| format!("{:?}", root.join(p).display().to_string());
    format!("{head}[[segments]]\nkind = \"straight\"\nduration_s = 150.0\n\n{tail}")
        .replace("until_s = 2030.0", "until_s = 150.0")
        .replace(
            "\"../../config/long-range.toml\"",
            &abs("config/long-range.toml"),
        )
        .replace(
            "\"../maps/naip_nd_2014.tif\"",
            &abs("sitl/maps/naip_nd_2014.tif"),
        )
        .replace("mosaic = [10, 12]", "mosaic = [3, 2]")
        .replace("map_tile_m = 10000.0", "map_tile_m = 4000.0")
}

fn sim(scenario: &Path, out: &Path) -> serde_json::Value {
    let res = Command::new(env!("CARGO_BIN_EXE_visnav"))
        .args(["sim", "--json", "--scenario"])
        .arg(scenario)
        .arg("--out")
        .arg(out)
        .output()
        .expect("run visnav sim");
    assert!(
        res.status.success(),
        "visnav sim failed: {}",
        String::from_utf8_lossy(&res.stderr)
    );
    serde_json::from_slice(&res.stdout).expect("JSON summary")
}

#[test]
fn a_paged_tiled_map_flies_across_its_seams_the_same_twice() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let dir = tempfile::tempdir().unwrap();
    let sc = dir.path().join("paged.toml");
    std::fs::write(&sc, short_long_range(root)).unwrap();
    let a = sim(&sc, &dir.path().join("a"));
    let s = &a;
    let p = &s["map_paging"];
    eprintln!("{}", serde_json::to_string_pretty(p).unwrap());
    eprintln!(
        "fix rate {} nav p90 {} control p90 {}",
        s["fix_rate"], s["nav_err_m"]["p90"], s["control_err_m"]["p90"]
    );
    // 3 x 2 copies of 4.67 x 3.62 km in 4 km squares: 4 x 2 or more squares with features.
    assert!(p["tiles"].as_u64().unwrap() >= 8, "{p}");
    assert!(p["area_km2"].as_f64().unwrap() > 90.0, "{p}");
    assert_eq!(p["load_errors"], 0, "{p}");
    assert_eq!(p["misses"], 0, "{p}");
    // Only the first frame meets tiles not yet in memory (nothing is at the start).
    assert_eq!(p["late_frames"], 1, "{p}");
    assert!(p["loads"].as_u64().unwrap() >= 3, "{p}");
    assert!(p["attempts_near_seams"].as_u64().unwrap() >= 10, "{p}");
    assert!(p["fix_rate_near_seams"].as_f64().unwrap() >= 0.8, "{p}");
    assert!(s["fix_rate"].as_f64().unwrap() >= 0.8, "{}", s["fix_rate"]);
    assert!(
        s["nav_err_m"]["p90"].as_f64().unwrap()
            <= 0.1 * s["control_err_m"]["p90"].as_f64().unwrap(),
        "{} against {}",
        s["nav_err_m"]["p90"],
        s["control_err_m"]["p90"]
    );
    // Inline loads in lock-step: the same numbers again.
    let b = sim(&sc, &dir.path().join("b"));
    for key in ["fix_rate", "nav_err_m", "map_paging", "fix_err_m"] {
        let (x, y) = (&a[key], &b[key]);
        if key == "map_paging" {
            for k in [
                "loads",
                "evictions",
                "misses",
                "late",
                "late_frames",
                "attempts_near_seams",
                "fix_rate_near_seams",
            ] {
                assert_eq!(x[k], y[k], "{key}.{k}");
            }
        } else {
            assert_eq!(x, y, "{key}");
        }
    }
}
