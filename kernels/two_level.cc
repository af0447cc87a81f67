// Two-level grid: sub-grid records for dense cells (conservative 8x8x8 binning of the parent
// cell's list), the leaf lists, the SAH-style cost model that decides which cells to refine and
// which lambda to use (the scalar traversal over both levels is kernels/dda.cc's).
#include "kernels/two_level.h"

#include <algorithm>
#include <atomic>
#include <bit>
#include <cfloat>
#include <cmath>
#include <limits>
#include <string>
#include <vector>

#include "kernels/build_threads.h"
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

namespace {

// One refined cell's sub-grid before it is placed: its record (first_leaf not set), its leaf
// lists (sorted by sub-cell, ids ascending in each) appended to a caller's id array, and the
// start of each occupied sub-cell's list in it.
struct CellRefiner {
  const Grid& grid;
  const TriangleSoA& source;  // the grid's triangles
  double max_abs;   // largest |bound| of the grid
  double min_cell;  // smallest sub-cell edge
  bool by_cost;
  GridCostModel model;
  // scratch, reused across cells
  std::vector<uint16_t> ref_sub;  // sub-cell of each reference of the current cell
  std::vector<uint32_t> ref_tri;
  TriangleSoA cell_tris;  // the current cell's triangles, for the SIMD cell ranges
  ListedBinScratch bin;
  uint32_t counts[kSubCells];

  CellRefiner(const Grid& g, const TriangleSoA& tris, double max_abs_bound, double min_cell_size,
              bool cost, const GridCostModel& m)
      : grid(g),
        source(tris),
        max_abs(max_abs_bound),
        min_cell(min_cell_size),
        by_cost(cost),
        model(m) {}

  // Refines `cell` if it pays off (by_cost), its sub-cells are not too fine and it makes at
  // most `room` sub-cell references: fills *rec (all but first_leaf), appends the leaf lists to
  // *ids and the start of each occupied sub-cell's list (an index into *ids) to *starts, and
  // returns true; else returns false and leaves *ids and *starts as they were.
  bool Refine(size_t cell, size_t room, SubGridRecord* out_rec, std::vector<uint32_t>* ids_out,
              std::vector<uint32_t>* starts) {
    const uint32_t* begin = grid.cell_begin.get();
    const uint32_t* ids = grid.tri_ids.get();
    const uint32_t n = begin[cell + 1] - begin[cell];
    const int cz = int(cell / (size_t(grid.res[0]) * grid.res[1]));
    const int cy = int(cell / size_t(grid.res[0]) % size_t(grid.res[1]));
    const int cx = int(cell % size_t(grid.res[0]));
    const int c[3] = {cx, cy, cz};
    SubGridRecord rec{};
    BinGeometry geo;
    bool too_fine = false;
    for (int a = 0; a < 3; ++a) too_fine |= double(grid.cell_size[a]) / kSubRes < min_cell;
    if (too_fine) return false;
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
    // cell_tris (none is degenerate: the grid lists none), then BinListed
    const uint32_t* list = ids + begin[cell];
    GatherListed(source, list, n, &cell_tris);
    std::fill(counts, counts + kSubCells, 0u);
    size_t num_sub_refs = 0;
    uint16_t* sub_out = nullptr;  // the next reference's sub-cell and triangle
    uint32_t* tri_out = nullptr;
    uint32_t* const counts_out = counts;
    const bool fits = BinListed<kSubRes>(
        cell_tris, geo, n, &bin,
        [&](size_t most) {  // at most the bounding-box cells: room once per block
          if (ref_sub.size() < num_sub_refs + most) {
            ref_sub.resize(num_sub_refs + most);
            ref_tri.resize(num_sub_refs + most);
          }
          sub_out = ref_sub.data() + num_sub_refs;
          tri_out = ref_tri.data() + num_sub_refs;
        },
        [&](size_t t, uint32_t sc) {
          *sub_out++ = uint16_t(sc);
          *tri_out++ = list[t];
          ++counts_out[sc];
        },
        [&] {  // over the budget: stays a leaf
          num_sub_refs = size_t(sub_out - ref_sub.data());
          return num_sub_refs <= room;
        });
    if (!fits) return false;
    size_t occupied = 0;
    for (const uint32_t k : counts) occupied += k != 0;
    if (by_cost && !(SubGridCost(occupied, num_sub_refs, model) < LeafCost(n, model))) {
      return false;
    }

    // record: bits, ranks; leaf lists by a stable counting sort (ids stay ascending)
    rec.parent = uint32_t(cell);
    rec.refs = uint32_t(num_sub_refs);
    uint32_t start[kSubCells];
    uint32_t rank = 0;
    const size_t base = ids_out->size();
    uint32_t offset = uint32_t(base);
    for (int z = 0; z < kSubRes; ++z) {
      rec.rank[z] = uint16_t(rank);
      uint64_t bits = 0;
      for (int b = 0; b < 64; ++b) {
        const int s = 64 * z + b;
        start[s] = offset;
        if (counts[s] == 0) continue;
        bits |= uint64_t{1} << b;
        starts->push_back(offset);
        offset += counts[s];
        ++rank;
      }
      rec.bits[z] = bits;
    }
    ids_out->resize(offset);
    uint32_t* sorted = ids_out->data();
    for (size_t r = 0; r < num_sub_refs; ++r) sorted[start[ref_sub[r]]++] = ref_tri[r];
    *out_rec = rec;
    return true;
  }
};

}  // namespace

void BuildTwoLevel(const Grid& grid, const TriangleSoA& tris, int threshold, bool by_cost,
                   const GridCostModel& model, TwoLevelGrid* out, int threads) {
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
  // sub-cells no smaller than the top level's (grid.h: kMinCellMargins), and the sub-cell
  // references within one more reference budget in all
  const double min_cell = kMinCellMargins * 4.0 * FLT_EPSILON * max_abs;
  const size_t budget = GridRefBudget(tris.size - tris.num_degenerate);
  // the candidates: more than `threshold` triangles, and (by_cost) a sub-grid that could gain
  std::vector<uint32_t> candidates;
  size_t candidate_refs = 0;
  for (size_t cell = 0; cell < num_cells; ++cell) {
    const uint32_t n = begin[cell + 1] - begin[cell];
    if (n <= uint32_t(std::max(threshold, 0))) continue;
    // a sub-grid costs at least its entry and 8 steps: skip cells that cannot gain
    if (by_cost && !(SubGridCost(0, 0, model) < LeafCost(n, model))) continue;
    candidates.push_back(uint32_t(cell));
    candidate_refs += n;
  }

  std::vector<SubGridRecord> records;
  std::vector<uint32_t> sub_begin;  // per occupied sub-cell (all records): start in sub_ids
  std::vector<uint32_t> sub_ids;
  std::vector<uint32_t> refined_cells;
  uint32_t next_leaf = uint32_t(num_cells);
  // Places a refined cell: its record gets its first leaf; the budget and id checks.
  const auto place = [&](SubGridRecord rec, size_t leaves) {
    rec.first_leaf = next_leaf;
    next_leaf += uint32_t(leaves);
    if (size_t(next_leaf) + 1 >= size_t{UINT32_MAX} || sub_ids.size() >= size_t{UINT32_MAX}) {
      throw Error("two-level grid build: more than 2^32 - 1 leaves or references");
    }
    records.push_back(rec);
    refined_cells.push_back(rec.parent);
    out->refined_top_refs += begin[rec.parent + 1] - begin[rec.parent];
  };
  // Threaded when there is enough to share: chunks of the candidates with about equal
  // references (8 per thread, handed out in turn: the work per reference varies), each refined
  // with the whole budget as room into its chunk's own lists; then in cell order a cell is kept
  // iff its references fit the room the cells before it left, as the serial loop decides (a
  // refinement does not depend on the others), and its lists are appended: the same records,
  // leaves and lists for any thread count.
  const int parts = int(std::min<size_t>(size_t(BuildThreadCount(threads)),
                                         candidate_refs / 4096 + 1));
  if (parts <= 1) {
    CellRefiner refiner(grid, tris, max_abs, min_cell, by_cost, model);
    for (const uint32_t cell : candidates) {
      SubGridRecord rec;
      const size_t leaves_before = sub_begin.size();
      if (!refiner.Refine(cell, budget - sub_ids.size(), &rec, &sub_ids, &sub_begin)) continue;
      place(rec, sub_begin.size() - leaves_before);
    }
  } else {
    struct Part {
      std::vector<SubGridRecord> records;
      std::vector<uint32_t> ids, starts;
      std::vector<size_t> id_end, start_end;  // per record: its lists' ends in ids / starts
    };
    const size_t chunks = std::min(candidates.size(), size_t(8) * size_t(parts));
    std::vector<Part> part(chunks);
    std::vector<size_t> first(chunks + 1, candidates.size());
    {
      size_t acc = 0, k = 1;
      first[0] = 0;
      for (size_t i = 0; i < candidates.size() && k < chunks; ++i) {
        acc += begin[candidates[i] + 1] - begin[candidates[i]];
        while (k < chunks && acc * chunks >= candidate_refs * k) first[k++] = i + 1;
      }
    }
    std::atomic<size_t> next_chunk{0};
    RunParts(parts, [&](int) {
      CellRefiner refiner(grid, tris, max_abs, min_cell, by_cost, model);
      // relaxed: the chunks are independent; RunParts' joins publish the results
      for (size_t k = next_chunk.fetch_add(1, std::memory_order_relaxed); k < chunks;
           k = next_chunk.fetch_add(1, std::memory_order_relaxed)) {
        Part& pt = part[k];
        for (size_t i = first[k]; i < first[k + 1]; ++i) {
          SubGridRecord rec;
          if (!refiner.Refine(candidates[i], budget, &rec, &pt.ids, &pt.starts)) continue;
          pt.records.push_back(rec);
          pt.id_end.push_back(pt.ids.size());
          pt.start_end.push_back(pt.starts.size());
        }
      }
    });
    for (const Part& pt : part) {
      size_t id0 = 0, start0 = 0;
      for (size_t r = 0; r < pt.records.size(); ++r) {
        const size_t refs = pt.id_end[r] - id0, leaves = pt.start_end[r] - start0;
        if (refs <= budget - sub_ids.size()) {
          const uint32_t shift = uint32_t(sub_ids.size()) - uint32_t(id0);
          for (size_t s = start0; s < pt.start_end[r]; ++s) {
            sub_begin.push_back(pt.starts[s] + shift);
          }
          sub_ids.insert(sub_ids.end(), pt.ids.begin() + long(id0),
                         pt.ids.begin() + long(pt.id_end[r]));
          place(pt.records[r], leaves);
        }
        id0 = pt.id_end[r];
        start0 = pt.start_end[r];
      }
    }
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
