// Uniform grid over a TriangleSoA: padded bounds, density-heuristic resolution, an occupancy
// bit array (1 bit per cell) and CSR cell -> triangle id lists, built in two passes with no
// per-cell allocation. The DDA (kernels/dda.h) reads the bits before touching the lists.
#pragma once

#include <hwy/aligned_allocator.h>

#include <cstddef>
#include <cstdint>

#include "kernels/triangle.h"

namespace rs {

struct Grid {
  // Bounds of the non-degenerate triangles, enlarged on every side by a pad (about 1e-5 of
  // the largest extent plus 1e-6 of the largest |coordinate|), so hits lie strictly inside.
  float lo[3] = {0.0f, 0.0f, 0.0f};
  float hi[3] = {0.0f, 0.0f, 0.0f};
  int res[3] = {0, 0, 0};  // cells per axis; all 0 for an empty grid
  // Cell (x, y, z) spans [lo + x * cell_size, lo + (x + 1) * cell_size] per axis.
  float cell_size[3] = {0.0f, 0.0f, 0.0f};
  float inv_cell_size[3] = {0.0f, 0.0f, 0.0f};
  // Binning margin (world units): a triangle is listed in every cell whose box, enlarged by
  // the margin, it overlaps. 1e-3 of a cell plus a few ulps of the coordinates; it covers the
  // rounding of the float DDA, so the DDA can never step past a cell that holds the hit.
  double margin[3] = {0.0, 0.0, 0.0};
  size_t num_cells = 0;
  size_t num_refs = 0;  // length of tri_ids
  size_t occupied_cells = 0;
  size_t max_per_cell = 0;
  // Cell index = x + res[0] * (y + res[1] * z).
  hwy::AlignedFreeUniquePtr<uint64_t[]> occupancy;  // (num_cells + 63) / 64 words
  hwy::AlignedFreeUniquePtr<uint32_t[]> cell_begin;  // num_cells + 1 offsets into tri_ids
  hwy::AlignedFreeUniquePtr<uint32_t[]> tri_ids;     // ascending ids within each cell

  bool empty() const { return num_cells == 0; }
  size_t CellIndex(int x, int y, int z) const {
    return size_t(x) + size_t(res[0]) * (size_t(y) + size_t(res[1]) * size_t(z));
  }
  bool Occupied(size_t cell) const { return (occupancy[cell >> 6] >> (cell & 63)) & 1u; }
  size_t Bytes() const {
    return num_cells == 0 ? 0
                          : ((num_cells + 63) / 64) * 8 + (num_cells + 1) * 4 + num_refs * 4;
  }
};

// Bounds that keep every grid within a fixed factor of its triangle count:
//  - Cells no smaller than the coordinates allow. The binning margin holds 4 FLT_EPSILON
//    max|coordinate| (the float DDA's rounding); a cell edge below that separates nothing the
//    DDA can tell apart, and lists every triangle in ~(1 + 2 margin / cell)^2 cells or more (73
//    per triangle for a radius-1 sphere at 2e5). At kMinCellMargins = 2 such terms a small
//    triangle grown by the margin on both sides is at most about a cell wide: 2 cells per axis.
//    SetGridGeometry lowers the resolution of finer axes, and a sub-grid is built only where its
//    cells keep that size.
//  - References: BuildGrid lists at most GridRefBudget(valid triangles) references; a
//    resolution that would list more (identical or overlapping triangles, long thin ones) is
//    coarsened before the lists are allocated (EstimateGridRefs), and again if the binning
//    itself passes the budget. The second level adds at most another budget (two_level.h).
//  - Cells: more than kMaxGridCells, or cell arrays larger than the physical memory, are
//    refused with rs::Error naming the resolution and the bytes (only BuildOptions can ask
//    for that many: the heuristic asks for lambda cells per triangle).
inline constexpr double kMinCellMargins = 2.0;
inline constexpr size_t kMaxRefsPerTriangle = 8;
inline constexpr size_t kRefSlack = size_t{1} << 16;  // small scenes are never coarsened
inline constexpr size_t kMaxGridCells = size_t{UINT32_MAX} - 1;  // 32-bit cell ids and offsets
inline size_t GridRefBudget(size_t num_valid) {
  const size_t budget = kMaxRefsPerTriangle * num_valid + kRefSlack;
  return budget < size_t{UINT32_MAX} - 1 ? budget : size_t{UINT32_MAX} - 2;
}

// Resolution from the density heuristic (Cleary & Wyvill): res_axis = extent_axis *
// cbrt(lambda * N / volume), rounded to nearest, clamped to [1, max_resolution]. Axes whose
// share would be < 1 cell (flat or thin scenes, zero extent) get 1 cell, and the cell budget
// lambda * N is spread over the remaining axes (res = extent * (lambda*N / area)^(1/2), or
// lambda*N cells along a single axis). N = 0 or lambda <= 0 gives 1 x 1 x 1.
void ComputeGridResolution(const double extent[3], size_t num_triangles, double lambda,
                           int max_resolution, int res[3]);

// The grid bounds: the float min/max of the non-degenerate triangles' vertices, enlarged by the
// pad described at Grid::lo and rounded outwards; num_valid = non-degenerate triangles.
struct GridBounds {
  float lo[3] = {0.0f, 0.0f, 0.0f};
  float hi[3] = {0.0f, 0.0f, 0.0f};
  size_t num_valid = 0;
};
GridBounds ComputeGridBounds(const TriangleSoA& tris);

// The frame a far-away scene is built in. The DDA rounds to the ulps of the coordinates it
// computes with, so bounds far from the origin (extent << |coordinate|) would allow no cells finer
// than those ulps (kMinCellMargins): a radius-1 sphere at 2e5 got cells of 0.22 and 101
// triangles per occupied cell. rs::Accel stores its triangles at world - shift instead, and
// translates each ray's origin the same way (fl(o - shift)) before tracing. Per axis, shift is
// the midpoint of the bounds if they lie on one side of 0 at least their extent away from it,
// else 0 (the frame gains nothing there). The translation of every coordinate inside the bounds
// is exact: it and the shift are multiples of ulp(m), m the smaller |bound|, and
// |v - shift| <= extent <= m < 2^24 ulp(m). Rays starting near the scene are translated exactly
// too; the DDA's rounding is then that of a scene at the origin, including its limit: a boundary's
// t is off by about 1.5 ulps of the origin's distance, which the margin's 1e-3 cell covers up to
// about 5,000 cells away (tests/kernels/grid_bounds_test.cc: rays from 2,000 cells away find
// exactly what a float brute force finds). From farther, a ray through a vertex may miss: 4 of
// 20,000 from the world origin to the radius-1 sphere at 2.7e5 in a 69^3 grid, head-on ones;
// none in world coordinates, whose cells there were 0.22 wide.
void ChooseFrameShift(const GridBounds& bounds, float shift[3]);

// Resets *grid and fills its geometry for `lambda` (bounds, res, cell sizes, margin, num_cells),
// without lists: the resolution of ComputeGridResolution, lowered on axes whose cells would be
// shorter than kMinCellMargins x the margin's ulp term (4 FLT_EPSILON max|bound|). What
// BuildGrid starts from before binning. num_valid = 0 gives an empty grid. Throws rs::Error if
// the grid would have more than kMaxGridCells cells or its cell arrays would not fit in the
// physical memory.
void SetGridGeometry(const GridBounds& bounds, float lambda, int max_resolution, Grid* grid);

// The references BuildGrid would list on `geometry`, estimated without binning everything: the
// exact sum of the bounding-box cell counts (an upper bound) if it is at most `limit`, else
// that sum scaled by the exact cells / box cells ratio of up to 256 triangles sampled with
// probability proportional to their box (systematic PPS sampling: one huge triangle among many
// small ones is seen; the estimate is unbiased). Deterministic.
size_t EstimateGridRefs(const TriangleSoA& tris, const Grid& geometry, size_t limit);

// Bounding-box statistics of the triangles on a grid geometry, without building lists: the sum
// of bounding-box cell counts (>= the references BuildGrid makes) and the cells some box touches
// (>= occupied). Cheap enough to compare several lambdas before building one grid.
struct GridBoxCounts {
  size_t cells = 0;
  size_t occupied = 0;
  size_t refs = 0;
};
// threads: BuildOptions::build_threads (the counts do not depend on it).
GridBoxCounts CountGridBoxes(const TriangleSoA& tris, const Grid& geometry, int threads = 1);

// Builds the grid over the non-degenerate triangles of `tris`. With none, the grid is empty
// (num_cells = 0, never hit). Binning is conservative: each triangle goes into every cell its
// bounding box overlaps that also passes a triangle/box separating-axis test in double
// (Akenine-Moller 2001: plane + 9 edge axes) against the cell enlarged by `margin`. The box
// ranges come from a SIMD float pass widened by a proven slack, and the SAT runs only on the
// axes that span more than one cell (kernels/grid_binning.h), so a triangle may also be listed
// in a cell its box reaches within ~1e-6 (res + 3) cells; ids ascend within each cell.
// The resolution is SetGridGeometry's, coarsened (the cell count divided by at least 2 per
// step) while the references would exceed GridRefBudget(num_valid): num_refs is always within
// the budget, so memory is O(triangles + cells) for any input.
// Preconditions: lambda > 0 and finite, max_resolution >= 1 (Accel checks them).
// Throws rs::Error (what, how many bytes) if the cells cannot be held (SetGridGeometry) or an
// allocation fails; never aborts.
// threads (BuildOptions::build_threads): the binning and the lists run on that many threads
// (std::thread, parts of the triangles); the grid is the same bit for bit for any count.
void BuildGrid(const TriangleSoA& tris, float lambda, int max_resolution, Grid* grid,
               int threads = 1);
// The same, given ComputeGridBounds(tris) (so a caller that has them does not recompute them).
void BuildGrid(const TriangleSoA& tris, const GridBounds& bounds, float lambda, int max_resolution,
               Grid* grid, int threads = 1);

}  // namespace rs
