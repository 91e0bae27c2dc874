//! `visnav run` (a subprocess, against the autopilot emulator over loopback UDP) with a hostile
//! `[frames]` folder: twenty thousand rows naming missing images, then a row an hour, a thousand
//! days or 1e300 s after the first. The missing frames are skipped with a few warning lines, not
//! one each, and SIGINT ends the process within the shutdown deadline although the frame source
//! waits for the late frame; a time no recording has (1e300 s) is refused at the start with an
//! error naming frames.csv and the line.

use std::io::BufRead;
use std::process::{Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use visnav::daemon::THREAD_STOP_DEADLINE;
use visnav::sitl::autopilot::{AutopilotEmulator, EmulatorConfig};

use crate::common;
use common::{TRUTH, free_udp_port};

/// Rows naming images that do not exist.
const MISSING: usize = 20_000;

/// Longest the process may take to end after SIGINT: the threads' deadline, plus the link's
/// shutdown and the process's exit on a loaded 2-core machine.
fn exit_limit() -> Duration {
    THREAD_STOP_DEADLINE + Duration::from_secs(5)
}

/// What `visnav run` does with the late row.
#[derive(Clone, Copy, PartialEq)]
enum Late {
    /// A legal time: the source waits for it, and SIGINT must still end the process in time.
    Waited,
    /// Beyond any recording: the folder is refused before the source starts.
    Refused,
}

/// The late row's line in frames.csv: the header, the first image, the missing rows.
const LATE_LINE: usize = MISSING + 3;

fn run_case(late_t_s: &str, late: Late) {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .unwrap();
    let port = free_udp_port();
    let emu = rt
        .block_on(AutopilotEmulator::start(
            EmulatorConfig::new(&format!("udpout:127.0.0.1:{port}")),
            TRUTH,
        ))
        .unwrap();
    let dir = tempfile::tempdir().unwrap();
    let frames = dir.path().join("frames");
    std::fs::create_dir(&frames).unwrap();
    image::GrayImage::from_fn(64, 48, |x, y| image::Luma([((x * 7 + y * 13) % 251) as u8]))
        .save(frames.join("a.png"))
        .unwrap();
    let mut csv = String::from("file,t_s\na.png,0\n");
    for k in 1..=MISSING {
        csv.push_str(&format!("missing_{k}.png,{}\n", k as f64 * 1e-4));
    }
    csv.push_str(&format!("a.png,{late_t_s}\n"));
    std::fs::write(frames.join("frames.csv"), csv).unwrap();
    let naip = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("sitl/maps/naip_nd_2009.tif");
    let cfg = dir.path().join("run.toml");
    std::fs::write(
        &cfg,
        format!(
            "[link]\nconnection = \"udpin:127.0.0.1:{port}\"\n\
             [camera]\nwidth_px = 64\nheight_px = 48\nhfov_deg = 60.0\n\
             [map]\northo = [{:?}]\nground_height_amsl_m = 300.0\n\
             [output]\nmodes = [\"gps_input\"]\nrate_hz = 5.0\ngps_id = 1\n\
             [nav]\nmax_imu_gap_s = 0.5\n\
             [frames]\nsource = \"directory\"\npath = \"frames\"\n",
            naip.display().to_string()
        ),
    )
    .unwrap();
    let mut child = Command::new(env!("CARGO_BIN_EXE_visnav"))
        .args(["run", "--config"])
        .arg(&cfg)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // stderr read to its end on a thread (a full pipe would stall the daemon's writes).
    let log = Arc::new(Mutex::new(Vec::<String>::new()));
    let stderr = child.stderr.take().unwrap();
    let l = log.clone();
    let reader = std::thread::spawn(move || {
        for line in std::io::BufReader::new(stderr).lines() {
            let Ok(line) = line else { return };
            l.lock().unwrap().push(line);
        }
    });
    let said = |what: &str| log.lock().unwrap().iter().any(|l| l.contains(what));
    let t0 = Instant::now();
    while !said("frames: image directory") {
        if let Some(st) = child.try_wait().unwrap() {
            reader.join().unwrap();
            let log = log.lock().unwrap().join("\n");
            assert!(
                late == Late::Refused
                    && !st.success()
                    && log.contains(&format!(
                        "frames.csv:{LATE_LINE}: t_s {late_t_s} is outside"
                    )),
                "t = {late_t_s}: visnav run ended ({st}): {log}"
            );
            // The value is quoted short, not as its 301 digits.
            assert!(log.len() < 2000, "{log}");
            eprintln!("t = {late_t_s}: refused at the start: {log}");
            return;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(120),
            "the frame source never started: {:#?}",
            log.lock().unwrap()
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    if late == Late::Refused {
        let _ = child.kill();
        let _ = child.wait();
        panic!(
            "t = {late_t_s}: the source started instead of refusing the folder: {:#?}",
            log.lock().unwrap()
        );
    }
    // The missing rows go by in well under a second; the source then waits for the last row.
    std::thread::sleep(Duration::from_secs(3));
    let pid = child.id() as libc::pid_t;
    // SAFETY: kill(2) on our own child's pid; no memory is touched.
    assert_eq!(
        unsafe { libc::kill(pid, libc::SIGINT) },
        0,
        "kill -INT failed"
    );
    let t_int = Instant::now();
    let status = loop {
        if let Some(st) = child.try_wait().unwrap() {
            break Some(st);
        }
        if t_int.elapsed() > Duration::from_secs(30) {
            let _ = child.kill();
            let _ = child.wait();
            break None;
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    let took = t_int.elapsed();
    reader.join().unwrap();
    let log = log.lock().unwrap().clone();
    let tail = log.iter().rev().take(15).collect::<Vec<_>>();
    let skipped: Vec<&String> = log.iter().filter(|l| l.contains("; skipped")).collect();
    eprintln!(
        "t = {late_t_s}: {} warning lines for {MISSING} missing frames; {:.2} s from SIGINT to \
         the end{}; the log's end:",
        skipped.len(),
        took.as_secs_f64(),
        if status.is_none() { " (killed)" } else { "" }
    );
    for l in tail.iter().rev() {
        eprintln!("  {l}");
    }
    assert!(
        !skipped.is_empty() && skipped.len() <= 3,
        "t = {late_t_s}: {} warning lines for {MISSING} missing frames; the first: {:?}",
        skipped.len(),
        skipped.first()
    );
    assert!(skipped[0].contains("WARN"), "{}", skipped[0]);
    let Some(status) = status else {
        panic!("t = {late_t_s}: visnav run still running 30 s after SIGINT (killed): {tail:#?}");
    };
    assert!(status.success(), "t = {late_t_s}: {status}: {tail:#?}");
    // The frame source polls while it waits, so its thread stops with the others rather than
    // being left behind at the deadline.
    assert!(
        !log.iter().any(|l| l.contains("visnav-frames did not stop")),
        "t = {late_t_s}: {tail:#?}"
    );
    assert!(
        took <= exit_limit(),
        "t = {late_t_s}: {:.1} s from SIGINT to exit: {tail:#?}",
        took.as_secs_f64()
    );
    let mut stdout = String::new();
    use std::io::Read;
    child
        .stdout
        .take()
        .unwrap()
        .read_to_string(&mut stdout)
        .unwrap();
    let m: serde_json::Value = serde_json::from_str(stdout.trim()).expect("JSON counters");
    assert_eq!(
        m["frame_errors"].as_u64(),
        Some(MISSING as u64),
        "every missing frame counted: {m}"
    );
    drop(emu);
}

#[test]
fn missing_frames_warn_in_a_few_lines_and_an_hour_long_gap_does_not_hold_the_shutdown() {
    run_case("3600", Late::Waited);
}

#[test]
fn a_frame_a_day_later_does_not_hold_the_shutdown() {
    run_case("86400000", Late::Waited);
}

#[test]
fn a_frame_1e300_s_later_is_refused_at_the_start_naming_frames_csv() {
    run_case("1e300", Late::Refused);
}
