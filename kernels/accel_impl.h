// rs::Accel's private state (the triangle SoA and the uniform grid), visible to the kernels,
// the SIMD traversal to come and the renderer through Accel::impl().
#pragma once

#include "include/raystream/raystream.h"
#include "kernels/grid.h"
#include "kernels/triangle.h"

namespace rs {

struct Accel::Impl {
  TriangleSoA triangles;  // indexed by the mesh's triangle ids (degenerate ones flagged)
  Grid grid;              // empty (num_cells = 0) when no triangle can be hit
  double build_seconds = 0.0;
};

}  // namespace rs
