//! The daemon end to end over real loopback UDP sockets against the built-in autopilot emulator
//! (src/sitl/autopilot.rs): lock-on and stream requests, filter initialisation from the
//! emulator's GPS, GPS_INPUT injection at `output.rate_hz` compared with the emulator's truth,
//! no injection while the IMU stream is gone (and recovery), clean shutdown; the frame path with
//! a test fix engine that returns the emulator's truth plus noise (a test of the PLUMBING, not of
//! the vision fix), vision-only initialisation, backpressure with a slow engine, stale frames,
//! and `visnav run` as a subprocess.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use mavlink::dialects::ardupilotmega::MavMessage;
use visnav::camera::source::{FramesConfig, SourceKind, write_y4m};
use visnav::daemon::{Daemon, DaemonConfig, DaemonSetup, FrameFixer, FramePipeline};
use visnav::fix::{FixPrior, FixReport};
use visnav::geo::{AutopilotFrame, GeoOrigin};
use visnav::link::config::{LinkConfig, OutputConfig, OutputMode};
use visnav::nav::NavConfig;
use visnav::sitl::autopilot::{AutopilotEmulator, EmulatorConfig, TruthSource};
use visnav::vision::GrayImage;
use visnav_core::rng::Rng;

use crate::common;
use common::{TRUTH, free_udp_port};

async fn emulator(port: u16, gps: bool) -> AutopilotEmulator {
    let mut cfg = EmulatorConfig::new(&format!("udpout:127.0.0.1:{port}"));
    cfg.gps_fix = gps;
    AutopilotEmulator::start(cfg, TRUTH).await.unwrap()
}

/// GPS_INPUT into the second GPS instance, so the emulator's GPS_RAW_INT (GPS1) is the real GPS.
fn setup(port: u16) -> DaemonSetup {
    let nav = NavConfig {
        // A loaded 2-core test machine delays the emulator's 100 Hz IMU now and then.
        max_imu_gap_s: 0.5,
        ..NavConfig::default()
    };
    DaemonSetup {
        link: LinkConfig::new(&format!("udpin:127.0.0.1:{port}")),
        output: OutputConfig {
            modes: vec![OutputMode::GpsInput],
            rate_hz: 5.0,
            gps_id: 1,
            ..OutputConfig::default()
        },
        nav,
        daemon: DaemonConfig {
            imu_timeout_s: 1.0,
            ..DaemonConfig::default()
        },
        frames: None,
        vo: Default::default(),
        dtm_nav: Default::default(),
    }
}

async fn wait_until(secs: f64, what: &str, mut f: impl FnMut() -> bool) {
    let t0 = Instant::now();
    while !f() {
        if t0.elapsed().as_secs_f64() > secs {
            panic!("timed out after {secs} s waiting for {what}");
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

fn initialised(d: &Daemon) -> bool {
    d.nav_outputs().borrow().is_some()
}

/// (arrival boot time µs, GPS_INPUT) received since `from_us`.
fn gps_inputs(
    emu: &AutopilotEmulator,
    from_us: u64,
) -> Vec<(u64, mavlink::dialects::ardupilotmega::GPS_INPUT_DATA)> {
    emu.received()
        .into_iter()
        .filter(|r| r.t_boot_us >= from_us)
        .filter_map(|r| match r.msg {
            MavMessage::GPS_INPUT(g) => Some((r.t_boot_us, g)),
            _ => None,
        })
        .collect()
}

/// Largest 3D distance between GPS_INPUT positions and the truth at their arrival.
fn max_error_m(gps: &[(u64, mavlink::dialects::ardupilotmega::GPS_INPUT_DATA)]) -> f64 {
    let mut max = 0.0f64;
    for (t, g) in gps {
        for v in [
            g.alt,
            g.vn,
            g.ve,
            g.vd,
            g.hdop,
            g.vdop,
            g.horiz_accuracy,
            g.vert_accuracy,
        ] {
            assert!(v.is_finite(), "non-finite GPS_INPUT field: {g:?}");
        }
        let s = TRUTH.state(*t as f64 * 1e-6);
        let o = GeoOrigin {
            lat_deg: s.lat_deg,
            lon_deg: s.lon_deg,
            alt_amsl_m: s.alt_amsl_m,
        };
        let d = AutopilotFrame::Tangent.to_ned(
            &o,
            g.lat as f64 * 1e-7,
            g.lon as f64 * 1e-7,
            g.alt as f64,
        );
        max = max.max(d.norm());
    }
    max
}

fn statustexts(emu: &AutopilotEmulator) -> Vec<String> {
    emu.received()
        .into_iter()
        .filter_map(|r| match r.msg {
            MavMessage::STATUSTEXT(s) => Some(
                String::from_utf8_lossy(&s.text.to_vec())
                    .trim_end_matches('\0')
                    .to_string(),
            ),
            _ => None,
        })
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn gps_aided_daemon_injects_stops_without_imu_and_shuts_down() {
    let port = free_udp_port();
    let emu = emulator(port, true).await;
    let d = Daemon::start(setup(port), None).await.unwrap();

    // Lock-on, stream requests, filter initialised from the emulator's GPS.
    wait_until(15.0, "filter initialisation from GPS", || initialised(&d)).await;
    assert_eq!(emu.companion(), Some((1, 197)));
    assert_eq!(
        emu.stream_interval(26),
        Some(Duration::from_millis(10)),
        "SCALED_IMU 100 Hz"
    );
    assert_eq!(
        emu.stream_interval(24),
        Some(Duration::from_millis(200)),
        "GPS_RAW_INT 5 Hz"
    );
    assert_eq!(
        emu.stream_interval(30),
        Some(Duration::from_millis(20)),
        "ATTITUDE 50 Hz"
    );

    // Injection at 5 Hz with a small error against the truth.
    tokio::time::sleep(Duration::from_secs(1)).await;
    let t0 = emu.time_boot_us();
    tokio::time::sleep(Duration::from_secs(3)).await;
    let gps = gps_inputs(&emu, t0);
    let err = max_error_m(&gps);
    let m = d.metrics();
    eprintln!(
        "{} GPS_INPUT in 3 s, max error vs truth {err:.2} m; imu {} outputs {} lagged {}",
        gps.len(),
        m.imu_samples,
        m.nav_outputs,
        m.telemetry_lagged
    );
    assert!(
        (11..=17).contains(&gps.len()),
        "{} GPS_INPUT in 3 s at 5 Hz",
        gps.len()
    );
    assert!(
        gps.iter()
            .all(|(_, g)| g.gps_id == 1 && g.satellites_visible == 10)
    );
    assert!(err < 5.0, "max position error {err} m");
    assert!(m.imu_samples > 200, "{m:?}");

    // The IMU (with everything else) stops: nothing is injected, STATUSTEXT says why.
    emu.set_muted(true);
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let t_quiet = emu.time_boot_us();
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let during = gps_inputs(&emu, t_quiet);
    assert!(
        during.is_empty(),
        "{} GPS_INPUT while the IMU was silent",
        during.len()
    );
    let texts = statustexts(&emu);
    eprintln!("STATUSTEXT: {texts:?}");
    assert!(
        texts
            .iter()
            .any(|t| t.contains("lost") && t.contains("no IMU")),
        "{texts:?}"
    );
    assert!(d.metrics().imu_timeouts >= 1);

    // The IMU comes back: the filter re-initialises from GPS and injection resumes.
    emu.set_muted(false);
    let t_back = emu.time_boot_us();
    wait_until(15.0, "injection to resume", || {
        !gps_inputs(&emu, t_back).is_empty()
    })
    .await;
    // Health texts are sent on changes only, not on every estimate.
    let n_texts = statustexts(&emu).len();
    assert!(
        n_texts < 12,
        "{n_texts} STATUSTEXT: {:?}",
        statustexts(&emu)
    );

    // Clean shutdown: returns promptly and nothing is sent afterwards.
    let t_stop = Instant::now();
    let fin = tokio::time::timeout(Duration::from_secs(10), d.shutdown())
        .await
        .expect("shutdown within 10 s");
    eprintln!(
        "shutdown in {:.2} s; {fin:?}",
        t_stop.elapsed().as_secs_f64()
    );
    tokio::time::sleep(Duration::from_millis(300)).await;
    let n = emu.received_counts().values().sum::<u64>();
    tokio::time::sleep(Duration::from_millis(1000)).await;
    assert_eq!(
        n,
        emu.received_counts().values().sum::<u64>(),
        "traffic after shutdown"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn autopilot_reboot_restarts_the_filter_and_injection_resumes() {
    let port = free_udp_port();
    let emu = emulator(port, true).await;
    let d = Daemon::start(setup(port), None).await.unwrap();
    wait_until(15.0, "filter initialisation from GPS", || initialised(&d)).await;
    wait_until(5.0, "first GPS_INPUT", || !gps_inputs(&emu, 0).is_empty()).await;
    tokio::time::sleep(Duration::from_secs(2)).await;
    emu.reboot();
    wait_until(10.0, "the reboot to be seen", || {
        d.metrics().autopilot_reboots >= 1
    })
    .await;
    // The emulator's truth runs on its run time (a reboot restarts only the boot clock the
    // messages carry): wait for injection on the new boot clock, then compare five injections
    // with the truth at their arrival.
    wait_until(15.0, "GPS_INPUT after the reboot", || {
        emu.received()
            .iter()
            .any(|r| r.boot == 1 && matches!(r.msg, MavMessage::GPS_INPUT(_)))
    })
    .await;
    // Five injections from 0.5 s later on: the rate is not asserted here (a loaded 2-core CI
    // machine starves the emulator and the daemon alike; the 5 Hz rate is asserted by the
    // GPS-aided test), only that injection continues and follows the truth.
    let t0 = emu.time_boot_us() + 500_000;
    let after_reboot = || -> Vec<_> {
        emu.received()
            .into_iter()
            .filter(|r| r.boot == 1 && r.t_boot_us >= t0)
            .filter_map(|r| match r.msg {
                MavMessage::GPS_INPUT(g) => Some((r.t_run_us, g)),
                _ => None,
            })
            .collect()
    };
    wait_until(15.0, "five GPS_INPUT after the reboot", || {
        after_reboot().len() >= 5
    })
    .await;
    let after = after_reboot();
    let err = max_error_m(&after);
    let m = d.shutdown().await;
    eprintln!(
        "after reboot: {} GPS_INPUT over {:.1} s, max error {err:.2} m; {m:?}",
        after.len(),
        after
            .last()
            .map_or(0, |(t, _)| *t)
            .saturating_sub(emu.run_us_of_boot_us(t0)) as f64
            / 1e6
    );
    assert!(err < 5.0, "{err}");
    assert_eq!(m.autopilot_reboots, 1);
}

/// A test fix engine: the emulator's truth at the capture time plus white noise, after a
/// delay. Records the priors it was given.
struct TruthPlusNoise {
    sigma_m: f64,
    delay: Duration,
    rng: Mutex<Rng>,
    calls: AtomicU64,
    with_position: AtomicU64,
    prior_err_m: Mutex<Vec<f64>>,
}

impl TruthPlusNoise {
    fn new(sigma_m: f64, delay: Duration) -> Arc<Self> {
        Arc::new(Self {
            sigma_m,
            delay,
            rng: Mutex::new(Rng::new(7)),
            calls: AtomicU64::new(0),
            with_position: AtomicU64::new(0),
            prior_err_m: Mutex::new(Vec::new()),
        })
    }
}

impl FrameFixer for TruthPlusNoise {
    fn fix(&self, image: &GrayImage, prior: &FixPrior) -> FixReport {
        assert_eq!((image.width(), image.height()), (32, 24));
        std::thread::sleep(self.delay);
        self.calls.fetch_add(1, Ordering::Relaxed);
        let s = TRUTH.state(prior.t_capture_us as f64 * 1e-6);
        let o = GeoOrigin {
            lat_deg: s.lat_deg,
            lon_deg: s.lon_deg,
            alt_amsl_m: s.alt_amsl_m,
        };
        if let Some(p) = prior.position {
            self.with_position.fetch_add(1, Ordering::Relaxed);
            let d = AutopilotFrame::Tangent.to_ned(&o, p.lat_deg, p.lon_deg, p.alt_amsl_m);
            self.prior_err_m.lock().unwrap().push(d.norm());
        }
        let (dn, de, dd) = {
            let mut r = self.rng.lock().unwrap();
            (
                r.normal() * self.sigma_m,
                r.normal() * self.sigma_m,
                r.normal() * self.sigma_m,
            )
        };
        let (lat, lon, alt) = visnav::geo::local::offset_geodetic(
            s.lat_deg,
            s.lon_deg,
            s.alt_amsl_m,
            &nalgebra::Vector3::new(dn, de, dd),
        );
        let n = visnav::geo::geoid::geoid_undulation_m(lat, lon).unwrap();
        let v = self.sigma_m * self.sigma_m;
        let mut r = FixReport::rejected(
            visnav::fix::Rejection::NoHypothesis,
            prior.t_capture_us,
            0.0,
        );
        r.accepted = true;
        r.rejection = None;
        r.lat_deg = lat;
        r.lon_deg = lon;
        r.alt_amsl_m = alt;
        r.h_ellip_m = alt + n;
        r.cov_ned_m2 = [[v, 0.0, 0.0], [0.0, v, 0.0], [0.0, 0.0, v]];
        r
    }

    /// As a tiled map's fixer would: a tile loaded per frame, three in memory.
    fn paging(&self) -> Option<visnav::map::paged::PagingStats> {
        Some(visnav::map::paged::PagingStats {
            loads: self.calls.load(Ordering::Relaxed),
            resident_tiles: 3,
            resident_bytes: 3 << 20,
            ..Default::default()
        })
    }
}

fn y4m(dir: &std::path::Path, n: usize, fps: u32) -> std::path::PathBuf {
    let frames: Vec<GrayImage> = (0..n)
        .map(|i| GrayImage::from_fn(32, 24, |x, y| ((x * 7 + y * 3 + i) % 256) as f32))
        .collect();
    let p = dir.join("flight.y4m");
    write_y4m(&p, &frames, fps, 1).unwrap();
    p
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn frame_plumbing_vision_only_init_with_truth_plus_noise_fixer() {
    let port = free_udp_port();
    let emu = emulator(port, false).await; // no GPS: the filter must start from vision
    let dir = tempfile::tempdir().unwrap();
    let mut s = setup(port);
    let mut fc = FramesConfig::new(SourceKind::Y4m, y4m(dir.path(), 400, 10));
    fc.max_age_s = 0.5;
    s.frames = Some(fc);
    let fix_log = dir.path().join("fixes.jsonl");
    s.daemon.fix_log = Some(fix_log.clone());
    let fixer = TruthPlusNoise::new(1.5, Duration::from_millis(30));
    let d = Daemon::start(s, Some(fixer.clone() as Arc<dyn FrameFixer>))
        .await
        .unwrap();
    wait_until(15.0, "filter initialisation from vision fixes", || {
        initialised(&d)
    })
    .await;
    tokio::time::sleep(Duration::from_secs(2)).await;
    let t0 = emu.time_boot_us();
    tokio::time::sleep(Duration::from_secs(3)).await;
    let gps = gps_inputs(&emu, t0);
    let err = max_error_m(&gps);
    let m = d.metrics();
    let perr = fixer.prior_err_m.lock().unwrap().clone();
    let perr_max = perr.iter().skip(5).fold(0.0f64, |a, b| a.max(*b));
    eprintln!(
        "{} GPS_INPUT in 3 s, max error {err:.2} m; fixer calls {}, with a position prior {}, \
         max prior error after the first 5 {perr_max:.2} m; {m:?}",
        gps.len(),
        fixer.calls.load(Ordering::Relaxed),
        fixer.with_position.load(Ordering::Relaxed)
    );
    assert!((11..=17).contains(&gps.len()), "{} GPS_INPUT", gps.len());
    assert!(err < 6.0, "max position error {err} m");
    assert!(m.fixes_accepted >= 10, "{m:?}");
    assert_eq!(m.fixes_filter_rejected, 0, "{m:?}");
    assert!(
        m.fixes_unused_before_init >= 1,
        "init waits for spaced fixes: {m:?}"
    );
    // Priors: none before initialisation (global relocalisation), then from the filter.
    let calls = fixer.calls.load(Ordering::Relaxed);
    let with_pos = fixer.with_position.load(Ordering::Relaxed);
    assert!(with_pos > 0 && with_pos < calls, "{with_pos} of {calls}");
    assert!(perr_max < 10.0, "prior error {perr_max} m");
    assert!(m.fix_latency_ms_max >= 30, "{m:?}");
    assert_eq!(m.queue_depth_max, 1);
    // The fixer's paging counters are the daemon's metrics after every fix.
    assert!(m.map_tile_loads > 0 && m.map_tile_loads <= calls, "{m:?}");
    assert_eq!(
        (m.map_tiles_resident, m.map_tile_bytes_resident),
        (3, 3 << 20)
    );
    let m = d.shutdown().await;
    // The fix log has one record per result the navigation task received, with its outcome.
    let log =
        visnav::daemon::fixlog::read_fix_log(&std::fs::read_to_string(&fix_log).unwrap()).unwrap();
    let count = |o: &str| log.iter().filter(|r| r.outcome == o).count() as u64;
    eprintln!("fix log: {} records", log.len());
    assert_eq!(count("unused_before_init"), m.fixes_unused_before_init);
    assert!(count("accepted") + count("initialised") + count("held") >= 10);
    assert_eq!(
        count("accepted") + count("initialised") + count("held") + count("reset"),
        m.fixes_accepted
    );
    for r in &log {
        assert!(
            r.accepted && r.lat_deg.is_some() && r.cov_ned_m2.is_some(),
            "{r:?}"
        );
        assert!(r.arrival_unix_us > 1_700_000_000_000_000);
    }
    assert!(
        log.windows(2)
            .all(|w| w[0].arrival_unix_us <= w[1].arrival_unix_us)
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn slow_fixer_drops_frames_and_never_blocks_imu() {
    let port = free_udp_port();
    let emu = emulator(port, true).await;
    let dir = tempfile::tempdir().unwrap();
    let path = y4m(dir.path(), 600, 30);
    let fixer = TruthPlusNoise::new(1.5, Duration::from_millis(400));
    let fp = FramePipeline::open(&FramesConfig::new(SourceKind::Y4m, &path)).unwrap();
    let d = Daemon::start_with(
        setup(port),
        Some(fixer.clone() as Arc<dyn FrameFixer>),
        Some(fp),
    )
    .await
    .unwrap();
    wait_until(15.0, "filter initialisation", || initialised(&d)).await;
    let m0 = d.metrics();
    let t0 = Instant::now();
    tokio::time::sleep(Duration::from_secs(4)).await;
    let m1 = d.metrics();
    let dt = t0.elapsed().as_secs_f64();
    let imu_hz = (m1.imu_samples - m0.imu_samples) as f64 / dt;
    eprintln!("IMU {imu_hz:.1} Hz processed while a 400 ms fix engine ran; {m1:?}");
    // 30 fps into a 2.5 fps engine: most frames are replaced in the one-frame queue.
    assert!(m1.frames_superseded > m1.fixes_attempted, "{m1:?}");
    assert_eq!(m1.queue_depth_max, 1, "the queue is bounded at one frame");
    assert!(m1.frames_in >= m1.frames_superseded + m1.fixes_attempted);
    // The IMU keeps flowing at its rate (100 Hz requested; half of it is a generous floor for a
    // loaded machine) and nothing was lost from the telemetry channel.
    assert!(imu_hz > 50.0, "{imu_hz} Hz");
    assert_eq!(m1.telemetry_lagged, 0);
    assert!(m1.fixes_accepted >= 3, "{m1:?}");
    let texts_before = emu.received().len();
    let fin = tokio::time::timeout(Duration::from_secs(10), d.shutdown())
        .await
        .expect("shutdown while a slow fix is running");
    assert!(fin.fixes_attempted >= m1.fixes_attempted);
    assert!(texts_before > 0);

    // Lossless replay with a short maximum age: frames wait for the busy worker and go stale.
    let port = free_udp_port();
    let _emu2 = emulator(port, true).await;
    let mut fc = FramesConfig::new(SourceKind::Y4m, &path);
    fc.realtime = false;
    fc.max_age_s = 0.1;
    let fp = FramePipeline::open(&fc).unwrap();
    let d = Daemon::start_with(
        setup(port),
        Some(fixer.clone() as Arc<dyn FrameFixer>),
        Some(fp),
    )
    .await
    .unwrap();
    wait_until(15.0, "frames to go stale", || d.metrics().frames_stale >= 2).await;
    let m = d.shutdown().await;
    eprintln!("lossless: {m:?}");
    assert_eq!(
        m.frames_superseded, 0,
        "lossless mode never replaces frames"
    );
}

#[test]
fn visnav_run_subprocess_injects_and_reports() {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .unwrap();
    let port = free_udp_port();
    let emu = rt.block_on(emulator(port, true));
    let dir = tempfile::tempdir().unwrap();
    // `run` validates what `check-config` validates: a placeholder
    // orthophoto is refused before anything starts, [frames] or not.
    std::fs::write(dir.path().join("ortho.tif"), b"placeholder: not a GeoTIFF").unwrap();
    let base = format!(
        "[link]\nconnection = \"udpin:127.0.0.1:{port}\"\n\
         [camera]\nwidth_px = 640\nheight_px = 480\nhfov_deg = 60.0\n\
         [map]\northo = [\"ortho.tif\"]\nground_height_amsl_m = 300.0\n\
         [output]\nmodes = [\"gps_input\"]\nrate_hz = 5.0\ngps_id = 1\n\
         [nav]\nmax_imu_gap_s = 0.5\n\
         [daemon]\nimu_timeout_s = 1.0\n"
    );
    let cfg = dir.path().join("run.toml");
    std::fs::write(&cfg, &base).unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_visnav"))
        .args(["run", "--config"])
        .arg(&cfg)
        .output()
        .unwrap();
    assert!(!out.status.success());
    let e = String::from_utf8_lossy(&out.stderr);
    assert!(e.contains("map.ortho") && e.contains("ortho.tif"), "{e}");
    // With a real orthophoto (the bundled NAIP excerpt) it runs and injects.
    let naip = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("sitl/maps/naip_nd_2009.tif");
    let base = base.replace(
        "\"ortho.tif\"",
        &format!("{:?}", naip.display().to_string()),
    );
    std::fs::write(&cfg, &base).unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_visnav"))
        .args(["run", "--config"])
        .arg(&cfg)
        .args(["--duration", "8"])
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    let m: serde_json::Value = serde_json::from_str(stdout.trim()).expect("JSON counters");
    assert!(m["imu_samples"].as_u64().unwrap() > 100, "{m}");
    let n_gps = emu
        .received()
        .iter()
        .filter(|r| matches!(r.msg, MavMessage::GPS_INPUT(_)))
        .count();
    eprintln!("visnav run: {n_gps} GPS_INPUT; {m}");
    assert!(n_gps >= 5, "{n_gps} GPS_INPUT; {stderr}");

    // A misspelt key in [frames] names the key.
    std::fs::write(dir.path().join("a.y4m"), b"YUV4MPEG2 W2 H2 F1:1\n").unwrap();
    std::fs::write(
        &cfg,
        format!("{base}[frames]\nsource = \"y4m\"\npath = \"a.y4m\"\nfps = 3\n"),
    )
    .unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_visnav"))
        .args(["run", "--config"])
        .arg(&cfg)
        .output()
        .unwrap();
    let e = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && e.contains("fps"), "{e}");
    drop(emu);
}

/// The emulator's vehicle with jMAVSim's IMU noise (0.006 rad/s, 0.03 m/s^2 per sample) and
/// PX4's EKF2 bias estimate, which a PX4-like emulator subtracts from HIGHRES_IMU.
struct NoisyPx4 {
    rng: Mutex<Rng>,
}

const EKF2_GYRO_BIAS: [f64; 3] = [0.002, -0.001, 0.0005];
const EKF2_ACCEL_BIAS: [f64; 3] = [0.1, -0.05, 0.02];

impl TruthSource for NoisyPx4 {
    fn state(&self, t_s: f64) -> visnav::sitl::autopilot::TruthState {
        TRUTH.state(t_s)
    }
    fn imu(&self, t_s: f64) -> ([f64; 3], [f64; 3]) {
        let s = TRUTH.state(t_s);
        let mut r = self.rng.lock().unwrap();
        (
            s.gyro_body_rad_s.map(|v| v + 0.006 * r.normal()),
            s.accel_body_m_s2.map(|v| v + 0.03 * r.normal()),
        )
    }
    fn autopilot_imu_bias(&self, _t_s: f64) -> ([f64; 3], [f64; 3]) {
        (EKF2_GYRO_BIAS, EKF2_ACCEL_BIAS)
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn px4_highres_imu_bias_is_restored_over_udp() {
    let port = free_udp_port();
    let mut ecfg = EmulatorConfig::new(&format!("udpout:127.0.0.1:{port}"));
    ecfg.gps_fix = true;
    ecfg.px4_imu = true;
    let emu = AutopilotEmulator::start(
        ecfg,
        NoisyPx4 {
            rng: Mutex::new(Rng::new(3)),
        },
    )
    .await
    .unwrap();
    // Defaults but the IMU rate: `imu_bias_restore = "auto"` restores because the HEARTBEAT says
    // PX4, and the link asks PX4 for SCALED_IMU at the IMU rate by itself. 100 Hz (PX4 sends
    // 250): lighter beside the other daemon tests on a loaded CI machine.
    let mut s = setup(port);
    s.link.streams.imu_hz = 100.0;
    assert_eq!(
        s.daemon.imu_bias_restore,
        visnav::daemon::ImuBiasRestore::Auto
    );
    assert_eq!(s.link.streams.scaled_imu_hz, None);
    let d = Daemon::start(s, None).await.unwrap();
    wait_until(15.0, "filter initialisation from GPS", || initialised(&d)).await;
    assert_eq!(
        emu.stream_interval(105),
        Some(Duration::from_millis(10)),
        "HIGHRES_IMU 100 Hz"
    );
    assert_eq!(
        emu.stream_interval(26),
        Some(Duration::from_millis(10)),
        "SCALED_IMU 100 Hz beside it (automatic for PX4)"
    );
    tokio::time::sleep(Duration::from_secs(3)).await;
    let m = d.metrics();
    let b = m.imu_bias.clone().expect("restorer status in the metrics");
    eprintln!("restorer over UDP: {b:?}; imu samples {}", m.imu_samples);
    let deg_h = |v: f64| v.to_degrees() * 3600.0;
    let g = b.gyro_bias_deg_h.expect("a gyro bias estimate");
    let a = b.accel_bias_mg.expect("an accelerometer bias estimate");
    for i in 0..3 {
        // 412 / -206 / 103 deg/h and 10.2 / -5.1 / 2.0 mg added back; the tracker's noise is
        // about 5 deg/h and 0.02 mg (1 sigma) with this IMU noise.
        let want_g = deg_h(EKF2_GYRO_BIAS[i]);
        let want_a = EKF2_ACCEL_BIAS[i] / 9.806_65 * 1e3;
        assert!(
            (g[i] - want_g).abs() < 25.0,
            "gyro {i}: {} vs {want_g}",
            g[i]
        );
        assert!(
            (a[i] - want_a).abs() < 0.5,
            "accel {i}: {} vs {want_a}",
            a[i]
        );
    }
    assert_eq!(b.bootstraps, 1, "{b:?}");
    assert!(b.paired > 150 && b.unpaired * 10 < b.paired, "{b:?}");
    assert!(b.restoring && b.age_s.is_some_and(|a| a < 1.0), "{b:?}");
    let _ = tokio::time::timeout(Duration::from_secs(10), d.shutdown()).await;
}
