//! The daemon's optional Prometheus endpoint (`[daemon] metrics_listen`, off by default): a
//! minimal HTTP/1.1 server on tokio that answers `GET /metrics` (and `HEAD`) with the text
//! exposition format 0.0.4
//! (<https://prometheus.io/docs/instrumenting/exposition_formats/#text-based-format>) of the
//! daemon's counters ([`DaemonMetrics`]), the link's counters ([`LinkMetrics`]) and the
//! navigation health.
//!
//! Format: per metric family one `# HELP name text` and one `# TYPE name counter|gauge|summary`
//! line, then its samples `name{label="value",...} number`. Counters end in `_total`; units are in
//! the names in base units (`_seconds`); the frame-to-fix latency is a summary without quantiles
//! (`visnav_fix_latency_seconds_sum` / `_count`). Label values are escaped (`\\`, `\"`, `\n`).
//! The health is one-hot: `visnav_nav_health{state="none|ok|degraded|lost"}`, exactly one is 1.
//!
//! HTTP: one request per connection (`Connection: close`), the request head must arrive within
//! [`MAX_REQUEST_BYTES`] and [`IO_TIMEOUT`]; anything else than `GET`/`HEAD /metrics` gets 404
//! (another path), 405 (another method), 400 (not HTTP) or 431 (head too large). At most
//! [`MAX_CONNECTIONS`] connections are served at once; more are closed at once. No input can
//! panic the server (the parser only slices what it has checked).

use std::fmt::Write as _;
use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{Semaphore, watch};
use tokio::task::{JoinHandle, JoinSet};
use tracing::{debug, info};

use crate::metrics::{DaemonMetrics, HealthState, MetricsSnapshot};
use visnav_link::metrics::Metrics as LinkMetrics;

/// Largest accepted request head (request line + headers), bytes.
pub const MAX_REQUEST_BYTES: usize = 8192;
/// Time allowed to receive the request and send the answer.
pub const IO_TIMEOUT: Duration = Duration::from_secs(5);
/// Connections served at once.
pub const MAX_CONNECTIONS: usize = 16;

// ---------------------------------------------------------------------------------------------
// Exposition text

/// Writes metric families in the text format.
struct Writer {
    out: String,
}

impl Writer {
    fn family(&mut self, name: &str, kind: &str, help: &str) {
        // HELP text escaping: backslash and line feed.
        let help = help.replace('\\', "\\\\").replace('\n', "\\n");
        let _ = writeln!(self.out, "# HELP {name} {help}\n# TYPE {name} {kind}");
    }

    fn sample(&mut self, name: &str, labels: &[(&str, &str)], v: f64) {
        self.out.push_str(name);
        if !labels.is_empty() {
            self.out.push('{');
            for (i, (k, val)) in labels.iter().enumerate() {
                if i > 0 {
                    self.out.push(',');
                }
                let _ = write!(self.out, "{k}=\"{}\"", escape_label(val));
            }
            self.out.push('}');
        }
        self.out.push(' ');
        self.out.push_str(&number(v));
        self.out.push('\n');
    }

    fn single(&mut self, name: &str, kind: &str, help: &str, v: f64) {
        self.family(name, kind, help);
        self.sample(name, &[], v);
    }
}

/// The frame-sequence counters of visual odometry (`prefix` "vo", a frame gives a "motion")
/// or the DTM navigator ("dtm", a "pose"; `started`: kept waiting for a partner).
fn sequence(w: &mut Writer, v: &crate::metrics::VoSnapshot, prefix: &str, what: &str, out: &str) {
    let c = |v: u64| v as f64;
    let name = |s: &str| format!("visnav_{prefix}_{s}");
    let frames = name("frames_total");
    w.family(
        &frames,
        "counter",
        &format!("frames given to {what}, by what came out"),
    );
    let refused: u64 = v.refused.values().sum();
    for (outcome, n) in [
        (out, v.motions),
        ("started", v.started),
        ("refused", refused),
    ] {
        w.sample(&frames, &[("outcome", outcome)], c(n));
    }
    let outs = name(&format!("{out}s_total"));
    w.family(
        &outs,
        "counter",
        &format!("{what} {out}s, by what the filter did with them"),
    );
    for (outcome, n) in [
        ("fused", v.fused),
        ("filter_rejected", v.filter_rejected),
        ("unused", v.unused),
    ] {
        w.sample(&outs, &[("outcome", outcome)], c(n));
    }
    let refusals = name("refusals_total");
    w.family(
        &refusals,
        "counter",
        &format!("frames without a {what} {out}, by reason"),
    );
    for (reason, n) in &v.refused {
        w.sample(&refusals, &[("reason", reason)], c(*n));
    }
    w.single(
        &name("frame_seconds_max"),
        "gauge",
        &format!("longest {what} computation of a frame"),
        v.ms_max * 1e-3,
    );
}

/// A label value with `\`, `"` and line feeds escaped.
pub fn escape_label(v: &str) -> String {
    let mut s = String::with_capacity(v.len());
    for c in v.chars() {
        match c {
            '\\' => s.push_str("\\\\"),
            '"' => s.push_str("\\\""),
            '\n' => s.push_str("\\n"),
            c => s.push(c),
        }
    }
    s
}

/// A sample value as Prometheus writes it (`NaN`, `+Inf`, `-Inf` for the non-finite).
fn number(v: f64) -> String {
    if v.is_nan() {
        "NaN".into()
    } else if v.is_infinite() {
        if v > 0.0 { "+Inf" } else { "-Inf" }.into()
    } else {
        format!("{v}")
    }
}

/// Render the daemon snapshot and the link counters as exposition text.
pub fn render(d: &MetricsSnapshot, link: &LinkMetrics) -> String {
    let mut w = Writer { out: String::new() };
    let c = |v: u64| v as f64;
    w.family("visnav_build_info", "gauge", "visnav version (always 1)");
    w.sample(
        "visnav_build_info",
        &[("version", env!("CARGO_PKG_VERSION"))],
        1.0,
    );

    if let Some(b) = crate::heap::heap_in_use_bytes() {
        w.single(
            "visnav_heap_bytes",
            "gauge",
            "bytes allocated on the heap and not freed (the process's own count)",
            b as f64,
        );
    }
    // Navigation.
    w.family(
        "visnav_nav_health",
        "gauge",
        "navigation health, one-hot over state (none = no solution yet)",
    );
    for s in HealthState::ALL {
        let v = if s == d.health { 1.0 } else { 0.0 };
        w.sample("visnav_nav_health", &[("state", s.name())], v);
    }
    for (name, help, v) in [
        (
            "visnav_nav_health_changes_total",
            "navigation health state changes",
            d.health_changes,
        ),
        (
            "visnav_nav_outputs_total",
            "filter outputs published",
            d.nav_outputs,
        ),
        (
            "visnav_nav_filter_restarts_total",
            "filter restarts after an autopilot reboot",
            d.autopilot_reboots,
        ),
        (
            "visnav_imu_samples_total",
            "IMU samples given to the filter",
            d.imu_samples,
        ),
        (
            "visnav_imu_timeouts_total",
            "IMU stream timeouts (solution declared lost)",
            d.imu_timeouts,
        ),
        (
            "visnav_telemetry_lagged_messages_total",
            "telemetry messages lost because the navigation task fell behind",
            d.telemetry_lagged,
        ),
    ] {
        w.single(name, "counter", help, c(v));
    }
    if let Some(b) = &d.imu_bias {
        for (name, help, v) in [
            (
                "visnav_imu_bias_pairs_total",
                "SCALED_IMU paired with a HIGHRES_IMU (daemon.imu_bias_restore)",
                b.paired,
            ),
            (
                "visnav_imu_bias_unpaired_total",
                "SCALED_IMU that no HIGHRES_IMU matched",
                b.unpaired,
            ),
            (
                "visnav_imu_bias_bootstraps_total",
                "autopilot bias estimates bootstrapped (more than 1: the autopilot's estimate jumped)",
                b.bootstraps,
            ),
            (
                "visnav_imu_samples_not_restored_total",
                "HIGHRES_IMU samples passed on without the autopilot's bias added back",
                b.not_restored,
            ),
        ] {
            w.single(name, "counter", help, c(v));
        }
        if let Some(a) = b.age_s {
            w.single(
                "visnav_imu_bias_age_seconds",
                "gauge",
                "time since the last SCALED_IMU / HIGHRES_IMU pair (the estimate is dropped after 5 s)",
                a,
            );
        }
        w.single(
            "visnav_imu_bias_restoring",
            "gauge",
            "1 while HIGHRES_IMU samples get the autopilot's bias estimate added back",
            if b.restoring { 1.0 } else { 0.0 },
        );
        for (name, help, v) in [
            (
                "visnav_imu_bias_gyro_deg_per_hour",
                "the autopilot's gyro bias estimate added back to HIGHRES_IMU, body FRD",
                b.gyro_bias_deg_h,
            ),
            (
                "visnav_imu_bias_accel_mg",
                "the autopilot's accelerometer bias estimate added back to HIGHRES_IMU, body FRD",
                b.accel_bias_mg,
            ),
        ] {
            if let Some(v) = v {
                w.family(name, "gauge", help);
                for (axis, x) in ["x", "y", "z"].iter().zip(v) {
                    w.sample(name, &[("axis", axis)], x);
                }
            }
        }
    }

    // Frames.
    w.single(
        "visnav_frames_read_total",
        "counter",
        "frames read from the source",
        c(d.frames_in),
    );
    w.family(
        "visnav_frames_dropped_total",
        "counter",
        "frames dropped before a fix, by reason",
    );
    for (reason, v) in [
        ("superseded", d.frames_superseded),
        ("stale", d.frames_stale),
        ("no_time", d.frames_no_time),
    ] {
        w.sample("visnav_frames_dropped_total", &[("reason", reason)], c(v));
    }
    w.single(
        "visnav_frame_errors_total",
        "counter",
        "frames that could not be read",
        c(d.frame_errors),
    );
    w.single(
        "visnav_frames_frozen_total",
        "counter",
        "frames dropped as identical to the one before (a frozen camera)",
        c(d.frames_frozen),
    );
    w.single(
        "visnav_frame_queue_depth_max",
        "gauge",
        "largest number of frames waiting at once",
        c(d.queue_depth_max),
    );

    // Fixes.
    w.single(
        "visnav_fixes_attempted_total",
        "counter",
        "frames given to the fix engine",
        c(d.fixes_attempted),
    );
    w.family(
        "visnav_fixes_total",
        "counter",
        "fixes the engine returned, by what the filter did with them",
    );
    for (outcome, v) in [
        ("accepted", d.fixes_accepted),
        ("filter_rejected", d.fixes_filter_rejected),
        ("too_old", d.fixes_too_old),
        ("invalid", d.fixes_invalid),
        ("unused_before_init", d.fixes_unused_before_init),
        ("dropped_at_shutdown", d.fixes_dropped_at_shutdown),
    ] {
        w.sample("visnav_fixes_total", &[("outcome", outcome)], c(v));
    }
    w.family(
        "visnav_fix_engine_rejections_total",
        "counter",
        "fixes the engine rejected, by reason",
    );
    for (reason, v) in &d.engine_rejected {
        w.sample(
            "visnav_fix_engine_rejections_total",
            &[("reason", reason)],
            c(*v),
        );
    }
    sequence(&mut w, &d.vo, "vo", "visual odometry", "motion");
    sequence(&mut w, &d.dtm, "dtm", "DTM navigation", "pose");
    w.family(
        "visnav_fix_latency_seconds",
        "summary",
        "time from taking a frame to the fix report",
    );
    w.sample(
        "visnav_fix_latency_seconds_sum",
        &[],
        d.fix_latency_ms_sum as f64 * 1e-3,
    );
    w.sample(
        "visnav_fix_latency_seconds_count",
        &[],
        c(d.fix_latency_count),
    );
    w.single(
        "visnav_fix_latency_last_seconds",
        "gauge",
        "frame-to-fix latency of the last fix",
        d.fix_latency_ms_last as f64 * 1e-3,
    );
    w.single(
        "visnav_fix_latency_max_seconds",
        "gauge",
        "largest frame-to-fix latency",
        d.fix_latency_ms_max as f64 * 1e-3,
    );

    // Link.
    let g = |a: &std::sync::atomic::AtomicU64| a.load(Ordering::Relaxed) as f64;
    for (name, help, v) in [
        (
            "visnav_link_rx_packets_total",
            "MAVLink packets received (any system)",
            &link.rx_packets,
        ),
        (
            "visnav_link_rx_autopilot_packets_total",
            "MAVLink packets received from the locked autopilot",
            &link.rx_autopilot,
        ),
        (
            "visnav_link_tx_packets_total",
            "MAVLink packets sent",
            &link.tx_packets,
        ),
        (
            "visnav_link_tx_errors_total",
            "MAVLink send failures",
            &link.tx_errors,
        ),
        (
            "visnav_link_connects_total",
            "connections established",
            &link.connects,
        ),
        (
            "visnav_link_autopilot_reboots_total",
            "autopilot reboots detected",
            &link.reboots,
        ),
        (
            "visnav_inject_sent_total",
            "injection messages sent (all output modes)",
            &link.injected,
        ),
        (
            "visnav_inject_refused_total",
            "injections refused (invalid, stale or lost estimate)",
            &link.inject_refused,
        ),
        (
            "visnav_link_rx_stale_total",
            "messages dropped as behind the autopilot clock (stale, replayed or spoofed)",
            &link.rx_stale,
        ),
        (
            "visnav_link_origins_refused_total",
            "GPS_GLOBAL_ORIGIN messages refused as impossible",
            &link.origins_refused,
        ),
        (
            "visnav_link_utc_steps_total",
            "steps of the autopilot UTC clock seen and not followed",
            &link.utc_steps,
        ),
        (
            "visnav_link_output_stamps_held_total",
            "output time stamps moved forward to stay monotonic",
            &link.output_stamps_held,
        ),
        (
            "visnav_link_relocks_total",
            "lock-on moved to another autopilot after the locked one fell silent",
            &link.relocks,
        ),
    ] {
        w.single(name, "counter", help, g(v));
    }
    w.single(
        "visnav_link_timesync_rtt_seconds",
        "gauge",
        "last TIMESYNC round trip",
        g(&link.timesync_rtt_us) * 1e-6,
    );
    w.single(
        "visnav_link_autopilot_alive",
        "gauge",
        "1 while the autopilot heartbeat is current",
        g(&link.autopilot_alive),
    );
    w.out
}

// ---------------------------------------------------------------------------------------------
// HTTP

/// What to answer a request head with.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Route {
    /// `GET /metrics` (body) or `HEAD /metrics` (headers only).
    Metrics { head_only: bool },
    /// An error status.
    Status(u16),
}

/// Route a complete request head (`buf` up to and including the blank line). Never panics.
pub fn route(buf: &[u8]) -> Route {
    let line_end = buf
        .windows(2)
        .position(|w| w == b"\r\n")
        .or_else(|| buf.iter().position(|&b| b == b'\n'))
        .unwrap_or(buf.len());
    let Ok(line) = std::str::from_utf8(&buf[..line_end]) else {
        return Route::Status(400);
    };
    let mut parts = line.split(' ');
    let (Some(method), Some(target), Some(version), None) =
        (parts.next(), parts.next(), parts.next(), parts.next())
    else {
        return Route::Status(400);
    };
    if !version.starts_with("HTTP/1.") || method.is_empty() || !target.starts_with('/') {
        return Route::Status(400);
    }
    let path = target.split(['?', '#']).next().unwrap_or(target);
    let head_only = match method {
        "GET" => false,
        "HEAD" => true,
        _ => return Route::Status(405),
    };
    if path == "/metrics" {
        Route::Metrics { head_only }
    } else {
        Route::Status(404)
    }
}

fn reason(status: u16) -> &'static str {
    match status {
        200 => "OK",
        400 => "Bad Request",
        404 => "Not Found",
        405 => "Method Not Allowed",
        408 => "Request Timeout",
        431 => "Request Header Fields Too Large",
        _ => "Error",
    }
}

/// The full response to send.
pub fn response(route: Route, render: impl FnOnce() -> String) -> Vec<u8> {
    let (status, ctype, body, head_only) = match route {
        Route::Metrics { head_only } => (
            200,
            "text/plain; version=0.0.4; charset=utf-8",
            render(),
            head_only,
        ),
        Route::Status(s) => (
            s,
            "text/plain; charset=utf-8",
            match s {
                404 => "not found: the metrics are at /metrics\n".to_string(),
                _ => format!("{}\n", reason(s).to_lowercase()),
            },
            false,
        ),
    };
    let allow = if status == 405 {
        "Allow: GET, HEAD\r\n"
    } else {
        ""
    };
    let mut out = format!(
        "HTTP/1.1 {status} {}\r\nContent-Type: {ctype}\r\nContent-Length: {}\r\n{allow}\
         Cache-Control: no-cache\r\nConnection: close\r\n\r\n",
        reason(status),
        body.len()
    )
    .into_bytes();
    if !head_only {
        out.extend_from_slice(body.as_bytes());
    }
    out
}

/// Read a request head: `Ok(route)` once the blank line arrived, a 431 when it does not within
/// [`MAX_REQUEST_BYTES`], a 400 when the peer closes first.
async fn read_head(sock: &mut TcpStream) -> std::io::Result<Route> {
    let mut buf = Vec::with_capacity(1024);
    let mut chunk = [0u8; 1024];
    loop {
        let n = sock.read(&mut chunk).await?;
        if n == 0 {
            return Ok(Route::Status(400));
        }
        let from = buf.len().saturating_sub(3);
        buf.extend_from_slice(&chunk[..n]);
        let tail = &buf[from..];
        if tail.windows(4).any(|w| w == b"\r\n\r\n") || tail.windows(2).any(|w| w == b"\n\n") {
            return Ok(route(&buf));
        }
        if buf.len() > MAX_REQUEST_BYTES {
            return Ok(Route::Status(431));
        }
    }
}

async fn serve_one(mut sock: TcpStream, render: Arc<dyn Fn() -> String + Send + Sync>) {
    let work = async {
        let route = read_head(&mut sock).await?;
        let resp = response(route, || render());
        sock.write_all(&resp).await?;
        sock.shutdown().await
    };
    match tokio::time::timeout(IO_TIMEOUT, work).await {
        Ok(Ok(())) => {}
        Ok(Err(e)) => debug!("metrics connection: {e}"),
        Err(_) => debug!("metrics connection: timed out"),
    }
}

/// A bound, not yet serving listener (bind first so a taken port fails before anything starts).
pub struct Endpoint {
    listener: TcpListener,
}

impl Endpoint {
    /// Bind `addr` (port 0: any free port).
    pub async fn bind(addr: SocketAddr) -> std::io::Result<Self> {
        Ok(Self {
            listener: TcpListener::bind(addr).await?,
        })
    }

    /// The bound address.
    pub fn local_addr(&self) -> std::io::Result<SocketAddr> {
        self.listener.local_addr()
    }

    /// Serve `render()` at `/metrics` until [`MetricsServer::stop`] (or drop).
    pub fn serve(self, render: Arc<dyn Fn() -> String + Send + Sync>) -> MetricsServer {
        let addr = self
            .listener
            .local_addr()
            .unwrap_or_else(|_| SocketAddr::from(([0, 0, 0, 0], 0)));
        let (stop, mut stop_rx) = watch::channel(false);
        let listener = self.listener;
        let task = tokio::spawn(async move {
            let permits = Arc::new(Semaphore::new(MAX_CONNECTIONS));
            let mut conns = JoinSet::new();
            loop {
                while conns.try_join_next().is_some() {}
                tokio::select! {
                    _ = stop_rx.changed() => break,
                    r = listener.accept() => match r {
                        Ok((sock, peer)) => {
                            let Ok(permit) = permits.clone().try_acquire_owned() else {
                                debug!(%peer, "metrics: too many connections; closed");
                                continue;
                            };
                            let render = render.clone();
                            conns.spawn(async move {
                                serve_one(sock, render).await;
                                drop(permit);
                            });
                        }
                        Err(e) => {
                            // E.g. out of file descriptors: do not spin.
                            debug!("metrics accept: {e}");
                            tokio::time::sleep(Duration::from_millis(100)).await;
                        }
                    },
                }
            }
            // Dropping the JoinSet aborts the connections still open.
        });
        info!(%addr, "Prometheus metrics at http://{addr}/metrics");
        MetricsServer {
            addr,
            stop,
            task: Some(task),
        }
    }
}

/// The running endpoint.
pub struct MetricsServer {
    addr: SocketAddr,
    stop: watch::Sender<bool>,
    task: Option<JoinHandle<()>>,
}

impl MetricsServer {
    /// Bind and serve the daemon's and the link's counters.
    pub async fn start(
        addr: SocketAddr,
        daemon: Arc<DaemonMetrics>,
        link: Arc<LinkMetrics>,
    ) -> std::io::Result<Self> {
        Ok(Endpoint::bind(addr).await?.serve(renderer(daemon, link)))
    }

    /// The address it listens on.
    pub fn local_addr(&self) -> SocketAddr {
        self.addr
    }

    /// Stop accepting, close open connections and wait for the task.
    pub async fn stop(mut self) {
        let _ = self.stop.send(true);
        if let Some(t) = self.task.take() {
            let _ = t.await;
        }
    }
}

impl Drop for MetricsServer {
    fn drop(&mut self) {
        if let Some(t) = self.task.take() {
            t.abort();
        }
    }
}

/// The render function of the daemon's endpoint.
pub fn renderer(
    daemon: Arc<DaemonMetrics>,
    link: Arc<LinkMetrics>,
) -> Arc<dyn Fn() -> String + Send + Sync> {
    Arc::new(move || render(&daemon.snapshot(), &link))
}

#[cfg(test)]
mod tests {
    use super::*;
    use visnav_link::Health as LinkHealth;

    fn sample_text() -> String {
        let d = DaemonMetrics::default();
        d.imu_samples.store(1234, Ordering::Relaxed);
        d.frames_stale.store(3, Ordering::Relaxed);
        d.fixes_accepted.store(7, Ordering::Relaxed);
        d.latency(250);
        d.latency(750);
        d.engine_reject("too few matches: 3 < 12");
        d.engine_reject("quote \" back\\slash\nnewline");
        d.set_health(&LinkHealth::Degraded {
            reason: "coasting".into(),
        });
        *d.imu_bias.lock().unwrap() = Some(crate::imu_bias::RestoreStatus {
            paired: 10,
            unpaired: 2,
            bootstraps: 1,
            not_restored: 3,
            bias: Some(([0.0, -0.5e-3, 0.0], [0.0; 3])),
            bias_t_us: Some(1_000_000),
            last_sample_t_us: Some(3_500_000),
            restoring: true,
        });
        let l = LinkMetrics::default();
        l.rx_packets.store(99, Ordering::Relaxed);
        l.timesync_rtt_us.store(1500, Ordering::Relaxed);
        render(&d.snapshot(), &l)
    }

    #[test]
    fn formatter_writes_valid_families_and_values() {
        let t = sample_text();
        let lines: Vec<&str> = t.lines().collect();
        assert!(t.ends_with('\n'));
        for want in [
            "visnav_imu_samples_total 1234",
            "visnav_imu_bias_pairs_total 10",
            "visnav_imu_bias_unpaired_total 2",
            "visnav_imu_samples_not_restored_total 3",
            "visnav_imu_bias_gyro_deg_per_hour{axis=\"x\"} 0",
            "visnav_imu_bias_accel_mg{axis=\"z\"} 0",
            "visnav_imu_bias_age_seconds 2.5",
            "visnav_imu_bias_restoring 1",
            "visnav_frames_dropped_total{reason=\"stale\"} 3",
            "visnav_fixes_total{outcome=\"accepted\"} 7",
            "visnav_fix_latency_seconds_sum 1",
            "visnav_fix_latency_seconds_count 2",
            "visnav_fix_latency_last_seconds 0.75",
            "visnav_fix_latency_max_seconds 0.75",
            "visnav_nav_health{state=\"degraded\"} 1",
            "visnav_nav_health{state=\"ok\"} 0",
            "visnav_nav_health{state=\"none\"} 0",
            "visnav_link_rx_packets_total 99",
            "visnav_link_timesync_rtt_seconds 0.0015",
            "visnav_fix_engine_rejections_total{reason=\"too few matches: N < N\"} 1",
            "visnav_fix_engine_rejections_total{reason=\"quote \\\" back\\\\slash\\nnewline\"} 1",
            "# TYPE visnav_fix_latency_seconds summary",
            "# TYPE visnav_nav_health gauge",
        ] {
            assert!(lines.contains(&want), "missing {want:?} in\n{t}");
        }
        // Every family: HELP then TYPE, once; counters end in _total; every sample belongs to
        // the family declared last.
        let mut seen = std::collections::HashSet::new();
        let mut family = String::new();
        let mut kind = String::new();
        for (i, l) in lines.iter().enumerate() {
            if let Some(rest) = l.strip_prefix("# HELP ") {
                let name = rest.split(' ').next().unwrap();
                assert!(seen.insert(name.to_string()), "family {name} twice");
                let ty = lines[i + 1];
                assert!(ty.starts_with(&format!("# TYPE {name} ")), "{ty}");
                family = name.to_string();
            } else if let Some(rest) = l.strip_prefix("# TYPE ") {
                kind = rest.split(' ').nth(1).unwrap().to_string();
                if kind == "counter" {
                    assert!(family.ends_with("_total"), "counter {family}");
                }
            } else {
                let name = l.split(['{', ' ']).next().unwrap();
                let ok = name == family
                    || (kind == "summary"
                        && (name == format!("{family}_sum") || name == format!("{family}_count")));
                assert!(ok, "sample {l} outside its family {family}");
                let v = l.rsplit(' ').next().unwrap();
                assert!(v.parse::<f64>().is_ok_and(f64::is_finite), "{l}");
            }
        }
        // One-hot health.
        let hot: Vec<&&str> = lines
            .iter()
            .filter(|l| l.starts_with("visnav_nav_health{") && l.ends_with(" 1"))
            .collect();
        assert_eq!(hot.len(), 1, "{hot:?}");
    }

    #[test]
    fn numbers_and_escapes() {
        assert_eq!(number(f64::NAN), "NaN");
        assert_eq!(number(f64::INFINITY), "+Inf");
        assert_eq!(number(f64::NEG_INFINITY), "-Inf");
        assert_eq!(number(0.5), "0.5");
        assert_eq!(number(3.0), "3");
        assert_eq!(escape_label("a\"b\\c\nd"), "a\\\"b\\\\c\\nd");
    }

    #[test]
    fn routing_of_good_and_bad_requests() {
        assert_eq!(
            route(b"GET /metrics HTTP/1.1\r\nHost: x\r\n\r\n"),
            Route::Metrics { head_only: false }
        );
        assert_eq!(
            route(b"HEAD /metrics?x=1 HTTP/1.0\r\n\r\n"),
            Route::Metrics { head_only: true }
        );
        assert_eq!(
            route(b"GET /metrics HTTP/1.1\n\n"),
            Route::Metrics { head_only: false }
        );
        for (req, want) in [
            (&b"GET / HTTP/1.1\r\n\r\n"[..], 404),
            (b"GET /metricsX HTTP/1.1\r\n\r\n", 404),
            (b"GET /../metrics HTTP/1.1\r\n\r\n", 404),
            (b"POST /metrics HTTP/1.1\r\n\r\n", 405),
            (b"DELETE /metrics HTTP/1.1\r\n\r\n", 405),
            (b"GET /metrics\r\n\r\n", 400),
            (b"GET /metrics HTTP/1.1 extra\r\n\r\n", 400),
            (b"GET metrics HTTP/1.1\r\n\r\n", 400),
            (b"GET /metrics SPDY/3\r\n\r\n", 400),
            (b"\xff\xfe\x00garbage\r\n\r\n", 400),
            (b"", 400),
            (b"\r\n\r\n", 400),
        ] {
            assert_eq!(route(req), Route::Status(want), "{req:?}");
        }
        let r = String::from_utf8(response(Route::Status(405), String::new)).unwrap();
        assert!(r.starts_with("HTTP/1.1 405 Method Not Allowed\r\n"), "{r}");
        assert!(r.contains("Allow: GET, HEAD\r\n") && r.contains("Connection: close\r\n"));
        let r = String::from_utf8(response(Route::Metrics { head_only: true }, || {
            "x 1\n".into()
        }))
        .unwrap();
        assert!(
            r.contains("Content-Length: 4\r\n") && r.ends_with("\r\n\r\n"),
            "{r}"
        );
        assert!(r.contains("text/plain; version=0.0.4"));
    }

    proptest::proptest! {
        #[test]
        fn route_never_panics(bytes in proptest::collection::vec(proptest::prelude::any::<u8>(), 0..300)) {
            let _ = route(&bytes);
        }
    }

    async fn ask(addr: SocketAddr, req: &[u8]) -> String {
        let mut s = TcpStream::connect(addr).await.unwrap();
        // The server may answer (and close) before all of an oversized request is written.
        let _ = s.write_all(req).await;
        let mut out = Vec::new();
        let _ = s.read_to_end(&mut out).await;
        String::from_utf8_lossy(&out).into_owned()
    }

    #[tokio::test]
    async fn server_answers_and_stops() {
        let d = Arc::new(DaemonMetrics::default());
        let l = Arc::new(LinkMetrics::default());
        let srv = MetricsServer::start("127.0.0.1:0".parse().unwrap(), d.clone(), l)
            .await
            .unwrap();
        let addr = srv.local_addr();
        d.imu_samples.store(5, Ordering::Relaxed);
        let r = ask(addr, b"GET /metrics HTTP/1.1\r\nHost: a\r\n\r\n").await;
        assert!(r.starts_with("HTTP/1.1 200 OK\r\n"), "{r}");
        assert!(r.contains("\nvisnav_imu_samples_total 5\n"), "{r}");
        // Split across packets.
        let mut s = TcpStream::connect(addr).await.unwrap();
        s.write_all(b"GET /met").await.unwrap();
        tokio::time::sleep(Duration::from_millis(50)).await;
        s.write_all(b"rics HTTP/1.1\r\n\r\n").await.unwrap();
        let mut out = String::new();
        s.read_to_string(&mut out).await.unwrap();
        assert!(out.starts_with("HTTP/1.1 200"), "{out}");
        assert!(
            ask(addr, b"GET /x HTTP/1.1\r\n\r\n")
                .await
                .starts_with("HTTP/1.1 404")
        );
        assert!(
            ask(addr, b"garbage\r\n\r\n")
                .await
                .starts_with("HTTP/1.1 400")
        );
        let big = vec![b'a'; MAX_REQUEST_BYTES * 2];
        let r = ask(addr, &big).await;
        assert!(r.is_empty() || r.starts_with("HTTP/1.1 431"), "{r}");
        // A client that sends nothing and closes: no answer needed, server keeps serving.
        drop(TcpStream::connect(addr).await.unwrap());
        assert!(
            ask(addr, b"GET /metrics HTTP/1.0\r\n\r\n")
                .await
                .starts_with("HTTP/1.1 200")
        );
        srv.stop().await;
        assert!(TcpStream::connect(addr).await.is_err(), "still listening");
    }
}
