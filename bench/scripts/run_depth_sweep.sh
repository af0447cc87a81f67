#!/usr/bin/env bash
# Run time against error (depth_sweep_bench): max depth 0..9 x weight cutoff {0, 1e-3, 1e-2, 5e-2}
# on spherebox and erw6, error vs a depth-16 cutoff-0 render. Writes depth_sweep.{csv,md} and,
# when matplotlib is importable, depth_sweep.png (never needed by the test suite).
# usage: bench/scripts/run_depth_sweep.sh BUILD_DIR [OUT_DIR (default bench/results/shade)] [bench args]
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
build=${1:?usage: run_depth_sweep.sh BUILD_DIR [OUT_DIR] [depth_sweep_bench args]}
out=${2:-$here/../results/shade}
shift $(( $# >= 2 ? 2 : 1 ))
ninja -C "$build" bench/render/depth_sweep_bench
mkdir -p "$out"
"$build/bench/render/depth_sweep_bench" --out "$out" "$@" | tee "$out/depth_sweep.log"
for py in python3 /usr/bin/python3; do
  if command -v "$py" >/dev/null && "$py" -c 'import matplotlib' 2>/dev/null; then
    exec "$py" "$here/plot_depth_sweep.py" "$out"
  fi
done
echo "matplotlib not found: tables only (Debian: apt-get install python3-matplotlib)"
