// Scalar 3D-DDA (Amanatides & Woo, "A Fast Voxel Traversal Algorithm", 1987) over the
// uniform grid, with the watertight triangle test per cell: the reference traversal that the
// SIMD stream kernels will be tested against.
#pragma once

#include <cmath>
#include <cstdint>

#include "include/raystream/raystream.h"
#include "kernels/grid.h"
#include "kernels/triangle.h"

namespace rs {

// Slab clip of a ray (o, d) to the box [lo, hi] of a grid (any type with float lo[3], hi[3]),
// shared by every scalar DDA (kernels/dda.cc, the Cell simulator's resumable DDA). Narrows
// [t0, t1]; axes with d = +-0 (or 1/d overflowing) are parallel: the origin must lie inside
// that slab and the DDA never steps along them (inv_d = 0). False if the ray misses the box.
template <class GridT>
inline bool ClipRayToGrid(const GridT& grid, const float o[3], const float d[3], float& t0,
                          float& t1, float inv_d[3], bool parallel[3]) {
  for (int a = 0; a < 3; ++a) {
    const float inv = 1.0f / d[a];
    parallel[a] = !(d[a] != 0.0f && std::isfinite(inv));
    if (parallel[a]) {
      inv_d[a] = 0.0f;
      if (o[a] < grid.lo[a] || o[a] > grid.hi[a]) return false;
      continue;
    }
    inv_d[a] = inv;
    float ta = (grid.lo[a] - o[a]) * inv;
    float tb = (grid.hi[a] - o[a]) * inv;
    if (ta > tb) {
      const float tmp = ta;
      ta = tb;
      tb = tmp;
    }
    t0 = ta > t0 ? ta : t0;
    t1 = tb < t1 ? tb : t1;
  }
  return t0 <= t1;
}

// Result of one traced ray: prim = -1 and t = +inf for a miss.
struct RayHit {
  float t;
  float u;
  float v;
  int32_t prim;
};

// Closest hit of one ray with t in (tmin, tmax] (tmax may be +inf). The ray is clipped to the
// grid bounds, stepped cell by cell (empty cells are skipped on their occupancy bit without
// reading the CSR lists), and each listed triangle is tested once (an 8-entry mailbox skips
// ids tested recently). A hit beyond the current cell is kept as the candidate; traversal
// stops when the candidate's t <= the current cell's exit t or the ray leaves the grid.
// On equal t the lower triangle id wins (as in rs::ref), so results do not depend on the
// visiting order. Rays with a NaN/Inf origin or direction component, a zero direction (all
// |d| < kMinDirection), or NaN tmin/tmax never hit; every ray terminates after at most
// res[0] + res[1] + res[2] cell steps. Adds cell steps and triangle tests to `stats`.
// Never allocates or throws.
bool TraceClosest(const Grid& grid, const TriangleSoA& tris, float ox, float oy, float oz,
                  float dx, float dy, float dz, float tmin, float tmax, RayHit* hit,
                  TraceStats* stats);

// True if any triangle is hit with t in (tmin, tmax]; returns at the first one found.
// Same ray validity rules and stats as TraceClosest.
bool TraceAny(const Grid& grid, const TriangleSoA& tris, float ox, float oy, float oz, float dx,
              float dy, float dz, float tmin, float tmax, TraceStats* stats);

}  // namespace rs
