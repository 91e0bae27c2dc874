//! The service behind `visnav run`: talks to the autopilot, runs the navigation pipeline and
//! injects the solution. An async shell around the pure modules.
//!
//! Tasks and channels (docs/architecture.md has the diagram):
//! * the link (`link::Link`): connection, lock-on, streams, TIMESYNC, and the injector task that
//!   sends the latest `watch<Option<NavEstimate>>` at `output.rate_hz` (never a lost, stale or
//!   non-finite estimate; health changes go out as STATUSTEXT).
//! * the navigation task (tokio): owns the `NavFilter`; reads `Link::telemetry()` (broadcast) and
//!   feeds IMU samples at full rate, GPS (see `[daemon] gps`), autopilot attitude and barometric
//!   altitude ([`inputs`]); takes fix results from a bounded mpsc channel and applies them as
//!   `Measurement::Vision` at their capture time (late measurements); publishes every filter
//!   output (estimate for the injector, `NavOutput` for observers, the output history for fix
//!   priors); a 100 ms watchdog declares the solution lost when the IMU stream stops.
//! * the frame path (OS threads, never on the runtime, [`frames`]): a reader thread paces the
//!   [`FrameSource`] into a one-frame slot (newest wins, replaced frames counted), `frames.workers`
//!   fix threads drop frames older than `frames.max_age_s`, build the [`FixPrior`] at the
//!   capture time and call the [`FrameFixer`].
//!
//! * the optional Prometheus endpoint (`[daemon] metrics_listen`, [`prometheus`]).
//!
//! Shutdown: [`Daemon::shutdown`] (or SIGINT/SIGTERM in [`run`]) closes the slot, stops the
//! navigation task, joins the threads (waiting at most [`THREAD_STOP_DEADLINE`] for them all: a
//! thread still busy then is left behind and ends with the process, never holds it) and shuts
//! the link down (flushing the .tlog). A second SIGINT/SIGTERM during the shutdown ends it at
//! once.

pub mod app_config;
pub mod app_config_overrides;
pub mod config;
pub mod config_reference;
pub mod fix_config;
pub mod fixlog;
pub mod frames;
pub mod handoff;
pub mod heap;
pub mod imu_bias;
pub mod inputs;
pub mod metrics;
pub mod prometheus;
pub mod replay;
pub mod unknown_keys;
pub mod vo_path;
pub mod volog;
pub mod wiring;

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;
// tokio's clock: real time, or the lock-step simulator's when the runtime runs paused.
use tokio::time::Instant;

use mavlink::dialects::ardupilotmega::{COMMAND_LONG_DATA, MavCmd, MavMessage};
use tokio::sync::{broadcast, mpsc, watch};
use tokio::task::JoinHandle;
use tracing::{Instrument, info, warn};

use app_config::Config;
use visnav_core::camera::Attitude;
use visnav_core::dtm_nav::{DtmNavConfig, DtmNavigator, DtmStep};
use visnav_core::fix::{FixPrior, FixReport};
use visnav_core::nav::{
    Health as NavHealth, Measurement, NavConfig, NavFilter, NavOutput, Outcome,
};
use visnav_core::vision::GrayImage;
use visnav_core::vo::{VoMotion, VoStep};
use visnav_io::frames::{Frame, FrameError, FrameSource, FramesConfig};
use visnav_link::config::{LinkConfig, OutputConfig};
use visnav_link::{Health as LinkHealth, Link, LinkError, LogLimiter, NavEstimate, Telemetry};

pub use config::{DaemonConfig, GpsSource, ImuBiasRestore};
pub use frames::{FixResult, Slot};
pub use metrics::{DaemonMetrics, MetricsSnapshot};
pub use wiring::engine_from_config;

use frames::PriorSource;
use inputs::{Inputs, NavInput, OutputBook};

/// The vision fix as the daemon sees it: one frame plus a prior to a report. Called on a fix
/// worker thread (blocking is fine); must not panic (a panic is caught and counted as a
/// rejection).
pub trait FrameFixer: Send + Sync + 'static {
    fn fix(&self, image: &GrayImage, prior: &FixPrior) -> FixReport;

    /// Visual odometry with this engine's camera and terrain (`[vo]`); `None`: not available.
    fn odometer(&self, _cfg: &visnav_core::vo::VoConfig) -> Option<visnav_core::vo::Odometer> {
        None
    }

    /// The DTM navigator with this engine's camera and terrain model (`[dtm_nav]`); `None`: not
    /// available.
    fn dtm_navigator(&self, _cfg: &DtmNavConfig) -> Option<DtmNavigator> {
        None
    }
}

/// Why the daemon could not start.
#[derive(Debug, thiserror::Error)]
pub enum DaemonError {
    #[error(transparent)]
    Link(#[from] LinkError),
    #[error(transparent)]
    Frames(#[from] FrameError),
    #[error("frames are configured but no vision fix engine was given")]
    NoFixer,
    #[error("cannot start a thread: {0}")]
    Thread(std::io::Error),
    #[error("daemon.vo_log: {path}: {cause}")]
    VoLog {
        path: std::path::PathBuf,
        cause: std::io::Error,
    },
    #[error("daemon.fix_log: {path}: {cause}")]
    FixLog {
        path: std::path::PathBuf,
        cause: std::io::Error,
    },
    #[error("daemon.metrics_listen: {addr}: {cause}")]
    Metrics { addr: String, cause: std::io::Error },
}

// Not `#[from]`: that would also make the error its `source()`, and the message already has its
// text (an error chain printed with `{:#}` would say it twice).
impl From<std::io::Error> for DaemonError {
    fn from(e: std::io::Error) -> Self {
        Self::Thread(e)
    }
}

/// Everything the daemon needs from the configuration.
#[derive(Debug, Clone)]
pub struct DaemonSetup {
    pub link: LinkConfig,
    pub output: OutputConfig,
    pub nav: NavConfig,
    pub daemon: DaemonConfig,
    pub frames: Option<FramesConfig>,
    /// Visual odometry (`[vo]`).
    pub vo: visnav_core::vo::VoConfig,
    /// DTM navigation (`[dtm_nav]`).
    pub dtm_nav: DtmNavConfig,
}

impl DaemonSetup {
    /// From a loaded (validated, paths resolved) configuration.
    pub fn from_config(cfg: &Config) -> Self {
        Self {
            link: cfg.link.clone(),
            output: cfg.output.clone(),
            // Vision fixes are positions of the camera: its lever arm from the mount unless
            // [nav] gives one.
            nav: cfg
                .nav
                .clone()
                .with_camera_lever_arm(cfg.camera.mount.to_mount().lever_arm_body_frd_m.into()),
            daemon: cfg.daemon.clone(),
            frames: cfg.frames.clone(),
            vo: cfg.vo.clone(),
            dtm_nav: cfg.dtm_nav.clone(),
        }
    }
}

/// An opened frame source with its pipeline settings.
pub struct FramePipeline {
    /// The source (already paced / stamped as wanted).
    pub source: Box<dyn FrameSource>,
    /// Wait for a free worker instead of dropping frames (replay without loss).
    pub lossless: bool,
    /// Frames older than this when a worker is free are dropped, s.
    pub max_age_s: f64,
    /// Number of fix worker threads.
    pub workers: usize,
    /// Lock-step (the simulator's one clock): frames taken on the runtime's clock and fixed on
    /// its blocking pool, results delivered this long after capture (`frames::lockstep_frames`)
    /// instead of the reader and worker threads. `None`: the threads (real time).
    pub lockstep_latency: Option<Duration>,
    /// When the reader hands on frames stamped on the autopilot's boot clock.
    pub release: frames::Release,
}

impl FramePipeline {
    /// Open the configured source.
    pub fn open(cfg: &FramesConfig) -> Result<Self, FrameError> {
        Ok(Self {
            source: visnav_io::frames::open(cfg)?,
            lossless: !cfg.realtime,
            max_age_s: cfg.max_age_s,
            workers: cfg.workers,
            lockstep_latency: None,
            release: if visnav_io::frames::releases_on_autopilot_clock(cfg) {
                frames::Release::OnAutopilotClock {
                    max_age_s: cfg.max_age_s,
                }
            } else {
                frames::Release::AsRead
            },
        })
    }
}

/// How long [`Daemon::shutdown`] waits for the frame threads, all together. A fix in progress
/// ends well within it (a fix takes well under a second, a widened heading search a few); a
/// thread still busy after it is stuck (a frame source blocked in a read or a long wait) and is
/// left behind: waiting longer would only keep the process from ending.
pub const THREAD_STOP_DEADLINE: Duration = Duration::from_secs(5);

/// How often shutdown looks whether the threads have ended.
const THREAD_STOP_POLL: Duration = Duration::from_millis(20);

/// Output history and autopilot attitudes shared with the fix workers.
struct SharedPriors {
    nav: NavConfig,
    book: Mutex<OutputBook>,
    attitudes: Mutex<std::collections::VecDeque<(u64, Attitude)>>,
    /// After an autopilot reboot restarted the filter: its last solution, re-stamped on the new
    /// boot clock, the fix prior's position until the new filter has an output
    /// (`inputs::reacquisition_prior`).
    reacquire: Mutex<Option<NavOutput>>,
}

impl PriorSource for SharedPriors {
    fn prior_at(&self, t_us: u64) -> FixPrior {
        let out = self
            .book
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .nearest(t_us)
            .cloned();
        let reacquire = match out {
            Some(_) => None,
            None => self
                .reacquire
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .clone(),
        };
        let att = self
            .attitudes
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .iter()
            .min_by_key(|(t, _)| t.abs_diff(t_us))
            .filter(|(t, _)| t.abs_diff(t_us) <= 200_000)
            .map(|(_, a)| *a);
        match reacquire {
            Some(r) => inputs::reacquisition_prior(t_us, &r, att, &self.nav),
            None => inputs::prior_at(t_us, out.as_ref(), att, &self.nav),
        }
    }

    fn pose_at(&self, t_us: u64) -> FixPrior {
        let out = self.book.lock().unwrap_or_else(|e| e.into_inner()).at(t_us);
        inputs::prior_at(t_us, out.as_ref(), None, &self.nav)
    }

    fn body_rotation(&self, t0_us: u64, t1_us: u64) -> Option<(nalgebra::Rotation3<f64>, f64)> {
        self.book
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .body_rotation(t0_us, t1_us)
    }
}

/// The last solution before a restart and the companion time (ns) it was made, waiting to be
/// re-stamped on the new boot clock once the link maps it.
struct PendingReacquire {
    out: NavOutput,
    made_ns: i64,
}

/// The running daemon.
pub struct Daemon {
    link: Arc<Link>,
    stop: watch::Sender<bool>,
    stop_threads: Arc<AtomicBool>,
    nav_task: Option<JoinHandle<()>>,
    /// The lock-step frame task (`FramePipeline::lockstep_latency`).
    lockstep_task: Option<JoinHandle<()>>,
    threads: Vec<std::thread::JoinHandle<()>>,
    /// The fix workers' and the odometry thread's frame slots (closed at shutdown).
    slots: Vec<Arc<Slot<Frame>>>,
    metrics: Arc<DaemonMetrics>,
    est_rx: watch::Receiver<Option<NavEstimate>>,
    out_rx: watch::Receiver<Option<NavOutput>>,
    prometheus: Option<prometheus::MetricsServer>,
}

impl Daemon {
    /// Start with the configured frame source (if any).
    pub async fn start(
        setup: DaemonSetup,
        fixer: Option<Arc<dyn FrameFixer>>,
    ) -> Result<Daemon, DaemonError> {
        let frames = match &setup.frames {
            Some(f) => {
                if fixer.is_none() {
                    return Err(DaemonError::NoFixer);
                }
                Some(FramePipeline::open(f)?)
            }
            None => None,
        };
        Self::start_with(setup, fixer, frames).await
    }

    /// Start with an explicit frame pipeline (ignores `setup.frames`).
    pub async fn start_with(
        setup: DaemonSetup,
        fixer: Option<Arc<dyn FrameFixer>>,
        frames: Option<FramePipeline>,
    ) -> Result<Daemon, DaemonError> {
        let fixer = match (&frames, fixer) {
            (Some(_), None) => return Err(DaemonError::NoFixer),
            (_, f) => f,
        };
        let gps = setup.daemon.gps_source(&setup.output);
        info!("GPS aiding source: {gps}");
        let fix_log = fixlog::JsonLinesLog::open_configured(setup.daemon.fix_log.as_deref())
            .map_err(|(path, source)| DaemonError::FixLog {
                path,
                cause: source,
            })?;
        if let Some(l) = &fix_log {
            info!(path = %l.path().display(), "vision fix log");
        }
        let vo_log = fixlog::JsonLinesLog::open_configured(setup.daemon.vo_log.as_deref())
            .map_err(|(path, source)| DaemonError::VoLog {
                path,
                cause: source,
            })?;
        if let Some(l) = &vo_log {
            info!(path = %l.path().display(), "visual odometry log");
        }
        let endpoint = match &setup.daemon.metrics_listen {
            Some(a) => Some(metrics_endpoint(a).await?),
            None => None,
        };
        let mut link_cfg = setup.link.clone();
        if setup.daemon.imu_bias_restore == ImuBiasRestore::ScaledImu
            && link_cfg.streams.scaled_imu_hz.is_none()
        {
            // Restoring needs SCALED_IMU beside HIGHRES_IMU whatever the autopilot says it is.
            link_cfg.streams.scaled_imu_hz = Some(link_cfg.streams.imu_hz);
        }
        let mut link = Link::start(link_cfg, setup.output.clone()).await?;
        let (est_tx, est_rx) = watch::channel(None);
        let (out_tx, out_rx) = watch::channel(None);
        link.spawn_injector(est_rx.clone());
        let tel = link.telemetry();
        let link = Arc::new(link);
        let metrics = Arc::new(DaemonMetrics::default());
        let prometheus = endpoint.map(|e| {
            let reg = metrics::registry(&metrics, &link.metrics());
            e.serve(prometheus::renderer(reg))
        });
        let shared = Arc::new(SharedPriors {
            nav: setup.nav.clone(),
            book: Mutex::new(OutputBook::default()),
            attitudes: Mutex::new(Default::default()),
            reacquire: Mutex::new(None),
        });
        let (stop, stop_rx) = watch::channel(false);
        let (fix_tx, fix_rx) = mpsc::channel(4);
        let (vo_tx, vo_rx) = mpsc::channel(8);
        let odometer = match (&frames, &fixer, setup.vo.enabled) {
            (Some(_), Some(f), true) => {
                let o = f.odometer(&setup.vo);
                if o.is_none() {
                    warn!("[vo] enabled, but the fix engine has no odometer: visual odometry off");
                }
                o
            }
            (None, _, true) => {
                warn!("[vo] enabled, but there is no camera ([frames]): visual odometry off");
                None
            }
            _ => None,
        };
        let dtm = match (&frames, &fixer, setup.dtm_nav.enabled) {
            (Some(_), Some(f), true) => {
                let d = f.dtm_navigator(&setup.dtm_nav);
                if d.is_none() {
                    warn!(
                        "[dtm_nav] enabled, but the fix engine has no terrain model: DTM navigation off"
                    );
                }
                d
            }
            (None, _, true) => {
                warn!("[dtm_nav] enabled, but there is no camera ([frames]): DTM navigation off");
                None
            }
            _ => None,
        };
        let vo_ctx = (odometer.is_some() || dtm.is_some()).then(|| vo_path::VoCtx {
            odometer,
            dtm,
            priors: shared.clone(),
            results: vo_tx.clone(),
            metrics: metrics.clone(),
            gyro: vo_path::GyroNoise::from_nav(&setup.nav),
            last_t_us: None,
        });
        let nav = NavTask {
            filter: NavFilter::new(setup.nav.clone()),
            nav_cfg: setup.nav.clone(),
            inputs: Inputs::new(setup.daemon.clone(), gps),
            dcfg: setup.daemon.clone(),
            gps,
            gps_hz: setup.link.streams.gps_raw_hz,
            link: link.clone(),
            shared: shared.clone(),
            metrics: metrics.clone(),
            est_tx,
            out_tx,
            last_health: None,
            last_est: None,
            reset_sum: 0,
            reset_counter: 0,
            last_imu_at: None,
            last_out_ns: None,
            pending_reacquire: None,
            imu_lost: false,
            gps2_asked: None,
            last_log: Instant::now(),
            imu_bias_restoring: false,
            drag_logged: [false; 2],
            init_spacing: inputs::InitSpacing::default(),
            fix_log,
            vo_log,
            vo_working: None,
            dtm_working: None,
            lag_log: LogLimiter::default(),
        };
        // Every task and thread of the daemon runs in the caller's span (the simulator labels
        // its two daemons so).
        let nav_task = tokio::spawn(nav.run(tel, fix_rx, vo_rx, stop_rx).in_current_span());
        let stop_threads = Arc::new(AtomicBool::new(false));
        let mut threads = Vec::new();
        let mut slots = Vec::new();
        let mut lockstep_task = None;
        let spawned: std::io::Result<()> = (|| {
            if let (Some(fp), Some(fixer)) = (frames, fixer) {
                let widening = Arc::new(frames::HeadingWidening::default());
                let ctx = |slot: Arc<Slot<Frame>>| frames::WorkerCtx {
                    slot,
                    fixer: fixer.clone(),
                    priors: shared.clone(),
                    clock: link.clock(),
                    max_age_s: fp.max_age_s,
                    results: fix_tx.clone(),
                    metrics: metrics.clone(),
                    widening: widening.clone(),
                };
                if let Some(latency) = fp.lockstep_latency {
                    let period = Duration::from_secs_f64(
                        1.0 / fp.source.rate_hz().filter(|r| *r > 0.0).unwrap_or(1.0),
                    );
                    let ctx = ctx(Arc::new(Slot::default()));
                    lockstep_task = Some(tokio::spawn(
                        frames::lockstep_frames(
                            fp.source,
                            ctx,
                            vo_ctx,
                            period,
                            latency,
                            stop.subscribe(),
                        )
                        .in_current_span(),
                    ));
                    return Ok(());
                }
                let slot = Arc::new(Slot::default());
                slots.push(slot.clone());
                let vo_slot = match vo_ctx {
                    Some(v) => {
                        let s = Arc::new(Slot::default());
                        slots.push(s.clone());
                        threads.push(vo_path::spawn_vo(s.clone(), v, link.clock(), fp.max_age_s)?);
                        Some(s)
                    }
                    None => None,
                };
                threads.push(frames::spawn_reader(
                    fp.source,
                    slot.clone(),
                    vo_slot,
                    fp.lossless,
                    fp.release,
                    link.clock(),
                    stop_threads.clone(),
                    metrics.clone(),
                )?);
                for i in 0..fp.workers.max(1) {
                    threads.push(frames::spawn_worker(i, ctx(slot.clone()))?);
                }
            }
            Ok(())
        })();
        if let Err(e) = spawned {
            // Stop what was started (the navigation task holds the link).
            stop_threads.store(true, Ordering::Relaxed);
            for s in &slots {
                s.close();
            }
            let _ = stop.send(true);
            return Err(e.into());
        }
        drop(fix_tx);
        drop(vo_tx);
        Ok(Daemon {
            link,
            stop,
            stop_threads,
            nav_task: Some(nav_task),
            lockstep_task,
            threads,
            slots,
            metrics,
            est_rx,
            out_rx,
            prometheus,
        })
    }

    /// Where the Prometheus endpoint listens (`None` when `daemon.metrics_listen` is off).
    pub fn metrics_addr(&self) -> Option<std::net::SocketAddr> {
        self.prometheus.as_ref().map(|p| p.local_addr())
    }

    /// The link (status, clock, link metrics).
    pub fn link(&self) -> &Link {
        &self.link
    }

    /// The daemon's counters.
    pub fn metrics(&self) -> MetricsSnapshot {
        self.metrics.snapshot()
    }

    /// The estimates handed to the injector.
    pub fn estimates(&self) -> watch::Receiver<Option<NavEstimate>> {
        self.est_rx.clone()
    }

    /// The filter outputs.
    pub fn nav_outputs(&self) -> watch::Receiver<Option<NavOutput>> {
        self.out_rx.clone()
    }

    /// Stop everything; returns the final counters.
    pub async fn shutdown(mut self) -> MetricsSnapshot {
        if let Some(p) = self.prometheus.take() {
            p.stop().await;
        }
        self.stop_threads.store(true, Ordering::Relaxed);
        for s in &self.slots {
            s.close();
        }
        let _ = self.stop.send(true);
        if let Some(t) = self.lockstep_task.take() {
            let _ = t.await;
        }
        if let Some(t) = self.nav_task.take() {
            let _ = t.await;
        }
        // Not joined on the blocking pool: the runtime waits for its blocking tasks when it is
        // dropped, so a thread that never ends would hold the process (deaf to SIGTERM, as the
        // signal handler is installed) until SIGKILL. The deadline is real time: it bounds how
        // long the process takes to end.
        let deadline = std::time::Instant::now() + THREAD_STOP_DEADLINE;
        for t in self.threads.drain(..) {
            while !t.is_finished() && std::time::Instant::now() < deadline {
                tokio::time::sleep(THREAD_STOP_POLL).await;
            }
            if t.is_finished() {
                let _ = t.join();
            } else {
                let name = t.thread().name().unwrap_or("thread").to_string();
                warn!(
                    "{name} did not stop within {} s of the shutdown; left behind (it ends with \
                     the process)",
                    THREAD_STOP_DEADLINE.as_secs()
                );
            }
        }
        let snap = self.metrics.snapshot();
        match Arc::try_unwrap(self.link) {
            Ok(l) => l.shutdown().await,
            Err(_) => warn!("link still referenced at shutdown; dropped instead"),
        }
        snap
    }
}

/// Bind the Prometheus endpoint (before the link starts, so a taken port fails first).
async fn metrics_endpoint(addr: &str) -> Result<prometheus::Endpoint, DaemonError> {
    let err = |source| DaemonError::Metrics {
        addr: addr.to_string(),
        cause: source,
    };
    let sa = addr.trim().parse().map_err(|_| {
        err(std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            "not an IP:PORT socket address",
        ))
    })?;
    prometheus::Endpoint::bind(sa).await.map_err(err)
}

/// `visnav run`: start, run until SIGINT/SIGTERM or `duration`, shut down cleanly.
pub async fn run(
    cfg: &Config,
    fixer: Option<Arc<dyn FrameFixer>>,
    duration: Option<Duration>,
) -> Result<MetricsSnapshot, DaemonError> {
    let d = Daemon::start(DaemonSetup::from_config(cfg), fixer).await?;
    let limit = async {
        match duration {
            Some(t) => tokio::time::sleep(t).await,
            None => std::future::pending().await,
        }
    };
    let why = tokio::select! {
        s = visnav_link::shutdown_signal() => match s {
            Ok(s) => s.to_string(),
            Err(e) => format!("signal handler failed: {e}"),
        },
        _ = limit => "run duration elapsed".to_string(),
    };
    info!("shutting down: {why}");
    let before = d.metrics();
    let m = tokio::select! {
        m = d.shutdown() => m,
        Ok(s) = visnav_link::shutdown_signal() => {
            warn!("{s} during the shutdown: ending without waiting for the tasks");
            before
        }
    };
    info!("{}", final_counters(&m));
    Ok(m)
}

/// The line `visnav run` logs at its end: its counters as one JSON object (the rejections by
/// reason each with the latest reason as written, its count and its class).
pub fn final_counters(m: &MetricsSnapshot) -> String {
    match serde_json::to_string(m) {
        Ok(json) => format!("final counters: {json}"),
        Err(e) => format!("final counters: cannot be written as JSON: {e}"),
    }
}

struct NavTask {
    filter: NavFilter,
    nav_cfg: NavConfig,
    inputs: Inputs,
    dcfg: DaemonConfig,
    gps: GpsSource,
    gps_hz: f64,
    link: Arc<Link>,
    shared: Arc<SharedPriors>,
    metrics: Arc<DaemonMetrics>,
    est_tx: watch::Sender<Option<NavEstimate>>,
    out_tx: watch::Sender<Option<NavOutput>>,
    last_health: Option<LinkHealth>,
    last_est: Option<NavEstimate>,
    reset_sum: u64,
    reset_counter: u8,
    last_imu_at: Option<Instant>,
    /// Companion time (ns) of the last published output that was not lost.
    last_out_ns: Option<i64>,
    /// The last solution before an autopilot reboot, until the new boot clock is mapped.
    pending_reacquire: Option<PendingReacquire>,
    imu_lost: bool,
    gps2_asked: Option<Instant>,
    last_log: Instant,
    /// The IMU bias restorer was restoring at the last watchdog tick (for its log lines).
    imu_bias_restoring: bool,
    /// Whether the learned drag law of body x / y was logged (`nav::drag`).
    drag_logged: [bool; 2],
    init_spacing: inputs::InitSpacing,
    fix_log: Option<fixlog::FixLog>,
    vo_log: Option<volog::VoLog>,
    /// Visual odometry's last state (motions or refusals), for logging its changes.
    vo_working: Option<bool>,
    /// The DTM navigator's (poses or refusals).
    dtm_working: Option<bool>,
    /// Rate limit of the "fell behind" warning (a starved task lags again and again).
    lag_log: LogLimiter,
}

impl NavTask {
    async fn run(
        mut self,
        mut tel: broadcast::Receiver<Telemetry>,
        mut fixes: mpsc::Receiver<FixResult>,
        mut vo: mpsc::Receiver<vo_path::VoResult>,
        mut stop: watch::Receiver<bool>,
    ) {
        let mut tick = tokio::time::interval(Duration::from_millis(100));
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            tokio::select! {
                _ = stop.changed() => {
                    // Results already queued, and any a worker finishes from now on (its send
                    // fails on the closed channel), are counted, not silently lost.
                    fixes.close();
                    while fixes.try_recv().is_ok() {
                        self.metrics.fixes_dropped_at_shutdown.inc();
                    }
                    return;
                }
                r = tel.recv() => match r {
                    Ok(t) => self.telemetry(&t),
                    Err(broadcast::error::RecvError::Lagged(n)) => {
                        self.metrics.telemetry_lagged.inc_by(n);
                        let t_s = self.link.companion_now_ns() as f64 * 1e-9;
                        if let Some(line) = self.lag_log.hit(t_s) {
                            warn!(
                                "navigation task fell behind: {n} telemetry messages lost{}",
                                line.suffix()
                            );
                        }
                    }
                    Err(broadcast::error::RecvError::Closed) => return,
                },
                Some(f) = fixes.recv() => self.fix(f),
                Some(r) = vo.recv() => self.vo(r),
                _ = tick.tick() => self.watchdog().await,
            }
        }
    }

    fn telemetry(&mut self, t: &Telemetry) {
        if let Some(tb) = t.t_boot_us
            && let Some(p) = self.pending_reacquire.take()
        {
            // Re-stamp the old solution on the new boot clock: as old as it is on the
            // companion's clock.
            let age_us = ((t.t_companion_ns - p.made_ns).max(0) / 1000) as u64;
            let mut o = p.out;
            o.t_us = tb.saturating_sub(age_us);
            info!(
                "reacquiring from the solution of {:.1} s before the reboot",
                age_us as f64 * 1e-6
            );
            *self
                .shared
                .reacquire
                .lock()
                .unwrap_or_else(|e| e.into_inner()) = Some(o);
        }
        if let MavMessage::ATTITUDE(a) = &t.msg {
            let mut q = self
                .shared
                .attitudes
                .lock()
                .unwrap_or_else(|e| e.into_inner());
            q.push_back((
                u64::from(a.time_boot_ms) * 1000,
                Attitude::new(f64::from(a.roll), f64::from(a.pitch), f64::from(a.yaw)),
            ));
            while q.len() > 200 {
                q.pop_front();
            }
        }
        for input in self.inputs.convert(t) {
            match input {
                NavInput::Imu(s) => {
                    self.metrics.imu_samples.inc();
                    self.last_imu_at = Some(Instant::now());
                    if self.imu_lost {
                        self.imu_lost = false;
                        info!("IMU data resumed");
                    }
                    if let Some(o) = self.filter.imu(&s) {
                        self.publish(o);
                    }
                }
                NavInput::Meas(m) => {
                    if self.init_spacing_ok(&m) {
                        self.filter.measure(m);
                    }
                }
                NavInput::Vehicle { multirotor } => self.filter.set_multirotor(multirotor),
                NavInput::Reboot => {
                    warn!("autopilot reboot: navigation filter restarted");
                    self.metrics.autopilot_reboots.inc();
                    self.filter = NavFilter::new(self.nav_cfg.clone());
                    self.filter.set_multirotor(self.inputs.multirotor());
                    self.drag_logged = [false; 2];
                    let last = {
                        let mut book = self.shared.book.lock().unwrap_or_else(|e| e.into_inner());
                        let last = book.last().cloned();
                        book.clear();
                        last
                    };
                    *self
                        .shared
                        .reacquire
                        .lock()
                        .unwrap_or_else(|e| e.into_inner()) = None;
                    self.pending_reacquire = last
                        .filter(inputs::usable_as_prior)
                        .zip(self.last_out_ns)
                        .map(|(out, made_ns)| PendingReacquire { out, made_ns });
                    self.publish_lost("autopilot rebooted; navigation restarting");
                }
            }
        }
    }

    fn fix(&mut self, f: FixResult) {
        let m = self.metrics.clone();
        let outcome = match inputs::vision_measurement(
            &f.report,
            f.t_capture_us,
            self.filter.config().vision_attitude,
            self.filter.config().vision_prior_dependence,
        ) {
            Err(reason) => {
                m.engine_reject(reason.class(), &reason.to_string());
                "engine_rejected"
            }
            Ok(meas) if !self.init_spacing_ok(&meas) => {
                m.fixes_unused_before_init.inc();
                "unused_before_init"
            }
            Ok(meas) => {
                let (c, name) = match self.filter.measure(meas) {
                    Outcome::Accepted { .. } => (&m.fixes_accepted, "accepted"),
                    Outcome::Initialised => (&m.fixes_accepted, "initialised"),
                    Outcome::Held => (&m.fixes_accepted, "held"),
                    Outcome::Reset => (&m.fixes_accepted, "reset"),
                    Outcome::Rejected { .. } => (&m.fixes_filter_rejected, "rejected"),
                    Outcome::TooOld => (&m.fixes_too_old, "too_old"),
                    Outcome::Invalid(_) | Outcome::Ignored => (&m.fixes_invalid, "invalid"),
                };
                c.inc();
                name
            }
        };
        if let Some(log) = self.fix_log.as_mut() {
            let r = fixlog::FixLogRecord::new(
                visnav_link::tlog::unix_now_us(),
                f.seq,
                f.latency_ms,
                &f.report,
                outcome,
            );
            if let Err(e) = log.write(&r) {
                warn!("fix log {}: {e}; logging stopped", log.path().display());
                self.fix_log = None;
            }
        }
    }

    /// A visual odometry result: a motion to the filter, everything counted; the first motion
    /// after refusals (and the first refusal after motions) logged with its reason.
    fn vo(&mut self, r: vo_path::VoResult) {
        if let Some(d) = &r.dtm {
            self.dtm(r.seq, d);
        }
        let Some(step) = &r.step else { return };
        let (outcome, nis) = match step {
            VoStep::Motion(motion) => self.vo_motion(r.seq, motion),
            VoStep::Refused(why) => {
                if self.vo_working != Some(false) {
                    info!("visual odometry: no motion from frame {}: {why}", r.seq);
                    self.vo_working = Some(false);
                }
                ("", None)
            }
            VoStep::Started => ("", None),
        };
        if let Some(log) = self.vo_log.as_mut() {
            let rec = volog::VoLogRecord::new(
                visnav_link::tlog::unix_now_us(),
                r.seq,
                r.t_capture_us,
                step,
                outcome,
                nis,
            )
            .with_prior_attitude(r.prior_attitude_deg);
            if let Err(e) = log.write(&rec) {
                warn!("VO log {}: {e}; logging stopped", log.path().display());
                self.vo_log = None;
            }
        }
    }

    /// A DTM navigation result: a pose to the filter (gated as a map fix's pose), everything
    /// counted; the first pose after refusals (and the first refusal after poses) logged.
    fn dtm(&mut self, seq: u64, step: &DtmStep) {
        let m = &self.metrics.dtm;
        match step {
            DtmStep::Fix(f) => {
                let c = match self.filter.measure(Measurement::VisionPose(f.fix)) {
                    Outcome::Accepted { .. } => &m.fused,
                    Outcome::Rejected { .. } => &m.filter_rejected,
                    _ => &m.unused,
                };
                c.inc();
                if self.dtm_working != Some(true) {
                    info!(
                        "DTM navigation: pose from frame {seq} ({:.0} m baseline, {} of {} flow vectors, {:.2} px, {:.1} m horizontal sigma given the attitude)",
                        f.baseline_m, f.inliers, f.tracks, f.rms_px, f.sigma_h_given_attitude_m
                    );
                    self.dtm_working = Some(true);
                }
            }
            DtmStep::Refused(why) => {
                if self.dtm_working != Some(false) {
                    info!("DTM navigation: no pose from frame {seq}: {why}");
                    self.dtm_working = Some(false);
                }
            }
            DtmStep::Waiting => {}
        }
    }

    /// A motion to the filter; returns what the filter did (the VO log's `outcome`) and its NIS.
    fn vo_motion(&mut self, seq: u64, motion: &VoMotion) -> (&'static str, Option<f64>) {
        let m = &self.metrics.vo;
        let (c, outcome, nis) = match self.filter.measure(Measurement::Vo(motion.fix)) {
            Outcome::Accepted { nis } => (&m.fused, "fused", Some(nis)),
            Outcome::Rejected { nis, .. } => (&m.filter_rejected, "filter_rejected", Some(nis)),
            _ => (&m.unused, "unused", None),
        };
        c.inc();
        if self.vo_working != Some(true) {
            info!(
                "visual odometry: measuring from frame {seq} ({} tracks, {} inliers, {:.2} px)",
                motion.tracks, motion.inliers, motion.rms_px
            );
            self.vo_working = Some(true);
        }
        (outcome, nis)
    }

    /// See [`inputs::InitSpacing`].
    fn init_spacing_ok(&mut self, m: &Measurement) -> bool {
        if self.filter.is_initialised() {
            return true; // the common case: no clock read per measurement
        }
        let gps_recent = self.inputs.gps_recent(self.link.companion_now_ns(), 2.0);
        self.init_spacing.ok(
            self.filter.is_initialised(),
            m,
            gps_recent,
            &self.nav_cfg.init,
        )
    }

    fn health(&mut self, h: NavHealth, reason: &str) -> LinkHealth {
        let new = inputs::link_health(h, reason, self.last_health.as_ref());
        let changed = self
            .last_health
            .as_ref()
            .is_none_or(|p| std::mem::discriminant(p) != std::mem::discriminant(&new));
        self.metrics.health.set(&new);
        if changed {
            self.metrics.health_changes.inc();
            info!("navigation health {new}");
        }
        self.last_health = Some(new.clone());
        new
    }

    fn publish(&mut self, o: NavOutput) {
        self.metrics.nav_outputs.inc();
        let c = self.filter.counters();
        let sum = c.initialisations + c.divergence_resets + c.covariance_resets + c.hard_resets;
        if sum != self.reset_sum {
            self.reset_sum = sum;
            self.reset_counter = self.reset_counter.wrapping_add(1);
        }
        let health = self.health(o.health, &o.reason);
        if inputs::usable_as_prior(&o) {
            self.last_out_ns = Some(self.link.companion_now_ns());
            // The new filter has its own solution: the reacquisition prior is done.
            let mut r = self
                .shared
                .reacquire
                .lock()
                .unwrap_or_else(|e| e.into_inner());
            if r.take().is_some() {
                info!("reacquired: the filter has its own solution again");
            }
        }
        let est = inputs::estimate_from_output(&o, health, self.reset_counter);
        self.shared
            .book
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .push(o.clone());
        if est.is_some() {
            self.last_est = est.clone();
        }
        self.est_tx.send_replace(est);
        self.out_tx.send_replace(Some(o));
    }

    /// Republish the last estimate as lost (the injector then stops, and the link reports it).
    fn publish_lost(&mut self, reason: &str) {
        let h = self.health(NavHealth::Lost, reason);
        if let Some(mut e) = self.last_est.clone() {
            e.health = h;
            self.est_tx.send_replace(Some(e));
        }
    }

    async fn watchdog(&mut self) {
        let imu_silent = self
            .last_imu_at
            .is_some_and(|t| t.elapsed().as_secs_f64() > self.dcfg.imu_timeout_s);
        if imu_silent {
            if !self.imu_lost {
                self.imu_lost = true;
                self.metrics.imu_timeouts.inc();
                warn!(
                    "no IMU data for {} s: solution lost",
                    self.dcfg.imu_timeout_s
                );
            }
            self.publish_lost("no IMU data from the autopilot");
        } else if !self.filter.is_initialised() && self.last_est.is_some() {
            let (_, why) = self.filter.health();
            self.publish_lost(&why);
        }
        for (k, law) in self.filter.drag_status().into_iter().enumerate() {
            if let (Ok(m), false) = (law, self.drag_logged[k]) {
                self.drag_logged[k] = true;
                info!(
                    axis = ["x", "y"][k],
                    linear_per_s = (m.a * 1e4).round() / 1e4,
                    quadratic_per_m = (m.b * 1e5).round() / 1e5,
                    residual_m_s2 = (m.resid_m_s2 * 1e3).round() / 1e3,
                    quadratic_form = match m.form {
                        visnav_core::nav::drag::QuadForm::PerAxis => "per axis v|v|",
                        visnav_core::nav::drag::QuadForm::Vector => "vector v|v_h|",
                    },
                    forms_undecided = m.alternative.is_some(),
                    "multirotor drag law learned (fused when the GPS is gone, nav.drag)"
                );
            }
        }
        if let Some(st) = self.inputs.imu_bias_status() {
            if st.restoring != self.imu_bias_restoring {
                self.imu_bias_restoring = st.restoring;
                if st.restoring {
                    info!("autopilot IMU bias: restoring HIGHRES_IMU with SCALED_IMU");
                } else if st.bias.is_some() {
                    warn!(
                        unpaired = st.unpaired,
                        paired = st.paired,
                        "autopilot IMU bias: no consistent SCALED_IMU / HIGHRES_IMU pair for 5 s \
                         (SCALED_IMU stopped, the two come from different IMUs, or their gyro \
                         scales differ); HIGHRES_IMU is used as sent"
                    );
                }
            }
            self.metrics.imu_bias.set(st);
        }
        let now_ns = self.link.companion_now_ns();
        if self.dcfg.baro
            && !self.inputs.baro_calibrated()
            && !self.inputs.gps_recent(now_ns, 5.0)
            && let Some(o) = self.filter.output()
            && o.health == NavHealth::Ok
            && o.cov_pos_ned_m2[2][2] < 25.0
        {
            self.inputs.calibrate_baro_from_filter(o.h_m);
            info!("barometric altitude offset calibrated against the filter");
        }
        if self.gps == GpsSource::Gps2 && self.gps_hz > 0.0 && !self.inputs.gps_recent(now_ns, 5.0)
        {
            self.request_gps2().await;
        }
        if self.dcfg.log_interval_s > 0.0
            && self.last_log.elapsed().as_secs_f64() >= self.dcfg.log_interval_s
        {
            self.last_log = Instant::now();
            let m = self.metrics.snapshot();
            info!(
                imu = m.imu_samples,
                frames_in = m.frames_in,
                dropped = m.frames_superseded + m.frames_stale + m.frames_no_time + m.frames_frozen,
                fixes_accepted = m.fixes_accepted,
                fixes_rejected = m.fixes_filter_rejected
                    + m.engine_rejected.iter().map(|r| r.count).sum::<u64>(),
                latency_ms = m.fix_latency_ms_last,
                "daemon"
            );
            if let Some(b) = &m.imu_bias {
                let f = |v: Option<[f64; 3]>, d: usize| {
                    v.map_or("none".to_string(), |v| {
                        format!("{:.d$} {:.d$} {:.d$}", v[0], v[1], v[2])
                    })
                };
                info!(
                    paired = b.paired,
                    unpaired = b.unpaired,
                    bootstraps = b.bootstraps,
                    not_restored = b.not_restored,
                    restoring = b.restoring,
                    age_s = b.age_s.map_or(-1.0, |a| (a * 10.0).round() / 10.0),
                    gyro_deg_h = %f(b.gyro_bias_deg_h, 1),
                    accel_mg = %f(b.accel_bias_mg, 2),
                    "autopilot IMU bias restored"
                );
            }
        }
    }

    /// GPS2_RAW is not in the link's stream set: ask for it every 5 s while it does not arrive.
    async fn request_gps2(&mut self) {
        if self
            .gps2_asked
            .is_some_and(|t| t.elapsed() < Duration::from_secs(5))
        {
            return;
        }
        let Some(ap) = self.link.status().borrow().autopilot else {
            return;
        };
        self.gps2_asked = Some(Instant::now());
        let m = MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
            param1: 124.0,
            param2: (1e6 / self.gps_hz) as f32,
            target_system: ap.system_id,
            target_component: ap.component_id,
            command: MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL,
            ..COMMAND_LONG_DATA::DEFAULT
        });
        if let Err(e) = self.link.send(&m).await {
            tracing::debug!("GPS2_RAW request: {e}");
        }
    }
}
