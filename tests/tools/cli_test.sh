#!/usr/bin/env bash
# The `raystream` command as a user meets it: renders, info, and a clear error (non-zero exit,
# one line naming the file and line or element, no partial image) for every kind of bad input.
# usage: cli_test.sh RAYSTREAM_BINARY
set -uo pipefail
rs=$1
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
fails=0 checks=0
ok() { checks=$((checks+1)); echo "ok   $*"; }
bad() { checks=$((checks+1)); fails=$((fails+1)); echo "FAIL $*"; }

# expect_error NAME PATTERN CMD...: exit status non-zero, stderr matches PATTERN, no crash.
expect_error() {
  local name=$1 pattern=$2; shift 2
  "$@" >"$tmp/out" 2>"$tmp/err"; local rc=$?
  if [ $rc -eq 0 ]; then bad "$name: exit 0"; return; fi
  if [ $rc -ge 128 ]; then bad "$name: crashed (exit $rc)"; cat "$tmp/err"; return; fi
  if grep -qE "$pattern" "$tmp/err"; then ok "$name: $(head -1 "$tmp/err")"
  else bad "$name: stderr does not match /$pattern/:"; cat "$tmp/err"; fi
}

# A render that works, with the summary a user reads.
if "$rs" render --scene cornell --width 64 --height 48 --depth 2 --out "$tmp/c.png" >"$tmp/out" 2>&1 \
   && [ -s "$tmp/c.png" ] && grep -q 'Mrays/s' "$tmp/out" && grep -q 'shadow' "$tmp/out"; then
  ok "render cornell 64x48"
else bad "render cornell"; cat "$tmp/out"; fi
if "$rs" render --scene cornell --width 32 --height 32 --out "$tmp/c.exr" -q && [ -s "$tmp/c.exr" ]; then
  ok "render to EXR"; else bad "render to EXR"; fi
# OpenImageIO (~270 libraries) is a module loaded only for textures and formats other than PNG
# (scenes/image_module.h): the loader's log names it for an EXR render and not for a PNG one.
LD_DEBUG=files LD_DEBUG_OUTPUT="$tmp/ld_png" "$rs" render --width 16 --height 16 -q --out "$tmp/m.png"
LD_DEBUG=files LD_DEBUG_OUTPUT="$tmp/ld_exr" "$rs" render --width 16 --height 16 -q --out "$tmp/m.exr"
if [ -s "$tmp/m.png" ] && [ -s "$tmp/m.exr" ] && ! grep -q 'file=libOpenImageIO' "$tmp"/ld_png.* \
   && grep -q 'raystream-oiio\.so' "$tmp"/ld_exr.* && grep -q 'file=libOpenImageIO' "$tmp"/ld_exr.*; then
  ok "PNG render maps no OpenImageIO, EXR render loads the module"
else bad "OpenImageIO module loading"; grep -h 'file=' "$tmp"/ld_png.* | head -5; fi
if "$rs" render --scene cornell --width 16 --height 16 --frames 3 --out "$tmp/f#.png" --stats "$tmp/s.json" -q \
   && [ -s "$tmp/f0000.png" ] && [ -s "$tmp/f0002.png" ] && python3 -c "import json,sys; d=json.load(open('$tmp/s.json')); sys.exit(0 if len(d['frames'])==3 else 1)"; then
  ok "3-frame walk-through with per-frame files and stats"; else bad "multi-frame render"; fi
if "$rs" info --scene erw6 --json >"$tmp/i.json" && python3 -c "import json,sys; d=json.load(open('$tmp/i.json')); sys.exit(0 if d['triangles']>0 and d['grid']['occupied_cells']>0 else 1)"; then
  ok "info --json"; else bad "info --json"; cat "$tmp/i.json"; fi
if "$rs" info --scene erw6 | grep -q 'features'; then ok "info text"; else bad "info text"; fi
# a scene 2.7e5 from the origin is built around itself (kernels/grid.h ChooseFrameShift)
if "$rs" info --scene farsphere | grep -q '^frame  *built around (148376, 123[0-9], -223423)' &&
   ! "$rs" info --scene nearsphere | grep -q '^frame'; then
  ok "info frame"; else bad "info frame"; "$rs" info --scene farsphere; fi

# Bad input.
printf 'v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n' >"$tmp/range.obj"
expect_error "OBJ index out of range" 'range\.obj:4: .*index 9' "$rs" info --scene "$tmp/range.obj"
printf 'v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n' >"$tmp/nan.obj"
expect_error "OBJ NaN vertex" 'nan\.obj:2: ' "$rs" info --scene "$tmp/nan.obj"
printf 'ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n' >"$tmp/short.ply"
expect_error "truncated PLY" 'short\.ply' "$rs" info --scene "$tmp/short.ply"
printf '{ "meshes": [ { "file": "x.obj" } ], "lights": [ { "position": [1, 2] } ] ' >"$tmp/broken.json"
expect_error "broken scene JSON" 'broken\.json:1:[0-9]+: ' "$rs" info --scene "$tmp/broken.json"
: >"$tmp/empty.obj"
expect_error "empty scene" 'empty\.obj.*(no triangles|empty)' "$rs" info --scene "$tmp/empty.obj"
expect_error "missing file" 'nothere\.obj' "$rs" info --scene "$tmp/nothere.obj"
expect_error "unknown scene name" 'nosuchscene' "$rs" info --scene nosuchscene
expect_error "bad amphitheater count" 'amphitheater' "$rs" info --scene amphitheater:0
mkdir -p "$tmp/ro"; chmod 0555 "$tmp/ro"
if [ "$(id -u)" = 0 ]; then target="/proc/raystream-cannot-write/x.png"; else target="$tmp/ro/x.png"; fi
expect_error "unwritable output" 'cannot-write|ro/x\.png' "$rs" render --scene cornell --width 8 --height 8 --out "$target"
expect_error "unknown image extension" 'x\.bogus' "$rs" render --scene cornell --width 8 --height 8 --out "$tmp/x.bogus"
[ -e "$tmp/x.bogus" ] && bad "partial image left behind" || ok "no partial image left behind"
expect_error "unknown backend" 'backend' "$rs" render --scene cornell --backend nosuch --width 8 --height 8 --out "$tmp/y.png"
expect_error "bad width" 'width' "$rs" render --scene cornell --width 0 --out "$tmp/z.png"

# Host schedulers: every backend writes the serial image byte for byte; stats as JSON or CSV.
"$rs" render --scene cornell --width 32 --height 24 --depth 3 --out "$tmp/b-serial.png" -q
"$rs" render --scene cornell --width 32 --height 24 --depth 3 --frames 2 --out "$tmp/b-serial2.png" -q
for b in "lock --threads 2" "lfree --threads 3" "local --threads 2" "tiles --threads 2 --tile 640x2" \
         "tiles --threads 2 --tile 7x5" "tiles --threads 2 --pbt 2 --assign visit --frames 2" \
         "tiles --threads 2 --pbt 3 --pbt-workers 4 --assign greedy --steal"; do
  name=$(echo "$b" | tr ' ' '_')
  want="$tmp/b-serial.png"; case "$b" in *"--frames 2"*) want="$tmp/b-serial2.png";; esac
  # shellcheck disable=SC2086
  if "$rs" render --scene cornell --width 32 --height 24 --depth 3 --backend $b --out "$tmp/b-$name.png" -q \
     && cmp -s "$want" "$tmp/b-$name.png"; then ok "backend $b: same image as serial"
  else bad "backend $b: image differs from serial or render failed"; fi
done
# --grid: every acceleration structure renders the serial image byte for byte (the irregular
# grid traces the reflected and refracted rays); the cell backend refuses the irregular grid.
for g in uniform two-level irregular; do
  if "$rs" render --scene cornell --width 32 --height 24 --depth 3 --grid $g --backend tiles --threads 2 \
       --out "$tmp/g-$g.png" -q && cmp -s "$tmp/b-serial.png" "$tmp/g-$g.png"; then ok "--grid $g: same image as serial"
  else bad "--grid $g: image differs from serial or render failed"; fi
done
if "$rs" info --scene cornell --grid irregular | grep -qE '^irregular +[0-9]+ cells'; then ok "info --grid irregular: irregular grid printed"
else bad "info --grid irregular: no irregular line"; fi
expect_error "cell backend with --grid irregular" 'grid irregular.*cell backend' "$rs" render --scene cornell --width 8 --height 8 --backend cell --grid irregular --out "$tmp/gc.png"
expect_error "unknown grid" 'grid' "$rs" render --scene cornell --grid nosuch --width 8 --height 8 --out "$tmp/gn.png"
# The tiles backend's demand-driven master (--demand, tools/raystream.cc): a free thread asks for
# the next tile in PBT order (its own lists' first). The serial image with 2 re-tiled frames, as
# many threads as PBT workers or fewer; every tile rendered once; "demand" in the statistics.
for d in "--threads 2 --pbt 2" "--threads 3 --pbt 3 --pbt-workers 4 --assign greedy"; do
  name=$(echo "$d" | tr ' ' '_')
  # shellcheck disable=SC2086
  if "$rs" render --scene cornell --width 32 --height 24 --depth 3 --frames 2 --backend tiles $d --demand \
       --out "$tmp/d$name.png" --stats "$tmp/d$name.json" -q && cmp -s "$tmp/b-serial2.png" "$tmp/d$name.png" \
     && python3 -c "
import json, sys
d = json.load(open('$tmp/d$name.json'))
o, f = d['options'], d['frames']
ok = d['backend'] == 'tiles' and o['demand'] is True and o['steal'] is False and len(f) == 2
ok = ok and all(len(x['tiles']) == o['pbt_workers'] * o['pbt_tiles_per_worker'] for x in f)
ok = ok and all(sum((t['x1'] - t['x0']) * (t['y1'] - t['y0']) for t in x['tiles']) == 32 * 24 for x in f)
ok = ok and all(sum(t['rays'] for t in x['tiles']) == sum(x['rays'].values()) for x in f)
sys.exit(0 if ok else 1)"; then ok "tiles $d --demand, 2 frames: serial image, every tile once, demand in stats"
  else bad "tiles $d --demand: image differs from serial, render failed or bad stats"; fi
done
expect_error "--demand needs PBT" 'error: --demand: needs a PBT' "$rs" render --scene cornell --backend tiles --demand --width 8 --height 8 --out "$tmp/y.png"
expect_error "--demand on a queue backend" 'error: --demand: .*tiles backend.*not lock' "$rs" render --scene cornell --backend lock --pbt 2 --demand --width 8 --height 8 --out "$tmp/y.png"
expect_error "--demand on the mpi backend" 'error: --demand: the mpi backend' "$rs" render --scene cornell --backend mpi --pbt 2 --demand --width 8 --height 8 --out "$tmp/y.png"
expect_error "--demand with --steal" 'error: --demand: with --steal' "$rs" render --scene cornell --backend tiles --pbt 2 --demand --steal --width 8 --height 8 --out "$tmp/y.png"
expect_error "--demand with --assign counter" 'error: --demand: --assign counter' "$rs" render --scene cornell --backend tiles --pbt 2 --assign counter --demand --width 8 --height 8 --out "$tmp/y.png"
[ -e "$tmp/y.png" ] && bad "rejected --demand left an image" || ok "rejected --demand options leave no image"
# PBT tiles feeding the queue backends: the serial image after 3 re-tiled frames; the tiles'
# costs are their ray counts (--pbt-cost work, the only cost a queue backend has).
"$rs" render --scene cornell --width 32 --height 24 --depth 3 --frames 3 --out "$tmp/b-serial3.png" -q
if "$rs" render --scene cornell --width 32 --height 24 --depth 3 --backend local --threads 2 --pbt 2 --assign greedy \
     --frames 3 --out "$tmp/q-local.png" --stats "$tmp/q-local.json" -q && cmp -s "$tmp/b-serial3.png" "$tmp/q-local.png" \
   && python3 -c "
import json, sys
f = json.load(open('$tmp/q-local.json'))['frames']
ok = len(f) == 3 and all(len(x['tiles']) == 4 and x['pbt']['has_prediction'] == (i > 0) for i, x in enumerate(f))
ok = ok and all(sum(t['rays'] for t in x['tiles']) == sum(x['rays'].values()) for x in f)
ok = ok and all(t['predicted_seconds'] > 0 and t['work'] > 0 for t in f[2]['tiles'])
sys.exit(0 if ok else 1)"; then ok "local --pbt 2 --assign greedy, 3 frames: serial image, per-tile work stats"
else bad "local --pbt 2 --assign greedy: image differs from serial, render failed or bad stats"; fi
expect_error "--pbt-predict unknown" 'error: --pbt-predict costmapp: expected paper or costmap' "$rs" render --scene cornell --backend tiles --pbt 2 --pbt-predict costmapp --width 8 --height 8 --out "$tmp/y.png"
expect_error "--pbt-predict needs PBT" 'error: --pbt-predict paper: needs --pbt k' "$rs" render --scene cornell --backend tiles --pbt-predict paper --width 8 --height 8 --out "$tmp/y.png"
expect_error "queue backend: --pbt-cost wall" 'pbt-cost wall.*lock backend.*no wall or CPU time' "$rs" render --scene cornell --backend lock --pbt 2 --pbt-cost wall --width 8 --height 8 --out "$tmp/y.png"
if "$rs" render --scene erw6 --width 24 --height 24 --backend lfree --threads 2 --frames 2 --out "$tmp/l.png" \
     --stats "$tmp/l.json" >"$tmp/out" 2>&1 \
   && grep -q 'idle at the barrier' "$tmp/out" && grep -q 'Mrays/s' "$tmp/out" \
   && python3 -c "import json,sys; d=json.load(open('$tmp/l.json')); f=d['frames']; sys.exit(0 if len(f)==2 and len(f[1]['threads'])==2 and d['backend']=='lfree' and f[0]['rays']['primary']==576 else 1)"; then
  ok "lfree: summary with idle/queue times, per-thread JSON stats"
else bad "lfree stats"; cat "$tmp/out"; fi
if "$rs" render --scene erw6 --width 24 --height 24 --backend tiles --threads 2 --pbt 2 --assign greedy --frames 3 \
     --speed 2 --out "$tmp/p.png" --stats "$tmp/p.csv" -q \
   && head -1 "$tmp/p.csv" | grep -q '^frame,scope,index' \
   && [ "$(grep -c '^[0-9]*,tile,' "$tmp/p.csv")" -eq 12 ] && [ "$(grep -c '^[0-9]*,thread,' "$tmp/p.csv")" -eq 6 ]; then
  ok "tiles + PBT: CSV stats with 12 tile rows and 6 thread rows"
else bad "tiles + PBT CSV stats"; head -3 "$tmp/p.csv"; fi
if "$rs" render --scene cornell --width 16 --height 16 --backend local --threads 4 --out "$tmp/o.png" 2>&1 \
   | grep -q 'oversubscribe\|idle'; then ok "4 threads: runs (oversubscription noted when threads > cores)"
else bad "local 4 threads"; fi
expect_error "unknown backend lists the choices" 'nosuch.*(lock|lfree|local|tiles)' "$rs" render --scene cornell --backend nosuch --width 8 --height 8 --out "$tmp/y.png"
expect_error "bad tile shape" 'tile.*WIDTHxHEIGHT|--tile' "$rs" render --scene cornell --backend tiles --tile 32 --width 8 --height 8 --out "$tmp/y.png"
expect_error "zero tile size" '\-\-tile 0x4' "$rs" render --scene cornell --backend tiles --tile 0x4 --width 8 --height 8 --out "$tmp/y.png"
expect_error "PBT needs a parallel backend" 'pbt.*serial' "$rs" render --scene cornell --backend serial --pbt 2 --width 8 --height 8 --out "$tmp/y.png"
expect_error "--steal needs PBT" 'steal' "$rs" render --scene cornell --backend tiles --steal --width 8 --height 8 --out "$tmp/y.png"
expect_error "unknown PBT assignment" 'assign' "$rs" render --scene cornell --backend tiles --pbt 1 --assign sjf --width 8 --height 8 --out "$tmp/y.png"
expect_error "serial with threads" 'threads' "$rs" render --scene cornell --backend serial --threads 2 --width 8 --height 8 --out "$tmp/y.png"
expect_error "more PBT tiles than pixels" '(tile|pixel)' "$rs" render --scene cornell --backend tiles --threads 2 --pbt 64 --width 8 --height 8 --out "$tmp/y.png"
expect_error "stats file extension" 'stats.*(json|csv)' "$rs" render --scene cornell --width 8 --height 8 --stats "$tmp/s.txt" --out "$tmp/y2.png"
[ -e "$tmp/y2.png" ] && bad "image written despite a bad --stats name" || ok "bad --stats name: checked before rendering"

# An exponential ray tree (the camera inside two nested boxes whose walls reflect and transmit
# everything, depth 64, no cutoff) stops at the ray budget with a warning, in bounded memory.
box() {  # box NAME HALF: a closed cube of 12 triangles
  h=$2; printf 'v -%s -%s -%s\nv %s -%s -%s\nv %s %s -%s\nv -%s %s -%s\nv -%s -%s %s\nv %s -%s %s\nv %s %s %s\nv -%s %s %s\nf 1 2 3\nf 1 3 4\nf 6 5 8\nf 6 8 7\nf 5 1 4\nf 5 4 8\nf 2 6 7\nf 2 7 3\nf 4 3 7\nf 4 7 8\nf 5 6 2\nf 5 2 1\n' \
    $h $h $h $h $h $h $h $h $h $h $h $h $h $h $h $h $h $h $h $h $h $h $h $h >"$tmp/$1.obj"
}
box inner 1; box outer 3
cat >"$tmp/mirrors.json" <<'JSON'
{"name": "mirrors",
 "materials": [{"name": "glass", "diffuse": 0.5, "reflectivity": 1, "transmission": 1, "ior": 1.2}],
 "meshes": [{"file": "inner.obj", "material": "glass"}, {"file": "outer.obj", "material": "glass"}],
 "lights": [{"position": [0.3, 0.4, 0.2]}],
 "camera": {"eye": [0.1, 0.2, 0.5], "look_at": [0, 0, -1]}}
JSON
if timeout 120 "$rs" render --scene "$tmp/mirrors.json" --width 16 --height 16 --depth 64 --cutoff 0 \
     --out "$tmp/mirrors.png" -q 2>"$tmp/mirrors.err" && grep -q 'bounce rays dropped.*--ray-budget 1024' "$tmp/mirrors.err" \
   && test -s "$tmp/mirrors.png"; then
  ok "exponential ray tree: stops at the ray budget with a warning"
else bad "exponential ray tree: no warning, failure or timeout"; cat "$tmp/mirrors.err"; fi

# Memory does not grow with the ray tree: a 2048x2048 render at depth 4 peaks below its
# framebuffer (24 bytes per pixel) + 256 MiB.
if python3 -c "
import resource, subprocess, sys
subprocess.run(['$rs', 'render', '--width', '2048', '--height', '2048', '--depth', '4',
                '--out', '$tmp/big.png', '-q'], check=True)
peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024
limit = 24 * 2048 * 2048 + 256 * 2**20
print(f'peak {peak / 2**20:.0f} MiB, limit {limit / 2**20:.0f} MiB')
sys.exit(0 if peak <= limit else 1)" >"$tmp/mem.out" 2>&1; then ok "2048x2048 depth 4: $(cat "$tmp/mem.out")"
else bad "2048x2048 depth 4 over framebuffer + 256 MiB: $(cat "$tmp/mem.out")"; fi

# Cell simulator backend (--backend cell): the serial image byte for byte (through the SPEs'
# local-store pixel buffers and their DMA write-back), the cycle report, simulated cycles that are
# the same in every process, and clear errors for bad options.
if "$rs" render --scene cornell --width 32 --height 24 --depth 3 --backend cell --out "$tmp/b-cell.png" >"$tmp/out" 2>&1 \
   && cmp -s "$tmp/b-serial.png" "$tmp/b-cell.png" && grep -qE '^cell +6 SPEs: .* cycles at 3\.2 GHz' "$tmp/out" \
   && grep -q 'SPE  compute%   dma%  atomic%  cache%   idle%' "$tmp/out" && grep -q '^memory .* DMA commands' "$tmp/out"; then
  ok "backend cell: same image as serial, cycle report printed"
else bad "backend cell: image differs from serial, render failed or no cycle report"; cat "$tmp/out"; fi
for b in "--spes 1 --tile 640x2" "--spes 8 --tile 7x5" "--spes 3 --pbt 2 --frames 2"; do
  name=$(echo "$b" | tr ' ' '_')
  want="$tmp/b-serial.png"; case "$b" in *"--frames 2"*) want="$tmp/b-serial2.png";; esac
  # shellcheck disable=SC2086
  if "$rs" render --scene cornell --width 32 --height 24 --depth 3 --backend cell $b --out "$tmp/bc$name.png" \
       --stats "$tmp/bc$name.json" -q && cmp -s "$want" "$tmp/bc$name.png"; then ok "backend cell $b: same image as serial"
  else bad "backend cell $b: image differs from serial or render failed"; fi
done
if python3 -c "
import json, sys
f = json.load(open('$tmp/bc--spes_3_--pbt_2_--frames_2.json'))['frames']
t = f[1]['tiles']
sys.exit(0 if len(f) == 2 and len(t) == 6 and all(x['predicted_seconds'] > 0 for x in t)
         and abs(sum(x['predicted_seconds'] for x in t) - sum(x['work'] for x in f[0]['tiles'])) < 1e-6 * sum(x['predicted_seconds'] for x in t) else 1)"; then
  ok "backend cell + PBT: frame 2 predicted from frame 1's simulated tile cycles"
else bad "backend cell + PBT stats"; fi
# A textured scene: the software cache reads materials and texels. A texture larger than the
# malloc mmap threshold (forced low) lands at an address whose page bits differ from run to run;
# the simulated cycles must not (they depend on simulated effective addresses only).
"$rs" render --scene cornell --width 512 --height 384 --depth 1 --out "$tmp/tex-big.png" -q
"$rs" render --scene erw6 --width 40 --height 30 --depth 1 --out "$tmp/tex-small.png" -q
printf 'v -4 0 4\nv 4 0 4\nv 4 0 -4\nv -4 0 -4\nvt -1.3 -1.3\nvt 2.3 -1.3\nvt 2.3 2.3\nvt -1.3 2.3\nf 1/1 2/2 3/3\nf 1/1 3/3 4/4\n' >"$tmp/floor.obj"
printf 'v -4 0 -3\nv 4 0 -3\nv 4 5 -3\nv -4 5 -3\nvt -1.3 -1.3\nvt 2.3 -1.3\nvt 2.3 2.3\nvt -1.3 2.3\nf 1/1 2/2 3/3\nf 1/1 3/3 4/4\n' >"$tmp/wall.obj"
cat >"$tmp/textured.json" <<'JSON'
{"name": "textured",
 "materials": [{"name": "floor", "diffuse": 0.8, "texture": "tex-big.png", "reflectivity": 0.3, "specular": 0.4, "shininess": 20},
               {"name": "wall", "diffuse": 0.6, "texture": "tex-small.png", "reflectivity": 0.3, "specular": 0.4, "shininess": 20}],
 "meshes": [{"file": "floor.obj", "material": "floor"}, {"file": "wall.obj", "material": "wall"}],
 "lights": [{"position": [1, 4, 2]}],
 "camera": {"eye": [0, 3, 6], "look_at": [0, 1, -2]}}
JSON
if "$rs" info --scene "$tmp/textured.json" | grep -q 'textures=true' \
   && "$rs" render --scene "$tmp/textured.json" --width 64 --height 48 --depth 2 --out "$tmp/tx-serial.png" -q \
   && "$rs" render --scene "$tmp/textured.json" --width 64 --height 48 --depth 2 --backend cell --out "$tmp/tx-cell.png" -q \
   && cmp -s "$tmp/tx-serial.png" "$tmp/tx-cell.png"; then ok "backend cell, textured scene: same image as serial"
else bad "backend cell, textured scene: image differs from serial or render failed"; fi
det_ok=1
for i in 1 2 3 4 5 6; do
  GLIBC_TUNABLES=glibc.malloc.mmap_threshold=65536 "$rs" render --scene "$tmp/textured.json" --width 64 --height 48 \
    --depth 2 --backend cell --out "$tmp/det$i.png" --stats "$tmp/det$i.json" >"$tmp/det$i.txt" 2>&1 || det_ok=0
  sed -e 's/; host .*//' "$tmp/det$i.txt" | grep -vE '^(load|wrote|cell image) ' >"$tmp/det$i.report"
  cmp -s "$tmp/det1.report" "$tmp/det$i.report" || det_ok=0
done
if [ $det_ok = 1 ] && grep -q 'SW cache' "$tmp/det1.report" && python3 -c "
import json, sys
def strip(d):
    if isinstance(d, dict): return {k: strip(v) for k, v in d.items() if k != 'host_seconds'}
    if isinstance(d, list): return [strip(x) for x in d]
    return d
runs = [strip(json.load(open('$tmp/det%d.json' % i))) for i in range(1, 7)]
sys.exit(0 if all(r == runs[0] for r in runs) and runs[0]['frames'][0]['cycles'] > 0 else 1)"; then
  ok "backend cell: cycle report and --stats JSON identical in 6 processes (textured scene)"
else bad "backend cell: simulated cycles differ between processes"; diff "$tmp/det1.report" "$tmp/det2.report"; fi
expect_error "cell: --spes 9" '\-\-spes.*9' "$rs" render --scene cornell --backend cell --spes 9 --width 8 --height 8 --out "$tmp/y.png"
expect_error "cell: --spes 0" '\-\-spes.*0' "$rs" render --scene cornell --backend cell --spes 0 --width 8 --height 8 --out "$tmp/y.png"
expect_error "cell: --threads" 'threads.*cell backend' "$rs" render --scene cornell --backend cell --threads 2 --width 8 --height 8 --out "$tmp/y.png"
# One statistics writer for every backend: the cell backend's CSV has the host columns, one thread
# row per SPE and its own columns after them.
if "$rs" render --scene cornell --backend cell --spes 3 --stats "$tmp/c.csv" --width 16 --height 16 --out "$tmp/c.png" -q \
   && python3 -c "
import csv, sys
rows = list(csv.DictReader(open('$tmp/c.csv')))
spes = [r for r in rows if r['scope'] == 'thread']
frame = [r for r in rows if r['scope'] == 'frame'][0]
sys.exit(0 if len(spes) == 3 and all(int(r['compute_cycles']) > 0 for r in spes)
         and int(frame['cycles']) > 0 and int(frame['rays']) > 0 else 1)"; then ok "cell: CSV statistics (host columns, one row per SPE, cycles)"
else bad "cell: CSV statistics"; fi
expect_error "cell: zero tile size" '\-\-tile 0x4' "$rs" render --scene cornell --backend cell --tile 0x4 --width 8 --height 8 --out "$tmp/y.png"
expect_error "cell: more PBT tiles than pixels" '(tile|pixel)' "$rs" render --scene cornell --backend cell --pbt 64 --width 8 --height 8 --out "$tmp/y.png"
[ -e "$tmp/y.png" ] && bad "cell: image written despite bad options" || ok "cell: bad options checked before rendering"

echo "cli_test: $((checks-fails)) of $checks checks passed"
[ $fails -eq 0 ]
