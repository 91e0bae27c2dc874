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
//!   fix threads drop frames older than `frames.max_age_s`, build the [`FixPrior`](visnav_core::fix::FixPrior) at the
//!   capture time and call the [`FrameFixer`].
//!
//! * the optional Prometheus endpoint (`[daemon] metrics_listen`, [`prometheus`]).
//!
//! Shutdown: [`Daemon::shutdown`] (or SIGINT/SIGTERM in [`run`]) closes the slot, stops the
//! navigation task, joins the threads (waiting at most [`THREAD_STOP_DEADLINE`] for them all: a
//! thread still busy then is left behind and ends with the process, never holds it) and shuts
//! the link down (flushing the .tlog). A second SIGINT/SIGTERM during the shutdown ends it at
//! once.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use tokio::sync::{mpsc, watch};
use tokio::task::JoinHandle;
use tracing::{Instrument, info, warn};

use crate::config::Config;
use crate::config::{DaemonConfig, ImuBiasRestore};
use crate::fixer::FrameFixer;
use crate::frames::{self, Slot};
use crate::inputs::OutputBook;
use crate::metrics::{DaemonMetrics, MetricsSnapshot};
use crate::nav_task::{NavTask, NavWiring};
use crate::priors::SharedPriors;
use crate::{fixlog, metrics, prometheus, vo_path, volog};
use visnav_core::dtm_nav::DtmNavConfig;
use visnav_core::nav::{NavConfig, NavOutput};
use visnav_io::frames::{Frame, FrameError, FrameSource, FramesConfig};
use visnav_link::config::{LinkConfig, OutputConfig};
use visnav_link::{Link, LinkError, NavEstimate};

/// Why the daemon could not start.
#[derive(Debug, thiserror::Error)]
pub enum DaemonError {
    /// The MAVLink link could not start.
    #[error(transparent)]
    Link(#[from] LinkError),
    /// The frame source could not open.
    #[error(transparent)]
    Frames(#[from] FrameError),
    /// Frames are configured but no fix engine was given.
    #[error("frames are configured but no vision fix engine was given")]
    NoFixer,
    /// A thread could not be started.
    #[error("cannot start a thread: {0}")]
    Thread(std::io::Error),
    /// The visual odometry log could not be opened.
    #[error("daemon.vo_log: {path}: {cause}")]
    VoLog {
        /// The file.
        path: std::path::PathBuf,
        /// The operating system's error.
        cause: std::io::Error,
    },
    /// The fix log could not be opened.
    #[error("daemon.fix_log: {path}: {cause}")]
    FixLog {
        /// The file.
        path: std::path::PathBuf,
        /// The operating system's error.
        cause: std::io::Error,
    },
    /// The metrics endpoint could not listen.
    #[error("daemon.metrics_listen: {addr}: {cause}")]
    Metrics {
        /// The address, as configured.
        addr: String,
        /// The operating system's error.
        cause: std::io::Error,
    },
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
    /// `[link]`.
    pub link: LinkConfig,
    /// `[output]`.
    pub output: OutputConfig,
    /// `[nav]`.
    pub nav: NavConfig,
    /// `[daemon]`.
    pub daemon: DaemonConfig,
    /// `[frames]` (None: no camera, no vision).
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
        let (fix_log, vo_log) = open_logs(&setup.daemon)?;
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
        let (odometer, dtm) = motion_paths(frames.is_some(), fixer.as_ref(), &setup);
        let vo_ctx = (odometer.is_some() || dtm.is_some()).then(|| vo_path::VoCtx {
            odometer,
            dtm,
            priors: shared.clone(),
            results: vo_tx.clone(),
            metrics: metrics.clone(),
            gyro: vo_path::GyroNoise::from_nav(&setup.nav),
            last_t_us: None,
        });
        let wiring = NavWiring {
            link: link.clone(),
            shared: shared.clone(),
            metrics: metrics.clone(),
            est_tx,
            out_tx,
            fix_log,
            vo_log,
        };
        let nav = NavTask::new(
            &setup.nav,
            &setup.daemon,
            gps,
            setup.link.streams.gps_raw_hz,
            wiring,
        );
        // Every task and thread of the daemon runs in the caller's span (the simulator labels
        // its two daemons so).
        let nav_task = tokio::spawn(nav.run(tel, fix_rx, vo_rx, stop_rx).in_current_span());
        let stop_threads = Arc::new(AtomicBool::new(false));
        let mut paths = FramePaths::default();
        if let (Some(fp), Some(fixer)) = (frames, fixer) {
            let wiring = FrameWiring {
                fixer,
                shared,
                link: link.clone(),
                results: fix_tx.clone(),
                metrics: metrics.clone(),
                stop: &stop,
                stop_threads: &stop_threads,
            };
            if let Err(e) = paths.spawn(fp, &wiring, vo_ctx) {
                // Stop what was started (the navigation task holds the link).
                stop_threads.store(true, Ordering::Relaxed);
                for s in &paths.slots {
                    s.close();
                }
                let _ = stop.send(true);
                return Err(e.into());
            }
        }
        drop(fix_tx);
        drop(vo_tx);
        Ok(Daemon {
            link,
            stop,
            stop_threads,
            nav_task: Some(nav_task),
            lockstep_task: paths.lockstep_task,
            threads: paths.threads,
            slots: paths.slots,
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

/// The fix log and the visual odometry log, where configured.
fn open_logs(
    d: &DaemonConfig,
) -> Result<(Option<fixlog::FixLog>, Option<volog::VoLog>), DaemonError> {
    let fix_log =
        fixlog::JsonLinesLog::open_configured(d.fix_log.as_deref()).map_err(|(path, source)| {
            DaemonError::FixLog {
                path,
                cause: source,
            }
        })?;
    if let Some(l) = &fix_log {
        info!(path = %l.path().display(), "vision fix log");
    }
    let vo_log =
        fixlog::JsonLinesLog::open_configured(d.vo_log.as_deref()).map_err(|(path, source)| {
            DaemonError::VoLog {
                path,
                cause: source,
            }
        })?;
    if let Some(l) = &vo_log {
        info!(path = %l.path().display(), "visual odometry log");
    }
    Ok((fix_log, vo_log))
}

/// Visual odometry and DTM navigation, each where enabled and possible: both need a camera and
/// an engine that has them; an enabled one that cannot run is said so.
fn motion_paths(
    has_frames: bool,
    fixer: Option<&Arc<dyn FrameFixer>>,
    setup: &DaemonSetup,
) -> (
    Option<visnav_core::vo::Odometer>,
    Option<visnav_core::dtm_nav::DtmNavigator>,
) {
    let odometer = match (has_frames, fixer, setup.vo.enabled) {
        (true, Some(f), true) => {
            let o = f.odometer(&setup.vo);
            if o.is_none() {
                warn!("[vo] enabled, but the fix engine has no odometer: visual odometry off");
            }
            o
        }
        (false, _, true) => {
            warn!("[vo] enabled, but there is no camera ([frames]): visual odometry off");
            None
        }
        _ => None,
    };
    let dtm = match (has_frames, fixer, setup.dtm_nav.enabled) {
        (true, Some(f), true) => {
            let d = f.dtm_navigator(&setup.dtm_nav);
            if d.is_none() {
                warn!(
                    "[dtm_nav] enabled, but the fix engine has no terrain model: DTM navigation off"
                );
            }
            d
        }
        (false, _, true) => {
            warn!("[dtm_nav] enabled, but there is no camera ([frames]): DTM navigation off");
            None
        }
        _ => None,
    };
    (odometer, dtm)
}

/// What the frame path's threads and tasks are wired to.
struct FrameWiring<'a> {
    fixer: Arc<dyn FrameFixer>,
    shared: Arc<SharedPriors>,
    link: Arc<Link>,
    results: mpsc::Sender<frames::FixResult>,
    metrics: Arc<DaemonMetrics>,
    stop: &'a watch::Sender<bool>,
    stop_threads: &'a Arc<AtomicBool>,
}

/// The frame path once started: the reader, worker and odometry threads with their slots, or
/// the lock-step task.
#[derive(Default)]
struct FramePaths {
    threads: Vec<std::thread::JoinHandle<()>>,
    slots: Vec<Arc<Slot<Frame>>>,
    lockstep_task: Option<JoinHandle<()>>,
}

impl FramePaths {
    /// Starts the frame path of `fp`. On an error, what was started is in `self` to be stopped.
    fn spawn(
        &mut self,
        fp: FramePipeline,
        w: &FrameWiring,
        vo_ctx: Option<vo_path::VoCtx>,
    ) -> std::io::Result<()> {
        let widening = Arc::new(frames::HeadingWidening::default());
        let ctx = |slot: Arc<Slot<Frame>>| frames::WorkerCtx {
            slot,
            fixer: w.fixer.clone(),
            priors: w.shared.clone(),
            clock: w.link.clock(),
            max_age_s: fp.max_age_s,
            results: w.results.clone(),
            metrics: w.metrics.clone(),
            widening: widening.clone(),
        };
        if let Some(latency) = fp.lockstep_latency {
            let period = Duration::from_secs_f64(
                1.0 / fp.source.rate_hz().filter(|r| *r > 0.0).unwrap_or(1.0),
            );
            let ctx = ctx(Arc::new(Slot::default()));
            self.lockstep_task = Some(tokio::spawn(
                frames::lockstep_frames(
                    fp.source,
                    ctx,
                    vo_ctx,
                    period,
                    latency,
                    w.stop.subscribe(),
                )
                .in_current_span(),
            ));
            return Ok(());
        }
        let slot = Arc::new(Slot::default());
        self.slots.push(slot.clone());
        let vo_slot = match vo_ctx {
            Some(v) => {
                let s = Arc::new(Slot::default());
                self.slots.push(s.clone());
                self.threads.push(vo_path::spawn_vo(
                    s.clone(),
                    v,
                    w.link.clock(),
                    fp.max_age_s,
                )?);
                Some(s)
            }
            None => None,
        };
        self.threads.push(frames::spawn_reader(
            fp.source,
            slot.clone(),
            vo_slot,
            fp.lossless,
            fp.release,
            w.link.clock(),
            w.stop_threads.clone(),
            w.metrics.clone(),
        )?);
        for i in 0..fp.workers.max(1) {
            self.threads
                .push(frames::spawn_worker(i, ctx(slot.clone()))?);
        }
        Ok(())
    }
}
