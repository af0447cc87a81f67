#!/usr/bin/env python3
"""Plots the CSV tables of bench/sim/cell_bench.cc (Cell simulator reproductions) as small PNGs, each
beside what the paper (Bingel & Hinkenjann, "Streamed Ray Tracing of Single Rays on the Cell
Processor", shared/papers/streamed-single-ray-tracing-cell.md) reports for it.

The paper gives numbers only in Table 1 (bench/sim/load_cost_bench.cc compares it). For the figures our copy has the captions and the text,
not the plots, so nothing here is read off a figure: every paper value drawn below is a statement
of the text, quoted in the legend or the note under the plot (PAPER holds them, with the section).

usage: plot_cell.py RESULTS_DIR   (reads speedup/tiles/microcache/atonce/depth/build.csv)
"""
import csv
import os
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

# What the paper's text says about each reproduced figure (none of it read off a plot).
PAPER = {
    "fig2": '3.9/Fig. 2: speed-up "nearly linear"; the memory controller "limits the parallel\n'
            'processing by only a few percent" (text only: no values given)',
    "fig3": "3.9/Fig. 3 (text only, no values): 8x8 slow (synchronisation); squares faster up to\n"
            "32x32; 1280-px shapes: line-like better for memory, 640x2 the best trade-off,\n"
            "1280x1 slower (low coherence)",
    "fig3_best": "640x2",
    "fig3_slow": ("8x8", "1280x1"),
    "micro": '3.5: "a speed-up of about 20%" for highly coherent rays, "no drawback" for\n'
             "low-coherent rays (text)",
    "atonce": "3.7: 1 to 7 % (text)",
    "fig8": '4.3/Fig. 8: "Starting at a depth of four, the render times for the grids are stable\n'
            'at 1 second" at 1280x1024 (text; depths 0-3 not given). Right: times relative to\n'
            "depth 9, where the paper's plateau is 1.0",
}


def read(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def note(fig, text):
    fig.text(0.01, 0.005, "paper: " + text, fontsize=6.5, va="bottom", ha="left", color="0.25")


def save(fig, out, name, bottom=0.0):
    fig.tight_layout(rect=(0, bottom, 1, 1))
    fig.savefig(os.path.join(out, name), dpi=90)
    plt.close(fig)
    print("wrote", os.path.join(out, name))


def speedup(out):
    rows = read(os.path.join(out, "speedup.csv"))
    fig, ax = plt.subplots(figsize=(5.6, 4.2))
    n = max(int(r["spes"]) for r in rows)
    # The paper's statement: near the linear line, a few percent below it, over 1..6 SPEs (the
    # band is our reading of "a few percent": 0 to 5 % below linear).
    xs = list(range(1, 7))
    ax.fill_between(xs, [0.95 * x for x in xs], xs, color="tab:green", alpha=0.25,
                    label='paper: "nearly linear", "a few percent" below\n(text; band = 0-5 %)')
    for scene in dict.fromkeys(r["scene"] for r in rows):
        rs = [r for r in rows if r["scene"] == scene]
        ax.plot([int(r["spes"]) for r in rs], [float(r["speedup"]) for r in rs], "o-",
                label=f"simulated, {scene}")
    ax.plot([1, n], [1, n], "k:", lw=0.8, label="linear")
    ax.axvline(6, color="grey", lw=0.5)
    ax.set_xlabel("SPEs")
    ax.set_ylabel("speed-up")
    ax.set_title("Fig. 2: speed-up")
    ax.legend(fontsize=7)
    note(fig, PAPER["fig2"])
    save(fig, out, "speedup.png", bottom=0.08)


def tiles(out):
    rows = read(os.path.join(out, "tiles.csv"))
    shapes = list(dict.fromkeys(r["tile"] for r in rows))
    group = {r["tile"]: r["group"] for r in rows}
    fig, ax = plt.subplots(figsize=(7.4, 4.3))
    for k, variant in enumerate(("drain", "overlap")):
        ms = {r["tile"]: float(r["simulated_ms"]) for r in rows if r["variant"] == variant}
        colors = ["tab:blue" if group[t] == "square" else "tab:red" for t in shapes]
        ax.bar([i + (k - 0.5) * 0.4 for i in range(len(shapes))], [ms[t] for t in shapes], 0.4,
               color=colors, alpha=1.0 if k == 0 else 0.45,
               label="simulated, tile ends drain the pipeline" if k == 0
               else "simulated, tiles overlap")
    lo = min(float(r["simulated_ms"]) for r in rows)
    hi = max(float(r["simulated_ms"]) for r in rows)
    # The paper's ranking (text): its best shape and its slow ones.
    for i, t in enumerate(shapes):
        if t == PAPER["fig3_best"]:
            ax.annotate("paper:\nbest", (i, hi * 1.005), ha="center", fontsize=7,
                        color="tab:green")
        elif t in PAPER["fig3_slow"]:
            ax.annotate("paper:\nslow", (i, hi * 1.005), ha="center", fontsize=7,
                        color="tab:purple")
    ax.set_xticks(range(len(shapes)), shapes, rotation=30)
    ax.set_ylim(lo * 0.9, hi * 1.04)
    ax.set_ylabel("simulated frame time (ms)")
    ax.set_title("Fig. 3: squares (blue), 1280-pixel shapes (red)")
    ax.legend(fontsize=7, loc="lower left")
    note(fig, PAPER["fig3"])
    save(fig, out, "tiles.png", bottom=0.11)


def microcache(out):
    rows = read(os.path.join(out, "microcache.csv"))
    fig, ax = plt.subplots(figsize=(6.4, 3.9))
    labels = [f'{r["scene"]}\ndepth {r["depth"]}\n{r.get("kind", "")}' for r in rows]
    ax.bar(range(len(rows)), [float(r["speedup_pct"]) for r in rows], 0.6, label="simulated")
    first = True
    for i, r in enumerate(rows):
        p = r.get("paper_speedup_pct", "")
        if p == "":
            continue
        ax.plot([i - 0.4, i + 0.4], [float(p)] * 2, color="tab:green", lw=2.5,
                label="paper (text): about +20 % coherent,\nno drawback incoherent" if first
                else None)
        first = False
    ax.set_xticks(range(len(rows)), labels, fontsize=7)
    ax.set_ylabel("speed-up from the micro-cache (%)")
    ax.axhline(0, color="k", lw=0.5)
    ax.legend(fontsize=7)
    ax.set_title("3.5: micro-cache")
    note(fig, PAPER["micro"])
    save(fig, out, "microcache.png", bottom=0.08)


def atonce(out):
    rows = read(os.path.join(out, "atonce.csv"))
    fig, ax = plt.subplots(figsize=(6, 3.4))
    labels = [f'{r["scene"]}\n{r["grid"]}\ndepth {r["depth"]}' for r in rows]
    ax.axhspan(1, 7, color="tab:green", alpha=0.25, zorder=0, label="paper 3.7 (text): 1 to 7 %")
    ax.bar(range(len(rows)), [float(r["speedup_pct"]) for r in rows], 0.6, zorder=2,
           label="simulated")
    ax.set_xticks(range(len(rows)), labels, fontsize=8)
    ax.set_ylabel("speed-up, secondary rays\nintersected at once (%)")
    ax.axhline(0, color="k", lw=0.5)
    ax.legend(fontsize=8)
    save(fig, out, "atonce.png")


def depth(out):
    rows = read(os.path.join(out, "depth.csv"))
    d = [int(r["depth"]) for r in rows]
    uni = [float(r["uniform_ms"]) for r in rows]
    two = [float(r["two_level_ms"]) for r in rows]
    fig, (ax, rel) = plt.subplots(1, 2, figsize=(8.6, 3.9))
    ax.plot(d, uni, "o-", label="simulated, uniform grid")
    ax.plot(d, two, "s-", label="simulated, two-level grid")
    ax.set_xlabel("recursion depth")
    ax.set_ylabel("simulated frame time (ms)")
    ax.set_title("Fig. 8: spherebox")
    ax.legend(fontsize=7)
    rel.plot(d, [u / uni[-1] for u in uni], "o-", label="simulated, uniform grid")
    rel.plot(d, [t / two[-1] for t in two], "s-", label="simulated, two-level grid")
    paper = [(int(r["depth"]), float(r["paper_s"])) for r in rows if r.get("paper_s", "")]
    if paper:
        rel.plot([p[0] for p in paper], [p[1] for p in paper], "D", color="tab:green", ms=7,
                 label='paper (text): grids "stable at 1 second"\nfrom depth 4 (= 1.0 here)')
    rel.set_xlabel("recursion depth")
    rel.set_ylabel("frame time / frame time at depth 9")
    rel.set_ylim(0, 1.15)
    rel.legend(fontsize=7, loc="lower right")
    rel.set_title("relative to depth 9")
    note(fig, PAPER["fig8"])
    save(fig, out, "depth.png", bottom=0.12)


def build(out):
    rows = read(os.path.join(out, "build.csv"))
    fig, ax = plt.subplots(figsize=(7, 3.6))
    x = range(len(rows))
    b = [float(r["build_ms"]) for r in rows]
    lay = [float(r["image_ms"]) for r in rows]
    ren = [float(r["render_ms"]) for r in rows]
    ax.bar(x, b, label="grid build (host)")
    ax.bar(x, lay, bottom=b, label="SPE image layout (host)")
    ax.bar(x, ren, bottom=[i + j for i, j in zip(b, lay)], label="render (simulated)")
    ax.set_xticks(list(x), [r["scene"] for r in rows], rotation=30)
    ax.set_ylabel("ms")
    ax.set_yscale("log")
    ax.set_title("Fig. 6: build and render (paper: no values in the text)", fontsize=9)
    ax.legend(fontsize=8)
    save(fig, out, "build.png")


def main():
    out = sys.argv[1] if len(sys.argv) > 1 else "bench/results/cell"
    for f in (speedup, tiles, microcache, atonce, depth, build):
        name = f.__name__ + ".csv"
        if os.path.exists(os.path.join(out, name)):
            f(out)


if __name__ == "__main__":
    main()
