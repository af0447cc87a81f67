#!/usr/bin/env python3
"""Summary (summary.md) and plot (mpi.png) of bench/scripts/mpi_bench.sh: frames per second, imbalance,
messages and bytes per worker count and tiling, and the PBT paper's prediction-accuracy table
(Cosenza et al., Table 1) from the tile times the MPI workers measured.

usage: plot_mpi.py OUT_DIR [--plot | --no-plot]   (reads OUT_DIR/mpi_bench.csv, OUT_DIR/meta.txt)
"""
import collections
import csv
import os
import sys

# The paper's Table 1 (n = 32 workers, modified ERW6, 512x512): share of tile estimates whose
# error is at most 15 % / 10 % / 5 % (its "85th / 90th / 95th percentile" rows).
PAPER = {  # (k, speed) -> (within15, within10, within5)
    (1, 1): (96.2, 93.2, 92.6),
    (1, 2): (95.3, 92.0, 84.0),
    (4, 1): (92.1, 86.2, 68.0),
    (4, 2): (89.7, 79.8, 55.0),
}
LABEL = {"static": "static", "pbt": "PBT-Random", "greedy": "PBT-Greedy", "visit": "PBT-Visit",
         "pbt_x2": "PBT-Random, 2x camera", "pbt_wall": "PBT-Random, wall-time feed"}


def load(out):
    rows = list(csv.DictReader(open(os.path.join(out, "mpi_bench.csv"))))
    meta = {}
    path = os.path.join(out, "meta.txt")
    if os.path.exists(path):
        for line in open(path):
            free = line.startswith(("command:", "binary:"))  # "key: free text"
            key, _, value = line.strip().partition(": " if free else "=")
            if free:
                meta[key] = value
            else:
                for part in line.split():
                    k, _, v = part.partition("=")
                    meta[k] = v
    return rows, meta


def runs(rows):
    """(config, k, workers) -> frames after the first (the first has no PBT prediction)."""
    agg = collections.defaultdict(list)
    for r in rows:
        if int(r["frame"]) > 0:
            agg[(r["config"], int(r["k"]), int(r["workers"]))].append(r)
    return agg


def mean(xs):
    xs = list(xs)
    return sum(xs) / len(xs) if xs else float("nan")


def fps(rs):  # frames / total time
    return 1.0 / mean(float(r["seconds"]) for r in rs)


def model_fps(rs):
    """Frames per second with a dedicated core per worker: 1 / slowest worker's CPU time."""
    return 1.0 / mean(float(r["worker_cpu_max"]) for r in rs)


def pooled(rs, column):
    """Share of predicted tiles within the bound, pooled over frames (weights: tiles)."""
    num = den = 0.0
    for r in rs:
        if r[column] != "" and r["predicted_tiles"] not in ("", "0"):
            n = float(r["predicted_tiles"])
            num += n * float(r[column])
            den += n
    return (100.0 * num / den, int(den)) if den else (float("nan"), 0)


def fmt(x, digits=1):
    return "n/a" if x != x else f"{x:.{digits}f}"


def summary(rows, meta, agg, plotted):
    workers = sorted({w for (_, _, w) in agg})
    ks = sorted({k for (_, k, _) in agg})
    cores = int(meta.get("cores", "2") or 2)
    lines = ["# MPI master-worker backend: scaling, balance, messages, PBT prediction accuracy", ""]
    lines += [
        f"Scene `{meta.get('scene', '?')}` ({meta.get('size', '?')}, "
        f"{meta.get('frames', '?')}-frame"
        f" camera walk-through, depth 4), `raystream render --backend mpi` under `mpirun "
        f"--oversubscribe --bind-to none`; rank 0 is the master, workers = ranks - 1.",
        f"**This machine has {cores} cores, shared with other jobs (1-minute load average "
        f"{meta.get('load_start', '?')} at the start, {meta.get('load_end', '?')} at the end): "
        f"beyond {cores} workers the cores are oversubscribed**, so frames per second cannot grow "
        f"there; the figures measure the protocol and the balance, not a cluster's speed-up.",
        "PBT-Update is fed each tile's worker CPU time "
        f"(`--pbt-time {meta.get('pbt_time', 'cpu')}`);"
        " imbalance (cpu) = slowest worker's CPU time / mean (what dedicated nodes would see), "
        "imbalance (wall) = the same with wall-clock busy times. Means over the frames after the "
        "first (frame 0 has no prediction). Static = the initial equal-area PBT tiles, never "
        "updated; both are demand-driven (an idle worker takes a waiting tile of the most loaded"
        " worker).",
        f"Command: `{meta.get('command', 'bench/scripts/mpi_bench.sh')}`; {meta.get('runs', '?')} runs, "
        f"{meta.get('wall_seconds', '?')} s wall; binary: {meta.get('binary', 'not recorded')}.",
        ""]

    def pivot(title, value, digits, per_worker=()):
        cols = [(c, k) for k in ks for c in ("static", "pbt") if any((c, k, w) in agg
                                                                     for w in workers)]
        head = "| workers | " + " | ".join(f"{LABEL[c]} k={k}" for c, k in cols)
        ratio = [k for k in ks
                 if ("static", k, workers[0]) in agg and ("pbt", k, workers[0]) in agg]
        head += "".join(f" | PBT/static k={k}" for k in ratio)
        head += "".join(f" | {name}" for name, _ in per_worker) + " |"
        out = [f"### {title}", "", head,
               "|" + "---|" * (1 + len(cols) + len(ratio) + len(per_worker))]
        for w in workers:
            cells = [fmt(value(agg[(c, k, w)]), digits) if (c, k, w) in agg else ""
                     for c, k in cols]
            for k in ratio:
                a, b = agg.get(("pbt", k, w)), agg.get(("static", k, w))
                cells.append(fmt(value(a) / value(b), 2) if a and b else "")
            for _, f in per_worker:  # over every configuration run with w workers
                cells.append(f([r for (c, k, w2), rs in agg.items() if w2 == w for r in rs]))
            tag = f"{w}" + (" (oversubscribed)" if w > cores else "")
            out.append(f"| {tag} | " + " | ".join(cells) + " |")
        return out + [""]

    lines += pivot("Frames per second (measured, wall clock)", fps, 2, [
        ("load (1 min)", lambda rs: fmt(mean(float(r["load1"]) for r in rs), 1)),
        ("cores obtained", lambda rs: fmt(mean(float(r["worker_cpu_sum"]) / float(r["seconds"])
                                               for r in rs), 2))])
    lines += ["load: the machine's 1-minute load average as the runs started (other jobs "
              "included); cores obtained: the workers' CPU seconds per wall second (at most "
              f"{cores}). The measured rate follows the CPU share the shared machine gave each "
              "run more than the worker count.", ""]
    mbytes = mean(float(r["bytes"]) for r in rows) / 1e6
    lines += ["Modelled below: the frame rate the same tiles would give with a dedicated core per "
              "worker, 1 / (slowest worker's CPU seconds); it leaves out the master and the "
              f"messages (~{mbytes:.2f} MB per frame here) and is the figure where the tiling's "
              f"balance shows, since on {cores} shared cores the measured rate is the machine's "
              "CPU share.", ""]
    lines += pivot("Frames per second, dedicated-core model", model_fps, 2)
    lines += pivot("Imbalance (cpu): slowest worker / mean",
                   lambda rs: mean(float(r["imbalance_cpu"]) for r in rs), 3)
    lines += pivot("Imbalance (wall): slowest worker / mean",
                   lambda rs: mean(float(r["imbalance_wall"]) for r in rs), 3)
    lines += pivot("Worker idle share of the render span (%)",
                   lambda rs: 100 * mean(float(r["idle_fraction"]) for r in rs), 1)

    lines += ["### Messages and bytes per frame (master <-> workers, both directions)", "",
              "| workers | k | tiles | messages | bytes | bytes/pixel | steals (static) | "
              "steals (PBT) |", "|---|---|---|---|---|---|---|---|"]
    side = meta.get("size", "0x0").split("x")
    pixels = int(side[0]) * int(side[-1]) if side[0].isdigit() else 0
    for w in workers:
        for k in ks:
            rs = agg.get(("pbt", k, w)) or agg.get(("static", k, w))
            if not rs:
                continue
            msgs = mean(float(r["messages"]) for r in rs)
            nbytes = mean(float(r["bytes"]) for r in rs)
            st = [mean(float(r["steals"]) for r in agg[(c, k, w)]) if (c, k, w) in agg else
                  float("nan") for c in ("static", "pbt")]
            lines.append(f"| {w} | {k} | {fmt(mean(float(r['tiles']) for r in rs), 0)} | "
                         f"{fmt(msgs, 0)} | {fmt(nbytes, 0)} | "
                         f"{fmt(nbytes / pixels if pixels else float('nan'), 2)} | "
                         f"{fmt(st[0], 1)} | {fmt(st[1], 1)} |")
    lines += ["", "A tile costs one 24-byte message to the worker and one result of 128 bytes "
              "(the tile's times and statistics) + 24 bytes per pixel (3 int64 fixed-point sums) "
              "back, so bytes grow with pixels, messages with m = k * n. Per run (not in these "
              "per-frame counts) each worker also sends its setup status and its goodbye and "
              "receives the setup outcome and the stop message: 4 messages of 4 bytes.", ""]

    # Table 1.
    extra = sorted({w for (c, _, w) in agg if c == "pbt_x2"})
    lines += ["### Prediction accuracy (the paper's Table 1)", ""]
    if extra:
        lines += [f"Share of tile estimates (PBT-Update from the previous frame's MPI-measured tile"
                  f" times) whose error is within 15 / 10 / 5 % of the measured time (the paper's "
                  f"85th / 90th / 95th rows), PBT-Random, pooled over {', '.join(map(str, extra))}"
                  f" workers and frames 1-{int(meta.get('frames', '2')) - 1}; the paper: 32 "
                  f"workers, 512x512. Measured / paper.", "",
                  "| error within | k=1 x1 | k=1 x2 | k=4 x1 | k=4 x2 |", "|---|---|---|---|---|"]
        for i, (col, name) in enumerate((("within15", "15 % (85th)"), ("within10", "10 % (90th)"),
                                         ("within5", "5 % (95th)"))):
            cells = []
            for k, speed in ((1, 1), (1, 2), (4, 1), (4, 2)):
                config = "pbt" if speed == 1 else "pbt_x2"
                rs = [r for w in extra for r in agg.get((config, k, w), [])]
                share, n = pooled(rs, col)
                cells.append(f"{fmt(share)} % / {PAPER[(k, speed)][i]} % (n={n})")
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
        lines += ["", "Within 10 % by assignment method (1x camera, same pooling):", "",
                  "| assignment | k=1 | k=4 |", "|---|---|---|"]
        for config in ("pbt", "greedy", "visit", "pbt_x2"):
            cells = []
            for k in (1, 4):
                share, n = pooled([r for w in extra for r in agg.get((config, k, w), [])],
                                  "within10")
                cells.append(f"{fmt(share)} % (n={n})")
            lines.append(f"| {LABEL[config]} | " + " | ".join(cells) + " |")
        lines += ["", "Paper, within 10 %: 93.2 % (k=1, 1x camera) and 79.8 % (k=4, 2x camera).",
                  ""]
        if any(("pbt_wall", k, 2) in agg for k in (1, 4)):
            lines += ["Tile time fed to PBT-Update, 2 workers (3 ranks), PBT-Random, within 10 %:",
                      "", "| feed | k=1 | k=4 |", "|---|---|---|"]
            for config, name in (("pbt", "worker CPU time"), ("pbt_wall", "wall clock")):
                cells = []
                for k in (1, 4):
                    share, n = pooled(agg.get((config, k, 2), []), "within10")
                    cells.append(f"{fmt(share)} % (n={n})")
                lines.append(f"| {name} | " + " | ".join(cells) + " |")
            lines += ["", "Wall-clock tile times also count the time a rank waited for a core, "
                      "so they predict worse the more other jobs load the machine; CPU times do "
                      "not (with more ranks than cores, wall times are not used).", ""]
    lines += ["Within 10 % per worker count (PBT-Random, 1x camera):", "",
              "| workers | " + " | ".join(f"k={k}" for k in ks) + " |",
              "|---|" + "---|" * len(ks)]
    for w in workers:
        cells = []
        for k in ks:
            share, n = pooled(agg.get(("pbt", k, w), []), "within10")
            cells.append(f"{fmt(share)} % (n={n})")
        lines.append(f"| {w} | " + " | ".join(cells) + " |")
    if plotted:
        lines += ["", "![fps, imbalance, prediction accuracy, messages and bytes against "
                  "workers](mpi.png)"]
    return "\n".join(lines) + "\n"


def plot(out, meta, agg):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    workers = sorted({w for (_, _, w) in agg})
    ks = sorted({k for (_, k, _) in agg})
    cores = int(meta.get("cores", "2") or 2)
    fig, grid = plt.subplots(2, 3, figsize=(17, 8.6))
    axes = grid.flatten()
    panels = [("frames per second (measured)", fps),
              ("frames per second, dedicated-core model\n(1 / slowest worker's CPU time)",
               model_fps),
              ("imbalance (cpu): slowest / mean worker",
               lambda rs: mean(float(r["imbalance_cpu"]) for r in rs)),
              ("imbalance (wall): slowest / mean worker",
               lambda rs: mean(float(r["imbalance_wall"]) for r in rs)),
              ("share of PBT estimates within 10 % (%)", lambda rs: pooled(rs, "within10")[0])]
    for ax, (ylabel, value) in zip(axes, panels):
        for i, k in enumerate(ks):
            for config, style in (("static", "--"), ("pbt", "-")):
                if config == "static" and "within" in ylabel:
                    continue
                xs = [w for w in workers if (config, k, w) in agg]
                if not xs:
                    continue
                ax.plot(xs, [value(agg[(config, k, w)]) for w in xs], style, marker="o",
                        color=f"C{i}", label=f"{LABEL[config]} k={k}")
        if max(workers) > cores:
            ax.axvspan(cores + 0.5, max(workers) + 0.5, color="0.9", zorder=0)
            ax.text(cores + 0.6, 0.02, f"oversubscribed (> {cores} cores)", fontsize=8,
                    transform=ax.get_xaxis_transform())
        ax.set_xlabel("workers (ranks - 1)")
        ax.set_ylabel(ylabel)
        ax.set_xticks(workers)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    for k, paper in ((1, PAPER[(1, 1)][1]), (4, PAPER[(4, 1)][1])):
        if k in ks:
            axes[4].axhline(paper, color=f"C{ks.index(k)}", lw=0.8, ls=":",
                            label=f"paper k={k}, n=32, 1x camera: {paper} %")
    axes[4].legend(fontsize=8, loc="best")
    # Messages and bytes per frame (both directions, PBT runs; static sends the same): messages
    # (left axis) grow with m = k * n, bytes (right axis) are 24 per pixel plus 152 per tile.
    ax, twin = axes[5], axes[5].twinx()
    for i, k in enumerate(ks):
        xs = [w for w in workers if ("pbt", k, w) in agg]
        if not xs:
            continue
        rs = [agg[("pbt", k, w)] for w in xs]
        ax.plot(xs, [mean(float(r["messages"]) for r in x) for x in rs], "-", marker="o",
                color=f"C{i}", label=f"messages, k={k}")
        twin.plot(xs, [mean(float(r["bytes"]) for r in x) / 1e6 for x in rs], ":", marker="s",
                  color=f"C{i}", alpha=0.7, label=f"MB, k={k}")
    ax.set_ylabel("messages per frame (solid)")
    twin.set_ylabel("MB per frame (dotted)")
    twin.set_ylim(0, twin.get_ylim()[1] * 1.25)
    ax.set_ylim(0, ax.get_ylim()[1] * 1.1)
    ax.set_xlabel("workers (ranks - 1)")
    ax.set_xticks(workers)
    ax.grid(alpha=0.3)
    if max(workers) > cores:
        ax.axvspan(cores + 0.5, max(workers) + 0.5, color="0.9", zorder=0)
    lines0, labels0 = ax.get_legend_handles_labels()
    lines1, labels1 = twin.get_legend_handles_labels()
    ax.legend(lines0 + lines1, labels0 + labels1, fontsize=8, loc="upper left", ncol=2)
    ax.set_title("messages and bytes per frame (master <-> workers)", fontsize=9)
    fig.suptitle(f"raystream --backend mpi, {meta.get('scene', '?')} {meta.get('size', '?')}, "
                 f"{meta.get('frames', '?')}-frame walk-through: static tiling vs PBT\n"
                 f"{cores}-core machine, shared with other jobs (load {meta.get('load_start', '?')}"
                 f" to {meta.get('load_end', '?')}): oversubscribed beyond {cores} workers",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(os.path.join(out, "mpi.png"), dpi=110)


def main():
    out = sys.argv[1]
    want_plot = len(sys.argv) < 3 or sys.argv[2] != "--no-plot"
    rows, meta = load(out)
    agg = runs(rows)
    if want_plot:
        plot(out, meta, agg)
    with open(os.path.join(out, "summary.md"), "w") as f:
        f.write(summary(rows, meta, agg, want_plot))


if __name__ == "__main__":
    main()
