#!/usr/bin/env bash
# Installs what visnav's build and tests need beyond the Rust toolchain. Idempotent.
# Python packages for the interop/benchmark scripts go into a venv under target/ (never the system).
set -euo pipefail
cd "$(dirname "$0")/.."
command -v cargo >/dev/null || { echo "setup: cargo not found: install Rust (rustup) first" >&2; exit 1; }
rustup component add rustfmt clippy >/dev/null 2>&1 || true
