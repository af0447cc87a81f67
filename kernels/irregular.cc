// Irregular grid build (kernels/irregular.h): a coarse uniform grid, each top cell cut to the
// depth its count asks for (conservative binning of its list, kernels/grid_binning.h), cells
// merged pairwise along x, y, z while the cost model gains, traversal boxes expanded over empty
// cells, then compacted into the lookup tables, boxes and CSR lists. The scalar traversal is
// kernels/dda.cc's.
#include "kernels/irregular.h"

#include <algorithm>
#include <cfloat>
#include <cmath>
#include <limits>
#include <vector>

#include "kernels/grid_binning.h"

namespace rs {
namespace {

struct Box {
  int lo[3];
  int hi[3];
};

double BoxArea(const IrregularGrid& g, const int32_t lo[3], const int32_t hi[3]) {
  double e[3];
  for (int a = 0; a < 3; ++a) e[a] = double(hi[a] - lo[a]) * double(g.voxel_size[a]);
  return e[0] * e[1] + e[1] * e[2] + e[0] * e[2];
}

double CellCost(double area, size_t refs, const GridCostModel& m) {
  return area * (kIrregularStep * m.step + (refs > 0 ? m.visit : 0.0) + double(refs) * m.triangle);
}

// Size of the union of two ascending id lists.
size_t UnionSize(const uint32_t* a, size_t na, const uint32_t* b, size_t nb) {
  size_t i = 0, j = 0, n = 0;
  while (i < na && j < nb) {
    if (a[i] < b[j]) {
      ++i;
    } else if (b[j] < a[i]) {
      ++j;
    } else {
      ++i;
      ++j;
    }
    ++n;
  }
  return n + (na - i) + (nb - j);
}

// The cells while they are built: boxes in voxels, lists as (begin, count) in one pool (a merged
// list is appended; the dead ones are dropped at compaction), and the lookup tables of the final
// layout, rewritten in place when cells merge.
class Builder {
 public:
  Builder(IrregularGrid* g, const GridCostModel& m) : g_(*g), model_(m) {}

  IrregularGrid& g_;
  const GridCostModel& model_;
  std::vector<int32_t> lo_[3], hi_[3];
  std::vector<uint32_t> begin_, count_;
  std::vector<uint32_t> pool_;
  std::vector<uint8_t> alive_;
  std::vector<uint32_t> top_, fine_;

  size_t Cells() const { return begin_.size(); }
  // Drops the cells from `cells` on, the pool from `pool` on and the entries from `fine` on.
  void Truncate(size_t cells, size_t pool, size_t fine) {
    for (int a = 0; a < 3; ++a) {
      lo_[a].resize(cells);
      hi_[a].resize(cells);
    }
    begin_.resize(cells);
    count_.resize(cells);
    alive_.resize(cells);
    pool_.resize(pool);
    fine_.resize(fine);
  }
  void AddCell(const int lo[3], const int hi[3], uint32_t begin, uint32_t count) {
    for (int a = 0; a < 3; ++a) {
      lo_[a].push_back(lo[a]);
      hi_[a].push_back(hi[a]);
    }
    begin_.push_back(begin);
    count_.push_back(count);
    alive_.push_back(1);
  }
  uint32_t Lookup(const int v[3]) const {
    const int D = g_.depth;
    const int x = v[0] >> D, y = v[1] >> D, z = v[2] >> D;
    const uint32_t e = top_[size_t(x) + size_t(g_.top_res[0]) *
                                            (size_t(y) + size_t(g_.top_res[1]) * size_t(z))];
    const int s = int(e & 3u), q = D - s, m = (1 << D) - 1;
    return fine_[(e >> 2) + uint32_t((v[0] & m) >> q) + (uint32_t((v[1] & m) >> q) << s) +
                 (uint32_t((v[2] & m) >> q) << (2 * s))];
  }
  // Writes `id` into every table entry of the region [lo, hi) (a union of whole sub-cells of
  // every top cell it touches).
  void Paint(const int lo[3], const int hi[3], uint32_t id) {
    const int D = g_.depth;
    int t0[3], t1[3];
    for (int a = 0; a < 3; ++a) {
      t0[a] = lo[a] >> D;
      t1[a] = (hi[a] - 1) >> D;
    }
    for (int tz = t0[2]; tz <= t1[2]; ++tz) {
      for (int ty = t0[1]; ty <= t1[1]; ++ty) {
        for (int tx = t0[0]; tx <= t1[0]; ++tx) {
          const int tc[3] = {tx, ty, tz};
          const uint32_t e = top_[size_t(tx) + size_t(g_.top_res[0]) *
                                                   (size_t(ty) + size_t(g_.top_res[1]) * size_t(tz))];
          const int s = int(e & 3u), q = D - s;
          int s0[3], s1[3];
          for (int a = 0; a < 3; ++a) {
            const int base = tc[a] << D;
            s0[a] = (std::max(lo[a], base) - base) >> q;
            s1[a] = (std::min(hi[a], base + (1 << D)) - 1 - base) >> q;
          }
          for (int z = s0[2]; z <= s1[2]; ++z) {
            for (int y = s0[1]; y <= s1[1]; ++y) {
              for (int x = s0[0]; x <= s1[0]; ++x) {
                fine_[(e >> 2) + uint32_t(x) + (uint32_t(y) << s) + (uint32_t(z) << (2 * s))] = id;
              }
            }
          }
        }
      }
    }
  }

  double Cost(uint32_t k) const {
    const int32_t lo[3] = {lo_[0][k], lo_[1][k], lo_[2][k]};
    const int32_t hi[3] = {hi_[0][k], hi_[1][k], hi_[2][k]};
    return CellCost(BoxArea(g_, lo, hi), count_[k], model_);
  }

  // Merges pairs of cells along each axis while the cost model gains: a cell and its neighbour
  // across its +a face with the same extent on the other axes. Each cell merges at most once per
  // pass, so sizes grow evenly; rounds repeat while any pass merged.
  void Merge() {
    std::vector<uint8_t> used(Cells());
    std::vector<uint32_t> alive(Cells()), still;
    for (size_t k = 0; k < Cells(); ++k) alive[k] = uint32_t(k);
    for (int round = 0; round < 64; ++round) {
      bool changed = false;
      for (int a = 0; a < 3; ++a) {
        const int b = (a + 1) % 3, c = (a + 2) % 3;
        for (const uint32_t k : alive) used[k] = 0;
        for (const uint32_t k : alive) {
          if (!alive_[k] || used[k] || hi_[a][k] >= g_.vres[a]) continue;
          int v[3];
          v[a] = hi_[a][k];
          v[b] = lo_[b][k];
          v[c] = lo_[c][k];
          const uint32_t m = Lookup(v);
          if (used[m] || lo_[b][m] != lo_[b][k] || hi_[b][m] != hi_[b][k] ||
              lo_[c][m] != lo_[c][k] || hi_[c][m] != hi_[c][k]) {
            continue;
          }
          const uint32_t* la = pool_.data() + begin_[k];
          const uint32_t* lb = pool_.data() + begin_[m];
          const size_t nu = UnionSize(la, count_[k], lb, count_[m]);
          int32_t lo[3] = {lo_[0][k], lo_[1][k], lo_[2][k]};
          int32_t hi[3] = {hi_[0][k], hi_[1][k], hi_[2][k]};
          hi[a] = hi_[a][m];
          const double merged = CellCost(BoxArea(g_, lo, hi), nu, model_);
          if (merged > Cost(k) + Cost(m)) continue;
          if (count_[m] > 0) {
            // the union, appended to the pool
            const uint32_t nb = uint32_t(pool_.size());
            pool_.resize(pool_.size() + nu);
            la = pool_.data() + begin_[k];
            lb = pool_.data() + begin_[m];
            std::set_union(la, la + count_[k], lb, lb + count_[m], pool_.data() + nb);
            begin_[k] = nb;
            count_[k] = uint32_t(nu);
          }
          const int mlo[3] = {lo_[0][m], lo_[1][m], lo_[2][m]};
          const int mhi[3] = {hi_[0][m], hi_[1][m], hi_[2][m]};
          Paint(mlo, mhi, k);
          hi_[a][k] = hi_[a][m];
          alive_[m] = 0;
          used[k] = used[m] = 1;
          ++g_.merged;
          changed = true;
        }
      }
      if (!changed) break;
      // the next round visits the cells still alive
      still.clear();
      for (const uint32_t k : alive) {
        if (alive_[k]) still.push_back(k);
      }
      alive.swap(still);
    }
  }

  // The layers of empty cells ahead of a box's face: [lo, hi) is the one-voxel layer beyond
  // the face on axis a (up: in +a), walked in rows along its longest axis that jump to the end
  // of each cell met. 0 if a cell there lists a triangle; else the least extent of those cells
  // beyond the face (they tile the layer, so they cover that many layers).
  int EmptyReach(const int lo[3], const int hi[3], int a, bool up) const {
    int r = 0;
    for (int k = 1; k < 3; ++k) {
      if (hi[k] - lo[k] > hi[r] - lo[r]) r = k;
    }
    const int p = (r + 1) % 3, q = (r + 2) % 3;
    int reach = std::numeric_limits<int>::max();
    int v[3];
    for (v[q] = lo[q]; v[q] < hi[q]; ++v[q]) {
      for (v[p] = lo[p]; v[p] < hi[p]; ++v[p]) {
        for (v[r] = lo[r]; v[r] < hi[r];) {
          const uint32_t m = Lookup(v);
          if (count_[m] != 0) return 0;
          reach = std::min(reach, up ? hi_[a][m] - lo[a] : hi[a] - lo_[a][m]);
          v[r] = hi_[r][m];
        }
      }
    }
    return reach;
  }
};


// The cells of one top cell: an octree cut to at most `s` levels, whose node is split into its
// 8 children (conservative binning of its list: BinListed, kernels/grid_binning.h) while it
// holds more than leaf_triangles triangles and has levels left; leaves become cells, painted
// into the top cell's 8^s table entries (a leaf at level l covers 8^(s - l) of them). Empty space inside a
// dense top cell is a few large leaves, not 8^s empty sub-cells.
class Octree {
 public:
  Octree(Builder* b, const TriangleSoA& tris, int leaf_triangles)
      : b_(*b), tris_(tris), leaf_(size_t(std::max(leaf_triangles, 0))) {}

  // Builds the cells of the top cell whose first voxel is lo (its entries from fine_base, at
  // depth s) from its list ids[0, n) (ascending); returns the references of its leaves.
  size_t Build(const int lo[3], uint32_t fine_base, int s, const uint32_t* ids, size_t n) {
    for (int a = 0; a < 3; ++a) base_[a] = lo[a];
    fine_base_ = fine_base;
    s_ = s;
    refs_ = 0;
    Node(lo, 1 << b_.g_.depth, 0, ids, n);
    return refs_;
  }

 private:
  static constexpr size_t kNoSplitMin = 64;

  // Makes [lo, lo + size)^3 a cell listing ids[0, n) and paints its entries.
  void Leaf(const int lo[3], int size, const uint32_t* ids, size_t n) {
    const IrregularGrid& g = b_.g_;
    const int hi[3] = {lo[0] + size, lo[1] + size, lo[2] + size};
    const uint32_t id = uint32_t(b_.Cells());
    b_.AddCell(lo, hi, uint32_t(b_.pool_.size()), uint32_t(n));
    b_.pool_.insert(b_.pool_.end(), ids, ids + n);
    refs_ += n;
    // this leaf's entries: (size / 2^q)^3 of the top cell's table, q = depth - s
    const int q = g.depth - s_, span = size >> q;
    const int e0[3] = {(lo[0] - base_[0]) >> q, (lo[1] - base_[1]) >> q, (lo[2] - base_[2]) >> q};
    for (int z = e0[2]; z < e0[2] + span; ++z) {
      for (int y = e0[1]; y < e0[1] + span; ++y) {
        for (int x = e0[0]; x < e0[0] + span; ++x) {
          b_.fine_[fine_base_ + uint32_t(x) + (uint32_t(y) << s_) + (uint32_t(z) << (2 * s_))] = id;
        }
      }
    }
  }

  void Node(const int lo[3], int size, int level, const uint32_t* ids, size_t n) {
    const IrregularGrid& g = b_.g_;
    if (n <= leaf_ || level == s_) {
      Leaf(lo, size, ids, n);
      return;
    }
    // bin the list into the 8 children (ids stay ascending within each child)
    const int half = size / 2;
    BinGeometry geo;
    float lo_f[3], inv_f[3];
    for (int a = 0; a < 3; ++a) {
      lo_f[a] = g.lo[a] + float(lo[a]) * g.voxel_size[a];
      inv_f[a] = g.inv_voxel_size[a] / float(half);
      geo.lo[a] = double(lo_f[a]);
      geo.cs[a] = double(g.voxel_size[a] * float(half));
      geo.margin[a] = g.margin[a];
      geo.res[a] = 2;
    }
    FinishBinGeometry(lo_f, inv_f, &geo);
    std::vector<uint32_t>& list = lists_[level];
    size_t count[8] = {};
    pairs_.clear();
    GatherListed(tris_, ids, n, &node_tris_);
    BinListed<2>(
        node_tris_, geo, n, &bin_, [](size_t) {},  // pairs_ grows geometrically
        [&](size_t t, uint32_t c) {  // c = x + 2 (y + 2 z)
          pairs_.push_back((uint64_t(c) << 32) | ids[t]);
          ++count[c];
        },
        [] { return true; });
    // A split of many triangles that leaves them all in one child and lists them at least twice
    // over separates nothing (copies of one triangle spanning a child boundary): the node stays
    // a leaf, so such input is binned once per top cell instead of once per level. (Triangles
    // that all lie in one child are split: the other seven children are empty space.)
    size_t sum = 0;
    for (const size_t c : count) sum += c;
    if (n > kNoSplitMin && *std::max_element(count, count + 8) == n && sum >= 2 * n) {
      Leaf(lo, size, ids, n);
      return;
    }
    size_t begin[9] = {};
    for (int c = 0; c < 8; ++c) begin[c + 1] = begin[c] + count[c];
    list.resize(begin[8]);
    size_t fill[8];
    std::copy(begin, begin + 8, fill);
    for (const uint64_t p : pairs_) list[fill[p >> 32]++] = uint32_t(p);
    for (int c = 0; c < 8; ++c) {
      const int child[3] = {lo[0] + (c & 1) * half, lo[1] + ((c >> 1) & 1) * half,
                            lo[2] + (c >> 2) * half};
      Node(child, half, level + 1, list.data() + begin[c], count[c]);
    }
  }

  Builder& b_;
  const TriangleSoA& tris_;
  size_t leaf_;
  int base_[3] = {0, 0, 0};
  uint32_t fine_base_ = 0;
  int s_ = 0;
  size_t refs_ = 0;
  std::vector<uint32_t> lists_[kIrregularMaxDepth + 1];  // the children's lists, per level
  std::vector<uint64_t> pairs_;
  TriangleSoA node_tris_;  // the node's triangles, gathered for BinListed
  ListedBinScratch bin_;
};

}  // namespace

double IrregularGridCost(const IrregularGrid& g, const GridCostModel& model) {
  if (g.empty() || !g.box) return 0.0;
  const int32_t lo[3] = {0, 0, 0};
  const int32_t hi[3] = {g.vres[0], g.vres[1], g.vres[2]};
  const double total = BoxArea(g, lo, hi);
  if (!(total > 0.0)) return 0.0;
  double sum = 0.0;
  for (size_t k = 0; k < g.num_cells; ++k) {
    const int32_t* b = g.Box(uint32_t(k));
    sum += CellCost(BoxArea(g, b, b + 3),
                    g.lists.cell_begin[k + 1] - g.lists.cell_begin[k], model);
  }
  return sum / total;
}

void BuildIrregularGrid(const TriangleSoA& tris, const GridBounds& bounds,
                        const IrregularOptions& options, int max_resolution, IrregularGrid* out) {
  *out = IrregularGrid();
  Grid top;
  BuildGrid(tris, bounds, options.top_lambda, max_resolution, &top);
  if (top.empty()) return;
  IrregularGrid& g = *out;
  double max_abs = 0.0;
  for (int a = 0; a < 3; ++a) {
    max_abs = std::max({max_abs, std::fabs(double(top.lo[a])), std::fabs(double(top.hi[a]))});
  }
  const double ulp_margin = 4.0 * FLT_EPSILON * max_abs;
  const double min_cell = kMinCellMargins * ulp_margin;
  int depth = kIrregularMaxDepth;
  for (int a = 0; a < 3; ++a) {
    // sub-cells no finer than the coordinates allow; at most 65535 voxels per axis (the SIMD
    // kernel packs a box's lo and hi into 16 bits each)
    while (depth > 0 && (double(top.cell_size[a]) / double(1 << depth) < min_cell ||
                         (top.res[a] << depth) > 65535)) {
      --depth;
    }
  }
  if (top.res[0] > 65535 || top.res[1] > 65535 || top.res[2] > 65535) {
    throw Error("irregular grid build: " + std::to_string(top.res[0]) + "x" +
                std::to_string(top.res[1]) + "x" + std::to_string(top.res[2]) +
                " top cells exceed 65535 per axis; lower BuildOptions::max_resolution");
  }
  g.depth = depth;
  for (int a = 0; a < 3; ++a) {
    g.lo[a] = top.lo[a];
    g.hi[a] = top.hi[a];
    g.top_res[a] = top.res[a];
    g.vres[a] = top.res[a] << depth;
    g.voxel_size[a] = top.cell_size[a] / float(1 << depth);
    g.inv_voxel_size[a] = top.inv_cell_size[a] * float(1 << depth);
    g.margin[a] = 1e-3 * double(g.voxel_size[a]) + ulp_margin;
  }
  g.num_top = top.num_cells;

  Builder b(&g, options.model);
  b.top_.resize(top.num_cells);
  const size_t budget = GridRefBudget(bounds.num_valid);
  size_t total_refs = top.num_refs;
  Octree octree(&b, tris, options.leaf_triangles);
  const double log8 = std::log(8.0);
  size_t cell = 0;
  for (int tz = 0; tz < top.res[2]; ++tz) {
    for (int ty = 0; ty < top.res[1]; ++ty) {
      for (int tx = 0; tx < top.res[0]; ++tx, ++cell) {
        const uint32_t lb = top.cell_begin[cell];
        const uint32_t n = top.cell_begin[cell + 1] - lb;
        int s = 0;
        if (n > 0) {
          s = int(std::lround(std::log(double(options.sub_lambda) * double(n)) / log8));
          s = std::clamp(s, 0, depth);
        }
        const int lo[3] = {tx << depth, ty << depth, tz << depth};
        const size_t cells_before = b.Cells(), pool_before = b.pool_.size();
        const uint32_t fine_base = uint32_t(b.fine_.size());
        b.top_[cell] = (fine_base << 2) | uint32_t(s);
        b.fine_.resize(fine_base + (size_t{1} << (3 * s)));
        const size_t refs = octree.Build(lo, fine_base, s, top.tri_ids.get() + lb, n);
        if (s > 0 && total_refs - n + refs > budget) {
          // over the budget: the top cell stays one cell
          b.Truncate(cells_before, pool_before, fine_base);
          b.top_[cell] = fine_base << 2;
          b.fine_.resize(fine_base + 1);
          octree.Build(lo, fine_base, 0, top.tri_ids.get() + lb, n);
        } else {
          total_refs = total_refs - n + refs;
        }
      }
    }
  }
  if (b.fine_.size() >= (size_t{1} << 30) || b.Cells() >= (size_t{1} << 31)) {
    throw Error("irregular grid build: " + std::to_string(b.Cells()) +
                " cells exceed the 32-bit tables; lower the lambdas");
  }
  g.base_cells = b.Cells();
  if (options.merge) b.Merge();

  // compaction: live cells in order
  std::vector<uint32_t> renumber(b.Cells(), UINT32_MAX);
  size_t live = 0, refs = 0;
  for (size_t k = 0; k < b.Cells(); ++k) {
    if (!b.alive_[k]) continue;
    renumber[k] = uint32_t(live++);
    refs += b.count_[k];
  }
  g.num_cells = live;
  g.num_fine = b.fine_.size();
  g.top = AllocateBuildArray<uint32_t>(g.num_top, "irregular top entries");
  std::copy(b.top_.begin(), b.top_.end(), g.top.get());
  g.fine = AllocateBuildArray<uint32_t>(g.num_fine, "irregular sub-cell entries");
  for (size_t i = 0; i < g.num_fine; ++i) g.fine[i] = renumber[b.fine_[i]];
  g.box = AllocateBuildArray<int32_t>(8 * live, "irregular cell boxes");
  Grid& lists = g.lists;
  lists.num_cells = live;
  lists.num_refs = refs;
  lists.cell_begin = AllocateBuildArray<uint32_t>(live + 1, "irregular cell offsets");
  lists.tri_ids = AllocateBuildArray<uint32_t>(std::max<size_t>(refs, 1), "irregular triangle ids");
  size_t at = 0;
  for (size_t k = 0; k < b.Cells(); ++k) {
    if (!b.alive_[k]) continue;
    const uint32_t c = renumber[k];
    int32_t* box = g.box.get() + 8 * size_t(c);
    for (int a = 0; a < 3; ++a) {
      box[a] = b.lo_[a][k];
      box[3 + a] = b.hi_[a][k];
    }
    box[6] = box[7] = 0;
    lists.cell_begin[c] = uint32_t(at);
    std::copy(b.pool_.begin() + b.begin_[k], b.pool_.begin() + b.begin_[k] + b.count_[k],
              lists.tri_ids.get() + at);
    at += b.count_[k];
    lists.occupied_cells += b.count_[k] != 0;
    lists.max_per_cell = std::max<size_t>(lists.max_per_cell, b.count_[k]);
  }
  lists.cell_begin[live] = uint32_t(at);
  g.region_cost = IrregularGridCost(g, options.model);

  if (!options.expand) return;
  const int kMaxExpand = 1 << depth;  // voxels per face: one top cell
  // Expansion: grow each non-empty cell's box over the empty cells beyond its faces (b's
  // regions: the boxes before expansion), by whole empty cells at a time, at most kMaxExpand
  // voxels per face, on all six faces until none grows.
  for (size_t c = 0; c < live; ++c) {
    if (lists.cell_begin[c + 1] == lists.cell_begin[c]) continue;  // empty cells are merged
    int32_t* box = g.box.get() + 8 * c;
    const int32_t own[6] = {box[0], box[1], box[2], box[3], box[4], box[5]};
    bool grew_any = false;
    for (bool grew = true; grew;) {
      grew = false;
      for (int f = 0; f < 6; ++f) {
        const int a = f >> 1;
        const bool up = f & 1;
        int lo[3] = {box[0], box[1], box[2]};
        int hi[3] = {box[3], box[4], box[5]};
        int room;
        if (up) {
          room = std::min(g.vres[a] - hi[a], kMaxExpand - (hi[a] - own[3 + a]));
          lo[a] = hi[a];
          hi[a] = hi[a] + 1;
        } else {
          room = std::min(lo[a], kMaxExpand - (own[a] - lo[a]));
          hi[a] = lo[a];
          lo[a] = lo[a] - 1;
        }
        if (room <= 0) continue;
        const int n = std::min(room, b.EmptyReach(lo, hi, a, up));
        if (n <= 0) continue;
        if (up) {
          box[3 + a] += n;
        } else {
          box[a] -= n;
        }
        grew = grew_any = true;
      }
    }
    g.expanded += grew_any;
  }
}

}  // namespace rs
