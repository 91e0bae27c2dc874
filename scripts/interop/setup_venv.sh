#!/usr/bin/env bash
# Creates (once) the Python venv used by the MAVLink interop test and the SITL recipes:
# target/pyenv with pymavlink (VISNAV_PYENV overrides; a relative path is taken from the
# repository root). With the argument `mavproxy` it also installs, once, MAVProxy into the same
# venv (requirements-mavproxy.txt, without its GUI dependencies); with `dask`, Dask distributed
# (requirements-dask.txt, for scripts/map_build_dask.py). Prints the venv python's
# absolute path on success, from any working directory. Exit 3 = python3/venv/pip unavailable
# (the test skips).
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
WANT_MAVPROXY=0
WANT_DASK=0
[ "${1:-}" = mavproxy ] && WANT_MAVPROXY=1
[ "${1:-}" = dask ] && WANT_DASK=1
# Tests run side by side (cargo-nextest): one creates or fills the venv, the others wait for it.
if command -v flock >/dev/null 2>&1; then
    mkdir -p "${VENV%/*}"
    exec 9>"$VENV.lock"
    flock 9
fi
has_mavproxy() {
    "$PY" -c "import MAVProxy, serial" >/dev/null 2>&1 && [ -f "$VENV/bin/mavproxy.py" ]
}
add_mavproxy() {
    if [ "$WANT_MAVPROXY" = 1 ] && ! has_mavproxy; then
        "$PY" -m pip install --quiet --disable-pip-version-check --no-deps \
            -r "$REPO/scripts/interop/requirements-mavproxy.txt" >&2 \
            || { echo "setup_venv: pip install MAVProxy failed" >&2; exit 3; }
        has_mavproxy || { echo "setup_venv: MAVProxy does not import" >&2; exit 3; }
    fi
    return 0
}
add_dask() {
    if [ "$WANT_DASK" = 1 ] && ! "$PY" -c "import dask.distributed" >/dev/null 2>&1; then
        "$PY" -m pip install --quiet --disable-pip-version-check \
            -r "$REPO/scripts/interop/requirements-dask.txt" >&2 \
            || { echo "setup_venv: pip install dask[distributed] failed" >&2; exit 3; }
        "$PY" -c "import dask.distributed" >&2 || { echo "setup_venv: dask.distributed does not import" >&2; exit 3; }
    fi
    return 0
}
if [ -x "$PY" ] && "$PY" -c "import pymavlink" >/dev/null 2>&1; then
    add_mavproxy
    add_dask
    echo "$PY"
    exit 0
fi
command -v python3 >/dev/null 2>&1 || { echo "setup_venv: python3 not found" >&2; exit 3; }
python3 -m venv "$VENV" >&2 || { echo "setup_venv: python3 -m venv failed" >&2; exit 3; }
"$PY" -m pip install --quiet --disable-pip-version-check "pymavlink>=2.4.40" >&2 \
    || { echo "setup_venv: pip install pymavlink failed" >&2; exit 3; }
"$PY" -c "import pymavlink" >&2 || { echo "setup_venv: pymavlink does not import" >&2; exit 3; }
add_mavproxy
add_dask
echo "$PY"
