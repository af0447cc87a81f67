// What the SIMD traversals read besides the grid (kernels/dda_simd.h: DdaGrid): the triangle
// bundles of every leaf, the occupancy bits of both levels as 32-bit words for the lane gathers,
// and the empty-space skip rings. Build-side code, run once per grid.
#include "kernels/dda_simd.h"

#include <algorithm>
#include <bit>
#include <cstdint>
#include <memory>
#include <vector>

#include "kernels/build_threads.h"
#include "kernels/grid_binning.h"  // SimdMinMaxOffset
#include "streams/ray_stream.h"  // AllocateAlignedOrThrow

namespace rs {

size_t DdaGrid::Bytes() const {
  const size_t records = two_level != nullptr ? two_level->num_records : 0;
  const size_t skip_bytes = grid != nullptr && skip ? (grid->num_cells + 3) / 4 * 4 : 0;  // 4/word
  return bundles.Bytes() + (top_words32 + records * (kSubCells / 32)) * sizeof(uint32_t) +
         skip_bytes;
}

namespace {

// out[i] = min(out[i], max(d, in[i])) for i < n: one offset of the windowed min-max below, over
// contiguous bytes (kernels/grid_simd.cc, a vector at a time).
void MinMaxOffset(uint8_t* out, const uint8_t* in, size_t n, uint8_t d) {
  SimdMinMaxOffset(out, in, n, d);
}

// BuildSkipRings with 2 num_cells bytes of scratch (every byte is written before it is read).
void BuildSkipRings(const Grid& grid, uint8_t* skip, int threads, uint8_t* scratch) {
  // Chebyshev distance to the nearest occupied cell, capped at kFar, is separable:
  // dist = min_z' max(|dz|, min_y' max(|dy|, min_x' |dx|)) over occupied (x', y', z'). Pass 1
  // takes the 1-D distance along each x row (two sweeps); passes 2 and 3 take windowed min-max
  // along y and z, out[i] = min over |j - i| <= kFar of max(|j - i|, in[j]), one offset d = j - i
  // at a time over whole runs of cells (for offset d along y, the d-th row on of each z layer
  // with the row d before it, (ny - d) nx contiguous bytes; along z, the whole xy range): long
  // contiguous loops the compiler vectorizes. Offset kFar adds nothing (every value is <= kFar).
  // Threaded: each pass is split where its outputs are independent (rows, z layers, x ranges).
  constexpr int kFar = kMaxSkipRings + 1;
  const size_t nx = size_t(grid.res[0]), ny = size_t(grid.res[1]), nz = size_t(grid.res[2]);
  const size_t plane = nx * ny;
  const int parts = int(std::min<size_t>(size_t(BuildThreadCount(threads)),
                                         grid.num_cells / 16384 + 1));
  uint8_t* const a = scratch;
  uint8_t* const b = scratch + grid.num_cells;
  RunParts(parts, [&](int k) {
    const size_t rows = ny * nz;
    for (size_t row = PartBegin(rows, parts, k, 1); row < PartBegin(rows, parts, k + 1, 1); ++row) {
      uint8_t* r = a + row * nx;
      int dist = kFar;
      for (size_t x = 0; x < nx; ++x) {
        dist = grid.Occupied(row * nx + x) ? 0 : std::min(dist + 1, kFar);
        r[x] = uint8_t(dist);
      }
      dist = kFar;
      for (size_t x = nx; x-- > 0;) {
        dist = r[x] == 0 ? 0 : std::min(dist + 1, kFar);
        r[x] = std::min(r[x], uint8_t(dist));
      }
    }
  });
  RunParts(parts, [&](int k) {  // along y, per z layer
    for (size_t z = PartBegin(nz, parts, k, 1); z < PartBegin(nz, parts, k + 1, 1); ++z) {
      const uint8_t* in = a + z * plane;
      uint8_t* out = b + z * plane;
      std::copy_n(in, plane, out);
      for (size_t d = 1; d < size_t(kFar) && d < ny; ++d) {
        const size_t n = (ny - d) * nx, shift = d * nx;
        MinMaxOffset(out, in + shift, n, uint8_t(d));  // j = i + d
        MinMaxOffset(out + shift, in, n, uint8_t(d));  // j = i - d
      }
    }
  });
  RunParts(parts, [&](int k) {  // along z, per range of the xy plane
    const size_t w0 = PartBegin(plane, parts, k, 64), w1 = PartBegin(plane, parts, k + 1, 64);
    if (w1 <= w0) return;
    const size_t width = w1 - w0;
    for (size_t z = 0; z < nz; ++z) std::copy_n(b + z * plane + w0, width, a + z * plane + w0);
    for (size_t d = 1; d < size_t(kFar) && d < nz; ++d) {
      for (size_t z = 0; z + d < nz; ++z) {
        uint8_t* lo = a + z * plane + w0;
        uint8_t* hi = a + (z + d) * plane + w0;
        MinMaxOffset(lo, b + (z + d) * plane + w0, width, uint8_t(d));  // j = i + d
        MinMaxOffset(hi, b + z * plane + w0, width, uint8_t(d));        // j = i - d
      }
    }
  });
  // rings = distance - 1 (0 for occupied cells): a saturating decrement
  for (size_t c = 0; c < grid.num_cells; ++c) skip[c] = uint8_t(a[c] - (a[c] != 0));
}

}  // namespace

void BuildSkipRings(const Grid& grid, uint8_t* skip, int threads) {
  const std::unique_ptr<uint8_t[]> scratch(new uint8_t[2 * grid.num_cells]);
  BuildSkipRings(grid, skip, threads, scratch.get());
}

void BuildDdaGrid(const Grid& grid, const TwoLevelGrid* two_level, const TriangleSoA& tris,
                  DdaGrid* out, int threads) {
  out->grid = &grid;
  out->two_level = two_level != nullptr && !two_level->empty() ? two_level : nullptr;
  out->tris = &tris;
  out->simd_ok = grid.num_cells < size_t{0x7fffffc0};
  if (grid.empty()) {
    out->bundles = TriBundles();
    out->bits.reset();
    out->skip.reset();
    out->top_words32 = 0;
    return;
  }
  BuildTriBundles(out->two_level != nullptr ? out->two_level->leaves : grid, tris, &out->bundles,
                  threads);
  // the 64-bit occupancy words as little-endian 32-bit words (a copy: no aliasing), then the
  // 512 bits of each sub-grid record
  const size_t words64 = (grid.num_cells + 63) / 64;
  const size_t records = out->two_level != nullptr ? out->two_level->num_records : 0;
  out->top_words32 = 2 * words64;
  const size_t total = out->top_words32 + records * (kSubCells / 32);
  out->simd_ok = out->simd_ok && total < size_t{0x7fffffc0};
  // the rings' scratch first, freed last: a block below the arrays allocated here, so that
  // freeing it does not hand the top of the heap back to the system (glibc trims a free top
  // past its threshold), which made every later build fault those pages in again
  const std::unique_ptr<uint8_t[]> scratch(new uint8_t[2 * grid.num_cells]);
  {
    // the rings one byte per cell, four to a 32-bit word, low byte first: on a little-endian
    // machine the words' bytes in memory order, written in place
    const size_t skip_words = (grid.num_cells + 3) / 4;
    out->skip = AllocateAlignedOrThrow<uint32_t>(skip_words, "the grid's empty-space rings");
    std::vector<uint8_t> packed;
    uint8_t* rings = reinterpret_cast<uint8_t*>(out->skip.get());
    if constexpr (std::endian::native != std::endian::little) {
      packed.resize(4 * skip_words);
      rings = packed.data();
    }
    std::fill(rings + grid.num_cells, rings + 4 * skip_words, uint8_t{0});
    BuildSkipRings(grid, rings, threads, scratch.get());
    size_t blocks = 0;
    for (size_t c = 0; c < grid.num_cells; ++c) blocks += rings[c] >= 2;
    out->empty_block_share = double(blocks) / double(grid.num_cells);
    if constexpr (std::endian::native != std::endian::little) {
      for (size_t w = 0; w < skip_words; ++w) {
        out->skip[w] = uint32_t(rings[4 * w]) | uint32_t(rings[4 * w + 1]) << 8 |
                       uint32_t(rings[4 * w + 2]) << 16 | uint32_t(rings[4 * w + 3]) << 24;
      }
    }
  }
  out->bits = AllocateAlignedOrThrow<uint32_t>(total, "the grid's occupancy bits");
  for (size_t w = 0; w < words64; ++w) {
    out->bits[2 * w] = uint32_t(grid.occupancy[w]);
    out->bits[2 * w + 1] = uint32_t(grid.occupancy[w] >> 32);
  }
  for (size_t r = 0; r < records; ++r) {
    uint32_t* dst = out->bits.get() + out->top_words32 + r * (kSubCells / 32);
    for (int z = 0; z < kSubRes; ++z) {
      const uint64_t w = out->two_level->records[r].bits[z];
      dst[2 * z] = uint32_t(w);
      dst[2 * z + 1] = uint32_t(w >> 32);
    }
  }
}

}  // namespace rs
