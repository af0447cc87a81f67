// The SPE's 128-B ray record (ray + resumable traversal state) and a resumable 3D-DDA over the
// flat or two-level grid that mirrors rs::TraceClosestTwoLevel / TraceAnyTwoLevel
// (kernels/two_level.cc; flat: kernels/dda.cc) operation for operation, so a ray that stops at
// each occupied cell or sub-cell (to wait for its triangles) and resumes later walks exactly the
// reference's cells with exactly its floats. The triangle test is raystream's own
// IntersectWatertightPermuted on bundles in local store.
#pragma once

#include <cfloat>
#include <cmath>
#include <cstdint>
#include <limits>

#include "kernels/dda.h"
#include "kernels/triangle.h"
#include "kernels/two_level.h"
#include "sim/cell_image.h"

namespace rs::sim {

enum RayState : uint8_t {
  kRayFresh = 0,   // not yet set up: DdaBegin next
  kRayAtCell = 1,  // at cell `idx` (or sub-cell `sub_c` if in_sub), not yet examined
  kRayTraced = 2,  // traversal finished (best_* final): shade (closest hit) next
};

// One ray in the SPE's ring buffer (8 quadwords of ray, 8 of traversal state).
struct alignas(128) RayRecord {
  // ray
  float o[3];
  float d[3];
  float tmin;
  float tmax;
  uint32_t pixel;
  float w[3];
  int32_t depth;
  int32_t kind;       // RayKind
  uint16_t subtile;   // pixel-buffer slot of the sub-tile the ray's pixel belongs to
  uint8_t state;      // RayState
  int8_t enter_axis;  // axis the current top-level cell was entered across (-1: started inside)
  float t_enter;      // t where the current top-level cell was entered
  // traversal (top level)
  float t_next[3];
  float t1;  // end of the ray's segment inside the grid
  int32_t cell[3];
  uint32_t idx;  // current top-level cell
  int8_t step[3];
  uint8_t in_sub;  // 1: inside the sub-grid of cell idx, at sub-cell sub_c
  float t_exit;    // exit t of the current top-level cell
  float best_t;    // closest: candidate t (starts at the clamped tmax)
  float best_u;
  float best_v;
  uint32_t best_prim;  // UINT32_MAX: no candidate
  // traversal (sub-grid)
  uint32_t sub_record;  // index of the SubGridRecord of cell idx
  uint8_t sub_c[3];
  uint8_t pad;
};
static_assert(sizeof(RayRecord) == 128);

// Prologue of kernels/dda.cc Traverse: validity, slab clip, start cell, per-axis step and first
// boundary t. Returns false if the ray cannot hit anything (then it is finished: a miss, or an
// unoccluded shadow ray); else r is at its first cell in state kRayAtCell.
inline bool DdaBegin(const GridHeader& grid, RayRecord& r) {
  r.best_prim = UINT32_MAX;
  r.best_u = r.best_v = 0.0f;
  r.best_t = std::numeric_limits<float>::infinity();
  if (grid.empty != 0 || !RayIsValid(r.o[0], r.o[1], r.o[2], r.d[0], r.d[1], r.d[2])) {
    return false;
  }
  const float tmax_f = r.tmax > FLT_MAX ? FLT_MAX : r.tmax;  // NaN stays NaN
  if (!(r.tmin < tmax_f)) return false;
  const float o[3] = {r.o[0] - grid.shift[0], r.o[1] - grid.shift[1], r.o[2] - grid.shift[2]};
  const float* d = r.d;
  float t0 = r.tmin, t1 = tmax_f;
  float inv_d[3];
  bool parallel[3];
  if (!ClipRayToGrid(grid, o, d, t0, t1, inv_d, parallel)) return false;
  r.t_enter = t0;
  r.enter_axis = -1;
  r.in_sub = 0;
  size_t idx = 0;
  const size_t stride[3] = {1, size_t(grid.res[0]), size_t(grid.res[0]) * size_t(grid.res[1])};
  for (int a = 0; a < 3; ++a) {
    const float p = o[a] + t0 * d[a];
    const float f = (p - grid.lo[a]) * grid.inv_cell_size[a];
    int c = f >= 0.0f ? (f < float(grid.res[a]) ? int(f) : grid.res[a] - 1) : 0;  // NaN -> 0
    if (c >= grid.res[a]) c = grid.res[a] - 1;
    r.cell[a] = c;
    idx += size_t(c) * stride[a];
    if (parallel[a]) {
      r.step[a] = 0;
      r.t_next[a] = std::numeric_limits<float>::infinity();
    } else {
      r.step[a] = d[a] > 0.0f ? 1 : -1;
      const int boundary = c + (r.step[a] > 0 ? 1 : 0);
      r.t_next[a] = (grid.lo[a] + float(boundary) * grid.cell_size[a] - o[a]) * inv_d[a];
    }
  }
  r.idx = static_cast<uint32_t>(idx);
  r.t1 = t1;
  r.best_t = tmax_f;
  r.state = kRayAtCell;
  return true;
}

// The end of the reference loop body after a cell: stop if the candidate (or the end of the
// segment) lies before the next cell, else step across the nearest boundary. Returns false when
// the ray is finished (stopped or left the grid).
inline bool DdaStep(const GridHeader& grid, RayRecord& r, float t_exit) {
  if (r.best_t <= t_exit || r.t1 <= t_exit) return false;
  const float* t_next = r.t_next;
  const int a =
      t_next[0] < t_next[1] ? (t_next[0] < t_next[2] ? 0 : 2) : (t_next[1] < t_next[2] ? 1 : 2);
  r.cell[a] += r.step[a];
  if (r.cell[a] < 0 || r.cell[a] >= grid.res[a]) return false;
  const uint32_t stride = a == 0   ? 1u
                          : a == 1 ? uint32_t(grid.res[0])
                                   : uint32_t(grid.res[0]) * uint32_t(grid.res[1]);
  r.idx = r.step[a] > 0 ? r.idx + stride : r.idx - stride;
  const int boundary = r.cell[a] + (r.step[a] > 0 ? 1 : 0);
  const float inv = 1.0f / r.d[a];  // the prologue's inv_d for a stepping axis
  const float o = r.o[a] - grid.shift[a];
  r.t_next[a] = (grid.lo[a] + float(boundary) * grid.cell_size[a] - o) * inv;
  r.t_enter = t_exit;
  r.enter_axis = static_cast<int8_t>(a);
  return true;
}

// --- Sub-grid (kernels/two_level_dda.h TraverseSubGrid, made resumable) ---------------------

enum class SubResult {
  kOccupied,  // at an occupied sub-cell (not yet visited)
  kDone,      // the candidate or the segment end lies before the sub-cell's exit: finished
  kLeft,      // stepped out of the 8x8x8 block: continue in the top level
};

// The sub-grid steps take the Accel's frame `shift` (GridHeader::shift): the ray's origin is
// translated by it as in DdaBegin.
// t of the next sub-cell boundary along axis a (TraverseSubGrid's formula; +inf if parallel).
inline float SubTNext(const SubGridRecord& rec, const RayRecord& r, const float shift[3], int a) {
  if (r.step[a] == 0) return std::numeric_limits<float>::infinity();
  const int boundary = int(r.sub_c[a]) + (r.step[a] > 0 ? 1 : 0);
  const float o = r.o[a] - shift[a];
  return (rec.lo[a] + float(boundary) * rec.cell_size[a] - o) * (1.0f / r.d[a]);
}

// Entry into the sub-grid of the current top-level cell at r.t_enter across r.enter_axis.
inline void SubInit(const SubGridRecord& rec, RayRecord& r, const float shift[3]) {
  for (int a = 0; a < 3; ++a) {
    int c;
    if (a == r.enter_axis) {
      c = r.step[a] > 0 ? 0 : kSubRes - 1;
    } else {
      const float p = (r.o[a] - shift[a]) + r.t_enter * r.d[a];
      const float f = (p - rec.lo[a]) * rec.inv_cell_size[a];
      c = f >= 0.0f ? (f < float(kSubRes) ? int(f) : kSubRes - 1) : 0;  // NaN -> 0
      if (c >= kSubRes) c = kSubRes - 1;
    }
    r.sub_c[a] = static_cast<uint8_t>(c);
  }
  r.in_sub = 1;
}

inline float SubTExit(const SubGridRecord& rec, const RayRecord& r, const float shift[3]) {
  const float t0 = SubTNext(rec, r, shift, 0), t1 = SubTNext(rec, r, shift, 1),
              t2 = SubTNext(rec, r, shift, 2);
  return t0 < t1 ? (t0 < t2 ? t0 : t2) : (t1 < t2 ? t1 : t2);
}

// After the current sub-cell (visited or empty): stop, step to the next sub-cell (kOccupied
// means "moved", the new sub-cell not yet examined) or leave the block.
inline SubResult SubStep(const SubGridRecord& rec, RayRecord& r, const float shift[3]) {
  const float t_next[3] = {SubTNext(rec, r, shift, 0), SubTNext(rec, r, shift, 1),
                           SubTNext(rec, r, shift, 2)};
  const float t_exit = t_next[0] < t_next[1] ? (t_next[0] < t_next[2] ? t_next[0] : t_next[2])
                                             : (t_next[1] < t_next[2] ? t_next[1] : t_next[2]);
  if (r.best_t <= t_exit || r.t1 <= t_exit) return SubResult::kDone;
  const int a =
      t_next[0] < t_next[1] ? (t_next[0] < t_next[2] ? 0 : 2) : (t_next[1] < t_next[2] ? 1 : 2);
  const int c = int(r.sub_c[a]) + r.step[a];
  if (c < 0 || c >= kSubRes) {
    r.in_sub = 0;
    return SubResult::kLeft;
  }
  r.sub_c[a] = static_cast<uint8_t>(c);
  return SubResult::kOccupied;
}

// From the current sub-cell (not yet examined) to the first occupied one (*leaf set), or
// finished / left. Adds the sub-cells examined to *steps.
inline SubResult SubAdvance(const SubGridRecord& rec, RayRecord& r, const float shift[3],
                            uint64_t* steps, uint32_t* leaf) {
  for (;;) {
    ++*steps;
    if (rec.Occupied(r.sub_c[0], r.sub_c[1], r.sub_c[2])) {
      *leaf = rec.Leaf(r.sub_c[0], r.sub_c[1], r.sub_c[2]);
      return SubResult::kOccupied;
    }
    const SubResult s = SubStep(rec, r, shift);
    if (s != SubResult::kOccupied) return s;
  }
}

// Listing 1 of the paper: steps through empty cells on their occupancy bits (in local store)
// until an occupied cell (returns true; r.t_exit set, cell not yet stepped past) or the ray is
// finished (false). Adds the cells examined to *steps (the reference's cell_steps).
inline bool DdaAdvance(const GridHeader& grid, const uint64_t* occupancy, RayRecord& r,
                       uint64_t* steps) {
  for (;;) {
    ++*steps;
    const float t_exit = std::fmin(r.t_next[0], std::fmin(r.t_next[1], r.t_next[2]));
    if ((occupancy[r.idx >> 6] >> (r.idx & 63)) & 1u) {
      r.t_exit = t_exit;
      return true;
    }
    if (!DdaStep(grid, r, t_exit)) return false;
  }
}

// Tests ray `r` (prepared as `wr`) against the live lanes of `count` bundles. Closest hit: keeps
// the reference's candidate rule (t <= candidate, lower id on ties). Any hit (shadow rays):
// returns true at the first hit. Returns the number of triangle tests in *tests.
template <bool kAnyHit>
inline bool IntersectBundles(const WatertightRay& wr, const TriangleBundle* bundles, uint32_t count,
                             RayRecord& r, uint64_t* tests) {
  const int kx = wr.kx, ky = wr.ky, kz = wr.kz;
  bool found = false;
  for (uint32_t k = 0; k < count; ++k) {
    const TriangleBundle& p = bundles[k];
    for (int lane = 0; lane < 4; ++lane) {
      const uint32_t id = p.id[lane];
      if (id == UINT32_MAX) continue;
      ++*tests;
      TriHit th;
      if (!IntersectWatertightPermuted(wr, p.p[0][kx][lane], p.p[0][ky][lane], p.p[0][kz][lane],
                                       p.p[1][kx][lane], p.p[1][ky][lane], p.p[1][kz][lane],
                                       p.p[2][kx][lane], p.p[2][ky][lane], p.p[2][kz][lane], r.tmin,
                                       r.best_t, &th)) {
        continue;
      }
      if constexpr (kAnyHit) {
        return true;
      } else {
        if (th.t < r.best_t || id < r.best_prim) {
          r.best_t = th.t;
          r.best_u = th.u;
          r.best_v = th.v;
          r.best_prim = id;
          found = true;
        }
      }
    }
  }
  return found;
}

}  // namespace rs::sim
