#!/usr/bin/env bash
# Create/refresh the project virtualenv (.venv at the repository root).
#
# Idempotent: the pip work is skipped when .venv/.t42-installed holds the
# sha256 of what decides the install (requirements files, setup.py, setup.cfg,
# the top-level Python packages: the editable finder maps each one) and the
# interpreter version.  Set T42_BOOTSTRAP_FORCE=1
# to redo it anyway, PYTHON=/path/to/python3 to pick the interpreter.
#
# Then the interface package t42_interfaces is built and installed into the
# venv by interfaces/build.sh (its own stamp: a no-op when up to date).  It
# goes into the venv's prefix, beside the ros-jazzy-* wheels, so it is found
# the way they are with no environment variable: Python imports it from
# site-packages, and the wheels' ros_wheels_bootstrapper.pth starts every
# Python of the venv with <venv>/lib on LD_LIBRARY_PATH, where its C type
# support libraries are (rosidl looks them up by name there; an RPATH would
# not be enough); rclpy needs no AMENT_PREFIX_PATH for it.  Without cmake, a
# C++ compiler or the Python headers the bootstrap stops with one line naming
# the Debian packages (the suite's nodes import the package).
# interfaces/build.sh says more (the wheels' two snags).
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="$ROOT/.venv"
STAMP="$VENV/.t42-installed"
LOG="$VENV/.t42-bootstrap.log"
PYTHON="${PYTHON:-python3}"
TORCH_PIN="torch==2.13.0"

die() { echo "bootstrap: error: $*" >&2; exit 1; }

cd "$ROOT"
for f in requirements.txt requirements-test.txt setup.py setup.cfg; do
    [[ -f "$f" ]] || die "missing $ROOT/$f"
done

if [[ ! -x "$VENV/bin/python" ]]; then
    command -v "$PYTHON" >/dev/null 2>&1 || die "'$PYTHON' not found (set PYTHON=/path/to/python3)"
    echo "bootstrap: creating $VENV with $("$PYTHON" -V 2>&1)" >&2
    "$PYTHON" -m venv "$VENV" || die "could not create the virtualenv $VENV"
fi
VPY="$VENV/bin/python"

stamp_value() {
    {
        "$VPY" -c 'import sys; print(sys.version)'
        cat requirements.txt requirements-test.txt setup.py setup.cfg
        ls -d -- */__init__.py 2>/dev/null || true
    } | sha256sum | cut -d' ' -f1
}

# Serialise concurrent bootstraps (several test runs may start at once).
if command -v flock >/dev/null 2>&1; then
    exec 9>"$VENV/.t42-bootstrap.lock"
    flock 9
fi

build_interfaces() {
    local rc=0
    bash "$ROOT/interfaces/build.sh" "$VENV" || rc=$?
    case $rc in
        0) ;;
        3) die "t42_interfaces cannot be built here (the line above names what to install); its nodes need it" ;;
        *) die "building t42_interfaces failed (see above)" ;;
    esac
}

want="$(stamp_value)"
if [[ "${T42_BOOTSTRAP_FORCE:-0}" != "1" && -f "$STAMP" && "$(cat "$STAMP")" == "$want" ]]; then
    build_interfaces
    exit 0
fi

rm -f "$STAMP"
: >"$LOG"
run_pip() {
    local what="$1"; shift
    if ! "$VPY" -m pip install --disable-pip-version-check -q "$@" >>"$LOG" 2>&1; then
        echo "bootstrap: error: pip failed while installing $what; last lines of $LOG:" >&2
        # (skip pip's notes about index locations missing on this machine)
        grep -v "is ignored: it is neither a file nor a directory" "$LOG" | tail -n 25 >&2
        exit 1
    fi
}

echo "bootstrap: installing pinned dependencies into $VENV (log: $LOG)" >&2
# torch first: it resolves to the local CPU build here, and installing it
# before anything else keeps another package from dragging in a CUDA build.
run_pip "$TORCH_PIN" "$TORCH_PIN"
# The torch pin is repeated as a constraint so nothing below can replace it.
run_pip "the pinned requirements" -c <(echo "$TORCH_PIN") \
    -r requirements.txt -r requirements-test.txt
# The package itself, editable, without touching the pinned dependencies.
# PEP 517 editable install (no build isolation: use the venv's setuptools)
# puts the console scripts into .venv/bin, unlike `setup.py develop`, which
# would honour setup.cfg's ROS layout (lib/t42_transfer).
run_pip "the t42_transfer package (editable)" --no-deps --no-build-isolation \
    --use-pep517 -e .

[[ -x "$VENV/bin/t42" ]] || die "the editable install did not create $VENV/bin/t42"
"$VPY" -c 'import torch, t42_transfer' >>"$LOG" 2>&1 \
    || die "the venv cannot import torch and t42_transfer (see $LOG)"
echo "$want" >"$STAMP"
build_interfaces
echo "bootstrap: done" >&2
