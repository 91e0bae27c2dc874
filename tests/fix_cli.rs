//! `visnav fix` end to end: a frame rendered from the 2014 NAIP image against the bundled 2009
//! orthophoto (GeoTIFF map), its JSON keys, exit codes, and clear errors on bad input.

use std::path::{Path, PathBuf};
use std::process::Command;

use nalgebra::Vector3;
use visnav::camera::{Attitude, Mount};
use visnav::geo::dem::Dem;
use visnav::geo::geotiff::load_geotiff;
use visnav::sitl::fixeval::NAIP_GROUND_M;
use visnav::sitl::render::{
    ColourMode, RenderPose, RenderSpec, Renderer, Scene, grid_convergence_rad, vga_camera,
};

fn visnav() -> Command {
    Command::new(env!("CARGO_BIN_EXE_visnav"))
}

fn maps() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("sitl/maps")
}

const VGA_CAMERA: &str = "[camera]\nwidth_px = 640\nheight_px = 480\nhfov_deg = 60.0\n";

/// Renders a 2014 frame 2000 m above the map centre, returns (frame path, camera path, truth
/// lat/lon/alt, attitude).
fn naip_frame(dir: &Path) -> (PathBuf, PathBuf, [f64; 3], Attitude) {
    let cam = load_geotiff(&maps().join("naip_nd_2014.tif"), None).unwrap();
    let scene = Scene::new(&cam, Dem::flat(NAIP_GROUND_M).unwrap(), ColourMode::Grey).unwrap();
    let b = cam.bounds();
    let (x, y) = (0.5 * (b.min_x_m + b.max_x_m), 0.5 * (b.min_y_m + b.max_y_m));
    let crs = cam.crs();
    let gamma = grid_convergence_rad(&crs, x, y).unwrap();
    let att = Attitude::from_deg(4.0, -6.0, 35.0);
    let body = Vector3::new(x, y, NAIP_GROUND_M + 2000.0);
    let pose = RenderPose::from_body(body, &att, &Mount::nadir(), gamma);
    let frame = Renderer::new(vga_camera().unwrap(), RenderSpec::default())
        .unwrap()
        .render(&scene, &pose, 0)
        .unwrap();
    let png = dir.join("frame.png");
    frame.to_gray_image().save(&png).unwrap();
    let camera = dir.join("camera.toml");
    std::fs::write(&camera, VGA_CAMERA).unwrap();
    let (lat, lon) = crs.to_geodetic(x, y).unwrap();
    (png, camera, [lat, lon, NAIP_GROUND_M + 2000.0], att)
}

#[test]
fn fix_json_has_the_issue_keys() {
    let dir = tempfile::tempdir().unwrap();
    let (png, camera, truth, att) = naip_frame(dir.path());
    let out = visnav()
        .args(["fix", "--json", "--ground-height", "580"])
        .arg("--map")
        .arg(maps().join("naip_nd_2009.tif"))
        .arg("--image")
        .arg(&png)
        .arg("--camera")
        .arg(&camera)
        .arg("--attitude")
        .arg(format!(
            "{},{},{}",
            att.roll_rad.to_degrees() + 0.2,
            att.pitch_rad.to_degrees() - 0.2,
            att.yaw_rad.to_degrees() + 0.3
        ))
        .args(["--attitude-sigma-deg", "0.5"])
        .arg("--prior")
        .arg(format!(
            "{},{},{},150",
            truth[0] + 0.0008,
            truth[1] - 0.001,
            truth[2] + 15.0
        ))
        .args(["--prior-sigma-v-m", "30"])
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    eprintln!("{stdout}\n{}", String::from_utf8_lossy(&out.stderr));
    let code = out.status.code().unwrap_or(-1);
    assert!(code == 0 || code == 2, "exit {code}");
    let v: serde_json::Value = serde_json::from_str(&stdout).expect("JSON");
    for k in ["accepted", "reason", "inliers", "method", "ms"] {
        assert!(v.get(k).is_some(), "key {k} missing: {stdout}");
    }
    // Every number present is a number: what a fix does not have is left out, never null.
    assert!(!stdout.contains("null"), "{stdout}");
    let accepted = v["accepted"].as_bool().unwrap();
    assert_eq!(accepted, code == 0);
    if accepted {
        for k in [
            "lat_deg",
            "lon_deg",
            "alt_amsl_m",
            "x_m",
            "y_m",
            "z_m",
            "roll_deg",
            "pitch_deg",
            "yaw_deg",
            "cov_ned_m2",
        ] {
            assert!(v[k].is_number() || v[k].is_array(), "key {k}: {stdout}");
        }
        if v["method"] != "placement" {
            assert!(v["reproj_rms_px"].is_number(), "{stdout}");
        }
        let dlat_m = (v["lat_deg"].as_f64().unwrap() - truth[0]) * 111_000.0;
        let dlon_m = (v["lon_deg"].as_f64().unwrap() - truth[1]) * 111_000.0 * 0.68;
        let sigma_n = v["cov_ned_m2"][0][0].as_f64().unwrap().sqrt();
        assert!(
            dlat_m.abs() <= 3.0 * sigma_n + 5.0,
            "north error {dlat_m} m"
        );
        assert!(dlon_m.abs() <= 3.0 * v["cov_ned_m2"][1][1].as_f64().unwrap().sqrt() + 5.0);
        assert!((v["alt_amsl_m"].as_f64().unwrap() - truth[2]).abs() < 200.0);
    } else {
        assert!(!v["reason"].as_str().unwrap().is_empty());
        // Rejected reports carry no position.
        assert!(v.get("lat_deg").is_none(), "{stdout}");
    }
}

/// `visnav fix --json` of the frame `png` against `map` with the frame's attitude (0.5 deg) and a
/// 150 m position prior at `truth`.
fn fix_json(
    map: &Path,
    png: &Path,
    camera: &Path,
    truth: [f64; 3],
    att: &Attitude,
) -> std::process::Output {
    visnav()
        .args(["fix", "--json"])
        .arg("--map")
        .arg(map)
        .arg("--image")
        .arg(png)
        .arg("--camera")
        .arg(camera)
        .arg("--attitude")
        .arg(format!(
            "{},{},{}",
            att.roll_rad.to_degrees(),
            att.pitch_rad.to_degrees(),
            att.yaw_rad.to_degrees()
        ))
        .args(["--attitude-sigma-deg", "0.5"])
        .arg("--prior")
        .arg(format!("{},{},{},150", truth[0], truth[1], truth[2]))
        .output()
        .unwrap()
}

#[test]
fn map_build_then_fix_against_the_vnm() {
    let dir = tempfile::tempdir().unwrap();
    let (png, camera, truth, att) = naip_frame(dir.path());
    let map = dir.path().join("naip2009.vnm");
    let out = visnav()
        .args(["map", "build", "--ground-height", "580"])
        .arg("--ortho")
        .arg(maps().join("naip_nd_2009.tif"))
        .arg("--out")
        .arg(&map)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let out = fix_json(&map, &png, &camera, truth, &att);
    let stdout = String::from_utf8_lossy(&out.stdout);
    eprintln!("{stdout}");
    let v: serde_json::Value = serde_json::from_str(&stdout).expect("JSON");
    assert_eq!(v["accepted"].as_bool(), Some(out.status.code() == Some(0)));
    assert!(v["ms"].as_f64().is_some());
    // A corrupt map is an error naming the file.
    let bad = dir.path().join("bad.vnm");
    std::fs::write(&bad, b"VNMAP not really").unwrap();
    let out = visnav()
        .arg("fix")
        .arg("--map")
        .arg(&bad)
        .arg("--image")
        .arg(&png)
        .arg("--camera")
        .arg(&camera)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("bad.vnm"));
}

#[test]
fn fix_reports_bad_input_clearly() {
    let dir = tempfile::tempdir().unwrap();
    let camera = dir.path().join("camera.toml");
    std::fs::write(&camera, VGA_CAMERA).unwrap();
    let map = maps().join("naip_nd_2009.tif");
    let run = |extra: &[&str], image: &Path| {
        let out = visnav()
            .arg("fix")
            .arg("--map")
            .arg(&map)
            .arg("--camera")
            .arg(&camera)
            .arg("--image")
            .arg(image)
            .args(extra)
            .output()
            .unwrap();
        (
            out.status.code(),
            String::from_utf8_lossy(&out.stderr).into_owned(),
        )
    };
    // Missing frame: exit 1, the file named.
    let (code, err) = run(
        &["--ground-height", "580"],
        Path::new("/nonexistent/frame.png"),
    );
    assert_eq!(code, Some(1));
    assert!(err.contains("/nonexistent/frame.png"), "{err}");
    // Wrong frame size for the camera.
    let small = dir.path().join("small.png");
    image::GrayImage::new(100, 80).save(&small).unwrap();
    let (code, err) = run(&["--ground-height", "580"], &small);
    assert_eq!(code, Some(1));
    assert!(err.contains("100x80") && err.contains("640x480"), "{err}");
    // Bad prior text.
    let frame = dir.path().join("frame.png");
    image::GrayImage::new(640, 480).save(&frame).unwrap();
    let (code, err) = run(
        &["--ground-height", "580", "--prior", "47.1,abc,900,50"],
        &frame,
    );
    assert_eq!(code, Some(1));
    assert!(err.contains("--prior"), "{err}");
    // A GeoTIFF map without heights.
    let (code, err) = run(&[], &frame);
    assert_eq!(code, Some(1));
    assert!(err.contains("--ground-height"), "{err}");
    // A bad camera key is named.
    std::fs::write(
        &camera,
        "[camera]\nwidth_px = 640\nheight_px = 480\nhfov_dg = 60\n",
    )
    .unwrap();
    let (code, err) = run(&["--ground-height", "580"], &frame);
    assert_eq!(code, Some(1));
    assert!(err.contains("hfov_dg"), "{err}");
    // A blank frame is rejected (exit 2), not an error.
    std::fs::write(&camera, VGA_CAMERA).unwrap();
    let (code, _) = run(&["--ground-height", "580", "--attitude", "0,0,0"], &frame);
    assert_eq!(code, Some(2));
}

/// `visnav map build --detector orb` writes a map of binary features whose header says so,
/// `visnav map info` names the family, and `visnav fix` runs against it (the query's detector
/// comes from the map).
#[test]
fn an_orb_map_is_built_described_and_fixed_against() {
    let dir = tempfile::tempdir().unwrap();
    let (png, camera, truth, att) = naip_frame(dir.path());
    let map = dir.path().join("naip2009_orb.vnm");
    let out = visnav()
        .args([
            "map",
            "build",
            "--ground-height",
            "580",
            "--detector",
            "orb",
        ])
        .arg("--ortho")
        .arg(maps().join("naip_nd_2009.tif"))
        .arg("--out")
        .arg(&map)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let out = visnav().args(["map", "info"]).arg(&map).output().unwrap();
    let info = String::from_utf8_lossy(&out.stdout);
    assert!(info.contains("binary-256 (ORB) descriptors"), "{info}");
    let out = fix_json(&map, &png, &camera, truth, &att);
    let stdout = String::from_utf8_lossy(&out.stdout);
    let v: serde_json::Value = serde_json::from_str(&stdout).expect("JSON");
    // Accepted or refused, the report is whole (the query was described as the map's features
    // are); accepted, it is near the truth.
    assert_eq!(
        v["accepted"].as_bool(),
        Some(out.status.code() == Some(0)),
        "{stdout}"
    );
    assert!(!stdout.contains("kinds differ"), "{stdout}");
    if v["accepted"].as_bool() == Some(true) {
        let (lat, lon) = (
            v["lat_deg"].as_f64().unwrap(),
            v["lon_deg"].as_f64().unwrap(),
        );
        let dn = (lat - truth[0]) * 111_320.0;
        let de = (lon - truth[1]) * 111_320.0 * truth[0].to_radians().cos();
        assert!(dn.hypot(de) < 60.0, "{stdout}");
    }
}
