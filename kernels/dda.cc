// The scalar 3D-DDA over the uniform grid and the two-level grid (see dda.h, two_level.h): one
// traversal for both (a flat grid is a two-level grid with no refined cell): slab clip, start
// cell, per-axis stepping with boundary t recomputed from the cell index (no drift), occupancy
// bit before the lists, refined cells through their sub-grid, mailboxed watertight tests,
// candidate hits kept across cells.
#include "kernels/dda.h"

#include <cfloat>
#include <cmath>
#include <limits>

#include "kernels/irregular.h"
#include "kernels/two_level.h"
#include "kernels/two_level_dda.h"

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

// The triangle tests of one ray: the ray's watertight setup, the 9 SoA arrays in its (kx, ky,
// kz) order, the mailbox and the candidate. Visit(list, begin, end) tests a leaf's ids; true iff
// kAnyHit and a hit was found. On equal t the lower triangle id wins.
template <bool kAnyHit>
class LeafTester {
 public:
  LeafTester(const TriangleSoA& tris, float ox, float oy, float oz, float dx, float dy, float dz,
             float tmin, float tmax_f)
      : ray_(PrepareWatertightRay(ox, oy, oz, dx, dy, dz)), tmin_(tmin), best_t(tmax_f) {
    for (int k = 0; k < 3; ++k) {
      v_[k][0] = tris.p[k][ray_.kx].data();
      v_[k][1] = tris.p[k][ray_.ky].data();
      v_[k][2] = tris.p[k][ray_.kz].data();
    }
  }

  bool Visit(const uint32_t* ids, uint32_t begin, uint32_t end) {
    for (uint32_t k = begin; k < end; ++k) {
      const uint32_t id = ids[k];
      if (mailbox_.Contains(id)) continue;
      mailbox_.Insert(id);
      ++triangle_tests;
      TriHit th;
      if (!IntersectWatertightPermuted(ray_, v_[0][0][id], v_[0][1][id], v_[0][2][id],
                                       v_[1][0][id], v_[1][1][id], v_[1][2][id], v_[2][0][id],
                                       v_[2][1][id], v_[2][2][id], tmin_, best_t, &th)) {
        continue;
      }
      if constexpr (kAnyHit) {
        found = true;
        return true;
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
    return false;
  }

  // Adds the counts to `stats` (may be null) and writes the candidate to `hit` (closest hit).
  bool Finish(uint64_t cell_steps, RayHit* hit, TraceStats* stats) const {
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

 private:
  WatertightRay ray_;
  const float* v_[3][3];
  float tmin_;
  Mailbox mailbox_;

 public:
  float best_t;
  uint32_t best_prim = UINT32_MAX;
  TriHit best{};
  bool found = false;
  uint64_t triangle_tests = 0;
};

// `two` is null for a flat grid; else occupied refined cells are traversed through their
// sub-grid (TraverseSubGrid) and leaves are tested from the leaf lists.
template <bool kAnyHit>
bool Traverse(const Grid& grid, const TwoLevelGrid* two, const TriangleSoA& tris, float ox,
              float oy, float oz, float dx, float dy, float dz, float tmin, float tmax,
              RayHit* hit, TraceStats* stats) {
  if (grid.empty()) return false;
  DdaRay r;
  float t0, tmax_f;
  if (!BeginDdaRay(grid, ox, oy, oz, dx, dy, dz, tmin, tmax, &r, &t0, &tmax_f)) return false;
  const float t1 = r.t1;
  int cell[3];
  float t_next[3];
  size_t idx = DdaStartCell(grid, r, t0, cell, t_next);
  const size_t stride[3] = {1, size_t(grid.res[0]), size_t(grid.res[0]) * size_t(grid.res[1])};

  const uint32_t* list_begin = two == nullptr ? grid.cell_begin.get() : two->leaves.cell_begin.get();
  const uint32_t* list_ids = two == nullptr ? grid.tri_ids.get() : two->leaves.tri_ids.get();
  const uint64_t* occupancy = grid.occupancy.get();

  LeafTester<kAnyHit> tester(tris, ox, oy, oz, dx, dy, dz, tmin, tmax_f);
  uint64_t cell_steps = 0;
  // Tests leaf `leaf` (a top-level cell, or a sub-cell's leaf); true iff any-hit found.
  auto visit = [&](size_t leaf) {
    return tester.Visit(list_ids, list_begin[leaf], list_begin[leaf + 1]);
  };
  float t_enter = t0;
  int enter_axis = -1;
  for (;;) {
    ++cell_steps;
    const float t_exit = std::fmin(t_next[0], std::fmin(t_next[1], t_next[2]));
    if ((occupancy[idx >> 6] >> (idx & 63)) & 1u) {
      if (two != nullptr && two->Refined(idx)) {
        const SubExit e = TraverseSubGrid(two->Record(idx), r, t_enter, enter_axis,
                                          &tester.best_t, &cell_steps, visit);
        if (e != SubExit::kLeft) break;
      } else if (visit(idx)) {
        break;
      }
    }
    // The candidate (or the end of the segment) lies before the next cell: done.
    if (tester.best_t <= t_exit || t1 <= t_exit) break;
    // Step into the neighbour across the nearest boundary (ties to the last axis).
    const int a = t_next[0] < t_next[1] ? (t_next[0] < t_next[2] ? 0 : 2)
                                        : (t_next[1] < t_next[2] ? 1 : 2);
    cell[a] += r.step[a];
    if (cell[a] < 0 || cell[a] >= grid.res[a]) break;
    idx = r.step[a] > 0 ? idx + stride[a] : idx - stride[a];
    t_next[a] = DdaBoundaryT(grid, r, a, cell[a] + (r.step[a] > 0 ? 1 : 0));
    t_enter = t_exit;
    enter_axis = a;
  }
  return tester.Finish(cell_steps, hit, stats);
}

// The irregular grid (kernels/irregular.h): from the start voxel's cell, test the cell's list,
// stop when the candidate or the segment end lies before the exit of the cell's box, else move
// to the voxel across the nearest far face (the other axes: o + t_exit d, clamped into the box).
// Every step moves the voxel by at least one on the exit axis and never back on any axis
// (IrregularNextVoxel), so a ray enters at most vres[0] + vres[1] + vres[2] cells.
template <bool kAnyHit>
bool TraverseIrregular(const IrregularGrid& g, const TriangleSoA& tris, float ox, float oy,
                       float oz, float dx, float dy, float dz, float tmin, float tmax,
                       RayHit* hit, TraceStats* stats) {
  if (g.empty()) return false;
  DdaRay r;
  float t0, tmax_f;
  if (!BeginDdaRay(g, ox, oy, oz, dx, dy, dz, tmin, tmax, &r, &t0, &tmax_f)) return false;
  int v[3];
  IrregularStartVoxel(g, r, t0, v);
  const uint32_t* list_begin = g.lists.cell_begin.get();
  const uint32_t* list_ids = g.lists.tri_ids.get();
  LeafTester<kAnyHit> tester(tris, ox, oy, oz, dx, dy, dz, tmin, tmax_f);
  uint64_t cell_steps = 0;
  float t_enter = t0;
  for (;;) {
    ++cell_steps;
    const uint32_t cell = g.Lookup(v);
    const int32_t* box = g.Box(cell);
    if (tester.Visit(list_ids, list_begin[cell], list_begin[cell + 1])) break;
    float t_face[3];
    for (int a = 0; a < 3; ++a) {
      t_face[a] = r.step[a] == 0 ? std::numeric_limits<float>::infinity()
                                 : IrregularFaceT(g, r, a, r.step[a] > 0 ? box[3 + a] : box[a]);
    }
    // The ray is covered up to t_exit, or up to t_enter if the box lies behind it (the lookup
    // clamped the exit point of the cell before into this box): t never decreases, so a ray
    // cannot cycle between two overlapping boxes.
    const float t_exit =
        std::fmax(t_enter, std::fmin(t_face[0], std::fmin(t_face[1], t_face[2])));
    if (tester.best_t <= t_exit || r.t1 <= t_exit) break;
    const int a = t_face[0] < t_face[1] ? (t_face[0] < t_face[2] ? 0 : 2)
                                        : (t_face[1] < t_face[2] ? 1 : 2);
    if (!IrregularNextVoxel(g, r, box, a, t_exit, v)) break;
    t_enter = t_exit;
  }
  return tester.Finish(cell_steps, hit, stats);
}

const TwoLevelGrid* SecondLevel(const TwoLevelGrid* two) {
  return two != nullptr && !two->empty() ? two : nullptr;
}

}  // namespace

bool TraceClosestGrid(const Grid& grid, const TwoLevelGrid* two, const TriangleSoA& tris,
                      float ox, float oy, float oz, float dx, float dy, float dz, float tmin,
                      float tmax, RayHit* hit, TraceStats* stats) {
  hit->t = std::numeric_limits<float>::infinity();
  hit->u = hit->v = 0.0f;
  hit->prim = -1;
  return Traverse<false>(grid, SecondLevel(two), tris, ox, oy, oz, dx, dy, dz, tmin, tmax, hit,
                         stats);
}

bool TraceAnyGrid(const Grid& grid, const TwoLevelGrid* two, const TriangleSoA& tris, float ox,
                  float oy, float oz, float dx, float dy, float dz, float tmin, float tmax,
                  TraceStats* stats) {
  return Traverse<true>(grid, SecondLevel(two), tris, ox, oy, oz, dx, dy, dz, tmin, tmax,
                        nullptr, stats);
}

bool TraceClosest(const Grid& grid, const TriangleSoA& tris, float ox, float oy, float oz,
                  float dx, float dy, float dz, float tmin, float tmax, RayHit* hit,
                  TraceStats* stats) {
  return TraceClosestGrid(grid, nullptr, tris, ox, oy, oz, dx, dy, dz, tmin, tmax, hit, stats);
}

bool TraceAny(const Grid& grid, const TriangleSoA& tris, float ox, float oy, float oz, float dx,
              float dy, float dz, float tmin, float tmax, TraceStats* stats) {
  return TraceAnyGrid(grid, nullptr, tris, ox, oy, oz, dx, dy, dz, tmin, tmax, stats);
}

bool TraceClosestIrregular(const IrregularGrid& g, const TriangleSoA& tris, float ox, float oy,
                           float oz, float dx, float dy, float dz, float tmin, float tmax,
                           RayHit* hit, TraceStats* stats) {
  hit->t = std::numeric_limits<float>::infinity();
  hit->u = hit->v = 0.0f;
  hit->prim = -1;
  return TraverseIrregular<false>(g, tris, ox, oy, oz, dx, dy, dz, tmin, tmax, hit, stats);
}

bool TraceAnyIrregular(const IrregularGrid& g, const TriangleSoA& tris, float ox, float oy,
                       float oz, float dx, float dy, float dz, float tmin, float tmax,
                       TraceStats* stats) {
  return TraverseIrregular<true>(g, tris, ox, oy, oz, dx, dy, dz, tmin, tmax, nullptr, stats);
}

bool TraceClosestTwoLevel(const Grid& grid, const TwoLevelGrid& two, const TriangleSoA& tris,
                          float ox, float oy, float oz, float dx, float dy, float dz, float tmin,
                          float tmax, RayHit* hit, TraceStats* stats) {
  return TraceClosestGrid(grid, &two, tris, ox, oy, oz, dx, dy, dz, tmin, tmax, hit, stats);
}

bool TraceAnyTwoLevel(const Grid& grid, const TwoLevelGrid& two, const TriangleSoA& tris,
                      float ox, float oy, float oz, float dx, float dy, float dz, float tmin,
                      float tmax, TraceStats* stats) {
  return TraceAnyGrid(grid, &two, tris, ox, oy, oz, dx, dy, dz, tmin, tmax, stats);
}

}  // namespace rs
