//! Interop: pymavlink (a different MAVLink implementation) decodes everything visnav sends over a
//! real UDP socket and checks each field: MAVLink 2 framing, CRC, signatures, extension fields,
//! units, scaling and frame ids (scripts/interop/fake_autopilot.py).
//!
//! The Python venv (target/pyenv with pymavlink) is created by scripts/interop/setup_venv.sh on
//! first use. Without python3/venv/pip the test prints why and skips, except under CI (CI=true),
//! where pip is reachable and a failed setup is a failure.

use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use nalgebra::{Matrix3, UnitQuaternion, Vector3};
use serde_json::json;
use visnav::geo::GeoOrigin;
use visnav::link::config::{LinkConfig, OutputConfig, OutputMode, SigningSettings};
use visnav::link::inject::DOP_UERE_M;
use visnav::link::{Health, Link, NavEstimate};

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn python() -> Option<PathBuf> {
    let out = Command::new("bash")
        .arg(repo().join("scripts/interop/setup_venv.sh"))
        .stderr(Stdio::inherit())
        .output();
    let ci = std::env::var("CI").is_ok_and(|v| v == "true" || v == "1");
    match out {
        Ok(o) if o.status.success() => {
            let p = String::from_utf8_lossy(&o.stdout).trim().to_string();
            Some(repo().join(p))
        }
        Ok(o) => {
            assert!(
                !ci,
                "CI: the pymavlink venv could not be set up ({})",
                o.status
            );
            eprintln!(
                "SKIP link_interop: pymavlink venv unavailable ({})",
                o.status
            );
            None
        }
        Err(e) => {
            assert!(!ci, "CI: cannot run bash: {e}");
            eprintln!("SKIP link_interop: cannot run bash: {e}");
            None
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn pymavlink_decodes_and_checks_every_field() {
    let Some(py) = python() else { return };
    let dir = tempfile::tempdir().unwrap();
    let port = std::net::UdpSocket::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let key: [u8; 32] = core::array::from_fn(|i| (i as u8) ^ 0x5A);
    let key_hex: String = key.iter().map(|b| format!("{b:02x}")).collect();
    let key_file = dir.path().join("signing.key");
    std::fs::write(&key_file, &key_hex).unwrap();

    let rpy = [0.05, -0.08, 2.5];
    let pos_cov = [[9.0, 1.5, 0.0], [1.5, 4.0, 0.0], [0.0, 0.0, 25.0]];
    let vel_cov = [[0.04, 0.0, 0.0], [0.0, 0.04, 0.0], [0.0, 0.0, 0.09]];
    let est = NavEstimate {
        t_boot_us: 0,
        lat_deg: 46.901_234_5,
        lon_deg: -96.798_765_4,
        alt_amsl_m: 412.5,
        geoid_undulation_m: Some(-27.25),
        vel_ned_m_s: Vector3::new(1.5, -0.75, 0.2),
        q_ned_body: UnitQuaternion::from_euler_angles(rpy[0], rpy[1], rpy[2]),
        pos_cov_ned_m2: Matrix3::from_fn(|i, j| pos_cov[i][j]),
        vel_cov_ned_m2_s2: Matrix3::from_fn(|i, j| vel_cov[i][j]),
        att_sigma_rad: Vector3::new(0.01, 0.015, 0.04),
        health: Health::Ok,
        reset_counter: 7,
    };
    let origin = GeoOrigin {
        lat_deg: 46.9,
        lon_deg: -96.8,
        alt_amsl_m: 380.0,
    };
    let out = OutputConfig {
        modes: vec![
            OutputMode::GpsInput,
            OutputMode::VisionPositionEstimate,
            OutputMode::Odometry,
            OutputMode::GlobalPositionSensor,
        ],
        rate_hz: 10.0,
        gps_id: 1,
        gps_yaw: true,
        ..OutputConfig::default()
    };
    let mut cfg = LinkConfig::new(&format!("udpout:127.0.0.1:{port}"));
    cfg.autopilot_system_id = Some(1);
    cfg.signing = Some(SigningSettings {
        key_file,
        sign_outgoing: true,
        reject_unsigned: true,
        link_id: 3,
    });
    let streams: serde_json::Map<String, serde_json::Value> = [
        (30, cfg.streams.attitude_hz),
        (105, cfg.streams.imu_hz),
        (33, cfg.streams.global_position_hz),
        (24, cfg.streams.gps_raw_hz),
        (2, cfg.streams.system_time_hz),
        (29, cfg.streams.pressure_hz),
    ]
    .into_iter()
    .map(|(k, v)| (k.to_string(), json!(v)))
    .collect();
    let expected = json!({
        "port": port,
        "duration_s": 8.0,
        "autopilot_system_id": 1,
        "our_system_id": 1,
        "our_component_id": cfg.component_id,
        "signing_key_hex": key_hex,
        "gps_id": out.gps_id,
        "gps_satellites": out.gps_satellites,
        "max_age_s": out.max_age_s,
        "dop_uere_m": DOP_UERE_M,
        "injected": ["GPS_INPUT", "VISION_POSITION_ESTIMATE", "ODOMETRY", "GLOBAL_POSITION_SENSOR"],
        "streams": streams,
        "origin": {"lat_deg": origin.lat_deg, "lon_deg": origin.lon_deg, "alt_amsl_m": origin.alt_amsl_m},
        "estimate": {
            "lat_deg": est.lat_deg, "lon_deg": est.lon_deg, "alt_amsl_m": est.alt_amsl_m,
            "geoid_undulation_m": -27.25,
            "vel_ned_m_s": [1.5, -0.75, 0.2],
            "rpy_rad": rpy,
            "pos_cov_ned_m2": pos_cov,
            "vel_cov_ned_m2_s2": vel_cov,
            "att_sigma_rad": [0.01, 0.015, 0.04],
            "reset_counter": 7,
        },
    });
    let exp_file = dir.path().join("expected.json");
    let report_file = dir.path().join("report.json");
    std::fs::write(&exp_file, serde_json::to_string_pretty(&expected).unwrap()).unwrap();
    let child = Command::new(&py)
        .arg(repo().join("scripts/interop/fake_autopilot.py"))
        .arg(&exp_file)
        .arg(&report_file)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start python");
    // Give the script time to bind its UDP port before we send.
    tokio::time::sleep(Duration::from_millis(1500)).await;

    let link = Link::start(cfg, out).await.unwrap();
    let mut status = link.status();
    let ready = tokio::time::timeout(
        Duration::from_secs(5),
        status.wait_for(|s| s.autopilot.is_some() && s.time_synced && s.origin.is_some()),
    )
    .await
    .map(|r| r.map(|s| s.clone())); // never hold the watch's read guard
    if let Ok(Ok(s)) = &ready {
        let o = s.origin.unwrap();
        assert!((o.lat_deg - origin.lat_deg).abs() < 1e-7, "{o:?}");
        assert!((o.alt_amsl_m - origin.alt_amsl_m).abs() < 1e-3, "{o:?}");
    }
    let clock = link.clock();
    let started = Instant::now();
    let waiter = tokio::task::spawn_blocking(move || child.wait_with_output());
    // Inject until the script ends (it listens for 8 s).
    while started.elapsed() < Duration::from_secs(10) && !waiter.is_finished() {
        if let Some(now) = clock.autopilot_now_us() {
            let e = NavEstimate {
                t_boot_us: now.saturating_sub(20_000),
                ..est.clone()
            };
            link.inject(&e).await;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let output = waiter.await.unwrap().unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout);
    eprintln!("{stdout}");
    eprintln!("{}", String::from_utf8_lossy(&output.stderr));
    link.shutdown().await;
    assert!(
        ready.is_ok(),
        "link was not ready (lock, time sync, origin)"
    );
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&report_file).unwrap()).unwrap();
    eprintln!("report: {report:#}");
    assert!(
        output.status.success(),
        "pymavlink checks failed:\n{stdout}"
    );
    assert!(report["passed"].as_u64().unwrap() > 200, "{report}");
    for m in [
        "GPS_INPUT",
        "VISION_POSITION_ESTIMATE",
        "ODOMETRY",
        "GLOBAL_POSITION_SENSOR",
    ] {
        assert!(
            report["counts"][m].as_u64().unwrap_or(0) >= 20,
            "{m}: {report}"
        );
    }
}
