#!/usr/bin/env bash
# Run the test suite in the project virtualenv (created/refreshed first).
# Extra arguments go to pytest unchanged.  Without a -m of its own the fast
# suite runs (-m "not slow") in 3 pytest-xdist worker processes, one test file
# per worker at a time: most of its time is spent waiting on node processes and
# the ROS graph (one core busy of two when serial), so 3 workers on 2 cores
# overlap the waits.  Give -n yourself to choose (-n 0: one process).
# `scripts/test.sh -m slow` runs the long checks in one process: soak and
# timing checks there want the machine to themselves.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$ROOT/scripts/bootstrap.sh"
cd "$ROOT"

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
    exec "$ROOT/.venv/bin/python" -m pytest -m "not slow" -n 3 --dist loadfile "$@"
fi
