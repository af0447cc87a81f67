// SIMD 3D-DDA traversal with Highway dynamic dispatch: SoA ray streams with one ray per lane
// (lanes refilled from the stream as rays finish; kernels/dda_stream.cc), and the Cell paper's
// single-ray form (one ray, x y z in the lanes of a 4-lane vector, section 3.3;
// kernels/dda_single.cc) for comparison. Flat and two-level grids (DdaGrid, kernels/dda_grid.h);
// cells are tested with the 1-ray x 4-triangle bundle kernels (kernels/tri_intersect.h).
#pragma once

#include <cstddef>
#include <cstdint>

#include "include/raystream/raystream.h"
#include "streams/ray_stream.h"  // SubView
#include "kernels/dda.h"
#include "kernels/dda_grid.h"
#include "kernels/grid.h"
#include "kernels/triangle.h"
#include "kernels/two_level.h"

namespace rs {

inline constexpr int kMaxMicroCache = 16;

struct DdaOptions {
  // Micro-cache entries (Cell paper section 3.5): the last `micro_cache` leaves looked up by any
  // lane, with their bundle spans; 0 disables it, at most kMaxMicroCache. See dda_stream.cc for
  // what it does (and does not) save on a CPU.
  int micro_cache = 8;
  // Jump over blocks of empty cells (DdaGrid::skip). The cells a lane visits that hold
  // triangles, and so every result, are those of the exact DDA; only cell_steps drop (the
  // empty cells jumped over are not entered). Off: every cell is stepped, and cell_steps equal
  // the scalar DDA's.
  bool empty_skip = true;
};

// Closest hit of rays[0, size) (contract of Accel::Intersect): hits[i] for i < size are written
// (a miss is t = +inf, u = v = 0, prim = -1); padding lanes of `hits` are never written. The
// result (prim, and t, u, v bit for bit) equals TraceClosest / TraceClosestTwoLevel on the same
// grid on every SIMD target: the same float DDA arithmetic visits the same cells and the bundle
// test rounds like the scalar watertight test. Stream arrays are 64-B aligned and padded to
// PaddedSize(size) (RayStream/HitStream). stats (may be null) gets rays, cell_steps (identical to
// the scalar DDA's), triangle_tests (bundle lanes holding a triangle; no mailbox, so >= the
// scalar count), cache lookups and hits. No allocation; never throws.
void IntersectStreamDda(const DdaGrid& g, const RayStreamView& rays, const HitStreamView& hits,
                        const DdaOptions& options, TraceStats* stats);

// Any hit of rays[0, size): occluded[i] = 1 if ray i is blocked in (tmin, tmax], else 0; only
// occluded[0, size) is written (it need not be padded). Same rules as IntersectStreamDda.
void OccludedStreamDda(const DdaGrid& g, const RayStreamView& rays, int32_t* occluded,
                       const DdaOptions& options, TraceStats* stats);

// The single-ray form: one ray, its x y z cell state in the lanes of one 4-lane vector, the
// next axis chosen with two lane rotations and compares as in the paper's Listing 1. Same
// results and cell_steps as TraceClosest / TraceAny (the SCALAR target runs the scalar DDA).
bool IntersectSingleDda(const DdaGrid& g, float ox, float oy, float oz, float dx, float dy,
                        float dz, float tmin, float tmax, RayHit* hit, TraceStats* stats);
bool OccludedSingleDda(const DdaGrid& g, float ox, float oy, float oz, float dx, float dy,
                       float dz, float tmin, float tmax, TraceStats* stats);


// Name of the target dynamic dispatch runs the kernels above on (e.g. "AVX3").
const char* DdaTargetName();

}  // namespace rs
