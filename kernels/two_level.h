// Two-level grid (Cell paper, section 3.8): top-level cells holding many triangles get an 8x8x8
// sub-grid whose occupancy bits and lookup data fit one 128-byte record, plus a scalar traversal
// over both levels (the oracle of the SIMD kernels) and the cost model that picks flat or
// two-level and lambda for BuildOptions::grid = kAuto.
#pragma once

#include <hwy/aligned_allocator.h>

#include <bit>
#include <cstddef>
#include <cstdint>

#include "include/raystream/raystream.h"
#include "kernels/dda.h"
#include "kernels/grid.h"
#include "kernels/triangle.h"

namespace rs {

inline constexpr int kSubRes = 8;  // sub-cells per axis
inline constexpr int kSubCells = kSubRes * kSubRes * kSubRes;

// Everything needed to traverse one 8x8x8 sub-grid, in one 128-byte record: on the Cell this is
// the one atomic 128-B load of section 3.4; here it is two cache lines read together.
//   bits       64 B  512 occupancy bits: word z, bit x + 8 y = sub-cell (x, y, z)
//   lo         12 B  sub-grid origin = the parent cell's lower corner, as the float DDA computes
//                    it (lo + float(c) * cell_size)
//   cell_size  12 B  parent cell size / 8 (exact in float)
//   inv_cell_size 12 B  8 x the parent's inverse cell size (exact)
//   first_leaf  4 B  leaf id of the first occupied sub-cell (see TwoLevelGrid::leaves)
//   rank       16 B  occupied sub-cells in words 0 .. z-1, so an occupied sub-cell's leaf is
//                    first_leaf + rank[z] + popcount(bits[z] below its bit): no per-sub-cell
//                    table is needed in the record
//   parent, refs 8 B the top-level cell, the references in its sub-cells (statistics)
// All 512 (begin, end) ranges (>= 2 KiB) cannot fit; storing ranks lets the leaf id be computed
// from the record alone, and the leaf's range (or bundle span) is one more read elsewhere.
// Records are stored 64-B aligned (hwy::AllocateAligned), so each is exactly two cache lines.
struct SubGridRecord {
  uint64_t bits[8];
  float lo[3];
  float cell_size[3];
  float inv_cell_size[3];
  uint32_t first_leaf;
  uint16_t rank[8];
  uint32_t parent;
  uint32_t refs;

  bool Occupied(int x, int y, int z) const { return (bits[z] >> (x + 8 * y)) & 1u; }
  // Leaf id of occupied sub-cell (x, y, z).
  uint32_t Leaf(int x, int y, int z) const {
    const int b = x + 8 * y;
    const uint64_t below = b == 0 ? 0 : bits[z] & (~uint64_t{0} >> (64 - b));
    return first_leaf + rank[z] + uint32_t(std::popcount(below));
  }
};
static_assert(sizeof(SubGridRecord) == 128, "one sub-grid record is one 128-byte load");

// The second level over a built uniform Grid (which stays a complete flat grid: its lists are
// still valid, so the flat scalar DDA keeps working on it). Leaves are the units whose triangles
// are tested: leaf c < grid.num_cells is top-level cell c (empty if the cell is refined), leaf
// grid.num_cells + k is the k-th occupied sub-cell (records in top-cell order, sub-cells in
// (z, y, x) order within a record).
struct TwoLevelGrid {
  size_t num_records = 0;
  hwy::AlignedFreeUniquePtr<SubGridRecord[]> records;
  hwy::AlignedFreeUniquePtr<uint64_t[]> refined;       // 1 bit per top-level cell
  hwy::AlignedFreeUniquePtr<uint32_t[]> refined_rank;  // records before each 64-cell word
  // Leaf lists, CSR (only num_cells, cell_begin, tri_ids, num_refs, occupied_cells and
  // max_per_cell are set; the geometry fields are unused).
  Grid leaves;
  size_t sub_refs = 0;         // references held by sub-cells
  size_t sub_leaves = 0;       // occupied sub-cells (leaves after the top-level cells)
  size_t refined_top_refs = 0; // references of the refined top-level cells (replaced by those)
  int threshold = 0;           // cells with more triangles than this were candidates

  bool empty() const { return num_records == 0; }
  bool Refined(size_t cell) const { return (refined[cell >> 6] >> (cell & 63)) & 1u; }
  // Precondition: Refined(cell).
  const SubGridRecord& Record(size_t cell) const {
    const uint64_t word = refined[cell >> 6];
    const uint64_t below = (cell & 63) == 0 ? 0 : word & (~uint64_t{0} >> (64 - (cell & 63)));
    return records[refined_rank[cell >> 6] + uint32_t(std::popcount(below))];
  }
  size_t Bytes() const;
};

// Cost model of one ray through a grid, in units of one empty cell step, from the surface
// area heuristic for grids: a random ray that hits the grid box passes through cell c with
// probability SA(c) / SA(box) (Cauchy-Crofton), so the expected cost is
//   sum over cells of SA(c) / SA(box) * (step + [occupied] visit + n_c * triangle)
// and a refined cell costs, per ray through it, subgrid + 8 steps (sum of the 512 sub-cells'
// SA over the cell's) + (occupied sub-cells * visit + sub references * triangle) / 64. Rays
// stopping at their first hit are ignored (as in the SAH), so the figures compare structures
// rather than predict times. The weights fit the SIMD stream kernel (bench/kernels/dda_bench.cc
// and a lambda sweep over bunny, spherebox, sponza, conference, amphitheater:16, AVX3/AVX2): a
// lane step costs ~3 cycles, a leaf visit (lookup, bundle call, the lane waiting) about as much as
// 4 steps, and a bundle-tested triangle a quarter of a step (8 triangles per vector). Entering
// a sub-grid (Descend: record read, start cell, saving the top-level state, plus the heavier
// per-lane geometry of sub-grid steps) is charged 16 steps: with less, sponza and
// amphitheater:16 were refined for a predicted 2-5 % gain and measured 7-10 % slower. With these
// weights the predicted best lambda (0.5-1) is the measured one on those scenes.
struct GridCostModel {
  double step = 1.0;
  double visit = 4.0;
  double triangle = 0.25;
  double subgrid = 16.0;
};

// kAuto keeps the two-level grid only if its cost is below this fraction of the flat grid's
// (the model's error is about 5-10 %, and the second level costs build time and memory).
inline constexpr double kTwoLevelMinGain = 0.9;

// Expected cost per ray of a flat grid with the given counts (model above).
double FlatGridCost(const Grid& grid, const GridCostModel& model = {});
// Expected cost per ray of the two-level grid.
double TwoLevelGridCost(const Grid& grid, const TwoLevelGrid& two, const GridCostModel& model = {});

// A lower bound of TwoLevelGridCost for any refinement of cells above `threshold`: each such
// cell at min(its leaf cost, the cheapest possible sub-grid). Lets kAuto skip building a second
// level that cannot pay off.
double TwoLevelCostBound(const Grid& grid, int threshold, const GridCostModel& model = {});

// Builds the second level. A top-level cell is refined iff it holds more than `threshold`
// triangles and, when `by_cost` is set, its sub-grid is cheaper under `model` than testing the
// list (cells that do not pay off are left as leaves). Sub-cells are binned conservatively like
// the top level (kernels/grid_binning.h), with a margin of 1e-3 sub-cell plus the grid's ulp
// term. Bounded like the top level (grid.h): a cell is never refined if its sub-cells would be
// shorter than kMinCellMargins x that ulp term on some axis, nor if its sub-cell references
// would take the sub-cells' total past GridRefBudget(non-degenerate triangles) (cells in index
// order; such a cell stays a leaf), so sub_refs <= that budget for any input.
// With no refined cell, `out` is empty (num_records = 0) and the grid is flat. Throws rs::Error
// if an allocation fails. threads (BuildOptions::build_threads): the candidate cells are refined
// on that many threads (parts of about equal references); the result is the same bit for bit.
void BuildTwoLevel(const Grid& grid, const TriangleSoA& tris, int threshold, bool by_cost,
                   const GridCostModel& model, TwoLevelGrid* out, int threads = 1);

// The lambda among {0.5, 1, 2, 4, 8} whose flat grid has the lowest cost under `model`, from
// bounding-box counts (CountGridBoxes: no lists are built; references and occupied cells are
// slightly overestimated, equally for every candidate), trying them in increasing order and
// stopping at the first that costs more than the one before. *cost (may be null) gets its cost.
// The counts run on `threads` threads (the result does not depend on it).
float ChooseLambda(const TriangleSoA& tris, int max_resolution, const GridCostModel& model = {},
                   double* cost = nullptr, int threads = 1);
// The same, given ComputeGridBounds(tris).
float ChooseLambda(const TriangleSoA& tris, const GridBounds& bounds, int max_resolution,
                   const GridCostModel& model = {}, double* cost = nullptr, int threads = 1);

// Scalar traversal of the two-level grid: TraceClosest / TraceAny (kernels/dda.h) with the same
// contracts, stepping into a refined cell's sub-grid (TraverseSubGrid in two_level_dda.h) and
// testing leaf lists with the mailboxed watertight test; the same code as the flat DDA
// (kernels/dda.cc). `two` may be empty (then this is the flat DDA). The oracle of the SIMD
// two-level kernels; same cell_steps (top and sub cells).
bool TraceClosestTwoLevel(const Grid& grid, const TwoLevelGrid& two, const TriangleSoA& tris,
                          float ox, float oy, float oz, float dx, float dy, float dz, float tmin,
                          float tmax, RayHit* hit, TraceStats* stats);
bool TraceAnyTwoLevel(const Grid& grid, const TwoLevelGrid& two, const TriangleSoA& tris,
                      float ox, float oy, float oz, float dx, float dy, float dz, float tmin,
                      float tmax, TraceStats* stats);

}  // namespace rs
