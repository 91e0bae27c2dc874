#!/usr/bin/env bash
# Installs what visnav's build and tests need beyond the Rust toolchain. Idempotent.
# Python packages for the interop/benchmark scripts go into a venv under target/ (never the system).
set -euo pipefail
cd "$(dirname "$0")/.."
command -v cargo >/dev/null || { echo "setup: cargo not found: install Rust (rustup) first" >&2; exit 1; }
rustup component add rustfmt clippy >/dev/null 2>&1 || true

# GStreamer command-line tools for live capture (`[frames] source = "gstreamer"`) and its test.
# Installed with apt when missing and we may (root or passwordless sudo); otherwise the test that
# needs it skips with a printed reason.
if [ "$(id -u)" = 0 ]; then sudo_cmd=""; elif sudo -n true 2>/dev/null; then sudo_cmd="sudo -n"; else sudo_cmd="none"; fi
if ! command -v gst-launch-1.0 >/dev/null 2>&1; then
    pkgs="gstreamer1.0-tools gstreamer1.0-plugins-base gstreamer1.0-plugins-good"
    if [ "$sudo_cmd" != none ] && command -v apt-get >/dev/null 2>&1; then
        echo "setup: installing $pkgs" >&2
        $sudo_cmd env DEBIAN_FRONTEND=noninteractive apt-get update -qq >/dev/null 2>&1 || true
        $sudo_cmd env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $pkgs >/dev/null 2>&1 \
            || echo "setup: could not install $pkgs (the GStreamer capture test will skip)" >&2
    else
        echo "setup: gst-launch-1.0 missing and no root/sudo: the GStreamer capture test will skip" >&2
    fi
fi

# A Vulkan driver for the GPU SURF tests (crates/visnav-gpu): Mesa's lavapipe is a software Vulkan
# device, so the GPU path's equivalence with the CPU runs on any machine (issue 25). A real GPU's
# driver serves as well. Under CI the GPU tests fail without an adapter; elsewhere they skip.
if ! ls /usr/share/vulkan/icd.d/*.json >/dev/null 2>&1 || ! ldconfig -p 2>/dev/null | grep -q 'libvulkan.so.1'; then
    pkgs="mesa-vulkan-drivers libvulkan1"
    if [ "$sudo_cmd" != none ] && command -v apt-get >/dev/null 2>&1; then
        echo "setup: installing $pkgs" >&2
        $sudo_cmd env DEBIAN_FRONTEND=noninteractive apt-get update -qq >/dev/null 2>&1 || true
        $sudo_cmd env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $pkgs >/dev/null 2>&1 \
            || echo "setup: could not install $pkgs (the GPU tests will skip, or fail under CI)" >&2
    else
        echo "setup: no Vulkan driver and no root/sudo: the GPU tests will skip (fail under CI)" >&2
    fi
fi

echo "setup: ready (rustfmt, clippy$(command -v gst-launch-1.0 >/dev/null 2>&1 && echo ', GStreamer tools')$(ls /usr/share/vulkan/icd.d/*.json >/dev/null 2>&1 && echo ', a Vulkan driver'))" >&2
