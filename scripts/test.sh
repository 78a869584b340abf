#!/usr/bin/env bash
# Run the test suite in the project virtualenv (created/refreshed first).
# Extra arguments go to pytest unchanged.  Without a -m of its own the fast
# suite runs (-m "not slow"); `scripts/test.sh -m slow` runs the long checks.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$ROOT/scripts/bootstrap.sh"
cd "$ROOT"

has_marker=0
for arg in "$@"; do
    case "$arg" in
        -m|-m?*|--markexpr|--markexpr=*) has_marker=1 ;;
    esac
done
if [[ $has_marker -eq 1 ]]; then
    exec "$ROOT/.venv/bin/python" -m pytest "$@"
else
    exec "$ROOT/.venv/bin/python" -m pytest -m "not slow" "$@"
fi
