// Embree 3 behind the frame engine's rs::Tracer interface (bench only): the renderer traces
// through an EmbreePeer instead of rs::Accel, so render_bench times both on the same rays, the
// same shading and the same image.
#pragma once

#include <cstdint>

#include "bench/peer/embree_peer.h"
#include "include/raystream/raystream.h"
#include "sched/tracer.h"

namespace rs::bench {

// Traces every call with one EmbreeMode (k16, rtcIntersect16 / rtcOccluded16 on 16
// consecutive rays, is the fastest on every coherent set in ANCHORS.md and ties on diffuse
// rays). The coherence hint follows the ray kind of the call (ANCHORS.md): coherent for primary
// and shadow rays, incoherent for bounce rays (the engine never mixes primary rays with
// others; a call whose first ray is primary is taken as primary). Adds the rays to
// TraceStats::rays; the grid counters (cells, tests, packets) stay 0. The peer must outlive
// the tracer; thread-safe like the peer.
class EmbreeTracer final : public Tracer {
 public:
  explicit EmbreeTracer(const EmbreePeer& peer, EmbreeMode mode = EmbreeMode::k16)
      : peer_(&peer), mode_(mode) {}
  EmbreeMode mode() const { return mode_; }

  void Intersect(const RayStreamView& rays, const HitStreamView& hits,
                 TraceStats* stats) const override {
    const bool primary = rays.size > 0 && rays.kind != nullptr &&
                         rays.kind[0] == static_cast<int32_t>(RayKind::kPrimary);
    peer_->Intersect(mode_, rays, hits, primary ? Coherence::kCoherent : Coherence::kIncoherent);
    if (stats != nullptr) stats->rays += rays.size;
  }
  void Occluded(const RayStreamView& rays, int32_t* occluded, TraceStats* stats) const override {
    peer_->Occluded(mode_, rays, occluded, Coherence::kCoherent);
    if (stats != nullptr) stats->rays += rays.size;
  }

 private:
  const EmbreePeer* peer_;
  EmbreeMode mode_;
};

}  // namespace rs::bench
