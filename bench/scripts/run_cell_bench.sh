#!/usr/bin/env bash
# Runs the Cell simulator reproductions (bench/sim/cell_bench.cc) into bench/results/cell/ and plots
# them beside the paper's values (bench/scripts/plot_cell.py, needs python3 with matplotlib).
#   bench/scripts/run_cell_bench.sh BUILD_DIR [--full] [--only loads,speedup,...]
set -euo pipefail
build=${1:?usage: run_cell_bench.sh BUILD_DIR [cell_bench options]}
shift
src=$(cd "$(dirname "$0")/../.." && pwd)
out="$src/bench/results/cell"
"$build/bench/sim/cell_bench" --out "$out" "$@"
python=python3
if ! "$python" -c 'import matplotlib' 2>/dev/null; then python=/usr/bin/python3; fi
if ! "$python" -c 'import matplotlib' 2>/dev/null; then
  echo "run_cell_bench.sh: the plots need matplotlib (apt-get install python3-matplotlib)" >&2
  exit 1
fi
"$python" "$src/bench/scripts/plot_cell.py" "$out"
