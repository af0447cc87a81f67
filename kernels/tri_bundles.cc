// Builds the per-cell 4-wide triangle bundles (see tri_bundles.h): bundle offsets from the CSR
// offsets, then one pass over the CSR lists copying each reference's 9 floats out of the
// triangles' interleaved records (TriangleSoA::verts: one 36-B record per reference, where
// gathering from the nine SoA arrays touched nine cache lines).
#include "kernels/tri_bundles.h"

#include <algorithm>
#include <limits>
#include <vector>

#include "kernels/build_threads.h"
#include "streams/ray_stream.h"  // AllocateAlignedOrThrow

namespace rs {
namespace {

// Writes the blocks of `cells` lists (list c = tri_ids[list_begin[c] .. list_begin[c + 1])) one
// after the other from bundle 0, and bundle_begin[c + 1] (bundle_begin[0] is the caller's). Each
// block holds the list's n triangles as ceil(n / 4) bundles, component by component, NaN in the
// padding lanes (n .. 4 ceil(n / 4)), which get id -1. Listed degenerate triangles get NaN.
void FillBundleCells(const TriangleSoA& tris, const uint32_t* tri_ids, const uint32_t* list_begin,
                     size_t cells, float* data, int32_t* ids, uint32_t* bundle_begin) {
  // null when the mesh has no degenerate triangle (the usual case)
  const uint8_t* degenerate = tris.num_degenerate != 0 ? tris.degenerate.data() : nullptr;
  constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();
  static constexpr float kNaNRecord[kBundleComponents] = {kNaN, kNaN, kNaN, kNaN, kNaN,
                                                          kNaN, kNaN, kNaN, kNaN};
  // the records are read in list order, about one cache miss each: fetched kAhead references
  // ahead (the lists are contiguous in tri_ids, across cells)
  constexpr size_t kAhead = 16;
  const size_t end = list_begin[cells];
  size_t first = 0;  // bundles written so far
  for (size_t c = 0; c < cells; ++c) {
    const size_t n = list_begin[c + 1] - list_begin[c];
    if (n == 0) {  // most cells of a sparse grid: no bundle
      bundle_begin[c + 1] = uint32_t(first);
      continue;
    }
    const uint32_t* list = tri_ids + list_begin[c];
    const size_t stride = (n + kBundleLanes - 1) / kBundleLanes * kBundleLanes;
    float* const block = data + kBundleFloats * first;
    int32_t* const block_ids = ids + kBundleLanes * first;
    for (size_t j = 0; j < n; ++j) {
      if (list_begin[c] + j + kAhead < end) {
        __builtin_prefetch(tris.Vertices(list[j + kAhead]));
      }
      const uint32_t id = list[j];
      const float* v =
          degenerate != nullptr && degenerate[id] != 0 ? kNaNRecord : tris.Vertices(id);
      for (size_t k = 0; k < kBundleComponents; ++k) block[k * stride + j] = v[k];
      block_ids[j] = int32_t(id);
    }
    for (size_t j = n; j < stride; ++j) {
      for (size_t k = 0; k < kBundleComponents; ++k) block[k * stride + j] = kNaN;
      block_ids[j] = -1;
    }
    first += stride / kBundleLanes;
    bundle_begin[c + 1] = uint32_t(first);
  }
}

template <typename T>
void Grow(hwy::AlignedFreeUniquePtr<T[]>* p, size_t n) {
  *p = AllocateAlignedOrThrow<T>(n == 0 ? 1 : n, "the grid's triangle bundles");
}

// Makes room for `bundles` bundles and `cells` cells (contents are not kept).
void Reserve(size_t bundles, size_t cells, TriBundles* out) {
  if (bundles > out->bundle_capacity || !out->data) {
    Grow(&out->data, kBundleFloats * bundles);
    Grow(&out->ids, kBundleLanes * bundles);
    out->bundle_capacity = bundles;
  }
  if (cells > out->cell_capacity || !out->cell_begin) {
    Grow(&out->cell_begin, cells + 1);
    out->cell_capacity = cells;
  }
}

}  // namespace

void BuildTriBundles(const Grid& grid, const TriangleSoA& tris, TriBundles* out, int threads) {
  const size_t cells = grid.empty() ? 0 : grid.num_cells;
  const uint32_t* cell_begin = grid.cell_begin.get();
  // Bundle offsets: cell c gets ceil(refs / 4) bundles. Reads only the CSR offsets.
  size_t bundles = 0;
  for (size_t c = 0; c < cells; ++c) {
    bundles += (cell_begin[c + 1] - cell_begin[c] + kBundleLanes - 1) / kBundleLanes;
  }
  Reserve(bundles, cells, out);
  out->num_cells = cells;
  out->num_bundles = bundles;
  out->num_triangles = cells == 0 ? 0 : cell_begin[cells] - cell_begin[0];
  out->cell_begin[0] = 0;
  if (cells == 0) return;
  // One pass over the lists, in cell order: the output is written sequentially. Threaded: each
  // part fills a contiguous range of cells from its first bundle (its offsets come out relative
  // to it and are shifted after; FillBundleCells writes only offsets c0 + 1 .. c1), the same
  // bytes as one pass. The parts hold about as many bundles each, not as many cells (a scene's
  // occupied cells bunch up in some parts of its grid); their first cells are multiples of 64.
  const int parts = int(std::min<size_t>(size_t(BuildThreadCount(threads)), cells / 4096 + 1));
  std::vector<size_t> part_cell(size_t(parts) + 1, cells), part_first(size_t(parts) + 1, bundles);
  part_cell[0] = part_first[0] = 0;
  {
    size_t n = 0;
    int k = 1;
    for (size_t c = 0; c < cells && k < parts; ++c) {
      if (c % 64 == 0 && n * size_t(parts) >= bundles * size_t(k)) {
        part_cell[size_t(k)] = c, part_first[size_t(k)] = n;
        ++k;
      }
      n += (cell_begin[c + 1] - cell_begin[c] + kBundleLanes - 1) / kBundleLanes;
    }
  }
  RunParts(parts, [&](int k) {
    const size_t c0 = part_cell[size_t(k)], c1 = part_cell[size_t(k) + 1];
    if (c1 <= c0) return;
    const size_t first = part_first[size_t(k)];
    uint32_t* bundle_begin = out->cell_begin.get() + c0;
    FillBundleCells(tris, grid.tri_ids.get(), cell_begin + c0, c1 - c0,
                    out->data.get() + kBundleFloats * first, out->ids.get() + kBundleLanes * first,
                    bundle_begin);
    for (size_t c = 1; c <= c1 - c0; ++c) bundle_begin[c] += uint32_t(first);
  });
}

void BuildTriBundleList(const TriangleSoA& tris, const uint32_t* ids, size_t n, TriBundles* out) {
  const size_t bundles = (n + kBundleLanes - 1) / kBundleLanes;
  Reserve(bundles, 1, out);
  out->num_cells = 1;
  out->num_bundles = bundles;
  out->num_triangles = n;
  out->cell_begin[0] = 0;
  out->cell_begin[1] = uint32_t(bundles);
  if (n == 0) return;
  const uint32_t list_begin[2] = {0, uint32_t(n)};
  FillBundleCells(tris, ids, list_begin, 1, out->data.get(), out->ids.get(),
                  out->cell_begin.get());
}

}  // namespace rs
