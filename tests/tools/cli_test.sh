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
if "$rs" render --scene cornell --width 16 --height 16 --frames 3 --out "$tmp/f#.png" --stats "$tmp/s.json" -q \
   && [ -s "$tmp/f0000.png" ] && [ -s "$tmp/f0002.png" ] && python3 -c "import json,sys; d=json.load(open('$tmp/s.json')); sys.exit(0 if len(d['frames'])==3 else 1)"; then
  ok "3-frame walk-through with per-frame files and stats"; else bad "multi-frame render"; fi
if "$rs" info --scene erw6 --json >"$tmp/i.json" && python3 -c "import json,sys; d=json.load(open('$tmp/i.json')); sys.exit(0 if d['triangles']>0 and d['grid']['occupied_cells']>0 else 1)"; then
  ok "info --json"; else bad "info --json"; cat "$tmp/i.json"; fi
if "$rs" info --scene erw6 | grep -q 'features'; then ok "info text"; else bad "info text"; fi

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

echo "cli_test: $((checks-fails)) of $checks checks passed"
[ $fails -eq 0 ]
