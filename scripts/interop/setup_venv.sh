#!/usr/bin/env bash
# Creates (once) the Python venv used by the MAVLink interop test: target/pyenv with pymavlink.
# Prints the venv's python path on success. Exit 3 = python3/venv/pip unavailable (the test skips).
set -euo pipefail
cd "$(dirname "$0")/../.."
VENV="${VISNAV_PYENV:-target/pyenv}"
PY="$VENV/bin/python"
if [ -x "$PY" ] && "$PY" -c "import pymavlink" >/dev/null 2>&1; then
    echo "$PY"
    exit 0
fi
command -v python3 >/dev/null 2>&1 || { echo "setup_venv: python3 not found" >&2; exit 3; }
python3 -m venv "$VENV" >&2 || { echo "setup_venv: python3 -m venv failed" >&2; exit 3; }
"$PY" -m pip install --quiet --disable-pip-version-check "pymavlink>=2.4.40" >&2 \
    || { echo "setup_venv: pip install pymavlink failed" >&2; exit 3; }
"$PY" -c "import pymavlink" >&2 || { echo "setup_venv: pymavlink does not import" >&2; exit 3; }
echo "$PY"
