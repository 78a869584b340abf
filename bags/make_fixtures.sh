#!/usr/bin/env bash
# Regenerate the fixture bags with the project's own collector (run from the repo root).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
rm -rf bags/source_small bags/target_small
.venv/bin/t42 sim collect --hand source --episodes 6 --steps 100 --seed 100 --workers 1 --quiet --out bags/source_small
.venv/bin/t42 sim collect --hand target --episodes 4 --steps 100 --seed 101 --workers 1 --quiet --out bags/target_small
