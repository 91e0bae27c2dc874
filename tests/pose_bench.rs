//! Prints the resection timings of `visnav::pose::bench` (the lead's `visnav bench` calls the same
//! function). Timing is printed, never asserted. Run in release:
//! `cargo test --release --test pose_bench -- --ignored --nocapture`.

#[test]
#[ignore = "benchmark: run explicitly in release mode"]
fn print_resection_timings() {
    for r in visnav::pose::bench::bench_suite(50) {
        eprintln!("{r}");
    }
}
