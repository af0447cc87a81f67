#!/usr/bin/env bash
# Host-scheduler measurements: runs sched_bench (a release build) and writes CSV tables, results.md
# and PNG plots (plots only when matplotlib is importable; never needed by the test suite).
# usage: bench/scripts/run_sched_bench.sh BUILD_DIR [OUT_DIR (default bench/results/sched)] [sched_bench args]
# About 7 minutes on 2 cores. Note: this machine has 2 cores; the 4- and 8-thread runs
# oversubscribe it (the tables and plots say so). Parts: `--only scaling,tiles,pbt,amphitheater,
# calibrate`; pbt = the PBT paper's Table 1 with the work / cpu / wall tile costs at batch 1024
# and 20 (about 10 minutes), calibrate = the work cost's coefficients (sched/tile_plan.cc). A
# partial run writes its meta_PARTS.txt and keeps the other parts' tables.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
build=${1:?usage: run_sched_bench.sh BUILD_DIR [OUT_DIR] [sched_bench args]}
out=${2:-$here/../results/sched}
shift $(( $# >= 2 ? 2 : 1 ))
ninja -C "$build" bench/sched/sched_bench
mkdir -p "$out"
"$build/bench/sched/sched_bench" --out "$out" "$@" | tee "$out/sched_bench.log"
py=
for candidate in python3 /usr/bin/python3; do
  if command -v "$candidate" >/dev/null && "$candidate" -c 'import matplotlib' 2>/dev/null; then
    py=$candidate; break
  fi
done
if [ -z "$py" ]; then
  echo "matplotlib not found: tables only (Debian: apt-get install python3-matplotlib)"
  py=python3
fi
"$py" "$here/sched_plot.py" "$out"
