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

#[test]
fn bench_surf_exports_features() {
    let img = concat!(env!("CARGO_MANIFEST_DIR"), "/sitl/maps/naip_nd_2014.tif");
    let dir = std::env::temp_dir().join(format!("visnav-surf-export-{}", std::process::id()));
    let out = Command::new(env!("CARGO_BIN_EXE_visnav"))
        .args([
            "bench", "surf", "--json", "--runs", "1", "--mode", "oriented", "--image", img,
        ])
        .arg("--export-features")
        .arg(&dir)
        .output()
        .expect("run visnav");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let path = dir.join("naip_nd_2014_oriented.json");
    let doc: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&path).expect("exported file")).expect("JSON");
    let kps = doc["keypoints"].as_array().expect("keypoints");
    let desc = doc["descriptors"].as_array().expect("descriptors");
    assert!(kps.len() > 500);
    assert_eq!(kps.len(), desc.len());
    assert_eq!(kps[0].as_array().unwrap().len(), 8);
    let d0: Vec<f64> = desc[0]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    assert_eq!(d0.len(), 64);
    let n: f64 = d0.iter().map(|v| v * v).sum();
    assert!((n - 1.0).abs() < 1e-3, "unit norm, got {n}");
    assert_eq!(doc["params"]["upright"], false);
    let _ = std::fs::remove_dir_all(&dir);
}
