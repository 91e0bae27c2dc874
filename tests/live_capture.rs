//! Live capture through a capture process (`[frames] source = "command"` / `"gstreamer"`) with
//! real external processes: a shell that writes a y4m file in two chunks with a pause, processes
//! that exit early, write garbage, stall or are not found (each a clear error naming the command,
//! its exit status and its stderr; no panic), the process killed when the source is dropped, and
//! a real GStreamer `videotestsrc` pipeline when `gst-launch-1.0` is installed (skipped with a
//! printed reason otherwise).

use std::path::Path;
use std::time::{Duration, Instant};

use visnav::camera::source::{CaptureTime, FramesConfig, SourceKind, open, write_y4m};
use visnav::vision::GrayImage;
use visnav_core::validate::{Base, Problems, Validate};

fn img(w: usize, h: usize, k: usize) -> GrayImage {
    GrayImage::from_fn(w, h, |x, y| ((x * 3 + y * 5 + k * 17) % 256) as f32)
}

fn sh(script: &str, args: &[&str]) -> FramesConfig {
    // $0 is the first argument, $1 the second.
    let mut argv = vec!["sh", "-c", script];
    argv.extend_from_slice(args);
    let mut c = FramesConfig::command(&argv);
    c.realtime = false; // lossless: every frame the process writes is delivered
    c
}

fn first_error(cfg: &FramesConfig) -> String {
    let mut s = open(cfg).expect("the process starts");
    for _ in 0..100 {
        match s.next_frame() {
            Ok(Some(_)) => continue,
            Ok(None) => panic!("clean end instead of an error"),
            Err(e) => return e.to_string(),
        }
    }
    panic!("no error after 100 frames");
}

#[test]
fn shell_command_streams_y4m_in_chunks() {
    let d = tempfile::tempdir().unwrap();
    let f = d.path().join("clip.y4m");
    let frames: Vec<GrayImage> = (0..6).map(|k| img(40, 30, k)).collect();
    write_y4m(&f, &frames, 25, 1).unwrap();
    let size = std::fs::metadata(&f).unwrap().len();
    // Frame size 40*30*1.5 = 1800 bytes + "FRAME\n": the first chunk ends inside frame 2.
    let cut = "4000";
    let cfg = sh(
        "head -c \"$1\" \"$0\"; sleep 0.3; tail -c +\"$(($1 + 1))\" \"$0\"",
        &[f.to_str().unwrap(), cut],
    );
    let mut p = Problems::default();
    cfg.validate_in(&Base::config_folder(d.path()), &mut p);
    assert!(p.list.is_empty(), "{:?}", p.list);

    let t0 = Instant::now();
    let mut s = open(&cfg).unwrap();
    let mut stamps = Vec::new();
    for (i, want) in frames.iter().enumerate() {
        let g = s.next_frame().unwrap().expect("a frame");
        assert_eq!(g.seq, i as u64);
        assert_eq!(&g.image, want, "frame {i}");
        match g.t_capture {
            CaptureTime::Companion(t) => stamps.push(t),
            CaptureTime::AutopilotBootUs(_) => panic!("arrival stamps expected"),
        }
    }
    assert!(s.next_frame().unwrap().is_none(), "clean end after exit 0");
    assert!(s.next_frame().unwrap().is_none());
    assert!(s.describe().contains("40x30"), "{}", s.describe());
    assert_eq!(s.rate_hz(), Some(25.0));
    assert!(stamps.windows(2).all(|w| w[1] >= w[0]));
    // Arrival stamps: frames 0 and 1 came before the pause, frame 2 after it.
    let pause = stamps[2].duration_since(stamps[1]);
    eprintln!(
        "{} bytes in 2 chunks; gap at the pause {:.0} ms; total {:.0} ms",
        size,
        pause.as_secs_f64() * 1e3,
        t0.elapsed().as_secs_f64() * 1e3
    );
    assert!(pause >= Duration::from_millis(250), "{pause:?}");
    assert!(stamps[0] >= t0);
}

#[test]
fn process_that_exits_early_is_a_clear_error() {
    let cfg = sh("echo 'no camera at /dev/video9' >&2; exit 3", &[]);
    let e = first_error(&cfg);
    eprintln!("{e}");
    for want in [
        "capture command `sh -c",
        "before a YUV4MPEG2 header",
        "exit status: 3",
        "no camera at /dev/video9",
    ] {
        assert!(e.contains(want), "{want:?} not in {e}");
    }

    // Ends inside frame 2 and fails.
    let d = tempfile::tempdir().unwrap();
    let f = d.path().join("clip.y4m");
    write_y4m(
        &f,
        &(0..4).map(|k| img(16, 8, k)).collect::<Vec<_>>(),
        10,
        1,
    )
    .unwrap();
    let cfg = sh(
        "head -c 500 \"$0\"; echo 'device lost' >&2; exit 1",
        &[f.to_str().unwrap()],
    );
    let mut s = open(&cfg).unwrap();
    // 16*8*1.5 + 6 = 198 bytes per frame after a ~40-byte header: frames 0 and 1 are whole.
    assert!(s.next_frame().unwrap().is_some());
    assert!(s.next_frame().unwrap().is_some());
    let e = s.next_frame().unwrap_err().to_string();
    eprintln!("{e}");
    for want in ["frame 2", "truncated", "exit status: 1", "device lost"] {
        assert!(e.contains(want), "{want:?} not in {e}");
    }
    // The error stays.
    assert!(s.next_frame().is_err());

    // A program that does not exist: an error at start, naming it.
    let cfg = FramesConfig::command(&["visnav-no-such-capture-program", "-x"]);
    let e = open(&cfg).err().expect("start fails").to_string();
    assert!(
        e.contains("visnav-no-such-capture-program") && e.contains("cannot start"),
        "{e}"
    );
    let mut p = Problems::default();
    cfg.validate_in(&Base::config_folder(Path::new("/")), &mut p);
    assert!(
        p.list
            .iter()
            .any(|i| i.key == "command" && i.reason.contains("not found")),
        "{:?}",
        p.list
    );
}

#[test]
fn garbage_output_is_a_clear_error() {
    // Random bytes: never a y4m header.
    let e = first_error(&sh("head -c 200000 /dev/urandom", &[]));
    eprintln!("{e}");
    assert!(
        e.contains("not YUV4MPEG2") || e.contains("before a YUV4MPEG2 header"),
        "{e}"
    );
    // Text on stdout (a gst-launch without -q prints its state changes).
    let e = first_error(&sh("echo 'Setting pipeline to PAUSED ...'", &[]));
    assert!(e.contains("not YUV4MPEG2") && e.contains("-q"), "{e}");
    // A valid header, then garbage where a frame should start.
    let e = first_error(&sh(
        "printf 'YUV4MPEG2 W8 H8 F10:1 C420jpeg\\n'; head -c 5000 /dev/urandom",
        &[],
    ));
    eprintln!("{e}");
    assert!(e.contains("frame 0") && e.contains("FRAME"), "{e}");
    // An absurd size in the header is refused before any allocation.
    let e = first_error(&sh(
        "printf 'YUV4MPEG2 W16384 H16384 F10:1 C444p16\\n'",
        &[],
    ));
    assert!(e.contains("exceeds"), "{e}");
}

#[test]
fn stalled_process_times_out_and_is_killed_on_drop() {
    let d = tempfile::tempdir().unwrap();
    let pid_file = d.path().join("pid");
    // Header, one frame, then silence (exec: the kill reaches the sleeping process itself).
    let script =
        "echo $$ > \"$0\"; printf 'YUV4MPEG2 W2 H2 F10:1 Cmono\\nFRAME\\nabcd'; exec sleep 30";
    let mut cfg = sh(script, &[pid_file.to_str().unwrap()]);
    cfg.timeout_s = 0.5;
    let mut s = open(&cfg).unwrap();
    let f = s.next_frame().unwrap().unwrap();
    assert_eq!(f.image.data(), &[97.0, 98.0, 99.0, 100.0]);
    let t0 = Instant::now();
    let e = s.next_frame().unwrap_err().to_string();
    let waited = t0.elapsed();
    eprintln!("{e} (after {waited:?})");
    assert!(
        e.contains("no new frame for 0.5 s") && e.contains("timeout_s"),
        "{e}"
    );
    assert!(waited >= Duration::from_millis(450), "{waited:?}");
    let pid: u32 = std::fs::read_to_string(&pid_file)
        .unwrap()
        .trim()
        .parse()
        .unwrap();
    assert!(
        !Path::new(&format!("/proc/{pid}")).exists(),
        "process {pid} still alive after the timeout"
    );

    // Killed on drop while streaming.
    let pid_file2 = d.path().join("pid2");
    let script = "echo $$ > \"$0\"; printf 'YUV4MPEG2 W2 H2 F10:1 Cmono\\n'; exec sleep 30";
    let cfg = sh(script, &[pid_file2.to_str().unwrap()]);
    let s = open(&cfg).unwrap();
    let t0 = Instant::now();
    while !s.describe().contains("2x2") {
        assert!(t0.elapsed() < Duration::from_secs(10), "no header");
        std::thread::sleep(Duration::from_millis(20));
    }
    let pid: u32 = std::fs::read_to_string(&pid_file2)
        .unwrap()
        .trim()
        .parse()
        .unwrap();
    assert!(Path::new(&format!("/proc/{pid}")).exists());
    drop(s);
    assert!(
        !Path::new(&format!("/proc/{pid}")).exists(),
        "process {pid} still alive after drop"
    );
}

#[test]
fn config_keys_of_live_sources() {
    let c: FramesConfig = toml::from_str(
        "source = \"command\"\ncommand = [\"ffmpeg\", \"-f\", \"v4l2\", \"-i\", \"/dev/video0\", \"-f\", \"yuv4mpegpipe\", \"-\"]\nlatency_s = 0.05\n",
    )
    .unwrap();
    assert_eq!(c.source, SourceKind::Command);
    assert_eq!(c.argv()[0], "ffmpeg");
    assert_eq!((c.timeout_s, c.latency_s), (5.0, 0.05));
    let mut p = Problems::default();
    let mut bad = c.clone();
    bad.rate_hz = Some(10.0);
    bad.path = "x.y4m".into();
    bad.command.clear();
    bad.timeout_s = 0.0;
    bad.validate_in(&Base::config_folder(Path::new("/")), &mut p);
    let keys: Vec<&str> = p.list.iter().map(|i| i.key.as_str()).collect();
    for k in ["command", "rate_hz", "path", "timeout_s"] {
        assert!(keys.contains(&k), "{k} not in {:?}", p.list);
    }
    let g: FramesConfig = toml::from_str(
        "source = \"gstreamer\"\npipeline = \"v4l2src device=/dev/video0 ! video/x-raw,width=640\"\n",
    )
    .unwrap();
    let argv = g.argv();
    assert_eq!(&argv[..2], ["gst-launch-1.0", "-q"]);
    assert_eq!(
        argv[2..].join(" "),
        "v4l2src device=/dev/video0 ! video/x-raw,width=640 ! videoconvert ! \
         video/x-raw,format=I420 ! y4menc ! fdsink fd=1"
    );
    let mut p = Problems::default();
    FramesConfig::new(SourceKind::Gstreamer, "").validate(&mut p);
    assert!(p.list.iter().any(|i| i.key == "pipeline"), "{:?}", p.list);
    let mut p = Problems::default();
    FramesConfig::new(SourceKind::Y4m, "").validate(&mut p);
    assert!(p.list.iter().any(|i| i.key == "path"), "{:?}", p.list);
    // A relative program path is relative to the config folder.
    let mut r = FramesConfig::command(&["./capture.sh", "a/b"]);
    r.resolve_paths(&Base::config_folder(Path::new("/etc/visnav")));
    assert_eq!(r.command, ["/etc/visnav/./capture.sh", "a/b"]);
}

#[test]
fn gstreamer_videotestsrc_pipeline() {
    let found = std::env::var_os("PATH")
        .is_some_and(|p| std::env::split_paths(&p).any(|d| d.join("gst-launch-1.0").is_file()));
    if !found {
        eprintln!(
            "SKIP: gst-launch-1.0 is not installed (gstreamer1.0-tools, -plugins-base, -plugins-good)"
        );
        return;
    }
    let mut cfg = FramesConfig::new(SourceKind::Gstreamer, "");
    cfg.pipeline = Some(
        "videotestsrc num-buffers=20 pattern=ball ! video/x-raw,width=160,height=120,framerate=30/1"
            .into(),
    );
    cfg.realtime = false;
    cfg.timeout_s = 30.0;
    let mut p = Problems::default();
    cfg.validate_in(&Base::config_folder(Path::new("/")), &mut p);
    assert!(p.list.is_empty(), "{:?}", p.list);
    let mut s = open(&cfg).unwrap();
    let mut n = 0;
    let mut prev: Option<GrayImage> = None;
    let mut changed = 0;
    while let Some(f) = s.next_frame().unwrap_or_else(|e| panic!("{e}")) {
        assert_eq!((f.image.width(), f.image.height()), (160, 120));
        assert_eq!(f.seq, n);
        let (lo, hi) = f
            .image
            .data()
            .iter()
            .fold((f32::MAX, f32::MIN), |(a, b), &v| (a.min(v), b.max(v)));
        assert!(hi - lo > 100.0, "flat frame {n}: {lo}..{hi}");
        if prev.as_ref().is_some_and(|p| p != &f.image) {
            changed += 1;
        }
        prev = Some(f.image);
        n += 1;
    }
    eprintln!("{}: {n} frames, {changed} changed", s.describe());
    assert_eq!(n, 20);
    assert!(changed >= 10, "the ball does not move: {changed}");
    assert!(s.describe().contains("160x120"));
}

/// Counts frames and rejects them (tests the plumbing, not the vision fix).
struct CountingFixer(std::sync::atomic::AtomicU64);

impl visnav::daemon::FrameFixer for CountingFixer {
    fn fix(&self, image: &GrayImage, prior: &visnav::fix::FixPrior) -> visnav::fix::FixReport {
        assert_eq!((image.width(), image.height()), (32, 24));
        let n = self.0.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        // A reason with numbers, as the engine's are: the counters must keep them.
        let reason = visnav::fix::Rejection::Internal {
            stage: "test engine",
            detail: format!("no map under frame {n} (32 x 24 px)"),
        };
        visnav::fix::FixReport::rejected(reason, prior.t_capture_us, 0.0)
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn daemon_runs_a_live_capture_process_and_kills_it_on_shutdown() {
    use std::sync::Arc;
    use visnav::daemon::{Daemon, DaemonConfig, DaemonSetup};
    use visnav::link::config::{LinkConfig, OutputConfig, OutputMode};
    use visnav::sitl::autopilot::{AutopilotEmulator, ConstantVelocity, EmulatorConfig};

    let d = tempfile::tempdir().unwrap();
    // Two 32x24 frames, written in turn again and again at about 20 Hz by a shell loop (the
    // same frame twice in a row would be dropped as a frozen camera).
    for (name, seed) in [("a", 1), ("b", 2)] {
        let clip = d.path().join(format!("{name}.y4m"));
        write_y4m(&clip, &[img(32, 24, seed)], 20, 1).unwrap();
        let bytes = std::fs::read(&clip).unwrap();
        let split = bytes.iter().position(|&b| b == b'\n').unwrap() + 1;
        std::fs::write(d.path().join("header"), &bytes[..split]).unwrap();
        std::fs::write(d.path().join(format!("frame_{name}")), &bytes[split..]).unwrap();
    }
    let pid_file = d.path().join("pid");
    let script = "echo $$ > pid; cat header; while cat frame_a && sleep 0.05 && cat frame_b; do sleep 0.05; done";
    let mut frames = FramesConfig::command(&[
        "sh",
        "-c",
        &format!("cd '{}' && {script}", d.path().display()),
    ]);
    frames.max_age_s = 5.0;

    let port = std::net::UdpSocket::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let truth = ConstantVelocity {
        lat_deg: 46.9,
        lon_deg: -96.8,
        alt_amsl_m: 400.0,
        vel_ned_m_s: [8.0, -3.0, 0.0],
        yaw_rad: 0.7,
    };
    let emu = AutopilotEmulator::start(
        EmulatorConfig::new(&format!("udpout:127.0.0.1:{port}")),
        truth,
    )
    .await
    .unwrap();
    let setup = DaemonSetup {
        link: LinkConfig::new(&format!("udpin:127.0.0.1:{port}")),
        output: OutputConfig {
            modes: vec![OutputMode::GpsInput],
            gps_id: 1,
            ..OutputConfig::default()
        },
        nav: visnav::nav::NavConfig {
            max_imu_gap_s: 0.5,
            ..Default::default()
        },
        daemon: DaemonConfig {
            imu_timeout_s: 1.0,
            ..DaemonConfig::default()
        },
        frames: Some(frames),
        vo: Default::default(),
        dtm_nav: Default::default(),
    };
    let fixer = Arc::new(CountingFixer(Default::default()));
    let daemon = Daemon::start(setup, Some(fixer.clone())).await.unwrap();
    let t0 = Instant::now();
    while daemon.metrics().fixes_attempted < 10 {
        assert!(
            t0.elapsed() < Duration::from_secs(20),
            "no fixes from the capture process: {:?}",
            daemon.metrics()
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let m = daemon.shutdown().await;
    emu.stop();
    eprintln!(
        "frames in {}, attempted {}, superseded {}, stale {}, no time {}",
        m.frames_in, m.fixes_attempted, m.frames_superseded, m.frames_stale, m.frames_no_time
    );
    assert!(m.frames_in >= 10 && m.frame_errors == 0, "{m:?}");
    // Every engine call is accounted for: its rejection reached the navigation task, or it
    // finished after shutdown began and is counted as dropped.
    // Counted by class (`fix::Rejection::class`): the check's name without its details.
    let rejected = m.engine_rejected.iter().find(|r| r.class == "internal");
    assert_eq!(
        rejected.map_or(0, |r| r.count) + m.fixes_dropped_at_shutdown,
        fixer.0.load(std::sync::atomic::Ordering::Relaxed),
        "{m:?}"
    );
    // What `visnav run` logs at its end shows the reason with its numbers, beside its count and
    // class; no number stands in as a placeholder.
    let line = visnav::daemon::final_counters(&m);
    if let Some(r) = rejected {
        assert!(
            r.reason.starts_with("test engine: no map under frame ")
                && r.reason.ends_with(" (32 x 24 px)"),
            "{r:?}"
        );
        let json = serde_json::to_string(&r.reason).unwrap();
        assert!(
            line.contains(&format!(r#""reason":{json},"count":{}"#, r.count)),
            "{line}"
        );
    }
    assert!(!line.contains(" N "), "{line}");
    let pid: u32 = std::fs::read_to_string(&pid_file)
        .unwrap()
        .trim()
        .parse()
        .unwrap();
    assert!(
        !Path::new(&format!("/proc/{pid}")).exists(),
        "capture process {pid} still alive after the daemon's shutdown"
    );
}
