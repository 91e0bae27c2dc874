//! Helpers shared by the integration tests that run the autopilot emulator over loopback.
#![allow(dead_code)] // each test crate uses a subset

use visnav::sitl::autopilot::ConstantVelocity;

/// The emulator's vehicle in the link and daemon tests: level flight at 8 m/s north, 3 m/s west.
pub const TRUTH: ConstantVelocity = ConstantVelocity {
    lat_deg: 46.9,
    lon_deg: -96.8,
    alt_amsl_m: 400.0,
    vel_ned_m_s: [8.0, -3.0, 0.0],
    yaw_rad: 0.7,
};

/// A loopback UDP port free right now.
pub fn free_udp_port() -> u16 {
    std::net::UdpSocket::bind("127.0.0.1:0")
        .and_then(|s| s.local_addr())
        .map(|a| a.port())
        .expect("a free loopback UDP port")
}

/// Wait up to `secs` for the link status to satisfy `f`; panics naming `what` and the status.
pub async fn wait_for(
    rx: &mut tokio::sync::watch::Receiver<visnav::link::LinkStatus>,
    secs: f64,
    what: &str,
    f: impl Fn(&visnav::link::LinkStatus) -> bool,
) -> visnav::link::LinkStatus {
    let r = tokio::time::timeout(
        std::time::Duration::from_secs_f64(secs),
        rx.wait_for(|s| f(s)),
    )
    .await
    .map(|r| r.map(|s| s.clone()));
    match r {
        Ok(Ok(s)) => s,
        _ => panic!("timed out waiting for {what}; status {:#?}", *rx.borrow()),
    }
}

/// The short closed-loop scenario (sitl/scenarios/closed_loop_short.toml) shortened to 45 s for tests
/// about messages and faults: 700 m further east (the western fields changed between the years
/// and give few fixes, docs/closed-loop.md), legs of 25, 10 and 10 s, the GPS until 20 s, the
/// evaluation 20-45 s; its configuration `config` (a path), its camera image by absolute path.
pub fn short_demo_scenario(root: &std::path::Path, config: &std::path::Path) -> String {
    let abs = |p: &std::path::Path| format!("{:?}", p.display().to_string());
    std::fs::read_to_string(root.join("sitl/scenarios/closed_loop_short.toml"))
        .expect("read the short scenario")
        .replace("\"../../config/demo.toml\"", &abs(config))
        .replace(
            "\"../maps/naip_nd_2014.tif\"",
            &abs(&root.join("sitl/maps/naip_nd_2014.tif")),
        )
        .replace("lat_deg = 47.01279 ", "lat_deg = 47.01280 ")
        .replace("lon_deg = -99.17367", "lon_deg = -99.16446")
        .replace("duration_s = 50.0", "duration_s = 25.0")
        .replace(
            "duration_s = 20.0\nturn_rate_deg_s",
            "duration_s = 10.0\nturn_rate_deg_s",
        )
        .replace(
            "[[segments]]\nkind = \"straight\"\nduration_s = 20.0\n",
            "[[segments]]\nkind = \"straight\"\nduration_s = 10.0\n",
        )
        .replace("until_s = 30.0\nsigma_h_m", "until_s = 20.0\nsigma_h_m")
        .replace(
            "from_s = 30.0\nuntil_s = 90.0",
            "from_s = 20.0\nuntil_s = 45.0",
        )
}

/// The number `v[key][field]` of a `visnav sim --json` summary; panics naming it when missing.
pub fn json_stat(v: &serde_json::Value, key: &str, field: &str) -> f64 {
    v[key][field]
        .as_f64()
        .unwrap_or_else(|| panic!("{key}.{field} missing or not a number in {v}"))
}

/// A navigation solution over Casselton, North Dakota (healthy, moving at 8.5 m/s), stamped
/// `t_boot_us`: what the link tests inject.
pub fn nav_estimate(t_boot_us: u64) -> visnav::link::NavEstimate {
    use nalgebra::{Matrix3, UnitQuaternion, Vector3};
    visnav::link::NavEstimate {
        t_boot_us,
        lat_deg: 46.9,
        lon_deg: -96.8,
        alt_amsl_m: 400.0,
        geoid_undulation_m: Some(-27.0),
        vel_ned_m_s: Vector3::new(8.0, -3.0, 0.0),
        q_ned_body: UnitQuaternion::from_euler_angles(0.0, 0.0, 0.7),
        pos_cov_ned_m2: Matrix3::from_diagonal(&Vector3::new(4.0, 4.0, 9.0)),
        vel_cov_ned_m2_s2: Matrix3::from_diagonal_element(0.01),
        att_sigma_rad: Vector3::new(0.02, 0.02, 0.05),
        health: visnav::link::Health::Ok,
        reset_counter: 0,
    }
}

/// Waits up to `limit` for `child` to exit and returns its status; past the deadline kills it,
/// reaps it and returns `None`, so a hung child never holds a test (or its pipes) for ever.
pub fn wait_with_deadline(
    child: &mut std::process::Child,
    limit: std::time::Duration,
) -> Option<std::process::ExitStatus> {
    let deadline = std::time::Instant::now() + limit;
    loop {
        match child.try_wait() {
            Ok(Some(status)) => return Some(status),
            Ok(None) if std::time::Instant::now() < deadline => {
                std::thread::sleep(std::time::Duration::from_millis(50));
            }
            _ => {
                let _ = child.kill();
                let _ = child.wait();
                return None;
            }
        }
    }
}

/// Bytes of a child's output as text (invalid UTF-8 replaced).
pub fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

/// Panics with the exit code, stdout and stderr unless `out` is a success; `what` names the
/// command.
pub fn assert_ok(out: &std::process::Output, what: &str) {
    assert!(
        out.status.success(),
        "{what}: exit {:?}\nstdout:\n{}\nstderr:\n{}",
        out.status.code(),
        text(&out.stdout),
        text(&out.stderr)
    );
}

/// Runs `cmd` (stdout discarded, stderr captured) for at most `limit`: its exit status and
/// stderr, or `None` when it was still running (then killed, as [`wait_with_deadline`]).
pub fn stderr_within(
    cmd: &mut std::process::Command,
    limit: std::time::Duration,
) -> Option<(std::process::ExitStatus, String)> {
    use std::io::Read;
    let mut child = cmd
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("spawn the command");
    let status = wait_with_deadline(&mut child, limit)?;
    let mut err = String::new();
    if let Some(mut e) = child.stderr.take() {
        e.read_to_string(&mut err).expect("read its stderr");
    }
    Some((status, err))
}
