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

// Resets *grid and fills its geometry for `lambda` (bounds, res, cell sizes, margin, num_cells),
// without lists: what BuildGrid does before binning. num_valid = 0 gives an empty grid.
void SetGridGeometry(const GridBounds& bounds, float lambda, int max_resolution, Grid* grid);

// Bounding-box statistics of the triangles on a grid geometry, without building lists: the sum
// of bounding-box cell counts (>= the references BuildGrid makes) and the cells some box touches
// (>= occupied). Cheap enough to compare several lambdas before building one grid.
struct GridBoxCounts {
  size_t cells = 0;
  size_t occupied = 0;
  size_t refs = 0;
};
GridBoxCounts CountGridBoxes(const TriangleSoA& tris, const Grid& geometry);

// Builds the grid over the non-degenerate triangles of `tris`. With none, the grid is empty
// (num_cells = 0, never hit). Binning is conservative: each triangle goes into every cell its
// bounding box overlaps that also passes a triangle/box separating-axis test in double
// (Akenine-Moller 2001: plane + 9 edge axes) against the cell enlarged by `margin`. The box
// ranges come from a SIMD float pass widened by a proven slack, and the SAT runs only on the
// axes that span more than one cell (kernels/grid_binning.h), so a triangle may also be listed
// in a cell its box reaches within ~1e-6 (res + 3) cells; ids ascend within each cell.
// Preconditions: lambda > 0 and finite, max_resolution >= 1 (Accel checks them).
// Throws rs::Error if the references do not fit 32-bit offsets.
void BuildGrid(const TriangleSoA& tris, float lambda, int max_resolution, Grid* grid);
// The same, given ComputeGridBounds(tris) (so a caller that has them does not recompute them).
void BuildGrid(const TriangleSoA& tris, const GridBounds& bounds, float lambda, int max_resolution,
               Grid* grid);

}  // namespace rs
