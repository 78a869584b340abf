#!/usr/bin/env bash
# Run the test suite in the project virtualenv (created/refreshed first).
# Extra arguments go to pytest unchanged.  Without a -m of its own the fast
# suite runs (-m "not slow") in 4 pytest-xdist worker processes, one test file
# per worker at a time: most of its time is spent waiting on node processes and
# the ROS graph (one core busy of two when serial), so 4 workers on 2 cores
# overlap the waits (1.6 cores busy with 4 workers, 1.4 with 3).  6 workers took
# the batch from 226 s to 205 s on a quiet machine (2026-12-07), but on a fresh
# clone 3 timing checks of the emulated hand and the transfer server failed
# under their contention (each passes alone, and beside 3 CPU burners).  Tests marked
# `serial` (real-time checks a loaded machine can break: driver stalls, the
# quick demos) then run in one process on their own.  The batch hands out its
# files longest first, by the seconds of a measured batch (test/file_order.py,
# test/file_seconds.json; --no-loadscope-reorder keeps that order), so that no
# long file is left for the end while the other workers idle.  Give -n yourself to run
# everything in one batch (-n 0: one process).
# `scripts/test.sh -m slow` runs the long checks in one process: soak and
# timing checks there want the machine to themselves.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$ROOT/scripts/bootstrap.sh"
cd "$ROOT"
# pytest keeps its assertion-rewritten test modules as bytecode only where bytecode may be written: with
# PYTHONDONTWRITEBYTECODE set (as on these machines) every collection rewrote all ~190 test modules again,
# 9 of its 12.5 s, in each worker and in the serial batch.
unset PYTHONDONTWRITEBYTECODE

has_marker=0
has_workers=0
for arg in "$@"; do
    case "$arg" in
        -m|-m?*|--markexpr|--markexpr=*) has_marker=1 ;;
        -n|-n?*|--numprocesses|--numprocesses=*) has_workers=1 ;;
    esac
done
if [[ $has_marker -eq 1 ]]; then
    exec "$ROOT/.venv/bin/python" -m pytest "$@"
elif [[ $has_workers -eq 1 ]]; then
    exec "$ROOT/.venv/bin/python" -m pytest -m "not slow" "$@"
else
    # pytest exits 5 when a batch collects nothing (e.g. named files hold no serial test): not a failure.
    rc=0
    "$ROOT/.venv/bin/python" -m pytest -m "not slow and not serial" -n 4 --dist loadfile --no-loadscope-reorder "$@" || rc=$?
    rc_serial=0
    # With no arguments, only the files that mark a test serial are collected again (collecting all takes ~3 s).
    serial_files=()
    if [[ $# -eq 0 ]]; then mapfile -t serial_files < <(grep -l "mark\.serial" "$ROOT"/test/test_*.py); fi
    "$ROOT/.venv/bin/python" -m pytest -m "not slow and serial" "${serial_files[@]}" "$@" || rc_serial=$?
    if [[ $rc -eq 5 && $rc_serial -eq 5 ]]; then exit 5; fi
    for code in "$rc" "$rc_serial"; do
        if [[ $code -ne 0 && $code -ne 5 ]]; then exit "$code"; fi
    done
fi
