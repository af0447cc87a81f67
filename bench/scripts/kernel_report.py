#!/usr/bin/env python3
"""Writes bench/results/kernels/embree.md from Google Benchmark JSON files of one session:
trace_bench (raystream vs Embree 3, RS_BENCH_FULL=1), dda_bench (CPU ticks per ray per target),
tri_bench (CPU ticks per ray/triangle test over a cell per target) and step_bench (one DDA step
and one triangle test per target), plus robust_bench's text output.
Ratios are taken within one file (same run); medians when the run has repetitions.

Usage: kernel_report.py --trace T.json --dda D.json --tri R.json [--step S.json]
                        [--robust robust.txt] [--commands commands.txt] --out embree.md
"""
import argparse
import json
import re

SCENES = ["bunny", "sponza", "office-graz", "conference", "spherebox"]
EMBREE = ["embree1", "embree16", "embree1M"]


def load(path):
    with open(path) as f:
        return json.load(f)


def rows(data):
    """run_name -> benchmark row (the median aggregate if repeated, else the single run)."""
    out = {}
    for b in data["benchmarks"]:
        if b.get("error_occurred"):
            out[b["run_name"]] = {"error": b.get("error_message", "error")}
            continue
        if b["run_type"] == "aggregate":
            if b["aggregate_name"] == "median":
                out[b["run_name"]] = b
        elif b["run_name"] not in out:
            out[b["run_name"]] = b
    return out


def rate(r, name):
    b = r.get(name)
    if not b or "error" in b:
        return None
    return b["items_per_second"]


def fmt(x, spec=".2f"):
    return "n/a" if x is None else format(x, spec)


def trace_tables(data, lines, goals):
    r = rows(data)
    lines.append("### Ratios: raystream speed ÷ Embree speed (> 1: raystream faster)\n")
    lines.append("Rays/s for primary, shadow, diffuse; frames/s for time to image (build + one "
                 "1024x1024 frame of primary and shadow rays, scene rebuilt every frame); "
                 "triangles/s for the build (raystream grid vs Embree BVH, both one thread). "
                 "raystream = rs::Accel (coherent 64-ray packets where the rays allow, else the "
                 "per-ray stream DDA); ÷ per-ray = its speed over the per-ray stream DDA alone on "
                 "the same grid (`raystream-rays`), same run.\n")
    lines.append("| scene | set | raystream | ÷ Embree 1 | ÷ Embree 16 | ÷ Embree 1M | "
                 "÷ best Embree | ÷ per-ray |")
    lines.append("|---|---|---:|---:|---:|---:|---:|---:|")
    worst = {}
    for scene in SCENES:
        for group in ["primary", "shadow", "diffuse", "frame"]:
            ours = rate(r, f"{group}/{scene}/raystream")
            if ours is None:
                lines.append(f"| {scene} | {group} | skipped | | | | | |")
                continue
            theirs = [rate(r, f"{group}/{scene}/{e}") for e in EMBREE]
            ratios = [ours / t if t else None for t in theirs]
            best = min((x for x in ratios if x is not None), default=None)
            if group == "frame":
                absolute = f"{1e3 / ours:.0f} ms"
            else:
                absolute = f"{ours * 1e-6:.2f} Mrays/s"
            per_ray = rate(r, f"{group}/{scene}/raystream-rays")
            vs_rays = fmt(ours / per_ray) if per_ray else ""
            lines.append(f"| {scene} | {group} | {absolute} | " +
                         " | ".join(fmt(x) for x in ratios) + f" | **{fmt(best)}** | {vs_rays} |")
            worst.setdefault(group, []).append((scene, best))
        ours = rate(r, f"build/{scene}/raystream")
        theirs = rate(r, f"build/{scene}/embree")
        if ours is not None and theirs:
            lines.append(f"| {scene} | build | {ours * 1e-6:.1f} Mtris/s | "
                         f"(Embree {theirs * 1e-6:.2f} Mtris/s) | | | **{ours / theirs:.2f}** | |")
            worst.setdefault("build_mtris", []).append((scene, ours * 1e-6))
    lines.append("")
    lines.append("### Absolute rates (for orientation only: the machine was shared)\n")
    lines.append("| scene | set | raystream | Embree 1 | Embree 16 | Embree 1M |")
    lines.append("|---|---|---:|---:|---:|---:|")
    for scene in SCENES:
        for group in ["primary", "shadow", "diffuse"]:
            vals = [rate(r, f"{group}/{scene}/{t}") for t in ["raystream"] + EMBREE]
            lines.append(f"| {scene} | {group} (Mrays/s) | " +
                         " | ".join(fmt(v * 1e-6 if v else None) for v in vals) + " |")
        vals = [rate(r, f"frame/{scene}/{t}") for t in ["raystream"] + EMBREE]
        lines.append(f"| {scene} | frame (ms) | " +
                     " | ".join(fmt(1e3 / v if v else None, ".0f") for v in vals) + " |")
    lines.append("")
    goals["primary"] = worst.get("primary", [])
    goals["diffuse"] = worst.get("diffuse", [])
    goals["frame"] = worst.get("frame", [])
    goals["build"] = worst.get("build_mtris", [])


def counter(b, key):
    return None if not b or "error" in b else b.get(key)


def dda_tables(data, lines, goals):
    r = rows(data)
    names = list(r.keys())
    targets = []
    for n in names:
        m = re.match(r"^Dda/([^/]+)/", n)
        if m and m.group(1) not in targets:
            targets.append(m.group(1))
    workloads = []
    for n in names:
        m = re.match(r"^DdaScalar/(.+)$", n)
        if m:
            workloads.append(m.group(1))
    lines.append("### 3D-DDA: CPU ticks per ray, per Highway target (dda_bench)\n")
    lines.append("cpu_ticks/ray = the whole traversal's thread CPU time (rdtsc reference ticks) ÷ "
                 "rays, triangle tests, setup and lane refills included (steps/ray beside it); "
                 "not a per-step cost: the DDA step alone is in step_bench's table. "
                 "Stream = rays in lanes (rs::Accel's kernel); single = the Cell paper's one ray, "
                 "xyz in lanes; scalar = the scalar DDA (oracle).\n")
    lines.append("| workload | form | steps/ray | " + " | ".join(targets) + " | scalar oracle |")
    lines.append("|---|---|---:|" + "---:|" * (len(targets) + 1))
    for w in workloads:
        scalar_row = r.get(f"DdaScalar/{w}")
        scalar = ticks_per_ray(scalar_row)
        steps = counter(scalar_row, "steps/ray")
        for form, prefix in [("stream", "Dda"), ("single", "DdaSingle")]:
            vals = [ticks_per_ray(r.get(f"{prefix}/{t}/{w}")) for t in targets]
            lines.append(f"| {w} | {form} | {fmt(steps, '.1f')} | " +
                         " | ".join(fmt(v, ".1f") for v in vals) + f" | {fmt(scalar, '.1f')} |")
    lines.append("")


def ticks_per_ray(b):
    """dda_bench's CPU ticks per ray (named cyc/ray in runs before the rename)."""
    v = counter(b, "cpu_ticks/ray")
    return v if v is not None else counter(b, "cyc/ray")


def step_tables(data, lines, goals):
    """step_bench: the marginal cost of one DDA step and of one ray/triangle test per target."""
    r = rows(data)
    targets = []
    for n in r:
        m = re.match(r"^DdaStep/([^/]+)/stream$", n)
        if m and m.group(1) not in targets:
            targets.append(m.group(1))
    lines.append("### One DDA step and one ray/triangle test, per Highway target (step_bench)\n")
    lines.append("The kernel in a tight loop, twice on the same rays (short and long), the "
                 "difference of the thread CPU times (rdtsc ticks) ÷ the difference of the work: "
                 "setup, lane refills, the call and its dispatch drop out. DDA: empty cells of the "
                 "64^3 `corners` grid, no empty-space skipping. Triangles: cells of 16 and 64 "
                 "random triangles, `auto` bundle width for 1x4.\n")
    lines.append("| kernel | form | " + " | ".join(targets) + " | scalar |")
    lines.append("|---|---|" + "---:|" * (len(targets) + 1))
    for form in ["stream", "single"]:
        vals = [counter(r.get(f"DdaStep/{t}/{form}"), "cpu_ticks/step") for t in targets]
        scalar = counter(r.get("DdaStep/scalar"), "cpu_ticks/step")
        lines.append(f"| DDA step | {form} | " + " | ".join(fmt(v, ".2f") for v in vals) +
                     f" | {fmt(scalar, '.2f')} |")
        if form == "stream" and targets:
            goals["dda_step"] = (targets[0], vals[0])
    best = None
    for test in ["watertight", "moller"]:
        for form in ["1x4", "Nx1"]:
            vals = [counter(r.get(f"TriTest/{t}/{test}/{form}"), "cpu_ticks/test")
                    for t in targets]
            scalar = counter(r.get(f"TriTest/ref/{test}/{form}"), "cpu_ticks/test")
            lines.append(f"| {test} test | {form} | " + " | ".join(fmt(v, ".2f") for v in vals) +
                         f" | {fmt(scalar, '.2f')} |")
            if targets and test == "watertight" and vals[0] is not None:
                if best is None or vals[0] < best[2]:
                    best = (f"step_bench {form}", targets[0], vals[0])
    lines.append("")
    if best:
        goals["tri_test"] = best


def tri_tables(data, lines, goals):
    r = rows(data)
    targets = []
    for n in r:
        m = re.match(r"^Tri1x4/([^/]+)/", n)
        if m and m.group(1) not in targets:
            targets.append(m.group(1))
    lines.append("### Ray/triangle tests: CPU ticks per test, per Highway target (tri_bench)\n")
    lines.append("One cell of 16 or 64 random triangles (4-wide triangle bundles), 4096 rays through it "
                 "(21 % hit), per-ray setup excluded; cpu_ticks/test = the pass's CPU time in "
                 "rdtsc ticks (call and dispatch per ray included) ÷ "
                 "(rays × triangles). 1x4 = one ray against the bundles, `auto` width (16 lanes "
                 "on AVX3, 8 on AVX2, 4 below); N x 1 = rays in lanes, one triangle at a time "
                 "(hit reset included); any = occlusion, which stops at the first hit (the count "
                 "assumes all lanes ran: a lower bound on the real cost per test).\n")
    lines.append("| kernel | test | tris | " + " | ".join(targets) + " |")
    lines.append("|---|---|---:|" + "---:|" * len(targets))
    best_avx3 = None
    for tris in ["16", "64"]:
        for kernel, label in [("Tri1x4", "1x4 closest"), ("TriNx1", "N x 1 closest"),
                              ("TriAny1x4", "1x4 any")]:
            for test in ["watertight", "moller"]:
                if kernel == "TriAny1x4" and test != "watertight":
                    continue
                vals = []
                for t in targets:
                    if t == "ref":
                        name = f"{kernel}/ref/{test}/tris:{tris}"
                    elif kernel == "TriNx1":
                        name = f"{kernel}/{t}/{test}/tris:{tris}"
                    else:
                        name = f"{kernel}/{t}/{test}/auto/tris:{tris}"
                    v = counter(r.get(name), "cpu_ticks/test")
                    vals.append(v if v is not None else counter(r.get(name), "cyc/test"))
                lines.append(f"| {label} | {test} | {tris} | " +
                             " | ".join(fmt(v, ".2f") for v in vals) + " |")
                # the widest target (the first column: AVX3 where the CPU has AVX-512)
                if targets and test == "watertight" and \
                        kernel != "TriAny1x4" and vals[0] is not None:
                    if best_avx3 is None or vals[0] < best_avx3[2]:
                        best_avx3 = (f"{label}, {tris} triangles", targets[0], vals[0])
    lines.append("")
    if "tri_test" not in goals:
        goals["tri_test"] = best_avx3


def packet_tables(data, lines):
    r = rows(data)
    targets, scenes = [], []
    for n in r:
        m = re.match(r"^Packet/([^/]+)/([^/]+)/", n)
        if m:
            if m.group(1) not in targets:
                targets.append(m.group(1))
            if m.group(2) not in scenes:
                scenes.append(m.group(2))
    lines.append("### Coherent 64-ray packets vs the per-ray stream DDA, per target (packet_bench)\n")
    lines.append("Same rays as above (1024x1024 primary rays in scanline order, one shadow ray per "
                 "primary hit), same grid; each cell: CPU rdtsc ticks per ray, packets / per-ray "
                 "(ratio < 1: packets faster); share = packets traced as packets (the rest are "
                 "refused up front and traced per ray). Results validated identical first.\n")
    lines.append("| scene | set | share | " + " | ".join(targets) + " |")
    lines.append("|---|---|---:|" + "---:|" * len(targets))
    for scene in scenes:
        for group in ["primary", "shadow"]:
            cells = []
            share = None
            for t in targets:
                a = r.get(f"Packet/{t}/{scene}/{group}")
                b = r.get(f"PerRay/{t}/{scene}/{group}")
                pa, pb = counter(a, "cpu_ticks/ray"), counter(b, "cpu_ticks/ray")
                if share is None:
                    share = counter(a, "packet_share")
                cells.append(f"{pa:.0f} / {pb:.0f} = {pa / pb:.2f}" if pa and pb else "n/a")
            lines.append(f"| {scene} | {group} | {fmt(share)} | " + " | ".join(cells) + " |")
    lines.append("")


def goals_section(goals, lines):
    lines.append("## Where the kernel goals stand (this run)\n")
    lines.append("| goal | measured | met |")
    lines.append("|---|---|---|")

    def worst(items):
        items = [(s, v) for s, v in items if v is not None]
        return min(items, key=lambda x: x[1]) if items else (None, None)

    def span(items):
        vals = [v for _, v in items if v is not None]
        return f"{min(vals):.2f} – {max(vals):.2f}" if vals else "n/a"

    s, v = worst(goals.get("primary", []))
    lines.append(f"| primary rays ≥ Embree (best mode) | ÷ best Embree {span(goals.get('primary', []))}"
                 f" (worst {s}) | {'yes' if v is not None and v >= 1 else 'no'} |")
    s, v = worst(goals.get("diffuse", []))
    lines.append(f"| diffuse rays ≥ 0.6x Embree | ÷ best Embree {span(goals.get('diffuse', []))}"
                 f" (worst {s}) | {'yes' if v is not None and v >= 0.6 else 'no'} |")
    s, v = worst(goals.get("frame", []))
    lines.append(f"| time to image ≥ 2x faster than Embree | ÷ best Embree "
                 f"{span(goals.get('frame', []))} (worst {s}) | "
                 f"{'yes' if v is not None and v >= 2 else 'no'} |")
    s, v = worst(goals.get("build", []))
    lines.append(f"| grid build ≥ 50 Mtris/s | {span(goals.get('build', []))} Mtris/s (one thread) "
                 f"| {'yes' if v is not None and v >= 50 else 'no'} |")
    t, v = goals.get("dda_step", ("?", None))
    lines.append(f"| ≤ 2 cycles per ray-cell step (AVX-512) | {fmt(v, '.1f')} rdtsc ticks per "
                 f"empty-cell step ({t}, step_bench) | "
                 f"{'yes' if v is not None and v <= 2 else 'no'} |")
    b = goals.get("tri_test")
    lines.append(f"| ≤ 1.5 cycles per ray/triangle test (AVX-512) | "
                 f"{fmt(b[2] if b else None, '.2f')} rdtsc ticks per test ({b[1] if b else '?'}"
                 f", best closest-hit row: {b[0] if b else 'n/a'}) | "
                 f"{'yes' if b and b[2] <= 1.5 else 'no'} |")
    lines.append("")
    lines.append("\"Cycles\" here are rdtsc reference ticks of CPU time (the TSC runs at a "
                 f"constant {goals.get('tsc_ghz', '?')} GHz), not core cycles: hardware performance counters are not "
                 "available on these machines (KVM guest without a PMU; `perf stat -e cycles` "
                 "says `<not supported>`). Instruction counts: callgrind.md.\n")


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--trace", required=True)
    p.add_argument("--dda", required=True)
    p.add_argument("--tri", required=True)
    p.add_argument("--robust")
    p.add_argument("--packet", help="packet_bench JSON (packets vs per-ray walk)")
    p.add_argument("--step", help="step_bench JSON (one DDA step, one triangle test)")
    p.add_argument("--commands")
    p.add_argument("--preamble", help="markdown inserted after the title")
    p.add_argument("--out", required=True)
    a = p.parse_args()
    trace = load(a.trace)
    ctx = trace["context"]
    lines = ["# raystream vs Embree 3, and kernel cycles per target\n"]
    if a.preamble:
        with open(a.preamble) as f:
            lines.append(f.read().rstrip() + "\n")
    lines.append(f"Session: trace_bench {ctx.get('date', '?')}, {ctx.get('num_cpus')} CPUs, "
                 f"load average {', '.join(f'{x:.1f}' for x in ctx.get('load_avg', []))} at "
                 f"its start; Embree {ctx.get('embree', '?')}; ray sets {ctx.get('ray_sets', '?')};"
                 f" tsc_ghz {ctx.get('tsc_ghz', '?')}.\n")
    goals = {"tsc_ghz": ctx.get("tsc_ghz", "?")}
    body = []
    trace_tables(trace, body, goals)
    if a.step:
        step_tables(load(a.step), body, goals)
    dda_tables(load(a.dda), body, goals)
    tri_tables(load(a.tri), body, goals)
    if a.packet:
        packet_tables(load(a.packet), body)
    goals_section(goals, lines)
    lines.append("## Results\n")
    lines += body
    if a.robust:
        with open(a.robust) as f:
            text = f.read()
        lines.append("## Robustness at 1e6 rays (robust_bench)\n")
        lines.append("```")
        lines.append(text.rstrip())
        lines.append("```\n")
    if a.commands:
        with open(a.commands) as f:
            lines.append("## Commands\n")
            lines.append("```")
            lines.append(f.read().rstrip())
            lines.append("```\n")
    with open(a.out, "w") as f:
        f.write("\n".join(lines))


if __name__ == "__main__":
    main()
