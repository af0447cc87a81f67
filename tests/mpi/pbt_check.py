#!/usr/bin/env python3
"""PBT re-tiling and affinity of an MPI run, checked from its --stats JSON (mpi_test.sh).

Replays the master's PBT (sched/pbt.cc) from the run's own measured tile times: the initial tree
of m = k * n equal-area leaves, then after every frame Algorithm 1 (SetMeasuredTimes + Update)
fed with each tile's wall or CPU seconds as the run chose (--pbt-time). The master's tiling and
the backend's per-tile list owner ("worker") must equal the replay's in every frame:
  - every frame's tiles, in order, are the replayed PBT's leaves (PBT re-tiles between frames;
    static never does);
  - greedy: a tile's owner is its leaf's affinity (§4): the initial runs of k leaves per worker,
    then a leaf that Update did not touch keeps its worker from the previous frame (asserted
    directly on the stats as well), a1 <- worker(a), a2 <- worker(b1), b <- worker(b2), so each
    worker owns exactly k tiles;
  - visit: the owner is floor(n * (P_i + e_i / 2) / E) over the in-order estimates (the stats'
    predicted_seconds; runs of m / n tiles before the first measurement), so owners are
    contiguous, non-decreasing runs along the in-order tiles;
  - random / static: every tile has one owner, floor(m/n) or ceil(m/n) tiles each.
Owners are what the code guarantees; who rendered a tile ("thread") can differ when a worker
done with its own list takes a waiting tile of the most loaded one (a steal, counted).
Doubles are compared exactly: the JSON holds them round-trip, and Python's float arithmetic is
the C++ code's (IEEE double, -ffp-contract=off, same operation order).

usage: pbt_check.py STATS.json [--expect-retile]   prints one line per finding; exit 1 on failure
"""
import json
import math
import sys

KX, KY = 0, 1


class Node:
    __slots__ = ("tile", "parent", "child", "depth", "axis", "estimate", "worker", "touched")

    def __init__(self, tile, parent=None, depth=0):
        self.tile, self.parent, self.child, self.depth = tile, parent, None, depth
        self.axis, self.estimate, self.worker = KX, 0.0, -1
        self.touched = False  # split or merged by the last update (maybe back to its old tile)


def extent(t, axis):
    return t[2] - t[0] if axis == KX else t[3] - t[1]


def cut(t, axis, first):
    x0, y0, x1, y1 = t
    if axis == KX:
        return (x0, y0, x0 + first, y1), (x0 + first, y0, x1, y1)
    return (x0, y0, x1, y0 + first), (x0, y0 + first, x1, y1)


class Pbt:
    """sched/pbt.h Pbt: the same tree, the same choices and ties (in-order first)."""

    def __init__(self, width, height, workers, k):
        self.root_axis = KX if width >= height else KY
        self.root = Node((0, 0, width, height))
        self.build(self.root, workers * k)
        for i, leaf in enumerate(self.leaves()):
            leaf.worker = i // k

    def split_axis(self, n):
        preferred = self.root_axis if n.depth % 2 == 0 else 1 - self.root_axis
        return preferred if extent(n.tile, preferred) >= 2 else 1 - preferred

    def children(self, n, t0, t1, axis):
        n.axis = axis
        n.child = [Node(t0, n, n.depth + 1), Node(t1, n, n.depth + 1)]

    def build(self, n, q):
        if q <= 1:
            return
        axis = self.split_axis(n)
        ext, across = extent(n.tile, axis), extent(n.tile, 1 - axis)
        q1_ideal = q // 2
        x = float(ext) * q1_ideal / float(q)
        first = min(max(int(math.floor(x + 0.5)), 1), ext - 1)  # std::lround, x >= 0
        area0, area1 = first * across, (ext - first) * across
        q1 = min(max(q1_ideal, max(1, q - area1)), min(area0, q - 1))
        t0, t1 = cut(n.tile, axis, first)
        self.children(n, t0, t1, axis)
        self.build(n.child[0], q1)
        self.build(n.child[1], q - q1)

    def leaves(self):
        out, stack = [], [self.root]
        while stack:
            n = stack.pop()
            if n.child is None:
                out.append(n)
            else:
                stack += [n.child[1], n.child[0]]
        return out

    def update(self, times):
        """SetMeasuredTimes + Update (Algorithm 1 with pbt.cc's two deviations); returns steps."""
        for leaf, t in zip(self.leaves(), times):
            leaf.estimate, leaf.touched = t, False
        steps = 0
        m = len(times)
        while True:
            leaves = self.leaves()
            a = None
            for n in leaves:
                if (n.tile[2] - n.tile[0]) * (n.tile[3] - n.tile[1]) < 2:
                    continue
                if a is None or n.estimate > a.estimate:
                    a = n
            if a is None:
                break
            pair, best = None, 0.0
            for n in leaves:
                p = n.parent
                if p is None or p.child[0] is not n or p.child[1].child is not None:
                    continue
                if n is a or p.child[1] is a:
                    continue
                product = n.estimate * p.child[1].estimate
                if pair is None or product < best:
                    pair, best = p, product
            if pair is None or a.estimate * a.estimate <= 4.0 * best:
                break
            if steps >= 16 * m + 64:
                break
            b1, b2 = pair.child
            pair.child = None
            pair.estimate = b1.estimate + b2.estimate
            pair.worker = b2.worker
            pair.touched = a.touched = True
            axis = self.split_axis(a)
            t0, t1 = cut(a.tile, axis, extent(a.tile, axis) // 2)
            self.children(a, t0, t1, axis)
            for c in a.child:
                c.estimate = a.estimate * 0.5
            a.child[0].worker, a.child[1].worker = a.worker, b1.worker
            steps += 1
        return steps


def visit_owners(estimates, n):
    m, total, prefix, out = len(estimates), 0.0, 0.0, []
    for e in estimates:
        total += e
    for i, e in enumerate(estimates):
        if total > 0.0:
            out.append(min(n - 1, int((prefix + 0.5 * e) / total * float(n))))
        else:
            out.append(i * n // m)
        prefix += e
    return out


def main():
    d = json.load(open(sys.argv[1]))
    expect_retile = "--expect-retile" in sys.argv[2:]
    o = d["options"]
    k, n, assign, feed = o["pbt_tiles_per_worker"], o["pbt_workers"], o["assign"], o["pbt_time"]
    frames = d["frames"]
    width = max(t["x1"] for t in frames[0]["tiles"])
    height = max(t["y1"] for t in frames[0]["tiles"])
    pbt = Pbt(width, height, n, k)
    problems = []
    prev = None  # the previous frame's leaves (Node objects) and stats tiles
    for f in frames:
        tiles = f["tiles"]
        leaves = pbt.leaves()
        rects = [(t["x0"], t["y0"], t["x1"], t["y1"]) for t in tiles]
        if rects != [leaf.tile for leaf in leaves]:
            problems.append(f"frame {f['frame']}: tiles are not the replayed PBT's leaves")
            break
        owners = [t["worker"] for t in tiles]
        if assign == "greedy":
            want = [leaf.worker for leaf in leaves]
            if prev is not None:  # untouched leaves keep their worker, seen in the stats alone
                # (a leaf split and merged back in one update has its old tile and a new worker)
                before = {id(leaf): t["worker"] for leaf, t in zip(*prev)}
                kept = [(before[id(leaf)], t["worker"]) for leaf, t in zip(leaves, tiles)
                        if id(leaf) in before and not leaf.touched]
                if any(a != b for a, b in kept):
                    problems.append(f"frame {f['frame']}: a tile Update did not touch moved")
                print(f"frame {f['frame']}: {len(kept)} of {len(tiles)} tiles untouched by "
                      f"PBT-Update, each kept its worker")
        elif assign == "visit":
            est = [t["predicted_seconds"] for t in tiles] if f["frame"] > 0 else [0.0] * len(tiles)
            want = visit_owners(est, n)
            if owners != sorted(owners):
                problems.append(f"frame {f['frame']}: visit owners are not contiguous runs")
        else:
            want = None
        if want is not None and owners != want:
            problems.append(f"frame {f['frame']}: {assign} owners {owners}, expected {want}")
        counts = [owners.count(w) for w in range(n)]
        if assign in ("greedy", "random", "static") and sorted(set(counts)) not in (
                [len(tiles) // n], [len(tiles) // n, -(-len(tiles) // n)]):
            problems.append(f"frame {f['frame']}: tiles per owner {counts}")
        if f["frame"] > 0 and assign != "static":
            est = [t["predicted_seconds"] for t in tiles]
            if est != [leaf.estimate for leaf in leaves]:
                problems.append(f"frame {f['frame']}: predictions are not the replayed estimates")
        stolen = sum(1 for t in tiles if t["thread"] != t["worker"])
        if stolen != sum(w["steals"] for w in f["threads"]):
            problems.append(f"frame {f['frame']}: {stolen} tiles off their owner, steals differ")
        prev = (leaves, tiles)
        if assign != "static":
            steps = pbt.update([t["cpu_seconds" if feed == "cpu" else "seconds"] for t in tiles])
            if steps != f["pbt"]["update_steps"]:
                problems.append(f"frame {f['frame']}: {steps} update steps replayed, "
                                f"{f['pbt']['update_steps']} in the stats")
    if expect_retile and len(frames) >= 3:
        first = [(t["x0"], t["y0"], t["x1"], t["y1"]) for t in frames[0]["tiles"]]
        third = [(t["x0"], t["y0"], t["x1"], t["y1"]) for t in frames[2]["tiles"]]
        steps = [f["pbt"]["update_steps"] for f in frames]
        if first == third:
            problems.append(f"frame 2 has frame 0's tiles (update steps {steps})")
        else:
            changed = len(set(third) - set(first))
            print(f"re-tiled: {changed} of {len(third)} tiles of frame 2 are not frame 0's "
                  f"(update steps per frame {steps})")
    for p in problems:
        print("FAIL", p)
    print(f"{assign} k={k} n={n}: {len(frames)} frames replayed, "
          f"{'ok' if not problems else f'{len(problems)} problems'}")
    sys.exit(1 if problems else 0)


if __name__ == "__main__":
    main()
