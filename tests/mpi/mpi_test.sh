#!/usr/bin/env bash
# The cluster backend (sched/mpi_backend.h) under mpirun: on every procedural and shared scene,
# with 3 and 5 ranks, every frame of a 3-frame walk-through (PBT re-tiled between frames) equals
# the serial backend's framebuffer bit for bit (hidden --dump-raw: the int64 fixed-point sums),
# statistics are written, and a dead or silent worker (dead after a tile; hung while loading,
# after a tile, in the middle of sending a result, or after its last tile) ends the run non-zero
# within bounded time, naming the rank, with no image. The statistics are the host backends'
# format (same JSON keys and CSV columns as the tiles backend, the cluster's after them) with the
# serial render's ray counts; every PBT run's tiles and per-tile owners equal a replay of the
# master's PBT from the run's own tile times (pbt_check.py: re-tiling between frames, PBT-Greedy
# and PBT-Visit affinity as sched/pbt.h defines them). The replay is the paper's Algorithm 1, so
# those runs take --pbt-predict paper; the default cost map (the workers return each tile's
# block work and hit distances) must give the tiles backend's tiles and predictions exactly.
# usage: mpi_test.sh RAYSTREAM_BINARY MPIRUN   (env CI=true: a missing shared scene is a FAIL)
set -uo pipefail
rs=$1
paper=(--pbt-predict paper)  # what pbt_check.py replays
mpirun=$2
check_pbt="$(dirname "$0")/pbt_check.py"
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
export OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1
# Keep OpenMPI off the network probes it does not need on one host.
export OMPI_MCA_btl=self,vader OMPI_MCA_btl_vader_single_copy_mechanism=none
fails=0 checks=0
# Each line starts with the seconds since the start (the suite must stay well under its meson
# timeout on a loaded 2-core machine).
ok() { checks=$((checks+1)); printf 'ok   %4ss %s\n' "$SECONDS" "$*"; }
bad() { checks=$((checks+1)); fails=$((fails+1)); printf 'FAIL %4ss %s\n' "$SECONDS" "$*"; }
run_mpi() { local np=$1; shift; timeout 120 "$mpirun" --allow-run-as-root --oversubscribe -np "$np" "$@"; }

# Procedural scenes at 96x96; the shared (file) scenes at 64x64, which keeps the suite short
# (conference has 331k triangles and every rank loads it). The walk-through: frames 0-2 of each
# scene's camera path (scenes/scene.h CameraPath), so the camera moves between frames.
walk=(--frames 3 --depth 3)
size_of() { case $1 in cornell|erw6|spherebox|amphitheater*) echo 96;; *) echo 64;; esac; }

# compare NAME DIR_A DIR_B: every frame's raw framebuffer identical and non-empty.
compare() {
  local name=$1 a=$2 b=$3 f same=1
  for f in 0000 0001 0002; do
    if [ ! -s "$a/r$f.raw" ] || [ ! -s "$b/r$f.raw" ]; then same=0; echo "  missing frame $f"; continue; fi
    cmp -s "$a/r$f.raw" "$b/r$f.raw" || { same=0; echo "  frame $f differs"; }
  done
  if [ $same = 1 ]; then ok "$name: 3 frames bit-identical to serial"; else bad "$name"; fi
}

scenes=(cornell erw6 spherebox amphitheater:1)
for shared in bunny teapot sponza office-graz conference sibenik; do
  if "$rs" info --scene "$shared" >/dev/null 2>&1; then
    scenes+=("$shared")
  elif [ "${CI:-}" = true ]; then
    bad "shared scene $shared missing under CI"
  else
    echo "skip $shared (shared scene not found: $rs info --scene $shared failed)"
  fi
done

i=0
for scene in "${scenes[@]}"; do
  n=$(size_of "$scene")
  size=(--width "$n" --height "$n" "${walk[@]}")
  mkdir -p "$tmp/$scene/serial"
  if ! "$rs" render --backend serial --scene "$scene" "${size[@]}" -q --stats "$tmp/$scene/serial/s.json" \
      --out "$tmp/$scene/serial/i#.png" --dump-raw "$tmp/$scene/serial/r#.raw" 2>"$tmp/serial.log"
  then
    bad "$scene: serial render"; cat "$tmp/serial.log"; continue
  fi
  # The walk-through really moves the camera: frame 2 differs from frame 0.
  if cmp -s "$tmp/$scene/serial/r0000.raw" "$tmp/$scene/serial/r0002.raw"; then
    bad "$scene: serial frames 0 and 2 are equal (camera did not move)"
  fi
  # Rotate the tilings over the scenes so each one runs somewhere with 3 and with 5 ranks, and
  # every PBT assignment on the procedural scenes.
  case $((i % 4)) in
    0) t3=(--pbt 2 --assign random "${paper[@]}")                t5=(--pbt 2 --assign greedy "${paper[@]}") ;;
    1) t3=(--pbt 3 --assign visit "${paper[@]}")                 t5=(--pbt 1 --assign static "${paper[@]}") ;;
    2) t3=(--pbt 4 --assign random --pbt-time cpu "${paper[@]}") t5=(--pbt 2 --assign visit --pbt-time cpu "${paper[@]}") ;;
    3) t3=(--pbt 2 --assign greedy "${paper[@]}")                t5=(--tile 40x24 --threads 3) ;;
  esac
  i=$((i+1))
  for np in 3 5; do
    d="$tmp/$scene/np$np"; mkdir -p "$d"
    # Statistics as JSON (checked against the PBT replay), CSV for cornell with 3 ranks.
    if [ $np = 3 ]; then t=("${t3[@]}"); else t=("${t5[@]}"); fi
    st=s.json; if [ $np = 3 ] && [ "$scene" = cornell ]; then st=s.csv; fi
    if run_mpi $np "$rs" render --backend mpi --scene "$scene" "${size[@]}" -q "${t[@]}" \
        --out "$d/i#.png" --dump-raw "$d/r#.raw" --stats "$d/$st" >"$d/log" 2>&1; then
      compare "$scene -np $np ${t[*]}" "$tmp/$scene/serial" "$d"
      if [ $st = s.json ] && [ "${t[0]}" = --pbt ]; then
        if python3 "$check_pbt" "$d/s.json" >"$d/pbt.log" 2>&1; then
          ok "$scene -np $np ${t[*]}: tiles and owners = PBT replay ($(tail -1 "$d/pbt.log"))"
        else bad "$scene -np $np ${t[*]}: PBT replay"; cat "$d/pbt.log"; fi
      fi
    else
      bad "$scene -np $np ${t[*]}: mpirun failed"; cat "$d/log"
    fi
  done
done

# PBT re-tiles between frames on a scene of uneven cost: a glass sphere (reflection and
# refraction to depth 3 under 3 lights) in one corner of a diffuse wall, its tiles 10-30x the
# cost of the wall's. Frame 2's tiles differ from frame 0's; PBT-Greedy (4 workers) and
# PBT-Visit (2 workers with 2 render threads each) follow the replayed PBT, images bit-identical.
# (PBT-Update does not promise a change; with m = 16 tiles it moved 8-16 of them in every trial
# run, with m = 8 as few as 3 and once back to frame 0's tiling.)
u="$tmp/uneven"; mkdir -p "$u/serial"
cat >"$u/uneven.json" <<'JSON'
{"name": "uneven",
 "materials": [{"name": "wall", "diffuse": 0.6},
               {"name": "glass", "diffuse": 0.1, "specular": 0.8, "shininess": 60,
                "reflectivity": 0.5, "transmission": 0.5, "ior": 1.5}],
 "meshes": [{"quad": [[-5, -5, 0], [5, -5, 0], [5, 5, 0], [-5, 5, 0]], "material": "wall"},
            {"sphere": {"center": [-2.2, 1.2, 1.5], "radius": 1.3, "slices": 48, "stacks": 24},
             "material": "glass"}],
 "lights": [{"position": [0, 0, 6]}, {"position": [3, 3, 5]}, {"position": [-3, 3, 5]}],
 "camera": {"eye": [0, 0, 9], "look_at": [0, 0, 0], "fov": 50},
 "path": {"frames": 8, "keys": [{"eye": [0, 0, 9], "look_at": [0, 0, 0]},
                                {"eye": [1.5, -0.5, 9], "look_at": [1.5, -0.5, 0]}]}}
JSON
usize=(--scene "$u/uneven.json" --width 96 --height 96 "${walk[@]}" -q)
if "$rs" render --backend serial "${usize[@]}" --out "$u/serial/i#.png" --dump-raw "$u/serial/r#.raw"; then
  for run in "5 4 greedy" "3 8 visit --threads 2"; do
    read -r np k assign extra <<<"$run"
    d="$u/np$np"; mkdir -p "$d"
    # shellcheck disable=SC2086  # $extra: zero or two words
    if run_mpi "$np" "$rs" render --backend mpi "${usize[@]}" --pbt "$k" --assign "$assign" "${paper[@]}" $extra \
        --out "$d/i#.png" --dump-raw "$d/r#.raw" --stats "$d/s.json" >"$d/log" 2>&1; then
      compare "uneven -np $np --pbt $k --assign $assign${extra:+ $extra}" "$u/serial" "$d"
      if python3 "$check_pbt" "$d/s.json" --expect-retile >"$d/pbt.log" 2>&1; then
        ok "uneven -np $np $assign: $(grep '^re-tiled' "$d/pbt.log"); $(tail -1 "$d/pbt.log")"
      else bad "uneven -np $np $assign: PBT re-tiling / replay"; cat "$d/pbt.log"; fi
    else
      bad "uneven -np $np $assign: mpirun failed"; cat "$d/log"
    fi
  done
  if python3 -c 'import json, sys; sys.exit(json.load(open(sys.argv[1]))["options"]
                                        ["worker_threads"] != 2)' "$u/np3/s.json" 2>/dev/null
  then ok "uneven -np 3: statistics say 2 render threads per worker"
  else bad "uneven -np 3: options.worker_threads is not 2"; fi
else
  bad "uneven: serial render"
fi

# PBT's cost map (the default predictor) over the cluster: the workers' engines record each
# tile's block work and primary hit distances as the tiles backend's threads do and return them
# with the tile's result, the master sums them and moves the map to the next camera. With one
# render thread per worker (a tile's batches are then the tiles backend's) and the deterministic
# work cost, every frame's tiles, predictions and tile costs equal the tiles backend's at as
# many threads as workers, exactly; with 2 render threads per worker (a tile's rows split into
# bands) the images stay the serial ones. Each result carries the record after the sums: a word
# per cost block the tile overlaps (4x4 pixels), then the hit distances, two floats a word.
cm=(--pbt 4 --pbt-cost work)
if "$rs" render --backend tiles --threads 4 "${usize[@]}" "${cm[@]}" --out "$u/cm_tiles.png" \
     --stats "$u/cm_tiles.json"; then
  for run in "5 1" "3 2"; do
    read -r np threads <<<"$run"
    d="$u/cm_np$np"; mkdir -p "$d"
    if run_mpi "$np" "$rs" render --backend mpi "${usize[@]}" "${cm[@]}" --threads "$threads" \
        --out "$d/i#.png" --dump-raw "$d/r#.raw" --stats "$d/s.json" >"$d/log" 2>&1; then
      compare "uneven -np $np cost map, $threads thread(s) per worker" "$u/serial" "$d"
      if python3 - "$d/s.json" "$u/cm_tiles.json" "$threads" <<'PY'
import json, sys
d, host = (json.load(open(p)) for p in sys.argv[1:3])
same = sys.argv[3] == "1"
kh = 16  # result header words (sched/mpi_backend.cc ResultWord)
for fr, hf in zip(d["frames"], host["frames"]):
    tiles = fr["tiles"]
    # 6 int32 per tile message; back the header, 3 sums per pixel, then the record.
    want = 0
    for t in tiles:
        w, h = t["x1"] - t["x0"], t["y1"] - t["y0"]
        blocks = ((t["x1"] - 1) // 4 + 1 - t["x0"] // 4) * ((t["y1"] - 1) // 4 + 1 - t["y0"] // 4)
        want += 24 + 8 * (kh + 3 * w * h + blocks + (w * h + 1) // 2)
    assert fr["bytes"] == want, (fr["frame"], fr["bytes"], want)
    assert fr["pbt"]["has_prediction"] == (fr["frame"] > 0)
    if same:
        key = lambda t: (t["x0"], t["y0"], t["x1"], t["y1"], t["predicted_seconds"], t["work"])
        assert [key(t) for t in tiles] == [key(t) for t in hf["tiles"]], fr["frame"]
        assert fr["pbt"].get("within10") == hf["pbt"].get("within10"), fr["frame"]
print(f"{len(d['frames'])} frames, within10 " +
      " ".join(f"{fr['pbt']['within10']:.3f}" for fr in d["frames"][1:]))
PY
      then
        same=""; [ "$threads" = 1 ] && same=", tiles and predictions = the tiles backend's"
        ok "uneven -np $np cost map: result bytes with the record$same"
      else bad "uneven -np $np cost map: statistics"; fi
    else
      bad "uneven -np $np cost map: mpirun failed"; cat "$d/log"
    fi
  done
else
  bad "uneven: tiles backend with the cost map"
fi

# Statistics: the host backends' format (the tiles backend's keys and CSV columns, the same
# PBT k and worker count), the cluster's fields after them; 3 frames, tiles covering the image,
# rays equal to the serial render's, per-worker idle, messages and bytes, PBT accuracy and update.
# Host references: cornell with the tiles backend, 4 threads (JSON, as -np 5) and 2 (CSV, -np 3).
h="$tmp/cornell/host"; mkdir -p "$h"
if "$rs" render --backend tiles --threads 4 --pbt 2 --assign greedy --scene cornell \
      --width 96 --height 96 "${walk[@]}" -q --out "$h/i.png" --stats "$h/s.json" &&
   "$rs" render --backend tiles --threads 2 --pbt 2 --scene cornell \
      --width 96 --height 96 "${walk[@]}" -q --out "$h/i.png" --stats "$h/s.csv"; then
  ok "host tiles statistics for the comparison"
else bad "host tiles statistics"; fi
s="$tmp/cornell/np5/s.json"
if python3 - "$s" "$h/s.json" "$tmp/cornell/serial/s.json" <<'PY'
import json, sys
d, host, serial = (json.load(open(p)) for p in sys.argv[1:4])
f = d["frames"]
# Same keys as the host backends, in the same order, the cluster's after them.
assert list(d) == list(host), (list(d), list(host))
assert d["backend"] == "mpi" and d["threads"] == 4 and len(f) == 3, d
o = d["options"]
assert list(o) == list(host["options"]) + ["ranks", "workers", "worker_threads", "prefetch",
                                           "timeout_seconds"], o
assert o["name"] == "mpi" and o["ranks"] == 5 and o["workers"] == 4 and o["pbt_workers"] == 4, o
assert o["worker_threads"] == 1, o
cluster_frame = ["messages", "bytes", "dropped_nan", "clamped"]
cluster_worker = ["rank", "messages_sent", "bytes_sent", "messages_received", "bytes_received"]
for fr, hf, sf in zip(f, host["frames"], serial["frames"]):
    assert list(fr) == list(hf) + cluster_frame, (list(fr), list(hf))
    assert list(fr["pbt"]) == list(hf["pbt"]), (fr["pbt"], hf["pbt"])
    assert all(list(t) == list(hf["tiles"][0]) for t in fr["tiles"])
    assert all(list(w) == list(hf["threads"][0]) + cluster_worker for w in fr["threads"])
    ws, tiles = fr["threads"], fr["tiles"]
    assert len(ws) == 4 and len(tiles) == 8
    # Tiles partition the 96x96 image; each was rendered by one worker.
    covered = set()
    for t in tiles:
        assert 0 <= t["x0"] < t["x1"] <= 96 and 0 <= t["y0"] < t["y1"] <= 96, t
        px = {(x, y) for x in range(t["x0"], t["x1"]) for y in range(t["y0"], t["y1"])}
        assert not covered & px, t
        covered |= px
        assert t["seconds"] > 0 and 0 <= t["thread"] < 4 and 0 <= t["worker"] < 4, t
    assert len(covered) == 96 * 96
    # Rays by kind equal the serial render's; workers' and tiles' rays add up to them.
    assert fr["rays"] == sf["rays"], (fr["rays"], sf["rays"])
    total = sum(fr["rays"].values())
    assert sum(t["rays"] for t in tiles) == total
    for kind in fr["rays"]:
        assert sum(w["rays"][kind] for w in ws) == fr["rays"][kind], kind
    assert sum(w["tasks"] for w in ws) == fr["tasks"] > 0
    assert fr["cell_steps"] > 0 and fr["triangle_tests"] > 0 and fr["trace_seconds"] > 0
    assert sum(w["tiles"] for w in ws) == 8 and [w["rank"] for w in ws] == [1, 2, 3, 4]
    assert sum(1 for t in tiles if t["thread"] != t["worker"]) == sum(w["steals"] for w in ws)
    assert all(w["messages_sent"] >= 1 and w["bytes_received"] > 0 for w in ws), ws
    assert all(0 <= w["idle_seconds"] <= fr["render_seconds"] <= fr["seconds"] for w in ws), ws
    assert fr["imbalance"] >= 1 and fr["fps"] > 0 and fr["mrays_per_second"] > 0
    # Every tile is one message each way: 6 int32 out; back 16 int64 of header and statistics
    # plus 3 int64 sums per pixel.
    assert fr["messages"] == sum(w["messages_sent"] + w["messages_received"] for w in ws) == 16
    assert fr["bytes"] == sum(w["bytes_sent"] + w["bytes_received"] for w in ws), fr
    assert fr["bytes"] == 8 * (24 + 128) + 96 * 96 * 3 * 8, fr["bytes"]
    pbt = fr["pbt"]
    assert pbt["has_prediction"] == (fr["frame"] > 0) and pbt["worker_imbalance"] >= 1
    assert ("within10" in pbt) == (fr["frame"] > 0), pbt
    assert all((t["predicted_seconds"] >= 0) == (fr["frame"] > 0) for t in tiles)
PY
then ok "stats JSON: host keys + cluster's, tiles cover the image, rays = serial, messages, bytes, PBT"
else bad "stats JSON"; fi
s="$tmp/cornell/np3/s.csv"
if python3 - "$s" "$h/s.csv" "$tmp/cornell/serial/s.json" <<'PY'
import csv, json, sys
header = open(sys.argv[1]).readline().strip().split(",")
host_header = open(sys.argv[2]).readline().strip().split(",")
assert header == host_header + ["messages", "bytes", "dropped_nan", "clamped", "rank",
    "messages_sent", "bytes_sent", "messages_received", "bytes_received"], header
serial = json.load(open(sys.argv[3]))["frames"]
rows = list(csv.DictReader(open(sys.argv[1])))
frames = [r for r in rows if r["scope"] == "frame"]
assert [r["frame"] for r in frames] == ["0", "1", "2"], frames
kinds = ("primary", "shadow", "reflection", "refraction")
for fr, sf in zip(frames, serial):
    mine = [r for r in rows if r["frame"] == fr["frame"]]
    workers = [r for r in mine if r["scope"] == "thread"]
    tiles = [r for r in mine if r["scope"] == "tile"]
    assert sum(r["scope"] == "app" for r in mine) == 1
    assert len(workers) == 2 and len(tiles) == int(fr["tiles"]) == 4, (workers, tiles)
    assert [w["rank"] for w in workers] == ["1", "2"]
    assert sum((int(t["x1"]) - int(t["x0"])) * (int(t["y1"]) - int(t["y0"])) for t in tiles) == 96 * 96
    assert all(float(t["seconds"]) > 0 and t["thread"] in ("0", "1") for t in tiles)
    assert all(float(w["idle_seconds"]) >= 0 and int(w["bytes_received"]) > 0 for w in workers)
    assert [int(fr[k]) for k in kinds] == [sf["rays"][k] for k in kinds], fr
    assert sum(int(t["rays"]) for t in tiles) == int(fr["rays"]) == sum(int(w["rays"]) for w in workers)
    assert int(fr["messages"]) == 8 == sum(int(w["messages_sent"]) + int(w["messages_received"])
                                           for w in workers)
    assert int(fr["bytes"]) == sum(int(w["bytes_sent"]) + int(w["bytes_received"])
                                   for w in workers) > 0
    assert (fr["within10"] != "") == (fr["frame"] != "0")
    assert all((t["predicted_seconds"] != "") == (fr["frame"] != "0") for t in tiles)
PY
then ok "stats CSV: host columns + cluster's, frame/app/thread/tile rows, rays = serial, messages, bytes"
else bad "stats CSV"; fi

# Only the last frame is written without '#'.
d="$tmp/last"; mkdir -p "$d"
if run_mpi 3 "$rs" render --backend mpi --scene cornell --width 32 --height 32 --frames 2 -q \
    --out "$d/last.png" && [ -s "$d/last.png" ] && [ "$(ls "$d" | wc -l)" = 1 ]; then
  ok "single output file for a 2-frame run"; else bad "single output file"; ls "$d"; fi

# expect_fail NAME PATTERN MAX_SECONDS OUTFILE CMD...: non-zero, stderr/stdout matches, in time,
# and OUTFILE was not written.
expect_fail() {
  local name=$1 pattern=$2 max=$3 outfile=$4; shift 4
  local t0=$SECONDS
  "$@" >"$tmp/fail.log" 2>&1; local rc=$?
  local took=$((SECONDS - t0))
  if [ $rc -eq 0 ]; then bad "$name: exit 0"; cat "$tmp/fail.log"; return; fi
  if [ $rc -eq 124 ]; then bad "$name: hung (killed by timeout)"; cat "$tmp/fail.log"; return; fi
  if [ $took -gt "$max" ]; then bad "$name: took ${took}s > ${max}s"; return; fi
  if [ -e "$outfile" ]; then bad "$name: wrote $outfile"; return; fi
  if grep -qE "$pattern" "$tmp/fail.log"; then ok "$name (exit $rc, ${took}s)"
  else bad "$name: output does not match /$pattern/:"; cat "$tmp/fail.log"; fi
}

# A worker that dies after its first tile: mpirun ends the job, naming rank 2.
expect_fail "dead worker (rank 2 exits)" 'process rank 2|Process name: \[\[[0-9]+,[0-9]+\],2\]' 60 "$tmp/dead.png" \
  env RAYSTREAM_MPI_TEST_KILL_RANK=2 timeout 120 "$mpirun" --allow-run-as-root --oversubscribe \
  -np 3 -x RAYSTREAM_MPI_TEST_KILL_RANK "$rs" render --backend mpi --scene cornell \
  --width 96 --height 96 --frames 3 --pbt 2 -q --out "$tmp/dead.png"
# A worker that stops answering: the master's per-tile timeout names it and aborts.
expect_fail "silent worker (rank 3 hangs)" 'mpi rank 0: worker rank 3 did not return tile' 60 \
  "$tmp/hung.png" \
  env RAYSTREAM_MPI_TEST_HANG_RANK=3 timeout 120 "$mpirun" --allow-run-as-root --oversubscribe \
  -np 5 -x RAYSTREAM_MPI_TEST_HANG_RANK "$rs" render --backend mpi --scene cornell \
  --width 96 --height 96 --frames 3 --pbt 2 -q --mpi-timeout 3 --out "$tmp/hung.png"
# A worker that hangs while loading the scene: the master's bounded setup wait names it.
expect_fail "worker hung in setup (rank 2)" \
  'mpi rank 0: worker rank 2 did not finish its setup \(loading the scene cornell' 30 \
  "$tmp/setup.png" \
  env RAYSTREAM_MPI_TEST_HANG_SETUP_RANK=2 timeout 60 "$mpirun" --allow-run-as-root --oversubscribe \
  -np 3 -x RAYSTREAM_MPI_TEST_HANG_SETUP_RANK "$rs" render --backend mpi --scene cornell \
  --width 96 --height 96 --frames 3 --pbt 2 -q --mpi-timeout 3 --out "$tmp/setup.png"
# A worker that stops in the middle of sending a result (larger than the eager limit, so the
# master has matched it but its data never comes): the bounded receive names it.
expect_fail "worker stalled sending a result (rank 1)" \
  'mpi rank 0: worker rank 1 stopped while sending a result of frame 0' 30 "$tmp/stall.png" \
  env RAYSTREAM_MPI_TEST_STALL_RANK=1 timeout 60 "$mpirun" --allow-run-as-root --oversubscribe \
  -np 3 -x RAYSTREAM_MPI_TEST_STALL_RANK "$rs" render --backend mpi --scene cornell \
  --width 96 --height 96 --frames 3 --pbt 2 -q --mpi-timeout 3 --out "$tmp/stall.png"
# A worker that hangs after its last tile (holding none, so no tile clock runs): the master's
# bounded wait for its goodbye names it, so MPI_Finalize never waits for it; neither the last
# frame's image nor the statistics are written.
expect_fail "worker hung after its last tile (rank 4)" \
  'mpi rank 0: worker rank 4 did not answer the end of the run within 3 s' 30 "$tmp/end.png" \
  env RAYSTREAM_MPI_TEST_HANG_END_RANK=4 timeout 60 "$mpirun" --allow-run-as-root --oversubscribe \
  -np 5 -x RAYSTREAM_MPI_TEST_HANG_END_RANK "$rs" render --backend mpi --scene cornell \
  --width 96 --height 96 --frames 3 --pbt 2 -q --mpi-timeout 3 --out "$tmp/end.png" \
  --stats "$tmp/end.json"
if [ -e "$tmp/end.json" ]; then bad "worker hung after its last tile: statistics written"
else ok "worker hung after its last tile: no statistics written"; fi

# Setup errors: one clear line, status 1, no hang.
expect_fail "one rank only" 'needs at least 2 ranks' 60 "$tmp/one.png" \
  timeout 60 "$rs" render --backend mpi --scene cornell --width 16 --height 16 -q --out "$tmp/one.png"
expect_fail "bad scene on every rank" 'no-such-scene' 60 "$tmp/bad.png" \
  run_mpi 3 "$rs" render --backend mpi --scene no-such-scene.obj -q --out "$tmp/bad.png"
if [ "$(grep -c 'raystream: error' "$tmp/fail.log")" = 1 ]; then ok "setup error printed once"
else bad "setup error printed $(grep -c 'raystream: error' "$tmp/fail.log") times"; cat "$tmp/fail.log"; fi

echo "$checks checks, $fails failed"
[ $fails -eq 0 ]
