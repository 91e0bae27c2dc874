//! The daemon's Prometheus endpoint (`[daemon] metrics_listen`) end to end: the daemon runs
//! against the built-in autopilot emulator over loopback UDP, the endpoint listens on a free
//! loopback port, and it is scraped over a real TCP socket. The exposition text is parsed line by
//! line (every line a valid comment or sample, every sample in a declared family, counters named
//! `_total`), every metric declared in the registry must be served with its HELP and TYPE, the
//! expected metric names must be present, the counters must grow between two
//! scrapes, the health is one-hot; bad requests get their error status, and the endpoint is gone
//! after shutdown.

use std::collections::{BTreeMap, HashMap};
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::time::{Duration, Instant};

use visnav::daemon::{Daemon, DaemonConfig, DaemonError, DaemonMetrics, DaemonSetup};
use visnav::link::config::{LinkConfig, OutputConfig, OutputMode};
use visnav::link::metrics::Metrics as LinkMetrics;
use visnav::nav::NavConfig;
use visnav::sitl::autopilot::{AutopilotEmulator, EmulatorConfig};

use crate::common;
use common::{TRUTH, free_udp_port};

fn setup(port: u16, metrics_listen: &str) -> DaemonSetup {
    DaemonSetup {
        link: LinkConfig::new(&format!("udpin:127.0.0.1:{port}")),
        output: OutputConfig {
            modes: vec![OutputMode::GpsInput],
            rate_hz: 5.0,
            gps_id: 1,
            ..OutputConfig::default()
        },
        nav: NavConfig {
            max_imu_gap_s: 0.5,
            ..NavConfig::default()
        },
        daemon: DaemonConfig {
            imu_timeout_s: 1.0,
            metrics_listen: Some(metrics_listen.into()),
            ..DaemonConfig::default()
        },
        frames: None,
        vo: Default::default(),
        dtm_nav: Default::default(),
    }
}

/// One HTTP exchange over a blocking socket: (status line, headers, body).
fn http(addr: SocketAddr, request: &[u8]) -> (String, String, String) {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    s.write_all(request).unwrap();
    let mut out = Vec::new();
    s.read_to_end(&mut out).unwrap();
    let text = String::from_utf8(out).expect("response is UTF-8");
    let (head, body) = text.split_once("\r\n\r\n").expect("header/body separator");
    let (status, headers) = head.split_once("\r\n").unwrap_or((head, ""));
    (status.to_string(), headers.to_string(), body.to_string())
}

/// Label pairs of a sample.
type Labels = Vec<(String, String)>;
/// A parsed sample: metric name and labels (sorted) -> value.
type Samples = BTreeMap<(String, Labels), f64>;

fn valid_name(n: &str) -> bool {
    let mut c = n.chars();
    c.next()
        .is_some_and(|f| f.is_ascii_alphabetic() || f == '_' || f == ':')
        && c.all(|x| x.is_ascii_alphanumeric() || x == '_' || x == ':')
}

/// Parse `{k="v",...}` with the format's escapes; returns the labels and the rest of the line.
fn parse_labels(s: &str) -> Result<(Labels, &str), String> {
    let mut labels = Vec::new();
    let b = s.as_bytes();
    let mut i = 1; // after '{'
    loop {
        if b.get(i) == Some(&b'}') {
            return Ok((labels, &s[i + 1..]));
        }
        let eq = s[i..].find('=').ok_or("label without '='")? + i;
        let key = &s[i..eq];
        if !valid_name(key) {
            return Err(format!("bad label name {key:?}"));
        }
        if b.get(eq + 1) != Some(&b'"') {
            return Err("label value not quoted".into());
        }
        let mut j = eq + 2;
        let mut val = String::new();
        loop {
            match b.get(j) {
                None => return Err("unterminated label value".into()),
                Some(b'"') => break,
                Some(b'\\') => {
                    match b.get(j + 1) {
                        Some(b'\\') => val.push('\\'),
                        Some(b'"') => val.push('"'),
                        Some(b'n') => val.push('\n'),
                        _ => return Err("bad escape in label value".into()),
                    }
                    j += 2;
                }
                Some(_) => {
                    let ch = s[j..].chars().next().unwrap();
                    val.push(ch);
                    j += ch.len_utf8();
                }
            }
        }
        labels.push((key.to_string(), val));
        i = j + 1;
        match b.get(i) {
            Some(b',') => i += 1,
            Some(b'}') => {}
            _ => return Err("expected ',' or '}' after a label".into()),
        }
    }
}

/// Parse exposition text 0.0.4; panics naming the line on anything invalid.
fn parse_exposition(text: &str) -> (Samples, HashMap<String, String>) {
    let helps: Vec<&str> = text
        .lines()
        .filter_map(|l| l.strip_prefix("# HELP ")?.split(' ').next())
        .collect();
    // Every metric declared in the registry (the daemon's and the link's) is served with its
    // HELP and TYPE: a counter as `name_total`, a set of families (VO, DTM) by its prefix. The
    // IMU bias restorer's families exist only while it runs (off here).
    let declared = DaemonMetrics::NAMES.iter().chain(LinkMetrics::NAMES);
    for name in declared.filter(|n| **n != "visnav_imu_bias") {
        let family = helps.iter().find(|h| {
            h.strip_prefix(name)
                .is_some_and(|rest| rest.is_empty() || rest.starts_with('_'))
        });
        let family = family.unwrap_or_else(|| panic!("{name}: no # HELP"));
        assert!(
            text.contains(&format!("\n# TYPE {family} ")),
            "{family}: no # TYPE"
        );
    }
    let mut samples = Samples::new();
    let mut types: HashMap<String, String> = HashMap::new();
    let mut helps = std::collections::HashSet::new();
    assert!(text.ends_with('\n'), "exposition must end with a line feed");
    for (n, line) in text.lines().enumerate() {
        let ctx = || format!("line {}: {line:?}", n + 1);
        assert!(!line.is_empty(), "{}: empty line", ctx());
        if let Some(rest) = line.strip_prefix("# HELP ") {
            let name = rest.split(' ').next().unwrap();
            assert!(valid_name(name), "{}", ctx());
            assert!(helps.insert(name.to_string()), "{}: HELP twice", ctx());
        } else if let Some(rest) = line.strip_prefix("# TYPE ") {
            let parts: Vec<&str> = rest.split(' ').collect();
            assert_eq!(parts.len(), 2, "{}", ctx());
            assert!(valid_name(parts[0]), "{}", ctx());
            assert!(
                ["counter", "gauge", "summary", "histogram", "untyped"].contains(&parts[1]),
                "{}",
                ctx()
            );
            assert!(
                types
                    .insert(parts[0].to_string(), parts[1].to_string())
                    .is_none(),
                "{}: TYPE twice",
                ctx()
            );
            if parts[1] == "counter" {
                assert!(parts[0].ends_with("_total"), "{}: counter name", ctx());
            }
        } else if line.starts_with('#') {
            // Other comments are allowed by the format.
        } else {
            let name_end = line.find(['{', ' ']).unwrap_or(line.len());
            let name = &line[..name_end];
            assert!(valid_name(name), "{}: metric name", ctx());
            let (mut labels, rest) = if line[name_end..].starts_with('{') {
                parse_labels(&line[name_end..]).unwrap_or_else(|e| panic!("{}: {e}", ctx()))
            } else {
                (Vec::new(), &line[name_end..])
            };
            let value = rest
                .strip_prefix(' ')
                .unwrap_or_else(|| panic!("{}: no value", ctx()));
            let v: f64 = match value {
                "NaN" => f64::NAN,
                "+Inf" => f64::INFINITY,
                "-Inf" => f64::NEG_INFINITY,
                v => v
                    .parse()
                    .unwrap_or_else(|_| panic!("{}: value {v:?}", ctx())),
            };
            let family = [
                name,
                name.trim_end_matches("_sum"),
                name.trim_end_matches("_count"),
                name.trim_end_matches("_bucket"),
            ]
            .into_iter()
            .find(|f| types.contains_key(*f))
            .unwrap_or_else(|| panic!("{}: sample before its # TYPE", ctx()));
            if family != name {
                assert!(
                    ["summary", "histogram"].contains(&types[family].as_str()),
                    "{}",
                    ctx()
                );
            }
            if name.ends_with("_bucket") {
                assert!(labels.iter().any(|(k, _)| k == "le"), "{}: no le", ctx());
            }
            labels.sort();
            assert!(
                samples.insert((name.to_string(), labels), v).is_none(),
                "{}: duplicate series",
                ctx()
            );
        }
    }
    (samples, types)
}

fn get(s: &Samples, name: &str, labels: &[(&str, &str)]) -> f64 {
    let mut l: Vec<(String, String)> = labels
        .iter()
        .map(|(k, v)| (k.to_string(), v.to_string()))
        .collect();
    l.sort();
    *s.get(&(name.to_string(), l))
        .unwrap_or_else(|| panic!("no sample {name}{labels:?}"))
}

fn scrape(addr: SocketAddr) -> (Samples, HashMap<String, String>) {
    let (status, headers, body) = http(addr, b"GET /metrics HTTP/1.1\r\nHost: visnav\r\n\r\n");
    assert_eq!(status, "HTTP/1.1 200 OK");
    assert!(
        headers.contains("Content-Type: text/plain; version=0.0.4"),
        "{headers}"
    );
    assert!(
        headers.contains(&format!("Content-Length: {}", body.len())),
        "{headers}"
    );
    parse_exposition(&body)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn daemon_serves_prometheus_metrics_over_tcp() {
    let port = free_udp_port();
    let mut ecfg = EmulatorConfig::new(&format!("udpout:127.0.0.1:{port}"));
    ecfg.gps_fix = true;
    let emu = AutopilotEmulator::start(ecfg, TRUTH).await.unwrap();
    let d = Daemon::start(setup(port, "127.0.0.1:0"), None)
        .await
        .unwrap();
    let addr = d.metrics_addr().expect("endpoint configured");
    assert!(addr.ip().is_loopback() && addr.port() != 0, "{addr}");

    let t0 = Instant::now();
    while d.nav_outputs().borrow().is_none() {
        assert!(
            t0.elapsed() < Duration::from_secs(15),
            "filter not initialised from the emulator's GPS"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    tokio::time::sleep(Duration::from_millis(500)).await;

    let (a, types) = tokio::task::spawn_blocking(move || scrape(addr))
        .await
        .unwrap();
    for name in [
        "visnav_build_info",
        "visnav_nav_health",
        "visnav_nav_health_changes_total",
        "visnav_nav_outputs_total",
        "visnav_imu_samples_total",
        "visnav_imu_timeouts_total",
        "visnav_frames_read_total",
        "visnav_frames_dropped_total",
        "visnav_fixes_attempted_total",
        "visnav_fixes_total",
        "visnav_fix_engine_rejections_total",
        "visnav_fix_latency_seconds",
        "visnav_fix_latency_last_seconds",
        "visnav_link_rx_packets_total",
        "visnav_link_tx_packets_total",
        "visnav_link_timesync_rtt_seconds",
        "visnav_link_autopilot_alive",
        "visnav_inject_sent_total",
    ] {
        assert!(types.contains_key(name), "family {name} missing");
    }
    assert_eq!(types["visnav_imu_samples_total"], "counter");
    assert_eq!(types["visnav_nav_health"], "gauge");
    assert_eq!(types["visnav_fix_latency_seconds"], "histogram");
    let health: Vec<(&str, f64)> = ["none", "ok", "degraded", "lost"]
        .into_iter()
        .map(|s| (s, get(&a, "visnav_nav_health", &[("state", s)])))
        .collect();
    assert_eq!(
        health.iter().map(|h| h.1).sum::<f64>(),
        1.0,
        "one-hot health {health:?}"
    );
    assert_eq!(
        get(&a, "visnav_nav_health", &[("state", "none")]),
        0.0,
        "the filter is initialised: {health:?}"
    );
    assert_eq!(get(&a, "visnav_link_autopilot_alive", &[]), 1.0);
    let rtt = get(&a, "visnav_link_timesync_rtt_seconds", &[]);
    assert!((0.0..1.0).contains(&rtt), "rtt {rtt} s");

    tokio::time::sleep(Duration::from_millis(1500)).await;
    let (b, _) = tokio::task::spawn_blocking(move || scrape(addr))
        .await
        .unwrap();
    let snap = d.metrics();
    for name in [
        "visnav_imu_samples_total",
        "visnav_nav_outputs_total",
        "visnav_link_rx_packets_total",
        "visnav_link_rx_autopilot_packets_total",
        "visnav_link_tx_packets_total",
        "visnav_inject_sent_total",
    ] {
        let (x, y) = (get(&a, name, &[]), get(&b, name, &[]));
        eprintln!("{name}: {x} -> {y}");
        assert!(y > x, "{name} did not grow: {x} -> {y}");
    }
    // Every counter is monotonic between the scrapes; the second scrape is not ahead of the
    // snapshot taken after it.
    for ((name, labels), x) in &a {
        if name.ends_with("_total") {
            let y = b[&(name.clone(), labels.clone())];
            assert!(y >= *x, "{name}{labels:?} went down: {x} -> {y}");
        }
    }
    assert!(get(&b, "visnav_imu_samples_total", &[]) <= snap.imu_samples as f64);

    // Bad requests over the same real socket.
    let bad = tokio::task::spawn_blocking(move || {
        [
            http(addr, b"GET / HTTP/1.1\r\n\r\n").0,
            http(addr, b"POST /metrics HTTP/1.1\r\nContent-Length: 0\r\n\r\n").0,
            http(addr, b"\x16\x03\x01\x02\x00garbage-tls-hello\r\n\r\n").0,
        ]
    })
    .await
    .unwrap();
    assert_eq!(
        bad,
        [
            "HTTP/1.1 404 Not Found",
            "HTTP/1.1 405 Method Not Allowed",
            "HTTP/1.1 400 Bad Request"
        ]
    );

    d.shutdown().await;
    emu.stop();
    assert!(
        TcpStream::connect_timeout(&addr, Duration::from_secs(1)).is_err(),
        "endpoint still listening after shutdown"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn taken_port_is_a_clear_startup_error() {
    let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = taken.local_addr().unwrap().to_string();
    let port = free_udp_port();
    let e = match Daemon::start(setup(port, &addr), None).await {
        Err(e) => e,
        Ok(_) => panic!("started on a taken port"),
    };
    assert!(matches!(e, DaemonError::Metrics { .. }), "{e:?}");
    let msg = e.to_string();
    assert!(
        msg.starts_with("daemon.metrics_listen: ") && msg.contains(&addr),
        "{msg}"
    );
}
