// rs::Accel's private state (the triangle SoA, the uniform grid, the optional second level and
// the SIMD traversal data), visible to the kernels, the renderer and tests through AccelImpl
// (this header is internal: the installed header declares Impl only).
#pragma once

#include "include/raystream/raystream.h"
#include "kernels/dda_simd.h"
#include "kernels/grid.h"
#include "kernels/irregular.h"
#include "kernels/irregular_simd.h"
#include "kernels/triangle.h"
#include "kernels/two_level.h"
#include "streams/block_memory.h"

namespace rs {

struct Accel::Impl {
  BlockCache cache;        // first: every array below is allocated through it during a build
                           // (Accel::Rebuild takes their blocks back) and freed before it
  bool built = false;      // false after a Rebuild that threw
  TriangleSoA triangles;   // indexed by the mesh's triangle ids (degenerate ones flagged)
  Grid grid;               // empty (num_cells = 0) when no triangle can be hit; always a
                           // complete flat grid (also when two_level refines some cells)
  TwoLevelGrid two_level;  // empty for a flat grid
  IrregularGrid irregular;  // empty unless BuildOptions::grid = kIrregular
  IrregularDda irregular_dda;
  DdaGrid dda;             // borrows grid, two_level, triangles, irregular_dda (Impl never
                           // moves: unique_ptr)
  DdaOptions dda_options;
  bool packets = true;     // BuildOptions::packets
  float lambda = 0.0f;
  double cost_estimate = 0.0;
  double flat_cost_estimate = 0.0;
  double build_seconds = 0.0;
};

// The state of a built Accel; throws rs::Error for a moved-from one or one whose last Rebuild
// failed.
const Accel::Impl& AccelImpl(const Accel& accel);

namespace ref {

// The scalar traversal of the same structure (TraceClosest / TraceClosestTwoLevel per ray): the
// oracle of Accel::Intersect / Occluded, which run the SIMD stream kernels. Same contracts and
// results; triangle_tests counts differ (the scalar code mailboxes), cell_steps are identical.
void AccelIntersect(const Accel::Impl& impl, const RayStreamView& rays, const HitStreamView& hits,
                    TraceStats* stats = nullptr);
void AccelOccluded(const Accel::Impl& impl, const RayStreamView& rays, int32_t* occluded,
                   TraceStats* stats = nullptr);

}  // namespace ref
}  // namespace rs
