//! The first run of docs/first-flight.md ("A first run against the simulated autopilot"), end to
//! end with the real binary: `visnav sim --write-frames` renders a scenario's camera into a
//! frames folder, `visnav sim --autopilot-only` flies the scenario as a simulated autopilot in
//! real time over loopback UDP MAVLink, and `visnav run` with config/sim-autopilot.toml (its
//! paths made absolute, the folder and the port of this test) reads the folder as its camera,
//! fixes, fuses and injects GPS_INPUT, which the emulator scores against its truth.
//!
//! `visnav run` starts late on purpose (the flight is 6 s old): the frames taken before the
//! autopilot's clock reached the present are skipped, the rest are handed on when the clock
//! reaches them (`[frames] stamp = "source"`). About 50 s of real time.
#![cfg(feature = "sim")]

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::Duration;

use crate::common;

fn visnav() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_visnav"));
    c.current_dir(env!("CARGO_MANIFEST_DIR"));
    c
}

/// config/sim-autopilot.toml with absolute paths: the map, and `frames` as the camera folder.
fn run_config(root: &Path, frames: &Path) -> String {
    let abs = |p: &Path| format!("{:?}", p.display().to_string());
    let text = std::fs::read_to_string(root.join("config/sim-autopilot.toml"))
        .expect("read config/sim-autopilot.toml");
    assert!(
        text.contains("\"../sim-frames\"") && text.contains("\"../sitl/maps/naip_nd_2010.tif\"")
    );
    text.replace("\"../sim-frames\"", &abs(frames)).replace(
        "\"../sitl/maps/naip_nd_2010.tif\"",
        &abs(&root.join("sitl/maps/naip_nd_2010.tif")),
    )
}

/// The JSON object logged after `final counters: ` by `visnav run`.
fn final_counters(log: &str) -> serde_json::Value {
    let line = log
        .lines()
        .find_map(|l| l.split_once("final counters: ").map(|(_, j)| j))
        .unwrap_or_else(|| panic!("no final counters in the log:\n{log}"));
    serde_json::from_str(line)
        .unwrap_or_else(|e| panic!("final counters are not JSON ({e}): {line}"))
}

#[test]
fn visnav_run_fixes_from_a_frames_folder_against_the_simulated_autopilot() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let tmp = tempfile::tempdir().expect("temporary folder");
    // The 45 s test flight (GPS until 20 s), with config/demo.toml's camera for the frames.
    let scenario = tmp.path().join("flight.toml");
    std::fs::write(
        &scenario,
        common::short_demo_scenario(root, &root.join("config/demo.toml")),
    )
    .expect("write the scenario");
    let frames = tmp.path().join("frames");
    let w = visnav()
        .args(["sim", "--scenario"])
        .arg(&scenario)
        .arg("--write-frames")
        .arg(&frames)
        .output()
        .expect("run visnav sim --write-frames");
    let out = String::from_utf8_lossy(&w.stdout);
    assert!(
        w.status.success(),
        "{out}\n{}",
        String::from_utf8_lossy(&w.stderr)
    );
    // 5 s to 45 s at 2 Hz.
    assert!(out.contains("wrote 81 frames (640 x 480 px, 2 Hz"), "{out}");
    let csv = std::fs::read_to_string(frames.join("frames.csv")).expect("frames.csv");
    assert!(
        csv.contains("\nfile,t_boot_us\nframe_000000.png,5000000\n"),
        "{csv}"
    );
    assert!(frames.join("frame_000080.png").is_file());
    // Writing into the same folder again is refused (two flights' frames never mix).
    let again = visnav()
        .args(["sim", "--scenario"])
        .arg(&scenario)
        .arg("--write-frames")
        .arg(&frames)
        .output()
        .expect("run visnav sim --write-frames again");
    assert!(!again.status.success());
    assert!(String::from_utf8_lossy(&again.stderr).contains("the folder is not empty"));

    let config = tmp.path().join("visnav.toml");
    std::fs::write(&config, run_config(root, &frames)).expect("write the configuration");
    let port = common::free_udp_port();
    let autopilot = visnav()
        .args(["sim", "--scenario"])
        .arg(&scenario)
        .args([
            "--json",
            "--autopilot-only",
            &format!("udpout:127.0.0.1:{port}"),
        ])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start visnav sim --autopilot-only");
    std::thread::sleep(Duration::from_secs(6));
    let run = visnav()
        .args(["run", "--config"])
        .arg(&config)
        .args(["--connection", &format!("udpin:127.0.0.1:{port}")])
        .args(["--duration", "36"])
        .output()
        .expect("run visnav run");
    let log = String::from_utf8_lossy(&run.stderr);
    let ap = autopilot
        .wait_with_output()
        .expect("wait for the autopilot");
    let ap_log = String::from_utf8_lossy(&ap.stderr);
    assert!(run.status.success(), "visnav run failed:\n{log}");
    assert!(ap.status.success(), "autopilot failed:\n{ap_log}");
    assert!(
        log.contains("each released when the autopilot's clock reaches its t_boot_us"),
        "{log}"
    );
    assert!(log.contains("GPS aiding source: gps2 (GPS2_RAW)"), "{log}");
    let c = final_counters(&log);
    let n = |k: &str| c[k].as_u64().unwrap_or_else(|| panic!("counter {k}: {c}"));
    // Started 6 s into the flight: the frames of 5-6 s and those of the startup are skipped.
    assert!(n("frames_stale") >= 2, "{c}");
    assert!(log.contains("frames: skipped the "), "{log}");
    assert!(n("fixes_attempted") >= 50, "{c}");
    assert!(
        n("fixes_accepted") as f64 >= 0.8 * n("fixes_attempted") as f64,
        "{c}"
    );
    assert_eq!(n("frame_errors"), 0, "{c}");

    let report: serde_json::Value = serde_json::from_slice(&ap.stdout).unwrap_or_else(|e| {
        panic!(
            "autopilot stdout is not JSON ({e}): {}",
            String::from_utf8_lossy(&ap.stdout)
        )
    });
    assert_eq!(report["companion"], serde_json::json!([1, 197]), "{report}");
    assert_eq!(report["non_finite"], 0, "{report}");
    assert!(
        report["injections"]["gps_input"].as_u64().unwrap_or(0) >= 150,
        "{report}"
    );
    // The GPS outage 20-45 s: visnav's positions, at 5 Hz until visnav run stops at ~42 s.
    let scored = report["injections_scored"].as_u64().unwrap_or(0);
    assert!(scored >= 80, "{report}");
    let p90 = report["injected_err_m"]["p90"].as_f64().unwrap_or(f64::NAN);
    let max = report["injected_err_m"]["max"].as_f64().unwrap_or(f64::NAN);
    println!(
        "first run: {scored} positions in the outage, horizontal error p90 {p90:.1} m, max {max:.1} m"
    );
    assert!(p90 < 20.0 && max < 40.0, "{report}");
}
