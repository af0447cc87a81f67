#!/usr/bin/env python3
"""Plots bench/results/shade/depth_sweep.csv (depth_sweep_bench): render time against image error
(RMSE vs the depth-16 cutoff-0 reference, log scale), one line per weight cutoff with the maximum
depth annotated, one panel per scene. Optional: needs matplotlib; never used by the tests.
usage: plot_depth_sweep.py RESULTS_DIR  (reads depth_sweep.csv, writes depth_sweep.png)"""
import csv
import os
import sys

try:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
except ImportError:
    print("plot_depth_sweep.py: matplotlib not available, no plot (tables are in the CSV/MD)")
    sys.exit(0)


def main():
    here = os.path.dirname(__file__)
    out = sys.argv[1] if len(sys.argv) > 1 else os.path.join(here, "..", "results", "shade")
    rows = list(csv.DictReader(open(os.path.join(out, "depth_sweep.csv"))))
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    fig, axes = plt.subplots(1, len(scenes), figsize=(6.5 * len(scenes), 5), squeeze=False)
    for ax, scene in zip(axes[0], scenes):
        cutoffs = list(dict.fromkeys(r["cutoff"] for r in rows if r["scene"] == scene))
        for cutoff in cutoffs:
            pts = sorted(((int(r["max_depth"]), 1e3 * float(r["seconds"]), float(r["rmse"]))
                          for r in rows if r["scene"] == scene and r["cutoff"] == cutoff))
            # RMSE 0 (identical to the reference) cannot be drawn on a log axis: floor it.
            xs = [p[1] for p in pts]
            ys = [max(p[2], 1e-7) for p in pts]
            ax.plot(xs, ys, marker="o", label=f"cutoff {cutoff}")
            for depth, x, y in zip((p[0] for p in pts), xs, ys):
                ax.annotate(str(depth), (x, y), textcoords="offset points", xytext=(4, 3),
                            fontsize=7)
        ax.axhline(0.01, color="grey", linestyle=":", linewidth=1)  # 40 dB at peak 1.0
        ax.text(ax.get_xlim()[0], 0.01, " 40 dB", va="bottom", fontsize=8, color="grey")
        ax.set_yscale("log")
        ax.set_xlabel("render time per frame (ms, serial renderer, thread CPU time)")
        ax.set_ylabel("RMSE vs depth-16 cutoff-0 reference")
        w, h = rows[0]["width"], rows[0]["height"]
        ax.set_title(f"{scene} {w}x{h}: time vs error (labels: max depth)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    fig.tight_layout()
    path = os.path.join(out, "depth_sweep.png")
    fig.savefig(path, dpi=120)
    print("wrote", path)


if __name__ == "__main__":
    main()
