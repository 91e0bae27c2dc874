//! The link's metrics ([`Metrics`], declared with `visnav_metrics::metric_set!`), its own
//! endpoint (`link.metrics_listen`, [`serve`]: a registry with the link's metrics alone; `visnav
//! run`'s endpoint registers them beside the daemon's in one registry), and the rate limit of
//! repeated warnings ([`LogLimiter`]).

use std::net::SocketAddr;
use std::sync::Arc;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpListener;
use visnav_metrics::{CONTENT_TYPE, Counter, Gauge, Registry, render};

visnav_metrics::metric_set! {
    /// The link's counters and gauges (atomics; cheap to update from any task).
    pub struct Metrics => MetricsSnapshot {
        /// Packets received (any system).
        rx_packets: Counter "visnav_link_rx_packets" "MAVLink packets received (any system)",
        /// Packets received from the locked autopilot.
        rx_autopilot: Counter "visnav_link_rx_autopilot_packets"
            "MAVLink packets received from the locked autopilot",
        /// Packets sent.
        tx_packets: Counter "visnav_link_tx_packets" "MAVLink packets sent",
        /// Send failures.
        tx_errors: Counter "visnav_link_tx_errors" "MAVLink send failures",
        /// Connections (re)established.
        connects: Counter "visnav_link_connects" "connections established",
        /// Autopilot reboots detected.
        reboots: Counter "visnav_link_autopilot_reboots" "autopilot reboots detected",
        /// Injection messages sent (all modes).
        injected: Counter "visnav_inject_sent" "injection messages sent (all output modes)",
        /// Injections refused (invalid, stale or lost estimate).
        inject_refused: Counter "visnav_inject_refused"
            "injections refused (invalid, stale or lost estimate)",
        /// Messages dropped because their boot time was behind the autopilot's clock (stale,
        /// replayed or spoofed; `time::BootClock`).
        rx_stale: Counter "visnav_link_rx_stale"
            "messages dropped as behind the autopilot clock (stale, replayed or spoofed)",
        /// EKF origins refused: coordinates outside the Earth's, or farther than
        /// `session::MAX_ORIGIN_DISTANCE_M` from the navigation solution.
        origins_refused: Counter "visnav_link_origins_refused"
            "EKF origins refused (impossible, or too far from the navigation solution)",
        /// 1 while VISION_POSITION_ESTIMATE / ODOMETRY are configured but cannot be sent for
        /// want of a usable EKF origin.
        pose_output_held: Gauge "visnav_link_pose_output_held"
            "1 while VISION_POSITION_ESTIMATE / ODOMETRY are held for want of a usable EKF origin",
        /// Steps of the autopilot's UTC clock (SYSTEM_TIME) seen and not followed.
        utc_steps: Counter "visnav_link_utc_steps"
            "steps of the autopilot UTC clock seen and not followed",
        /// Output stamps moved forward so that output time never goes back.
        output_stamps_held: Counter "visnav_link_output_stamps_held"
            "output time stamps moved forward to stay monotonic",
        /// Lock-on changes (the locked autopilot fell silent and another took its place).
        relocks: Counter "visnav_link_relocks"
            "lock-on moved to another autopilot after the locked one fell silent",
        /// Last TIMESYNC round trip, µs.
        timesync_rtt_us: Gauge "visnav_link_timesync_rtt_seconds" "last TIMESYNC round trip"
            / 1e6,
        /// 1 while the autopilot's heartbeat is current.
        autopilot_alive: Gauge "visnav_link_autopilot_alive"
            "1 while the autopilot heartbeat is current",
    }
}

impl Metrics {
    /// The link's metrics alone as Prometheus text.
    pub fn render(&self) -> String {
        let mut reg = Registry::default();
        self.register(&mut reg);
        render(&reg)
    }
}

/// Seconds between two log lines of one repeated warning ([`LogLimiter`]). An operator
/// following the log still sees within this time that a fault goes on, while a fault hit
/// thousands of times a second (every file of a camera folder missing, a spoofer's every
/// packet) writes a few lines a minute instead of megabytes.
pub const LOG_REPEAT_INTERVAL_S: f64 = 10.0;

/// Rate limit of one repeated warning, with counts: the first occurrence is logged, later ones
/// at most once per interval, each logged line saying how many went unlogged since the one
/// before ([`LogLine::suffix`]). The caller passes the time, seconds on its own monotonic clock
/// (the link's companion clock: the simulator's in lock-step, so a run logs the same lines
/// whatever the CPU's speed); a clock that goes back counts as the interval elapsed.
#[derive(Debug, Clone, PartialEq)]
pub struct LogLimiter {
    interval_s: f64,
    last_line_s: Option<f64>,
    suppressed: u64,
    total: u64,
}

/// A line [`LogLimiter::hit`] lets through: occurrences not logged since the line before, and
/// occurrences in all (this one included).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LogLine {
    /// Occurrences not logged since the line before.
    pub suppressed: u64,
    /// Occurrences in all, this one included.
    pub total: u64,
}

impl LogLine {
    /// What to append to the warning: nothing on the first occurrence, else the counts, e.g.
    /// ` (4170 more like this not logged; 4172 so far)`.
    pub fn suffix(&self) -> String {
        match (self.total, self.suppressed) {
            (0..=1, _) => String::new(),
            (t, 0) => format!(" ({t} so far)"),
            (t, s) => format!(" ({s} more like this not logged; {t} so far)"),
        }
    }
}

impl Default for LogLimiter {
    fn default() -> Self {
        Self::new(LOG_REPEAT_INTERVAL_S)
    }
}

impl LogLimiter {
    /// At most one line per `interval_s` seconds.
    pub fn new(interval_s: f64) -> Self {
        Self {
            interval_s,
            last_line_s: None,
            suppressed: 0,
            total: 0,
        }
    }

    /// One occurrence at `t_s`: `Some` when it is to be logged (with the counts to append).
    pub fn hit(&mut self, t_s: f64) -> Option<LogLine> {
        self.total = self.total.saturating_add(1);
        // Written so that a NaN time logs (never silences a warning for good).
        let due = self.last_line_s.is_none_or(|last| {
            let within = t_s >= last && t_s - last < self.interval_s;
            !within
        });
        if !due {
            self.suppressed = self.suppressed.saturating_add(1);
            return None;
        }
        self.last_line_s = Some(t_s);
        Some(LogLine {
            suppressed: std::mem::take(&mut self.suppressed),
            total: self.total,
        })
    }

    /// At the end of the repeats (a source that ended, a shutdown): the occurrences not yet
    /// said, if any.
    pub fn flush(&mut self) -> Option<LogLine> {
        (self.suppressed > 0).then(|| LogLine {
            suppressed: std::mem::take(&mut self.suppressed),
            total: self.total,
        })
    }

    /// Occurrences so far.
    pub fn total(&self) -> u64 {
        self.total
    }
}

/// Serve `metrics` on `addr` until the task is aborted. Returns the bound address (useful with
/// port 0) once listening.
pub async fn serve(
    addr: SocketAddr,
    metrics: Arc<Metrics>,
) -> std::io::Result<(SocketAddr, tokio::task::JoinHandle<()>)> {
    let listener = TcpListener::bind(addr).await?;
    let local = listener.local_addr()?;
    let mut reg = Registry::default();
    metrics.register(&mut reg);
    let reg = Arc::new(reg);
    let task = tokio::spawn(async move {
        loop {
            let Ok((mut sock, _)) = listener.accept().await else {
                continue;
            };
            let reg = reg.clone();
            tokio::spawn(async move {
                let mut buf = [0u8; 1024];
                let n = match tokio::time::timeout(
                    std::time::Duration::from_secs(2),
                    sock.read(&mut buf),
                )
                .await
                {
                    Ok(Ok(n)) => n,
                    _ => return,
                };
                let req = String::from_utf8_lossy(&buf[..n]);
                let (status, body) = if req.starts_with("GET /metrics") {
                    ("200 OK", render(&reg))
                } else {
                    ("404 Not Found", "see /metrics\n".to_string())
                };
                let resp = format!(
                    "HTTP/1.1 {status}\r\nContent-Type: {CONTENT_TYPE}\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
                    body.len()
                );
                let _ = sock.write_all(resp.as_bytes()).await;
                let _ = sock.shutdown().await;
            });
        }
    });
    Ok((local, task))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_flood_of_one_warning_gives_a_line_per_interval_with_counts() {
        let mut l = LogLimiter::new(10.0);
        // 200,001 occurrences over 22 s (a folder of missing frames read as fast as it goes).
        let n = 200_001u64;
        let lines: Vec<(f64, LogLine)> = (0..n)
            .filter_map(|k| {
                let t = 100.0 + 22.0 * k as f64 / n as f64;
                l.hit(t).map(|line| (t, line))
            })
            .collect();
        assert_eq!(lines.len(), 3, "{lines:?}");
        assert_eq!(
            lines[0].1,
            LogLine {
                suppressed: 0,
                total: 1
            }
        );
        assert_eq!(lines[0].1.suffix(), "");
        assert!(lines.windows(2).all(|w| w[1].0 - w[0].0 >= 10.0));
        let said: u64 = lines.iter().map(|(_, l)| 1 + l.suppressed).sum();
        let rest = l.flush().expect("the last ones not yet said");
        assert_eq!(
            said + rest.suppressed,
            n,
            "every occurrence is counted once"
        );
        assert_eq!(rest.total, n);
        assert_eq!(l.flush(), None);
        assert_eq!(l.total(), n);
        let s = lines[1].1.suffix();
        assert!(
            s.contains("more like this not logged") && s.contains("so far"),
            "{s}"
        );
    }

    #[test]
    fn a_rare_warning_is_always_logged_and_odd_clocks_never_silence_it() {
        let mut l = LogLimiter::default();
        assert!(l.hit(0.0).is_some());
        assert!(l.hit(LOG_REPEAT_INTERVAL_S).is_some());
        let line = l.hit(3.0 * LOG_REPEAT_INTERVAL_S).unwrap();
        assert_eq!(line.suffix(), " (3 so far)");
        // A clock that went back (another clock's times) logs rather than waits.
        assert!(l.hit(1.0).is_some());
        // A NaN time logs (and never silences what follows).
        assert!(l.hit(f64::NAN).is_some());
        assert!(l.hit(2.0).is_some());
        assert_eq!(l.total(), 6);
    }

    #[tokio::test]
    async fn serves_prometheus_text() {
        let m = Arc::new(Metrics::default());
        m.tx_packets.inc_by(7);
        m.timesync_rtt_us.set(1500);
        let (addr, task) = serve("127.0.0.1:0".parse().unwrap(), m).await.unwrap();
        let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
        s.write_all(b"GET /metrics HTTP/1.1\r\nHost: x\r\n\r\n")
            .await
            .unwrap();
        let mut body = String::new();
        s.read_to_string(&mut body).await.unwrap();
        assert!(body.starts_with("HTTP/1.1 200"), "{body}");
        for want in [
            "\n# TYPE visnav_link_tx_packets_total counter\n",
            "\nvisnav_link_tx_packets_total 7\n",
            "\nvisnav_link_timesync_rtt_seconds 0.0015\n",
        ] {
            assert!(body.contains(want), "{want:?} missing in {body}");
        }
        task.abort();
    }
}
