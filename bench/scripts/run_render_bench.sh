#!/usr/bin/env bash
# Renderer measurements for bench/results/render: render_bench (raystream vs the same renderer
# with Embree 3 as the traversal), the command's time and peak RSS on the shared scenes, peak
# RSS against image size, the parallel efficiency of LOCAL, LFREE and tiles at 2 threads, and
# the machine's own ceiling for it (two 1-thread renders at once).
# usage: [ONLY=efficiency] [REPS=3] bench/scripts/run_render_bench.sh BUILD_DIR [OUT_DIR (default
# bench/results/render)]
# Run it with nothing else on the machine: it records the load average at the start.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
build=${1:?usage: run_render_bench.sh BUILD_DIR [OUT_DIR]}
out=${2:-$here/../results/render}
rs=$build/tools/raystream
ninja -C "$build" bench/render/render_bench tools/raystream
mkdir -p "$out"
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
{
  echo "# $(date -u +%Y-%m-%dT%H:%MZ) $(git -C "$here/.." rev-parse --short HEAD), $(nproc) cores,"\
       "$(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | sed 's/^ *//')"
  echo "# load average at the start: $(cut -d' ' -f1-3 /proc/loadavg)"
} >"$out/machine.txt"
cat "$out/machine.txt"

# ONLY=efficiency runs sections 3 and 4 alone (the 2-thread measurements).
if [ "${ONLY:-}" != efficiency ]; then
# 1. render_bench: 1024x1024, depth 4, one thread; JSON rows, summary on stderr. One scene at a
# time, its Embree and raystream rows repeated RENDER_REPS (default 5) times in random order,
# so that the host's drift (+-30 % between minutes on a shared 2-vCPU guest) lands on both
# sides of each ratio; the summary takes the medians.
: >"$out/render_summary.txt"
echo "[" >"$out/render.json"
first=1
for scene in erw6 bunny sponza office-graz conference; do
  RS_BENCH_SCENES=$scene "$build/bench/render/render_bench" --benchmark_format=json \
    --benchmark_repetitions="${RENDER_REPS:-5}" --benchmark_enable_random_interleaving=true \
    >"$tmp/render_$scene.json" 2>>"$out/render_summary.txt"
  [ $first = 1 ] || echo "," >>"$out/render.json"
  first=0
  cat "$tmp/render_$scene.json" >>"$out/render.json"
done
echo "]" >>"$out/render.json"
cat "$out/render_summary.txt"

# peak RSS (MiB) and wall seconds of one command.
measure() {
  python3 - "$@" <<'EOF'
import resource, subprocess, sys, time
t = time.time()
p = subprocess.run(sys.argv[1:], capture_output=True, text=True)
wall = time.time() - t
if p.returncode != 0:
    sys.exit(p.stderr)
rss = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
trace = [l for l in p.stdout.splitlines() if l.startswith(('trace', 'kernels'))]
print(f"{wall:.2f} s wall, {rss:.0f} MiB peak | " + " | ".join(' '.join(l.split()) for l in trace))
EOF
}

# 2. The command as a new user runs it.
{
  echo "| run | result |"
  echo "|---|---|"
  echo "| render (default: tiles, all threads), erw6 512x512 depth 4 | $(measure "$rs" render --out "$tmp/a.png") |"
  for scene in bunny conference; do
    for b in "--backend serial" "--backend tiles --threads 1"; do
      if "$rs" info --scene $scene >/dev/null 2>&1; then
        echo "| $scene 1024x1024 $b | $(measure "$rs" render --scene $scene --width 1024 --height 1024 $b --out "$tmp/a.png") |"
      fi
    done
  done
  for size in 256 512 1024 2048 4096; do
    echo "| erw6 ${size}x${size} depth 4, default backend | $(measure "$rs" render --width $size --height $size --out "$tmp/a.png") |"
  done
} | tee "$out/command.md"

fi

# 3. Parallel efficiency at 2 threads: T(1 thread) / (2 T(2 threads)), 3 frames per render, the
# best of REPS (default 3) renders per thread count, 1 and 2 threads alternating (a shared
# machine's noise only ever adds time). "all frames" is the command's trace total; "frames 2-3"
# leaves out the first frame's one-off work (arenas, first touch of the framebuffer).
reps=${REPS:-3}
{
  echo "| scene | backend | 1 thread | 2 threads | efficiency | frames 2-3: 1 thread | 2 threads | efficiency |"
  echo "|---|---|---|---|---|---|---|---|"
  for scene in bunny office-graz conference; do
    "$rs" info --scene $scene >/dev/null 2>&1 || continue
    for b in local lfree tiles; do
      for n in 1 2; do all[$n]=; steady[$n]=; done
      for r in $(seq "$reps"); do
        for n in 1 2; do
          got=$("$rs" render --scene $scene --width 1024 --height 1024 --frames 3 --backend $b \
                  --threads $n --out "$tmp/e.png" 2>&1 |
                awk '/^trace/ {t = $2} /^frame [23]\/3/ {s += $3} END {print t, s}')
          read -r t st <<<"$got"
          all[$n]=$(python3 -c "print(min(x for x in ($t, ${all[$n]:-$t})))")
          steady[$n]=$(python3 -c "print(min(x for x in ($st, ${steady[$n]:-$st})))")
        done
      done
      python3 -c "print(f'| $scene | $b | {${all[1]}:.1f} ms | {${all[2]}:.1f} ms | {${all[1]} / (2 * ${all[2]}):.3f} | {${steady[1]}:.1f} ms | {${steady[2]}:.1f} ms | {${steady[1]} / (2 * ${steady[2]}):.3f} |')"
    done
  done
} | tee "$out/efficiency.md"

# 4. What this machine gives a second thread: the same 1-thread render (tiles, frames 2-3) alone
# and as two processes at once, alternating, the best of REPS each. With two cores of their own
# the pair would take the time of one render alone (ceiling 1.0); a shared host's vCPUs give
# less, and no backend's 2-thread efficiency can exceed what two independent processes get.
steady_of() {
  "$rs" render --scene "$1" --width 1024 --height 1024 --frames 3 --backend tiles --threads 1 \
    --out "$2" 2>&1 | awk '/^frame [23]\/3/ {s += $3} END {print s}'
}
{
  echo "| scene | 1 thread alone | each of 2 at once | ceiling (alone / at once) |"
  echo "|---|---|---|---|"
  for scene in bunny office-graz conference; do
    "$rs" info --scene $scene >/dev/null 2>&1 || continue
    alone=; pair=
    for r in $(seq "$reps"); do
      a=$(steady_of $scene "$tmp/c0.png")
      steady_of $scene "$tmp/c1.png" >"$tmp/p1" &
      steady_of $scene "$tmp/c2.png" >"$tmp/p2"
      wait
      p=$(python3 -c "print(($(cat "$tmp/p1") + $(cat "$tmp/p2")) / 2)")
      alone=$(python3 -c "print(min($a, ${alone:-$a}))")
      pair=$(python3 -c "print(min($p, ${pair:-$p}))")
    done
    python3 -c "print(f'| $scene | {$alone:.1f} ms | {$pair:.1f} ms | {$alone / $pair:.3f} |')"
  done
} | tee "$out/ceiling.md"
