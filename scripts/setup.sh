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
# apt_install PACKAGES WITHOUT: install Debian packages when we may, else say what is missed.
apt_install() {
    if [ "$sudo_cmd" != none ] && command -v apt-get >/dev/null 2>&1; then
        echo "setup: installing $1" >&2
        $sudo_cmd env DEBIAN_FRONTEND=noninteractive apt-get update -qq >/dev/null 2>&1 || true
        # shellcheck disable=SC2086 # the package list splits at spaces
        $sudo_cmd env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $1 >/dev/null 2>&1 \
            || echo "setup: could not install $1 ($2)" >&2
    else
        echo "setup: $1 missing and no root/sudo ($2)" >&2
    fi
}
if ! command -v gst-launch-1.0 >/dev/null 2>&1; then
    apt_install "gstreamer1.0-tools gstreamer1.0-plugins-base gstreamer1.0-plugins-good" \
        "the GStreamer capture test will skip"
fi

# A Vulkan driver for the GPU SURF tests (crates/visnav-gpu): Mesa's lavapipe is a software Vulkan
# device, so the GPU path's equivalence with the CPU runs on any machine. A real GPU's
# driver serves as well. Under CI the GPU tests fail without an adapter; elsewhere they skip.
if ! ls /usr/share/vulkan/icd.d/*.json >/dev/null 2>&1 || ! ldconfig -p 2>/dev/null | grep 'libvulkan.so.1' >/dev/null; then
    apt_install "mesa-vulkan-drivers libvulkan1" "the GPU tests will skip, or fail under CI"
fi

echo "setup: ready (rustfmt, clippy$(command -v gst-launch-1.0 >/dev/null 2>&1 && echo ', GStreamer tools')$(ls /usr/share/vulkan/icd.d/*.json >/dev/null 2>&1 && echo ', a Vulkan driver'))" >&2
