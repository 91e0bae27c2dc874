#!/usr/bin/env bash
# The project's test command (README): every unit and integration test.
# Tests that need ../shared/data skip with a printed reason when it is absent.
#
# With cargo-nextest installed (it is on the project's build machines) the tests run one process
# each, as many at a time as there are CPUs, to the end (measured on 2 cores: 605 s against about
# 14 min with `cargo test`). Otherwise, or with VISNAV_TEST_RUNNER=cargo, `cargo test`; there the
# wall-clock flight of tests/first_run.rs runs after the others, alone, as .config/nextest.toml
# has nextest run it (the integration tests are one binary whose tests `cargo test` runs side by
# side). Extra arguments go to the runner (a test-name filter works with both).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
if [ "${VISNAV_TEST_RUNNER:-}" != cargo ] && cargo nextest --version >/dev/null 2>&1; then
    cargo nextest run --locked --workspace --all-targets --no-fail-fast "$@"
elif [ $# -gt 0 ]; then
    cargo test --locked --workspace --all-targets "$@"
else
    cargo test --locked --workspace --all-targets -- --skip first_run::
    cargo test --locked --test integration first_run::
fi
