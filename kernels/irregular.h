// Irregular grid (Perard-Gayot, Kalojanov, Slusallek, "GPU Ray Tracing using Irregular Grids",
// Computer Graphics Forum 36(2), 2017): cells of varying size on a fine virtual lattice. Each cell
// of a coarse uniform grid holds an octree of at most the depth its triangle count asks for
// (d <= 3: 2^d finest sub-cells per axis; nodes with few triangles are not split), neighbouring
// cells are merged where the grid cost model says the merged cell is cheaper, and each non-empty
// cell's traversal box is then expanded over the empty cells around it, so a ray leaves empty
// space in one step. A ray steps from cell to cell
// by the exit point of the current cell's box: one lookup (top-level entry, then the sub-cell
// entry) finds the next cell; the cell's triangles are tested with the same watertight test as
// the uniform and two-level grids, so every structure gives the same hits.
#pragma once

#include <hwy/aligned_allocator.h>

#include <cstddef>
#include <cstdint>

#include "include/raystream/raystream.h"
#include "kernels/dda.h"
#include "kernels/grid.h"
#include "kernels/triangle.h"
#include "kernels/two_level.h"

namespace rs {

inline constexpr int kIrregularMaxDepth = 3;  // at most 8 sub-cells per top cell and axis

// Geometry. The lattice has vres[a] = top_res[a] << depth voxels per axis over the box [lo, hi]
// (the box of the uniform grid the build starts from); voxel boundary i on axis a lies at
//   lo[a] + float(i) * voxel_size[a]
// (voxel_size = the top cell size / 2^depth, exact; for i = k << depth this is the top grid's
// boundary k, bit for bit). A point's voxel is floor((p - lo) * inv_voxel_size), clamped to the
// lattice.
// Lookup of voxel v: top cell c = v >> depth (x fastest), entry e = top[c]; the top cell is cut
// into 2^s sub-cells per axis, s = e & 3 (s <= depth); with m = (1 << depth) - 1 and
// q = depth - s, the voxel's cell is
//   fine[(e >> 2) + ((v.x & m) >> q) + (((v.y & m) >> q) << s) + (((v.z & m) >> q) << 2s)].
// Cells. Cell k has a traversal box box[8 k .. 8 k + 5] = lo x y z, hi x y z in voxels (hi
// exclusive; box[8 k + 6], box[8 k + 7] are 0): its own region, expanded over empty cells, so
// a box never overlaps the region of another non-empty cell (boxes may overlap each other over
// empty space: IrregularNextVoxel copes). lists.cell_begin[k] ..
// lists.cell_begin[k + 1] index its triangle ids in lists.tri_ids (ascending); a triangle is
// listed in every cell whose own region, grown by `margin`, it overlaps (the conservative test
// of the uniform grid, kernels/grid_binning.h).
struct IrregularGrid {
  float lo[3] = {0.0f, 0.0f, 0.0f};
  float hi[3] = {0.0f, 0.0f, 0.0f};
  int top_res[3] = {0, 0, 0};
  int depth = 0;
  int vres[3] = {0, 0, 0};
  float voxel_size[3] = {0.0f, 0.0f, 0.0f};
  float inv_voxel_size[3] = {0.0f, 0.0f, 0.0f};
  double margin[3] = {0.0, 0.0, 0.0};
  size_t num_top = 0;
  size_t num_fine = 0;
  size_t num_cells = 0;
  hwy::AlignedFreeUniquePtr<uint32_t[]> top;   // num_top entries
  hwy::AlignedFreeUniquePtr<uint32_t[]> fine;  // num_fine cell ids
  hwy::AlignedFreeUniquePtr<int32_t[]> box;    // 8 per cell
  // CSR lists (only num_cells, cell_begin, tri_ids, num_refs, occupied_cells and max_per_cell
  // are set), so the triangle bundles of the SIMD kernels are built from it as from any grid.
  Grid lists;
  // Build statistics.
  size_t base_cells = 0;     // cells before merging
  size_t merged = 0;         // merges done
  size_t expanded = 0;       // cells whose box grew
  double region_cost = 0.0;  // IrregularGridCost over the cells' own regions (before expansion)

  bool empty() const { return num_cells == 0; }
  uint32_t Lookup(const int v[3]) const {
    const int x = v[0] >> depth, y = v[1] >> depth, z = v[2] >> depth;
    const uint32_t e = top[size_t(x) + size_t(top_res[0]) * (size_t(y) + size_t(top_res[1]) * size_t(z))];
    const int s = int(e & 3u), q = depth - s, m = (1 << depth) - 1;
    const uint32_t local = uint32_t((v[0] & m) >> q) + (uint32_t((v[1] & m) >> q) << s) +
                           (uint32_t((v[2] & m) >> q) << (2 * s));
    return fine[(e >> 2) + local];
  }
  const int32_t* Box(uint32_t cell) const { return box.get() + 8 * size_t(cell); }
  size_t Bytes() const {
    return num_top * 4 + num_fine * 4 + num_cells * 32 +
           (num_cells == 0 ? 0 : (num_cells + 1) * 4 + lists.num_refs * 4);
  }
};

// Cost of one ray through an irregular grid (the model of two_level.h: a ray crosses cell k with
// probability SA(box_k) / SA(grid box)): sum over cells of SA(k) / SA(box) (irregular_step +
// [listed] visit + n_k triangle). An irregular step (a point lookup through two tables and the
// cell's box) is charged `kIrregularStep` uniform steps.
inline constexpr double kIrregularStep = 2.0;
double IrregularGridCost(const IrregularGrid& g, const GridCostModel& model = {});

struct IrregularOptions {
  float top_lambda = 0.125f;  // top-level cells per triangle
  float sub_lambda = 1.0f;    // a top cell of n triangles is cut to depth round(log8(sub_lambda n))
  int leaf_triangles = 2;     // octree nodes with more triangles are split (to that depth)
  bool merge = true;
  bool expand = true;
  GridCostModel model;        // the merge criterion (IrregularGridCost's weights)
};

// Builds the irregular grid over the non-degenerate triangles of `tris` (bounds as for
// BuildGrid). No triangle: empty grid. Bounded like the uniform grid: the top grid is one
// (BuildGrid, within GridRefBudget), sub-cells are never shorter than kMinCellMargins x the ulp
// term of the coordinates (the depth is lowered), and a top cell is not subdivided if its
// sub-cell references would take the total past GridRefBudget. Merging only lowers the cell
// count; a merged list is the union of its parts. Throws rs::Error if memory runs out.
void BuildIrregularGrid(const TriangleSoA& tris, const GridBounds& bounds,
                        const IrregularOptions& options, int max_resolution, IrregularGrid* out);

// Scalar traversal (the oracle of the SIMD kernels): TraceClosest / TraceAny (kernels/dda.h)
// with the same contracts and results, stepping cell to cell: the exit t of the current cell's
// box is the nearest of its far faces (lo[a] + float(face) * voxel_size[a] - o[a]) * inv_d[a]
// (ties to the last axis, as the DDA), the next voxel is the face's neighbour on that axis and,
// on the other axes, the voxel of o + t_exit d clamped into the current box. cell_steps counts
// the cells entered.
bool TraceClosestIrregular(const IrregularGrid& g, const TriangleSoA& tris, float ox, float oy,
                           float oz, float dx, float dy, float dz, float tmin, float tmax,
                           RayHit* hit, TraceStats* stats);
bool TraceAnyIrregular(const IrregularGrid& g, const TriangleSoA& tris, float ox, float oy,
                       float oz, float dx, float dy, float dz, float tmin, float tmax,
                       TraceStats* stats);

// Start voxel of a ray entering at t0 (clamped into the lattice, NaN -> 0), and the step from a
// cell: given the current box and the exit axis a, the next voxel (false if it leaves the
// lattice). Shared by the scalar and SIMD traversals.
inline void IrregularStartVoxel(const IrregularGrid& g, const DdaRay& r, float t0, int v[3]) {
  for (int a = 0; a < 3; ++a) {
    v[a] = EntryCell(r.o[a], r.d[a], t0, g.lo[a], g.inv_voxel_size[a], g.vres[a]);
  }
}

// t of voxel boundary `face` along stepping axis a.
inline float IrregularFaceT(const IrregularGrid& g, const DdaRay& r, int a, int face) {
  return (g.lo[a] + float(face) * g.voxel_size[a] - r.o[a]) * r.inv_d[a];
}

// The voxel after leaving `box` across its far face on axis a at t_exit, given in v the voxel
// whose cell owns `box`: on a, the face's neighbour; on the others, the voxel of o + t_exit d
// clamped into the box (the exit point lies on the box's face; rounding may put it just outside)
// and never behind v in the ray's direction. So every axis moves monotonically along the ray
// and the exit axis by at least one voxel: no ray enters more than vres[0] + vres[1] + vres[2]
// cells, even where expanded boxes overlap and rounding disagrees at a corner. False if the
// voxel leaves the lattice.
inline bool IrregularNextVoxel(const IrregularGrid& g, const DdaRay& r, const int32_t* box, int a,
                               float t_exit, int v[3]) {
  for (int b = 0; b < 3; ++b) {
    if (b == a || r.step[b] == 0) continue;  // parallel axes keep their voxel
    const float p = r.o[b] + t_exit * r.d[b];
    const float f = (p - g.lo[b]) * g.inv_voxel_size[b];
    const int lo = box[b], hi = box[3 + b] - 1;
    const int c = f >= float(lo) ? (f < float(hi) ? int(f) : hi) : lo;  // NaN -> lo
    v[b] = r.step[b] > 0 ? (c > v[b] ? c : v[b]) : (c < v[b] ? c : v[b]);
  }
  v[a] = r.step[a] > 0 ? box[3 + a] : box[a] - 1;
  return v[a] >= 0 && v[a] < g.vres[a];
}

}  // namespace rs
