// Shading of a hit stream: background for misses, ambient + phong lights (as shadow rays whose
// weight is the contribution), mirror reflection and refraction rays, robust secondary origins.
// Scalar reference now (rs::ref::Shade); a Highway version will sit beside it in shade.cc.
#pragma once

#include <glm/glm.hpp>

#include <bit>
#include <cmath>
#include <cstddef>
#include <cstdint>

#include "include/raystream/raystream.h"
#include "scenes/scene.h"
#include "sched/framebuffer.h"  // header-only use (Framebuffer::Add is inline): no link cycle
#include "streams/ray_stream.h"

namespace rs {

struct ShadeOptions {
  int max_depth = 4;            // a ray of depth d spawns bounces (depth d + 1) only if d < max
  float weight_cutoff = 1e-3f;  // bounce rays with max(weight channel) below this are dropped
};

// Work counters, accumulated (never reset) by Shade.
struct ShadeStats {
  uint64_t rays = 0;             // rays given to Shade (hits + misses)
  uint64_t shading_calls = 0;    // hit points shaded
  uint64_t misses = 0;           // background contributions
  uint64_t light_tests = 0;      // (hit point, light) pairs evaluated
  uint64_t texture_fetches = 0;  // bilinear texture samples
  uint64_t culled = 0;           // bounce rays not spawned: weight below the cutoff
  uint64_t spawned[kNumRayKinds] = {};  // secondary rays emitted, by RayKind
  void Merge(const ShadeStats& o);
};

// A shadow ray runs from the offset hit point o to the light L as o + t (L - o); it stops at
// t = kShadowTmax so geometry within 1e-4 of the distance around the light (e.g. a lamp
// touching the ceiling it hangs from) does not shadow it. tmin is 0: o is already offset.
inline constexpr float kShadowTmax = 1.0f - 1e-4f;

// Shades rays[0, n) with their closest hits (hits.size == rays.size; the rays must not be
// shadow rays, and pixel/weight/depth/kind must be non-null). Per ray, with weight w:
//   miss: w * scene.background is added to its pixel.
//   hit:  local = clamp(1 - reflectivity - transmission, 0, 1);
//         w * local * scene.ambient * kd is added (kd = diffuse x texture when textured);
//         per light above the surface (only if scene.features.lights): a shadow ray is
//         appended whose weight is (kd cos + ks max(0, R.V)^shininess) * colour * falloff
//         * w * local; the caller adds it to the pixel if Accel::Occluded says it is free;
//         if depth < max_depth: a reflection ray (w * reflectivity * (Ks if nonzero else 1))
//         and a refraction ray (w * transmission; total internal reflection emits it as a
//         reflection ray instead) are appended when their max channel >= weight_cutoff.
// Stages the scene does not have (SceneFeatures: lights, specular, reflection, transmission,
// textures) are never run. Contributions go to `fb` via atomic adds; secondary rays are
// appended to `secondary` (grown as needed; its padding is not refilled). The contributions and
// rays of one input ray depend on that ray and its hit only, never on the stream around it.
// Scene indices must be valid (ValidateScene). Rays whose prim < 0 are misses.
void Shade(const Scene& scene, const ShadeOptions& options, const RayStreamView& rays,
           const HitStreamView& hits, Framebuffer& fb, RayStream& secondary,
           ShadeStats* stats = nullptr);

// Robust secondary-ray origin (Waechter and Binder, "A Fast and Robust Method for Avoiding
// Self-Intersection", Ray Tracing Gems ch. 6): moves p by ~256 ulps per unit of the normal in
// integer space, so the offset scales with |p|, and by 2^-16 * n in absolute terms for
// coordinates within 1/32 of 0 (where ulps become tiny). n must be unit length and point to the
// side the new ray leaves toward. p must be finite.
inline glm::vec3 OffsetRayOrigin(const glm::vec3& p, const glm::vec3& n) {
  constexpr float kOrigin = 1.0f / 32.0f;
  constexpr float kFloatScale = 1.0f / 65536.0f;
  constexpr float kIntScale = 256.0f;
  glm::vec3 out;
  for (int a = 0; a < 3; ++a) {
    const int32_t of = static_cast<int32_t>(kIntScale * n[a]);
    const int32_t bits = std::bit_cast<int32_t>(p[a]);
    // In sign-magnitude float bits, adding moves away from 0: flip the step for p < 0.
    const float pi = std::bit_cast<float>(bits + (p[a] < 0.0f ? -of : of));
    out[a] = std::fabs(p[a]) < kOrigin ? p[a] + kFloatScale * n[a] : pi;
  }
  return out;
}

// Mirror direction of d about the unit normal n: d - 2 (d.n) n.
inline glm::vec3 Reflect(const glm::vec3& d, const glm::vec3& n) {
  return d - 2.0f * glm::dot(d, n) * n;
}

// Snell's law for unit d and unit n facing the incoming ray (dot(d, n) < 0), eta = n_from /
// n_to. Returns false on total internal reflection; otherwise *t is the unit refracted
// direction: eta d + (eta cos_i - cos_t) n.
inline bool Refract(const glm::vec3& d, const glm::vec3& n, float eta, glm::vec3* t) {
  const float cos_i = -glm::dot(d, n);
  const float sin2_t = eta * eta * (1.0f - cos_i * cos_i);
  if (sin2_t > 1.0f) return false;
  const float cos_t = std::sqrt(1.0f - sin2_t);
  *t = glm::normalize(eta * d + (eta * cos_i - cos_t) * n);
  return true;
}

// Bilinear texture sample with wrap-around addressing. uv (0, 0) is the bottom-left corner of
// the image (OBJ convention; row 0 of Texture::rgb is the top). Non-finite uv samples (0, 0).
// An empty texture returns white.
glm::vec3 SampleTexture(const Texture& texture, glm::vec2 uv);

namespace ref {
// The scalar reference (the oracle for SIMD versions). Same contract as rs::Shade.
void Shade(const Scene& scene, const ShadeOptions& options, const RayStreamView& rays,
           const HitStreamView& hits, Framebuffer& fb, RayStream& secondary, ShadeStats* stats);
}  // namespace ref

}  // namespace rs
