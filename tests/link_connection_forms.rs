//! Connection strings as MAVProxy and pymavlink write them, over real sockets: `udp:HOST:PORT`
//! listens (pymavlink's meaning) and receives an autopilot's MAVLink 2 HEARTBEAT; a listen port
//! another program holds is reported by `check-config` and ends `visnav run` at start, naming
//! the key and the port. And `visnav --version` names the commit.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use mavlink::dialects::ardupilotmega::{
    HEARTBEAT_DATA, MavAutopilot, MavMessage, MavModeFlag, MavState, MavType,
};
use mavlink::{MavHeader, MavlinkVersion};

use visnav::link::config::LinkConfig;
use visnav::link::config::OutputConfig;
use visnav::link::{Link, LinkError};

use crate::common;

/// The autopilot's system id in these tests.
const AUTOPILOT_SYSID: u8 = 7;

/// A real `visnav run` loads and checks the configuration (the NAIP raster) before it opens
/// anything; on a loaded 2-core machine that takes a few seconds. Far below "for ever".
const RUN_EXIT_LIMIT: Duration = Duration::from_secs(20);

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// A quadcopter ArduPilot's HEARTBEAT framed as MAVLink 2.
fn heartbeat_v2(seq: u8) -> Vec<u8> {
    let header = MavHeader {
        system_id: AUTOPILOT_SYSID.into(),
        component_id: 1,
        sequence: seq,
    };
    let msg = MavMessage::HEARTBEAT(HEARTBEAT_DATA {
        custom_mode: 0,
        mavtype: MavType::MAV_TYPE_QUADROTOR,
        autopilot: MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA,
        base_mode: MavModeFlag::empty(),
        system_status: MavState::MAV_STATE_STANDBY,
        mavlink_version: 3,
    });
    let mut buf = Vec::new();
    mavlink::write_versioned_msg(&mut buf, MavlinkVersion::V2, header, &msg).unwrap();
    buf
}

/// `udp:127.0.0.1:PORT` listens as pymavlink's `udp:` does: an autopilot that sends its
/// MAVLink 2 HEARTBEAT to that port from a socket of its own is heard and locked onto.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn udp_form_listens_and_receives_a_mavlink2_heartbeat() {
    let port = common::free_udp_port();
    let link = Link::start(
        LinkConfig::new(&format!("udp:127.0.0.1:{port}")),
        OutputConfig::default(),
    )
    .await
    .unwrap();
    let frame = heartbeat_v2(0);
    assert_eq!(frame[0], 0xFD, "a MAVLink 2 frame starts with 0xFD");
    let sender = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let stop_tx = stop.clone();
    let tx = std::thread::spawn(move || {
        let mut seq = 0u8;
        while !stop_tx.load(std::sync::atomic::Ordering::Relaxed) {
            sender
                .send_to(&heartbeat_v2(seq), ("127.0.0.1", port))
                .unwrap();
            seq = seq.wrapping_add(1);
            std::thread::sleep(Duration::from_millis(100));
        }
    });
    let mut rx = link.status();
    let s = common::wait_for(&mut rx, 10.0, "the autopilot's lock", |s| {
        s.autopilot.is_some()
    })
    .await;
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    tx.join().unwrap();
    let ap = s.autopilot.unwrap();
    assert_eq!(ap.system_id, AUTOPILOT_SYSID);
    assert_eq!(ap.vehicle, MavType::MAV_TYPE_QUADROTOR);
    link.shutdown().await;
}

/// A listen port another socket holds ends `Link::start` with an error naming the key and the
/// port, instead of a link retrying "address in use" for ever.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn link_start_refuses_a_busy_listen_port() {
    let held = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
    let port = held.local_addr().unwrap().port();
    let e = match Link::start(
        LinkConfig::new(&format!("udp:127.0.0.1:{port}")),
        OutputConfig::default(),
    )
    .await
    {
        Err(e @ LinkError::Listen { .. }) => e.to_string(),
        Err(e) => panic!("another error: {e}"),
        Ok(_) => panic!("started on a busy port"),
    };
    assert!(
        e.starts_with(&format!(
            "link.connection: \"udp:127.0.0.1:{port}\": UDP port {port} (127.0.0.1:{port}) is in use"
        )),
        "{e}"
    );
}

/// A configuration listening on `connection`, with the bundled NAIP excerpt as its map.
fn config(dir: &Path, connection: &str) -> PathBuf {
    let naip = repo().join("sitl/maps/naip_nd_2009.tif");
    let text = format!(
        "[link]\nconnection = \"{connection}\"\n\
         [camera]\nwidth_px = 640\nheight_px = 480\nhfov_deg = 60.0\n\
         [map]\northo = [{:?}]\nground_height_amsl_m = 300.0\n",
        naip.display().to_string()
    );
    let file = dir.join("busy.toml");
    std::fs::write(&file, text).unwrap();
    file
}

/// `check-config` binds and releases the listen port: one a test socket holds is a problem
/// naming `link.connection` and the port; once released, the check passes.
#[test]
fn check_config_reports_a_busy_listen_port() {
    let d = tempfile::tempdir().unwrap();
    let held = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
    let port = held.local_addr().unwrap().port();
    let file = config(d.path(), &format!("udp:127.0.0.1:{port}"));
    let out = Command::new(env!("CARGO_BIN_EXE_visnav"))
        .arg("check-config")
        .arg(&file)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(
        err.contains(&format!(
            "  link.connection: UDP port {port} (127.0.0.1:{port}) is in use by another program"
        )),
        "{err}"
    );
    drop(held);
    let out = Command::new(env!("CARGO_BIN_EXE_visnav"))
        .arg("check-config")
        .arg(&file)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        text.contains(&format!("OK (link udp:127.0.0.1:{port},")),
        "{text}"
    );
}

/// `visnav run` with its TCP listen port taken exits non-zero at start with the key and the
/// port, instead of retrying "Address already in use" for ever.
#[test]
fn run_with_a_busy_listen_port_exits_at_start() {
    let d = tempfile::tempdir().unwrap();
    let held = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let port = held.local_addr().unwrap().port();
    let file = config(d.path(), &format!("tcpin:127.0.0.1:{port}"));
    let t0 = Instant::now();
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_visnav"));
    cmd.args(["run", "--config"]).arg(&file);
    let Some((status, err)) = common::stderr_within(&mut cmd, RUN_EXIT_LIMIT) else {
        panic!(
            "visnav run still running after {} s on a busy port",
            RUN_EXIT_LIMIT.as_secs_f64()
        );
    };
    eprintln!("exited in {:.2} s", t0.elapsed().as_secs_f64());
    assert!(!status.success(), "{err}");
    assert!(
        err.contains(&format!(
            "link.connection: TCP port {port} (127.0.0.1:{port}) is in use"
        )),
        "{err}"
    );
    assert!(!err.contains("retrying"), "{err}");
    drop(held);
}

/// `--version` names the commit the binary was built from: a short hash of this repository
/// (with `-dirty` when the tree had changes), or `unknown` outside a git checkout.
#[test]
fn version_names_the_git_commit() {
    let out = Command::new(env!("CARGO_BIN_EXE_visnav"))
        .arg("--version")
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout).trim().to_string();
    assert!(out.status.success(), "{text}");
    let prefix = concat!("visnav ", env!("CARGO_PKG_VERSION"), " (commit ");
    let commit = text
        .strip_prefix(prefix)
        .and_then(|r| r.strip_suffix(')'))
        .unwrap_or_else(|| panic!("{text:?} is not {prefix:?}HASH)"));
    let in_git = Command::new("git")
        .args(["rev-parse", "--git-dir"])
        .current_dir(repo())
        .output()
        .is_ok_and(|o| o.status.success());
    if !in_git {
        assert_eq!(commit, "unknown");
        return;
    }
    let hash = commit.strip_suffix("-dirty").unwrap_or(commit);
    assert!(
        hash.len() >= 7 && hash.bytes().all(|b| b.is_ascii_hexdigit()),
        "{text}"
    );
    // A commit of this repository (HEAD may have moved since the build).
    let known = Command::new("git")
        .args(["cat-file", "-e", &format!("{hash}^{{commit}}")])
        .current_dir(repo())
        .status()
        .unwrap();
    assert!(known.success(), "{hash} is no commit here");
}
