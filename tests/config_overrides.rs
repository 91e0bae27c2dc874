//! Command-line and environment overrides of the configuration: `--connection`,
//! `--map`, `--camera` and `VISNAV_CONNECTION`, `VISNAV_MAP`, `VISNAV_CAMERA`, `VISNAV_CONFIG`
//! on `visnav check-config` and `visnav run`; the command line beats the environment, which
//! beats the file. Also the path errors (the key, the value as written, the resolved path, the
//! rule) and OS errors said once.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// `visnav` in `cwd` with none of the override variables of the test's own environment.
fn visnav(cwd: &Path) -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_visnav"));
    c.current_dir(cwd);
    for v in [
        "VISNAV_CONFIG",
        "VISNAV_CONNECTION",
        "VISNAV_MAP",
        "VISNAV_CAMERA",
    ] {
        c.env_remove(v);
    }
    c
}

fn text(o: &Output) -> (i32, String, String) {
    (
        o.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&o.stdout).into_owned(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    )
}

/// A valid configuration (the NAIP orthophoto, no `[frames]`) at `dir/config/c.toml`.
fn config(dir: &Path, extra: &str) -> PathBuf {
    std::fs::create_dir_all(dir.join("config")).unwrap();
    let path = dir.join("config/c.toml");
    std::fs::write(
        &path,
        format!(
            "[link]\nconnection = \"udpin:127.0.0.1:14999\"\n\
             [camera]\nwidth_px = 640\nheight_px = 480\nhfov_deg = 60.0\n\
             [map]\northo = [\"{}\"]\nground_height_amsl_m = 580.0\n{extra}",
            repo().join("sitl/maps/naip_nd_2009.tif").display()
        ),
    )
    .unwrap();
    path
}

/// A `.vnm` map at `path`, built from the NAIP orthophoto.
fn build_map(path: &Path) {
    let spec = visnav::map::BuildSpec::new(
        vec![repo().join("sitl/maps/naip_nd_2009.tif")],
        visnav::map::HeightSource::ConstantAmsl(580.0),
    );
    visnav::map::build_map(&spec, path, &mut |_| {}).unwrap();
}

#[test]
fn each_override_changes_what_check_config_reports() {
    let d = tempfile::tempdir().unwrap();
    let cfg = config(d.path(), "");
    let (code, out, err) = text(
        &visnav(d.path())
            .arg("check-config")
            .arg(&cfg)
            .output()
            .unwrap(),
    );
    assert_eq!(code, 0, "{err}");
    assert!(
        out.contains("link udpin:127.0.0.1:14999") && !out.contains("override"),
        "{out}"
    );

    // Relative paths on the command line are relative to the current directory.
    build_map(&d.path().join("area.vnm"));
    std::fs::create_dir(d.path().join("rec")).unwrap();
    std::fs::write(d.path().join("rec/frames.csv"), "file,t_s\n0.png,0\n").unwrap();
    let (code, out, err) = text(
        &visnav(d.path())
            .args([
                "check-config",
                "config/c.toml",
                "--connection",
                "udpin:0.0.0.0:14550",
            ])
            .args(["--map", "area.vnm", "--camera", "rec"])
            .output()
            .unwrap(),
    );
    assert_eq!(code, 0, "{err}");
    let root = d.path().display();
    for want in [
        "link udpin:0.0.0.0:14550".to_string(),
        format!("map {root}/area.vnm"),
        format!("vision: camera frames from [frames] (directory {root}/rec)"),
        "override: connection udpin:0.0.0.0:14550 (from --connection)".to_string(),
        "override: map area.vnm (from --map)".to_string(),
        "override: camera rec (from --camera)".to_string(),
    ] {
        assert!(out.contains(&want), "missing {want:?} in:\n{out}");
    }

    // A y4m file and a live source keep the file's other [frames] keys.
    let cfg = config(
        d.path(),
        "[frames]\nsource = \"directory\"\npath = \"nowhere\"\nlatency_s = 0.05\n",
    );
    let (code, out, err) = text(
        &visnav(d.path())
            .arg("check-config")
            .arg(&cfg)
            .args(["--camera", "cmd:sh -c true"])
            .output()
            .unwrap(),
    );
    assert_eq!(code, 0, "{err}");
    assert!(out.contains("(command sh -c true)"), "{out}");
}

#[test]
fn command_line_beats_environment_beats_file() {
    let d = tempfile::tempdir().unwrap();
    let cfg = config(d.path(), "");
    let check = |env: &[(&str, &str)], args: &[&str]| {
        let mut c = visnav(d.path());
        c.arg("check-config").args(args).envs(env.iter().copied());
        text(&c.output().unwrap())
    };
    let cfg_s = cfg.to_str().unwrap();
    let env = [("VISNAV_CONNECTION", "udpin:0.0.0.0:14561")];
    let (code, out, err) = check(&env, &[cfg_s]);
    assert_eq!(code, 0, "{err}");
    assert!(
        out.contains("link udpin:0.0.0.0:14561")
            && out.contains("connection udpin:0.0.0.0:14561 (from VISNAV_CONNECTION)"),
        "{out}"
    );
    let (code, out, err) = check(&env, &[cfg_s, "--connection", "tcpout:127.0.0.1:5760"]);
    assert_eq!(code, 0, "{err}");
    assert!(
        out.contains("link tcpout:127.0.0.1:5760") && !out.contains("14561"),
        "{out}"
    );
    // VISNAV_CONFIG names the file when none is given, relative to the current directory.
    let (code, out, err) = check(&[("VISNAV_CONFIG", "config/c.toml")], &[]);
    assert_eq!(code, 0, "{err}");
    assert!(
        out.contains("config/c.toml: OK (link udpin:127.0.0.1:14999"),
        "{out}"
    );
    let (code, _, err) = check(&[], &[]);
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("give FILE or set VISNAV_CONFIG"), "{err}");
    // An environment map that does not exist: named with its variable and the rule.
    let (code, _, err) = check(&[("VISNAV_MAP", "maps/x.vnm")], &[cfg_s]);
    assert_eq!(code, 2, "{err}");
    let want = format!(
        "map.file (from VISNAV_MAP): \"maps/x.vnm\": {}/maps/x.vnm does not exist (paths on the \
         command line and in the environment are relative to the current directory)",
        d.path().display()
    );
    assert!(err.contains(&want), "missing {want:?} in:\n{err}");
    // A bad connection from the command line is refused by the file's validation, named so.
    let (code, _, err) = check(&[], &[cfg_s, "--connection", "udpin:0.0.0.0:99999"]);
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("link.connection (from --connection): \"udpin:0.0.0.0:99999\""),
        "{err}"
    );
}

#[test]
fn bad_camera_specs_are_refused_clearly() {
    let d = tempfile::tempdir().unwrap();
    let cfg = config(d.path(), "");
    for (spec, env) in [
        ("nothing-here", false),
        ("v4l2:", false),
        ("nothing-here", true),
    ] {
        let mut c = visnav(d.path());
        c.arg("check-config").arg(&cfg);
        if env {
            c.env("VISNAV_CAMERA", spec);
        } else {
            c.args(["--camera", spec]);
        }
        let (code, _, err) = text(&c.output().unwrap());
        assert_eq!(code, 2, "{spec}: {err}");
        let origin = if env { "VISNAV_CAMERA" } else { "--camera" };
        assert!(
            err.contains(&format!("{origin} {spec}:"))
                && err.contains("v4l2:DEVICE, gst:PIPELINE or cmd:PROGRAM ARGS"),
            "{spec}: {err}"
        );
        assert!(!err.contains("Some(") && !err.contains("\\\""), "{err}");
    }
    // A configuration without [camera]: the camera's intrinsics are missing, said as such.
    let path = d.path().join("nocam.toml");
    std::fs::write(
        &path,
        "[link]\nconnection = \"udpin:127.0.0.1:14999\"\n[map]\nfile = \"m.vnm\"\n",
    )
    .unwrap();
    let (code, _, err) = text(
        &visnav(d.path())
            .arg("check-config")
            .arg(&path)
            .args(["--camera", "v4l2:/dev/video0"])
            .output()
            .unwrap(),
    );
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("--camera v4l2:/dev/video0: the configuration has no [camera] section"),
        "{err}"
    );
}

#[test]
fn a_missing_path_names_key_value_resolved_path_and_rule() {
    let d = tempfile::tempdir().unwrap();
    // The map file instead of the orthophoto, and a y4m recording, both missing.
    let path = config(
        d.path(),
        "[frames]\nsource = \"y4m\"\npath = \"rec/flight.y4m\"\n",
    );
    let body = std::fs::read_to_string(&path)
        .unwrap()
        .replace("ortho = [", "file = \"maps/x.vnm\"\n# ortho = [")
        .replace("ground_height_amsl_m = 580.0\n", "");
    std::fs::write(&path, body).unwrap();
    let (code, _, err) = text(
        &visnav(d.path())
            .args(["check-config", "config/c.toml"])
            .output()
            .unwrap(),
    );
    assert_eq!(code, 2, "{err}");
    let root = d.path().display();
    for want in [
        format!(
            "map.file: \"maps/x.vnm\": {root}/config/maps/x.vnm does not exist (paths in the \
             config are relative to the config file's folder)"
        ),
        format!(
            "frames.path: \"rec/flight.y4m\": {root}/config/rec/flight.y4m does not exist (paths \
             in the config are relative to the config file's folder)"
        ),
    ] {
        assert!(err.contains(&want), "missing {want:?} in:\n{err}");
    }
    // The same values on the command line: relative to the current directory.
    let (code, _, err) = text(
        &visnav(d.path())
            .args(["check-config", "config/c.toml", "--map", "maps/x.vnm"])
            .args(["--camera", "rec/flight.y4m"])
            .output()
            .unwrap(),
    );
    assert_eq!(code, 2, "{err}");
    for want in [
        format!("map.file (from --map): \"maps/x.vnm\": {root}/maps/x.vnm does not exist"),
        format!(
            "frames.path (from --camera): \"rec/flight.y4m\": {root}/rec/flight.y4m does not \
             exist (paths on the command line and in the environment are relative to the current \
             directory)"
        ),
    ] {
        assert!(err.contains(&want), "missing {want:?} in:\n{err}");
    }
}

/// `visnav run` starts with the overrides check-config reports: the log names them, and the
/// link listens on the overriding connection (its no-HEARTBEAT warning names it).
#[test]
fn run_uses_the_overrides() {
    let d = tempfile::tempdir().unwrap();
    let cfg = config(d.path(), "");
    let body = std::fs::read_to_string(&cfg)
        .unwrap()
        .replace("[camera]", "heartbeat_timeout_s = 1.0\n[camera]");
    std::fs::write(&cfg, body).unwrap();
    let port = std::net::UdpSocket::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let conn = format!("udpin:127.0.0.1:{port}");
    let (code, _, err) = text(
        &visnav(d.path())
            .args(["run", "--duration", "2.5", "--connection", &conn])
            .env("VISNAV_CONFIG", "config/c.toml")
            .env("VISNAV_CONNECTION", "udpin:127.0.0.1:1")
            .output()
            .unwrap(),
    );
    assert_eq!(code, 0, "{err}");
    for want in [
        format!("connection {conn} (from --connection)"),
        format!("no autopilot HEARTBEAT on {conn}"),
    ] {
        assert!(err.contains(&want), "missing {want:?} in:\n{err}");
    }
    assert!(!err.contains("udpin:127.0.0.1:1 "), "{err}");
}

/// An OS error appears once in a message, not once per link of the error chain.
#[test]
fn an_os_error_is_said_once() {
    let d = tempfile::tempdir().unwrap();
    let cfg = config(d.path(), "");
    let os = "No such file or directory (os error 2)";
    let cases: Vec<Vec<String>> = vec![
        vec!["run".into(), "--config".into(), "missing.toml".into()],
        vec!["check-config".into(), "missing.toml".into()],
        vec![
            "check-config".into(),
            cfg.display().to_string(),
            "--map".into(),
            "missing.vnm".into(),
        ],
        vec!["map".into(), "info".into(), "missing.vnm".into()],
        vec![
            "map".into(),
            "build".into(),
            "--ortho".into(),
            "missing.tif".into(),
            "--ground-height".into(),
            "100".into(),
            "--out".into(),
            "m.vnm".into(),
        ],
        vec![
            "map".into(),
            "build".into(),
            "--ortho".into(),
            repo()
                .join("sitl/maps/naip_nd_2009.tif")
                .display()
                .to_string(),
            "--dem".into(),
            "missing_dem.tif".into(),
            "--out".into(),
            "m.vnm".into(),
        ],
        vec!["camera".into(), "import".into(), "missing.yaml".into()],
    ];
    for args in cases {
        let (code, _, err) = text(&visnav(d.path()).args(&args).output().unwrap());
        assert_ne!(code, 0, "{args:?}: {err}");
        // check-config says "does not exist" for a missing map; the others the OS's words.
        let n = err.matches(os).count() + err.matches("does not exist").count();
        assert_eq!(n, 1, "{args:?}: {err}");
    }
    // `fix` with a missing image (a real map and camera, so the image is what is missing).
    build_map(&d.path().join("m.vnm"));
    let cam = d.path().join("cam.toml");
    std::fs::write(&cam, "width_px = 640\nheight_px = 480\nhfov_deg = 60.0\n").unwrap();
    let (code, _, err) = text(
        &visnav(d.path())
            .args([
                "fix",
                "--map",
                "m.vnm",
                "--image",
                "missing.png",
                "--camera",
            ])
            .arg(&cam)
            .output()
            .unwrap(),
    );
    assert_ne!(code, 0, "{err}");
    assert_eq!(err.matches(os).count(), 1, "{err}");
}

/// `visnav sitl-run` needs a camera world (`--ortho` or `--scenario`), and a scenario that is
/// not there is named before anything waits for the simulator.
#[test]
fn sitl_run_needs_a_camera_world_and_names_a_missing_scenario() {
    let d = tempfile::tempdir().expect("tempdir");
    let cfg = repo().join("sitl/ardupilot/visnav.toml");
    let cfg = cfg.display().to_string();
    let (code, _, err) = text(
        &visnav(d.path())
            .args(["sitl-run", "--config", &cfg])
            .output()
            .expect("run"),
    );
    assert_ne!(code, 0);
    assert!(err.contains("--ortho"), "{err}");
    let (code, _, err) = text(
        &visnav(d.path())
            .args([
                "sitl-run",
                "--config",
                &cfg,
                "--scenario",
                "no_such_scenario.toml",
            ])
            .output()
            .expect("run"),
    );
    assert_ne!(code, 0);
    assert!(err.contains("no_such_scenario.toml"), "{err}");
    assert!(!err.contains("waiting for the simulator"), "{err}");
}
