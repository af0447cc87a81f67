// The grid-side data of the SIMD traversals (kernels/dda_simd.h), built once per grid in
// kernels/dda_grid.cc: triangle bundles per leaf, occupancy bits of both levels as 32-bit words
// for the lane gathers, and empty-space skip rings.
#pragma once

#include <hwy/aligned_allocator.h>

#include <cstddef>
#include <cstdint>

#include "kernels/grid.h"
#include "kernels/tri_bundles.h"
#include "kernels/triangle.h"
#include "kernels/two_level.h"

namespace rs {

// What the SIMD traversal reads, derived once from a built grid: the grid (geometry), the
// optional second level, all occupancy bits in one gather-able array, and the triangles of every
// leaf as 4-wide bundles (leaf = top-level cell for a flat grid; TwoLevelGrid::leaves otherwise).
// Borrows `grid`, `two_level` and `tris`: they must outlive it and stay unmodified.
struct DdaGrid {
  const Grid* grid = nullptr;
  const TwoLevelGrid* two_level = nullptr;  // null for a flat grid
  const TriangleSoA* tris = nullptr;        // for the scalar fallback
  TriBundles bundles;
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
  // If set, the per-ray stream kernels (IntersectStreamDda / OccludedStreamDda, and so the rays
  // the coherent packets refuse) trace the irregular grid instead (kernels/irregular_simd.h):
  // the same results; the packets keep this grid. Borrowed, like the rest.
  const struct IrregularDda* irregular = nullptr;

  bool empty() const { return grid == nullptr || grid->empty(); }
  size_t Bytes() const;
};

// Builds `out` for `grid` (and `two_level` if non-null and non-empty) over `tris`, on `threads`
// threads (BuildOptions::build_threads; the same data for any count).
void BuildDdaGrid(const Grid& grid, const TwoLevelGrid* two_level, const TriangleSoA& tris,
                  DdaGrid* out, int threads = 1);

inline constexpr int kMaxSkipRings = 15;

// Fills skip[cell] = min(Chebyshev distance to the nearest occupied cell - 1, kMaxSkipRings)
// for the empty cells of `grid` (occupied cells get 0); skip holds at least num_cells bytes.
// threads: as BuildDdaGrid.
void BuildSkipRings(const Grid& grid, uint8_t* skip, int threads = 1);

}  // namespace rs
