//! Clean shutdown: SIGTERM resolves `shutdown_signal`, and `Link::shutdown` leaves a complete,
//! decodable .tlog behind.

use std::time::Duration;

use visnav::link::config::{LinkConfig, OutputConfig};
use visnav::link::{Link, shutdown_signal};
use visnav::sitl::autopilot::{AutopilotEmulator, ConstantVelocity, EmulatorConfig};

#[cfg(unix)]
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_then_shutdown_flushes_the_tlog() {
    let port = std::net::UdpSocket::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let truth = ConstantVelocity {
        lat_deg: 47.0,
        lon_deg: -97.0,
        alt_amsl_m: 300.0,
        vel_ned_m_s: [0.0; 3],
        yaw_rad: 0.0,
    };
    let _emu = AutopilotEmulator::start(
        EmulatorConfig::new(&format!("udpout:127.0.0.1:{port}")),
        truth,
    )
    .await
    .unwrap();
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = LinkConfig::new(&format!("udpin:127.0.0.1:{port}"));
    cfg.tlog = Some(dir.path().join("run-{t}.tlog"));
    let link = Link::start(cfg, OutputConfig::default()).await.unwrap();
    let waiter = tokio::spawn(shutdown_signal());
    // Let the link lock on and record, and the handler install.
    tokio::time::sleep(Duration::from_millis(2500)).await;
    let status = std::process::Command::new("kill")
        .arg("-TERM")
        .arg(std::process::id().to_string())
        .status()
        .unwrap();
    assert!(status.success());
    let which = tokio::time::timeout(Duration::from_secs(5), waiter)
        .await
        .expect("signal seen")
        .unwrap()
        .unwrap();
    assert_eq!(which, "SIGTERM");
    link.shutdown().await;
    let file = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.extension().is_some_and(|e| e == "tlog"))
        .expect("a .tlog named with the start time");
    let bytes = std::fs::read(&file).unwrap();
    let recs = visnav::link::tlog::read_tlog(&bytes);
    assert!(recs.len() > 5, "{} records", recs.len());
    // Every byte belongs to a complete record (nothing half-written at shutdown).
    let total: usize = recs.iter().map(|(_, p)| 8 + p.len()).sum();
    assert_eq!(total, bytes.len());
}
