//! Link counters and an optional Prometheus text-format endpoint (`GET /metrics`, off by default).
//! The exposition format: <https://prometheus.io/docs/instrumenting/exposition_formats/>.

use std::fmt::Write as _;
use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpListener;

/// Counters and gauges of the link (all atomics; cheap to update from any task).
#[derive(Debug, Default)]
pub struct Metrics {
    /// Packets received (any system).
    pub rx_packets: AtomicU64,
    /// Packets received from the locked autopilot.
    pub rx_autopilot: AtomicU64,
    /// Packets sent.
    pub tx_packets: AtomicU64,
    /// Send failures.
    pub tx_errors: AtomicU64,
    /// Connections (re)established.
    pub connects: AtomicU64,
    /// Autopilot reboots detected.
    pub reboots: AtomicU64,
    /// Injection messages sent (all modes).
    pub injected: AtomicU64,
    /// Injections refused (invalid, stale or lost estimate).
    pub inject_refused: AtomicU64,
    /// Last TIMESYNC round trip, µs.
    pub timesync_rtt_us: AtomicU64,
    /// 1 while the autopilot's heartbeat is current.
    pub autopilot_alive: AtomicU64,
    /// Messages dropped because their boot time was behind the autopilot's clock (stale,
    /// replayed or spoofed; `time::BootClock`).
    pub rx_stale: AtomicU64,
    /// GPS_GLOBAL_ORIGIN messages refused (coordinates outside the Earth's).
    pub origins_refused: AtomicU64,
    /// Steps of the autopilot's UTC clock (SYSTEM_TIME) seen and not followed.
    pub utc_steps: AtomicU64,
    /// Output stamps moved forward so that output time never goes back.
    pub output_stamps_held: AtomicU64,
    /// Lock-on changes (the locked autopilot fell silent and another took its place).
    pub relocks: AtomicU64,
}

impl Metrics {
    /// Render in the Prometheus text format.
    pub fn render(&self) -> String {
        let mut s = String::new();
        let items: [(&str, &str, &str, &AtomicU64); 15] = [
            (
                "visnav_link_rx_packets_total",
                "counter",
                "MAVLink packets received",
                &self.rx_packets,
            ),
            (
                "visnav_link_rx_autopilot_packets_total",
                "counter",
                "packets from the locked autopilot",
                &self.rx_autopilot,
            ),
            (
                "visnav_link_tx_packets_total",
                "counter",
                "MAVLink packets sent",
                &self.tx_packets,
            ),
            (
                "visnav_link_tx_errors_total",
                "counter",
                "send failures",
                &self.tx_errors,
            ),
            (
                "visnav_link_connects_total",
                "counter",
                "connections established",
                &self.connects,
            ),
            (
                "visnav_link_autopilot_reboots_total",
                "counter",
                "autopilot reboots detected",
                &self.reboots,
            ),
            (
                "visnav_inject_sent_total",
                "counter",
                "injection messages sent",
                &self.injected,
            ),
            (
                "visnav_inject_refused_total",
                "counter",
                "injections refused",
                &self.inject_refused,
            ),
            (
                "visnav_link_timesync_rtt_us",
                "gauge",
                "last TIMESYNC round trip in microseconds",
                &self.timesync_rtt_us,
            ),
            (
                "visnav_link_autopilot_alive",
                "gauge",
                "1 while the autopilot heartbeat is current",
                &self.autopilot_alive,
            ),
            (
                "visnav_link_rx_stale_total",
                "counter",
                "messages dropped as behind the autopilot clock",
                &self.rx_stale,
            ),
            (
                "visnav_link_origins_refused_total",
                "counter",
                "GPS_GLOBAL_ORIGIN messages refused as impossible",
                &self.origins_refused,
            ),
            (
                "visnav_link_utc_steps_total",
                "counter",
                "steps of the autopilot UTC clock not followed",
                &self.utc_steps,
            ),
            (
                "visnav_link_output_stamps_held_total",
                "counter",
                "output time stamps moved forward to stay monotonic",
                &self.output_stamps_held,
            ),
            (
                "visnav_link_relocks_total",
                "counter",
                "lock-on moved to another autopilot",
                &self.relocks,
            ),
        ];
        for (name, kind, help, v) in items {
            let _ = writeln!(
                s,
                "# HELP {name} {help}\n# TYPE {name} {kind}\n{name} {}",
                v.load(Ordering::Relaxed)
            );
        }
        s
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
    let task = tokio::spawn(async move {
        loop {
            let Ok((mut sock, _)) = listener.accept().await else {
                continue;
            };
            let m = metrics.clone();
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
                    ("200 OK", m.render())
                } else {
                    ("404 Not Found", "see /metrics\n".to_string())
                };
                let resp = format!(
                    "HTTP/1.1 {status}\r\nContent-Type: text/plain; version=0.0.4\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
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

    #[tokio::test]
    async fn serves_prometheus_text() {
        let m = Arc::new(Metrics::default());
        m.tx_packets.store(7, Ordering::Relaxed);
        let (addr, task) = serve("127.0.0.1:0".parse().unwrap(), m).await.unwrap();
        let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
        s.write_all(b"GET /metrics HTTP/1.1\r\nHost: x\r\n\r\n")
            .await
            .unwrap();
        let mut body = String::new();
        s.read_to_string(&mut body).await.unwrap();
        assert!(body.starts_with("HTTP/1.1 200"), "{body}");
        assert!(
            body.contains("\nvisnav_link_tx_packets_total 7\n"),
            "{body}"
        );
        task.abort();
    }
}
