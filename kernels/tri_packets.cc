// Builds the per-cell 4-wide triangle packets (see tri_packets.h): packet offsets from the CSR
// offsets, then one pass over the CSR lists copying 9 floats per reference.
#include "kernels/tri_packets.h"

#include <limits>

namespace rs {
namespace {

template <typename T>
void Grow(hwy::AlignedFreeUniquePtr<T[]>* p, size_t n) {
  *p = hwy::AllocateAligned<T>(n == 0 ? 1 : n);
  HWY_ASSERT(*p);
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

// Writes the block of one cell: the n triangles of `list` as ceil(n / 4) packets, component by
// component (each inner loop gathers from one SoA array of `tris` into contiguous floats; this
// order measured ~10% faster than triangle by triangle, and an AoS staging copy was slower).
// `degenerate` is null when the mesh has no degenerate triangle (the usual case).
inline void FillBlock(const float* const src[kPacketComponents], const uint8_t* degenerate,
                      const uint32_t* list, size_t n, float* block, int32_t* ids) {
  const size_t stride = (n + kPacketLanes - 1) / kPacketLanes * kPacketLanes;
  const float nan = std::numeric_limits<float>::quiet_NaN();
  for (size_t c = 0; c < kPacketComponents; ++c) {
    const float* from = src[c];
    float* to = block + c * stride;
    for (size_t j = 0; j < n; ++j) to[j] = from[list[j]];
    for (size_t j = n; j < stride; ++j) to[j] = nan;
  }
  for (size_t j = 0; j < n; ++j) ids[j] = int32_t(list[j]);
  for (size_t j = n; j < stride; ++j) ids[j] = -1;
  if (degenerate == nullptr) return;
  for (size_t j = 0; j < n; ++j) {
    if (degenerate[list[j]] == 0) continue;
    for (size_t c = 0; c < kPacketComponents; ++c) block[c * stride + j] = nan;
  }
}

void Sources(const TriangleSoA& tris, const float* src[kPacketComponents]) {
  for (size_t c = 0; c < kPacketComponents; ++c) src[c] = tris.p[c / 3][c % 3].data();
}

}  // namespace

void BuildTriPackets(const Grid& grid, const TriangleSoA& tris, TriPackets* out) {
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
  const uint32_t* tri_ids = grid.tri_ids.get();
  float* data = out->data.get();
  int32_t* ids = out->ids.get();
  uint32_t* begin = out->cell_begin.get();
  // One pass over the lists, in cell order: the output is written sequentially.
  size_t first = 0;
  for (size_t c = 0; c < cells; ++c) {
    const size_t n = cell_begin[c + 1] - cell_begin[c];
    if (n != 0) {
      FillBlock(src, degenerate, tri_ids + cell_begin[c], n, data + kPacketFloats * first,
                ids + kPacketLanes * first);
      first += (n + kPacketLanes - 1) / kPacketLanes;
    }
    begin[c + 1] = uint32_t(first);
  }
}

void BuildTriPacketList(const TriangleSoA& tris, const uint32_t* ids, size_t n, TriPackets* out) {
  const size_t packets = (n + kPacketLanes - 1) / kPacketLanes;
  Reserve(packets, 1, out);
  out->num_cells = 1;
  out->num_packets = packets;
  out->num_triangles = n;
  out->cell_begin[0] = 0;
  out->cell_begin[1] = uint32_t(packets);
  const float* src[kPacketComponents];
  Sources(tris, src);
  const uint8_t* degenerate = tris.num_degenerate != 0 ? tris.degenerate.data() : nullptr;
  if (n != 0) FillBlock(src, degenerate, ids, n, out->data.get(), out->ids.get());
}

}  // namespace rs
