// Builds the per-cell 4-wide triangle packets (see tri_packets.h): packet offsets from the CSR
// offsets, then one pass over the CSR lists gathering 9 floats per reference, a vector of
// references at a time (hardware gathers where the target has them). Per-target code;
// foreach_target re-includes this file.
#include "streams/ray_stream.h"  // AllocateAlignedOrThrow
#include "kernels/tri_packets.h"

#include <algorithm>
#include <limits>
#include <vector>

#include "kernels/build_threads.h"

#undef HWY_TARGET_INCLUDE
#define HWY_TARGET_INCLUDE "kernels/tri_packets.cc"
#include <hwy/foreach_target.h>  // IWYU pragma: keep
#include <hwy/highway.h>         // must follow foreach_target.h

HWY_BEFORE_NAMESPACE();
namespace rs {
namespace HWY_NAMESPACE {
namespace hn = hwy::HWY_NAMESPACE;

// Writes the blocks of `cells` lists (list c = tri_ids[list_begin[c] .. list_begin[c + 1])) one
// after the other from packet 0, and packet_begin[c + 1] (packet_begin[0] is the caller's). Each
// block holds the list's n triangles as ceil(n / 4) packets, component by component: per
// component, a vector of references at a time, the floats gathered from one SoA array of `tris`
// and stored contiguously, NaN in the padding lanes (n .. 4 ceil(n / 4)), which get id -1. No
// store reaches past a block (stores are masked to it). `degenerate` is null when the mesh has
// no degenerate triangle (the usual case); otherwise listed degenerate triangles get NaN (it is
// read as aligned 32-bit words: the array must extend to a multiple of 4 bytes, as
// TriangleSoA::degenerate, an AlignedArray padded to 16 elements, does).
void FillPacketCells(const float* const* src, const uint8_t* degenerate, const uint32_t* tri_ids,
                     const uint32_t* list_begin, size_t cells, float* data, int32_t* ids,
                     uint32_t* packet_begin) {
  const hn::ScalableTag<float> df;
  const hn::RebindToSigned<decltype(df)> di;
  const size_t lanes = hn::Lanes(df);
  const auto nan = hn::Set(df, std::numeric_limits<float>::quiet_NaN());
  const auto minus1 = hn::Set(di, -1);
  HWY_ALIGN int32_t tail[HWY_MAX_BYTES / sizeof(int32_t)];
  size_t first = 0;  // packets written so far
  for (size_t c = 0; c < cells; ++c) {
    const uint32_t* list = tri_ids + list_begin[c];
    const size_t n = list_begin[c + 1] - list_begin[c];
    const size_t stride = (n + kPacketLanes - 1) / kPacketLanes * kPacketLanes;
    float* block = data + kPacketFloats * first;
    int32_t* block_ids = ids + kPacketLanes * first;
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
      for (size_t k = 0; k < kPacketComponents; ++k) {
        const auto v = hn::GatherIndex(df, src[k], index);
        hn::BlendedStore(hn::IfThenElse(keep, v, nan), in_block, df, block + k * stride + j);
      }
      hn::BlendedStore(hn::IfThenElse(live_i, index, minus1), hn::RebindMask(di, in_block), di,
                       block_ids + j);
    }
    // padding lanes no vector reached (only with fewer than 4 lanes per vector)
    for (size_t j = (n + lanes - 1) / lanes * lanes; j < stride; ++j) {
      for (size_t k = 0; k < kPacketComponents; ++k) block[k * stride + j] = hn::GetLane(nan);
      block_ids[j] = -1;
    }
    first += stride / kPacketLanes;
    packet_begin[c + 1] = uint32_t(first);
  }
}

}  // namespace HWY_NAMESPACE
}  // namespace rs
HWY_AFTER_NAMESPACE();

#if HWY_ONCE
namespace rs {
namespace {

HWY_EXPORT(FillPacketCells);

template <typename T>
void Grow(hwy::AlignedFreeUniquePtr<T[]>* p, size_t n) {
  *p = AllocateAlignedOrThrow<T>(n == 0 ? 1 : n, "the grid's triangle packets");
}

// Makes room for `packets` packets and `cells` cells (contents are not kept).
void Reserve(size_t packets, size_t cells, TriPackets* out) {
  if (packets > out->packet_capacity || !out->data) {
    Grow(&out->data, kPacketFloats * packets);
    Grow(&out->ids, kPacketLanes * packets);
    out->packet_capacity = packets;
  }
  if (cells > out->cell_capacity || !out->cell_begin) {
    Grow(&out->cell_begin, cells + 1);
    out->cell_capacity = cells;
  }
}

void Sources(const TriangleSoA& tris, const float* src[kPacketComponents]) {
  for (size_t c = 0; c < kPacketComponents; ++c) src[c] = tris.p[c / 3][c % 3].data();
}

}  // namespace

void BuildTriPackets(const Grid& grid, const TriangleSoA& tris, TriPackets* out, int threads) {
  const size_t cells = grid.empty() ? 0 : grid.num_cells;
  const uint32_t* cell_begin = grid.cell_begin.get();
  // Packet offsets: cell c gets ceil(refs / 4) packets. Reads only the CSR offsets.
  size_t packets = 0;
  for (size_t c = 0; c < cells; ++c) {
    packets += (cell_begin[c + 1] - cell_begin[c] + kPacketLanes - 1) / kPacketLanes;
  }
  Reserve(packets, cells, out);
  out->num_cells = cells;
  out->num_packets = packets;
  out->num_triangles = cells == 0 ? 0 : cell_begin[cells] - cell_begin[0];
  out->cell_begin[0] = 0;
  if (cells == 0) return;
  const float* src[kPacketComponents];
  Sources(tris, src);
  const uint8_t* degenerate = tris.num_degenerate != 0 ? tris.degenerate.data() : nullptr;
  // One pass over the lists, in cell order: the output is written sequentially. Threaded: each
  // part fills a contiguous range of cells from its first packet (its offsets come out relative
  // to it and are shifted after; FillPacketCells writes only offsets c0 + 1 .. c1), the same
  // bytes as one pass.
  const int parts = int(std::min<size_t>(size_t(BuildThreadCount(threads)), cells / 4096 + 1));
  std::vector<size_t> part_first(size_t(parts) + 1, 0);
  for (int k = 0; k < parts; ++k) {
    const size_t c0 = PartBegin(cells, parts, k, 64), c1 = PartBegin(cells, parts, k + 1, 64);
    size_t n = 0;
    for (size_t c = c0; c < c1; ++c) {
      n += (cell_begin[c + 1] - cell_begin[c] + kPacketLanes - 1) / kPacketLanes;
    }
    part_first[size_t(k) + 1] = part_first[size_t(k)] + n;
  }
  RunParts(parts, [&](int k) {
    const size_t c0 = PartBegin(cells, parts, k, 64), c1 = PartBegin(cells, parts, k + 1, 64);
    const size_t first = part_first[size_t(k)];
    uint32_t* packet_begin = out->cell_begin.get() + c0;
    HWY_DYNAMIC_DISPATCH(FillPacketCells)(src, degenerate, grid.tri_ids.get(), cell_begin + c0,
                                          c1 - c0, out->data.get() + kPacketFloats * first,
                                          out->ids.get() + kPacketLanes * first, packet_begin);
    for (size_t c = 1; c <= c1 - c0; ++c) packet_begin[c] += uint32_t(first);
  });
}

void BuildTriPacketList(const TriangleSoA& tris, const uint32_t* ids, size_t n, TriPackets* out) {
  const size_t packets = (n + kPacketLanes - 1) / kPacketLanes;
  Reserve(packets, 1, out);
  out->num_cells = 1;
  out->num_packets = packets;
  out->num_triangles = n;
  out->cell_begin[0] = 0;
  out->cell_begin[1] = uint32_t(packets);
  if (n == 0) return;
  const float* src[kPacketComponents];
  Sources(tris, src);
  const uint8_t* degenerate = tris.num_degenerate != 0 ? tris.degenerate.data() : nullptr;
  const uint32_t list_begin[2] = {0, uint32_t(n)};
  HWY_DYNAMIC_DISPATCH(FillPacketCells)(src, degenerate, ids, list_begin, 1, out->data.get(),
                                        out->ids.get(), out->cell_begin.get());
}

}  // namespace rs
#endif  // HWY_ONCE
