// Builds the per-cell 4-wide triangle bundles (see tri_bundles.h): bundle offsets from the CSR
// offsets, then one pass over the CSR lists gathering 9 floats per reference, a vector of
// references at a time (hardware gathers where the target has them). Per-target code;
// foreach_target re-includes this file.
#include "kernels/tri_bundles.h"

#include <algorithm>
#include <limits>
#include <vector>

#include "kernels/build_threads.h"
#include "streams/ray_stream.h"  // AllocateAlignedOrThrow

#undef HWY_TARGET_INCLUDE
#define HWY_TARGET_INCLUDE "kernels/tri_bundles.cc"
#include <hwy/foreach_target.h>  // IWYU pragma: keep
#include <hwy/highway.h>         // must follow foreach_target.h

HWY_BEFORE_NAMESPACE();
namespace rs {
namespace HWY_NAMESPACE {
namespace hn = hwy::HWY_NAMESPACE;

// Writes the blocks of `cells` lists (list c = tri_ids[list_begin[c] .. list_begin[c + 1])) one
// after the other from bundle 0, and bundle_begin[c + 1] (bundle_begin[0] is the caller's). Each
// block holds the list's n triangles as ceil(n / 4) bundles, component by component: per
// component, a vector of references at a time, the floats gathered from one SoA array of `tris`
// and stored contiguously, NaN in the padding lanes (n .. 4 ceil(n / 4)), which get id -1. No
// store reaches past a block (stores are masked to it). `degenerate` is null when the mesh has
// no degenerate triangle (the usual case); otherwise listed degenerate triangles get NaN (it is
// read as aligned 32-bit words: the array must extend to a multiple of 4 bytes, as
// TriangleSoA::degenerate, an AlignedArray padded to 16 elements, does).
void FillBundleCells(const float* const* src, const uint8_t* degenerate, const uint32_t* tri_ids,
                     const uint32_t* list_begin, size_t cells, float* data, int32_t* ids,
                     uint32_t* bundle_begin) {
  const hn::ScalableTag<float> df;
  const hn::RebindToSigned<decltype(df)> di;
  const size_t lanes = hn::Lanes(df);
  const auto nan = hn::Set(df, std::numeric_limits<float>::quiet_NaN());
  const auto minus1 = hn::Set(di, -1);
  HWY_ALIGN int32_t tail[HWY_MAX_BYTES / sizeof(int32_t)];
  size_t first = 0;  // bundles written so far
  for (size_t c = 0; c < cells; ++c) {
    const size_t n = list_begin[c + 1] - list_begin[c];
    if (n == 0) {  // most cells of a sparse grid: no bundle
      bundle_begin[c + 1] = uint32_t(first);
      continue;
    }
    const uint32_t* list = tri_ids + list_begin[c];
    const size_t stride = (n + kBundleLanes - 1) / kBundleLanes * kBundleLanes;
    float* block = data + kBundleFloats * first;
    int32_t* block_ids = ids + kBundleLanes * first;
    for (size_t j = 0; j < n; j += lanes) {
      const size_t live = std::min(lanes, n - j);
      // the ids of this vector of references; the last partial vector goes through a copy, so
      // nothing past the list is read (padding lanes gather triangle 0, then become NaN)
      const auto live_i = hn::FirstN(di, live);
      const int32_t* at = reinterpret_cast<const int32_t*>(list + j);
      hn::Vec<decltype(di)> index;
      if (live == lanes) {
        index = hn::LoadU(di, at);
      } else {
#if HWY_TARGET <= HWY_AVX2
        index = hn::MaskedLoad(live_i, di, at);  // masked lanes are not read (no fault)
#else
        for (size_t l = 0; l < lanes; ++l) tail[l] = l < live ? at[l] : 0;
        index = hn::Load(di, tail);
#endif
      }
      auto keep = hn::RebindMask(df, live_i);
      if (degenerate != nullptr) {
        // the flag bytes, gathered as the aligned 32-bit words that hold them
        const auto words = hn::GatherIndex(di, reinterpret_cast<const int32_t*>(degenerate),
                                           hn::ShiftRight<2>(index));
        const auto shift = hn::ShiftLeft<3>(hn::And(index, hn::Set(di, 3)));
        const auto flag = hn::And(hn::Shr(words, shift), hn::Set(di, 0xff));
        keep = hn::AndNot(hn::RebindMask(df, hn::Ne(flag, hn::Zero(di))), keep);
      }
      const auto in_block = hn::FirstN(df, stride - j);  // live lanes and the padding after
      for (size_t k = 0; k < kBundleComponents; ++k) {
        const auto v = hn::GatherIndex(df, src[k], index);
        hn::BlendedStore(hn::IfThenElse(keep, v, nan), in_block, df, block + k * stride + j);
      }
      hn::BlendedStore(hn::IfThenElse(live_i, index, minus1), hn::RebindMask(di, in_block), di,
                       block_ids + j);
    }
    // padding lanes no vector reached (only with fewer than 4 lanes per vector)
    for (size_t j = (n + lanes - 1) / lanes * lanes; j < stride; ++j) {
      for (size_t k = 0; k < kBundleComponents; ++k) block[k * stride + j] = hn::GetLane(nan);
      block_ids[j] = -1;
    }
    first += stride / kBundleLanes;
    bundle_begin[c + 1] = uint32_t(first);
  }
}

}  // namespace HWY_NAMESPACE
}  // namespace rs
HWY_AFTER_NAMESPACE();

#if HWY_ONCE
namespace rs {
namespace {

HWY_EXPORT(FillBundleCells);

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

void Sources(const TriangleSoA& tris, const float* src[kBundleComponents]) {
  for (size_t c = 0; c < kBundleComponents; ++c) src[c] = tris.p[c / 3][c % 3].data();
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
  const float* src[kBundleComponents];
  Sources(tris, src);
  const uint8_t* degenerate = tris.num_degenerate != 0 ? tris.degenerate.data() : nullptr;
  // One pass over the lists, in cell order: the output is written sequentially. Threaded: each
  // part fills a contiguous range of cells from its first bundle (its offsets come out relative
  // to it and are shifted after; FillBundleCells writes only offsets c0 + 1 .. c1), the same
  // bytes as one pass.
  const int parts = int(std::min<size_t>(size_t(BuildThreadCount(threads)), cells / 4096 + 1));
  std::vector<size_t> part_first(size_t(parts) + 1, 0);
  for (int k = 0; k < parts; ++k) {
    const size_t c0 = PartBegin(cells, parts, k, 64), c1 = PartBegin(cells, parts, k + 1, 64);
    size_t n = 0;
    for (size_t c = c0; c < c1; ++c) {
      n += (cell_begin[c + 1] - cell_begin[c] + kBundleLanes - 1) / kBundleLanes;
    }
    part_first[size_t(k) + 1] = part_first[size_t(k)] + n;
  }
  RunParts(parts, [&](int k) {
    const size_t c0 = PartBegin(cells, parts, k, 64), c1 = PartBegin(cells, parts, k + 1, 64);
    const size_t first = part_first[size_t(k)];
    uint32_t* bundle_begin = out->cell_begin.get() + c0;
    HWY_DYNAMIC_DISPATCH(FillBundleCells)
    (src, degenerate, grid.tri_ids.get(), cell_begin + c0, c1 - c0,
     out->data.get() + kBundleFloats * first, out->ids.get() + kBundleLanes * first, bundle_begin);
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
  const float* src[kBundleComponents];
  Sources(tris, src);
  const uint8_t* degenerate = tris.num_degenerate != 0 ? tris.degenerate.data() : nullptr;
  const uint32_t list_begin[2] = {0, uint32_t(n)};
  HWY_DYNAMIC_DISPATCH(FillBundleCells)
  (src, degenerate, ids, list_begin, 1, out->data.get(), out->ids.get(), out->cell_begin.get());
}

}  // namespace rs
#endif  // HWY_ONCE
