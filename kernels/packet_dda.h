// Coherent packet traversal of the grid (Wald, Ize, Kensler, Knoll, Parker 2006, "Ray tracing
// animated scenes using coherent grid traversal"): 64 neighbouring rays walk the grid together,
// slice by slice along their common major axis, and every triangle of the cells their slice
// footprint covers is tested against them N rays x 1 triangle. For primary and shadow rays in a
// coherent order (scanline or tile order) this replaces 64 per-ray cell walks by one walk and
// the per-ray triangle-bundle tests by broadcast tests; incoherent packets are left to the stream
// DDA.
#pragma once

#include <cstddef>
#include <cstdint>

#include "include/raystream/raystream.h"
#include "kernels/dda_simd.h"

namespace rs {

// Rays per packet: consecutive rays [64 k, 64 k + 64) of a stream.
inline constexpr size_t kCoherentPacketRays = 64;

// Closest hits of rays[0, size) with the contract and the results of IntersectStreamDda (prim,
// and t, u, v bit for bit, on every target): consecutive packets of kCoherentPacketRays rays
// whose directions agree in sign along one axis are traced as packets, the others (and streams
// shorter than one packet) by IntersectStreamDda. A packet gives the same result as the per-ray
// walk because both return the closest watertight hit over every triangle listed in a cell the
// ray passes (the cells are binned conservatively with a margin larger than the rounding of
// either walk; see Grid::margin), and ties go to the lower id in both. A packet is abandoned
// for the stream DDA when its footprint grows too wide to pay (rays that diverge), which only
// costs time. Refused packets get a second chance: their rays, up to 1024 at a time, are sorted
// by direction and origin into packets of rays that run together (in grids without dense
// cells); the order never changes a result. stats: rays, cell_steps (cells whose occupancy a
// packet read, plus the stream DDA's steps), triangle_tests (ray lanes tested), packets,
// packets_refused, packets_regrouped, packet_rays. Same alignment rules; no allocation (about
// 130 KB of stack: PacketScratch, the regrouped rays and one packet's state).
void IntersectCoherent(const DdaGrid& g, const RayStreamView& rays, const HitStreamView& hits,
                       const DdaOptions& options, TraceStats* stats);

// Any hit (contract of OccludedStreamDda), with packets as above; a ray of a packet stops at
// its first occluder.
void OccludedCoherent(const DdaGrid& g, const RayStreamView& rays, int32_t* occluded,
                      const DdaOptions& options, TraceStats* stats);

namespace detail {

// Scratch memory of the packet kernels, on the caller's stack (no allocation): the cells marked
// in one slice (a ray mask per cell of a 64 x 64 footprint, zero between uses) and the mailbox
// (triangle id -> vectors tested, valid for entries stamped with the current packet's serial).
struct PacketScratch {
  static constexpr int kMaxFoot = 64;
  static constexpr size_t kMailbox = 1024;
  uint64_t marks[kMaxFoot * kMaxFoot];
  uint16_t list[kMaxFoot * kMaxFoot];
  uint64_t sub_marks[8 * 8];  // the same for one sub-slice of an 8x8x8 sub-grid
  uint16_t sub_list[8 * 8];
  int32_t mb_id[kMailbox];
  uint32_t mb_stamp[kMailbox];
  uint64_t mb_tested[kMailbox];
  uint32_t serial;
};

}  // namespace detail
}  // namespace rs
