#!/usr/bin/env python3
"""Tables (results.md) and plots (PNG) from the CSV files bench/sched/sched_bench writes.

usage: sched_plot.py RESULTS_DIR

Optional tooling: needs only the standard library for the tables; the plots need matplotlib
(Debian: python3-matplotlib) and are skipped with a note when it is missing. Never used by tests.
"""
import csv
import os
import sys
from collections import defaultdict


def read(path):
    if not os.path.exists(path):
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def num(row, key):
    try:
        return float(row[key])
    except (KeyError, ValueError):
        return float("nan")


def md_table(header, rows):
    out = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    for r in rows:
        out.append("| " + " | ".join(str(c) for c in r) + " |")
    return "\n".join(out) + "\n"


def main():
    if len(sys.argv) != 2:
        print(__doc__)
        return 2
    d = sys.argv[1]
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        plt = None

    meta = open(os.path.join(d, "meta.txt")).read() if os.path.exists(os.path.join(d, "meta.txt")) else ""
    md = ["# Host schedulers: measurements\n", "```\n" + meta + "```\n"]
    md.append(
        "**This machine has 2 cores. Runs with 4 and 8 render threads oversubscribe it**: their "
        "threads time-share the two cores, so their speed-up cannot exceed ~2 and their idle "
        "times include waiting for a core. Other processes shared the machine while these ran "
        "(load average in the tables), so wall-clock figures are noisy.\n"
    )
    figures = []

    # --- iRT Figs. 3-7 --------------------------------------------------------------------
    scaling = read(os.path.join(d, "scaling.csv"))
    if scaling:
        md.append("\n## fps and speed-up against threads (iRT Figs. 3-5), 300x300, depth 4\n")
        md.append(
            "Every configuration renders the same frame; rounds interleave all configurations "
            "(one warm-up round, then the median of 3 frames). Two figures per run:\n\n"
            "* **measured**: wall-clock frame time and speed-up against the serial renderer. On "
            "this shared machine it mostly measures the CPU share the OS gave the run (column "
            "cpu = process CPU time / wall time = cores actually obtained), not the scheduler.\n"
            "* **contention-free estimate** (est): the frame time on an idle machine with a core "
            "per thread, from per-thread CPU times: application CPU (primary generation) + "
            "max(slowest thread's CPU, all threads' CPU / 2 cores). Spinning on an EMPTY queue "
            "counts as work; barrier wake-ups and memory bandwidth are not modelled. "
            "work = total CPU / serial CPU (overhead of queues, spinning, cache effects).\n\n"
            "idle = time per thread per frame at the closing barrier (Fig. 6); queue = time in queue "
            "operations summed over threads per frame (Fig. 7; for TILES32 the tile counter).\n\n")
        rows = []
        for r in scaling:
            rows.append([r["scene"], r["backend"], r["threads"], "%.1f" % num(r, "median_ms"),
                         "%.2f" % num(r, "speedup"), "%.2f" % num(r, "cpu_utilization"),
                         "%.1f" % num(r, "est_ms"), "%.2f" % num(r, "est_fps"),
                         "%.2f" % num(r, "est_speedup"), "%.0f %%" % (100 * num(r, "est_efficiency")),
                         "%.2f" % num(r, "work_inflation"),
                         "%.2f" % num(r, "idle_ms_per_thread"), "%.3f" % num(r, "queue_ms_aggregate"),
                         "%.3f" % num(r, "imbalance")])
        md.append(md_table(["scene", "backend", "threads", "measured ms", "measured speed-up", "cpu",
                            "est ms", "est fps", "est speed-up", "est efficiency", "work",
                            "idle ms/thread", "queue ms (sum)", "imbalance"], rows))
        eff2 = [r for r in scaling if r["threads"] == "2" and r["backend"] != "serial"]
        if eff2:
            md.append("\n**Parallel efficiency at 2 threads** (speed-up vs serial / 2; "
                      "contention-free estimate, in brackets measured): " + "; ".join(
                "%s %s %.0f %% (%.0f %%)" % (r["scene"], r["backend"], 100 * num(r, "est_efficiency"),
                                           100 * num(r, "efficiency")) for r in eff2) + ".\n")
        if plt:
            scenes = list(dict.fromkeys(r["scene"] for r in scaling))
            backends = ["LOCK", "LFREE", "LOCAL", "TILES32"]
            fig, axes = plt.subplots(1, len(scenes), figsize=(5.4 * len(scenes), 4.4), squeeze=False)
            for ax, scene in zip(axes[0], scenes):
                rs = [r for r in scaling if r["scene"] == scene]
                threads = sorted({int(r["threads"]) for r in rs if r["backend"] != "serial"})
                ax2 = ax.twinx()
                width = 0.8 / len(backends)
                for i, b in enumerate(backends):
                    pts = {int(r["threads"]): r for r in rs if r["backend"] == b}
                    xs = [t for t in threads if t in pts]
                    line, = ax.plot(range(len(xs)), [num(pts[t], "est_fps") for t in xs], marker="o", label=b)
                    ax2.bar([j + (i - 1.5) * width for j in range(len(xs))],
                            [num(pts[t], "est_speedup") for t in xs], width=width, alpha=0.3,
                            color=line.get_color())
                    ax2.plot([j + (i - 1.5) * width for j in range(len(xs))],
                             [num(pts[t], "speedup") for t in xs], ls="none", marker="x",
                             color=line.get_color())
                serial = [r for r in rs if r["backend"] == "serial"]
                if serial:
                    ax.axhline(num(serial[0], "est_fps"), color="gray", ls="--", lw=1, label="serial")
                ax.set_xticks(range(len(threads)))
                ax.set_xticklabels([str(t) + ("*" if t > 2 else "") for t in threads])
                ax.set_xlabel("threads (* = oversubscribed: 2 cores)")
                ax.set_ylabel("fps, contention-free estimate (lines)")
                ax2.set_ylabel("speed-up vs serial: est (bars), measured (x)")
                ax.set_title(scene)
                ax.legend(fontsize=8, loc="upper left")
            fig.suptitle("fps and speed-up against threads (iRT Figs. 3-5), 2-core shared machine")
            fig.tight_layout()
            fig.savefig(os.path.join(d, "scaling.png"), dpi=90)
            plt.close(fig)
            figures.append("scaling.png")

            for key, name, title, ylabel in [
                    ("idle_ms_per_thread", "idle.png", "idle time per thread per frame at the barrier (Fig. 6)", "ms"),
                    ("queue_ms_aggregate", "queue.png", "aggregate queue access time per frame (Fig. 7)", "ms (sum over threads)")]:
                fig, axes = plt.subplots(1, len(scenes), figsize=(5.2 * len(scenes), 3.8), squeeze=False)
                for ax, scene in zip(axes[0], scenes):
                    rs = [r for r in scaling if r["scene"] == scene and r["backend"] != "serial"]
                    threads = sorted({int(r["threads"]) for r in rs})
                    width = 0.8 / len(backends)
                    for i, b in enumerate(backends):
                        pts = {int(r["threads"]): r for r in rs if r["backend"] == b}
                        ax.bar([j + (i - 1.5) * width for j in range(len(threads))],
                               [num(pts[t], key) if t in pts else 0 for t in threads], width=width, label=b)
                    ax.set_xticks(range(len(threads)))
                    ax.set_xticklabels([str(t) + ("*" if t > 2 else "") for t in threads])
                    ax.set_xlabel("threads (* = oversubscribed)")
                    ax.set_ylabel(ylabel)
                    ax.set_title(scene)
                    if key == "queue_ms_aggregate":
                        ax.set_yscale("symlog", linthresh=0.01)
                    ax.legend(fontsize=8)
                fig.suptitle(title)
                fig.tight_layout()
                fig.savefig(os.path.join(d, name), dpi=90)
                plt.close(fig)
                figures.append(name)

    per_thread = read(os.path.join(d, "idle_threads.csv"))
    if per_thread:
        md.append("\n### Idle time per thread (ms per frame), highest thread count\n\n")
        top = max(int(r["threads"]) for r in per_thread)
        groups = defaultdict(list)
        for r in per_thread:
            if int(r["threads"]) == top:
                groups[(r["scene"], r["backend"])].append("%.2f" % num(r, "idle_ms"))
        md.append(md_table(["scene", "backend", "idle ms per thread (thread 0, 1, ...)"],
                           [[k[0], k[1], " ".join(v)] for k, v in groups.items()]))

    # --- Cell Fig. 3 ----------------------------------------------------------------------
    tiles = read(os.path.join(d, "tiles.csv"))
    if tiles:
        t0 = tiles[0]
        md.append("\n## Tile size and shape (Cell paper Fig. 3): %s %sx%s, %s threads, tile counter\n\n"
                  % (t0["scene"], t0["width"], t0["height"], t0["threads"]))
        md.append("est = contention-free frame time (see above); tile CPU = mean CPU time per tile "
                  "(coherence and memory effects of the shape, robust to other load).\n\n")
        md.append(md_table(["shape", "family", "tiles", "measured ms", "est ms", "tile CPU ms",
                            "counter us/frame", "idle ms/thread", "imbalance"],
                           [[r["shape"], r["family"], r["tiles"], "%.1f" % num(r, "median_ms"),
                             "%.1f" % num(r, "est_ms"), "%.3f" % num(r, "mean_tile_cpu_ms"),
                             "%.1f" % num(r, "counter_us_per_frame"), "%.2f" % num(r, "idle_ms_per_thread"),
                             "%.3f" % num(r, "imbalance")] for r in tiles]))
        if plt:
            fig, ax = plt.subplots(figsize=(8, 3.8))
            colors = {"square": "tab:blue", "1280px": "tab:red", "row": "tab:gray"}
            ax.bar(range(len(tiles)), [num(r, "est_ms") for r in tiles],
                   color=[colors.get(r["family"], "k") for r in tiles])
            ax.plot(range(len(tiles)), [num(r, "median_ms") for r in tiles], "kx", label="measured (wall)")
            ax.set_xticks(range(len(tiles)))
            ax.set_xticklabels([r["shape"] for r in tiles], rotation=30)
            ax.set_ylabel("ms per frame (bars: contention-free est)")
            ax.legend(fontsize=8)
            ax.set_title("tile shapes (blue: squares, red: 1280-pixel tiles, gray: single rows)")
            fig.tight_layout()
            fig.savefig(os.path.join(d, "tiles.png"), dpi=90)
            plt.close(fig)
            figures.append("tiles.png")

    # --- PBT Table 1 and imbalance ----------------------------------------------------------
    # The Table 1 rows are the tiles backend's (older tables have no backend column); queue
    # backend rows (sched_bench --pbt-backends) are listed in pbt.csv only.
    pbt = [r for r in read(os.path.join(d, "pbt.csv")) if (r.get("backend") or "tiles") == "tiles"]
    if pbt:
        p0 = pbt[0]
        meta_pbt = os.path.join(d, "meta_pbt.txt")
        md.append("\n## PBT prediction accuracy (PBT paper Table 1): %s %sx%s walk-through, n = %s PBT workers "
                  "on %s threads, %s predicted frames\n\n" % (p0["scene"], p0["size"], p0["size"], p0["workers"],
                                                            p0["threads"], p0["frames"]))
        if os.path.exists(meta_pbt):
            md.append("```\n" + open(meta_pbt).read() + "```\n\n")
        md.append("Share of tile predictions within 5 / 10 / 15 % of the tile's measured cost. cost = what "
                  "PBT-Update is fed and predictions are checked against: work (the deterministic count of "
                  "the tile's rays, cell steps, triangle tests and shading calls, sched/tile_plan.h: the same "
                  "numbers in every run, whatever the load), cpu (the rendering thread's CPU time), wall "
                  "(wall-clock, the paper's; these runs shared the machine with other processes). x1 / x2: "
                  "the camera speed along the scene's walk-through (x2 covers the same path in half the "
                  "frames). With the work cost the accuracy does not depend on the assignment; static = the "
                  "initial tiling kept, predicted by the same tile's previous cost (no split or merge).\n\n")
        paper = {("1", "1"): (96.2, 93.2, 92.6), ("1", "2"): (95.3, 92.0, 84.0),
                 ("4", "1"): (92.1, 86.2, 68.0), ("4", "2"): (89.7, 79.8, 55.0)}

        batches = list(dict.fromkeys(r.get("batch", "1024") for r in pbt))

        # PBT-Update's predictor (--pbt-predict; older tables have the paper's only). static is never
        # updated: its row is whichever predictor ran it.
        predicts = list(dict.fromkeys(r.get("predict") or "paper" for r in pbt))
        best = "costmap" if "costmap" in predicts else predicts[0]

        def pick(cost, assign, k, speed, batch, predict=None):
            if predict is None and assign != "static":
                predict = best
            m = [r for r in pbt if r["clock"] == cost and r["assign"] == assign and r["k"] == k
                 and r["speed"].rstrip("0").rstrip(".") == speed and r.get("batch", "1024") == batch
                 and (predict is None or (r.get("predict") or "paper") == predict)]
            return m[0] if m else None

        md.append("batch = rays per kernel call (--batch): the default 1024 traces coherent 64-ray packets, "
                  "which makes a tile's cost change more from frame to frame (a packet that an edge moves "
                  "into is traced ray by ray instead); 20 (the iRT paper's) traces ray by ray, like the PBT "
                  "paper's tracer.\n\n")
        rows = []
        for batch in batches:
            for (k, speed), (p15, p10, p5) in paper.items():
                row = [batch, "k=%s x%s" % (k, speed), "%.1f / %.1f / %.1f %%" % (p5, p10, p15)]
                for cost in ("work", "cpu", "wall"):
                    r = pick(cost, "random", k, speed, batch)
                    row.append("%.1f / %.1f / %.1f %%" % (100 * num(r, "within5"), 100 * num(r, "within10"),
                                                          100 * num(r, "within15")) if r else "-")
                r = pick("work", "static", k, speed, batch)
                row.append("%.1f %%" % (100 * num(r, "within10")) if r else "-")
                r = pick("work", "random", k, speed, batch, "paper") if best != "paper" else None
                row.append("%.1f / %.1f / %.1f %%" % (100 * num(r, "within5"), 100 * num(r, "within10"),
                                                      100 * num(r, "within15")) if r else "-")
                rows.append(row)
        md.append("Within 5 / 10 / 15 %% (PBT-Random, predictor %s; the paper's rows 95th / 90th / 85th "
                  "percentile; last column: the paper's predictor, split halves e/2):\n\n" % best)
        md.append(md_table(["batch", "config", "paper", "work", "cpu", "wall", "work, static tiling (10 %)",
                            "work, paper's predictor"], rows))
        imb = []
        for batch in batches:
            for assign in ("static", "random", "greedy", "visit", "counter"):
                row = [batch, assign]
                for speed in ("1", "2"):
                    r = pick("work", assign, "4", speed, batch)
                    row += ["%.3f" % num(r, "worker_imbalance") if r else "-",
                            "%.3f" % num(r, "demand_imbalance") if r else "-",
                            "%.3f" % num(r, "lpt_imbalance") if r and r.get("lpt_imbalance") else "-"]
                imb.append(row)
        md.append("\nImbalance with k = 4, work cost (slowest / mean of the 32 workers' measured costs): lists = "
                  "each worker renders its own list (no stealing); demand = the paper's demand-driven "
                  "master-worker (§2, with the §4 affinity: a worker done with its list takes the last waiting "
                  "tile of the most loaded one) on the same costs; counter (not in the paper) = no lists, "
                  "the workers take the tiles costliest-predicted first; lpt (not in the paper, a model) = "
                  "static lists by LPT over the frame's predictions, no stealing, charged the measured "
                  "costs.\n\n")
        md.append(md_table(["batch", "assign", "x1 lists", "x1 demand", "x1 lpt", "x2 lists", "x2 demand",
                            "x2 lpt"], imb))
        rows = []
        for r in pbt:
            rows.append([r.get("batch", ""), r["clock"], r.get("predict") or "paper", r["assign"], r["k"],
                         "x" + r["speed"].rstrip("0").rstrip("."),
                         "%.1f %%" % (100 * num(r, "within5")), "%.1f %%" % (100 * num(r, "within10")),
                         "%.1f %%" % (100 * num(r, "within15")), "%.3f" % num(r, "worker_imbalance"),
                         "%.3f" % num(r, "demand_imbalance"), "%.1f" % num(r, "update_steps"),
                         r.get("load_avg", "")])
        md.append("\nAll runs:\n\n")
        md.append(md_table(["batch", "cost", "predict", "assign", "k", "speed", "within 5 %", "within 10 %", "within 15 %",
                            "imbalance lists", "imbalance demand", "split-merge steps", "load"], rows))
        if plt:
            fig, axes = plt.subplots(1, 2, figsize=(11, 4))
            configs = [("1", "1"), ("1", "2"), ("4", "1"), ("4", "2")]
            series = [("paper", None, None)] + [("%s b%s" % (c, b), c, b) for b in batches
                                                for c in ("work", "cpu", "wall")]
            width = 0.8 / len(series)
            for i, (label, cost, batch) in enumerate(series):
                vals = []
                for k, speed in configs:
                    if cost is None:
                        vals.append(paper[(k, speed)][1])
                    else:
                        r = pick(cost, "random", k, speed, batch)
                        vals.append(100 * num(r, "within10") if r else 0)
                axes[0].bar([j + (i - (len(series) - 1) / 2) * width for j in range(len(configs))], vals,
                            width=width, label=label)
            axes[0].set_xticks(range(len(configs)))
            axes[0].set_xticklabels(["k=%s x%s" % c for c in configs])
            axes[0].set_ylabel("% of tile predictions within 10 %")
            axes[0].set_title("PBT prediction accuracy (Table 1, PBT-Random)")
            axes[0].legend(fontsize=8)
            assigns = ["static", "random", "greedy", "visit", "counter"]
            for i, a in enumerate(assigns):
                vals = []
                for k, speed in configs:
                    r = pick("work", a, k, speed, batches[0])
                    vals.append(num(r, "demand_imbalance") if r else 0)
                axes[1].bar([j + (i - 2) * 0.16 for j in range(len(configs))], vals, width=0.16, label=a)
            axes[1].axhline(1.10, color="gray", lw=0.8, ls="--")
            axes[1].set_xticks(range(len(configs)))
            axes[1].set_xticklabels(["k=%s x%s" % c for c in configs])
            axes[1].set_ylabel("slowest / mean worker (demand driven)")
            axes[1].set_ylim(bottom=1.0)
            axes[1].set_title("frame imbalance, work cost, batch %s: static tiling vs PBT" % batches[0])
            axes[1].legend(fontsize=8)
            fig.tight_layout()
            fig.savefig(os.path.join(d, "pbt.png"), dpi=90)
            plt.close(fig)
            figures.append("pbt.png")

    cal = os.path.join(d, "calibrate.txt")
    if os.path.exists(cal):
        md.append("\n## Calibration of the deterministic tile cost (sched/tile_plan.h kTileWorkCoefficients)\n\n")
        md.append("Least squares (non-negative, no intercept) of each tile's CPU time against its counts; one "
                  "row per tile in calibrate.csv.\n\n```\n" + open(cal).read() + "```\n")

    amph = read(os.path.join(d, "amphitheater.csv"))
    if amph:
        md.append("\n## PBT-Greedy / PBT-Visit vs PBT-Random (PBT paper Fig. 4)\n\n")
        md.append("2 threads = 2 PBT workers, k tiles each, walk-through frames; tile CPU = mean CPU "
                  "time per tile (what locality would lower); +steal = demand-driven with affinity.\n\n")
        md.append(md_table(["scene", "triangles", "assign", "k", "measured ms/frame", "est ms/frame",
                            "tile ms", "tile CPU ms", "imbalance (workers)", "imbalance (threads)"],
                           [[r["scene"], r["triangles"], r["assign"] + ("+steal" if r.get("steal") == "1" else ""),
                             r["k"], "%.2f" % num(r, "median_ms"), "%.2f" % num(r, "est_ms"),
                             "%.3f" % num(r, "mean_tile_ms"), "%.3f" % num(r, "mean_tile_cpu_ms"),
                             "%.3f" % num(r, "worker_imbalance"), "%.3f" % num(r, "thread_imbalance")]
                            for r in amph]))
        if plt:
            scenes = list(dict.fromkeys(r["scene"] for r in amph))
            fig, axes = plt.subplots(1, len(scenes), figsize=(5 * len(scenes), 3.6), squeeze=False)
            for ax, s in zip(axes[0], scenes):
                rs = [r for r in amph if r["scene"] == s]
                ax.bar([r["assign"] + ("+steal" if r.get("steal") == "1" else "") for r in rs],
                       [num(r, "mean_tile_cpu_ms") for r in rs],
                       color=["gray", "tab:blue", "tab:green", "tab:orange", "tab:olive", "tab:brown"][: len(rs)])
                ax.tick_params(axis="x", labelrotation=30)
                ax.set_ylabel("CPU ms per tile (mean)")
                ax.set_title("%s (%s triangles)" % (s, rs[0]["triangles"]))
            fig.suptitle("locality-aware PBT assignment, 2 threads")
            fig.tight_layout()
            fig.savefig(os.path.join(d, "amphitheater.png"), dpi=90)
            plt.close(fig)
            figures.append("amphitheater.png")

    if plt is None:
        md.append("\n(matplotlib not available: no plots. Debian: apt-get install python3-matplotlib)\n")
    else:
        md.append("\n## Plots\n\n" + "".join("![%s](%s)\n" % (f, f) for f in figures))
    with open(os.path.join(d, "results.md"), "w") as f:
        f.write("\n".join(md))
    print("wrote %s/results.md%s" % (d, "" if plt is None else " and " + ", ".join(figures)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
