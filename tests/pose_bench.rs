//! Prints the resection timings of `visnav::pose::bench` (the lead's `visnav bench` calls the same
//! functions). Timing is printed, never asserted. Run in release:
//! `cargo test --release --test integration pose_bench:: -- --ignored --nocapture`.
//!
//! On a loaded machine wall-clock percentiles include preemption; the on-CPU time of the thread
//! (Linux `/proc/thread-self/schedstat`, includes scene generation) is printed beside them.

fn thread_cpu_ns() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/thread-self/schedstat").ok()?;
    s.split_whitespace().next()?.parse().ok()
}

#[test]
#[ignore = "benchmark: run explicitly in release mode"]
fn print_resection_timings() {
    eprintln!(
        "lambda twist p3p: {:.3} us per call",
        visnav::pose::bench::bench_p3p(100_000, 1)
    );
    let trials = 50;
    for (n, r) in [(100, 0.5), (300, 0.5), (1000, 0.5), (300, 0.9)] {
        let t0 = std::time::Instant::now();
        let c0 = thread_cpu_ns();
        let res = visnav::pose::bench::bench_resection(n, r, trials, 1234);
        let wall_ms = t0.elapsed().as_secs_f64() * 1e3 / trials as f64;
        let cpu = match (c0, thread_cpu_ns()) {
            (Some(a), Some(b)) => format!("{:.3} ms", (b - a) as f64 / 1e6 / trials as f64),
            _ => "n/a".into(),
        };
        eprintln!("{res}  | per trial incl. scene generation: wall {wall_ms:.3} ms, on-CPU {cpu}");
    }
}

/// The resection bench runs and scores its trials.
#[test]
fn bench_helper_runs() {
    let r = visnav::pose::bench::bench_resection(100, 0.5, 4, 77);
    assert_eq!(r.trials, 4);
    assert_eq!(r.accepted, 4, "{r}");
    assert_eq!(r.accepted_beyond_3_sigma, 0, "{r}");
    assert!(
        r.median_ms.is_finite() && r.p95_ms >= r.median_ms && r.max_ms >= r.p95_ms,
        "{r}"
    );
}
