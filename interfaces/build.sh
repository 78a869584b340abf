#!/usr/bin/env bash
# Build the interface package t42_interfaces (interfaces/t42_interfaces) with plain cmake against the
# ROS 2 Jazzy wheels of a virtualenv, and install it INTO that virtualenv's prefix.
#
#   interfaces/build.sh [VENV]        (default: <repository>/.venv; scripts/bootstrap.sh runs it)
#
# Exit status: 0 built (or already up to date), 3 a build tool is missing (one line on stderr names the
# Debian packages; the suite's nodes cannot run without the package), 1 failed (the log's last lines on stderr).
#
# Why the venv's prefix: the ros-jazzy-* wheels install their C libraries into <venv>/lib, their Python
# packages into site-packages and their ament index into <venv>/share, and the wheels' own
# ros_wheels_bootstrapper.pth re-executes every Python start of the venv with <venv>/lib on LD_LIBRARY_PATH.
# Installed beside them, t42_interfaces is found the same way with no variable set by anyone: Python imports it
# from site-packages; the typesupport libraries, which rosidl_typesupport_c looks up by name on
# LD_LIBRARY_PATH (an RPATH would not do), come from <venv>/lib; rclpy needs no AMENT_PREFIX_PATH for it
# (serialisation, publishers and actions look type support up through the Python module), and a tool that
# reads the ament index (ros2 interface, ament_index_python) finds it under <venv>/share with the wheels'
# packages once AMENT_PREFIX_PATH names the venv.
# The build directory is <repository>/build/interfaces (git-ignored); what was installed is listed in
# <venv>/.t42-interfaces-manifest.txt and removed before the next install (a deleted .msg leaves nothing).
#
# Two snags of the wheels, fixed here (idempotent, no root needed):
# * their exported CMake files (<venv>/share/*/cmake/*.cmake) name the wheel builder's
#   /opt/python/cp3XX-cp3XX/include/python3.X and .../site-packages/numpy/_core/include as include
#   directories: the generate step fails ("includes non-existent path") until they name this interpreter's
#   include directory and numpy.get_include();
# * catkin_pkg (colcon) refuses a maintainer email like a@b.c: package.xml uses maintainer@example.com.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="$(cd "${1:-$ROOT/.venv}" && pwd)"
VPY="$VENV/bin/python"
PKG_DIR="$ROOT/interfaces/t42_interfaces"
BUILD="$ROOT/build/interfaces"
STAMP="$VENV/.t42-interfaces-installed"
MANIFEST="$VENV/.t42-interfaces-manifest.txt"
LOG="$VENV/.t42-interfaces-build.log"

# Exit 3: a build tool is missing.  The suite's nodes need t42_interfaces, so that is an error (the bootstrap stops).
missing_tool() { echo "interfaces: error: $* (the suite's nodes need t42_interfaces)" >&2; exit 3; }
fail() {
    echo "interfaces: error: $*; last lines of $LOG:" >&2
    tail -n 25 "$LOG" >&2 || true
    exit 1
}

[[ -x "$VPY" ]] || { echo "interfaces: error: no virtualenv at $VENV (run scripts/bootstrap.sh)" >&2; exit 1; }

stamp_value() {
    {
        "$VPY" -c 'import sys; print(sys.version, sys.prefix)'
        cat "${BASH_SOURCE[0]}"
        find "$PKG_DIR" -type f | LC_ALL=C sort | while read -r f; do echo "$f"; cat "$f"; done
    } | sha256sum | cut -d' ' -f1
}

# One build at a time per venv (bootstrap and tests may start together).
if command -v flock >/dev/null 2>&1; then
    exec 8>"$VENV/.t42-interfaces.lock"
    flock 8
fi

want="$(stamp_value)"
if [[ "${T42_BOOTSTRAP_FORCE:-0}" != "1" && -f "$STAMP" && "$(cat "$STAMP")" == "$want" ]]; then
    exit 0
fi
# Up to date needs no build tools; a build does.
missing=()
command -v cmake >/dev/null 2>&1 || missing+=(cmake)
if ! command -v c++ >/dev/null 2>&1 && ! command -v g++ >/dev/null 2>&1; then missing+=(g++); fi
if ! command -v make >/dev/null 2>&1 && ! command -v ninja >/dev/null 2>&1; then missing+=(make); fi
if ((${#missing[@]})); then
    missing_tool "no ${missing[*]}: install them (Debian: sudo apt-get install cmake g++ make) and rerun scripts/bootstrap.sh"
fi
PY_INCLUDE="$("$VPY" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')"
if [[ ! -f "$PY_INCLUDE/Python.h" ]]; then
    missing_tool "no Python.h in $PY_INCLUDE: install the interpreter's headers (Debian: sudo apt-get install python3-dev)"
fi

rm -f "$STAMP"
: >"$LOG"
started=$SECONDS
echo "interfaces: building t42_interfaces into $VENV (log: $LOG)" >&2

# Snag 1: the wheels' exported include directories (see the top).
"$VPY" - >>"$LOG" 2>&1 <<'EOF' || fail "could not rewrite the wheels' CMake include paths"
import glob, re, sys, sysconfig
import numpy
include, numpy_include = sysconfig.get_paths()["include"], numpy.get_include()
fixed = 0
for path in glob.glob(f"{sys.prefix}/share/*/cmake/*.cmake"):
    with open(path) as f:
        text = f.read()
    if "/opt/python/" not in text:
        continue
    new = re.sub(r"/opt/python/[^;\"]*?/site-packages/numpy/_core/include", numpy_include, text)
    new = re.sub(r"/opt/python/[^;\"/]+/include/python3\.\d+", include, new)
    if "/opt/python/" in new:
        sys.exit(f"unexpected /opt/python path left in {path}")
    with open(path, "w") as f:
        f.write(new)
    fixed += 1
print(f"rewrote the include paths of {fixed} exported CMake files")
EOF

# A build directory configured for another source tree (a copied checkout) or another venv (its cache names
# that venv's packages) is started afresh.
if [[ -f "$BUILD/CMakeCache.txt" ]] && ! { grep -qxF "CMAKE_HOME_DIRECTORY:INTERNAL=$PKG_DIR" "$BUILD/CMakeCache.txt" \
        && grep -qxF "CMAKE_INSTALL_PREFIX:PATH=$VENV" "$BUILD/CMakeCache.txt"; }; then
    rm -rf "$BUILD"
fi
mkdir -p "$BUILD"
touch "$BUILD/COLCON_IGNORE"  # not a package of a colcon workspace rooted above it

export CMAKE_PREFIX_PATH="$VENV${CMAKE_PREFIX_PATH:+:$CMAKE_PREFIX_PATH}"
export AMENT_PREFIX_PATH="$VENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
export PATH="$VENV/bin:$PATH"
cmake -S "$PKG_DIR" -B "$BUILD" -DCMAKE_INSTALL_PREFIX="$VENV" -DPython3_EXECUTABLE="$VPY" \
    -DCMAKE_BUILD_TYPE=Release -DBUILD_TESTING=OFF >>"$LOG" 2>&1 || fail "cmake could not configure t42_interfaces"
cmake --build "$BUILD" --parallel "$(nproc 2>/dev/null || echo 2)" >>"$LOG" 2>&1 || fail "t42_interfaces did not build"

# Remove what the previous install put into the venv, then install.
if [[ -f "$MANIFEST" ]]; then
    while IFS= read -r f; do
        [[ "$f" == "$VENV"/* ]] && rm -f -- "$f"
    done <"$MANIFEST"
fi
cmake --install "$BUILD" >>"$LOG" 2>&1 || fail "could not install t42_interfaces into $VENV"
cp "$BUILD/install_manifest.txt" "$MANIFEST"

# The check that matters: a fresh interpreter of the venv, with none of this script's variables, imports it.
env -u PYTHONPATH -u LD_LIBRARY_PATH -u AMENT_PREFIX_PATH -u CMAKE_PREFIX_PATH -u _ROS_WHEELS_BOOTSTRAP_COMPLETE \
    "$VPY" -c 'from t42_interfaces.action import Reach, Transfer
from t42_interfaces.msg import BagClosed, ModelUpdated, PlanResult
from rclpy.serialization import deserialize_message, serialize_message
assert deserialize_message(serialize_message(PlanResult(status="ok")), PlanResult).status == "ok"' \
    >>"$LOG" 2>&1 || fail "the venv's python cannot use the installed t42_interfaces"
echo "$want" >"$STAMP"
echo "interfaces: t42_interfaces installed in $((SECONDS - started)) s" >&2
