#!/usr/bin/env bash
# Cluster backend benchmark (sched/mpi_backend.h): frames per second, worker imbalance, messages
# and bytes, PBT prediction accuracy (the paper's Table 1) per worker count and tiling, over the
# scene's camera walk-through; one CSV row per frame, then summary.md and a plot (plot_mpi.py).
# Ranks share this machine's cores, so times measure the protocol and the balance, not a
# cluster's speed-up: beyond 2 workers the 2 cores are oversubscribed (the outputs say so).
# usage: mpi_bench.sh RAYSTREAM MPIRUN OUT_DIR [--quick]
#   env: MPI_BENCH_SCENE (erw6), MPI_BENCH_SIZE (256), MPI_BENCH_FRAMES (20),
#        MPI_BENCH_RANKS ("2 3 4 5 6 7 8 9": 1 to 8 workers, rank 0 is the master),
#        MPI_BENCH_EXTRA_RANKS ("3 5 9": PBT-Greedy, PBT-Visit and the 2x camera also run here),
#        MPI_BENCH_PBT_TIME (cpu: tile time fed to PBT-Update, see below),
#        MPI_BENCH_BINARY_NOTE (how RAYSTREAM was built, e.g. its commit and buildtype: meta.txt)
# Full sweep: 52 runs; 256x256 and 20 frames (a third of erw6's 60-frame path, two thirds at 2x
# speed) keep it at 4-15 minutes on the shared 2-core machine, depending on the other jobs' load
# (the paper used 512x512: 4x the work per frame).
#
# Configurations, for k = 1 and k = 4 tiles per worker (m = k * n tiles for n workers):
#   static  --pbt k --assign static: the initial equal-area PBT tiles, never updated, the same
#           random assignment every frame (the paper's "static random assignment")
#   pbt     --pbt k --assign random: PBT-Update between frames, PBT-Random assignment
#   greedy, visit (extra ranks): the locality-aware assignments; speed 2 (extra ranks): PBT-Random
#   with the camera moving twice as fast (the paper's 2x column); wall (3 ranks only): PBT fed
#   with wall-clock tile times where 2 workers have the 2 cores to themselves.
# Both the static and the PBT runs are demand-driven (a worker whose list is empty takes a
# waiting tile of the most loaded worker), so with k = 1 the tiling alone decides the balance.
# PBT is fed each tile's worker CPU time (--pbt-time cpu): with up to 9 ranks on 2 cores a tile's
# wall time mostly measures how often its rank was descheduled, which no tiling can predict.
# Ranks are not bound to cores (--bind-to none), so every rank count runs under the same rules.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
rs=$1 mpirun=$2 out=$3 quick=${4:-}
export OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1
export OMPI_MCA_btl=self,vader OMPI_MCA_btl_vader_single_copy_mechanism=none
scene=${MPI_BENCH_SCENE:-erw6} size=${MPI_BENCH_SIZE:-256} frames=${MPI_BENCH_FRAMES:-20}
pbt_time=${MPI_BENCH_PBT_TIME:-cpu}
read -r -a ranks <<<"${MPI_BENCH_RANKS:-2 3 4 5 6 7 8 9}"
read -r -a extra <<<"${MPI_BENCH_EXTRA_RANKS:-3 5 9}"
if [ "$quick" = --quick ]; then
  scene=${MPI_BENCH_SCENE:-cornell} size=128 frames=4 ranks=(3) extra=()
fi
mkdir -p "$out"
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
csv="$out/mpi_bench.csv"
echo "scene,size,frames,ranks,workers,config,k,assign,speed,pbt_time,load1,frame,seconds,fps,\
imbalance_wall,imbalance_cpu,worker_cpu_max,worker_cpu_sum,tiles,steals,messages,bytes,rays,\
idle_fraction,\
predicted_tiles,within5,within10,within15" >"$csv"
t_start=$SECONDS
load_start=$(cut -d' ' -f1 /proc/loadavg)
runs=0

# run NP CONFIG K ASSIGN SPEED PBT_TIME: one walk-through under mpirun, frames appended to the CSV.
run() {
  local np=$1 config=$2 k=$3 assign=$4 speed=$5 ptime=$6
  local json="$tmp/np${np}_${config}_k${k}.json" t0=$SECONDS
  local load1; load1=$(cut -d' ' -f1 /proc/loadavg)  # the machine's load when the run starts
  "$mpirun" --allow-run-as-root --oversubscribe --bind-to none -np "$np" "$rs" render \
    --backend mpi --scene "$scene" --width "$size" --height "$size" --frames "$frames" \
    --speed "$speed" --pbt "$k" --assign "$assign" --pbt-time "$ptime" -q \
    --out "$tmp/last.png" --stats "$json"
  python3 - "$json" "$scene" "$size" "$frames" "$np" "$config" "$k" "$assign" "$speed" \
    "$ptime" "$load1" >>"$csv" <<'PY'
import json, sys
# The host backends' statistics format (sched/backends.h WriteHostStats): one "threads" entry
# per worker, the cluster's fields (messages, bytes, options workers) on top.
d = json.load(open(sys.argv[1]))
head = sys.argv[2:5] + [sys.argv[5], str(d["options"]["workers"])] + sys.argv[6:12]
def imbalance(times):
    mean = sum(times) / len(times)
    return max(times) / mean if mean > 0 else 1.0
for f in d["frames"]:
    ws = f["threads"]
    idle = sum(w["idle_seconds"] for w in ws) / (len(ws) * f["render_seconds"])
    pbt = f.get("pbt", {})  # absent without --pbt
    acc = pbt if pbt.get("has_prediction") else None
    pred = sum(1 for t in f["tiles"] if t["predicted_seconds"] >= 0) if acc else ""
    row = head + [f["frame"], f["seconds"], f["fps"], f["imbalance"],
                  imbalance([w["cpu_seconds"] for w in ws]),
                  max(w["cpu_seconds"] for w in ws), sum(w["cpu_seconds"] for w in ws),
                  len(f["tiles"]),
                  sum(w["steals"] for w in ws), f["messages"], f["bytes"],
                  sum(f["rays"].values()), idle, pred]
    row += [acc[k] for k in ("within5", "within10", "within15")] if acc else ["", "", ""]
    print(",".join(str(x) for x in row))
PY
  runs=$((runs + 1))
  echo "np=$np ($((np - 1)) workers) $config k=$k speed $speed: $((SECONDS - t0)) s" >&2
}

in_list() { local x=$1; shift; for y in "$@"; do [ "$x" = "$y" ] && return 0; done; return 1; }

if [ "$quick" = --quick ]; then
  run 3 static 2 static 1 "$pbt_time"
  run 3 pbt 2 random 1 "$pbt_time"
  run 3 greedy 2 greedy 1 "$pbt_time"
else
  for np in "${ranks[@]}"; do
    for k in 1 4; do
      run "$np" static "$k" static 1 "$pbt_time"
      run "$np" pbt "$k" random 1 "$pbt_time"
      if in_list "$np" "${extra[@]}"; then
        run "$np" greedy "$k" greedy 1 "$pbt_time"
        run "$np" visit "$k" visit 1 "$pbt_time"
        run "$np" pbt_x2 "$k" random 2 "$pbt_time"
      fi
      if [ "$np" = 3 ]; then run "$np" pbt_wall "$k" random 1 wall; fi
    done
  done
fi

# Run conditions for summary.md.
{
  echo "command: bench/scripts/mpi_bench.sh $rs $mpirun $out $quick"
  echo "scene=$scene size=${size}x$size frames=$frames pbt_time=$pbt_time runs=$runs"
  echo "ranks=$(IFS=,; echo "${ranks[*]}") extra_ranks=$(IFS=,; echo "${extra[*]:-}")"
  echo "cores=$(nproc) load_start=$load_start load_end=$(cut -d' ' -f1 /proc/loadavg)"
  echo "wall_seconds=$((SECONDS - t_start))"
  echo "host=$(uname -n) date=$(date -u +%Y-%m-%dT%H:%MZ)"
  echo "binary: ${MPI_BENCH_BINARY_NOTE:-$rs}"
} >"$out/meta.txt"

# Summary (always) and plot (when matplotlib is importable).
py=python3 plot=--no-plot
for candidate in python3 /usr/bin/python3; do
  if command -v "$candidate" >/dev/null && "$candidate" -c 'import matplotlib' 2>/dev/null; then
    py=$candidate plot=--plot; break
  fi
done
if [ $plot = --no-plot ]; then
  echo "matplotlib not found: summary only (Debian: apt-get install python3-matplotlib)" >&2
fi
"$py" "$here/plot_mpi.py" "$out" "$plot"
cat "$out/summary.md"
echo "wrote $csv, $out/summary.md$([ $plot = --plot ] && echo ", $out/mpi.png")" >&2
