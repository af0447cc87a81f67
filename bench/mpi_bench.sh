#!/usr/bin/env bash
# Cluster backend benchmark (sched/mpi_backend.h): frame time, worker imbalance, messages and
# bytes, PBT prediction accuracy (the paper's Table 1) per rank count and tiling, over a
# walk-through; one CSV row per frame. Ranks share this machine's cores, so times measure the
# protocol and the balance, not a cluster's speed-up.
# usage: mpi_bench.sh RAYSTREAM MPIRUN OUT_DIR [--quick]
#   env: MPI_BENCH_SCENE (default amphitheater:1), MPI_BENCH_SIZE (512), MPI_BENCH_FRAMES (16),
#        MPI_BENCH_RANKS ("2 3 5 9")
set -euo pipefail
rs=$1 mpirun=$2 out=$3 quick=${4:-}
export OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1
export OMPI_MCA_btl=self,vader OMPI_MCA_btl_vader_single_copy_mechanism=none
scene=${MPI_BENCH_SCENE:-amphitheater:1} size=${MPI_BENCH_SIZE:-512} frames=${MPI_BENCH_FRAMES:-16}
read -r -a ranks <<<"${MPI_BENCH_RANKS:-2 3 5 9}"
tilings=("--tile 32x32" "--pbt 1 --assign static" "--pbt 1 --assign random" "--pbt 4 --assign random"
         "--pbt 4 --assign greedy" "--pbt 4 --assign visit")
if [ "$quick" = --quick ]; then
  scene=${MPI_BENCH_SCENE:-cornell} size=128 frames=4 ranks=(3) tilings=("--tile 32x32" "--pbt 2 --assign greedy")
fi
mkdir -p "$out"
csv="$out/mpi_bench.csv"
echo "scene,size,ranks,tiling,frame,seconds,imbalance,tiles,messages,bytes,rays,within10" >"$csv"
for np in "${ranks[@]}"; do
  for tiling in "${tilings[@]}"; do
    json="$out/stats_np${np}_$(echo "$tiling" | tr -c 'a-z0-9' '_').json"
    # shellcheck disable=SC2086
    "$mpirun" --allow-run-as-root --oversubscribe -np "$np" "$rs" render --backend mpi \
      --scene "$scene" --width "$size" --height "$size" --frames "$frames" $tiling -q \
      --out "$out/last.png" --stats "$json"
    python3 - "$json" "$scene" "$size" "$np" "$tiling" >>"$csv" <<'PY'
import json, sys
d = json.load(open(sys.argv[1]))
for f in d["frames"]:
    acc = f.get("accuracy", {}).get("within10", "")
    print(",".join(str(x) for x in [sys.argv[2], sys.argv[3], sys.argv[4], sys.argv[5], f["frame"],
          f["seconds"], f["imbalance"], f["tiles_count"], f["messages"], f["bytes"], f["rays"], acc]))
PY
    echo "np=$np $tiling: done" >&2
  done
done
# Summary: mean frame time and imbalance per configuration (frames after the first).
python3 - "$csv" <<'PY'
import csv, collections, sys
rows = list(csv.DictReader(open(sys.argv[1])))
agg = collections.defaultdict(list)
for r in rows:
    if int(r["frame"]) > 0:
        agg[(r["ranks"], r["tiling"])].append(r)
print(f"{'ranks':>5}  {'tiling':<26} {'ms/frame':>9} {'imbalance':>9} {'within10':>8}")
for (np, tiling), rs in agg.items():
    ms = 1e3 * sum(float(r["seconds"]) for r in rs) / len(rs)
    imb = sum(float(r["imbalance"]) for r in rs) / len(rs)
    w = [float(r["within10"]) for r in rs if r["within10"]]
    print(f"{np:>5}  {tiling:<26} {ms:9.2f} {imb:9.3f} {(sum(w)/len(w) if w else float('nan')):8.2f}")
PY
echo "wrote $csv" >&2
