#!/usr/bin/env python3
"""Plots the CSV tables of bench/cell_bench.cc (Cell simulator reproductions) as small PNGs.

usage: plot_cell.py RESULTS_DIR   (reads loads/speedup/tiles/microcache/atonce/depth/build.csv)
"""
import csv
import os
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def read(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def save(fig, out, name):
    fig.tight_layout()
    fig.savefig(os.path.join(out, name), dpi=90)
    plt.close(fig)
    print("wrote", os.path.join(out, name))


def loads(out):
    rows = read(os.path.join(out, "loads.csv"))
    names = [r["method"] for r in rows]
    x = range(len(rows))
    fig, ax = plt.subplots(figsize=(6, 3.4))
    ax.bar([i - 0.2 for i in x], [float(r["paper_cycles"]) for r in rows], 0.4, label="paper (Table 1)")
    ax.bar([i + 0.2 for i in x], [float(r["simulated_cycles"]) for r in rows], 0.4, label="simulated")
    ax.set_xticks(list(x), names)
    ax.set_ylabel("cycles to load 8 bytes")
    ax.legend()
    save(fig, out, "loads.png")


def speedup(out):
    rows = read(os.path.join(out, "speedup.csv"))
    fig, ax = plt.subplots(figsize=(5, 3.6))
    for scene in dict.fromkeys(r["scene"] for r in rows):
        rs = [r for r in rows if r["scene"] == scene]
        ax.plot([int(r["spes"]) for r in rs], [float(r["speedup"]) for r in rs], "o-", label=scene)
    n = max(int(r["spes"]) for r in rows)
    ax.plot([1, n], [1, n], "k:", label="linear")
    ax.axvline(6, color="grey", lw=0.5)
    ax.set_xlabel("SPEs")
    ax.set_ylabel("speed-up")
    ax.set_title("Fig. 2: speed-up (simulated)")
    ax.legend()
    save(fig, out, "speedup.png")


def tiles(out):
    rows = read(os.path.join(out, "tiles.csv"))
    shapes = list(dict.fromkeys(r["tile"] for r in rows))
    group = {r["tile"]: r["group"] for r in rows}
    fig, ax = plt.subplots(figsize=(7, 3.6))
    for k, variant in enumerate(("drain", "overlap")):
        ms = {r["tile"]: float(r["simulated_ms"]) for r in rows if r["variant"] == variant}
        colors = ["tab:blue" if group[t] == "square" else "tab:red" for t in shapes]
        ax.bar([i + (k - 0.5) * 0.4 for i in range(len(shapes))], [ms[t] for t in shapes], 0.4,
               color=colors, alpha=1.0 if k == 0 else 0.45,
               label="tile ends drain the pipeline" if k == 0 else "tiles overlap")
    ax.set_xticks(range(len(shapes)), shapes, rotation=30)
    lo = min(float(r["simulated_ms"]) for r in rows)
    ax.set_ylim(lo * 0.9, None)
    ax.set_ylabel("simulated frame time (ms)")
    ax.set_title("Fig. 3: squares (blue), 1280-pixel shapes (red)")
    ax.legend(fontsize=8)
    save(fig, out, "tiles.png")


def microcache(out):
    rows = read(os.path.join(out, "microcache.csv"))
    fig, ax = plt.subplots(figsize=(6, 3.4))
    labels = [f'{r["scene"]}\ndepth {r["depth"]}' for r in rows]
    ax.bar(range(len(rows)), [float(r["speedup_pct"]) for r in rows])
    ax.set_xticks(range(len(rows)), labels)
    ax.set_ylabel("speed-up from the micro-cache (%)")
    ax.axhline(0, color="k", lw=0.5)
    save(fig, out, "microcache.png")


def atonce(out):
    rows = read(os.path.join(out, "atonce.csv"))
    fig, ax = plt.subplots(figsize=(6, 3.4))
    labels = [f'{r["scene"]}\n{r["grid"]}\ndepth {r["depth"]}' for r in rows]
    ax.axhspan(1, 7, color="tab:green", alpha=0.25, zorder=0, label="paper 3.7: 1 to 7 %")
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
    fig, ax = plt.subplots(figsize=(5, 3.6))
    ax.plot(d, [float(r["uniform_ms"]) for r in rows], "o-", label="uniform grid")
    ax.plot(d, [float(r["two_level_ms"]) for r in rows], "s-", label="two-level grid")
    ax.set_xlabel("recursion depth")
    ax.set_ylabel("simulated frame time (ms)")
    ax.set_title("Fig. 8: spherebox")
    ax.legend()
    save(fig, out, "depth.png")


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
    ax.legend(fontsize=8)
    save(fig, out, "build.png")


def main():
    out = sys.argv[1] if len(sys.argv) > 1 else "bench/results/cell"
    for f in (loads, speedup, tiles, microcache, atonce, depth, build):
        name = f.__name__ + ".csv"
        if os.path.exists(os.path.join(out, name)):
            f(out)


if __name__ == "__main__":
    main()
