//! Sharing the autopilot's link with a ground station through MAVProxy (docs/first-flight.md,
//! "Sharing the link with a ground station"): the built-in autopilot emulator is MAVProxy's
//! `--master`, visnav's link listens on one `--out` and a plain UDP socket standing for the
//! ground station on the other, over real loopback sockets. visnav locks onto the autopilot and
//! receives its streams, what visnav sends (stream requests, GPS_INPUT, STATUSTEXT) reaches the
//! autopilot, and the ground station receives the autopilot's stream too, but not visnav's own
//! messages: MAVProxy passes an output's messages to the master only.
//!
//! MAVProxy comes from PyPI, pinned in scripts/interop/requirements-mavproxy.txt and installed
//! into the interop test's venv (target/pyenv) by `scripts/interop/setup_venv.sh mavproxy`.
//! When it cannot be installed (no python3, no network, a pip failure) the test prints why and
//! skips, under CI too: MAVProxy is a third party's router, not something visnav's CI must reach.

use std::collections::HashMap;
use std::fs::File;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use mavlink::dialects::ardupilotmega::{MavAutopilot, MavMessage, MavSeverity};
use mavlink::{MavlinkReader, Message};
use visnav::link::Link;
use visnav::link::config::{LinkConfig, OutputConfig, OutputMode};
use visnav::sitl::autopilot::{AutopilotEmulator, EmulatorConfig};

use crate::common;

/// A clean venv with pymavlink and MAVProxy installs in about 10 s on the project's machines; a
/// slow mirror or a network that drops packets makes pip retry for minutes. Past this it skips.
const SETUP_LIMIT: Duration = Duration::from_secs(300);

/// MAVProxy's start (Python imports its modules) plus visnav's lock-on, time sync and stream
/// checks: 5 s on an idle 2-core machine (measured), more beside a build.
const READY_LIMIT: Duration = Duration::from_secs(60);

/// How long visnav injects through MAVProxy.
const INJECT_FOR: Duration = Duration::from_secs(3);

/// visnav's ids (the link's defaults: the vehicle's system, MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY).
const VISNAV_IDS: (u32, u8) = (1, 197);

/// The emulator's ids (an ArduPilot's defaults).
const AUTOPILOT_IDS: (u32, u8) = (1, 1);

/// MAVLink message ids.
const HEARTBEAT: u32 = 0;
const ATTITUDE: u32 = 30;

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// Aborts a task when dropped: none outlives a failed test.
struct AbortOnDrop(tokio::task::JoinHandle<()>);

impl Drop for AbortOnDrop {
    fn drop(&mut self) {
        self.0.abort();
    }
}

/// Kills a child's whole process group (a script's pip, MAVProxy's helpers) and the child itself
/// when dropped, so no failure leaves a process behind; on a panic, prints the child's log.
struct ChildGuard {
    child: Child,
    log: Option<PathBuf>,
    name: &'static str,
}

impl ChildGuard {
    fn kill_all(&mut self) {
        // The child leads a process group of its own (`process_group(0)` at spawn).
        let _ = Command::new("kill")
            .args(["-KILL", "--", &format!("-{}", self.child.id())])
            .stderr(Stdio::null())
            .status();
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for ChildGuard {
    fn drop(&mut self) {
        self.kill_all();
        if std::thread::panicking()
            && let Some(log) = &self.log
        {
            let text = std::fs::read_to_string(log).unwrap_or_default();
            eprintln!(
                "--- {} output ---\n{text}--- end of {} output ---",
                self.name, self.name
            );
        }
    }
}

/// The venv python with MAVProxy, or `None` (after printing why) when it cannot be installed.
fn mavproxy_python() -> Option<PathBuf> {
    let t0 = Instant::now();
    let child = Command::new("bash")
        .arg(repo().join("scripts/interop/setup_venv.sh"))
        .arg("mavproxy")
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .process_group(0)
        .spawn();
    let child = match child {
        Ok(c) => c,
        Err(e) => {
            eprintln!("SKIP link_mavproxy: cannot run bash: {e}");
            return None;
        }
    };
    let mut guard = ChildGuard {
        child,
        log: None,
        name: "setup_venv.sh",
    };
    let Some(status) = common::wait_with_deadline(&mut guard.child, SETUP_LIMIT) else {
        guard.kill_all();
        eprintln!(
            "SKIP link_mavproxy: installing MAVProxy took more than {} s (network?)",
            SETUP_LIMIT.as_secs()
        );
        return None;
    };
    let mut out = String::new();
    if let Some(mut stdout) = guard.child.stdout.take() {
        use std::io::Read;
        let _ = stdout.read_to_string(&mut out);
    }
    if !status.success() {
        eprintln!(
            "SKIP link_mavproxy: MAVProxy could not be installed ({status}; setup_venv.sh said \
             why above)"
        );
        return None;
    }
    eprintln!(
        "venv with MAVProxy ready in {:.1} s",
        t0.elapsed().as_secs_f64()
    );
    Some(PathBuf::from(out.trim()))
}

/// MAVProxy between the autopilot (`--master`, listening on `master_port`) and two outputs.
fn start_mavproxy(py: &Path, dir: &Path, master_port: u16, outs: [u16; 2]) -> ChildGuard {
    // Run through the venv's python: a `#!` line longer than the kernel's limit (a deep
    // checkout) would not start the script on its own.
    let script = py.with_file_name("mavproxy.py");
    let log = dir.join("mavproxy.log");
    let out = File::create(&log).expect("create the MAVProxy log");
    let err = out.try_clone().expect("share the MAVProxy log");
    let child = Command::new(py)
        .arg(&script)
        .arg(format!("--master=udpin:127.0.0.1:{master_port}"))
        .arg(format!("--out=udp:127.0.0.1:{}", outs[0]))
        .arg(format!("--out=udp:127.0.0.1:{}", outs[1]))
        .args(["--daemon", "--non-interactive"])
        // Its telemetry log and state go to the test's folder; no start-up script of the
        // user's (~/.mavinit.scr) changes what it does.
        .current_dir(dir)
        .env("HOME", dir)
        .env("PYTHONUNBUFFERED", "1")
        .stdin(Stdio::null())
        .stdout(out)
        .stderr(err)
        .process_group(0)
        .spawn()
        .expect("start mavproxy.py");
    ChildGuard {
        child,
        log: Some(log),
        name: "MAVProxy",
    }
}

/// Counts per (message id, system, component) of what a UDP socket receives.
type Counts = Arc<Mutex<HashMap<(u32, u32, u8), u64>>>;

/// The ground station: a plain UDP socket decoding MAVLink with the `mavlink` crate.
fn spawn_gcs(sock: tokio::net::UdpSocket, counts: Counts) -> tokio::task::JoinHandle<()> {
    tokio::spawn(async move {
        let mut buf = vec![0u8; 65_536];
        while let Ok((n, _)) = sock.recv_from(&mut buf).await {
            let mut rd = MavlinkReader::new(&buf[..n]);
            while let Ok((h, m)) = rd.read_any_message::<MavMessage>() {
                let key = (m.message_id(), h.system_id, h.component_id);
                *counts
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .entry(key)
                    .or_default() += 1;
            }
        }
    })
}

fn count_of(counts: &HashMap<(u32, u32, u8), u64>, id: u32, ids: (u32, u8)) -> u64 {
    counts.get(&(id, ids.0, ids.1)).copied().unwrap_or(0)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn mavproxy_shares_the_link_between_visnav_and_a_ground_station() {
    let Some(py) = mavproxy_python() else { return };
    let t0 = Instant::now();
    let dir = tempfile::tempdir().expect("a temporary folder");

    // The ground station's socket stays bound from here, so its port cannot be taken meanwhile.
    let gcs_sock = tokio::net::UdpSocket::bind("127.0.0.1:0")
        .await
        .expect("bind the ground station's socket");
    let gcs_port = gcs_sock
        .local_addr()
        .expect("the ground station's address")
        .port();
    let gcs_counts = Counts::default();
    let gcs = AbortOnDrop(spawn_gcs(gcs_sock, gcs_counts.clone()));

    let master_port = common::free_udp_port();
    let visnav_port = common::free_udp_port();
    // The autopilot sends to MAVProxy's master port as an ArduPilot SITL's `--out` would.
    let emu = AutopilotEmulator::start(
        EmulatorConfig::new(&format!("udpout:127.0.0.1:{master_port}")),
        common::TRUTH,
    )
    .await
    .expect("start the autopilot emulator");
    let mut mavproxy = start_mavproxy(&py, dir.path(), master_port, [visnav_port, gcs_port]);

    // visnav listens on its output, as `--connection udp:127.0.0.1:PORT` does.
    let out = OutputConfig {
        modes: vec![OutputMode::GpsInput],
        rate_hz: 10.0,
        ..OutputConfig::default()
    };
    let link = Link::start(
        LinkConfig::new(&format!("udp:127.0.0.1:{visnav_port}")),
        out,
    )
    .await
    .expect("start visnav's link");
    let attitudes = Arc::new(std::sync::atomic::AtomicU64::new(0));
    let mut telemetry = link.telemetry();
    let counter = attitudes.clone();
    let _telemetry_task = AbortOnDrop(tokio::spawn(async move {
        use tokio::sync::broadcast::error::RecvError;
        loop {
            match telemetry.recv().await {
                Ok(t) => {
                    if matches!(t.msg, MavMessage::ATTITUDE(_))
                        && (t.header.system_id, t.header.component_id) == AUTOPILOT_IDS
                    {
                        counter.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                    }
                }
                Err(RecvError::Lagged(_)) => continue,
                Err(RecvError::Closed) => return,
            }
        }
    }));

    // 1. visnav hears the autopilot through MAVProxy: lock-on, TIMESYNC, every stream at rate.
    let mut status = link.status();
    let ready = tokio::time::timeout(
        READY_LIMIT,
        status.wait_for(|s| s.autopilot.is_some() && s.time_synced && s.streams_ok),
    )
    .await
    .map(|r| r.map(|s| s.clone())); // never hold the watch's read guard
    let s = match ready {
        Ok(Ok(s)) => s,
        _ => panic!(
            "visnav not locked, synced and streaming after {} s through MAVProxy; status: \
             connected {}, autopilot {}, time synced {}, streams ok {}",
            READY_LIMIT.as_secs(),
            status.borrow().connected,
            status.borrow().autopilot.is_some(),
            status.borrow().time_synced,
            status.borrow().streams_ok,
        ),
    };
    let ready_s = t0.elapsed().as_secs_f64();
    let ap = s.autopilot.expect("the locked autopilot");
    assert_eq!(
        (ap.system_id, ap.component_id),
        (AUTOPILOT_IDS.0 as u8, AUTOPILOT_IDS.1),
        "visnav locked onto the autopilot, not onto MAVProxy (sys 255 comp 230)"
    );
    assert_eq!(ap.autopilot, MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA);
    for st in &s.streams {
        eprintln!(
            "through MAVProxy: stream {:<20} asked {:>6.1} Hz measured {:>6.1} Hz",
            st.name, st.requested_hz, st.measured_hz
        );
    }

    // 2. visnav's messages reach the autopilot through MAVProxy: its GPS_INPUT at 10 Hz and a
    // STATUSTEXT (its stream requests already did: the emulator streams nothing unasked).
    let text = "visnav: through MAVProxy";
    link.status_text(MavSeverity::MAV_SEVERITY_INFO, text)
        .await
        .expect("send a STATUSTEXT");
    let clock = link.clock();
    let started = Instant::now();
    while started.elapsed() < INJECT_FOR {
        if let Some(now) = clock.autopilot_now_us() {
            link.inject(&common::nav_estimate(now.saturating_sub(20_000)))
                .await;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    // What is still on its way through MAVProxy.
    tokio::time::sleep(Duration::from_millis(500)).await;
    let alive = mavproxy.child.try_wait().ok().flatten().is_none();

    let got = emu.received();
    let from_visnav = |r: &&visnav::sitl::autopilot::Received| {
        (r.header.system_id, r.header.component_id) == VISNAV_IDS
    };
    let gps_inputs = got
        .iter()
        .filter(from_visnav)
        .filter(|r| matches!(r.msg, MavMessage::GPS_INPUT(_)))
        .count();
    let texts: Vec<String> = got
        .iter()
        .filter(from_visnav)
        .filter_map(|r| match &r.msg {
            MavMessage::STATUSTEXT(t) => Some(
                String::from_utf8_lossy(t.text.as_ref())
                    .trim_end_matches('\0')
                    .to_string(),
            ),
            _ => None,
        })
        .collect();
    let attitude_interval = emu.stream_interval(ATTITUDE);
    let visnav_attitudes = attitudes.load(std::sync::atomic::Ordering::Relaxed);
    let gcs_seen = gcs_counts.lock().unwrap_or_else(|e| e.into_inner()).clone();
    drop(gcs);
    link.shutdown().await;
    emu.stop();
    let mut summary: Vec<_> = gcs_seen.iter().collect();
    summary.sort();
    eprintln!(
        "ready {ready_s:.1} s after start; the autopilot received {gps_inputs} GPS_INPUT from \
         visnav in {} s and its STATUSTEXT {texts:?}; visnav received {visnav_attitudes} \
         ATTITUDE; the ground station received (id, sys, comp: count) {summary:?}; test {:.1} s",
        INJECT_FOR.as_secs(),
        t0.elapsed().as_secs_f64()
    );

    assert!(alive, "MAVProxy exited during the test");
    assert_eq!(
        attitude_interval,
        Some(Duration::from_millis(20)),
        "visnav's request for ATTITUDE at 50 Hz reached the autopilot"
    );
    assert!(
        gps_inputs >= 15,
        "{gps_inputs} of visnav's GPS_INPUT reached the autopilot in {} s at 10 Hz",
        INJECT_FOR.as_secs()
    );
    assert!(
        texts.iter().any(|t| t == text),
        "visnav's STATUSTEXT did not reach the autopilot: {texts:?}"
    );
    assert!(
        visnav_attitudes >= 50,
        "visnav received {visnav_attitudes} ATTITUDE from the autopilot"
    );

    // 3. The ground station receives the autopilot's stream, not visnav's messages.
    let hb = count_of(&gcs_seen, HEARTBEAT, AUTOPILOT_IDS);
    let att = count_of(&gcs_seen, ATTITUDE, AUTOPILOT_IDS);
    assert!(
        hb >= 2,
        "the ground station received {hb} autopilot HEARTBEAT"
    );
    assert!(
        att >= 50,
        "the ground station received {att} autopilot ATTITUDE"
    );
    let from_visnav_at_gcs: u64 = gcs_seen
        .iter()
        .filter(|((_, sys, comp), _)| (*sys, *comp) == VISNAV_IDS)
        .map(|(_, n)| n)
        .sum();
    assert_eq!(
        from_visnav_at_gcs, 0,
        "MAVProxy passes an output's messages to its master only (as docs/first-flight.md says)"
    );
    drop(mavproxy);
}
