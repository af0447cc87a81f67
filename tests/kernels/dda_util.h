// Helpers of the traversal tests (dda_simd_test, packet_dda_test): a grid with its SIMD
// traversal data built over a mesh, and test rays as a padded SoA stream.
#pragma once

#include <vector>

#include "include/raystream/raystream.h"
#include "kernels/dda_simd.h"
#include "kernels/grid.h"
#include "kernels/triangle.h"
#include "kernels/two_level.h"
#include "streams/ray_stream.h"
#include "tests/kernels/geometry_util.h"

namespace rs::test {

// A grid (flat if threshold < 0, else two-level with every cell above `threshold` refined) and
// the SIMD traversal data over it. Not movable: the DdaGrid points into it.
struct Built {
  TriangleSoA tris;
  Grid grid;
  TwoLevelGrid two;
  DdaGrid dda;
  Built(const MeshView& mesh, float lambda, int threshold) {
    BuildTriangleSoA(mesh, &tris);
    BuildGrid(tris, lambda, 512, &grid);
    if (threshold >= 0) BuildTwoLevel(grid, tris, threshold, false, GridCostModel{}, &two);
    BuildDdaGrid(grid, &two, tris, &dda);
  }
  Built(const Built&) = delete;
  Built& operator=(const Built&) = delete;
};

inline RayStream MakeStream(const std::vector<Ray>& rays) {
  RayStream s;
  for (const Ray& r : rays) {
    s.Push(r.o[0], r.o[1], r.o[2], r.d[0], r.d[1], r.d[2], r.tmin, r.tmax, 0, 1, 1, 1, 0,
           RayKind::kPrimary);
  }
  s.FillPadding();
  return s;
}

}  // namespace rs::test
