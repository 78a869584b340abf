#!/usr/bin/env bash
# Run the end-to-end demo (`t42 demo`) in the project virtualenv.
# Arguments go to `t42 demo` unchanged.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$ROOT/scripts/bootstrap.sh"
cd "$ROOT"
exec "$ROOT/.venv/bin/t42" demo "$@"
