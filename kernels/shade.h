// Shading of a hit stream: background for misses, ambient + phong lights (as shadow rays whose
// weight is the contribution), mirror reflection and refraction rays, robust secondary origins.
// It reads a ShadeScene (spans, no owning Scene) and emits contributions and secondary rays as
// streams; the caller adds the contributions to its framebuffer (kernels never see one).
// rs::Shade is the Highway SIMD kernel (one specialization per stage set, see ShadeStage);
// rs::ref::Shade is the scalar oracle it matches bit for bit on every target.
#pragma once

#include <glm/glm.hpp>

#include <bit>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <span>

#include "include/raystream/raystream.h"
#include "scenes/scene.h"  // Material, Texture, PointLight, SceneFeatures (types only)
#include "streams/ray_stream.h"

namespace rs {

// Optional pipeline stages of Shade. A frame runs only the stages its scene needs
// (ShadeStagesFor, chosen once per frame by MakeFrameContext); the SIMD kernel is compiled once
// per stage set, so a stage that is off costs nothing, not even a branch per ray.
enum ShadeStage : uint32_t {
  kShadeStageShadow = 1u << 0,      // per light: phong diffuse term, shadow-ray spawn
  kShadeStageSpecular = 1u << 1,    // phong highlight (PhongPow); only with kShadeStageShadow
  kShadeStageTexture = 1u << 2,     // bilinear texture fetch modulating the diffuse colour
  kShadeStageReflection = 1u << 3,  // mirror reflection rays
  kShadeStageRefraction = 1u << 4,  // refraction rays (total internal reflection included)
};
inline constexpr int kNumShadeStages = 5;
inline constexpr uint32_t kShadeAllStages = (1u << kNumShadeStages) - 1;  // the general pipeline
inline constexpr uint32_t kShadeStagesAuto = ~0u;  // ShadeOptions::stages: ShadeStagesFor per call
// "shadow", "specular", "texture", "reflection", "refraction" for stage index 0..4.
const char* ShadeStageName(int stage_index);

struct ShadeOptions {
  int max_depth = 4;            // a ray of depth d spawns bounces (depth d + 1) only if d < max
  float weight_cutoff = 1e-3f;  // bounce rays with max(weight channel) below this are dropped
  // The stage set (ShadeStage bits) to run, or kShadeStagesAuto for
  // ShadeStagesFor(scene, *this) on every call. Any superset of ShadeStagesFor gives the same
  // image, contributions and rays (up to their order in the output stream); kShadeAllStages is
  // the general pipeline. A subset drops the missing terms.
  uint32_t stages = kShadeStagesAuto;
};

// What Shade reads of a scene: non-owning views plus the shading constants. The arrays must
// outlive the call; nothing is copied. ShadeSceneOf(scene) views an rs::Scene; another owner
// (the Cell simulator's local store copies) fills the spans itself. Indices must be valid as
// ValidateScene checks them: triangles index positions (and normals / uvs when non-empty),
// material_ids[prim] < materials.size(), Material::texture < textures.size() or -1.
struct ShadeScene {
  std::span<const glm::vec3> positions;
  std::span<const glm::uvec3> triangles;
  std::span<const uint32_t> material_ids;  // one per triangle
  std::span<const glm::vec2> uvs;          // per vertex, or empty (no texturing)
  std::span<const glm::vec3> normals;      // per vertex, or empty (flat shading)
  std::span<const Material> materials;
  std::span<const Texture> textures;
  std::span<const PointLight> lights;
  glm::vec3 background{0.0f};
  float ambient = 0.0f;
  SceneFeatures features;  // selects the stages (ShadeStagesFor)
};

// A view of `scene` (valid while scene lives and its arrays are not resized). O(1).
inline ShadeScene ShadeSceneOf(const Scene& scene) {
  ShadeScene v;
  v.positions = scene.positions;
  v.triangles = scene.triangles;
  v.material_ids = scene.material_ids;
  v.uvs = scene.uvs;
  v.normals = scene.normals;
  v.materials = scene.materials;
  v.textures = scene.textures;
  v.lights = scene.lights;
  v.background = scene.background;
  v.ambient = scene.ambient;
  v.features = scene.features;
  return v;
}

// The stages `scene` needs (from scene.features, plus textures only with UVs and bounces only
// when options.max_depth > 0). Depths of rays given to Shade are assumed >= 0.
uint32_t ShadeStagesFor(const ShadeScene& scene, const ShadeOptions& options);
inline uint32_t ShadeStagesFor(const Scene& scene, const ShadeOptions& options) {
  return ShadeStagesFor(ShadeSceneOf(scene), options);
}

// Work counters, accumulated (never reset) by Shade.
struct ShadeStats {
  uint64_t rays = 0;             // rays given to Shade (hits + misses)
  uint64_t shading_calls = 0;    // hit points shaded
  uint64_t misses = 0;           // background contributions
  uint64_t light_tests = 0;      // (hit point, light) pairs evaluated
  uint64_t texture_fetches = 0;  // bilinear texture samples
  uint64_t culled = 0;           // bounce rays not spawned: weight below the cutoff
  uint64_t spawned[kNumRayKinds] = {};  // secondary rays emitted, by RayKind
  // What the pipeline ran. A block is one SIMD vector of rays in rs::Shade and one
  // ray in ref::Shade; the per-lane counters above are the same for both.
  uint64_t highlights = 0;                     // PhongPow evaluations (lanes)
  uint64_t blocks = 0;                         // blocks holding at least one hit
  uint64_t stage_runs[kNumShadeStages] = {};   // blocks that ran stage i (bit 1 << i); for
                                               // specular: (block, light) pairs
  uint32_t stages = 0;                         // OR of the stage sets Shade ran with
  void Merge(const ShadeStats& o);
};

// A shadow ray runs from the light L to the offset hit point o as L + t (o - L), t in
// (kShadowTmin, 1]: traced from the light, so that the shadow rays of one light share their
// origin (rs::LightBuffer reads one list per ray instead of walking cells). It starts at
// t = kShadowTmin so geometry within 1e-4 of the distance around the light (e.g. a lamp
// touching the ceiling it hangs from) does not shadow it, and ends at o, already offset.
inline constexpr float kShadowTmin = 1e-4f;

// Shades rays[0, n) with their closest hits (hits.size == rays.size; the rays must not be
// shadow rays, and pixel/weight/depth/kind must be non-null). Per ray, with weight w:
//   miss: w * scene.background is emitted for its pixel (if max(background) > 0).
//   hit:  local = clamp(1 - reflectivity - transmission, 0, 1);
//         w * local * scene.ambient * kd is emitted (kd = diffuse x texture when textured) if
//         local > 0 and std::max(r, std::max(g, b)) > 0 (which lets some NaN channels by);
//         per light above the surface (only if scene.features.lights): a shadow ray is
//         appended whose weight is (kd cos + ks max(0, R.V)^shininess) * colour * falloff
//         * w * local; the caller adds it to the pixel if Accel::Occluded says it is free;
//         if depth < max_depth: a reflection ray (w * reflectivity * (Ks if nonzero else 1))
//         and a refraction ray (w * transmission; total internal reflection emits it as a
//         reflection ray instead) are appended when their max channel >= weight_cutoff.
// Stages the scene does not have (SceneFeatures: lights, specular, reflection, transmission,
// textures) are never run (options.stages; see ShadeStage). Contributions (at most one per
// input ray) are appended to `contributions`, secondary rays to `secondary`; what either held
// before is kept. Both grow as needed, before the kernel runs: a contributions stream with
// capacity() >= size() + rays.size + kStreamPad is never reallocated (the SIMD kernel writes up
// to one vector past the new end); the padding of either stream is not refilled and may hold
// garbage afterwards. The caller adds the contributions to its framebuffer
// (Framebuffer::Add(ContributionView)). The contributions and rays of one input ray depend on
// that ray and its hit only, never on the stream around it, the SIMD target or the stage set.
// Scene indices must be valid (ValidateScene). Rays whose prim < 0 are misses.
// Streams: padded and aligned (ray_stream.h); lanes >= size are never read into results.
// Precision: bit-identical to ref::Shade on every Highway target (no FMA, the same operation
// order, IEEE add/mul/div/sqrt; the phong exponent uses PhongPow in both). NaN inputs (u, v,
// direction) give the same NaN-carrying rays and contributions as ref:: (a framebuffer drops
// those contributions and counts them). Within one call, the SIMD kernel emits the rays of each
// vector of input rays stage by stage (shadow rays light by light, then reflection, then
// refraction) and, per vector, miss contributions before hit ones, so the output ORDER differs from ref:: (which
// emits ray by ray); the multisets of rays and of contributions are identical.
// Textures must be smaller than 2^22 texels per side and 2^31 floats (larger ones are sampled
// per lane with SampleTexture: same result, slower).
void Shade(const ShadeScene& scene, const ShadeOptions& options, const RayStreamView& rays,
           const HitStreamView& hits, ContributionStream& contributions, RayStream& secondary,
           ShadeStats* stats = nullptr);
inline void Shade(const Scene& scene, const ShadeOptions& options, const RayStreamView& rays,
                  const HitStreamView& hits, ContributionStream& contributions,
                  RayStream& secondary, ShadeStats* stats = nullptr) {
  rs::Shade(ShadeSceneOf(scene), options, rays, hits, contributions, secondary, stats);
}

// The same with the secondary rays split as they are emitted, so that a caller tracing shadow
// rays as coherent packets needs no partition pass: the shadow rays toward scene.lights[l] are
// appended to *shadow[l] (shadow.size() >= lights.size()), the reflection and refraction rays
// to `bounce`. These are the rays of the one-stream overload, in its order within each light
// and within the bounce rays. The streams may repeat (rays to a shared stream keep the
// one-stream order); each grows as needed, and one that is not shared is never reallocated
// when its capacity() >= size() + rays.size + kStreamPad (bounce: that many per bounce stage).
void Shade(const ShadeScene& scene, const ShadeOptions& options, const RayStreamView& rays,
           const HitStreamView& hits, ContributionStream& contributions,
           std::span<RayStream* const> shadow, RayStream& bounce, ShadeStats* stats = nullptr);
inline void Shade(const Scene& scene, const ShadeOptions& options, const RayStreamView& rays,
                  const HitStreamView& hits, ContributionStream& contributions,
                  std::span<RayStream* const> shadow, RayStream& bounce,
                  ShadeStats* stats = nullptr) {
  rs::Shade(ShadeSceneOf(scene), options, rays, hits, contributions, shadow, bounce, stats);
}

// The power of two that brings m (> 0, the largest edge component) into [1, 2): its exponent
// clamped so that the factor stays a normal float (m of 0, inf or NaN keep their meaning).
inline float EdgeScale(float m) {
  int32_t e = (std::bit_cast<int32_t>(m) >> 23) & 0xFF;
  e = e < 1 ? 1 : (e > 253 ? 253 : e);
  return std::bit_cast<float>((254 - e) << 23);
}

// The unit face normal of (p0, p1, p2) by winding: normalize(cross(p1 - p0, p2 - p0)) with both
// edges first scaled by EdgeScale of their largest component. Scaling by a power of two is
// exact, so the result is the unscaled expression's bit for bit wherever that one neither
// overflows nor underflows, and triangles of 1e14 or 1e-15 units (whose cross product leaves
// the float range) keep a normal. The SIMD shading kernel computes the same (FaceNormal3).
inline glm::vec3 FaceNormal(const glm::vec3& p0, const glm::vec3& p1, const glm::vec3& p2) {
  const glm::vec3 e1 = p1 - p0, e2 = p2 - p0;
  float m = 0.0f;
  for (int a = 0; a < 3; ++a) m = std::fmax(m, std::fmax(std::fabs(e1[a]), std::fabs(e2[a])));
  const float s = EdgeScale(m);
  return glm::normalize(glm::cross(e1 * s, e2 * s));
}

// 2^floor(log2(m)) for finite m >= 0, the exponent clamped to a normal float (m = 0 gives the
// smallest normal): OffsetUnit's and LightOffsetUnit's power of two.
inline float PowerOfTwoFloor(float m) {
  int32_t e = (std::bit_cast<int32_t>(m) >> 23) & 0xFF;
  e = e < 1 ? 1 : (e > 254 ? 254 : e);
  return std::bit_cast<float>(e << 23);
}

// The unit of OffsetRayOrigin for a point on triangle (p0, p1, p2): the power of two
// 2^floor(log2(m)) of m = the largest |component| of the three vertices, the magnitude that the
// error of a point interpolated from them is relative to (exponent clamped to a normal float, as
// EdgeScale). Scaling a scene by a power of two scales it exactly.
inline float OffsetUnit(const glm::vec3& p0, const glm::vec3& p1, const glm::vec3& p2) {
  float m = 0.0f;
  for (int a = 0; a < 3; ++a) {
    m = std::fmax(m, std::fmax(std::fabs(p0[a]), std::fmax(std::fabs(p1[a]), std::fabs(p2[a]))));
  }
  return PowerOfTwoFloor(m);
}

// Secondary-ray origin: p moved off its triangle along n by 16 ulps of `unit` plus 32 ulps of
// `light_unit`, p + step n with step = 2^-19 unit + 2^-18 light_unit, one rounding per
// component. unit = OffsetUnit of the triangle hit, light_unit = LightOffsetUnit of p (0 for
// an origin no shadow ray ends at). The two terms cover the two errors that could put the
// origin on the wrong side of the triangle's plane:
// - p itself: b0 p0 + u p1 + v p2 in float is within about 4.5 ulps of unit of the plane per
//   component (the roundings of b0 = 1 - u - v, of the products and of the sums), 7.8 along
//   the unit normal; the step adds at most 0.9 more (its rounding per component). A ray that
//   leaves from the origin away from the plane then never re-hits the triangle (the watertight
//   test is conservative at the origin, kernels/triangle.h).
// - the shadow ray traced from a light to the origin (t <= 1): the watertight test's t is
//   exact up to a few ulps of the light's distance from the vertices, which light_unit bounds.
// Measured (tests/kernels/shade_test.cc, "no self-shadowing"): 1 M shadow rays from lights
// 2^-4 to 2^10 triangle sizes away, triangles at 0, 10, 1e3 and 1e5 from the origin: 0
// self-hits apart from lights within the rounding of the plane; Waechter and Binder's integer
// offset (Ray Tracing Gems ch. 6, 256 ulps of each component of p, the previous scheme) left
// 8 % (at 0) and 1.6 % (at 10) of them in their own shadow, and at 1.5e5 from the origin
// moved points by up to 4 units (farsphere's floor lost its sphere's shadow). A scene and its
// lights scaled by a power of two get exactly the scaled origins. n must be unit length and
// point to the side the new ray leaves toward; p finite; unit and light_unit powers of two
// (or 0).
inline glm::vec3 OffsetRayOrigin(const glm::vec3& p, const glm::vec3& n, float unit,
                                 float light_unit = 0.0f) {
  const float step = unit * (1.0f / 524288.0f) + light_unit * (1.0f / 262144.0f);
  glm::vec3 out;
  for (int a = 0; a < 3; ++a) out[a] = p[a] + step * n[a];
  return out;
}

// The light term of OffsetRayOrigin at p: PowerOfTwoFloor of the largest |light - p| component
// over `lights`; 0 without lights.
inline float LightOffsetUnit(const glm::vec3& p, std::span<const PointLight> lights) {
  if (lights.empty()) return 0.0f;
  float m = 0.0f;
  for (const PointLight& l : lights) {
    for (int a = 0; a < 3; ++a) m = std::fmax(m, std::fabs(l.position[a] - p[a]));
  }
  return PowerOfTwoFloor(m);
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

// SampleTexture's arithmetic for a w x h texture (w, h >= 1) whose texel at column x, row y
// (row 0 at the top) texel(x, y) returns: shared with the Cell simulator, which reads the
// texels through its software cache (sim/spe.cc), so that both round alike.
template <class TexelAt>
glm::vec3 SampleBilinear(int w, int h, glm::vec2 uv, const TexelAt& texel) {
  const float u = std::isfinite(uv.x) ? uv.x - std::floor(uv.x) : 0.0f;  // wrap to [0, 1]
  const float v = std::isfinite(uv.y) ? uv.y - std::floor(uv.y) : 0.0f;
  // Texel centres at (i + 0.5) / w; v = 0 is the bottom row (h - 1).
  const float x = u * static_cast<float>(w) - 0.5f;
  const float y = (1.0f - v) * static_cast<float>(h) - 0.5f;
  const float fx0 = std::floor(x);
  const float fy0 = std::floor(y);
  const float fx = x - fx0;
  const float fy = y - fy0;
  const auto wrap = [](int i, int n) { return ((i % n) + n) % n; };
  const int x0 = wrap(static_cast<int>(fx0), w);
  const int x1 = wrap(static_cast<int>(fx0) + 1, w);
  const int y0 = wrap(static_cast<int>(fy0), h);
  const int y1 = wrap(static_cast<int>(fy0) + 1, h);
  const glm::vec3 top = texel(x0, y0) * (1.0f - fx) + texel(x1, y0) * fx;
  const glm::vec3 bottom = texel(x0, y1) * (1.0f - fx) + texel(x1, y1) * fx;
  return top * (1.0f - fy) + bottom * fy;
}

// x^e for the phong highlight, shared by rs::Shade (vectorized, the same operations lane by
// lane) and ref::Shade, so both round identically. log2 by the atanh series on the mantissa in
// [sqrt(1/2), sqrt(2)), exp2 by a degree-8 Taylor polynomial on [-1/2, 1/2] scaled by 2^n; only
// IEEE add/mul/div and exact bit operations. Within 1e-6 + 1.2e-7 * |e log2 x| relative of the
// exact power for e log2 x >= -126 (e log2 x is rounded to float; its error grows with |e log2 x|). Defined results: x <= 0 or NaN -> 0; e log2 x < -126 -> 0
// (below 1.2e-38: invisible in the 2^-32 fixed-point framebuffer); e log2 x NaN (x = 1, e = inf)
// -> 1; e log2 x >= 127 saturates near 2^127. Meant for x in [0, 1] and finite e > 0.
float PhongPow(float x, float e);

namespace ref {
// The scalar reference (the oracle for SIMD versions). Same contract as rs::Shade, including
// options.stages; it emits a ray's shadow rays (light by light), reflection and refraction ray
// in that order, ray by ray, and grows `contributions` by Push. Its block counters count rays.
void Shade(const ShadeScene& scene, const ShadeOptions& options, const RayStreamView& rays,
           const HitStreamView& hits, ContributionStream& contributions, RayStream& secondary,
           ShadeStats* stats);
inline void Shade(const Scene& scene, const ShadeOptions& options, const RayStreamView& rays,
                  const HitStreamView& hits, ContributionStream& contributions,
                  RayStream& secondary, ShadeStats* stats) {
  ref::Shade(ShadeSceneOf(scene), options, rays, hits, contributions, secondary, stats);
}
}  // namespace ref

}  // namespace rs
