// What the frame engine traces with: rs::Accel by default (AccelTracer); a benchmark may put
// another traversal behind the same interface (bench/render: Embree 3) to compare time to image
// on the same rays, the same shading and the same image.
#pragma once

#include <cstdint>
#include <span>

#include "include/raystream/raystream.h"
#include "scenes/scene.h"

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

// rs::Accel with one rs::LightBuffer per light (buffers[l] built for lights[l]): a run of
// shadow rays from light l (origin == its position, kernels/shade.h) is traced through
// buffers[l], any other ray by the Accel. The results are AccelTracer's bit for bit (the
// LightBuffer's contract), only faster.
class LightAccelTracer final : public Tracer {
 public:
  LightAccelTracer(const Accel& accel, std::span<const PointLight> lights,
                   std::span<const LightBuffer> buffers)
      : accel_(&accel), lights_(lights), buffers_(buffers) {}
  void Intersect(const RayStreamView& rays, const HitStreamView& hits,
                 TraceStats* stats) const override {
    accel_->Intersect(rays, hits, stats);
  }
  void Occluded(const RayStreamView& rays, int32_t* occluded, TraceStats* stats) const override {
    for (size_t i = 0; i < rays.size;) {
      const float x = rays.ox[i], y = rays.oy[i], z = rays.oz[i];
      size_t j = i + 1;  // the run of rays from ray i's origin (a NaN origin is a run of 1)
      while (j < rays.size && rays.ox[j] == x && rays.oy[j] == y && rays.oz[j] == z) ++j;
      RayStreamView run = rays;
      run.ox += i, run.oy += i, run.oz += i, run.dx += i, run.dy += i, run.dz += i;
      run.tmin += i, run.tmax += i;
      run.size = j - i;
      const LightBuffer* buffer = nullptr;
      for (size_t l = 0; l < lights_.size() && l < buffers_.size(); ++l) {
        const auto& p = lights_[l].position;
        if (p.x == x && p.y == y && p.z == z) {
          buffer = &buffers_[l];
          break;
        }
      }
      if (buffer != nullptr) {
        buffer->Occluded(run, occluded + i, stats);
      } else {
        accel_->Occluded(run, occluded + i, stats);
      }
      i = j;
    }
  }

 private:
  const Accel* accel_;
  std::span<const PointLight> lights_;
  std::span<const LightBuffer> buffers_;
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
