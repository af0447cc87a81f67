// Scalar 3D-DDA over the uniform grid (see dda.h): slab clip, start cell, per-axis stepping
// with boundary t recomputed from the cell index (no drift), occupancy bit before CSR lists,
// mailboxed watertight tests, candidate hits kept across cells.
#include "kernels/dda.h"

#include <cfloat>
#include <cmath>
#include <limits>

namespace rs {
namespace {

// The ids of the last 8 triangles tested by this ray. A triangle spanning several cells is
// usually met again in the next few cells; skipping it is safe because its earlier result
// (hit kept as candidate, or t beyond a candidate that only shrinks) still holds.
class Mailbox {
 public:
  bool Contains(uint32_t id) const {
    bool found = false;
    for (const uint32_t m : ids_) found |= m == id;  // branch-free: the compiler vectorizes it
    return found;
  }
  void Insert(uint32_t id) { ids_[next_++ & 7u] = id; }

 private:
  uint32_t ids_[8] = {UINT32_MAX, UINT32_MAX, UINT32_MAX, UINT32_MAX,
                      UINT32_MAX, UINT32_MAX, UINT32_MAX, UINT32_MAX};
  uint32_t next_ = 0;
};

template <bool kAnyHit>
bool Traverse(const Grid& grid, const TriangleSoA& tris, float ox, float oy, float oz, float dx,
              float dy, float dz, float tmin, float tmax, RayHit* hit, TraceStats* stats) {
  if (grid.empty() || !RayIsValid(ox, oy, oz, dx, dy, dz)) return false;
  // (tmin, tmax] must be non-empty; NaN fails. +inf tmax becomes FLT_MAX so that an overflowed
  // t = inf is never a hit.
  const float tmax_f = tmax > FLT_MAX ? FLT_MAX : tmax;  // NaN stays NaN
  if (!(tmin < tmax_f)) return false;

  const float o[3] = {ox, oy, oz};
  const float d[3] = {dx, dy, dz};
  // Slab clip to the grid box. Axes with d = +-0 (or 1/d overflowing) are parallel: the origin
  // must lie inside that slab, and the DDA never steps along them.
  float t0 = tmin, t1 = tmax_f;
  float inv_d[3];
  bool parallel[3];
  if (!ClipRayToGrid(grid, o, d, t0, t1, inv_d, parallel)) return false;

  // Start cell: the entry point, clamped into the grid (rounding may put it just outside).
  // Per axis: step direction and t of the next cell boundary.
  int cell[3], step[3];
  float t_next[3];
  size_t idx = 0;
  const size_t stride[3] = {1, size_t(grid.res[0]), size_t(grid.res[0]) * size_t(grid.res[1])};
  for (int a = 0; a < 3; ++a) {
    const float p = o[a] + t0 * d[a];
    const float f = (p - grid.lo[a]) * grid.inv_cell_size[a];
    int c = f >= 0.0f ? (f < float(grid.res[a]) ? int(f) : grid.res[a] - 1) : 0;  // NaN -> 0
    if (c >= grid.res[a]) c = grid.res[a] - 1;
    cell[a] = c;
    idx += size_t(c) * stride[a];
    if (parallel[a]) {
      step[a] = 0;
      t_next[a] = std::numeric_limits<float>::infinity();
    } else {
      step[a] = d[a] > 0.0f ? 1 : -1;
      const int boundary = c + (step[a] > 0 ? 1 : 0);
      t_next[a] = (grid.lo[a] + float(boundary) * grid.cell_size[a] - o[a]) * inv_d[a];
    }
  }

  // The watertight test reads the vertex components in the ray's (kx, ky, kz) order: pick the
  // 9 SoA arrays once per ray.
  const WatertightRay ray = PrepareWatertightRay(ox, oy, oz, dx, dy, dz);
  const float* v[3][3];
  for (int k = 0; k < 3; ++k) {
    v[k][0] = tris.p[k][ray.kx].data();
    v[k][1] = tris.p[k][ray.ky].data();
    v[k][2] = tris.p[k][ray.kz].data();
  }
  const uint64_t* occupancy = grid.occupancy.get();
  const uint32_t* cell_begin = grid.cell_begin.get();
  const uint32_t* tri_ids = grid.tri_ids.get();

  Mailbox mailbox;
  uint64_t cell_steps = 0, triangle_tests = 0;
  float best_t = tmax_f;
  uint32_t best_prim = UINT32_MAX;
  TriHit best{};
  bool found = false;
  for (;;) {
    ++cell_steps;
    const float t_exit = std::fmin(t_next[0], std::fmin(t_next[1], t_next[2]));
    if ((occupancy[idx >> 6] >> (idx & 63)) & 1u) {
      const uint32_t end = cell_begin[idx + 1];
      for (uint32_t k = cell_begin[idx]; k < end; ++k) {
        const uint32_t id = tri_ids[k];
        if (mailbox.Contains(id)) continue;
        mailbox.Insert(id);
        ++triangle_tests;
        TriHit th;
        if (!IntersectWatertightPermuted(ray, v[0][0][id], v[0][1][id], v[0][2][id], v[1][0][id],
                                         v[1][1][id], v[1][2][id], v[2][0][id], v[2][1][id],
                                         v[2][2][id], tmin, best_t, &th)) {
          continue;
        }
        if constexpr (kAnyHit) {
          found = true;
          break;
        } else {
          // th.t <= best_t here; on a tie the lower id wins
          if (th.t < best_t || id < best_prim) {
            best_t = th.t;
            best_prim = id;
            best = th;
            found = true;
          }
        }
      }
      if constexpr (kAnyHit) {
        if (found) break;
      }
    }
    // The candidate (or the end of the segment) lies before the next cell: done.
    if (best_t <= t_exit || t1 <= t_exit) break;
    // Step into the neighbour across the nearest boundary.
    const int a = t_next[0] < t_next[1] ? (t_next[0] < t_next[2] ? 0 : 2)
                                        : (t_next[1] < t_next[2] ? 1 : 2);
    cell[a] += step[a];
    if (cell[a] < 0 || cell[a] >= grid.res[a]) break;
    idx = step[a] > 0 ? idx + stride[a] : idx - stride[a];
    const int boundary = cell[a] + (step[a] > 0 ? 1 : 0);
    t_next[a] = (grid.lo[a] + float(boundary) * grid.cell_size[a] - o[a]) * inv_d[a];
  }
  if (stats != nullptr) {
    stats->cell_steps += cell_steps;
    stats->triangle_tests += triangle_tests;
  }
  if constexpr (!kAnyHit) {
    if (found) {
      hit->t = best.t;
      hit->u = best.u;
      hit->v = best.v;
      hit->prim = int32_t(best_prim);
    }
  }
  return found;
}

}  // namespace

bool TraceClosest(const Grid& grid, const TriangleSoA& tris, float ox, float oy, float oz,
                  float dx, float dy, float dz, float tmin, float tmax, RayHit* hit,
                  TraceStats* stats) {
  hit->t = std::numeric_limits<float>::infinity();
  hit->u = hit->v = 0.0f;
  hit->prim = -1;
  return Traverse<false>(grid, tris, ox, oy, oz, dx, dy, dz, tmin, tmax, hit, stats);
}

bool TraceAny(const Grid& grid, const TriangleSoA& tris, float ox, float oy, float oz, float dx,
              float dy, float dz, float tmin, float tmax, TraceStats* stats) {
  return Traverse<true>(grid, tris, ox, oy, oz, dx, dy, dz, tmin, tmax, nullptr, stats);
}

}  // namespace rs
