#!/usr/bin/env bash
# Creates (once) the Python venv used by the MAVLink interop test and the SITL recipes:
# target/pyenv with pymavlink (VISNAV_PYENV overrides; a relative path is taken from the
# repository root). Prints the venv python's absolute path on success, from any working
# directory. Exit 3 = python3/venv/pip unavailable (the test skips).
set -euo pipefail
SRC="${BASH_SOURCE[0]}"
case "$SRC" in
    */*) HERE="${SRC%/*}" ;;
    *) HERE=. ;;
esac
REPO="$(cd "$HERE/../.." && pwd -P)"
cd "$REPO"
VENV="${VISNAV_PYENV:-target/pyenv}"
case "$VENV" in
    /*) ;;
    *) VENV="$REPO/$VENV" ;;
esac
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
