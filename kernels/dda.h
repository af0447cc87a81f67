// Scalar 3D-DDA (Amanatides & Woo, "A Fast Voxel Traversal Algorithm", 1987) over the
// uniform grid (and, through kernels/two_level.h, the two-level grid), with the watertight
// triangle test per cell: the reference traversal the SIMD kernels are tested against, and the
// ray prologue (validity, slab clip, start cell) every scalar DDA shares.
#pragma once

#include <cfloat>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>

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

// Per-ray constants of the DDA, shared by every traversal of the grid (the scalar oracle in
// kernels/dda.cc, the sub-grid DDA in kernels/two_level_dda.h, the single-ray SIMD form).
struct DdaRay {
  float o[3];
  float d[3];
  float inv_d[3];  // 1 / d, 0 on parallel axes
  int step[3];     // +1 / -1, 0 on parallel axes (d = +-0 or 1 / d not finite)
  float t1;        // end of the ray's segment inside the grid
};

// The DDA prologue of one ray: validity (RayIsValid), the segment (tmin, tmax] (+inf tmax
// becomes FLT_MAX, so an overflowed t = inf is never a hit; NaN fails) and the slab clip to the
// grid box (ClipRayToGrid). Fills *r, the entry t *t0 and the finite tmax *tmax_f; false if the
// ray can hit nothing in the grid.
template <class GridT>
inline bool BeginDdaRay(const GridT& grid, float ox, float oy, float oz, float dx, float dy,
                        float dz, float tmin, float tmax, DdaRay* r, float* t0, float* tmax_f) {
  if (!RayIsValid(ox, oy, oz, dx, dy, dz)) return false;
  *tmax_f = tmax > FLT_MAX ? FLT_MAX : tmax;  // NaN stays NaN
  if (!(tmin < *tmax_f)) return false;
  r->o[0] = ox;
  r->o[1] = oy;
  r->o[2] = oz;
  r->d[0] = dx;
  r->d[1] = dy;
  r->d[2] = dz;
  *t0 = tmin;
  r->t1 = *tmax_f;
  bool parallel[3];
  if (!ClipRayToGrid(grid, r->o, r->d, *t0, r->t1, r->inv_d, parallel)) return false;
  for (int a = 0; a < 3; ++a) r->step[a] = parallel[a] ? 0 : (r->d[a] > 0.0f ? 1 : -1);
  return true;
}

// t of the boundary `boundary` (a cell index, or index + 1) along a stepping axis: recomputed
// from the index at every step, so the DDA does not drift.
template <class GridT>
inline float DdaBoundaryT(const GridT& grid, const DdaRay& r, int a, int boundary) {
  return (grid.lo[a] + float(boundary) * grid.cell_size[a] - r.o[a]) * r.inv_d[a];
}

// The cell of o + t0 d along one axis of a lattice (origin lo, inverse cell size inv_cell, res
// cells), clamped into [0, res): rounding may put the entry point just outside; NaN gives 0.
inline int EntryCell(float o, float d, float t0, float lo, float inv_cell, int res) {
  const float p = o + t0 * d;
  const float f = (p - lo) * inv_cell;
  int c = f >= 0.0f ? (f < float(res) ? int(f) : res - 1) : 0;  // NaN -> 0
  if (c >= res) c = res - 1;
  return c;
}

// Start cell of the DDA: the entry point o + t0 d, clamped into the grid (rounding may put it
// just outside; NaN gives 0), and the t of the first boundary per axis (+inf on parallel axes).
// Returns the flat cell index.
template <class GridT>
inline size_t DdaStartCell(const GridT& grid, const DdaRay& r, float t0, int cell[3],
                           float t_next[3]) {
  size_t idx = 0;
  const size_t stride[3] = {1, size_t(grid.res[0]), size_t(grid.res[0]) * size_t(grid.res[1])};
  for (int a = 0; a < 3; ++a) {
    const int c = EntryCell(r.o[a], r.d[a], t0, grid.lo[a], grid.inv_cell_size[a], grid.res[a]);
    cell[a] = c;
    idx += size_t(c) * stride[a];
    t_next[a] = r.step[a] == 0 ? std::numeric_limits<float>::infinity()
                               : DdaBoundaryT(grid, r, a, c + (r.step[a] > 0 ? 1 : 0));
  }
  return idx;
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

// The one scalar traversal behind TraceClosest / TraceAny and TraceClosestTwoLevel /
// TraceAnyTwoLevel (kernels/two_level.h): `two` null or empty is the flat grid. For callers that
// hold either structure (the SIMD kernels' scalar fallbacks).
struct TwoLevelGrid;
bool TraceClosestGrid(const Grid& grid, const TwoLevelGrid* two, const TriangleSoA& tris,
                      float ox, float oy, float oz, float dx, float dy, float dz, float tmin,
                      float tmax, RayHit* hit, TraceStats* stats);
bool TraceAnyGrid(const Grid& grid, const TwoLevelGrid* two, const TriangleSoA& tris, float ox,
                  float oy, float oz, float dx, float dy, float dz, float tmin, float tmax,
                  TraceStats* stats);

}  // namespace rs
