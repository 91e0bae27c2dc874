//! `visnav check-config` end to end: the example files pass, bad files fail with messages that
//! name the file, the key and the reason.

use std::path::{Path, PathBuf};
use std::process::Command;

fn visnav() -> Command {
    Command::new(env!("CARGO_BIN_EXE_visnav"))
}

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

#[test]
fn every_example_config_passes() {
    let mut n = 0;
    for entry in std::fs::read_dir(repo().join("config")).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().and_then(|e| e.to_str()) != Some("toml") {
            continue;
        }
        let out = visnav().arg("check-config").arg(&path).output().unwrap();
        assert!(
            out.status.success(),
            "{}: {}",
            path.display(),
            String::from_utf8_lossy(&out.stderr)
        );
        n += 1;
    }
    assert!(n >= 4, "expected the four example configs, found {n}");
}

fn check(dir: &Path, text: &str) -> (i32, String) {
    let file = dir.join("bad.toml");
    std::fs::write(&file, text).unwrap();
    let out = visnav().arg("check-config").arg(&file).output().unwrap();
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn bad_configs_are_rejected_with_file_key_and_reason() {
    let dir = tempfile::tempdir().unwrap();
    let ortho = repo().join("sitl/maps/naip_nd_2009.tif");
    let good_map = format!(
        "[camera]\nwidth_px = 640\nheight_px = 480\nhfov_deg = 60.0\n\
         [map]\northo = [\"{}\"]\nground_height_amsl_m = 580.0\n",
        ortho.display()
    );

    // Unknown key.
    let (code, err) = check(
        dir.path(),
        &format!("[link]\nconnection = \"udpin:0.0.0.0:14550\"\nconection_typo = 1\n{good_map}"),
    );
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("bad.toml") && err.contains("conection_typo"),
        "{err}"
    );

    // Bad connection string, out-of-range rate, missing file, both dem and ground height.
    let (code, err) = check(
        dir.path(),
        "[link]\nconnection = \"udpin:0.0.0.0:99999\"\n\
         [camera]\nwidth_px = 640\nheight_px = 480\nhfov_deg = 200.0\n\
         [map]\northo = [\"nope.tif\"]\ndem = \"nope_dem.tif\"\nground_height_amsl_m = 3.0\n\
         [nav.imu]\ngyro_arw_deg_sqrt_h = -1.0\n\
         [output]\nrate_hz = 500.0\nmodes = [\"gps_input\", \"gps_input\"]\n",
    );
    assert_eq!(code, 2, "{err}");
    for needle in [
        "bad.toml",
        "link.connection",
        "99999",
        "map.ortho[0]",
        "nope.tif",
        "map.dem",
        "output.rate_hz",
        "500",
        "output.modes",
        "camera.hfov_deg",
        "nav.imu.gyro_arw_deg_sqrt_h",
    ] {
        assert!(err.contains(needle), "missing {needle:?} in:\n{err}");
    }

    // Wrong type.
    let (code, err) = check(
        dir.path(),
        &format!("[link]\nconnection = 14550\n{good_map}"),
    );
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("connection"), "{err}");

    // A file that exists but is not a GeoTIFF: check-config opens the map data and names it.
    let not_tiff = dir.path().join("not_a_tiff.tif");
    std::fs::write(&not_tiff, b"this is not a TIFF file").unwrap();
    let (code, err) = check(
        dir.path(),
        &format!(
            "[link]\nconnection = \"udpin:0.0.0.0:14550\"\n\
             [camera]\nwidth_px = 640\nheight_px = 480\nhfov_deg = 60.0\n\
             [map]\northo = [\"{}\"]\nground_height_amsl_m = 580.0\n",
            not_tiff.display()
        ),
    );
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("map.ortho[0]") && err.contains("not_a_tiff.tif"),
        "{err}"
    );

    // Missing file is a plain error, not a panic.
    let out = visnav()
        .arg("check-config")
        .arg(dir.path().join("absent.toml"))
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("absent.toml"));
}

#[test]
fn every_subcommand_has_help() {
    let out = visnav().arg("--help").output().unwrap();
    assert!(out.status.success());
    let text = String::from_utf8_lossy(&out.stdout).into_owned();
    // Subcommand names are listed as the first word of indented lines under "Commands:".
    let cmds: Vec<String> = text
        .lines()
        .skip_while(|l| !l.starts_with("Commands:"))
        .skip(1)
        .take_while(|l| l.starts_with("  "))
        .filter_map(|l| l.split_whitespace().next().map(str::to_string))
        .filter(|c| c != "help")
        .collect();
    for want in ["check-config", "sim", "bench", "run"] {
        assert!(cmds.contains(&want.to_string()), "{want} missing: {text}");
    }
    for c in cmds {
        let out = visnav().arg(&c).arg("--help").output().unwrap();
        assert!(out.status.success(), "visnav {c} --help failed");
        assert!(
            String::from_utf8_lossy(&out.stdout).contains("Usage:"),
            "visnav {c} --help"
        );
    }
}
