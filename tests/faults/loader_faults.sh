#!/usr/bin/env bash
# Hostile input and output faults through the `raystream` command (the loaders):
# every case must exit 1 (never >= 128), print exactly one line "raystream: error: <file>...",
# and leave nothing behind; valid-but-odd inputs must render with a one-line warning.
# Full disk: a size-limited write (ulimit -f, RLIMIT_FSIZE). usage: loader_faults.sh RAYSTREAM
set -uo pipefail
rs=$(realpath "$1")
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
. "$(dirname "$0")/fault_lib.sh"  # before the cd: $0 may be relative
cd "$tmp" || exit 1

tri='v 0 0 0\nv 1 0 0\nv 0 1 0\n'
tri_uv='v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\n'

# Rows 1, 2: output on a full disk (RLIMIT_FSIZE 8 KiB; noise-free renders still exceed it at
# 160x160 for every format). SIGXFSZ left at its default: the library must not die of it.
for ext in png jpg bmp tga exr; do
  mkdir -p "full_$ext"
  expect_error "full disk .$ext" "full_$ext/x\\.$ext: cannot write image: File too large\$" \
    bash -c "ulimit -f 8; exec \"\$0\" render --width 160 --height 160 --out full_$ext/x.$ext" "$rs"
  expect_empty "full disk .$ext" "full_$ext"
done
# A frame sequence on a full disk: the first frame fails, nothing left (no temporary).
mkdir -p seq
expect_error "full disk, frame sequence" "seq/f0000\\.png: cannot write image: File too large\$" \
  bash -c "ulimit -f 8; exec \"\$0\" render --width 160 --height 160 --frames 3 --out 'seq/f#.png' -q" "$rs"
expect_empty "full disk, frame sequence" seq

# Row 17: output into a missing folder or a place that refuses new files: the final path and why
# (from the up-front CheckImageOutputPath or from the write itself).
expect_error "missing output folder" "nosuch/x\\.png: .*folder 'nosuch' does not exist" \
  "$rs" render --width 8 --height 8 --out nosuch/x.png
expect_error "unwritable output folder" "/proc/x\\.png: (cannot write image|cannot create files in folder '/proc'): " \
  "$rs" render --width 8 --height 8 --out /proc/x.png
expect_error "output is a directory" "adir\\.png: .*is a directory" \
  bash -c 'mkdir -p adir.png && exec "$0" render --width 8 --height 8 --out adir.png' "$rs"

# Row 10: a 254-byte PNG claiming 16000x16000 as map_Kd: a warning, bounded memory and time.
python3 - <<'PY'
import struct, zlib
def chunk(t, d): return struct.pack('>I', len(d)) + t + d + struct.pack('>I', zlib.crc32(t + d) & 0xffffffff)
def png(w, h, rows):
    return (b'\x89PNG\r\n\x1a\n' + chunk(b'IHDR', struct.pack('>IIBBBBB', w, h, 8, 2, 0, 0, 0))
            + chunk(b'IDAT', zlib.compress(rows)) + chunk(b'IEND', b''))
big = png(16000, 16000, bytes(range(256)) * 2)
open('big.png', 'wb').write(big + b'\0' * max(0, 254 - len(big)))
good = png(2, 2, b'\x00' + b'\xff\x00\x00' * 2 + b'\x00' + b'\x00\xff\x00' * 2)
open('good.png', 'wb').write(good)
open('trunc.png', 'wb').write(good[:40])
bad = bytearray(good); bad[45] ^= 0xff; open('corrupt.png', 'wb').write(bytes(bad))
PY
printf "mtllib big.mtl\n${tri_uv}usemtl a\nf 1/1 2/2 3/3\n" >tex.obj
printf 'newmtl a\nmap_Kd big.png\n' >big.mtl
start=$(date +%s)
if [ "$asan" = 1 ]; then
  # ASan reserves terabytes of shadow memory, so RLIMIT_AS cannot be used: ASan's own limits
  # instead (no single allocation above 1.5 GB, RSS at most 1.5 GB, a failed allocation throws).
  limit="ASan's 1.5 GB allocation and RSS limits"
  ASAN_OPTIONS="${ASAN_OPTIONS:+$ASAN_OPTIONS:}allocator_may_return_null=1:max_allocation_size_mb=1500:hard_rss_limit_mb=1500" \
    "$rs" info --scene tex.obj >out.txt 2>err.txt; rc=$?
else
  limit="a 1.5 GB limit (ulimit -v)"
  bash -c "ulimit -v 1500000; exec \"\$0\" info --scene tex.obj" "$rs" >out.txt 2>err.txt; rc=$?
fi
secs=$(( $(date +%s) - start ))
if [ $rc -eq 0 ] && [ "$(wc -l <err.txt)" -eq 1 ] && grep -q 'big\.png: image 16000x16000 .* limit' err.txt && [ $secs -lt 20 ]; then
  ok "16000x16000 texture header under $limit: $(cat err.txt) (${secs}s)"
else bad "16000x16000 texture header under $limit: exit $rc, ${secs}s"; cat err.txt; fi

# Row 16: corrupt or truncated textures: one warning line, nothing from libpng.
for t in trunc corrupt; do
  printf "newmtl a\nmap_Kd $t.png\n" >big.mtl
  "$rs" info --scene tex.obj >out.txt 2>err.txt; rc=$?
  if [ $rc -eq 0 ] && [ "$(wc -l <err.txt)" -eq 1 ] && grep -q "^raystream: warning: .*big\.mtl: material 'a': .*$t\.png" err.txt \
     && ! grep -qi libpng err.txt; then ok "$t texture: $(cat err.txt)"
  else bad "$t texture: exit $rc"; cat err.txt; fi
done

# Rows 12, 13: strict .mtl values, errors name the .mtl and its line.
printf "mtllib m.mtl\n${tri}usemtl a\nf 1 2 3\n" >m.obj
mtl_case() {
  printf "$2" >m.mtl
  expect_error "$1" "$3" "$rs" info --scene m.obj
}
mtl_case "mtl Kd nan" 'newmtl a\nKd nan 1 1\n' '\./m\.mtl:2: Kd value .nan. is not a finite number'
mtl_case "mtl Kd abc" 'newmtl a\nKd abc 1 1\n' "\./m\.mtl:2: Kd: bad number 'abc'"
mtl_case "mtl Ns 1e39" 'newmtl a\nKd 1 1 1\nNs 1e39\n' '\./m\.mtl:3: Ns value .1e39. is not a finite number'
mtl_case "mtl d 2" 'newmtl a\nd 2\n' '\./m\.mtl:2: d value 2 outside \[0, 1\]'
head -c 400 /dev/urandom | tr -d '\n\r' | tr '\000-\010' '\001' >m.mtl
expect_error "binary mtl" '\./m\.mtl:1: unexpected control character 0x[0-9a-f]{2} \(binary data' "$rs" info --scene m.obj

# Row 14: directories, FIFOs and devices say what they are (a FIFO must not hang).
mkdir -p dir.obj
expect_error "directory as scene" 'dir\.obj: is a directory' "$rs" info --scene dir.obj
mkfifo fifo.obj
expect_error "FIFO as scene" 'fifo\.obj: is a named pipe \(FIFO\)' timeout 20 "$rs" info --scene fifo.obj
expect_error "/dev/zero as scene" '/dev/zero: is a character device' timeout 20 "$rs" info --scene /dev/zero
printf '{"meshes": [{"file": "."}]}' >dot.json
expect_error 'JSON "file": "."' 'dot\.json: /meshes/0/file: .*: is a directory' "$rs" info --scene dot.json
rm -f m.mtl; mkdir m.mtl
expect_error "directory as .mtl" '\./m\.mtl: is a directory' "$rs" info --scene m.obj
rmdir m.mtl

# Row 15 (and 19's zero-area scenes): degenerate faces name the line.
printf "${tri}f 1 2 3 1 2 3\n" >deg.obj
expect_error "repeated corners" 'deg\.obj:4: scene has no triangles: every face is degenerate' "$rs" info --scene deg.obj
printf 'v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n' >flat.obj
expect_error "zero-area scene" 'flat\.obj:4: every triangle has zero area' "$rs" info --scene flat.obj

# Row 18: JSON numbers and duplicate keys with line:column.
box='"meshes": [{"box": {"min": [0,0,0], "max": [1,1,1]}}]'
printf '{%s,\n "ambient": 1e400}' "$box" >j1.json
expect_error "JSON 1e400" 'j1\.json:2:13: number 1e400 out of range' "$rs" info --scene j1.json
printf '{%s,\n "path": {"frames": 18446744073709551615}}' "$box" >j2.json
expect_error "JSON 2^64-1" 'j2\.json: /path/frames: 18446744073709551615 outside' "$rs" info --scene j2.json
printf '{%s,\n "path": {"frames": 99999999999999999999}}' "$box" >j3.json
expect_error "JSON beyond 64 bits" 'j3\.json:2:21: integer 99999999999999999999 out of range' "$rs" info --scene j3.json
printf '{%s,\n "ambient": 0.5,\n "ambient": 0.7}' "$box" >j4.json
expect_error "JSON duplicate key" 'j4\.json:3:2: duplicate key "ambient"' "$rs" info --scene j4.json

# The OpenImageIO module (textures, formats other than PNG) under an address-space limit the
# command starts in but the ~500 MB its libraries need do not fit: one line naming the limit (the
# texture is dropped with a warning; an .exr output fails), never a crash in their initialisers.
if [ "$asan" = 1 ]; then
  skip "(ASan): image module under an address-space limit: ASan reserves terabytes of shadow memory"
else
  printf "mtllib small.mtl\n${tri_uv}usemtl a\nf 1/1 2/2 3/3\n" >small.obj
  printf 'newmtl a\nmap_Kd good.png\n' >small.mtl
  bash -c "ulimit -v 200000; exec \"\$0\" info --scene small.obj" "$rs" >out.txt 2>err.txt; rc=$?
  if [ $rc -eq 0 ] && [ "$(wc -l <err.txt)" -eq 1 ] && grep -q 'good\.png: .*address-space limit (ulimit -v) of 195 MB .* OpenImageIO' err.txt; then
    ok "texture under a 195 MB limit: $(cat err.txt)"
  else bad "texture under a 195 MB limit: exit $rc"; cat err.txt; fi
  mkdir -p exr
  expect_error "EXR output under a 195 MB limit" 'exr/x\.exr: cannot write image: the address-space limit \(ulimit -v\) of 195 MB' \
    bash -c "ulimit -v 200000; exec \"\$0\" render --width 8 --height 8 --out exr/x.exr" "$rs"
  expect_empty "EXR output under a 195 MB limit" exr
  bash -c "ulimit -v 1500000; exec \"\$0\" info --scene small.obj" "$rs" >out.txt 2>err.txt; rc=$?
  if [ $rc -eq 0 ] && [ ! -s err.txt ]; then ok "texture under a 1.5 GB limit: loaded, no warning"
  else bad "texture under a 1.5 GB limit: exit $rc"; cat err.txt; fi
fi

# Issue 15, row 7 before main: an address-space limit (ulimit -v) too small for the static
# initialisers of the shared libraries. From the smallest limit at which the dynamic loader can
# map the libraries (below it the loader's own one-line "error while loading shared libraries",
# exit 127; just above it, glibc's loader may still fail on its own bookkeeping, exit 127, with
# "Fatal glibc error: cannot allocate memory for find-object data", a bare "out of memory" or
# "cannot allocate TLS data structures for initial thread" (rtld's init_tls; which one depends on
# the binary's size), before any code of the program runs) up to one the command runs in,
# `--help` and a tiny render must each exit below 128 with one line on stderr, or succeed; at
# least one limit must give the command's own "needs ... to start" line. The command maps ~26 MB
# of libraries (OpenImageIO is a module loaded on first use, scenes/image_module.h).
if [ "$asan" = 1 ]; then
  skip "(ASan): address-space limit before main: ASan reserves terabytes of shadow memory at start-up, so no RLIMIT_AS lets it start"
else
  own=0 crashes=0 works=0 msg=""
  for mb in $(seq 8 8 400); do
    for cmd in "--help" "render --width 8 --height 8 --depth 1 -q --out as/x.png"; do
      mkdir -p as
      bash -c "ulimit -v $((mb * 1024)); exec \"\$0\" $cmd" "$rs" >out.txt 2>err.txt; rc=$?
      lines=$(wc -l <err.txt)
      if [ $rc -eq 0 ]; then works=$((works+1))
      elif [ $rc -ge 128 ] || [ "$lines" -ne 1 ]; then
        crashes=$((crashes+1)); bad "ulimit -v ${mb} MB, $cmd: exit $rc, $lines lines on stderr"; head -n 3 err.txt
      elif grep -q '^raystream: error: address-space limit (ulimit -v) .* needs to start' err.txt; then own=$((own+1)); msg=$(cat err.txt)
      elif [ $rc -eq 127 ] && grep -q -x -e 'out of memory' \
             -e 'cannot allocate TLS data structures for initial thread' err.txt; then :  # the loader
      elif ! grep -q -e 'error while loading shared libraries' -e '^Fatal glibc error: ' err.txt; then
        crashes=$((crashes+1)); bad "ulimit -v ${mb} MB, $cmd: exit $rc: $(cat err.txt)"
      fi
      rm -rf as
    done
  done
  if [ $crashes -eq 0 ] && [ $own -gt 0 ] && [ $works -gt 0 ]; then
    ok "address-space limits 8..400 MB before main: no crash, $own runs refused ($msg), $works ran"
  else bad "address-space limits before main: $crashes crashes, $own refused, $works ran"; fi
fi

echo "$checks checks, $fails failed, $skips skipped"
[ $fails -eq 0 ]
