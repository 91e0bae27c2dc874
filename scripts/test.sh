#!/usr/bin/env bash
# The project's test command (README): every unit and integration test.
# Tests that need ../shared/data skip with a printed reason when it is absent.
#
# With cargo-nextest installed (it is on the project's build machines) the tests run one process
# each, as many at a time as there are CPUs, to the end: `cargo test` runs the test binaries one
# after another, so a binary with one long simulation leaves the other cores idle (measured on
# 2 cores: 605 s with nextest against about 14 min). Otherwise, or with VISNAV_TEST_RUNNER=cargo,
# `cargo test`. Extra arguments go to the runner (a test-name filter works with both).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
if [ "${VISNAV_TEST_RUNNER:-}" != cargo ] && cargo nextest --version >/dev/null 2>&1; then
    cargo nextest run --locked --workspace --all-targets --no-fail-fast "$@"
else
    cargo test --locked --workspace --all-targets "$@"
fi
