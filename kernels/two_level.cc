// Two-level grid: sub-grid records for dense cells (conservative 8x8x8 binning of the parent
// cell's list), the leaf lists, the SAH-style cost model that decides which cells to refine and
// which lambda to use (the scalar traversal over both levels is kernels/dda.cc's).
#include "kernels/two_level.h"

#include <algorithm>
#include <cfloat>
#include <cmath>
#include <limits>
#include <string>
#include <vector>

#include "kernels/grid_binning.h"

namespace rs {
namespace {

// Surface area of one cell over that of the grid box: the probability that a ray through the
// box passes through a given cell.
double CellAreaRatio(const double cs[3], const int res[3]) {
  const double cell = cs[0] * cs[1] + cs[1] * cs[2] + cs[0] * cs[2];
  const double bx = cs[0] * res[0], by = cs[1] * res[1], bz = cs[2] * res[2];
  const double box = bx * by + by * bz + bx * bz;
  return box > 0.0 ? cell / box : 1.0;
}

// Per ray through a refined cell: enter the sub-grid, 8 expected sub-cell steps (the 512
// sub-cells have 1/64 of the cell's area each), then the sub-cells' visits and tests.
double SubGridCost(size_t occupied_sub, size_t sub_refs, const GridCostModel& m) {
  return m.subgrid + 8.0 * m.step +
         (double(occupied_sub) * m.visit + double(sub_refs) * m.triangle) / 64.0;
}

double LeafCost(size_t refs, const GridCostModel& m) { return m.visit + double(refs) * m.triangle; }

}  // namespace

size_t TwoLevelGrid::Bytes() const {
  if (num_records == 0) return 0;
  const size_t top_cells = leaves.num_cells - (leaves.num_cells > 0 ? sub_leaves : 0);
  return num_records * sizeof(SubGridRecord) + ((top_cells + 63) / 64) * 12 +
         (leaves.num_cells + 1) * 4 + leaves.num_refs * 4;
}

double FlatGridCost(const Grid& grid, const GridCostModel& model) {
  if (grid.empty()) return 0.0;
  const double cs[3] = {grid.cell_size[0], grid.cell_size[1], grid.cell_size[2]};
  return CellAreaRatio(cs, grid.res) *
         (double(grid.num_cells) * model.step + double(grid.occupied_cells) * model.visit +
          double(grid.num_refs) * model.triangle);
}

double TwoLevelGridCost(const Grid& grid, const TwoLevelGrid& two, const GridCostModel& model) {
  if (grid.empty()) return 0.0;
  if (two.empty()) return FlatGridCost(grid, model);
  const double cs[3] = {grid.cell_size[0], grid.cell_size[1], grid.cell_size[2]};
  double sum = double(grid.num_cells) * model.step +
               double(grid.occupied_cells - two.num_records) * model.visit +
               double(grid.num_refs - two.refined_top_refs) * model.triangle;
  for (size_t r = 0; r < two.num_records; ++r) {
    const SubGridRecord& rec = two.records[r];
    size_t occupied = 0;
    for (const uint64_t w : rec.bits) occupied += size_t(std::popcount(w));
    sum += SubGridCost(occupied, rec.refs, model);
  }
  return CellAreaRatio(cs, grid.res) * sum;
}

double TwoLevelCostBound(const Grid& grid, int threshold, const GridCostModel& model) {
  if (grid.empty()) return 0.0;
  const double cs[3] = {grid.cell_size[0], grid.cell_size[1], grid.cell_size[2]};
  double sum = double(grid.num_cells) * model.step;
  for (size_t c = 0; c < grid.num_cells; ++c) {
    const uint32_t n = grid.cell_begin[c + 1] - grid.cell_begin[c];
    if (n == 0) continue;
    const double leaf = LeafCost(n, model);
    sum += n > uint32_t(std::max(threshold, 0)) ? std::min(leaf, SubGridCost(0, 0, model)) : leaf;
  }
  return CellAreaRatio(cs, grid.res) * sum;
}

void BuildTwoLevel(const Grid& grid, const TriangleSoA& tris, int threshold, bool by_cost,
                   const GridCostModel& model, TwoLevelGrid* out) {
  *out = TwoLevelGrid();
  out->threshold = threshold;
  if (grid.empty()) return;
  const size_t num_cells = grid.num_cells;
  const uint32_t* begin = grid.cell_begin.get();
  const uint32_t* ids = grid.tri_ids.get();
  double max_abs = 0.0;
  for (int a = 0; a < 3; ++a) {
    max_abs = std::max({max_abs, std::fabs(double(grid.lo[a])), std::fabs(double(grid.hi[a]))});
  }
  const float* p[3][3];
  for (int k = 0; k < 3; ++k) {
    for (int a = 0; a < 3; ++a) p[k][a] = tris.p[k][a].data();
  }
  // sub-cells no smaller than the top level's (grid.h: kMinCellMargins), and the sub-cell
  // references within one more reference budget in all
  const double min_cell = kMinCellMargins * 4.0 * FLT_EPSILON * max_abs;
  const size_t budget = GridRefBudget(tris.size - tris.num_degenerate);

  std::vector<SubGridRecord> records;
  std::vector<uint32_t> sub_begin;  // per occupied sub-cell (all records): start in sub_ids
  std::vector<uint32_t> sub_ids;
  std::vector<uint32_t> refined_cells;
  std::vector<uint16_t> ref_sub;  // scratch: sub-cell of each reference of the current cell
  std::vector<uint32_t> ref_tri;
  BinScratch scratch;
  TriangleSoA cell_tris;  // scratch: the current cell's triangles, for the SIMD cell ranges
  RangeBlock block;
  uint32_t counts[kSubCells];
  uint32_t next_leaf = uint32_t(num_cells);
  for (size_t cell = 0; cell < num_cells; ++cell) {
    const uint32_t n = begin[cell + 1] - begin[cell];
    if (n <= uint32_t(std::max(threshold, 0))) continue;
    // a sub-grid costs at least its entry and 8 steps: skip cells that cannot gain
    if (by_cost && !(SubGridCost(0, 0, model) < LeafCost(n, model))) continue;
    const int cz = int(cell / (size_t(grid.res[0]) * grid.res[1]));
    const int cy = int(cell / size_t(grid.res[0]) % size_t(grid.res[1]));
    const int cx = int(cell % size_t(grid.res[0]));
    const int c[3] = {cx, cy, cz};
    SubGridRecord rec{};
    BinGeometry geo;
    bool too_fine = false;
    for (int a = 0; a < 3; ++a) too_fine |= double(grid.cell_size[a]) / kSubRes < min_cell;
    if (too_fine) continue;
    const size_t room = budget - sub_ids.size();  // sub-cell references this cell may add
    for (int a = 0; a < 3; ++a) {
      // the parent cell's lower corner exactly as the float DDA computes boundaries
      rec.lo[a] = grid.lo[a] + float(c[a]) * grid.cell_size[a];
      rec.cell_size[a] = grid.cell_size[a] / float(kSubRes);
      rec.inv_cell_size[a] = grid.inv_cell_size[a] * float(kSubRes);
      geo.lo[a] = double(rec.lo[a]);
      geo.cs[a] = double(rec.cell_size[a]);
      geo.margin[a] = 1e-3 * geo.cs[a] + 4.0 * FLT_EPSILON * max_abs;
      geo.res[a] = kSubRes;
    }
    FinishBinGeometry(rec.lo, rec.inv_cell_size, &geo);
    // bin the parent's list (ascending ids) into the sub-cells: the triangles gathered into
    // cell_tris (none is degenerate: the grid lists none), their cell ranges a vector at a time
    // (the arithmetic of TriangleCellRange), then the cells as BinTriangleCells emits them
    const uint32_t* list = ids + begin[cell];
    for (auto& vertex : cell_tris.p) {
      for (auto& axis : vertex) axis.Reserve(n);
    }
    if (cell_tris.size < n) {
      cell_tris.degenerate.Reserve(n);
      std::fill(cell_tris.degenerate.data(), cell_tris.degenerate.data() + n, uint8_t{0});
    }
    cell_tris.size = n;
    for (int k = 0; k < 3; ++k) {
      for (int a = 0; a < 3; ++a) {
        const float* from = p[k][a];
        float* to = cell_tris.p[k][a].data();
        for (uint32_t t = 0; t < n; ++t) to[t] = from[list[t]];
      }
    }
    std::fill(counts, counts + kSubCells, 0u);
    size_t num_sub_refs = 0;
    for (size_t first = 0; first < n; first += kRangeBlock) {
      const size_t count = std::min(kRangeBlock, n - first);
      SimdTriangleCellRanges(cell_tris, geo, first, count, &block);
      // at most the bounding-box cells are emitted: make room once per block
      size_t most = 0;
      for (size_t j = 0; j < count; ++j) most += size_t(block.box[j]);
      if (ref_sub.size() < num_sub_refs + most) {
        ref_sub.resize(num_sub_refs + most);
        ref_tri.resize(num_sub_refs + most);
      }
      uint16_t* sub_out = ref_sub.data();
      uint32_t* tri_out = ref_tri.data();
      for (size_t j = 0; j < count; ++j) {
        const int32_t flags = block.flags[j];
        if (flags & kRangeOutside) continue;
        const uint32_t id = list[first + j];
        const int c0[3] = {block.c0[0][j], block.c0[1][j], block.c0[2][j]};
        const int c1[3] = {block.c1[0][j], block.c1[1][j], block.c1[2][j]};
        const bool span[3] = {(flags & 1) != 0, (flags & 2) != 0, (flags & 4) != 0};
        const int spans = int(span[0]) + int(span[1]) + int(span[2]);
        const size_t t = first + j;
        const float v[3][3] = {
            {cell_tris.p[0][0][t], cell_tris.p[0][1][t], cell_tris.p[0][2][t]},
            {cell_tris.p[1][0][t], cell_tris.p[1][1][t], cell_tris.p[1][2][t]},
            {cell_tris.p[2][0][t], cell_tris.p[2][1][t], cell_tris.p[2][2][t]}};
        BinTriangleCells(geo, v, c0, c1, span, spans, &scratch, [&](int x, int y, int z) {
          const int sc = x + kSubRes * (y + kSubRes * z);
          sub_out[num_sub_refs] = uint16_t(sc);
          tri_out[num_sub_refs++] = id;
          ++counts[sc];
        });
      }
      if (num_sub_refs > room) break;  // over the budget: stays a leaf
    }
    if (num_sub_refs > room) continue;
    size_t occupied = 0;
    for (const uint32_t k : counts) occupied += k != 0;
    if (by_cost && !(SubGridCost(occupied, num_sub_refs, model) < LeafCost(n, model))) continue;

    // record: bits, ranks, leaves; leaf lists by a stable counting sort (ids stay ascending)
    rec.first_leaf = next_leaf;
    rec.parent = uint32_t(cell);
    rec.refs = uint32_t(num_sub_refs);
    uint32_t start[kSubCells];
    uint32_t rank = 0;
    const size_t base = sub_ids.size();
    uint32_t offset = uint32_t(base);
    for (int z = 0; z < kSubRes; ++z) {
      rec.rank[z] = uint16_t(rank);
      uint64_t bits = 0;
      for (int b = 0; b < 64; ++b) {
        const int s = 64 * z + b;
        start[s] = offset;
        if (counts[s] == 0) continue;
        bits |= uint64_t{1} << b;
        sub_begin.push_back(offset);
        offset += counts[s];
        ++rank;
      }
      rec.bits[z] = bits;
    }
    sub_ids.resize(offset);
    for (size_t r = 0; r < num_sub_refs; ++r) sub_ids[start[ref_sub[r]]++] = ref_tri[r];
    next_leaf += rank;
    if (size_t(next_leaf) + 1 >= size_t{UINT32_MAX} || sub_ids.size() >= size_t{UINT32_MAX}) {
      throw Error("two-level grid build: more than 2^32 - 1 leaves or references");
    }
    records.push_back(rec);
    refined_cells.push_back(uint32_t(cell));
    out->refined_top_refs += n;
  }
  if (records.empty()) return;

  // records and the refined-cell bits with their per-word ranks
  out->num_records = records.size();
  out->records = AllocateBuildArray<SubGridRecord>(records.size(), "sub-grid records");
  std::copy(records.begin(), records.end(), out->records.get());
  const size_t words = (num_cells + 63) / 64;
  out->refined = AllocateBuildArray<uint64_t>(words, "refined-cell bits");
  out->refined_rank = AllocateBuildArray<uint32_t>(words, "refined-cell ranks");
  std::fill(out->refined.get(), out->refined.get() + words, uint64_t{0});
  for (const uint32_t cell : refined_cells) out->refined[cell >> 6] |= uint64_t{1} << (cell & 63);
  uint32_t rank = 0;
  for (size_t w = 0; w < words; ++w) {
    out->refined_rank[w] = rank;
    rank += uint32_t(std::popcount(out->refined[w]));
  }

  // leaves: the top-level lists (refined cells emptied), then the sub-cell lists
  Grid& leaves = out->leaves;
  const size_t num_sub_leaves = sub_begin.size();
  leaves.num_cells = num_cells + num_sub_leaves;
  leaves.cell_begin = AllocateBuildArray<uint32_t>(leaves.num_cells + 1, "leaf offsets");
  const size_t top_refs = grid.num_refs - out->refined_top_refs;
  leaves.num_refs = top_refs + sub_ids.size();
  if (leaves.num_refs >= size_t{UINT32_MAX}) {
    throw Error("two-level grid build: more than 2^32 - 1 leaf references");
  }
  leaves.tri_ids = AllocateBuildArray<uint32_t>(leaves.num_refs, "leaf triangle ids");
  uint32_t* lb = leaves.cell_begin.get();
  uint32_t* li = leaves.tri_ids.get();
  uint32_t at = 0;
  size_t occupied = 0, max_per = 0;
  for (size_t cell = 0; cell < num_cells; ++cell) {
    lb[cell] = at;
    if (out->Refined(cell)) continue;
    const uint32_t n = begin[cell + 1] - begin[cell];
    std::copy(ids + begin[cell], ids + begin[cell + 1], li + at);
    at += n;
    occupied += n != 0;
    max_per = std::max<size_t>(max_per, n);
  }
  for (size_t s = 0; s < num_sub_leaves; ++s) {
    lb[num_cells + s] = at;
    const uint32_t end = s + 1 < num_sub_leaves ? sub_begin[s + 1] : uint32_t(sub_ids.size());
    const uint32_t n = end - sub_begin[s];
    std::copy(sub_ids.begin() + sub_begin[s], sub_ids.begin() + end, li + at);
    at += n;
    ++occupied;
    max_per = std::max<size_t>(max_per, n);
  }
  lb[leaves.num_cells] = at;
  HWY_ASSERT(size_t(at) == leaves.num_refs);
  leaves.occupied_cells = occupied;
  leaves.max_per_cell = max_per;
  out->sub_refs = sub_ids.size();
  out->sub_leaves = num_sub_leaves;
}

float ChooseLambda(const TriangleSoA& tris, int max_resolution, const GridCostModel& model,
                   double* cost, int threads) {
  return ChooseLambda(tris, ComputeGridBounds(tris), max_resolution, model, cost, threads);
}

float ChooseLambda(const TriangleSoA& tris, const GridBounds& bounds, int max_resolution,
                   const GridCostModel& model, double* cost, int threads) {
  static constexpr float kCandidates[] = {0.5f, 1.0f, 2.0f, 4.0f, 8.0f};
  // the cost is unimodal in lambda on every scene measured: stop at the first increase
  float best = 1.0f;
  double best_cost = HUGE_VAL;
  for (const float lambda : kCandidates) {
    Grid geometry;
    SetGridGeometry(bounds, lambda, max_resolution, &geometry);
    if (geometry.empty()) break;
    const GridBoxCounts counts = CountGridBoxes(tris, geometry, threads);
    const double cs[3] = {geometry.cell_size[0], geometry.cell_size[1], geometry.cell_size[2]};
    const double c = CellAreaRatio(cs, geometry.res) *
                     (double(counts.cells) * model.step + double(counts.occupied) * model.visit +
                      double(counts.refs) * model.triangle);
    if (!(c < best_cost)) break;
    best_cost = c;
    best = lambda;
  }
  if (cost != nullptr) *cost = best_cost;
  return best;
}

}  // namespace rs
