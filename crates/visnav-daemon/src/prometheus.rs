//! The daemon's optional Prometheus endpoint (`[daemon] metrics_listen`, off by default): a
//! minimal HTTP/1.1 server on tokio that answers `GET /metrics` (and `HEAD`) with the text
//! exposition format 0.0.4
//! (<https://prometheus.io/docs/instrumenting/exposition_formats/#text-based-format>) of one
//! registry ([`crate::metrics::registry`]: the daemon's metrics, the link's and the navigation
//! health), written by `prometheus-client`.
//!
//! Format: per metric family one `# HELP name text` and one `# TYPE name
//! counter|gauge|histogram` line, then its samples `name{label="value",...} number`. Counters end
//! in `_total`; units are in the names in base units (`_seconds`); computing times are
//! histograms (`_bucket{le}`, `_sum`, `_count`). Label values are escaped (`\\`, `\"`, `\n`).
//! The health is one-hot: `visnav_nav_health{state="none|ok|degraded|lost"}`, exactly one is 1.
//!
//! HTTP: one request per connection (`Connection: close`), the request head must arrive within
//! [`MAX_REQUEST_BYTES`] and [`IO_TIMEOUT`]; anything else than `GET`/`HEAD /metrics` gets 404
//! (another path), 405 (another method), 400 (not HTTP) or 431 (head too large). At most
//! [`MAX_CONNECTIONS`] connections are served at once; more are closed at once. No input can
//! panic the server (the parser only slices what it has checked).

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{Semaphore, watch};
use tokio::task::{JoinHandle, JoinSet};
use tracing::{debug, info};

use crate::metrics::DaemonMetrics;
use visnav_link::metrics::Metrics as LinkMetrics;
use visnav_metrics::{CONTENT_TYPE, Registry};

/// Largest accepted request head (request line + headers), bytes.
pub const MAX_REQUEST_BYTES: usize = 8192;
/// Time allowed to receive the request and send the answer.
pub const IO_TIMEOUT: Duration = Duration::from_secs(5);
/// Connections served at once.
pub const MAX_CONNECTIONS: usize = 16;

/// The registry as exposition text (format 0.0.4).
pub fn render(registry: &Registry) -> String {
    visnav_metrics::render(registry)
}

// ---------------------------------------------------------------------------------------------
// HTTP

/// What to answer a request head with.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Route {
    /// `GET /metrics` (body) or `HEAD /metrics` (headers only).
    /// `GET /metrics` (body) or `HEAD /metrics` (headers only).
    Metrics {
        /// `HEAD`: the headers without the body.
        head_only: bool,
    },
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
        Route::Metrics { head_only } => (200, CONTENT_TYPE, render(), head_only),
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
        let reg = crate::metrics::registry(&daemon, &link);
        Ok(Endpoint::bind(addr).await?.serve(renderer(reg)))
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

/// The render function of an endpoint serving `registry`.
pub fn renderer(registry: Registry) -> Arc<dyn Fn() -> String + Send + Sync> {
    Arc::new(move || render(&registry))
}

#[cfg(test)]
mod tests {
    use super::*;
    use visnav_link::Health as LinkHealth;

    /// Metrics with values, their registry and its text.
    fn sample() -> (DaemonMetrics, LinkMetrics, String) {
        let d = DaemonMetrics::default();
        d.imu_samples.inc_by(1234);
        d.frames_stale.inc_by(3);
        d.fixes_accepted.inc_by(7);
        d.latency(250);
        d.latency(750);
        d.engine_reject("few_matches", "only 3 matches (min 12)");
        d.vo.time(20_000);
        d.vo.refuse("few_tracks", "3 tracks, need 8");
        // A label value with the characters the text format escapes.
        d.vo.refuse("quote \"back\" back\\slash\nnewline", "x");
        d.dtm.refuse("flat_ground", "flat ground");
        d.health.set(&LinkHealth::Degraded {
            reason: "coasting".into(),
        });
        d.imu_bias.set(crate::imu_bias::RestoreStatus {
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
        l.rx_packets.inc_by(99);
        l.timesync_rtt_us.set(1500);
        let text = render(&crate::metrics::registry(&d, &l));
        (d, l, text)
    }

    #[test]
    fn formatter_writes_valid_families_and_values() {
        let (_, _, t) = sample();
        let lines: Vec<&str> = t.lines().collect();
        assert!(t.ends_with('\n'));
        for want in [
            "visnav_build_info{version=\"0.1.0\"} 1",
            "visnav_imu_samples_total 1234",
            "visnav_imu_bias_pairs_total 10",
            "visnav_imu_bias_unpaired_total 2",
            "visnav_imu_samples_not_restored_total 3",
            "visnav_imu_bias_gyro_deg_per_hour{axis=\"x\"} 0.0",
            "visnav_imu_bias_accel_mg{axis=\"z\"} 0.0",
            "visnav_imu_bias_age_seconds 2.5",
            "visnav_imu_bias_restoring 1.0",
            "visnav_frames_dropped_total{reason=\"stale\"} 3",
            "visnav_frames_dropped_total{reason=\"no_time\"} 0",
            "visnav_fixes_total{outcome=\"accepted\"} 7",
            "visnav_fix_latency_seconds_sum 1.0",
            "visnav_fix_latency_seconds_count 2",
            "visnav_fix_latency_seconds_bucket{le=\"0.25\"} 1",
            "visnav_fix_latency_seconds_bucket{le=\"1\"} 2",
            "visnav_fix_latency_last_seconds 0.75",
            "visnav_fix_latency_max_seconds 0.75",
            "visnav_nav_health{state=\"degraded\"} 1",
            "visnav_nav_health{state=\"ok\"} 0",
            "visnav_nav_health{state=\"none\"} 0",
            "visnav_vo_frames_total{outcome=\"refused\"} 2",
            "visnav_vo_refusals_total{reason=\"few_tracks\"} 1",
            "visnav_vo_refusals_total{reason=\"quote \\\"back\\\" back\\\\slash\\nnewline\"} 1",
            "visnav_vo_frame_seconds_count 1",
            "visnav_vo_frame_seconds_max 0.02",
            "visnav_dtm_poses_total{outcome=\"fused\"} 0",
            "visnav_link_rx_packets_total 99",
            "visnav_link_timesync_rtt_seconds 0.0015",
            "visnav_fix_engine_rejections_total{reason=\"few_matches\"} 1",
            "# TYPE visnav_fix_latency_seconds histogram",
            "# TYPE visnav_nav_health gauge",
            "# TYPE visnav_imu_samples_total counter",
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
                    || (kind == "histogram"
                        && ["_sum", "_count", "_bucket"]
                            .iter()
                            .any(|s| name == format!("{family}{s}")));
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

    /// The metric names in docs/operations.md's metrics table (`### Metrics`), labels removed.
    fn documented_metrics() -> std::collections::BTreeSet<String> {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../../docs/operations.md");
        let doc = std::fs::read_to_string(path).unwrap();
        let section = doc
            .split("\n### Metrics\n")
            .nth(1)
            .expect("a ### Metrics section");
        let table = section.split("\n#").next().unwrap_or(section);
        table
            .lines()
            .filter_map(|l| l.strip_prefix("| `"))
            // The first cell: the names, each in backquotes.
            .flat_map(|l| l.split(" | ").next().unwrap_or("").split('`'))
            .filter(|w| w.starts_with("visnav_"))
            .map(|w| w.split('{').next().unwrap_or(w).to_string())
            .collect()
    }

    /// Every metric declared in the registry is served with its HELP and TYPE (a counter as
    /// `name_total`, a set of families by its prefix), every served family has a sample, and
    /// the served families are the ones docs/operations.md's metrics table lists: a metric
    /// added to `DaemonMetrics` or the link's `Metrics` fails here until it is documented,
    /// rather than against a count kept by hand.
    #[test]
    fn every_registered_metric_is_served_with_help_and_type() {
        let (_, _, t) = sample();
        let helps: Vec<&str> = t
            .lines()
            .filter_map(|l| l.strip_prefix("# HELP ")?.split(' ').next())
            .collect();
        for f in &helps {
            assert!(t.contains(&format!("\n# TYPE {f} ")), "{f}: no TYPE");
            let sampled = t.lines().any(|l| !l.starts_with('#') && l.starts_with(f));
            assert!(sampled, "{f}: no sample");
        }
        let declared = DaemonMetrics::NAMES.iter().chain(LinkMetrics::NAMES);
        for name in declared.chain(&["visnav_build_info", "visnav_heap_bytes"]) {
            let served = helps.iter().any(|h| {
                h.strip_prefix(name)
                    .is_some_and(|rest| rest.is_empty() || rest.starts_with('_'))
            });
            // The heap is counted only by the binary's allocator (not in unit tests).
            assert!(served || *name == "visnav_heap_bytes", "{name} not served");
        }
        // The link's newest: the pose outputs held for want of an origin, and the origins
        // refused (impossible or too far from the solution).
        for (family, kind) in [
            ("visnav_link_pose_output_held", "gauge"),
            ("visnav_link_origins_refused_total", "counter"),
        ] {
            assert!(helps.contains(&family), "{family} not served");
            assert!(
                t.contains(&format!("\n# TYPE {family} {kind}\n")),
                "{family}"
            );
        }
        let documented = documented_metrics();
        let served: std::collections::BTreeSet<String> =
            helps.iter().map(|h| h.to_string()).collect();
        let undocumented: Vec<&String> = served.difference(&documented).collect();
        assert!(
            undocumented.is_empty(),
            "served but not in docs/operations.md's metrics table: {undocumented:?}"
        );
        // The heap is counted only by the binary's allocator (not in unit tests).
        let unserved: Vec<&String> = documented
            .difference(&served)
            .filter(|n| *n != "visnav_heap_bytes")
            .collect();
        assert!(
            unserved.is_empty(),
            "in docs/operations.md's metrics table but not served: {unserved:?}"
        );
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
        d.imu_samples.inc_by(5);
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
