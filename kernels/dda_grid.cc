// What the SIMD traversals read besides the grid (kernels/dda_simd.h: DdaGrid): the triangle
// bundles of every leaf, the occupancy bits of both levels as 32-bit words for the lane gathers,
// and the empty-space skip rings. Build-side code, run once per grid.
#include "kernels/dda_simd.h"

#include <algorithm>
#include <cstdint>
#include <vector>

#include "kernels/build_threads.h"
#include "streams/ray_stream.h"  // AllocateAlignedOrThrow

namespace rs {

size_t DdaGrid::Bytes() const {
  const size_t records = two_level != nullptr ? two_level->num_records : 0;
  const size_t skip_bytes = grid != nullptr && skip ? (grid->num_cells + 3) / 4 * 4 : 0;  // 4/word
  return bundles.Bytes() + (top_words32 + records * (kSubCells / 32)) * sizeof(uint32_t) +
         skip_bytes;
}

void BuildSkipRings(const Grid& grid, uint8_t* skip, int threads) {
  // Chebyshev distance to the nearest occupied cell, capped at kFar, is separable:
  // dist = min_z' max(|dz|, min_y' max(|dy|, min_x' |dx|)) over occupied (x', y', z'). Pass 1
  // takes the 1-D distance along each x row (two sweeps); passes 2 and 3 take windowed min-max
  // along y and z over whole x rows at once (contiguous bytes: the compiler vectorizes them).
  // Threaded: each pass is split where its outputs are independent (rows, z layers, x ranges).
  constexpr int kFar = kMaxSkipRings + 1;
  const size_t nx = size_t(grid.res[0]), ny = size_t(grid.res[1]), nz = size_t(grid.res[2]);
  const int parts = int(std::min<size_t>(size_t(BuildThreadCount(threads)),
                                         grid.num_cells / 16384 + 1));
  std::vector<uint8_t> a(grid.num_cells), b(grid.num_cells);
  RunParts(parts, [&](int k) {
    const size_t rows = ny * nz;
    for (size_t row = PartBegin(rows, parts, k, 1); row < PartBegin(rows, parts, k + 1, 1); ++row) {
      uint8_t* r = a.data() + row * nx;
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
  // out[i] = min over |j - i| <= kFar of max(|j - i|, in[j]), i and j along an axis of `count`
  // runs of `width` bytes, `pitch` bytes apart, in `blocks` such axes `block_pitch` apart
  auto window = [&](const uint8_t* in, uint8_t* out, size_t count, size_t width, size_t pitch,
                    size_t blocks, size_t block_pitch) {
    for (size_t blk = 0; blk < blocks; ++blk) {
      for (size_t i = 0; i < count; ++i) {
        uint8_t* o = out + blk * block_pitch + i * pitch;
        std::copy_n(in + blk * block_pitch + i * pitch, width, o);
        const size_t j0 = i >= size_t(kFar) ? i - kFar : 0;
        const size_t j1 = std::min(count - 1, i + kFar);
        for (size_t j = j0; j <= j1; ++j) {
          const uint8_t dj = uint8_t(j > i ? j - i : i - j);
          const uint8_t* q = in + blk * block_pitch + j * pitch;
          for (size_t x = 0; x < width; ++x) o[x] = std::min(o[x], std::max(dj, q[x]));
        }
      }
    }
  };
  RunParts(parts, [&](int k) {  // along y, x rows: z layers apart
    const size_t z0 = PartBegin(nz, parts, k, 1), z1 = PartBegin(nz, parts, k + 1, 1);
    window(a.data() + z0 * nx * ny, b.data() + z0 * nx * ny, ny, nx, nx, z1 - z0, nx * ny);
  });
  RunParts(parts, [&](int k) {  // along z, xy planes: ranges of the plane apart
    const size_t w0 = PartBegin(nx * ny, parts, k, 64), w1 = PartBegin(nx * ny, parts, k + 1, 64);
    if (w1 > w0) window(b.data() + w0, a.data() + w0, nz, w1 - w0, nx * ny, 1, 0);
  });
  for (size_t c = 0; c < grid.num_cells; ++c) skip[c] = uint8_t(a[c] == 0 ? 0 : a[c] - 1);
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
  {
    std::vector<uint8_t> rings((grid.num_cells + 3) / 4 * 4, uint8_t{0});
    BuildSkipRings(grid, rings.data(), threads);
    size_t blocks = 0;
    for (size_t c = 0; c < grid.num_cells; ++c) blocks += rings[c] >= 2;
    out->empty_block_share = double(blocks) / double(grid.num_cells);
    out->skip = AllocateAlignedOrThrow<uint32_t>(rings.size() / 4, "the grid's empty-space rings");
    for (size_t w = 0; w < rings.size() / 4; ++w) {
      out->skip[w] = uint32_t(rings[4 * w]) | uint32_t(rings[4 * w + 1]) << 8 |
                     uint32_t(rings[4 * w + 2]) << 16 | uint32_t(rings[4 * w + 3]) << 24;
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
