// rs::Accel's private state (the triangle SoA, the uniform grid, the optional second level and
// the SIMD traversal data), visible to the kernels, the renderer and tests through AccelImpl
// (this header is internal: the installed header declares Impl only).
#pragma once

#include <algorithm>
#include <cstddef>

#include "include/raystream/raystream.h"
#include "kernels/dda_simd.h"
#include "kernels/grid.h"
#include "kernels/irregular.h"
#include "kernels/irregular_simd.h"
#include "kernels/triangle.h"
#include "kernels/two_level.h"
#include "streams/block_memory.h"
#include "streams/ray_stream.h"

namespace rs {

struct Accel::Impl {
  BlockCache cache;        // first: every array below is allocated through it during a build
                           // (Accel::Rebuild takes their blocks back) and freed before it
  bool built = false;      // false after a Rebuild that threw
  // The Accel's frame (ChooseFrameShift, kernels/grid.h): the triangles and every structure
  // below are at world - shift; rays are translated at the entry points (ForEachFramePiece).
  float shift[3] = {0.0f, 0.0f, 0.0f};
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

  bool Shifted() const { return shift[0] != 0.0f || shift[1] != 0.0f || shift[2] != 0.0f; }
};

// The origins [first, first + n) of `rays` in the Accel's frame, fl(o - shift), into to[a][0, n),
// and zeros after them to PaddedSize(n).
inline void FrameOrigins(const Accel::Impl& m, const RayStreamView& rays, size_t first, size_t n,
                         float* const to[3]) {
  const float* const from[3] = {rays.ox, rays.oy, rays.oz};
  for (int a = 0; a < 3; ++a) {
    for (size_t i = 0; i < n; ++i) to[a][i] = from[a][first + i] - m.shift[a];
    std::fill(to[a] + n, to[a] + PaddedSize(n), 0.0f);
  }
}

// Calls trace(piece, first) on consecutive pieces of rays [0, count) (arrays readable to
// PaddedSize(count)) whose origins are in the Accel's frame: the caller's rays in one piece when
// the frame is the world's, else kFramePiece rays at a time (whole 64-ray packets) with
// fl(o - shift) in a stack copy and the other arrays the caller's. The kernels behind
// Accel::Intersect and Occluded see only such pieces, and so must any caller of the kernels on
// an Accel's structures (AccelImpl).
inline constexpr size_t kFramePiece = 1024;
template <class Trace>
void ForEachFramePiece(const Accel::Impl& m, const RayStreamView& rays, size_t count,
                       Trace&& trace) {
  if (!m.Shifted()) return trace(SubView(rays, 0, count), size_t{0});
  alignas(kStreamAlign) float o[3][kFramePiece];
  float* const to[3] = {o[0], o[1], o[2]};
  for (size_t first = 0; first < count; first += kFramePiece) {
    const size_t n = std::min(kFramePiece, count - first);
    FrameOrigins(m, rays, first, n, to);
    RayStreamView piece = SubView(rays, first, n);
    piece.ox = o[0], piece.oy = o[1], piece.oz = o[2];
    trace(piece, first);
  }
}

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
