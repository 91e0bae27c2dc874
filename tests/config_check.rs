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
        // A serial link names the companion computer's port (companion.toml: /dev/ttyAMA0) and
        // its tlog the folder the systemd unit creates (/var/log/visnav); check-config refuses a
        // device or a folder this machine does not have, and only that is allowed. The frames
        // folder of sim-autopilot.toml is written by `visnav sim --write-frames sim-frames`
        // (docs/first-flight.md), so it may be absent too.
        let err = String::from_utf8_lossy(&out.stderr);
        let board_only = |l: &str| {
            (l.starts_with("frames.path: \"../sim-frames\"")
                && l.contains("does not exist")
                && !repo().join("sim-frames").is_dir())
                || (l.starts_with("link.connection: the serial device")
                    && l.contains("No such file or directory"))
                || (l.starts_with("link.tlog:")
                    && l.contains("/var/log/visnav/")
                    && l.contains("in a folder that does not exist")
                    && !Path::new("/var/log/visnav").is_dir())
        };
        let problems: Vec<&str> = err
            .lines()
            .filter(|l| l.starts_with("  "))
            .map(str::trim)
            .collect();
        let absent_board_only = !problems.is_empty() && problems.iter().all(|l| board_only(l));
        assert!(
            out.status.success() || absent_board_only,
            "{}: {}",
            path.display(),
            String::from_utf8_lossy(&out.stderr)
        );
        // It says what the vision does; without a camera, loudly that there is none.
        let text = String::from_utf8_lossy(&out.stdout);
        if out.status.success() {
            let has_frames = std::fs::read_to_string(&path)
                .unwrap()
                .lines()
                .any(|l| l.trim() == "[frames]");
            let want = if has_frames {
                "vision: camera frames from [frames]"
            } else {
                "warning: no [frames] section: no camera, so no vision fixes"
            };
            assert!(text.contains(want), "{}: {text}", path.display());
        }
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
         [map]\northo = [\"nope.tif\"]\ndem = \"nope_dem.tif\"\nground_height_amsl_m = 3.0\nupsample = 3\nheight_sigma_m = -2.0\n\
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
        "map.upsample",
        "must be 1, 2 or 4",
        "map.height_sigma_m",
        "output.rate_hz",
        "500",
        "output.modes",
        "camera.hfov_deg",
        "nav.imu.gyro_arw_deg_sqrt_h",
    ] {
        assert!(err.contains(needle), "missing {needle:?} in:\n{err}");
    }

    // [fix]: a typo in a nested key and an out-of-range value are named with their section.
    let (code, err) = check(
        dir.path(),
        &format!(
            "[link]\nconnection = \"udpin:0.0.0.0:14550\"\n{good_map}\
             [fix]\nratio = 1.5\n[fix.pose.ransac]\nthreshhold_px = 2.0\n"
        ),
    );
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("threshhold_px"), "{err}");

    // Several unknown keys in several sections: all named at once with their sections,
    // the first with its line.
    let (code, err) = check(
        dir.path(),
        &format!(
            "[link]\nconnection = \"udpin:0.0.0.0:14550\"\nbaud = 57600\n{good_map}\
             [output]\nratee_hz = 4.0\n[fix.pose.ransac]\nthreshhold_px = 2.0\n[fram]\nsource = 1\n"
        ),
    );
    assert_eq!(code, 2, "{err}");
    for needle in [
        "line",
        "4 unknown keys in all",
        "link.baud",
        "output.ratee_hz",
        "fix.pose.ransac.threshhold_px",
        "fram: unknown field `fram`",
    ] {
        assert!(err.contains(needle), "missing {needle:?} in:\n{err}");
    }
    let (code, err) = check(
        dir.path(),
        &format!("[link]\nconnection = \"udpin:0.0.0.0:14550\"\n{good_map}[fix]\nratio = 1.5\n"),
    );
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("fix.ratio"), "{err}");

    // The PX4 IMU bias restoration needs SCALED_IMU: refused when it is switched off; an unknown
    // mode is named.
    let (code, err) = check(
        dir.path(),
        &format!(
            "[link]\nconnection = \"udpin:0.0.0.0:14550\"\n[link.streams]\nscaled_imu_hz = 0.0\n\
             {good_map}[daemon]\nimu_bias_restore = \"scaled_imu\"\n"
        ),
    );
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("daemon.imu_bias_restore") && err.contains("link.streams.scaled_imu_hz"),
        "{err}"
    );
    for ok in ["", "[link.streams]\nscaled_imu_hz = 250.0\n"] {
        let (code, err) = check(
            dir.path(),
            &format!(
                "[link]\nconnection = \"udpin:0.0.0.0:14550\"\n{ok}\
                 {good_map}[daemon]\nimu_bias_restore = \"scaled_imu\"\n"
            ),
        );
        assert_eq!(code, 0, "{ok}: {err}");
    }
    let (code, err) = check(
        dir.path(),
        &format!(
            "[link]\nconnection = \"udpin:0.0.0.0:14550\"\n{good_map}\
             [daemon]\nimu_bias_restore = \"ekf2\"\n"
        ),
    );
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("imu_bias_restore") && err.contains("ekf2"),
        "{err}"
    );

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

/// Subcommand names listed under "Commands:" in a help text.
fn listed_commands(help: &str) -> Vec<String> {
    help.lines()
        .skip_while(|l| !l.starts_with("Commands:"))
        .skip(1)
        .take_while(|l| l.starts_with("  "))
        .filter_map(|l| l.split_whitespace().next().map(str::to_string))
        .filter(|c| c != "help")
        .collect()
}

#[test]
fn every_subcommand_has_help() {
    let out = visnav().arg("--help").output().unwrap();
    assert!(out.status.success());
    let text = String::from_utf8_lossy(&out.stdout).into_owned();
    let cmds = listed_commands(&text);
    assert!(cmds.contains(&"check-config".to_string()), "{text}");
    // Top-level subcommands and their own subcommands (e.g. `bench fix`).
    for want in ["check-config", "sim", "bench", "run", "fix", "map"] {
        assert!(cmds.contains(&want.to_string()), "{want} missing: {text}");
    }
    let mut paths: Vec<Vec<String>> = Vec::new();
    for c in cmds {
        let out = visnav().arg(&c).arg("--help").output().unwrap();
        assert!(out.status.success(), "visnav {c} --help failed");
        let help = String::from_utf8_lossy(&out.stdout).into_owned();
        assert!(help.contains("Usage:"), "visnav {c} --help");
        for sub in listed_commands(&help) {
            paths.push(vec![c.clone(), sub]);
        }
        paths.push(vec![c]);
    }
    for p in paths {
        let out = visnav().args(&p).arg("--help").output().unwrap();
        assert!(
            out.status.success() && String::from_utf8_lossy(&out.stdout).contains("Usage:"),
            "visnav {} --help: {}",
            p.join(" "),
            String::from_utf8_lossy(&out.stderr)
        );
    }
    // Nested subcommands.
    for sub in [["map", "build"], ["map", "info"]] {
        let out = visnav().args(sub).arg("--help").output().unwrap();
        assert!(out.status.success(), "visnav {sub:?} --help failed");
        assert!(String::from_utf8_lossy(&out.stdout).contains("Usage:"));
    }
}

#[test]
fn example_configs_build_a_fix_engine_and_a_vnm_map_config_loads() {
    let cfg = visnav::daemon::config::Config::load(&repo().join("config/demo.toml")).unwrap();
    let engine = visnav::daemon::engine_from_config(&cfg).expect("demo engine");
    assert!(!engine.reference().level_gsd_m().is_empty());
    // A config naming a .vnm map (no ortho), built here.
    let dir = tempfile::tempdir().unwrap();
    let map = dir.path().join("m.vnm");
    let spec = visnav::map::BuildSpec::new(
        vec![repo().join("sitl/maps/naip_nd_2009.tif")],
        visnav::map::HeightSource::ConstantAmsl(580.0),
    );
    visnav::map::build_map(&spec, &map, &mut |_| {}).unwrap();
    let text = "[link]\nconnection = \"udpin:0.0.0.0:14550\"\n\
                [camera]\nwidth_px = 640\nheight_px = 480\nhfov_deg = 60.0\n\
                [map]\nfile = \"m.vnm\"\n[fix]\nratio = 0.85\n";
    let path = dir.path().join("c.toml");
    std::fs::write(&path, text).unwrap();
    let out = visnav().arg("check-config").arg(&path).output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let cfg = visnav::daemon::config::Config::load(&path).unwrap();
    assert_eq!(cfg.fix.ratio, 0.85);
    let engine = visnav::daemon::engine_from_config(&cfg).expect("vnm engine");
    assert_eq!(engine.reference().level_gsd_m()[0], 5.0);
    // A corrupt map file: check-config names map.file.
    std::fs::write(&map, b"garbage").unwrap();
    let out = visnav().arg("check-config").arg(&path).output().unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("map.file") && err.contains("m.vnm"), "{err}");
}

/// `visnav camera import`: a ROS camera_info calibration printed as `[camera]`, which
/// check-config accepts in a configuration; an unsupported model is refused naming the file.
#[test]
fn camera_import_gives_a_section_check_config_accepts() {
    let dir = tempfile::tempdir().unwrap();
    let ros = dir.path().join("downward.yaml");
    std::fs::write(
        &ros,
        "image_width: 640\nimage_height: 480\ncamera_name: downward\ncamera_matrix:\n  rows: 3\n  \
         cols: 3\n  data: [520.1, 0, 321.4, 0, 519.8, 238.9, 0, 0, 1]\ndistortion_model: plumb_bob\n\
         distortion_coefficients:\n  rows: 1\n  cols: 5\n  data: [-0.21, 0.08, 0.0004, -0.0002, 0]\n",
    )
    .unwrap();
    let out = visnav()
        .args(["camera", "import"])
        .arg(&ros)
        .output()
        .unwrap();
    let section = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        section.contains("fx_px = 520.1") && section.contains("p2 = -0.0002"),
        "{section}"
    );
    let ortho = repo().join("sitl/maps/naip_nd_2009.tif");
    let cfg = dir.path().join("c.toml");
    std::fs::write(
        &cfg,
        format!(
            "[link]\nconnection = \"udpin:127.0.0.1:14550\"\n{section}\n\
             [map]\northo = [\"{}\"]\nground_height_amsl_m = 580.0\n",
            ortho.display()
        ),
    )
    .unwrap();
    let out = visnav().arg("check-config").arg(&cfg).output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );

    std::fs::write(&ros, "camera_model: omni\nimage_width: 640\n").unwrap();
    let out = visnav()
        .args(["camera", "import"])
        .arg(&ros)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("downward.yaml"),
        "{err}"
    );
}
