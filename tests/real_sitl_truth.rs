//! The truth connection to a real SITL (`visnav::sitl::real_sitl`) over real loopback UDP: a
//! tokio task plays the simulator (ArduPilot: ATTITUDE + SIM_STATE + SIMSTATE; PX4:
//! HIL_STATE_QUATERNION) with the `mavlink` crate, and the feed must decode latitude, longitude,
//! altitude, velocity, attitude and time exactly, ask for the truth messages with
//! MAV_CMD_SET_MESSAGE_INTERVAL, and ignore another system.

use std::collections::HashSet;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use mavlink::dialects::ardupilotmega::{
    ATTITUDE_DATA, HEARTBEAT_DATA, HIL_STATE_QUATERNION_DATA, MavAutopilot, MavCmd, MavMessage,
    MavType, SIM_STATE_DATA, SIMSTATE_DATA,
};
use mavlink::{AsyncMavConnection, MavHeader};
use nalgebra::UnitQuaternion;
use tokio::sync::Mutex;
use visnav::sitl::camera_sim::TruthFeed;
use visnav::sitl::real_sitl::{SitlKind, TruthLink, TruthLinkConfig};

use crate::common;
use common::free_udp_port;

type Conn = mavlink::AsyncConnection<MavMessage>;

/// Plays a simulator as system `sysid`: a HEARTBEAT every second and, every 20 ms, those of
/// `msgs(k)` whose id was asked for with SET_MESSAGE_INTERVAL (as ArduPilot, which streams
/// nothing else until asked), or all of them when `unasked` (an intruder). Collects the asked ids.
/// `msgs` returning `None` ends the simulator (it sends nothing more, not even HEARTBEATs).
fn play(
    conn: Arc<Conn>,
    sysid: u8,
    unasked: bool,
    msgs: impl Fn(u32) -> Option<Vec<MavMessage>> + Send + 'static,
    asked: Arc<Mutex<HashSet<u32>>>,
) -> tokio::task::JoinHandle<()> {
    let rx = conn.clone();
    let asked_rx = asked.clone();
    tokio::spawn(async move {
        while let Ok((_, m)) = rx.recv().await {
            if let MavMessage::COMMAND_LONG(c) = m
                && c.command == MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL
            {
                asked_rx.lock().await.insert(c.param1 as u32);
            }
        }
    });
    tokio::spawn(async move {
        let mut k = 0u32;
        loop {
            let Some(mut out) = msgs(k) else {
                return;
            };
            if !unasked {
                let a = asked.lock().await;
                out.retain(|m| a.contains(&mavlink::Message::message_id(m)));
            }
            if k.is_multiple_of(50) {
                out.push(MavMessage::HEARTBEAT(HEARTBEAT_DATA {
                    mavtype: MavType::MAV_TYPE_QUADROTOR,
                    autopilot: MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA,
                    ..HEARTBEAT_DATA::DEFAULT
                }));
            }
            for m in out {
                let h = MavHeader {
                    system_id: u32::from(sysid),
                    component_id: 1,
                    sequence: (k % 256) as u8,
                };
                let _ = conn.send(&h, &m).await;
            }
            k += 1;
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
}

/// A simulator-side connection to the truth link on loopback port `port`.
async fn simulator(port: u16, what: &str) -> Arc<Conn> {
    Arc::new(
        mavlink::connect_async::<MavMessage>(&format!("udpout:127.0.0.1:{port}"))
            .await
            .unwrap_or_else(|e| panic!("{what}: {e}")),
    )
}

/// The truth link of `kind` listening on a free loopback port, and the simulator's side.
async fn truth_pair(kind: SitlKind) -> (u16, TruthLink, Arc<Conn>) {
    let port = free_udp_port();
    let link = TruthLink::start(TruthLinkConfig::new(
        format!("udpin:127.0.0.1:{port}"),
        kind,
    ))
    .await
    .expect("truth connection");
    let conn = simulator(port, "simulator side").await;
    (port, link, conn)
}

async fn wait_for<T>(mut f: impl FnMut() -> Option<T>) -> T {
    // The first requests go out at start; udpin learns where to reply from the first datagram,
    // so the first answered request is the one 2 s later.
    for _ in 0..800 {
        if let Some(v) = f() {
            return v;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    panic!("no truth sample within 8 s");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn ardupilot_simstate_and_sim_state_decode_exactly() {
    let (port, link, conn) = truth_pair(SitlKind::ArduPilot).await;
    // Another system first, with a different position: must be ignored.
    let intruder = simulator(port, "intruder side").await;
    let asked = Arc::new(Mutex::new(HashSet::new()));
    let intruder_task = play(
        intruder,
        7,
        true,
        |k| {
            // Only at the start, then silent, HEARTBEATs included: udpin sends to the last
            // sender, so while the intruder kept its 1 Hz HEARTBEAT some SET_MESSAGE_INTERVAL
            // requests went to it instead of the simulator (a CI run saw no truth for 8 s). The
            // real recipe has one simulator per truth port.
            if k >= 10 {
                return None;
            }
            Some(vec![
                MavMessage::ATTITUDE(ATTITUDE_DATA {
                    time_boot_ms: 1,
                    ..ATTITUDE_DATA::DEFAULT
                }),
                MavMessage::SIM_STATE(SIM_STATE_DATA {
                    alt: 5.0,
                    ..SIM_STATE_DATA::DEFAULT
                }),
                MavMessage::SIMSTATE(SIMSTATE_DATA {
                    lat: 100,
                    lng: 100,
                    ..SIMSTATE_DATA::DEFAULT
                }),
            ])
        },
        Arc::new(Mutex::new(HashSet::new())),
    );
    let sim = play(
        conn,
        1,
        false,
        |k| {
            Some(vec![
                MavMessage::ATTITUDE(ATTITUDE_DATA {
                    time_boot_ms: 600_000 + 20 * k,
                    ..ATTITUDE_DATA::DEFAULT
                }),
                MavMessage::SIM_STATE(SIM_STATE_DATA {
                    alt: 1030.25,
                    vn: 12.5,
                    ve: -3.25,
                    vd: 0.0,
                    // ArduPilot <= 4.5 writes degE7 into these floats: must not be used.
                    lat: 470_203_485.0,
                    lon: -991_548_094.0,
                    ..SIM_STATE_DATA::DEFAULT
                }),
                MavMessage::SIMSTATE(SIMSTATE_DATA {
                    roll: 0.125,
                    pitch: -0.0625,
                    yaw: -2.5,
                    xacc: 0.5,
                    yacc: 0.25,
                    zacc: -9.75,
                    xgyro: 0.0078125,
                    ygyro: -0.015625,
                    zgyro: 0.03125,
                    lat: 470_203_485,
                    lng: -991_548_094,
                }),
            ])
        },
        asked.clone(),
    );
    let feed = link.feed();
    let (t_us, s) = wait_for(|| feed.latest()).await;
    assert_eq!(s.lat_deg, 470_203_485.0 * 1e-7);
    assert_eq!(s.lon_deg, -991_548_094.0 * 1e-7);
    assert_eq!(s.alt_amsl_m, 1030.25);
    assert_eq!(s.vel_ned_m_s, [12.5, -3.25, 0.0]);
    assert_eq!(s.rpy_rad, [0.125, -0.0625, -2.5]);
    assert_eq!(s.gyro_body_rad_s, [0.0078125, -0.015625, 0.03125]);
    assert_eq!(s.accel_body_m_s2, [0.5, 0.25, -9.75]);
    // The boot time of the ATTITUDE sent with it plus the (loopback) delay between the two.
    assert!(t_us >= 600_000_000, "{t_us}");
    let ms = (t_us / 1000 - 600_000) % 20;
    assert!(
        ms <= 10,
        "t_us {t_us}: more than 10 ms after its ATTITUDE's time_boot_ms"
    );
    // Samples keep coming and time advances.
    tokio::time::sleep(Duration::from_millis(200)).await;
    let (t2, _) = feed.latest().expect("still a sample");
    assert!(t2 > t_us + 100_000, "{t2} vs {t_us}");
    // The simulator streams only what was asked: SIMSTATE, SIM_STATE and ATTITUDE were.
    assert_eq!(
        *asked.lock().await,
        HashSet::from([164u32, 108, 30]),
        "SET_MESSAGE_INTERVAL requests"
    );
    assert!(link.feed().counters.requests.load(Ordering::Relaxed) >= 3);
    sim.abort();
    intruder_task.abort();
    link.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn px4_hil_state_quaternion_decodes_exactly() {
    let (_, link, conn) = truth_pair(SitlKind::Px4).await;
    let (r, p, y) = (0.1f64, 0.05f64, 1.25f64);
    let q = UnitQuaternion::from_euler_angles(r, p, y);
    let qf = [q.w as f32, q.i as f32, q.j as f32, q.k as f32];
    let asked = Arc::new(Mutex::new(HashSet::new()));
    let sim = play(
        conn,
        1,
        false,
        move |k| {
            Some(vec![MavMessage::HIL_STATE_QUATERNION(
                HIL_STATE_QUATERNION_DATA {
                    time_usec: 90_000_000 + 20_000 * u64::from(k),
                    attitude_quaternion: qf,
                    lat: 470_100_000,
                    lon: -991_400_000,
                    alt: 1_080_500,
                    vx: 1000,
                    vy: -250,
                    vz: 30,
                    ..HIL_STATE_QUATERNION_DATA::DEFAULT
                },
            )])
        },
        asked.clone(),
    );
    let feed = link.feed();
    let (t_us, s) = wait_for(|| feed.latest()).await;
    assert_eq!((t_us - 90_000_000) % 20_000, 0, "{t_us}");
    assert_eq!((s.lat_deg, s.lon_deg), (47.01, -99.14));
    assert!((s.alt_amsl_m - 1080.5).abs() < 1e-9);
    assert_eq!(s.vel_ned_m_s, [10.0, -2.5, 0.3]);
    for (a, b) in s.rpy_rad.iter().zip([r, p, y]) {
        assert!((a - b).abs() < 1e-6, "{a} vs {b}");
    }
    assert!(
        asked.lock().await.contains(&115),
        "SET_MESSAGE_INTERVAL for 115"
    );
    sim.abort();
    link.shutdown().await;
}
