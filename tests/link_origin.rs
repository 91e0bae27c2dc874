//! EKF origins that are on the Earth but not where the vehicle is (a GPS_GLOBAL_ORIGIN at
//! latitude 0, longitude 42 from the autopilot's system id on an unsigned link) against the real
//! link over loopback UDP: a hand-driven fake autopilot sends raw MAVLink 2 frames, answers
//! TIMESYNC and records what it receives; the test hands estimates to the injector. The far
//! origin is refused, counted and reported, and VISION_POSITION_ESTIMATE / ODOMETRY never stop
//! without a word.

use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use mavlink::dialects::ardupilotmega::{
    ATTITUDE_DATA, GPS_GLOBAL_ORIGIN_DATA, HEARTBEAT_DATA, MavAutopilot, MavMessage, MavModeFlag,
    MavState, MavType, SYSTEM_TIME_DATA, TIMESYNC_DATA,
};
use mavlink::{MAVLinkV2MessageRaw, MavHeader, MavlinkReader};
use tokio::net::UdpSocket;
use tokio::sync::watch;
use visnav::link::Link;
use visnav::link::config::{LinkConfig, OutputConfig, OutputMode};

use crate::common;
use common::{free_udp_port, nav_estimate as estimate, wait_for};

/// The fake autopilot (sys 1, comp 1): its socket, what it received, its boot instant.
struct Autopilot {
    sock: Arc<UdpSocket>,
    to: SocketAddr,
    boot: Instant,
    received: Arc<Mutex<Vec<MavMessage>>>,
    rx_task: tokio::task::JoinHandle<()>,
}

impl Drop for Autopilot {
    fn drop(&mut self) {
        self.rx_task.abort();
    }
}

fn frame(msg: &MavMessage) -> Vec<u8> {
    let mut raw = MAVLinkV2MessageRaw::new();
    raw.serialize_message(
        MavHeader {
            system_id: 1,
            component_id: 1,
            sequence: 0,
        },
        msg,
    );
    raw.raw_bytes().to_vec()
}

impl Autopilot {
    async fn new(to: SocketAddr) -> Arc<Autopilot> {
        let sock = Arc::new(UdpSocket::bind("127.0.0.1:0").await.unwrap());
        let received = Arc::new(Mutex::new(Vec::new()));
        let boot = Instant::now();
        let (s, r) = (sock.clone(), received.clone());
        let rx_task = tokio::spawn(async move {
            let mut buf = vec![0u8; 65_536];
            while let Ok((n, from)) = s.recv_from(&mut buf).await {
                let mut rd = MavlinkReader::new(&buf[..n]);
                while let Ok((_, m)) = rd.read_any_message::<MavMessage>() {
                    if let MavMessage::TIMESYNC(t) = &m
                        && t.tc1 == 0
                    {
                        let reply = MavMessage::TIMESYNC(TIMESYNC_DATA {
                            tc1: boot.elapsed().as_nanos() as i64 + 5_000_000_000,
                            ts1: t.ts1,
                            target_system: 0,
                            target_component: 0,
                        });
                        let _ = s.send_to(&frame(&reply), from).await;
                    }
                    r.lock().unwrap().push(m);
                }
            }
        });
        Arc::new(Autopilot {
            sock,
            to,
            boot,
            received,
            rx_task,
        })
    }

    fn boot_ms(&self) -> u32 {
        self.boot.elapsed().as_millis() as u32 + 5000
    }

    async fn send(&self, msg: &MavMessage) {
        self.sock.send_to(&frame(msg), self.to).await.unwrap();
    }

    async fn origin(&self, lat_deg: f64, lon_deg: f64) {
        self.send(&MavMessage::GPS_GLOBAL_ORIGIN(GPS_GLOBAL_ORIGIN_DATA {
            latitude: (lat_deg * 1e7) as i32,
            longitude: (lon_deg * 1e7) as i32,
            altitude: 400_000,
            time_usec: 0,
        }))
        .await;
    }

    fn count(&self, f: impl Fn(&MavMessage) -> bool) -> usize {
        self.received
            .lock()
            .unwrap()
            .iter()
            .filter(|m| f(m))
            .count()
    }

    fn texts(&self) -> Vec<String> {
        self.received
            .lock()
            .unwrap()
            .iter()
            .filter_map(|m| match m {
                MavMessage::STATUSTEXT(t) => Some(t.text.to_str().unwrap_or("").to_string()),
                _ => None,
            })
            .collect()
    }
}

/// An ArduCopter's streams (heartbeat 2 Hz, ATTITUDE 50 Hz, SYSTEM_TIME 2 Hz) until stopped.
fn live_stream(ap: Arc<Autopilot>) -> watch::Sender<bool> {
    let (stop, mut rx) = watch::channel(false);
    tokio::spawn(async move {
        let mut tick = tokio::time::interval(Duration::from_millis(20));
        let mut k = 0u64;
        loop {
            tokio::select! {
                _ = tick.tick() => {}
                _ = rx.changed() => return,
            }
            let ms = ap.boot_ms();
            ap.send(&MavMessage::ATTITUDE(ATTITUDE_DATA {
                time_boot_ms: ms,
                ..ATTITUDE_DATA::DEFAULT
            }))
            .await;
            if k.is_multiple_of(25) {
                ap.send(&MavMessage::HEARTBEAT(HEARTBEAT_DATA {
                    custom_mode: 0,
                    mavtype: MavType::MAV_TYPE_QUADROTOR,
                    autopilot: MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA,
                    base_mode: MavModeFlag::empty(),
                    system_status: MavState::MAV_STATE_ACTIVE,
                    mavlink_version: 3,
                }))
                .await;
                ap.send(&MavMessage::SYSTEM_TIME(SYSTEM_TIME_DATA {
                    time_unix_usec: 1_704_067_200_000_000 + u64::from(ms) * 1000,
                    time_boot_ms: ms,
                }))
                .await;
            }
            k += 1;
        }
    });
    stop
}

async fn link(modes: Vec<OutputMode>, set_origin: bool) -> (Link, SocketAddr) {
    let addr: SocketAddr = format!("127.0.0.1:{}", free_udp_port()).parse().unwrap();
    let mut c = LinkConfig::new(&format!("udpin:{addr}"));
    c.heartbeat_timeout_s = 1.0;
    c.autopilot_system_id = Some(1);
    let out = OutputConfig {
        modes,
        rate_hz: 20.0,
        set_origin,
        ..OutputConfig::default()
    };
    (Link::start(c, out).await.unwrap(), addr)
}

/// Hand a fresh estimate to the injector every 50 ms for `secs`.
async fn inject_for(link: &Link, secs: f64) {
    let clock = link.clock();
    let t_end = Instant::now() + Duration::from_secs_f64(secs);
    while Instant::now() < t_end {
        if let Some(now) = clock.autopilot_now_us() {
            link.inject(&estimate(now.saturating_sub(20_000))).await;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

fn is_vpe(m: &MavMessage) -> bool {
    matches!(m, MavMessage::VISION_POSITION_ESTIMATE(_))
}

fn is_odometry(m: &MavMessage) -> bool {
    matches!(m, MavMessage::ODOMETRY(_))
}

/// An origin 12,000 km from the solution arriving while the vehicle flies on a good one is
/// refused (counted, a STATUSTEXT): the pose outputs go on about the good origin.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_far_origin_is_refused_and_the_pose_outputs_go_on() {
    let (link, addr) = link(
        vec![OutputMode::VisionPositionEstimate, OutputMode::Odometry],
        false,
    )
    .await;
    let mut status = link.status();
    let ap = Autopilot::new(addr).await;
    let stop = live_stream(ap.clone());
    wait_for(&mut status, 5.0, "time sync", |s| s.time_synced).await;
    ap.origin(46.9, -96.8).await;
    wait_for(&mut status, 2.0, "the origin", |s| s.origin.is_some()).await;
    inject_for(&link, 1.0).await;
    let (vpe0, odo0) = (ap.count(is_vpe), ap.count(is_odometry));
    assert!(vpe0 >= 5 && odo0 >= 5, "{vpe0} VPE, {odo0} ODOMETRY before");

    ap.origin(0.0, 42.0).await;
    inject_for(&link, 1.5).await;
    let s = status.borrow().clone();
    let o = s.origin.expect("the good origin kept");
    assert!(
        (o.lat_deg - 46.9).abs() < 1e-6 && (o.lon_deg + 96.8).abs() < 1e-6,
        "{o:?}"
    );
    assert_eq!(s.origin_refused, None, "a usable origin stands");
    assert_eq!(link.metrics().origins_refused.get(), 1);
    assert_eq!(link.metrics().pose_output_held.get(), 0);
    let texts = ap.texts();
    assert!(
        texts.iter().any(|t| t.contains("origin refused")),
        "{texts:?}"
    );
    let (vpe1, odo1) = (ap.count(is_vpe), ap.count(is_odometry));
    assert!(
        vpe1 >= vpe0 + 10 && odo1 >= odo0 + 10,
        "the pose outputs stopped: VPE {vpe0} -> {vpe1}, ODOMETRY {odo0} -> {odo1}"
    );
    let _ = stop.send(true);
    link.shutdown().await;
}

/// A far origin as the first one (before there is a solution to judge it by) is refused at the
/// first solution: without `output.set_origin` the pose outputs are held loudly (STATUSTEXT,
/// degraded health, the status and a metric), GPS_INPUT goes on, the far origin sent again is
/// refused on arrival, and a good one brings the pose outputs back.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_far_first_origin_holds_the_pose_outputs_loudly_until_a_good_one() {
    let (link, addr) = link(
        vec![OutputMode::GpsInput, OutputMode::VisionPositionEstimate],
        false,
    )
    .await;
    let mut status = link.status();
    let ap = Autopilot::new(addr).await;
    let stop = live_stream(ap.clone());
    wait_for(&mut status, 5.0, "time sync", |s| s.time_synced).await;
    ap.origin(0.0, 42.0).await;
    wait_for(&mut status, 2.0, "the first origin", |s| s.origin.is_some()).await;
    inject_for(&link, 1.0).await;
    let s = status.borrow().clone();
    assert_eq!(s.origin, None, "the far origin is in use");
    let why = s.origin_refused.expect("why the pose outputs are held");
    assert!(why.contains("km from the navigation solution"), "{why}");
    assert_eq!(link.metrics().origins_refused.get(), 1);
    assert_eq!(link.metrics().pose_output_held.get(), 1);
    assert_eq!(ap.count(is_vpe), 0);
    let gps = ap.count(|m| matches!(m, MavMessage::GPS_INPUT(_)));
    assert!(gps >= 5, "{gps} GPS_INPUT");
    let texts = ap.texts().join(" | ");
    assert!(texts.contains("origin refused"), "{texts}");
    assert!(texts.contains("navigation degraded: no pose"), "{texts}");
    assert!(!texts.contains("navigation OK"), "{texts}");

    ap.origin(0.0, 42.0).await;
    inject_for(&link, 0.5).await;
    assert_eq!(link.metrics().origins_refused.get(), 2);
    assert_eq!(status.borrow().origin, None);

    ap.origin(46.9, -96.8).await;
    inject_for(&link, 1.0).await;
    let s = status.borrow().clone();
    assert!(s.origin.is_some() && s.origin_refused.is_none(), "{s:?}");
    assert_eq!(link.metrics().pose_output_held.get(), 0);
    let vpe = ap.count(is_vpe);
    assert!(vpe >= 5, "{vpe} VPE after a good origin");
    let _ = stop.send(true);
    link.shutdown().await;
}

/// With `output.set_origin` (the default) a far first origin is refused just as loudly, and the
/// pose outputs go on about an origin set from the solution (SET_GPS_GLOBAL_ORIGIN sent).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_far_first_origin_gives_way_to_one_set_from_the_solution() {
    let (link, addr) = link(vec![OutputMode::VisionPositionEstimate], true).await;
    let mut status = link.status();
    let ap = Autopilot::new(addr).await;
    let stop = live_stream(ap.clone());
    wait_for(&mut status, 5.0, "time sync", |s| s.time_synced).await;
    ap.origin(0.0, 42.0).await;
    wait_for(&mut status, 2.0, "the first origin", |s| s.origin.is_some()).await;
    inject_for(&link, 1.0).await;
    let s = status.borrow().clone();
    let o = s.origin.expect("an origin set from the solution");
    assert!((o.lat_deg - 46.9).abs() < 1e-6, "{o:?}");
    assert_eq!(s.origin_refused, None);
    assert_eq!(link.metrics().origins_refused.get(), 1);
    assert!(ap.texts().iter().any(|t| t.contains("origin refused")));
    #[allow(deprecated)]
    let set = ap.count(|m| matches!(m, MavMessage::SET_GPS_GLOBAL_ORIGIN(_)));
    assert!(set >= 1, "no SET_GPS_GLOBAL_ORIGIN");
    let vpe = ap.count(is_vpe);
    assert!(vpe >= 5, "{vpe} VPE");
    let _ = stop.send(true);
    link.shutdown().await;
}
