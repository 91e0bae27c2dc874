//! The running link: a supervisor task that (re)connects with exponential backoff and, per
//! connection, a receive loop plus heartbeat, TIMESYNC and stream-manager loops. The rest of
//! visnav talks to it through [`Link`]: telemetry (broadcast), status (watch), clock mapping,
//! injection and STATUSTEXT.
//!
//! Protocol behaviour:
//! * We send HEARTBEAT as MAV_TYPE_ONBOARD_CONTROLLER / MAV_AUTOPILOT_INVALID with our system id
//!   (configured, else the autopilot's once locked, else the configured autopilot id, else 1) and
//!   component id (default 197).
//! * Lock-on: the link locks onto the first HEARTBEAT of an autopilot: a vehicle type (not a
//!   gimbal, camera, GCS, companion or other peripheral), a flight stack in the `autopilot` field,
//!   the configured `autopilot_component_id` (default 1), and `autopilot_system_id` when set.
//!   Everything else is ignored (still recorded in the .tlog). If the locked autopilot falls
//!   silent for the heartbeat timeout, another that passes the same test takes its place.
//! * `udpin`: replies go only to the address the locked autopilot's valid (and, with signing,
//!   authenticated) messages come from (`transport`).
//! * Every message's boot time goes through `time::BootClock`: stale ones (behind the autopilot's
//!   clock without a confirmed reboot) are dropped; a reboot needs several streams and the old
//!   clock's silence. GPS_GLOBAL_ORIGIN outside the Earth's coordinates is refused, and so is one
//!   farther than [`MAX_ORIGIN_DISTANCE_M`] from the navigation solution (before there is one:
//!   from the origin it would replace; the first origin is then checked against the first
//!   solution): the previous origin stays in use, and while none is usable the pose outputs are
//!   held with a warning, a STATUSTEXT, a degraded health and `visnav_link_pose_output_held`.
//! * Warnings that can repeat at the rate of messages (refused origins, clock steps, .tlog
//!   failures, pose outputs held) go through a [`LogLimiter`]: the first, then at most one line
//!   per [`crate::metrics::LOG_REPEAT_INTERVAL_S`] with the count of those not logged.
//! * Output times never go back (`time::Monotonic`); the autopilot's UTC is latched and a step of
//!   its clock is logged, counted and reported, not followed.
//! * After the lock, after a reconnect and after an autopilot reboot, every wanted stream is
//!   requested with MAV_CMD_SET_MESSAGE_INTERVAL; every 2 s the measured rates are checked and
//!   missing streams are requested again (with their alternative ids).
//! * Outgoing packets are MAVLink 2, signed when configured; each is appended to the .tlog.

use std::sync::atomic::{AtomicU8, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

// tokio's clock: the real one, or the simulator's when its runtime runs paused (lock-step).
use tokio::time::Instant;

use mavlink::dialects::ardupilotmega::{
    COMMAND_LONG_DATA, HEARTBEAT_DATA, MavAutopilot, MavCmd, MavMessage, MavModeFlag, MavSeverity,
    MavState, MavType, STATUSTEXT_DATA, TIMESYNC_DATA,
};
use mavlink::error::MessageReadError;
use mavlink::{
    MAVLinkMessageRaw, MAVLinkV2MessageRaw, MavHeader, Message, SigningConfig, SigningData,
};
use tokio::sync::{broadcast, watch};
use tokio::task::JoinHandle;
use tracing::{Instrument, debug, info, warn};

use crate::config::{LinkConfig, OnLost, OutputConfig, OutputMode};
use crate::inject::{self, Health, InjectError, NavEstimate, SendTime};
use crate::metrics::{LogLimiter, Metrics};
use crate::streams::{self, RateMonitor, StreamSpec, StreamStatus, ids};
use crate::time::{
    BootClock, BootVerdict, Monotonic, SyncUpdate, TimeSync, TimesyncSample, UtcMap,
};
use crate::tlog::{Tlog, expand_name, unix_now_us};
use crate::transport::Transport;
use visnav_core::geo::GeoOrigin;

type Conn = Transport;

/// Why the link could not start or a send failed.
#[derive(Debug, thiserror::Error)]
pub enum LinkError {
    /// The signing key file cannot be used.
    #[error("link.signing.key_file: {0}")]
    Key(crate::signing::KeyError),
    /// The telemetry log cannot be written.
    #[error("link.tlog: {path}: {cause}")]
    Tlog {
        /// The log's path.
        path: std::path::PathBuf,
        /// The operating system's error.
        cause: std::io::Error,
    },
    /// The metrics endpoint cannot listen.
    #[error("link.metrics_listen: {addr}: {cause}")]
    Metrics {
        /// The address configured.
        addr: String,
        /// The operating system's error.
        cause: std::io::Error,
    },
    /// The connection's listen port is taken by another program.
    #[error("link.connection: {connection}: {cause}")]
    Listen {
        /// The connection configured.
        connection: String,
        /// Why it cannot listen.
        cause: crate::config::ListenError,
    },
    /// A send before the link is connected.
    #[error("not connected")]
    NotConnected,
    /// A send the connection refused (its message).
    #[error("send failed: {0}")]
    Send(String),
}

// Not `#[from]`: that would also make the error its `source()`, and the message already has its
// text (an error chain printed with `{:#}` would say it twice).
impl From<crate::signing::KeyError> for LinkError {
    fn from(e: crate::signing::KeyError) -> Self {
        Self::Key(e)
    }
}

/// The autopilot the link is locked onto.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AutopilotInfo {
    /// Its system id.
    pub system_id: u8,
    /// Its component id.
    pub component_id: u8,
    /// Its flight stack (ArduPilot, PX4, ...).
    pub autopilot: MavAutopilot,
    /// Vehicle type.
    pub vehicle: MavType,
}

/// Snapshot of the link's state (published through a `watch` channel).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct LinkStatus {
    /// A transport is open.
    pub connected: bool,
    /// The locked autopilot.
    pub autopilot: Option<AutopilotInfo>,
    /// Its heartbeat is current.
    pub alive: bool,
    /// The TIMESYNC mapping is converged.
    pub time_synced: bool,
    /// Autopilot reboots detected.
    pub reboots: u32,
    /// Every wanted stream arrives at its rate.
    pub streams_ok: bool,
    /// Per-stream rates at the last check.
    pub streams: Vec<StreamStatus>,
    /// The EKF origin used for local positions.
    pub origin: Option<GeoOrigin>,
    /// While no origin is usable because the autopilot's was refused: why (the pose outputs,
    /// VISION_POSITION_ESTIMATE / ODOMETRY, are held).
    pub origin_refused: Option<String>,
}

/// One telemetry message from the locked autopilot.
#[derive(Debug, Clone)]
pub struct Telemetry {
    /// Companion clock at reception (ns, [`Link::companion_ns`]).
    pub t_companion_ns: i64,
    /// Autopilot boot time at reception, if the clock mapping is converged.
    pub t_boot_us: Option<u64>,
    /// Confirmed autopilot reboots and lock changes before this message (a change: the
    /// autopilot restarted or another one took its place, so its boot times start again and the
    /// navigation must restart).
    pub boot_epoch: u32,
    /// Packet header.
    pub header: MavHeader,
    /// The message.
    pub msg: MavMessage,
}

impl Telemetry {
    /// The sensor reading the message carries, typed and in SI units ([`crate::sensors`]); None
    /// for a message that is not sensor telemetry.
    pub fn sensor(&self) -> Option<crate::sensors::Sensor> {
        crate::sensors::Sensor::from_message(&self.msg)
    }
}

#[derive(Debug)]
struct State {
    autopilot: Option<AutopilotInfo>,
    last_heartbeat: Option<Instant>,
    timesync: TimeSync,
    utc: UtcMap,
    rates: RateMonitor,
    /// Outstanding TIMESYNC requests (ts1 values).
    pending_ts1: Vec<i64>,
    /// Streams need (re)requesting from scratch.
    streams_dirty: bool,
    origin: Option<GeoOrigin>,
    origin_from_autopilot: bool,
    origin_sent: u32,
    /// The origin was taken before there was a navigation solution to judge its distance by:
    /// checked against the first one ([`Shared::ensure_origin`]).
    origin_unverified: bool,
    /// Why no origin is usable, while the autopilot's stands refused ([`LinkStatus`]).
    origin_refused: Option<String>,
    /// The last usable navigation solution handed to the injector (lat, lon, degrees).
    solution: Option<(f64, f64)>,
    /// Rate limits of the warnings that can come with every message.
    origin_log: LogLimiter,
    utc_log: LogLimiter,
    companion_clock_log: LogLimiter,
    pose_log: LogLimiter,
    /// The last health STATUSTEXT sent, its severity rank (ok 0, degraded 1, lost 2), and since
    /// when a better or differently worded health has been waiting ([`HEALTH_TEXT_HOLD_S`]).
    last_health: Option<String>,
    last_health_rank: u8,
    health_pending_since: Option<Instant>,
    stream_checks: u32,
    /// The autopilot's boot clock: stale messages and reboots.
    boot: BootClock,
    /// Confirmed autopilot reboots.
    reboots: u32,
    /// Reboots plus lock changes: what `Telemetry::boot_epoch` reports.
    epoch: u32,
    /// Output stamps: boot time and Unix time.
    stamp_boot: Monotonic,
    stamp_unix: Monotonic,
    /// Validity stamps of VISION_POSITION_ESTIMATE / ODOMETRY (companion µs).
    stamp_validity: Monotonic,
    /// Boot time of the last estimate sent as a pose: one is never sent twice.
    last_pose_est_us: Option<u64>,
}

struct Shared {
    cfg: LinkConfig,
    out: OutputConfig,
    t0: Instant,
    conn: Mutex<Option<Arc<Conn>>>,
    state: Mutex<State>,
    signing_out: Option<SigningData>,
    signing_in: Option<SigningConfig>,
    seq: AtomicU8,
    tlog: Mutex<Option<Tlog>>,
    /// Rate limit of the .tlog's write failures (a full disk fails every packet).
    tlog_log: Mutex<LogLimiter>,
    metrics: Arc<Metrics>,
    telemetry: broadcast::Sender<Telemetry>,
    status: watch::Sender<LinkStatus>,
}

/// The running link. Dropping it (or [`Link::shutdown`]) stops every task.
pub struct Link {
    shared: Arc<Shared>,
    shutdown: watch::Sender<bool>,
    tasks: Vec<JoinHandle<()>>,
    metrics_addr: Option<std::net::SocketAddr>,
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    // A panic while holding one of these locks is a bug elsewhere; keep going with the data.
    m.lock().unwrap_or_else(|e| e.into_inner())
}

impl Link {
    /// Open the .tlog and metrics endpoint, load the signing key, and start connecting.
    /// Relative paths in `cfg` must already be resolved (`Config::load` does it).
    pub async fn start(cfg: LinkConfig, out: OutputConfig) -> Result<Link, LinkError> {
        // A listen port another program holds stays taken: retrying "address in use" for ever
        // would look like a link waiting for its autopilot. Other bind errors (an address not
        // assigned yet while the network comes up) are left to the reconnect loop.
        if let Ok(endpoint) = crate::config::parse_connection(&cfg.connection)
            && let Err(cause) = endpoint.probe_listen()
            && cause.in_use()
        {
            return Err(LinkError::Listen {
                connection: visnav_core::text::quote(&cfg.connection),
                cause,
            });
        }
        let (signing_out, signing_in) = match &cfg.signing {
            Some(s) => {
                let key = crate::signing::load_key(&s.key_file)?;
                let out_cfg = SigningConfig::new(key, s.link_id, true, !s.reject_unsigned);
                (
                    s.sign_outgoing.then(|| SigningData::from_config(out_cfg)),
                    Some(SigningConfig::new(
                        key,
                        s.link_id,
                        false,
                        !s.reject_unsigned,
                    )),
                )
            }
            None => (None, None),
        };
        let tlog = match &cfg.tlog {
            Some(p) => {
                let path = expand_name(p, unix_now_us() / 1_000_000);
                let t = Tlog::create(&path).map_err(|source| LinkError::Tlog {
                    path: path.clone(),
                    cause: source,
                })?;
                info!(path = %path.display(), "recording telemetry log");
                Some(t)
            }
            None => None,
        };
        let metrics = Arc::new(Metrics::default());
        let (shutdown, _) = watch::channel(false);
        let mut tasks = Vec::new();
        let mut metrics_addr = None;
        if let Some(addr) = &cfg.metrics_listen {
            let sa = addr.parse().map_err(|_| LinkError::Metrics {
                addr: addr.clone(),
                cause: std::io::Error::new(std::io::ErrorKind::InvalidInput, "not IP:PORT"),
            })?;
            let (bound, task) =
                crate::metrics::serve(sa, metrics.clone())
                    .await
                    .map_err(|source| LinkError::Metrics {
                        addr: addr.clone(),
                        cause: source,
                    })?;
            info!(%bound, "Prometheus metrics at http://{bound}/metrics");
            metrics_addr = Some(bound);
            tasks.push(task);
        }
        let state = State {
            autopilot: None,
            last_heartbeat: None,
            timesync: TimeSync::new(cfg.timesync_max_rtt_ms),
            utc: UtcMap::default(),
            rates: RateMonitor::new(2.0),
            pending_ts1: Vec::new(),
            streams_dirty: true,
            origin: None,
            origin_from_autopilot: false,
            origin_sent: 0,
            origin_unverified: false,
            origin_refused: None,
            solution: None,
            origin_log: LogLimiter::default(),
            utc_log: LogLimiter::default(),
            companion_clock_log: LogLimiter::default(),
            pose_log: LogLimiter::default(),
            last_health: None,
            last_health_rank: 0,
            health_pending_since: None,
            stream_checks: 0,
            boot: BootClock::default(),
            reboots: 0,
            epoch: 0,
            stamp_boot: Monotonic::default(),
            stamp_unix: Monotonic::default(),
            stamp_validity: Monotonic::default(),
            last_pose_est_us: None,
        };
        let shared = Arc::new(Shared {
            cfg,
            out,
            t0: Instant::now(),
            conn: Mutex::new(None),
            state: Mutex::new(state),
            signing_out,
            signing_in,
            seq: AtomicU8::new(0),
            tlog: Mutex::new(tlog),
            tlog_log: Mutex::new(LogLimiter::default()),
            metrics,
            telemetry: broadcast::channel(4096).0,
            status: watch::channel(LinkStatus::default()).0,
        });
        tasks.push(tokio::spawn(
            supervise(shared.clone(), shutdown.subscribe()).in_current_span(),
        ));
        Ok(Link {
            shared,
            shutdown,
            tasks,
            metrics_addr,
        })
    }

    /// Bound address of the metrics endpoint, if enabled.
    pub fn metrics_addr(&self) -> Option<std::net::SocketAddr> {
        self.metrics_addr
    }

    /// The link's counters.
    pub fn metrics(&self) -> Arc<Metrics> {
        self.shared.metrics.clone()
    }

    /// Subscribe to the locked autopilot's telemetry.
    pub fn telemetry(&self) -> broadcast::Receiver<Telemetry> {
        self.shared.telemetry.subscribe()
    }

    /// Watch the link status.
    pub fn status(&self) -> watch::Receiver<LinkStatus> {
        self.shared.status.subscribe()
    }

    /// Companion clock in ns of an instant (monotonic, arbitrary origin; the value this link
    /// answers TIMESYNC requests with).
    pub fn companion_ns(&self, t: std::time::Instant) -> i64 {
        self.shared.companion_ns(Instant::from_std(t))
    }

    /// Companion clock now in ns (the link's clock: real time, or the simulator's in lock-step).
    pub fn companion_now_ns(&self) -> i64 {
        self.shared.now_ns()
    }

    /// Autopilot boot time (µs) of a companion instant, e.g. a camera frame's capture time.
    /// `None` until TIMESYNC has converged.
    pub fn to_autopilot_us(&self, t: std::time::Instant) -> Option<u64> {
        let ns = self.shared.companion_ns(Instant::from_std(t));
        lock(&self.shared.state).timesync.to_autopilot_us(ns)
    }

    /// Autopilot boot time now.
    pub fn autopilot_now_us(&self) -> Option<u64> {
        let ns = self.shared.now_ns();
        lock(&self.shared.state).timesync.to_autopilot_us(ns)
    }

    /// A cloneable handle on the clock mapping (for camera and estimator tasks).
    pub fn clock(&self) -> Clock {
        Clock {
            shared: self.shared.clone(),
        }
    }

    /// Send one message to the autopilot (MAVLink 2, signed if configured, recorded).
    pub async fn send(&self, msg: &MavMessage) -> Result<(), LinkError> {
        self.shared.send(msg).await
    }

    /// Ask the locked autopilot to send message `message_id` at `rate_hz`
    /// (MAV_CMD_SET_MESSAGE_INTERVAL). Nothing is sent before an autopilot is locked on.
    pub async fn request_message_rate(
        &self,
        message_id: u32,
        rate_hz: f64,
    ) -> Result<(), LinkError> {
        let Some(ap) = self.status().borrow().autopilot else {
            return Ok(());
        };
        let m = MavMessage::COMMAND_LONG(mavlink::dialects::ardupilotmega::COMMAND_LONG_DATA {
            param1: message_id as f32,
            param2: (1e6 / rate_hz) as f32,
            target_system: ap.system_id,
            target_component: ap.component_id,
            command: mavlink::dialects::ardupilotmega::MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL,
            ..mavlink::dialects::ardupilotmega::COMMAND_LONG_DATA::DEFAULT
        });
        self.send(&m).await
    }

    /// Send a STATUSTEXT (split into 50-character chunks when longer).
    pub async fn status_text(&self, severity: MavSeverity, text: &str) -> Result<(), LinkError> {
        self.shared.status_text(severity, text).await
    }

    /// Build and send the configured injection messages for one estimate. Returns, per mode,
    /// the message name sent or why it was not sent.
    pub async fn inject(
        &self,
        est: &NavEstimate,
    ) -> Vec<(OutputMode, Result<&'static str, InjectError>)> {
        self.shared.inject(est).await
    }

    /// Inject the latest estimate from `rx` at `output.rate_hz` until the link shuts down.
    pub fn spawn_injector(&mut self, mut rx: watch::Receiver<Option<NavEstimate>>) {
        let shared = self.shared.clone();
        let mut stop = self.shutdown.subscribe();
        let period = Duration::from_secs_f64(1.0 / shared.out.rate_hz);
        self.tasks.push(tokio::spawn(
            async move {
                let mut tick = tokio::time::interval(period);
                tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
                loop {
                    tokio::select! {
                        _ = tick.tick() => {}
                        _ = stop.changed() => return,
                    }
                    let est = rx.borrow_and_update().clone();
                    if let Some(e) = est {
                        shared.inject(&e).await;
                    }
                }
            }
            .in_current_span(),
        ));
    }

    /// Stop every task, flush the .tlog.
    pub async fn shutdown(mut self) {
        self.stop_tasks().await;
    }

    async fn stop_tasks(&mut self) {
        let _ = self.shutdown.send(true);
        for t in self.tasks.drain(..) {
            t.abort();
            let _ = t.await;
        }
        if let Some(t) = lock(&self.shared.tlog).as_mut() {
            let _ = t.flush();
        }
    }
}

/// Cloneable handle on the link's companion -> autopilot clock mapping.
#[derive(Clone)]
pub struct Clock {
    shared: Arc<Shared>,
}

impl Clock {
    /// Autopilot boot time (µs) of a companion instant; `None` until TIMESYNC has converged.
    pub fn to_autopilot_us(&self, t: std::time::Instant) -> Option<u64> {
        let ns = self.shared.companion_ns(Instant::from_std(t));
        lock(&self.shared.state).timesync.to_autopilot_us(ns)
    }

    /// Autopilot boot time now.
    pub fn autopilot_now_us(&self) -> Option<u64> {
        let ns = self.shared.now_ns();
        lock(&self.shared.state).timesync.to_autopilot_us(ns)
    }

    /// Companion clock now in ns ([`Link::companion_now_ns`]): what threads away from the
    /// runtime time their log rate limits by.
    pub fn companion_now_ns(&self) -> i64 {
        self.shared.now_ns()
    }
}

impl Drop for Link {
    fn drop(&mut self) {
        let _ = self.shutdown.send(true);
        for t in &self.tasks {
            t.abort();
        }
        if let Some(t) = lock(&self.shared.tlog).as_mut() {
            let _ = t.flush();
        }
    }
}

impl Shared {
    fn companion_ns(&self, t: Instant) -> i64 {
        // +1 s so the clock is never 0 (TIMESYNC uses 0 as "request").
        t.saturating_duration_since(self.t0).as_nanos() as i64 + 1_000_000_000
    }

    fn now_ns(&self) -> i64 {
        self.companion_ns(Instant::now())
    }

    fn our_system_id(&self) -> u8 {
        self.cfg
            .system_id
            .or_else(|| lock(&self.state).autopilot.map(|a| a.system_id))
            .or(self.cfg.autopilot_system_id)
            .unwrap_or(1)
    }

    fn target(&self) -> Option<(u8, u8)> {
        lock(&self.state)
            .autopilot
            .map(|a| (a.system_id, a.component_id))
    }

    fn publish_status(&self) {
        let st = lock(&self.state);
        let connected = lock(&self.conn).is_some();
        let alive = st
            .last_heartbeat
            .is_some_and(|t| t.elapsed().as_secs_f64() < self.cfg.heartbeat_timeout_s);
        self.metrics.autopilot_alive.set(u64::from(alive));
        let new = LinkStatus {
            connected,
            autopilot: st.autopilot,
            alive,
            time_synced: st.timesync.converged(),
            reboots: st.reboots,
            streams_ok: self.status.borrow().streams_ok,
            streams: self.status.borrow().streams.clone(),
            origin: st.origin,
            origin_refused: st.origin_refused.clone(),
        };
        drop(st);
        self.status.send_if_modified(|s| {
            let changed = s.connected != new.connected
                || s.autopilot != new.autopilot
                || s.alive != new.alive
                || s.time_synced != new.time_synced
                || s.reboots != new.reboots
                || s.origin != new.origin
                || s.origin_refused != new.origin_refused;
            if changed {
                *s = new;
            }
            changed
        });
    }

    async fn send(&self, msg: &MavMessage) -> Result<(), LinkError> {
        let conn = lock(&self.conn).clone().ok_or(LinkError::NotConnected)?;
        let header = MavHeader {
            system_id: u32::from(self.our_system_id()),
            component_id: self.cfg.component_id,
            sequence: self.seq.fetch_add(1, Ordering::Relaxed),
        };
        let mut raw = MAVLinkV2MessageRaw::new();
        match &self.signing_out {
            Some(s) => {
                raw.serialize_message_for_signing(header, msg);
                s.sign_message(&mut raw);
            }
            None => raw.serialize_message(header, msg),
        }
        let bytes = raw.raw_bytes().to_vec();
        match conn.send_raw(&MAVLinkMessageRaw::V2(raw)).await {
            Ok(n) => {
                if n > 0 {
                    self.metrics.tx_packets.inc();
                    let failed = lock(&self.tlog)
                        .as_mut()
                        .and_then(|t| t.write(unix_now_us(), &bytes).err());
                    if let Some(e) = failed {
                        self.tlog_failed(&e);
                    }
                }
                Ok(())
            }
            Err(e) => {
                self.metrics.tx_errors.inc();
                Err(LinkError::Send(e.to_string()))
            }
        }
    }

    async fn status_text(&self, severity: MavSeverity, text: &str) -> Result<(), LinkError> {
        info!(target: "statustext", "{text}");
        let bytes = text.as_bytes();
        let chunks: Vec<&[u8]> = if bytes.is_empty() {
            vec![&[][..]]
        } else {
            bytes.chunks(50).collect()
        };
        // Multi-chunk texts share a non-zero id (MAVLink STATUSTEXT chunking).
        let id = if chunks.len() > 1 {
            (self.now_ns() as u16).max(1)
        } else {
            0
        };
        for (i, c) in chunks.iter().enumerate() {
            let mut text = [0u8; 50];
            text[..c.len()].copy_from_slice(c);
            let m = MavMessage::STATUSTEXT(STATUSTEXT_DATA {
                severity,
                text: mavlink::types::CharArray::new(text),
                id,
                chunk_seq: i as u8,
            });
            self.send(&m).await?;
        }
        Ok(())
    }

    fn send_time(&self, est: &NavEstimate) -> Option<SendTime> {
        let now_ns = self.now_ns();
        let mut st = lock(&self.state);
        let t_boot_us = st.timesync.to_autopilot_us(now_ns)?;
        // Fallback UTC: the companion's system clock (used when the autopilot has no clock).
        let companion_unix_minus_boot = Some(unix_now_us() as i128 - t_boot_us as i128);
        let steps_before = st.utc.steps;
        let unix_us = st.utc.unix_us(t_boot_us, companion_unix_minus_boot);
        if st.utc.steps > steps_before {
            self.metrics.utc_steps.inc();
            if let Some(line) = st.companion_clock_log.hit(now_ns as f64 * 1e-9) {
                warn!(
                    "the companion's system clock stepped; GPS_INPUT keeps its UTC{}",
                    line.suffix()
                );
            }
        }
        let unix_us = unix_us.map(|u| st.stamp_unix.stamp(u));
        let t_boot_us = st.stamp_boot.stamp(t_boot_us);
        let validity_companion_us = st
            .timesync
            .to_companion_ns(est.t_boot_us)
            .and_then(|ns| u64::try_from(ns / 1000).ok())
            .map(|us| st.stamp_validity.stamp(us));
        // A counter kept as the stamps' own running total (monotonic).
        self.metrics.output_stamps_held.inner().store(
            st.stamp_boot.held + st.stamp_unix.held + st.stamp_validity.held,
            Ordering::Relaxed,
        );
        Some(SendTime {
            t_boot_us,
            unix_us,
            validity_companion_us,
        })
    }

    async fn inject(
        &self,
        est: &NavEstimate,
    ) -> Vec<(OutputMode, Result<&'static str, InjectError>)> {
        let mut results = Vec::new();
        if let Some(p) = solution_of(est) {
            lock(&self.state).solution = Some(p);
        }
        let Some(now) = self.send_time(est) else {
            self.health_text(&est.health).await;
            self.metrics
                .inject_refused
                .inc_by(self.out.modes.len() as u64);
            return self
                .out
                .modes
                .iter()
                .map(|m| (*m, Err(InjectError::NoCompanionTime)))
                .collect();
        };
        let target = self.target().unwrap_or((1, 1));
        let needs_origin = self
            .out
            .modes
            .iter()
            .any(|m| matches!(m, OutputMode::VisionPositionEstimate | OutputMode::Odometry));
        let origin = if needs_origin {
            self.ensure_origin(est, &now, target.0).await
        } else {
            None
        };
        // Pose outputs held for want of an origin are news for the ground station: a refused
        // origin makes the health degraded (outputs must never stop with the health OK).
        let held = if needs_origin {
            self.metrics
                .pose_output_held
                .set(u64::from(origin.is_none()));
            origin
                .is_none()
                .then(|| lock(&self.state).origin_refused.clone())
                .flatten()
        } else {
            None
        };
        // Local positions go in the autopilot's own projection about its origin.
        let local = origin.map(|o| {
            let ap = lock(&self.state).autopilot.map(|a| a.autopilot);
            inject::AutopilotLocal::for_autopilot(o, ap)
        });
        match (&est.health, held) {
            (Health::Lost { .. }, _) | (_, None) => self.health_text(&est.health).await,
            (_, Some(why)) => {
                let h = Health::Degraded {
                    reason: format!("no pose output: {why}"),
                };
                self.health_text(&h).await;
            }
        }
        // A pose is a measurement for the autopilot's EKF: the same estimate twice would be
        // fused twice. GPS_INPUT is the position now (extrapolated), so it goes at every tick.
        let fresh_pose = {
            let mut st = lock(&self.state);
            let fresh = st.last_pose_est_us.is_none_or(|l| est.t_boot_us > l);
            if fresh && needs_origin {
                st.last_pose_est_us = Some(est.t_boot_us);
            }
            fresh
        };
        for mode in self.out.modes.clone() {
            let built = match mode {
                OutputMode::GpsInput => match (&est.health, self.out.on_lost) {
                    (Health::Lost { .. }, OnLost::NoFix) => {
                        inject::gps_input_no_fix(&now, &self.out)
                    }
                    _ => inject::gps_input(est, &now, &self.out),
                },
                OutputMode::VisionPositionEstimate | OutputMode::Odometry if !fresh_pose => {
                    results.push((mode, Err(InjectError::Repeated)));
                    continue;
                }
                OutputMode::VisionPositionEstimate => local
                    .ok_or(InjectError::NoOrigin)
                    .and_then(|l| inject::vision_position_estimate(est, &now, &l, &self.out)),
                OutputMode::Odometry => local
                    .ok_or(InjectError::NoOrigin)
                    .and_then(|l| inject::odometry(est, &now, &l, &self.out)),
                OutputMode::GlobalPositionSensor => {
                    inject::global_position_sensor(est, &now, target, &self.out)
                }
            };
            let r = match built {
                Ok(m) => {
                    let name = m.message_name();
                    match self.send(&m).await {
                        Ok(()) => {
                            self.metrics.injected.inc();
                            Ok(name)
                        }
                        Err(e) => {
                            debug!("inject {name}: {e}");
                            Err(InjectError::NotSent {
                                reason: e.to_string(),
                            })
                        }
                    }
                }
                Err(e) => {
                    self.metrics.inject_refused.inc();
                    debug!("inject {mode} refused: {e}");
                    self.pose_held(mode, &e);
                    Err(e)
                }
            };
            results.push((mode, r));
        }
        results
    }

    /// A pose output refused for want of a usable origin (none, or one too far for a local
    /// position): a warning, rate-limited, so that the outputs never stop without a word.
    fn pose_held(&self, mode: OutputMode, e: &InjectError) {
        let name = match mode {
            OutputMode::VisionPositionEstimate => "VISION_POSITION_ESTIMATE",
            OutputMode::Odometry => "ODOMETRY",
            _ => return,
        };
        let why = match e {
            InjectError::NoOrigin => {
                let refused = lock(&self.state).origin_refused.clone();
                match refused {
                    Some(r) => r,
                    None => "no EKF origin known (the autopilot has reported none; \
                             output.set_origin = true sets one from the solution)"
                        .to_string(),
                }
            }
            InjectError::OutOfRange {
                field: "local position",
                ..
            } => format!("the position is too far from the EKF origin for a local one: {e}"),
            _ => return,
        };
        let t = self.now_ns() as f64 * 1e-9;
        let line = lock(&self.state).pose_log.hit(t);
        if let Some(line) = line {
            warn!("{name} not sent: {why}{}", line.suffix());
        }
    }

    /// The EKF origin for local positions: the autopilot's, or (with `output.set_origin`) one we
    /// set from a healthy estimate with SET_GPS_GLOBAL_ORIGIN (sent up to 3 times until echoed).
    /// An autopilot origin taken before there was a solution is checked against the first one
    /// here, and refused when too far from it.
    async fn ensure_origin(
        &self,
        est: &NavEstimate,
        now: &SendTime,
        target_sys: u8,
    ) -> Option<GeoOrigin> {
        let (origin, resend, refused_text) = {
            let mut st = lock(&self.state);
            let mut refused_text = None;
            if st.origin_unverified
                && let (Some(o), Some(p)) = (st.origin, solution_of(est))
            {
                st.origin_unverified = false;
                if let Err(why) = check_origin_distance(&o, Some(p), None) {
                    st.origin = None;
                    st.origin_from_autopilot = false;
                    refused_text = self.refuse_origin(&mut st, why, self.now_ns());
                }
            }
            if st.origin.is_none()
                && self.out.set_origin
                && est.health == Health::Ok
                && inject::check_estimate(est).is_ok()
            {
                st.origin = Some(GeoOrigin {
                    lat_deg: est.lat_deg,
                    lon_deg: est.lon_deg,
                    alt_amsl_m: est.alt_amsl_m,
                });
                st.origin_refused = None;
            }
            let resend = !st.origin_from_autopilot && st.origin.is_some() && st.origin_sent < 3;
            if resend {
                st.origin_sent += 1;
            }
            (st.origin, resend, refused_text)
        };
        if let Some((sev, text)) = refused_text {
            let _ = self.status_text(sev, &text).await;
        }
        if resend && let Some(o) = origin {
            match inject::set_gps_global_origin(&o, target_sys, now.unix_us) {
                Ok(m) => {
                    if let Err(e) = self.send(&m).await {
                        debug!("SET_GPS_GLOBAL_ORIGIN: {e}");
                    }
                }
                Err(e) => warn!("SET_GPS_GLOBAL_ORIGIN refused: {e}"),
            }
        }
        self.publish_status();
        origin
    }

    /// The navigation health to the ground station (STATUSTEXT): worse news at once, a better
    /// or differently worded health once it has held for [`HEALTH_TEXT_HOLD_S`].
    async fn health_text(&self, h: &Health) {
        let text = match h {
            Health::Ok => "visnav: navigation OK".to_string(),
            Health::Degraded { reason } => format!("visnav: navigation degraded: {reason}"),
            Health::Lost { reason } => format!("visnav: navigation lost: {reason}"),
        };
        let rank = match h {
            Health::Ok => 0,
            Health::Degraded { .. } => 1,
            Health::Lost { .. } => 2,
        };
        let send = {
            let mut st = lock(&self.state);
            let now = Instant::now();
            let send = if st.last_health.as_deref() == Some(text.as_str()) {
                st.health_pending_since = None;
                false
            } else if st.last_health.is_none() || rank > st.last_health_rank {
                true
            } else {
                let since = *st.health_pending_since.get_or_insert(now);
                now.duration_since(since).as_secs_f64() >= HEALTH_TEXT_HOLD_S
            };
            if send {
                st.last_health = Some(text.clone());
                st.last_health_rank = rank;
                st.health_pending_since = None;
            }
            send
        };
        if send {
            let sev = match h {
                Health::Ok => MavSeverity::MAV_SEVERITY_INFO,
                Health::Degraded { .. } => MavSeverity::MAV_SEVERITY_WARNING,
                Health::Lost { .. } => MavSeverity::MAV_SEVERITY_CRITICAL,
            };
            let _ = self.status_text(sev, &text).await;
        }
    }

    fn record_rx(&self, raw: &MAVLinkMessageRaw) {
        self.metrics.rx_packets.inc();
        let bytes = match raw {
            MAVLinkMessageRaw::V1(m) => m.raw_bytes(),
            MAVLinkMessageRaw::V2(m) => m.raw_bytes(),
        };
        let failed = lock(&self.tlog)
            .as_mut()
            .and_then(|t| t.write(unix_now_us(), bytes).err());
        if let Some(e) = failed {
            self.tlog_failed(&e);
        }
    }

    fn tlog_failed(&self, e: &std::io::Error) {
        let line = lock(&self.tlog_log).hit(self.now_ns() as f64 * 1e-9);
        if let Some(line) = line {
            warn!("tlog write failed: {e}{}", line.suffix());
        }
    }

    /// Refuse an EKF origin: counted, warned (rate-limited), and while no origin is usable the
    /// reason stands in the status and the health. Returns the STATUSTEXT to send (the 1st,
    /// 2nd, 4th ... refusal).
    fn refuse_origin(
        &self,
        st: &mut State,
        why: OriginError,
        t_ns: i64,
    ) -> Option<(MavSeverity, String)> {
        let n = self.metrics.origins_refused.inc() + 1;
        let kept = match st.origin {
            Some(o) => format!(
                "; VISION_POSITION_ESTIMATE / ODOMETRY keep the origin {:.7} {:.7}",
                o.lat_deg, o.lon_deg
            ),
            None => {
                st.origin_refused = Some(format!("EKF origin refused: {why}"));
                "; no origin for VISION_POSITION_ESTIMATE / ODOMETRY".to_string()
            }
        };
        if let Some(line) = st.origin_log.hit(t_ns as f64 * 1e-9) {
            warn!("GPS_GLOBAL_ORIGIN refused: {why}{kept}{}", line.suffix());
        }
        n.is_power_of_two().then(|| {
            (
                MavSeverity::MAV_SEVERITY_WARNING,
                format!("visnav: EKF origin refused: {why}"),
            )
        })
    }

    /// Lock-on (module doc): lock onto a qualifying HEARTBEAT when unlocked, or when the locked
    /// autopilot has been silent for the heartbeat timeout. Returns texts to send.
    fn lock_on(
        &self,
        header: &MavHeader,
        sys: u8,
        hb: &HEARTBEAT_DATA,
    ) -> Vec<(MavSeverity, String)> {
        let comp = header.component_id;
        let (want_sys, want_comp) = (
            self.cfg.autopilot_system_id,
            self.cfg.autopilot_component_id,
        );
        if !is_lock_candidate(want_sys, want_comp, sys, comp, hb) {
            return Vec::new();
        }
        let mut st = lock(&self.state);
        let silent = st
            .last_heartbeat
            .is_none_or(|t| t.elapsed().as_secs_f64() >= self.cfg.heartbeat_timeout_s);
        let relock = match st.autopilot {
            None => false,
            Some(a) if (a.system_id, a.component_id) == (sys, comp) => return Vec::new(),
            Some(_) if silent => true,
            Some(_) => return Vec::new(),
        };
        let info = AutopilotInfo {
            system_id: sys,
            component_id: comp,
            autopilot: hb.autopilot,
            vehicle: hb.mavtype,
        };
        let name = autopilot_name(hb.autopilot);
        if relock {
            self.metrics.relocks.inc();
            warn!("the locked autopilot fell silent; locking onto {name} sys {sys} comp {comp}");
            // A different autopilot: its clock, streams and origin are its own.
            st.boot.reset();
            st.timesync.reset();
            st.utc.reset();
            st.rates.clear();
            st.origin = None;
            st.origin_from_autopilot = false;
            st.origin_sent = 0;
            st.origin_unverified = false;
            st.origin_refused = None;
            st.stamp_boot.reset();
            st.epoch += 1;
        } else {
            info!("locked onto {name} sys {sys} comp {comp}");
        }
        st.autopilot = Some(info);
        st.last_heartbeat = None;
        st.streams_dirty = true;
        vec![(
            MavSeverity::MAV_SEVERITY_INFO,
            format!("visnav: linked to {name} sys {sys}"),
        )]
    }

    /// Handle one message from `from` (udpin's source address).
    async fn handle(
        &self,
        header: MavHeader,
        msg: MavMessage,
        t_ns: i64,
        from: Option<std::net::SocketAddr>,
    ) {
        let Ok(sys) = u8::try_from(header.system_id) else {
            return;
        };
        let mut texts = match &msg {
            MavMessage::HEARTBEAT(hb) => self.lock_on(&header, sys, hb),
            _ => Vec::new(),
        };
        let Some(ap) = self.target() else { return };
        if sys != ap.0 || header.component_id != ap.1 {
            return;
        }
        self.metrics.rx_autopilot.inc();
        let conn = lock(&self.conn).clone();
        if let Some(c) = conn {
            let silence = Duration::from_secs_f64(self.cfg.heartbeat_timeout_s);
            if let Some(addr) = c.autopilot_heard(from, silence) {
                info!(%addr, "replying to the autopilot at {addr}");
            }
        }
        let Some(rebooted) = self.check_boot_clock(&msg, t_ns) else {
            return;
        };
        let reply = {
            let mut st = lock(&self.state);
            if rebooted {
                self.reset_for_reboot(&mut st);
            }
            st.rates.record(msg.message_id(), t_ns as f64 * 1e-9);
            self.observe(&mut st, &msg, ap, t_ns, &mut texts)
        };
        if rebooted {
            self.metrics.reboots.inc();
            warn!(
                "autopilot rebooted (several streams on a new clock); time sync and streams reset"
            );
            texts.push((
                MavSeverity::MAV_SEVERITY_WARNING,
                "visnav: autopilot reboot detected, resyncing".into(),
            ));
        }
        if let Some(r) = reply {
            let _ = self.send(&r).await;
        }
        self.publish_status();
        let (t_boot_us, boot_epoch) = {
            let st = lock(&self.state);
            (st.timesync.to_autopilot_us(t_ns), st.epoch)
        };
        let _ = self.telemetry.send(Telemetry {
            t_companion_ns: t_ns,
            t_boot_us,
            boot_epoch,
            header,
            msg,
        });
        for (sev, t) in texts {
            let _ = self.status_text(sev, &t).await;
        }
    }

    /// The message's boot time against the autopilot's clock: `None` for a stale message (to be
    /// dropped), `Some(true)` when it confirms a reboot.
    fn check_boot_clock(&self, msg: &MavMessage, t_ns: i64) -> Option<bool> {
        let boot_us = match msg {
            MavMessage::TIMESYNC(m) if m.tc1 > 0 => Some((m.tc1 / 1000) as u64),
            MavMessage::TIMESYNC(_) => None,
            m => boot_time_us(m),
        };
        let Some(us) = boot_us else {
            return Some(false);
        };
        match lock(&self.state).boot.observe(msg.message_id(), us, t_ns) {
            BootVerdict::Current => Some(false),
            BootVerdict::Stale => {
                self.metrics.rx_stale.inc();
                debug!("dropped a message behind the autopilot's clock");
                None
            }
            BootVerdict::Reboot => Some(true),
        }
    }

    /// After a reboot: time sync, UTC, stream rates and stamps start again; an origin the
    /// autopilot gave is forgotten (it sends its new one), one visnav sets is sent again.
    fn reset_for_reboot(&self, st: &mut State) {
        st.reboots += 1;
        st.epoch += 1;
        st.timesync.reset();
        st.utc.reset();
        st.rates.clear();
        st.streams_dirty = true;
        st.stamp_boot.reset();
        if !st.origin_from_autopilot || self.out.set_origin {
            st.origin_sent = 0;
        }
        st.origin_from_autopilot = false;
    }

    /// What the autopilot's message tells the session: heartbeat time, UTC steps, time sync,
    /// the EKF origin. Returns the reply to send (a time sync answer), if any; STATUSTEXTs to
    /// send go to `texts`.
    fn observe(
        &self,
        st: &mut State,
        msg: &MavMessage,
        ap: (u8, u8),
        t_ns: i64,
        texts: &mut Vec<(MavSeverity, String)>,
    ) -> Option<MavMessage> {
        match msg {
            MavMessage::HEARTBEAT(_) => st.last_heartbeat = Some(Instant::now()),
            MavMessage::SYSTEM_TIME(m) => {
                if let Some(step_us) = st.utc.observe_system_time(m.time_unix_usec, m.time_boot_ms)
                {
                    self.metrics.utc_steps.inc();
                    let text = format!(
                        "visnav: autopilot clock stepped {:+.3} s, not followed",
                        step_us as f64 * 1e-6
                    );
                    if let Some(line) = st.utc_log.hit(t_ns as f64 * 1e-9) {
                        warn!(
                            "{text} (SYSTEM_TIME; the output keeps its own UTC){}",
                            line.suffix()
                        );
                    }
                    if st.utc.steps.is_power_of_two() {
                        texts.push((MavSeverity::MAV_SEVERITY_WARNING, text));
                    }
                }
            }
            MavMessage::TIMESYNC(m) => return self.on_timesync(st, m, ap, t_ns),
            MavMessage::GPS_GLOBAL_ORIGIN(m) => {
                // The origin in use, sent again, is taken as it is (the vehicle may have flown
                // far from it); a new one must be near where the vehicle is.
                let judged = origin_of(m).and_then(|o| {
                    if st.origin == Some(o) {
                        return Ok(o);
                    }
                    check_origin_distance(&o, st.solution, st.origin.as_ref()).map(|()| o)
                });
                match judged {
                    Ok(o) => {
                        if st.origin != Some(o) {
                            info!(
                                "autopilot EKF origin {:.7} {:.7} {:.1} m",
                                o.lat_deg, o.lon_deg, o.alt_amsl_m
                            );
                            st.origin_unverified = st.solution.is_none();
                        }
                        st.origin = Some(o);
                        st.origin_from_autopilot = true;
                        st.origin_refused = None;
                    }
                    Err(why) => texts.extend(self.refuse_origin(st, why, t_ns)),
                }
            }
            MavMessage::COMMAND_ACK(m) => {
                debug!(command = ?m.command, result = ?m.result, "COMMAND_ACK");
            }
            _ => {}
        }
        None
    }

    /// TIMESYNC: the autopilot's own request gets our clock back; the answer to one of ours is
    /// a time sync sample.
    fn on_timesync(
        &self,
        st: &mut State,
        m: &TIMESYNC_DATA,
        ap: (u8, u8),
        t_ns: i64,
    ) -> Option<MavMessage> {
        if m.tc1 == 0 {
            return Some(MavMessage::TIMESYNC(TIMESYNC_DATA {
                tc1: self.now_ns(),
                ts1: m.ts1,
                target_system: ap.0,
                target_component: ap.1,
            }));
        }
        if let Some(i) = st.pending_ts1.iter().position(|t| *t == m.ts1) {
            st.pending_ts1.drain(..=i);
            let u = st.timesync.update(TimesyncSample {
                sent_companion_ns: m.ts1,
                autopilot_ns: m.tc1,
                received_companion_ns: t_ns,
            });
            if u == SyncUpdate::Accepted {
                self.metrics
                    .timesync_rtt_us
                    .set((st.timesync.last_rtt_ns / 1000.0) as u64);
            }
        }
        None
    }

    fn set_message_interval(&self, target: (u8, u8), id: u32, hz: f64) -> MavMessage {
        MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
            param1: id as f32,
            param2: (1e6 / hz) as f32,
            target_system: target.0,
            target_component: target.1,
            command: MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL,
            ..COMMAND_LONG_DATA::DEFAULT
        })
    }

    /// One stream-manager step: request everything when dirty, else re-request streams below rate.
    async fn manage_streams(&self, specs: &[StreamSpec]) {
        let Some(target) = self.target() else { return };
        let (dirty, statuses) = {
            let mut st = lock(&self.state);
            let dirty = std::mem::replace(&mut st.streams_dirty, false);
            if dirty {
                st.stream_checks = 0;
            } else {
                st.stream_checks += 1;
            }
            let t = self.now_ns() as f64 * 1e-9;
            let statuses =
                streams::evaluate(specs, &mut st.rates, t, self.cfg.streams.min_rate_fraction);
            (dirty, statuses)
        };
        let mut requests = Vec::new();
        if dirty {
            for s in specs {
                requests.push((s.ids[0], s.hz));
            }
            requests.push((ids::GPS_GLOBAL_ORIGIN, 0.0)); // 0.0: one-shot REQUEST_MESSAGE
        } else {
            for (s, stat) in specs.iter().zip(&statuses) {
                if !stat.ok {
                    // The preferred id is missing: ask for the alternatives too.
                    for id in &s.ids {
                        requests.push((*id, s.hz));
                    }
                }
            }
            let all_ok = statuses.iter().all(|s| s.ok);
            let was_ok = self.status.borrow().streams_ok;
            if all_ok != was_ok || self.status.borrow().streams != statuses {
                self.status.send_modify(|s| {
                    s.streams_ok = all_ok;
                    s.streams = statuses.clone();
                });
            }
            if all_ok && !was_ok {
                let _ = self
                    .status_text(
                        MavSeverity::MAV_SEVERITY_INFO,
                        "visnav: telemetry streams OK",
                    )
                    .await;
            } else if !all_ok && was_ok {
                let missing: Vec<&str> =
                    statuses.iter().filter(|s| !s.ok).map(|s| s.name).collect();
                let _ = self
                    .status_text(
                        MavSeverity::MAV_SEVERITY_WARNING,
                        &format!("visnav: streams low: {}", missing.join(",")),
                    )
                    .await;
            }
        }
        for (id, hz) in requests {
            let m = if hz > 0.0 {
                self.set_message_interval(target, id, hz)
            } else {
                MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
                    param1: id as f32,
                    target_system: target.0,
                    target_component: target.1,
                    command: MavCmd::MAV_CMD_REQUEST_MESSAGE,
                    ..COMMAND_LONG_DATA::DEFAULT
                })
            };
            if let Err(e) = self.send(&m).await {
                debug!("stream request: {e}");
            }
        }
    }
}

/// A flight stack's name for messages (never Rust debug formatting).
pub fn autopilot_name(a: MavAutopilot) -> &'static str {
    match a {
        MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA => "ArduPilot",
        MavAutopilot::MAV_AUTOPILOT_PX4 => "PX4",
        MavAutopilot::MAV_AUTOPILOT_GENERIC => "a generic autopilot",
        _ => "an autopilot",
    }
}

/// MAV_TYPE values that are vehicles (what an autopilot flies); peripherals (gimbal, camera,
/// ADS-B, battery, GCS, companion, ...) are not.
fn is_vehicle(t: MavType) -> bool {
    use MavType::*;
    matches!(
        t,
        MAV_TYPE_GENERIC
            | MAV_TYPE_FIXED_WING
            | MAV_TYPE_QUADROTOR
            | MAV_TYPE_COAXIAL
            | MAV_TYPE_HELICOPTER
            | MAV_TYPE_AIRSHIP
            | MAV_TYPE_FREE_BALLOON
            | MAV_TYPE_ROCKET
            | MAV_TYPE_GROUND_ROVER
            | MAV_TYPE_SURFACE_BOAT
            | MAV_TYPE_SUBMARINE
            | MAV_TYPE_HEXAROTOR
            | MAV_TYPE_OCTOROTOR
            | MAV_TYPE_TRICOPTER
            | MAV_TYPE_FLAPPING_WING
            | MAV_TYPE_KITE
            | MAV_TYPE_VTOL_TAILSITTER_DUOROTOR
            | MAV_TYPE_VTOL_TAILSITTER_QUADROTOR
            | MAV_TYPE_VTOL_TILTROTOR
            | MAV_TYPE_VTOL_FIXEDROTOR
            | MAV_TYPE_VTOL_TAILSITTER
            | MAV_TYPE_VTOL_TILTWING
            | MAV_TYPE_VTOL_RESERVED5
            | MAV_TYPE_PARAFOIL
            | MAV_TYPE_DODECAROTOR
            | MAV_TYPE_DECAROTOR
            | MAV_TYPE_GENERIC_MULTIROTOR
            | MAV_TYPE_GROUND_QUADRUPED
            | MAV_TYPE_VTOL_GYRODYNE
    )
}

/// Whether a HEARTBEAT from (`sys`, `comp`) is an autopilot the link may lock onto (module doc),
/// given the configured `autopilot_system_id` and `autopilot_component_id`.
pub fn is_lock_candidate(
    want_sys: Option<u8>,
    want_comp: u8,
    sys: u8,
    comp: u8,
    hb: &HEARTBEAT_DATA,
) -> bool {
    hb.autopilot != MavAutopilot::MAV_AUTOPILOT_INVALID
        && is_vehicle(hb.mavtype)
        && comp == want_comp
        && want_sys.is_none_or(|s| s == sys)
}

/// A received frame's header and message (`None`: a message id or payload this dialect does not
/// decode).
pub fn decode(raw: &MAVLinkMessageRaw) -> Option<(MavHeader, MavMessage)> {
    let msg = MavMessage::parse(raw.version(), raw.message_id(), raw.payload()).ok()?;
    let header = MavHeader {
        system_id: raw.system_id(),
        component_id: raw.component_id(),
        sequence: raw.sequence(),
    };
    Some((header, msg))
}

/// The autopilot boot time a message carries, µs (None for messages without one).
pub fn boot_time_us(msg: &MavMessage) -> Option<u64> {
    let ms = match msg {
        MavMessage::SYSTEM_TIME(m) => m.time_boot_ms,
        MavMessage::ATTITUDE(m) => m.time_boot_ms,
        MavMessage::GLOBAL_POSITION_INT(m) => m.time_boot_ms,
        MavMessage::SCALED_IMU(m) => m.time_boot_ms,
        MavMessage::SCALED_PRESSURE(m) => m.time_boot_ms,
        MavMessage::HIGHRES_IMU(m) => return Some(m.time_usec),
        MavMessage::RAW_IMU(m) => return Some(m.time_usec),
        _ => return None,
    };
    Some(u64::from(ms) * 1000)
}

/// Why a GPS_GLOBAL_ORIGIN cannot be an origin.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum OriginError {
    /// A latitude outside the Earth's, degrees.
    #[error("latitude {0:.7} deg is outside [-90, 90]")]
    Latitude(f64),
    /// A longitude outside the Earth's, degrees.
    #[error("longitude {0:.7} deg is outside [-180, 180]")]
    Longitude(f64),
    /// An altitude no origin can have, metres.
    #[error("altitude {0:.1} m is outside [{lo}, {hi}] m", lo = ORIGIN_ALT_RANGE_M.0, hi = ORIGIN_ALT_RANGE_M.1)]
    Altitude(f64),
    /// Farther than [`MAX_ORIGIN_DISTANCE_M`] from the navigation solution (or the origin it
    /// would replace).
    #[error("{distance_km:.0} km from {from} (limit {limit_km:.0} km)", limit_km = MAX_ORIGIN_DISTANCE_M / 1000.0)]
    Far {
        /// The distance, km.
        distance_km: f64,
        /// What it was measured from: the navigation solution or the previous origin.
        from: &'static str,
    },
}

/// Farthest an EKF origin may lie from the navigation solution (or, before there is one, from
/// the origin it would replace), m. The autopilot sets its origin where its first position
/// came from, near the take-off, and a small UAS flies within tens of kilometres of it; an
/// origin that is wrong rather than distant (a spoofed or corrupted message, a sign or a
/// hemisphere flipped, latitude and longitude swapped) lies hundreds to thousands of
/// kilometres away, and local positions about it are refused anyway beyond 1000 km
/// (`inject::local_pose`). A wrong origin closer than this is not found by distance: signing
/// (`[link.signing]`) keeps others' messages out.
pub const MAX_ORIGIN_DISTANCE_M: f64 = 100_000.0;

/// Straight-line distance between two positions at sea level (lat, lon in degrees), m: the
/// chord, within 1e-5 of the distance along the ground up to [`MAX_ORIGIN_DISTANCE_M`].
fn sea_level_distance_m(a: (f64, f64), b: (f64, f64)) -> f64 {
    let ecef = |(lat_deg, lon_deg): (f64, f64)| {
        visnav_core::geo::ecef::geodetic_to_ecef(lat_deg, lon_deg, 0.0)
            .unwrap_or_else(|_| nalgebra::Vector3::repeat(f64::NAN))
    };
    (ecef(a) - ecef(b)).norm()
}

/// Whether an origin on the Earth can be this vehicle's: within [`MAX_ORIGIN_DISTANCE_M`] of the
/// navigation solution (`solution`: lat, lon degrees) when there is one, else of the origin it
/// would replace; with neither there is nothing to judge it by.
pub fn check_origin_distance(
    o: &GeoOrigin,
    solution: Option<(f64, f64)>,
    previous: Option<&GeoOrigin>,
) -> Result<(), OriginError> {
    let (reference, from) = match (solution, previous) {
        (Some(s), _) => (s, "the navigation solution"),
        (None, Some(p)) => ((p.lat_deg, p.lon_deg), "the previous origin"),
        (None, None) => return Ok(()),
    };
    let d = sea_level_distance_m((o.lat_deg, o.lon_deg), reference);
    // Written so that a NaN distance is refused.
    if d <= MAX_ORIGIN_DISTANCE_M {
        Ok(())
    } else {
        Err(OriginError::Far {
            distance_km: d / 1000.0,
            from,
        })
    }
}

/// The position of an estimate the origin may be judged by: checked and not lost.
fn solution_of(est: &NavEstimate) -> Option<(f64, f64)> {
    (!matches!(est.health, Health::Lost { .. }) && inject::check_estimate(est).is_ok())
        .then_some((est.lat_deg, est.lon_deg))
}

/// A GPS_GLOBAL_ORIGIN's coordinates, or why they cannot be an origin.
pub fn origin_of(
    m: &mavlink::dialects::ardupilotmega::GPS_GLOBAL_ORIGIN_DATA,
) -> Result<GeoOrigin, OriginError> {
    let o = GeoOrigin {
        lat_deg: f64::from(m.latitude) * 1e-7,
        lon_deg: f64::from(m.longitude) * 1e-7,
        alt_amsl_m: f64::from(m.altitude) * 1e-3,
    };
    if !(-90.0..=90.0).contains(&o.lat_deg) {
        return Err(OriginError::Latitude(o.lat_deg));
    }
    if !(-180.0..=180.0).contains(&o.lon_deg) {
        return Err(OriginError::Longitude(o.lon_deg));
    }
    if !(ORIGIN_ALT_RANGE_M.0..=ORIGIN_ALT_RANGE_M.1).contains(&o.alt_amsl_m) {
        return Err(OriginError::Altitude(o.alt_amsl_m));
    }
    Ok(o)
}

/// How long a better (or differently worded) navigation health must hold before the STATUSTEXT
/// says so, s. A solution hovering at a threshold (horizontal sigma 15.0 m against 15 m,
/// sporadic rejected fixes) would otherwise send OK / degraded to the ground station several
/// times a second; worse news is sent at once.
pub const HEALTH_TEXT_HOLD_S: f64 = 3.0;

/// Altitudes an EKF origin can have, m AMSL: below the lowest land (-430 m) and above the
/// highest flight a small UAS makes (10 km), with margin.
pub const ORIGIN_ALT_RANGE_M: (f64, f64) = (-1000.0, 12_000.0);

/// Resolves on the first SIGINT or SIGTERM (Unix) / Ctrl-C (elsewhere): the daemon selects on it
/// and then calls [`Link::shutdown`], which stops the tasks and flushes the .tlog.
pub async fn shutdown_signal() -> std::io::Result<&'static str> {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{SignalKind, signal};
        let mut term = signal(SignalKind::terminate())?;
        let mut int = signal(SignalKind::interrupt())?;
        tokio::select! {
            _ = term.recv() => Ok("SIGTERM"),
            _ = int.recv() => Ok("SIGINT"),
        }
    }
    #[cfg(not(unix))]
    {
        tokio::signal::ctrl_c().await.map(|()| "Ctrl-C")
    }
}

async fn supervise(shared: Arc<Shared>, mut stop: watch::Receiver<bool>) {
    let min = Duration::from_secs_f64(shared.cfg.reconnect_min_s);
    let max = Duration::from_secs_f64(shared.cfg.reconnect_max_s);
    let mut backoff = min;
    loop {
        if *stop.borrow() {
            return;
        }
        let addr = shared.cfg.connection.clone();
        let connected = tokio::select! {
            c = Transport::connect(&addr, shared.signing_in.as_ref()) => c,
            _ = stop.changed() => return,
        };
        match connected {
            Ok(conn) => {
                shared.metrics.connects.inc();
                info!(%addr, "connected");
                let started = Instant::now();
                run_connection(&shared, Arc::new(conn), &mut stop).await;
                *lock(&shared.conn) = None;
                {
                    let mut st = lock(&shared.state);
                    st.last_heartbeat = None;
                    st.streams_dirty = true;
                    st.rates.clear();
                    st.pending_ts1.clear();
                }
                shared.publish_status();
                if *stop.borrow() {
                    return;
                }
                if started.elapsed() > max {
                    backoff = min;
                }
            }
            Err(e) => {
                warn!(%addr, "cannot connect: {e}; retrying in {:.1} s", backoff.as_secs_f64())
            }
        }
        tokio::select! {
            _ = tokio::time::sleep(backoff) => {}
            _ = stop.changed() => return,
        }
        backoff = (backoff * 2).min(max);
    }
}

struct AbortOnDrop(JoinHandle<()>);

impl Drop for AbortOnDrop {
    fn drop(&mut self) {
        self.0.abort();
    }
}

async fn run_connection(shared: &Arc<Shared>, conn: Arc<Conn>, stop: &mut watch::Receiver<bool>) {
    *lock(&shared.conn) = Some(conn.clone());
    shared.publish_status();
    // Aborted on drop too: `Link::shutdown` aborts the supervisor, which drops this future
    // before it reaches the abort below, and a detached heartbeat/TIMESYNC loop would keep
    // sending after shutdown.
    let mut periodic = AbortOnDrop(tokio::spawn(
        periodic_loop(shared.clone()).in_current_span(),
    ));
    let rx = async {
        loop {
            match conn.recv().await {
                Ok(crate::transport::Received { raw, from }) => {
                    let t_ns = shared.now_ns();
                    shared.record_rx(&raw);
                    let Some((header, msg)) = decode(&raw) else {
                        continue;
                    };
                    shared.handle(header, msg, t_ns, from).await;
                }
                Err(MessageReadError::Io(e)) => {
                    warn!("connection lost: {e}");
                    return;
                }
                Err(MessageReadError::Parse(e)) => debug!("dropped a packet: {e}"),
            }
        }
    };
    // Stream transports (TCP, serial) can stay open while the autopilot is gone (half-open TCP,
    // a rebooted USB bridge): reopen them after 3 heartbeat timeouts of silence. Silence counts
    // from the last heartbeat on *this* connection, or from its opening when none has come yet:
    // a peer that accepts the connection and never speaks (or goes quiet before its first
    // heartbeat) must not hold the link open forever.
    let stream_transport = !shared.cfg.connection.starts_with("udp");
    let opened = Instant::now();
    let watchdog = async {
        let mut heard = false;
        loop {
            tokio::time::sleep(Duration::from_millis(250)).await;
            let last = lock(&shared.state).last_heartbeat;
            heard |= last.is_some();
            let silent_s = last
                .map_or_else(|| opened.elapsed(), |h| h.elapsed())
                .as_secs_f64();
            if !heard && silent_s > shared.cfg.heartbeat_timeout_s {
                // Said once per connection: nothing is navigating until an autopilot speaks.
                heard = true;
                warn!(
                    "no autopilot HEARTBEAT on {} after {:.0} s: nothing is navigating. Check the \
                     connection string (udpin listens, udpout sends), the serial device and its \
                     baud rate, and that the autopilot sends MAVLink there (ArduPilot: \
                     SERIALn_PROTOCOL 2; PX4: MAV_n_CONFIG, mavlink-router's endpoints)",
                    shared.cfg.connection, silent_s
                );
            }
            if stream_transport && silent_s > 3.0 * shared.cfg.heartbeat_timeout_s {
                warn!("no autopilot heartbeat on the open connection; reconnecting");
                return;
            }
        }
    };
    tokio::select! {
        _ = rx => {}
        _ = watchdog => {}
        _ = stop.changed() => {}
    }
    periodic.0.abort();
    let _ = (&mut periodic.0).await;
}

/// Heartbeat, TIMESYNC requests, liveness and stream management on one timer.
async fn periodic_loop(shared: Arc<Shared>) {
    let tick_s = 0.05;
    let mut tick = tokio::time::interval(Duration::from_secs_f64(tick_s));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let hb_every = 1.0 / shared.cfg.heartbeat_hz;
    let ts_every = 1.0 / shared.cfg.timesync_hz;
    let (mut next_hb, mut next_ts, mut next_streams) = (0.0, 0.0, 0.5);
    let start = Instant::now();
    let mut was_alive = false;
    loop {
        tick.tick().await;
        let t = start.elapsed().as_secs_f64();
        if t >= next_hb {
            next_hb = t + hb_every;
            let hb = MavMessage::HEARTBEAT(HEARTBEAT_DATA {
                custom_mode: 0,
                mavtype: MavType::MAV_TYPE_ONBOARD_CONTROLLER,
                autopilot: MavAutopilot::MAV_AUTOPILOT_INVALID,
                base_mode: MavModeFlag::empty(),
                system_status: MavState::MAV_STATE_ACTIVE,
                mavlink_version: 3,
            });
            let _ = shared.send(&hb).await;
            let alive = lock(&shared.state)
                .last_heartbeat
                .is_some_and(|h| h.elapsed().as_secs_f64() < shared.cfg.heartbeat_timeout_s);
            if was_alive && !alive {
                warn!("autopilot heartbeat lost");
            }
            was_alive = alive;
            shared.publish_status();
        }
        if t >= next_ts {
            next_ts = t + ts_every;
            if let Some(target) = shared.target() {
                let ts1 = shared.now_ns();
                {
                    let mut st = lock(&shared.state);
                    st.pending_ts1.push(ts1);
                    let n = st.pending_ts1.len();
                    if n > 16 {
                        st.pending_ts1.drain(..n - 16);
                    }
                }
                let m = MavMessage::TIMESYNC(TIMESYNC_DATA {
                    tc1: 0,
                    ts1,
                    target_system: target.0,
                    target_component: target.1,
                });
                let _ = shared.send(&m).await;
            }
        }
        let dirty = lock(&shared.state).streams_dirty;
        if t >= next_streams || (dirty && shared.target().is_some()) {
            next_streams = t + 2.0;
            let autopilot = lock(&shared.state).autopilot.map(|a| a.autopilot);
            let specs = streams::wanted_streams(&shared.cfg.streams, autopilot);
            shared.manage_streams(&specs).await;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(lat_deg: f64, lon_deg: f64) -> GeoOrigin {
        GeoOrigin {
            lat_deg,
            lon_deg,
            alt_amsl_m: 400.0,
        }
    }

    #[test]
    fn an_origin_is_judged_by_the_solution_then_the_previous_origin() {
        let here = (46.9, -96.8);
        // 50 km north: a long flight from where the origin was set.
        assert_eq!(
            check_origin_distance(&at(47.35, -96.8), Some(here), None),
            Ok(())
        );
        // The other side of the world (latitude 0, longitude 42).
        let far = check_origin_distance(&at(0.0, 42.0), Some(here), Some(&at(46.9, -96.8)));
        let Err(OriginError::Far { distance_km, from }) = far else {
            panic!("{far:?}")
        };
        assert!(distance_km > 10_000.0, "{distance_km}");
        assert_eq!(from, "the navigation solution");
        let text = far.unwrap_err().to_string();
        assert!(
            text.contains("km from the navigation solution (limit 100 km)"),
            "{text}"
        );
        // No solution yet: the origin it would replace; with neither, nothing to judge by.
        let moved = check_origin_distance(&at(46.9, -94.0), None, Some(&at(46.9, -96.8)));
        assert!(
            matches!(
                moved,
                Err(OriginError::Far {
                    from: "the previous origin",
                    ..
                })
            ),
            "{moved:?}"
        );
        assert_eq!(check_origin_distance(&at(0.0, 42.0), None, None), Ok(()));
        // A sign flipped: the same latitude in the other hemisphere.
        assert!(check_origin_distance(&at(-46.9, -96.8), Some(here), None).is_err());
        // Not a number is never near.
        assert!(check_origin_distance(&at(f64::NAN, 0.0), Some(here), None).is_err());
    }
}
