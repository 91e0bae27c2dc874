//! `visnav check-config` and `visnav run` share one validation: what
//! check-config passes, run starts; what run refuses, check-config refuses first, naming the key.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use crate::common;

fn visnav() -> Command {
    Command::new(env!("CARGO_BIN_EXE_visnav"))
}

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// A valid configuration without `[frames]`: the link on a local UDP port, the NAIP map at a
/// constant height; `extra` is appended (its sections must not repeat these).
fn config(link_extra: &str, map: &str, extra: &str) -> String {
    format!(
        "[link]\nconnection = \"udpin:127.0.0.1:14999\"\n{link_extra}\n\
         [camera]\nwidth_px = 640\nheight_px = 480\nhfov_deg = 60.0\n\
         [map]\northo = [\"{}\"]\n{map}\n{extra}",
        repo().join("sitl/maps/naip_nd_2009.tif").display()
    )
}

fn check(dir: &Path, text: &str) -> (i32, String) {
    let file = dir.join("c.toml");
    std::fs::write(&file, text).unwrap();
    let out = visnav().arg("check-config").arg(&file).output().unwrap();
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// `visnav run` for at most `secs` seconds: `None` if it was still running (it started), else
/// its exit code and stderr.
fn run(dir: &Path, text: &str, secs: f64) -> Option<(i32, String)> {
    let file = dir.join("r.toml");
    std::fs::write(&file, text).unwrap();
    let (status, err) = common::stderr_within(
        visnav().args(["run", "--config"]).arg(&file),
        Duration::from_secs_f64(secs),
    )?;
    Some((status.code().unwrap_or(-1), err))
}

/// Each of these passed check-config and was refused by run (or, for the serial device, failed
/// at start): check-config must refuse it, naming the key.
#[test]
fn check_config_refuses_what_run_refuses() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::create_dir(d.join("logs")).unwrap();
    let heights = "ground_height_amsl_m = 580.0";
    let cases: Vec<(&str, String, &str)> = vec![
        (
            "tlog is a directory",
            config(
                &format!("tlog = \"{}\"", d.join("logs").display()),
                heights,
                "",
            ),
            "link.tlog",
        ),
        (
            "fix_log is a directory",
            config(
                "",
                heights,
                &format!("[daemon]\nfix_log = \"{}\"\n", d.join("logs").display()),
            ),
            "daemon.fix_log",
        ),
        (
            "fix_log in a missing folder",
            config(
                "",
                heights,
                &format!(
                    "[daemon]\nfix_log = \"{}\"\n",
                    d.join("nope/fix.jsonl").display()
                ),
            ),
            "daemon.fix_log",
        ),
        (
            "vo_log in a missing folder",
            config(
                "",
                heights,
                &format!(
                    "[daemon]\nvo_log = \"{}\"\n",
                    d.join("nope/vo.jsonl").display()
                ),
            ),
            "daemon.vo_log",
        ),
        (
            "serial device that does not exist",
            config("", heights, "").replace(
                "udpin:127.0.0.1:14999",
                "serial:/dev/ttyVISNAV_NOT_THERE:57600",
            ),
            "link.connection",
        ),
        (
            "empty gstreamer pipeline",
            config(
                "",
                heights,
                "[frames]\nsource = \"gstreamer\"\npipeline = \"!\"\n",
            ),
            "frames.pipeline",
        ),
        (
            "gstreamer pipeline ending in !",
            config(
                "",
                heights,
                "[frames]\nsource = \"gstreamer\"\npipeline = \"videotestsrc !\"\n",
            ),
            "frames.pipeline",
        ),
    ];
    for (what, text, key) in cases {
        let (code, err) = check(d, &text);
        assert_eq!(code, 2, "{what}: check-config passed it: {err}");
        assert!(err.contains("c.toml") && err.contains(key), "{what}: {err}");
        assert!(
            !err.contains("{:?}") && !err.contains("Some("),
            "{what}: {err}"
        );
    }
}

/// A DEM that is not a usable GeoTIFF, without `[frames]` (the map is then not used): check-config
/// refused it and run started anyway. Both now refuse it, naming `map.dem`.
#[test]
fn run_refuses_the_bad_dem_check_config_refuses() {
    let dir = tempfile::tempdir().unwrap();
    let dem = dir.path().join("dem.tif");
    std::fs::write(&dem, b"not a GeoTIFF").unwrap();
    let text = config("", &format!("dem = \"{}\"", dem.display()), "");
    let (code, err) = check(dir.path(), &text);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("map.dem") && err.contains("dem.tif"), "{err}");
    match run(dir.path(), &text, 15.0) {
        None => panic!("run started with the DEM check-config refuses"),
        Some((code, err)) => {
            assert_ne!(code, 0, "{err}");
            assert!(err.contains("map.dem") && err.contains("dem.tif"), "{err}");
        }
    }
}

/// No autopilot on the link: `visnav run` says so within the heartbeat timeout,
/// naming the connection and what to check, instead of waiting in silence.
#[test]
fn run_warns_when_no_autopilot_heartbeat_arrives() {
    let dir = tempfile::tempdir().unwrap();
    let port = std::net::UdpSocket::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let text = config(
        "heartbeat_timeout_s = 1.0",
        "ground_height_amsl_m = 300.0",
        "",
    )
    .replace("14999", &port.to_string());
    let file = dir.path().join("quiet.toml");
    std::fs::write(&file, text).unwrap();
    let out = visnav()
        .args(["run", "--duration", "3", "--config"])
        .arg(&file)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    let want = format!("no autopilot HEARTBEAT on udpin:127.0.0.1:{port}");
    let lines: Vec<&str> = err.lines().filter(|l| l.contains(&want)).collect();
    assert_eq!(lines.len(), 1, "said once: {err}");
    assert!(
        lines[0].contains("WARN") && lines[0].contains("SERIALn_PROTOCOL"),
        "{err}"
    );
}
