//! Hostile and faulty MAVLink traffic against the real link over loopback UDP: a hand-driven fake
//! autopilot (raw MAVLink 2 frames on a socket, so it can send anything: stale clocks, impossible
//! origins, clock jumps), a gimbal that speaks first, a local process spraying junk at the
//! daemon's `udpin` port.

use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use mavlink::dialects::ardupilotmega::{
    ATTITUDE_DATA, GPS_GLOBAL_ORIGIN_DATA, HEARTBEAT_DATA, MavAutopilot, MavMessage, MavModeFlag,
    MavState, MavType, SYSTEM_TIME_DATA, TIMESYNC_DATA,
};
use mavlink::{MAVLinkV2MessageRaw, MavHeader, MavlinkReader, SigningConfig, SigningData};
use tokio::net::UdpSocket;
use tokio::sync::watch;
use visnav::link::Link;
use visnav::link::config::{LinkConfig, OutputConfig, OutputMode, SigningSettings};

use crate::common;
use common::{free_udp_port, nav_estimate as estimate, wait_for};

/// A fake vehicle component on its own socket: sends what the test says, answers TIMESYNC with
/// its boot clock, records what it receives.
struct Fake {
    sock: Arc<UdpSocket>,
    to: SocketAddr,
    sys: u8,
    comp: u8,
    boot: Instant,
    seq: std::sync::atomic::AtomicU8,
    signing: Option<SigningData>,
    received: Arc<Mutex<Vec<MavMessage>>>,
    rx_task: tokio::task::JoinHandle<()>,
}

impl Drop for Fake {
    fn drop(&mut self) {
        self.rx_task.abort();
    }
}

impl Fake {
    async fn new(to: SocketAddr, sys: u8, comp: u8, key: Option<[u8; 32]>) -> Arc<Fake> {
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
                        let mut raw = MAVLinkV2MessageRaw::new();
                        raw.serialize_message(
                            MavHeader {
                                system_id: u32::from(sys),
                                component_id: comp,
                                sequence: 0,
                            },
                            &reply,
                        );
                        let _ = s.send_to(raw.raw_bytes(), from).await;
                    }
                    r.lock().unwrap().push(m);
                }
            }
        });
        Arc::new(Fake {
            sock,
            to,
            sys,
            comp,
            boot,
            seq: 0.into(),
            signing: key.map(|k| SigningData::from_config(SigningConfig::new(k, 0, true, false))),
            received,
            rx_task,
        })
    }

    /// Boot time as the autopilot reports it (5 s at creation), ms.
    fn boot_ms(&self) -> u32 {
        self.boot.elapsed().as_millis() as u32 + 5000
    }

    async fn send(&self, msg: &MavMessage) {
        let header = MavHeader {
            system_id: u32::from(self.sys),
            component_id: self.comp,
            sequence: self.seq.fetch_add(1, std::sync::atomic::Ordering::Relaxed),
        };
        let mut raw = MAVLinkV2MessageRaw::new();
        match &self.signing {
            Some(s) => {
                raw.serialize_message_for_signing(header, msg);
                s.sign_message(&mut raw);
            }
            None => raw.serialize_message(header, msg),
        }
        self.sock.send_to(raw.raw_bytes(), self.to).await.unwrap();
    }

    async fn heartbeat(&self, mavtype: MavType, autopilot: MavAutopilot) {
        self.send(&MavMessage::HEARTBEAT(HEARTBEAT_DATA {
            custom_mode: 0,
            mavtype,
            autopilot,
            base_mode: MavModeFlag::empty(),
            system_status: MavState::MAV_STATE_ACTIVE,
            mavlink_version: 3,
        }))
        .await;
    }

    async fn attitude(&self, time_boot_ms: u32) {
        self.send(&MavMessage::ATTITUDE(ATTITUDE_DATA {
            time_boot_ms,
            ..ATTITUDE_DATA::DEFAULT
        }))
        .await;
    }

    async fn system_time(&self, time_boot_ms: u32, time_unix_usec: u64) {
        self.send(&MavMessage::SYSTEM_TIME(SYSTEM_TIME_DATA {
            time_unix_usec,
            time_boot_ms,
        }))
        .await;
    }

    fn received(&self) -> Vec<MavMessage> {
        self.received.lock().unwrap().clone()
    }
}

/// Send a live ArduCopter stream (heartbeat 2 Hz, ATTITUDE 50 Hz, SYSTEM_TIME 2 Hz with UTC
/// `utc(k)` µs minus boot µs at message k) until the returned sender says stop.
fn live_stream(ap: Arc<Fake>, utc: fn(u64) -> i64) -> watch::Sender<bool> {
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
            ap.attitude(ms).await;
            if k.is_multiple_of(25) {
                ap.heartbeat(
                    MavType::MAV_TYPE_QUADROTOR,
                    MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA,
                )
                .await;
                let unix = 1_704_067_200_000_000i64 + utc(k / 25) + i64::from(ms) * 1000;
                ap.system_time(ms, unix as u64).await;
            }
            k += 1;
        }
    });
    stop
}

async fn udpin_link(cfg: impl FnOnce(&mut LinkConfig)) -> (Link, SocketAddr) {
    let port = free_udp_port();
    let addr: SocketAddr = format!("127.0.0.1:{port}").parse().unwrap();
    let mut c = LinkConfig::new(&format!("udpin:{addr}"));
    c.heartbeat_timeout_s = 1.0;
    cfg(&mut c);
    let out = OutputConfig {
        modes: vec![OutputMode::GpsInput, OutputMode::VisionPositionEstimate],
        rate_hz: 20.0,
        ..OutputConfig::default()
    };
    (Link::start(c, out).await.unwrap(), addr)
}

/// Item 8: a gimbal's HEARTBEAT (with a flight-stack autopilot field) arriving first, and a second
/// vehicle, never take the lock from the autopilot; a silent autopilot is replaced by the next.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn only_a_vehicle_autopilot_is_locked_onto() {
    let (link, addr) = udpin_link(|_| {}).await;
    let mut status = link.status();
    let gimbal = Fake::new(addr, 42, 154, None).await;
    let camera = Fake::new(addr, 1, 100, None).await;
    for _ in 0..5 {
        gimbal
            .heartbeat(
                MavType::MAV_TYPE_GIMBAL,
                MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA,
            )
            .await;
        camera
            .heartbeat(
                MavType::MAV_TYPE_CAMERA,
                MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA,
            )
            .await;
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert!(
        status.borrow().autopilot.is_none(),
        "{:?}",
        status.borrow().autopilot
    );
    let ap = Fake::new(addr, 1, 1, None).await;
    let stop = live_stream(ap.clone(), |_| 0);
    let s = wait_for(&mut status, 5.0, "lock-on", |s| s.autopilot.is_some()).await;
    let a = s.autopilot.unwrap();
    assert_eq!((a.system_id, a.component_id), (1, 1));
    // A second vehicle while the first is alive: ignored.
    let other = Fake::new(addr, 2, 1, None).await;
    for _ in 0..10 {
        other
            .heartbeat(
                MavType::MAV_TYPE_FIXED_WING,
                MavAutopilot::MAV_AUTOPILOT_PX4,
            )
            .await;
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert_eq!(status.borrow().autopilot.map(|a| a.system_id), Some(1));
    // The first falls silent for more than the heartbeat timeout: the second takes over.
    let _ = stop.send(true);
    tokio::time::sleep(Duration::from_millis(1300)).await;
    for _ in 0..5 {
        other
            .heartbeat(
                MavType::MAV_TYPE_FIXED_WING,
                MavAutopilot::MAV_AUTOPILOT_PX4,
            )
            .await;
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let s = wait_for(&mut status, 3.0, "relock", |s| {
        s.autopilot.is_some_and(|a| a.system_id == 2)
    })
    .await;
    assert_eq!(
        s.autopilot.map(|a| a.autopilot),
        Some(MavAutopilot::MAV_AUTOPILOT_PX4)
    );
    assert_eq!(link.metrics().relocks.get(), 1);
    link.shutdown().await;
}

/// Item 9: with `udpin`, a local process spraying one-byte junk (and, with signing on, unsigned
/// copies of the autopilot's heartbeat) at 1 kHz gets nothing; the autopilot gets the stream.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn udpin_replies_only_to_the_locked_autopilot() {
    for signed in [false, true] {
        let key: [u8; 32] = core::array::from_fn(|i| i as u8 ^ 0x3C);
        let dir = tempfile::tempdir().unwrap();
        let key_file = dir.path().join("k.key");
        std::fs::write(
            &key_file,
            key.iter().map(|b| format!("{b:02x}")).collect::<String>(),
        )
        .unwrap();
        let (link, addr) = udpin_link(|c| {
            if signed {
                c.signing = Some(SigningSettings {
                    key_file,
                    sign_outgoing: true,
                    reject_unsigned: true,
                    link_id: 0,
                });
            }
        })
        .await;
        let ap = Fake::new(addr, 1, 1, signed.then_some(key)).await;
        let thief = Fake::new(addr, 1, 1, None).await;
        let stop = live_stream(ap.clone(), |_| 0);
        let mut status = link.status();
        wait_for(&mut status, 5.0, "lock-on", |s| s.autopilot.is_some()).await;
        let t_end = Instant::now() + Duration::from_secs(3);
        let mut k = 0u32;
        while Instant::now() < t_end {
            thief.sock.send_to(&[0xFD], addr).await.unwrap();
            if signed && k.is_multiple_of(50) {
                thief
                    .heartbeat(
                        MavType::MAV_TYPE_QUADROTOR,
                        MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA,
                    )
                    .await;
            }
            k += 1;
            tokio::time::sleep(Duration::from_millis(1)).await;
        }
        let _ = stop.send(true);
        let to_ap = ap.received().len();
        let to_thief = thief.received().len();
        assert!(
            to_ap >= 3,
            "signed {signed}: the autopilot got {to_ap} messages"
        );
        assert_eq!(
            to_thief, 0,
            "signed {signed}: the junk sender got {to_thief} messages"
        );
        link.shutdown().await;
    }
}

/// Item 5: a spoofed ATTITUDE with time_boot_ms = 0 and a burst of stale messages of two kinds
/// among the live stream are dropped, never a reboot; a real reboot (silence, then every stream
/// on a new clock) is one.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn stale_messages_are_dropped_and_a_real_reboot_is_confirmed() {
    let (link, addr) = udpin_link(|c| c.autopilot_system_id = Some(1)).await;
    let mut status = link.status();
    let ap = Fake::new(addr, 1, 1, None).await;
    let stop = live_stream(ap.clone(), |_| 0);
    wait_for(&mut status, 5.0, "time sync", |s| s.time_synced).await;
    ap.attitude(0).await;
    for k in 0..300u32 {
        ap.attitude(1000 + k).await;
        ap.system_time(1000 + k, 1_704_067_200_000_000).await;
        if k.is_multiple_of(10) {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    }
    tokio::time::sleep(Duration::from_millis(700)).await;
    let s = status.borrow().clone();
    assert_eq!(s.reboots, 0);
    assert!(s.time_synced, "the stale burst broke the time sync");
    let stale = link.metrics().rx_stale.get();
    assert!(stale >= 601, "{stale} stale messages dropped");
    // A real reboot: 1.5 s of silence, then every stream on a clock that starts near 0.
    let _ = stop.send(true);
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let rebooted = Fake::new(addr, 1, 1, None).await;
    let t0 = Instant::now();
    let mut n = 0;
    while status.borrow().reboots == 0 && n < 200 {
        let ms = t0.elapsed().as_millis() as u32 + 300;
        rebooted.attitude(ms).await;
        if n % 5 == 0 {
            rebooted.system_time(ms, 0).await;
            rebooted
                .heartbeat(
                    MavType::MAV_TYPE_QUADROTOR,
                    MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA,
                )
                .await;
        }
        n += 1;
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert_eq!(
        status.borrow().reboots,
        1,
        "the real reboot was not detected"
    );
    link.shutdown().await;
}

/// Item 4: a GPS_GLOBAL_ORIGIN at latitude 190.7 deg is refused (counted, reported); a valid one
/// after it is taken.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_impossible_origin_is_refused() {
    let (link, addr) = udpin_link(|c| c.autopilot_system_id = Some(1)).await;
    let mut status = link.status();
    let ap = Fake::new(addr, 1, 1, None).await;
    let stop = live_stream(ap.clone(), |_| 0);
    wait_for(&mut status, 5.0, "lock-on", |s| s.autopilot.is_some()).await;
    let origin = |lat: f64| {
        MavMessage::GPS_GLOBAL_ORIGIN(GPS_GLOBAL_ORIGIN_DATA {
            latitude: (lat * 1e7) as i32,
            longitude: -968_000_000,
            altitude: 400_000,
            time_usec: 0,
        })
    };
    ap.send(&origin(190.7)).await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert_eq!(status.borrow().origin, None);
    assert_eq!(link.metrics().origins_refused.get(), 1);
    let texts: Vec<String> = ap
        .received()
        .iter()
        .filter_map(|m| match m {
            MavMessage::STATUSTEXT(t) => Some(t.text.to_str().unwrap_or("").to_string()),
            _ => None,
        })
        .collect();
    assert!(
        texts.iter().any(|t| t.contains("origin refused")),
        "{texts:?}"
    );
    ap.send(&origin(46.9)).await;
    let s = wait_for(&mut status, 2.0, "valid origin", |s| s.origin.is_some()).await;
    assert!((s.origin.unwrap().lat_deg - 46.9).abs() < 1e-6);
    let _ = stop.send(true);
    link.shutdown().await;
}

/// Item 6: the autopilot's UTC jumps +1 h, back a year and jitters by a second: GPS_INPUT's
/// time never goes back and does not follow the jumps (reported as steps);
/// VISION_POSITION_ESTIMATE's time strictly increases, one message per estimate.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn output_time_is_monotonic_through_clock_jumps() {
    let (link, addr) = udpin_link(|c| {
        c.autopilot_system_id = Some(1);
        c.timesync_hz = 10.0;
    })
    .await;
    let mut status = link.status();
    let ap = Fake::new(addr, 1, 1, None).await;
    // SYSTEM_TIME k (2 Hz): normal, then +1 h, then a year back, then +-1 s jitter.
    let stop = live_stream(ap.clone(), |k| match k {
        0..4 => 0,
        4..6 => 3_600_000_000,
        6..8 => -365 * 86_400_000_000,
        _ if k % 2 == 0 => 1_000_000,
        _ => -1_000_000,
    });
    wait_for(&mut status, 5.0, "time sync", |s| s.time_synced).await;
    let clock = link.clock();
    let t_end = Instant::now() + Duration::from_secs(6);
    let mut last_est = 0;
    while Instant::now() < t_end {
        if let Some(now) = clock.autopilot_now_us() {
            // A new estimate every other tick: the same one is offered twice.
            if last_est == 0 || now > last_est + 100_000 {
                last_est = now.saturating_sub(20_000);
            }
            link.inject(&estimate(last_est)).await;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let _ = stop.send(true);
    tokio::time::sleep(Duration::from_millis(100)).await;
    let got = ap.received();
    let gps: Vec<u64> = got
        .iter()
        .filter_map(|m| match m {
            MavMessage::GPS_INPUT(g) => Some(g.time_usec),
            _ => None,
        })
        .collect();
    let vpe: Vec<u64> = got
        .iter()
        .filter_map(|m| match m {
            MavMessage::VISION_POSITION_ESTIMATE(v) => Some(v.usec),
            _ => None,
        })
        .collect();
    assert!(gps.len() >= 60, "{} GPS_INPUT", gps.len());
    assert!(
        gps.windows(2).all(|w| w[1] > w[0]),
        "GPS_INPUT time went back: {gps:?}"
    );
    // It kept the first UTC mapping: within the run's length of the start, no hour or year jump.
    let span_s = (gps[gps.len() - 1] - gps[0]) as f64 * 1e-6;
    assert!(
        span_s < 10.0,
        "GPS_INPUT time followed a jump: span {span_s} s"
    );
    assert!(
        vpe.windows(2).all(|w| w[1] > w[0]),
        "VPE time not increasing: {vpe:?}"
    );
    assert!(
        vpe.len() < gps.len(),
        "an estimate was sent twice as a pose"
    );
    let steps = link.metrics().utc_steps.get();
    assert!(steps >= 5, "{steps} UTC steps reported");
    link.shutdown().await;
}

/// Item 10: `reject_unsigned` is on unless said otherwise.
#[test]
fn signing_is_fail_closed_by_default() {
    let c: LinkConfig =
        toml::from_str("connection = \"udpin:127.0.0.1:1\"\n[signing]\nkey_file = \"k\"\n")
            .unwrap();
    assert!(c.signing.unwrap().reject_unsigned);
    for f in [
        "config/px4-sitl.toml",
        "config/ardupilot-sitl.toml",
        "config/demo.toml",
    ] {
        let v: toml::Value = toml::from_str(&std::fs::read_to_string(f).unwrap()).unwrap();
        let conn = v["link"]["connection"].as_str().unwrap();
        assert!(
            !conn.contains("0.0.0.0"),
            "{f} binds every interface: {conn}"
        );
    }
}
