#!/usr/bin/env bash
# `t42 demo --quick` N times (default 8) while two busy loops load both cores; prints each run's
# outcome and the load average, then "passed K/N". Exit 0 only when every run passed.
set -uo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
RUNS="${1:-8}"
OUT="$(mktemp -d)"
bash "$ROOT/scripts/bootstrap.sh"
cd "$ROOT"
python3 -c "while True: pass" & hog1=$!
python3 -c "while True: pass" & hog2=$!
trap 'kill $hog1 $hog2 2>/dev/null; rm -rf "$OUT"' EXIT
passed=0
for i in $(seq 1 "$RUNS"); do
    if timeout 300 .venv/bin/t42 demo --quick --out "$OUT/runs" > "$OUT/run_$i.log" 2>&1; then
        passed=$((passed + 1))
        echo "run $i: ok ($(grep -o '[0-9]* s in all' "$OUT/run_$i.log")); load $(cut -d' ' -f1-3 /proc/loadavg)"
    else
        echo "run $i: FAILED; load $(cut -d' ' -f1-3 /proc/loadavg)"
        tail -n 8 "$OUT/run_$i.log"
    fi
done
echo "passed $passed/$RUNS"
[[ $passed -eq $RUNS ]]
