//! Issue 21: the fault table of docs/operations.md holds in the lock-step simulator.
//! `sitl/scenarios/faults.toml` flies the demo's aircraft on a racetrack over the bundled NAIP
//! map and scripts one fault after another (a 10 km GPS jump, two UTC clock steps, foreign
//! heartbeats, an autopilot reboot while the GPS works; then on vision alone a camera stall, a
//! frozen camera, torn frames, a 50 g accelerometer burst, 5 s of link silence, a second
//! reboot). `visnav sim --json` scores what the vision daemon sent around each fault
//! (`faults`) and its counters (`fault_counters`); each assertion below is a row of the table.
//! About 90 s (lock-step, one run).

use std::process::Command;

fn run_faults() -> serde_json::Value {
    let out = std::env::temp_dir().join(format!("visnav-sim-faults-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let res = Command::new(env!("CARGO_BIN_EXE_visnav"))
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .args([
            "sim",
            "--scenario",
            "sitl/scenarios/faults.toml",
            "--json",
            "--out",
        ])
        .arg(&out)
        .output()
        .expect("run visnav sim");
    let stderr = String::from_utf8_lossy(&res.stderr);
    assert!(res.status.success(), "visnav sim failed: {stderr}");
    let _ = std::fs::remove_dir_all(&out);
    serde_json::from_slice(&res.stdout).unwrap_or_else(|e| {
        panic!(
            "stdout is not JSON ({e}): {}",
            String::from_utf8_lossy(&res.stdout)
        )
    })
}

fn f64_of(v: &serde_json::Value, key: &str) -> f64 {
    v[key]
        .as_f64()
        .unwrap_or_else(|| panic!("{key} is not a number in {v}"))
}

fn u64_of(v: &serde_json::Value, key: &str) -> u64 {
    v[key]
        .as_u64()
        .unwrap_or_else(|| panic!("{key} is not a count in {v}"))
}

#[test]
fn the_fault_table_holds_in_the_lockstep_simulator() {
    let s = run_faults();
    let c = &s["fault_counters"];
    let faults = s["faults"].as_array().expect("faults");
    assert_eq!(faults.len(), 11, "{s}");
    let of = |kind: &str| -> Vec<&serde_json::Value> {
        faults.iter().filter(|f| f["kind"] == kind).collect()
    };
    for f in faults {
        eprintln!("{f}");
    }
    eprintln!("{c}");

    // Whatever the fault: nothing non-finite, nothing from another system, GPS_INPUT time
    // never back, and no injection whose error exceeds 3 times the accuracy it claims.
    assert_eq!(u64_of(c, "non_finite_injections"), 0);
    assert_eq!(u64_of(c, "foreign_injections"), 0);
    assert_eq!(u64_of(c, "gps_input_time_backsteps"), 0);
    for f in faults {
        if let Some(r) = f["max_err_over_claimed"].as_f64() {
            assert!(r < 3.0, "an overconfident injection around {f}");
        }
    }

    // A 10 km GPS jump is not followed: the injected position stays within metres.
    let jump = of("gps_jump")[0];
    assert!(f64_of(jump, "max_err_m") < 10.0, "{jump}");
    assert!(f64_of(jump, "max_output_gap_s") < 1.0, "{jump}");

    // Each UTC clock step is reported once, never followed.
    assert_eq!(u64_of(c, "utc_steps"), 2, "{c}");

    // Foreign heartbeats: no relock, the injections keep flowing to the autopilot (5 Hz).
    assert_eq!(u64_of(c, "relocks"), 0, "{c}");
    let spoof = of("spoofed_heartbeat")[0];
    assert!(u64_of(spoof, "outputs_during") >= 45, "{spoof}");

    // Both reboots are detected (no more: the stale-message rule holds); with the GPS, the
    // solution is back within seconds.
    assert_eq!(u64_of(c, "autopilot_reboots"), 2, "{c}");
    let reboot = of("reboot")[0];
    assert!(f64_of(reboot, "max_output_gap_s") < 8.0, "{reboot}");
    assert!(f64_of(reboot, "err_after_p90_m") < 5.0, "{reboot}");

    // On vision alone, the filter restarted by the reboot reacquires from the last solution
    // (its position moved on and its sigma grown, as the fixes' prior) instead of a
    // relocalisation without a prior (before: nothing for the 32 s left of the flight).
    let reboot = of("reboot")[1];
    assert!(f64_of(reboot, "max_output_gap_s") < 12.0, "{reboot}");

    // A stalled camera: no fix, the IMU carries the solution on.
    let stall = of("camera_stall")[0];
    assert_eq!(u64_of(stall, "fixes_attempted"), 0, "{stall}");
    assert!(u64_of(stall, "outputs_during") >= 45, "{stall}");

    // A frozen camera: its repeated frames are dropped as frozen, never fixed.
    let freeze = of("camera_freeze")[0];
    assert_eq!(u64_of(freeze, "fixes_attempted"), 0, "{freeze}");
    assert!(u64_of(c, "frames_frozen") >= 10, "{c}");

    // Torn frames: no accepted fix outside its own 3-sigma ellipse.
    let torn = of("camera_corrupt")[0];
    assert_eq!(u64_of(torn, "fixes_beyond_3sigma"), 0, "{torn}");

    // 50 g on the accelerometer for 4 s: navigating again within seconds.
    let burst = of("imu_burst")[0];
    assert!(f64_of(burst, "first_output_after_s") < 10.0, "{burst}");

    // 5 s of silence: nothing sent once the IMU is 0.5 s late (integrity), the gap bridged
    // rather than a restart, so the solution is back without a relocalisation.
    let silence = of("link_silence")[0];
    assert!(u64_of(silence, "outputs_during") <= 4, "{silence}");
    assert!(u64_of(c, "imu_timeouts") >= 1, "{c}");
    assert!(f64_of(silence, "first_output_after_s") < 15.0, "{silence}");
}
