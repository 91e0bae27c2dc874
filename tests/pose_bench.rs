//! Prints the resection timings of `visnav::pose::bench` (the lead's `visnav bench` calls the same
//! functions). Timing is printed, never asserted. Run in release:
//! `cargo test --release --test pose_bench -- --ignored --nocapture`.

#[test]
#[ignore = "benchmark: run explicitly in release mode"]
fn print_resection_timings() {
    eprintln!(
        "lambda twist p3p: {:.3} us per call",
        visnav::pose::bench::bench_p3p(100_000, 1)
    );
    for r in visnav::pose::bench::bench_suite(50) {
        eprintln!("{r}");
    }
}
