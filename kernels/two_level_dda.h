// The 3D-DDA through one 8x8x8 sub-grid record, shared (inline) by the scalar two-level traversal
// and the SIMD kernels' per-lane sub-grid step, so both visit the same sub-cells with the same
// float arithmetic as the top-level DDA (boundary t recomputed from the cell index, no drift).
#pragma once

#include <cstdint>
#include <limits>

#include "kernels/dda.h"  // DdaRay
#include "kernels/two_level.h"

namespace rs {

enum class SubExit : int {
  kLeft = 0,   // the ray left the sub-grid: continue in the top level
  kDone = 1,   // the candidate hit or the segment end lies before the current sub-cell's exit
  kFound = 2,  // visit() returned true (any-hit)
};

// The start of a sub-grid traversal: sub-cell c and boundary t per axis (see TraverseSubGrid).
inline void SubGridStart(const SubGridRecord& rec, const DdaRay& r, float t_enter, int enter_axis,
                         int c[3], float t_next[3]) {
  for (int a = 0; a < 3; ++a) {
    if (a == enter_axis) {
      c[a] = r.step[a] > 0 ? 0 : kSubRes - 1;
    } else {
      c[a] = EntryCell(r.o[a], r.d[a], t_enter, rec.lo[a], rec.inv_cell_size[a], kSubRes);
    }
    if (r.step[a] == 0) {
      t_next[a] = std::numeric_limits<float>::infinity();
    } else {
      t_next[a] = DdaBoundaryT(rec, r, a, c[a] + (r.step[a] > 0 ? 1 : 0));
    }
  }
}

// Steps ray r through the sub-grid of `rec`, starting where it entered the parent cell at
// t_enter across axis enter_axis (-1: the ray starts inside the parent cell; that axis's
// sub-cell is then the entry face, exactly, and the others come from o + t_enter d clamped to
// [0, 8)). For each occupied sub-cell, calls visit(leaf) (which may lower *best_t); returns
// kFound if visit returns true, kDone if *best_t or r.t1 <= the sub-cell's exit t, else kLeft
// when the ray steps out of the 8x8x8 block. Adds the sub-cells visited to *steps. At most
// 22 sub-cells are visited. Axis ties go to the last axis, as in the top-level DDA.
template <class Visit>
inline SubExit TraverseSubGrid(const SubGridRecord& rec, const DdaRay& r, float t_enter,
                               int enter_axis, const float* best_t, uint64_t* steps,
                               Visit&& visit) {
  int c[3];
  float t_next[3];
  SubGridStart(rec, r, t_enter, enter_axis, c, t_next);
  for (;;) {
    ++*steps;
    const float t_exit = t_next[0] < t_next[1] ? (t_next[0] < t_next[2] ? t_next[0] : t_next[2])
                                               : (t_next[1] < t_next[2] ? t_next[1] : t_next[2]);
    if (rec.Occupied(c[0], c[1], c[2])) {
      if (visit(rec.Leaf(c[0], c[1], c[2]))) return SubExit::kFound;
    }
    if (*best_t <= t_exit || r.t1 <= t_exit) return SubExit::kDone;
    const int a = t_next[0] < t_next[1] ? (t_next[0] < t_next[2] ? 0 : 2)
                                        : (t_next[1] < t_next[2] ? 1 : 2);
    c[a] += r.step[a];
    if (c[a] < 0 || c[a] >= kSubRes) return SubExit::kLeft;
    t_next[a] = DdaBoundaryT(rec, r, a, c[a] + (r.step[a] > 0 ? 1 : 0));
  }
}

}  // namespace rs
