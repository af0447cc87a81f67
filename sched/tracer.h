// What the frame engine traces with: rs::Accel by default (AccelTracer); a benchmark may put
// another traversal behind the same interface (bench/render: Embree 3) to compare time to image
// on the same rays, the same shading and the same image.
#pragma once

#include <cstdint>

#include "include/raystream/raystream.h"

namespace rs {

// Closest-hit and any-hit queries over SoA streams. The engine hands streams that are padded
// (PaddedSize lanes readable past size, the lanes after the last ray holding a ray that cannot
// hit) but whose base need not be 64-B aligned (a view into the middle of a stream).
// Implementations must be thread-safe for concurrent calls (one per worker).
class Tracer {
 public:
  virtual ~Tracer() = default;
  // hits.size == rays.size; hits[0, size) written (t = +inf, prim = -1 on a miss).
  virtual void Intersect(const RayStreamView& rays, const HitStreamView& hits,
                         TraceStats* stats) const = 0;
  // occluded[i] = 1 if ray i hits anything in [tmin, tmax], else 0, for i < rays.size.
  virtual void Occluded(const RayStreamView& rays, int32_t* occluded, TraceStats* stats) const = 0;
};

// rs::Accel behind the interface.
class AccelTracer final : public Tracer {
 public:
  explicit AccelTracer(const Accel& accel) : accel_(&accel) {}
  void Intersect(const RayStreamView& rays, const HitStreamView& hits,
                 TraceStats* stats) const override {
    accel_->Intersect(rays, hits, stats);
  }
  void Occluded(const RayStreamView& rays, int32_t* occluded, TraceStats* stats) const override {
    accel_->Occluded(rays, occluded, stats);
  }

 private:
  const Accel* accel_;
};

}  // namespace rs
