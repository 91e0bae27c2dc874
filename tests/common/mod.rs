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
