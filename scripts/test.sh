#!/usr/bin/env bash
# The project's test command (README): every unit and integration test.
# Tests that need ../shared/data skip with a printed reason when it is absent.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
cargo test --locked --workspace --all-targets "$@"
