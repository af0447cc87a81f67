#!/usr/bin/env bash
# Output faults and hostile options through the `raystream` command:
# a full disk (RLIMIT_FSIZE) for every image format and for the statistics, a missing or
# read-only folder, SIGINT / SIGTERM in a multi-frame render, a camera path that fails at frame
# 2, closed stderr, a full stdout, NaN and out-of-range options. Each failure exits 1 (never >= 128)
# with one line naming the final path and the reason, and leaves nothing behind: no image, no
# statistics, no temporary. usage: output_faults.sh RAYSTREAM
set -uo pipefail
rs=$(realpath "$1")
tmp=$(mktemp -d)
trap 'chmod -R u+w "$tmp"; rm -rf "$tmp"' EXIT
. "$(dirname "$0")/fault_lib.sh"  # before the cd: $0 may be relative
cd "$tmp" || exit 1
small=(--width 48 --height 32 --depth 1 -q)

# 1, 2: a full disk, as a file size limit of 4 KiB (the 256x256 image needs more): every format.
for ext in png jpg bmp tga exr; do
  mkdir -p "full_$ext"
  expect_error "full disk .$ext" "full_$ext/x\\.$ext: .*(File too large|too large|space|size limit)" \
    bash -c "ulimit -f 4; exec \"$rs\" render --width 256 --height 256 --depth 1 -q --out full_$ext/x.$ext"
  expect_empty "full disk .$ext" "full_$ext"
done
# 4: statistics on a full disk: neither the statistics nor the image.
mkdir -p full_stats
expect_error "full disk, statistics" "full_stats/s\\.json: .*(File too large|too large|space|size limit)" \
  bash -c "ulimit -f 4; exec \"$rs\" render --width 8 --height 8 --depth 1 --frames 40 -q --out full_stats/x.png --stats full_stats/s.json"
expect_empty "full disk, statistics" full_stats
# 4, 17: a missing folder or a read-only one, found before the render.
mkdir -p ro && chmod a-w ro
if [ "$(id -u)" != 0 ]; then
  expect_error "read-only folder" "ro/x\\.png: .*(ermission|read-only)" "$rs" render "${small[@]}" --out ro/x.png
  expect_error "statistics into a read-only folder" "ro/s\\.json: .*(ermission|read-only)" "$rs" render "${small[@]}" --out img.png --stats ro/s.json
  [ -e img.png ] && bad "image written although the statistics cannot be" || ok "no image when the statistics cannot be written"
fi
expect_empty "read-only folder" ro
expect_error "missing folder" "no/such/x\\.png: .*(does not exist|No such)" "$rs" render "${small[@]}" --out no/such/x.png
expect_error "statistics into a missing folder" "no/s\\.json: .*(does not exist|No such)" "$rs" render "${small[@]}" --out img.png --stats no/s.json
[ -e img.png ] && bad "image written although the statistics folder is missing" || ok "no image when the statistics folder is missing"
expect_error "--out ''" "--out '': empty" "$rs" render "${small[@]}" --out ''
expect_error "unknown image format" "x\\.xyz" "$rs" render "${small[@]}" --out x.xyz

# 3: SIGINT / SIGTERM during a multi-frame render: no temporary left, no frame placed.
for sig in INT TERM; do
  mkdir -p "sig_$sig"
  # 512x512: slow enough that fewer than the 256 outputs the command may stage are done in 1.5 s
  "$rs" render --width 512 --height 512 --depth 2 --frames 100000 -q --out "sig_$sig/f#.png" --stats "sig_$sig/s.json" &
  pid=$!
  sleep 1.5
  kill -s "$sig" "$pid"
  wait "$pid"; rc=$?
  if [ $rc -eq $((128 + $(kill -l "$sig"))) ]; then ok "SIG$sig: the process died of the signal (exit $rc)"
  else bad "SIG$sig: exit $rc"; fi
  expect_empty "SIG$sig during 100000 frames" "sig_$sig"
done

# 5: a camera path whose eye meets look_at at frame 2 (between its keys, which are valid): an
# error naming the file and the frame, and frames 0 and 1 are not left behind.
mkdir -p path/out
cat >path/scene.json <<'JSON'
{"name": "meet", "materials": [{"name": "m", "diffuse": 0.7}],
 "meshes": [{"quad": [[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], "material": "m"}],
 "lights": [{"position": [0, 0, 3]}],
 "camera": {"eye": [0, 0, 4], "look_at": [0, 0, 2]},
 "path": {"frames": 5, "keys": [{"eye": [0, 0, 4], "look_at": [0, 0, 2]},
                                {"eye": [0, 0, 0], "look_at": [0, 0, 2]}]}}
JSON
if "$rs" info --scene path/scene.json >/dev/null 2>&1; then
  expect_error "camera path fails at frame 2" "path/scene\\.json: camera path frame 2: " \
    "$rs" render --scene path/scene.json "${small[@]}" --frames 3 --out 'path/out/f#.png'
  expect_empty "camera path fails at frame 2" path/out
else
  expect_error "camera path meeting its look_at, refused at load" "path/scene\\.json: " \
    "$rs" info --scene path/scene.json
fi

# 6: stderr closed: no crash, the image is written.
"$rs" render --width 32 --height 32 --depth 1 --out closed.png 2>&-; rc=$?
if [ $rc -eq 0 ] && [ -s closed.png ]; then ok "stderr closed: exit 0, image written"; else bad "stderr closed: exit $rc"; fi
"$rs" render --width 32 --height 32 --out no/closed.png 2>&-; rc=$?
[ $rc -eq 1 ] && ok "stderr closed, bad output: exit 1" || bad "stderr closed, bad output: exit $rc"
# 19: stdout on a full device.
expect_error "info >/dev/full" "cannot write to standard output" bash -c "exec \"$rs\" info >/dev/full"
expect_error "render >/dev/full" "cannot write to standard output" bash -c "exec \"$rs\" render --width 8 --height 8 --out full.png >/dev/full"
# 19: NaN and out-of-range options.
for opt in "--speed nan" "--lambda nan" "--cutoff nan"; do
  # shellcheck disable=SC2086
  expect_error "$opt" "${opt%% *} " "$rs" render "${small[@]}" $opt --out o.png
done
# Rejected by the option parser (its own exit status, below 128).
for opt in "--seed -1:non-negative" "--speed inf:not in range" "--depth 65:not in range"; do
  set -- ${opt%%:*}
  "$rs" render "${small[@]}" --pbt 1 "$@" --out o.png >out.txt 2>err.txt; rc=$?
  if [ $rc -ne 0 ] && [ $rc -lt 128 ] && grep -q "${opt#*:}" err.txt; then ok "$1 $2 rejected (exit $rc)"
  else bad "$1 $2: exit $rc"; cat err.txt; fi
done
[ -e o.png ] && bad "an image was written despite bad options" || ok "bad options: nothing written"

echo "output_faults: $((checks - fails)) of $checks checks passed, $skips skipped"
[ $fails -eq 0 ]
