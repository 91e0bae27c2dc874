//! `visnav bench surf`: JSON output on a bundled image, and a clear error for a missing image.

use std::process::Command;

#[test]
fn bench_surf_json_on_bundled_map() {
    let img = concat!(env!("CARGO_MANIFEST_DIR"), "/sitl/maps/naip_nd_2014.tif");
    let out = Command::new(env!("CARGO_BIN_EXE_visnav"))
        .args([
            "bench", "surf", "--json", "--runs", "1", "--mode", "upright", "--image", img,
        ])
        .output()
        .expect("run visnav");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let doc: serde_json::Value = serde_json::from_slice(&out.stdout).expect("JSON on stdout");
    let rows = doc["surf"].as_array().expect("surf rows");
    assert_eq!(rows.len(), 2, "1 thread and all threads");
    for r in rows {
        assert_eq!(r["width"], 934);
        assert_eq!(r["mode"], "upright");
        assert!(r["features"].as_u64().unwrap() > 500);
        assert!(r["median_ms"].as_f64().unwrap() > 0.0);
    }
    assert_eq!(rows[0]["threads"], 1);
}

#[test]
fn bench_surf_missing_image_is_a_clear_error() {
    let out = Command::new(env!("CARGO_BIN_EXE_visnav"))
        .args(["bench", "surf", "--image", "/nonexistent/frame.png"])
        .output()
        .expect("run visnav");
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("/nonexistent/frame.png"), "{err}");
}
