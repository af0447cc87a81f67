// The ray sets of ../shared/ANCHORS.md, deterministic for a fixed seed: primary rays of a 60°
// pinhole camera (rows in order), and one shadow and one cosine-weighted diffuse ray per
// primary hit. Primary hits come from Embree, so raystream and Embree trace the same rays.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>
#include <glm/glm.hpp>

#include "bench/peer/embree_peer.h"
#include "include/raystream/raystream.h"
#include "scenes/scene.h"
#include "streams/ray_stream.h"

namespace rs::bench {

inline constexpr uint64_t kRaySetSeed = 0x2026112200000001ull;
inline constexpr float kBenchFovDeg = 60.0f;

enum class RaySet : int { kPrimary = 0, kShadow = 1, kDiffuse = 2, kLight = 3 };
inline constexpr int kNumRaySets = 4;
// "primary", "shadow", "diffuse", "light": the first part of the benchmark names.
const char* RaySetName(RaySet set);
// The coherence hint ANCHORS.md gives Embree for the set (incoherent for diffuse only).
Coherence RaySetCoherence(RaySet set);

// True for the scenes ANCHORS.md views from inside ("room scenes"): sponza, office-graz,
// conference, sibenik (by Scene::name).
bool IsRoomScene(const Scene& scene);

// The camera of the ray sets: for room scenes, the bounding-box centre looking along +x with
// the scene camera's dominant up axis (z if that is x); otherwise the scene's own camera. The
// field of view is always kBenchFovDeg.
Camera BenchCamera(const Scene& scene);

// The point light "near the top centre of the bounds": the centre of the bounds moved along
// the camera's dominant up axis to 95 % of the way to the top face.
glm::vec3 BenchLight(const Scene& scene);

// Distance by which spawned rays start off the surface, along the geometric normal on the
// side of the incoming ray: 1e-5 of the scene's scale (largest |coordinate| or extent), at most
// the larger of 16 ulps of the largest |coordinate| and 1.6e-4 of the extent (farsphere: 0.25,
// not 2.2 units off its radius-1 sphere; the other scenes: 1e-5 of the scale).
float SpawnOffset(const Scene& scene);

// Clears `out` and writes width x height primary rays of BenchCamera in scanline order (ray i is
// pixel i; tmin 0, tmax +inf, unit directions), then fills the padding lanes. Throws rs::Error
// for a bad size or camera (see MakeCameraBasis).
void MakePrimaryRays(const Scene& scene, int width, int height, RayStream& out);

// Clears `out` and writes one shadow ray per hit (hits.prim[i] >= 0) of `rays`, in ray order:
// origin = hit point (barycentric, from the scene's triangle) offset by SpawnOffset towards
// the ray's origin side, unit direction to `light`, tmin 0, tmax = distance to the light. The
// pixel, weight and depth of the parent ray are carried; kind is shadow. Padding is filled.
void MakeShadowRays(const Scene& scene, const RayStreamView& rays, const HitStreamView& hits,
                    const glm::vec3& light, RayStream& out);

// Clears `out` and writes one cosine-weighted diffuse ray per hit, in ray order: same origin as
// the shadow ray, direction about the geometric normal facing the ray, tmin 0, tmax +inf, kind
// reflection, depth + 1. The direction of hit ray i depends only on (seed, rays.pixel[i] or i).
void MakeDiffuseRays(const Scene& scene, const RayStreamView& rays, const HitStreamView& hits,
                     uint64_t seed, RayStream& out);

// Clears `out` and writes the shadow rays `shadow` (MakeShadowRays) traced from the light
// instead: origin `light`, direction (shadow origin - light), t in (0, 1]: the same segments,
// for rs::LightBuffer (and every tracer, so they compare on the same rays).
void MakeLightRays(const RayStreamView& shadow, const glm::vec3& light, RayStream& out);

// Clears `out` and writes n random rays for agreement tests: origins uniform in the bounds
// grown by 10 %; even rays aim at a uniform point of a uniformly chosen triangle (so most
// hit), odd rays take a uniform direction on the sphere. tmin 0, tmax +inf. Deterministic.
void MakeRandomRays(const Scene& scene, size_t n, uint64_t seed, RayStream& out);

// The benchmarks' environment: RS_BENCH_SCENES=a,b,c (else `fallback`) and RS_BENCH_SIZE=WxH
// (false, with a warning naming `who`, if it is set but malformed; false if unset).
std::vector<std::string> BenchScenes(const std::vector<std::string>& fallback);
bool BenchSize(const char* who, int* width, int* height);
// rs::Accel's options of the raystream rows: BuildOptions' defaults (as the raystream command
// builds), or RS_BENCH_GRID=auto|uniform|two-level|irregular (BuildOptions::grid) and
// RS_BENCH_LAMBDA=x (BuildOptions::lambda). Exits with a message naming `who` for a bad value.
BuildOptions BenchBuildOptions(const char* who);

// The three sets for one scene and image size, with Embree's primary hits.
struct RaySets {
  int width = 0;
  int height = 0;
  Camera camera;
  glm::vec3 light{0.0f};
  RayStream primary;
  HitStream primary_hits;  // Embree (rtcIntersect1M, coherent) closest hits of `primary`
  size_t primary_hit_count = 0;
  RayStream shadow;   // one per primary hit
  RayStream diffuse;  // one per primary hit
  RayStream from_light;  // the shadow rays traced from the light (MakeLightRays)

  RayStream& rays(RaySet set);
};

// Builds all three sets. The peer must have been built from scene.mesh().
RaySets MakeRaySets(const Scene& scene, const EmbreePeer& embree, int width, int height,
                    uint64_t seed = kRaySetSeed);

}  // namespace rs::bench
