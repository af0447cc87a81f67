// SIMD traversal of the irregular grid (kernels/irregular.h) over SoA ray streams, Highway
// dynamic dispatch (kernels/irregular_stream.cc): one ray per lane, lanes refilled as rays
// finish; the lookup, the box's exit t and the next voxel a vector of lanes at a time, each
// visited cell's triangles with the 1-ray x 4-triangle bundle kernel.
#pragma once

#include <cstddef>
#include <cstdint>

#include <hwy/aligned_allocator.h>

#include "include/raystream/raystream.h"
#include "kernels/irregular.h"
#include "kernels/tri_bundles.h"
#include "kernels/triangle.h"

namespace rs {

// What the SIMD traversal reads: the grid and its cells' triangles as bundles. Borrows `grid`
// and `tris` (they must outlive it, unmodified).
// cells[4 k .. 4 k + 3]: what a step reads of cell k, in one 16-B record (64-B aligned array):
// its traversal box per axis as lo | hi << 16 (IrregularGrid::box; the lattice has at most 65535
// voxels per axis), and its first bundle; its bundle count is the next record's first bundle
// minus its own (a record past the last cell holds the total).
struct IrregularDda {
  const IrregularGrid* grid = nullptr;
  const TriangleSoA* tris = nullptr;
  TriBundles bundles;
  hwy::AlignedFreeUniquePtr<int32_t[]> cells;
  bool empty() const { return grid == nullptr || grid->empty(); }
  size_t Bytes() const { return bundles.Bytes() + (grid == nullptr ? 0 : 16 * (grid->num_cells + 1)); }
};

void BuildIrregularDda(const IrregularGrid& grid, const TriangleSoA& tris, IrregularDda* out,
                       int threads = 1);

// Closest hit / any hit of rays[0, size), the contracts of IntersectStreamDda /
// OccludedStreamDda (kernels/dda_simd.h). Results (prim, t, u, v bit for bit) and cell_steps
// equal TraceClosestIrregular / TraceAnyIrregular on every target; triangle_tests counts bundle
// lanes holding a triangle (no mailbox). No allocation; never throws.
void IntersectStreamIrregular(const IrregularDda& g, const RayStreamView& rays,
                              const HitStreamView& hits, TraceStats* stats);
void OccludedStreamIrregular(const IrregularDda& g, const RayStreamView& rays, int32_t* occluded,
                             TraceStats* stats);

}  // namespace rs
