// What the frame engine traces with: rs::Accel by default (AccelTracer); a benchmark may put
// another traversal behind the same interface (bench/render: Embree 3) to compare time to image
// on the same rays, the same shading and the same image.
#pragma once

#include <bit>
#include <cstdint>
#include <cstring>
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
  // The end of the run of rays that share ray i's origin bit for bit: the first j > i whose
  // origin differs. Bit-equal origins are routed alike (the same light, or the Accel), so a run
  // may hold several NaN rays, and -0 and +0 start new runs to the same light. Whole chunks
  // are compared first, without a branch per ray: the runs are a light's shadow rays, hundreds
  // long (the per-ray comparison cost 1.9 TSC ticks per ray, this 0.5; a light buffer query
  // costs about 20 on office-graz).
  static size_t OriginRunEnd(const RayStreamView& rays, size_t i) {
    const auto bits = [](const float* p, size_t k) { return std::bit_cast<uint32_t>(p[k]); };
    const uint32_t x = bits(rays.ox, i), y = bits(rays.oy, i), z = bits(rays.oz, i);
    constexpr size_t kChunk = 32;
    size_t j = i + 1;
    for (; j + kChunk <= rays.size; j += kChunk) {
      uint32_t a[kChunk], b[kChunk], c[kChunk];  // (copies the compiler vectorizes)
      std::memcpy(a, rays.ox + j, sizeof a);
      std::memcpy(b, rays.oy + j, sizeof b);
      std::memcpy(c, rays.oz + j, sizeof c);
      uint32_t diff = 0;
      for (size_t k = 0; k < kChunk; ++k) diff |= (a[k] ^ x) | (b[k] ^ y) | (c[k] ^ z);
      if (diff != 0) break;
    }
    while (j < rays.size && bits(rays.ox, j) == x && bits(rays.oy, j) == y &&
           bits(rays.oz, j) == z) {
      ++j;
    }
    return j;
  }

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
      const size_t j = OriginRunEnd(rays, i);
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
