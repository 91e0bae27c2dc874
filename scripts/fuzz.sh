#!/usr/bin/env bash
# Builds the fuzz targets (fuzz/) and runs each for a bounded time from its committed corpus
# (fuzz/corpus/<target>/). Fails when any target crashes (a panic escaping the target, a timeout,
# running out of memory); prints one line per target. Run it before changing a parser and merge
# what it finds into the committed corpus (docs/operations.md, "Fuzzing"); CI replays that corpus
# through tests/fuzz_corpus.rs rather than building the fuzzers.
#
#   scripts/fuzz.sh [SECONDS] [TARGET...]     SECONDS per target (default 20), all targets by default
#
# The build is cargo-fuzz's without a sanitizer, on the stable toolchain: the same sancov
# instrumentation flags (stable -C options), libFuzzer from the libfuzzer-sys crate, debug
# assertions and overflow checks on. So it needs neither nightly nor `cargo install cargo-fuzz`.
# (With nightly and cargo-fuzz, `cargo +nightly fuzz run <target>` runs the same targets with
# AddressSanitizer; the code under test has no unsafe code besides the map's mmap.)
#
# The mutation seed is fixed (FUZZ_SEED, default 1), so a run explores the same inputs in the same
# order on every run and its verdict does not change from run to run; fuzz longer or with other
# seeds locally to find more (FUZZ_SEED=0: libFuzzer picks one).
# Environment: FUZZ_JOBS targets at a time (default: the number of CPUs), CARGO_BUILD_JOBS as
# for cargo, FUZZ_TOOLCHAIN (e.g. "+nightly"; default: the active toolchain),
# FUZZ_STRICT_PANICS=1 (a panic caught inside the code, e.g. the tiff crate's behind the GeoTIFF
# reader's guard, counts as a crash too).
# New inputs found go to fuzz/target/corpus-run/<target>/ (not committed); crashes to
# fuzz/artifacts/<target>/. To add inputs to the committed corpus:
#   fuzz/target/<triple>/release/<target> -merge=1 fuzz/corpus/<target> fuzz/target/corpus-run/<target>
set -euo pipefail
cd "$(dirname "$0")/.."
secs="${1:-20}"
shift || true
all=(config map_file geotiff frame mavlink)
targets=("$@")
[ ${#targets[@]} -gt 0 ] || targets=("${all[@]}")
jobs="${FUZZ_JOBS:-$(nproc 2>/dev/null || echo 1)}"
tc="${FUZZ_TOOLCHAIN:-}"

if ! command -v c++ >/dev/null 2>&1 && ! command -v clang++ >/dev/null 2>&1; then
    echo "SKIP fuzz: no C++ compiler to build libFuzzer (install g++ or clang)"
    exit 0
fi
triple="$(rustc $tc -vV | sed -n 's/^host: //p')"
start=$(date +%s)

# cargo-fuzz's flags (cargo-fuzz 0.13, `cargo fuzz build -s none`), codegen units left at the
# release default (16) for a shorter build. `--target` keeps build scripts uninstrumented.
export RUSTFLAGS="-Cpasses=sancov-module -Cllvm-args=-sanitizer-coverage-level=4 \
-Cllvm-args=-sanitizer-coverage-inline-8bit-counters -Cllvm-args=-sanitizer-coverage-pc-table \
-Cllvm-args=-sanitizer-coverage-trace-compares -Cllvm-args=-sanitizer-coverage-stack-depth \
-Cllvm-args=-simplifycfg-branch-fold-threshold=0 --cfg fuzzing -Cdebug-assertions"
unset CARGO_TARGET_DIR CARGO_BUILD_TARGET_DIR
cargo $tc build --locked --release --manifest-path fuzz/Cargo.toml --target "$triple" --bins \
    "${targets[@]/#/--bin=}"
built=$(date +%s)
echo "fuzz: built ${#targets[@]} targets in $((built - start)) s"

bin_dir="fuzz/target/$triple/release"
log_dir="fuzz/target/logs"
mkdir -p "$log_dir"
run_one() {
    local t="$1" run_corpus="fuzz/target/corpus-run/$1" art="fuzz/artifacts/$1/"
    mkdir -p "$run_corpus" "$art"
    # The first corpus directory receives new inputs, the committed one is only read.
    "$bin_dir/$t" "$run_corpus" "fuzz/corpus/$t" -max_total_time="$secs" -seed="${FUZZ_SEED:-1}" -timeout=20 \
        -rss_limit_mb=2048 -print_final_stats=1 -artifact_prefix="$art" \
        >"$log_dir/$t.log" 2>&1
}

status=0
report() {
    local t="$1" rc="$2" log="$log_dir/$1.log"
    local runs corp cov seeds
    runs=$(sed -n 's/^stat::number_of_executed_units: *//p' "$log" | tail -1)
    corp=$(grep -E '^#[0-9]+' "$log" | tail -1 | sed -n 's/.* corp: \([0-9]*\).*/\1/p')
    cov=$(grep -E '^#[0-9]+' "$log" | tail -1 | sed -n 's/.* cov: \([0-9]*\).*/\1/p')
    seeds=$(find "fuzz/corpus/$t" -type f | wc -l)
    if [ "$rc" = 0 ]; then
        echo "fuzz $t: ok, ${runs:-?} runs in ${secs} s, corpus ${corp:-?} (${seeds} committed), coverage ${cov:-?}"
    else
        status=1
        echo "fuzz $t: FAILED (exit $rc) after ${runs:-?} runs; the input is in fuzz/artifacts/$t/:"
        ls -1 "fuzz/artifacts/$t/" | sed 's/^/    /'
        grep -E 'panic|ERROR|SUMMARY|Test unit written|visnav-fuzz' "$log" | head -20 | sed 's/^/    /'
    fi
}

# Rounds of $jobs targets at a time.
i=0
while [ $i -lt ${#targets[@]} ]; do
    pids=()
    names=()
    for t in "${targets[@]:$i:$jobs}"; do
        run_one "$t" &
        pids+=($!)
        names+=("$t")
    done
    for k in "${!pids[@]}"; do
        rc=0
        wait "${pids[$k]}" || rc=$?
        report "${names[$k]}" "$rc"
    done
    i=$((i + jobs))
done
end=$(date +%s)
echo "fuzz: build $((built - start)) s, runs $((end - built)) s, total $((end - start)) s"
if [ $status != 0 ]; then
    echo "fuzz: crash(es) found; reproduce with tests/fuzz_corpus.rs after adding the input to fuzz/corpus/<target>/" >&2
fi
exit $status
