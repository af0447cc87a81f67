// SIMD 3D-DDA traversal with Highway dynamic dispatch: SoA ray streams with one ray per lane
// (lanes refilled from the stream as rays finish), and the Cell paper's single-ray form (one
// ray, x y z in the lanes of a 4-lane vector, section 3.3) for comparison. Flat and two-level
// grids; cells are tested with the 1-ray x 4-triangle packet kernels (kernels/tri_intersect.h).
#pragma once

#include <hwy/aligned_allocator.h>

#include <cstddef>
#include <cstdint>

#include "include/raystream/raystream.h"
#include "streams/ray_stream.h"  // SubView
#include "kernels/dda.h"
#include "kernels/grid.h"
#include "kernels/tri_packets.h"
#include "kernels/triangle.h"
#include "kernels/two_level.h"

namespace rs {

// What the SIMD traversal reads, derived once from a built grid: the grid (geometry), the
// optional second level, all occupancy bits in one gather-able array, and the triangles of every
// leaf as 4-wide packets (leaf = top-level cell for a flat grid; TwoLevelGrid::leaves otherwise).
// Borrows `grid`, `two_level` and `tris`: they must outlive it and stay unmodified.
struct DdaGrid {
  const Grid* grid = nullptr;
  const TwoLevelGrid* two_level = nullptr;  // null for a flat grid
  const TriangleSoA* tris = nullptr;        // for the scalar fallback
  TriPackets packets;
  // Occupancy bits as 32-bit words for the lane gathers: the grid's (top_words32 words; the Grid
  // keeps its 64-bit words for the scalar code), then 16 words per sub-grid record (its 512
  // bits), so one gather base serves lanes on either level.
  hwy::AlignedFreeUniquePtr<uint32_t[]> bits;
  size_t top_words32 = 0;
  // Empty-space skipping: per top-level cell, how many rings of empty cells surround it (its
  // Chebyshev distance to the nearest occupied cell, minus 1, capped at kMaxSkipRings); one
  // byte per cell, four to a 32-bit word (cell c in bits 8 * (c % 4) of word c / 4) for the
  // lane gathers. A lane in an empty cell with k rings jumps to where the exact DDA would leave
  // the (2k+1)^3 empty block.
  hwy::AlignedFreeUniquePtr<uint32_t[]> skip;
  double empty_block_share = 0.0;  // share of top-level cells with >= 2 empty rings
  // The stream kernels index cells with int32 lanes; larger grids (more than 2^31 - 64 cells)
  // are traced by the scalar DDA (false here).
  bool simd_ok = false;

  bool empty() const { return grid == nullptr || grid->empty(); }
  size_t Bytes() const;
};

// Builds `out` for `grid` (and `two_level` if non-null and non-empty) over `tris`.
void BuildDdaGrid(const Grid& grid, const TwoLevelGrid* two_level, const TriangleSoA& tris,
                  DdaGrid* out);

inline constexpr int kMaxMicroCache = 16;

struct DdaOptions {
  // Micro-cache entries (Cell paper section 3.5): the last `micro_cache` leaves looked up by any
  // lane, with their packet spans; 0 disables it, at most kMaxMicroCache. See dda_simd.cc for
  // what it does (and does not) save on a CPU.
  int micro_cache = 8;
  // Jump over blocks of empty cells (DdaGrid::skip). The cells a lane visits that hold
  // triangles, and so every result, are those of the exact DDA; only cell_steps drop (the
  // empty cells jumped over are not entered). Off: every cell is stepped, and cell_steps equal
  // the scalar DDA's.
  bool empty_skip = true;
};

inline constexpr int kMaxSkipRings = 15;

// Fills skip[cell] = min(Chebyshev distance to the nearest occupied cell - 1, kMaxSkipRings)
// for the empty cells of `grid` (occupied cells get 0); skip holds at least num_cells bytes.
void BuildSkipRings(const Grid& grid, uint8_t* skip);

// Closest hit of rays[0, size) (contract of Accel::Intersect): hits[i] for i < size are written
// (a miss is t = +inf, u = v = 0, prim = -1); padding lanes of `hits` are never written. The
// result (prim, and t, u, v bit for bit) equals TraceClosest / TraceClosestTwoLevel on the same
// grid on every SIMD target: the same float DDA arithmetic visits the same cells and the packet
// test rounds like the scalar watertight test. Stream arrays are 64-B aligned and padded to
// PaddedSize(size) (RayStream/HitStream). stats (may be null) gets rays, cell_steps (identical to
// the scalar DDA's), triangle_tests (packet lanes holding a triangle; no mailbox, so >= the
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
