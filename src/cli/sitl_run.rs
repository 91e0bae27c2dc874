//! `visnav sitl-run --config F --truth CONN --ortho CAMERA_YEAR.tif`: the navigation service
//! against a real autopilot SITL (ArduPilot or PX4), with the camera rendered from the
//! simulator's own truth.
//!
//! The daemon is the one `visnav run` starts (`[link]`, `[output]`, `[nav]`, `[daemon]` and the
//! vision fix engine of `[map]`/`[camera]`/`[fix]` from the configuration); only the frame source
//! differs: a [`SimCamera`] rendering `--ortho` (the camera year, never the map's image) on a flat
//! ground at `--ground-height` (default `map.ground_height_amsl_m`), or the camera world of a
//! scenario's `[closed_loop]` (`--scenario`: the orthophoto on its surface model, one degraded
//! copy for the camera and another for the map), at the pose the simulator reports on a second MAVLink connection (`--truth`, [`visnav::sitl::real_sitl`]). `[frames]` in
//! the configuration is ignored. Recipes: sitl/ardupilot/run.py, sitl/px4/run.py, docs/real-sitl.md.
//!
//! At the end (SIGINT/SIGTERM or `--duration`) one JSON line goes to stdout: the daemon's
//! counters and the truth connection's.

use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context;
use visnav::daemon::config::Config;
use visnav::daemon::{Daemon, DaemonSetup, FramePipeline};
use visnav::geo::dem::Dem;
use visnav::geo::geotiff::load_geotiff;
use visnav::sitl::camera_sim::{SimCamera, SimCameraSpec, TruthFeed};
use visnav::sitl::real_sitl::{SitlKind, TruthLink, TruthLinkConfig};
use visnav::sitl::render::{ColourMode, RenderSpec, Renderer, Scene};
use visnav_core::text::num;

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum Kind {
    /// ArduPilot SITL: SIMSTATE + SIM_STATE.
    Ardupilot,
    /// PX4 SITL (SIH or Gazebo): HIL_STATE_QUATERNION.
    Px4,
}

#[derive(clap::Args, Debug)]
pub struct SitlRunArgs {
    /// The TOML configuration file (as for `visnav run`; `[frames]` is ignored).
    #[arg(long)]
    pub config: PathBuf,
    /// MAVLink connection on which the simulator sends its truth (e.g. udpin:127.0.0.1:14552).
    #[arg(long, default_value = "udpin:127.0.0.1:14552")]
    pub truth: String,
    /// Which simulator speaks on `--truth`.
    #[arg(long, value_enum, default_value = "ardupilot")]
    pub kind: Kind,
    /// The orthophoto the camera sees (the camera year, e.g. sitl/maps/naip_nd_2014.tif), on a
    /// flat ground at --ground-height.
    #[arg(long, required_unless_present = "scenario")]
    pub ortho: Option<PathBuf>,
    /// Ground height AMSL of the rendered scene, m (default: map.ground_height_amsl_m).
    #[arg(long, conflicts_with = "scenario")]
    pub ground_height: Option<f64>,
    /// Instead of --ortho: the camera world of this scenario's [closed_loop] (camera_ortho on
    /// camera_dem, camera_degrade, [closed_loop.render]), the map built from the configuration's
    /// orthophotos degraded by its map_degrade (e.g. sitl/scenarios/drone_autzen.toml).
    #[arg(long, conflicts_with = "ortho")]
    pub scenario: Option<PathBuf>,
    /// Camera frame rate, Hz.
    #[arg(long, default_value_t = 2.0)]
    pub rate_hz: f64,
    /// Rate asked for the truth messages, Hz.
    #[arg(long, default_value_t = 50.0)]
    pub truth_rate_hz: f64,
    /// Fix worker threads.
    #[arg(long, default_value_t = 1)]
    pub workers: usize,
    /// Frames older than this when a worker is free are dropped, s.
    #[arg(long, default_value_t = 1.0)]
    pub max_age_s: f64,
    /// Write the true pose of every rendered frame here (JSON lines: seq, capture time in
    /// autopilot boot µs, latitude, longitude, altitude AMSL, NED velocity, roll/pitch/yaw);
    /// with `[daemon] vo_log`, `sitl/vo_check.py` scores each visual odometry motion against it.
    #[arg(long)]
    pub truth_log: Option<PathBuf>,
    /// Stop after this many seconds (default: run until SIGINT/SIGTERM).
    #[arg(long)]
    pub duration: Option<f64>,
}

pub fn run(args: SitlRunArgs) -> anyhow::Result<ExitCode> {
    let cfg = Config::load(&args.config)?;
    if !(args.rate_hz.is_finite() && args.rate_hz > 0.0 && args.rate_hz <= 50.0) {
        anyhow::bail!("--rate-hz {}: expected 0 < rate <= 50", num(args.rate_hz));
    }
    if !(args.max_age_s.is_finite() && args.max_age_s > 0.0) {
        anyhow::bail!(
            "--max-age-s {}: expected a positive number",
            num(args.max_age_s)
        );
    }
    let duration = match args.duration {
        Some(s) if s.is_finite() && s > 0.0 && s < 1e9 => Some(Duration::from_secs_f64(s)),
        Some(s) => anyhow::bail!(
            "--duration {}: expected a positive number of seconds",
            num(s)
        ),
        None => None,
    };
    let (world, engine) = camera_world(&args, cfg.clone())?;
    let kind = match args.kind {
        Kind::Ardupilot => SitlKind::ArduPilot,
        Kind::Px4 => SitlKind::Px4,
    };
    let mut tcfg = TruthLinkConfig::new(args.truth.clone(), kind);
    tcfg.rate_hz = args.truth_rate_hz;
    if let Some(id) = cfg.link.autopilot_system_id {
        tcfg.autopilot_system_id = id;
    }
    let truth_log = match &args.truth_log {
        Some(p) => Some(
            std::fs::File::create(p)
                .with_context(|| format!("--truth-log {}: cannot create it", p.display()))?,
        ),
        None => None,
    };
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    rt.block_on(async move {
        let truth = TruthLink::start(tcfg).await?;
        eprintln!(
            "sitl-run: waiting for the simulator's truth on {}",
            args.truth
        );
        if !truth.wait_first(Duration::from_secs(120)).await {
            anyhow::bail!("no truth from the simulator on {} within 120 s", args.truth);
        }
        let feed: Arc<dyn TruthFeed> = truth.feed();
        let mut source = SimCamera::new(
            SimCameraSpec {
                scene: world.scene,
                renderer: world.renderer,
                crs: world.crs,
                mount: world.mount,
                rate_hz: args.rate_hz,
                max_frames: None,
                lockstep: false,
            },
            feed,
        );
        if let Some(f) = truth_log {
            source = source.with_truth_log(Box::new(std::io::BufWriter::new(f)));
        }
        let pipeline = FramePipeline {
            source: Box::new(source),
            lossless: false,
            max_age_s: args.max_age_s,
            workers: args.workers.max(1),
            lockstep_latency: None,
            release: visnav_daemon::frames::Release::AsRead,
        };
        let daemon =
            Daemon::start_with(DaemonSetup::from_config(&cfg), Some(engine), Some(pipeline))
                .await?;
        let limit = async {
            match duration {
                Some(t) => tokio::time::sleep(t).await,
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            s = visnav::link::shutdown_signal() => {
                eprintln!("sitl-run: {}", s.unwrap_or("signal handler failed"));
            }
            _ = limit => eprintln!("sitl-run: run duration elapsed"),
        }
        let m = daemon.shutdown().await;
        let feed = truth.feed();
        let c = &feed.counters;
        let out = serde_json::json!({
            "daemon": m,
            "truth": {
                "samples": c.samples.load(std::sync::atomic::Ordering::Relaxed),
                "rejected": c.rejected.load(std::sync::atomic::Ordering::Relaxed),
                "requests": c.requests.load(std::sync::atomic::Ordering::Relaxed),
            }
        });
        truth.shutdown().await;
        println!("{out}");
        Ok(ExitCode::SUCCESS)
    })
}

/// What the simulated camera renders and the fix engine it feeds.
struct CameraWorld {
    scene: Arc<Scene>,
    renderer: Arc<Renderer>,
    crs: visnav::geo::Crs,
    mount: visnav::camera::Mount,
}

/// The camera world of `--scenario` (its `[closed_loop]`, the map from degraded copies) or of
/// `--ortho` on a flat ground, and the fix engine built from `cfg`'s map.
fn camera_world(
    args: &SitlRunArgs,
    mut cfg: Config,
) -> anyhow::Result<(CameraWorld, Arc<dyn visnav::daemon::FrameFixer>)> {
    if let Some(path) = &args.scenario {
        let sc = visnav::sitl::Scenario::load(path)?;
        let base = path.parent().unwrap_or(std::path::Path::new("."));
        let cam = visnav::sitl::closed_loop::scenario_camera(&sc, base, &mut cfg, &args.config)
            .with_context(|| format!("--scenario {}", path.display()))?;
        let engine = visnav::daemon::fixer_from_config(&cfg)
            .with_context(|| format!("{}: vision fix engine", args.config.display()))?;
        drop(cam.map_copies);
        let world = CameraWorld {
            scene: cam.scene,
            renderer: cam.renderer,
            crs: cam.crs,
            mount: cam.mount,
        };
        return Ok((world, engine));
    }
    let Some(ortho) = &args.ortho else {
        anyhow::bail!("give --ortho or --scenario");
    };
    let ground_m = match (args.ground_height, cfg.map.ground_height_amsl_m) {
        (Some(h), _) | (None, Some(h)) if h.is_finite() => h,
        _ => anyhow::bail!(
            "give --ground-height (the configuration has no finite map.ground_height_amsl_m)"
        ),
    };
    let engine = visnav::daemon::fixer_from_config(&cfg)
        .with_context(|| format!("{}: vision fix engine", args.config.display()))?;
    let camera = cfg
        .camera
        .build()
        .with_context(|| format!("{}: [camera]", args.config.display()))?;
    let mount = camera.mount;
    let raster = load_geotiff(ortho, cfg.map.crs_override)
        .with_context(|| format!("--ortho {}", ortho.display()))?;
    let crs = raster.crs();
    let dem = Dem::flat(ground_m).with_context(|| format!("--ground-height {ground_m}"))?;
    let scene = Scene::new(&raster, dem, ColourMode::Grey)
        .with_context(|| format!("--ortho {}: scene", ortho.display()))?;
    let renderer = Renderer::new(camera, RenderSpec::default()).context("camera renderer")?;
    let world = CameraWorld {
        scene: Arc::new(scene),
        renderer: Arc::new(renderer),
        crs,
        mount,
    };
    Ok((world, engine))
}
