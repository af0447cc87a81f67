// Ray sets of ANCHORS.md (see ray_sets.h). Random numbers come from a counter-based hash of
// (seed, ray, dimension), so a ray does not depend on the order rays are generated in.
#include "bench/peer/ray_sets.h"

#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <sstream>
#include <cmath>
#include <limits>
#include <numbers>
#include <string>

#include "streams/raygen.h"

namespace rs::bench {

const char* RaySetName(RaySet set) {
  switch (set) {
    case RaySet::kPrimary: return "primary";
    case RaySet::kShadow: return "shadow";
    case RaySet::kDiffuse: return "diffuse";
    case RaySet::kLight: return "light";
  }
  return "unknown";
}

Coherence RaySetCoherence(RaySet set) {
  return set == RaySet::kDiffuse ? Coherence::kIncoherent : Coherence::kCoherent;
}

namespace {

constexpr float kInf = std::numeric_limits<float>::infinity();

// splitmix64 finalizer: a good 64-bit mix for counter-based random numbers.
uint64_t Mix(uint64_t x) {
  x += 0x9e3779b97f4a7c15ull;
  x = (x ^ (x >> 30)) * 0xbf58476d1ce4e5b9ull;
  x = (x ^ (x >> 27)) * 0x94d049bb133111ebull;
  return x ^ (x >> 31);
}

// Uniform in [0, 1) with 24 random bits, from (seed, index, dimension).
float Uniform(uint64_t seed, uint64_t index, uint64_t dim) {
  const uint64_t h = Mix(seed ^ Mix(index * 8 + dim));
  return static_cast<float>(h >> 40) * (1.0f / 16777216.0f);
}

// The axis (0..2) and sign of the dominant component of v (y, +1 for a zero vector).
int DominantAxis(const glm::vec3& v, float& sign) {
  const glm::vec3 a = glm::abs(v);
  int axis = 1;
  if (a.x > a.y && a.x >= a.z) axis = 0;
  if (a.z > a.y && a.z > a.x) axis = 2;
  sign = v[axis] < 0.0f ? -1.0f : 1.0f;
  return axis;
}

// The spawn point and the geometric normal facing the incoming direction for hit i.
void SpawnFrame(const Scene& scene, const RayStreamView& rays, const HitStreamView& hits, size_t i,
                float offset, glm::vec3& origin, glm::vec3& normal) {
  const glm::uvec3 tri = scene.triangles[static_cast<size_t>(hits.prim[i])];
  const glm::dvec3 p0(scene.positions[tri.x]);
  const glm::dvec3 p1(scene.positions[tri.y]);
  const glm::dvec3 p2(scene.positions[tri.z]);
  const double u = hits.u[i];
  const double v = hits.v[i];
  // Barycentric point in double: more accurate than o + t d for distant hits.
  const glm::dvec3 p = (1.0 - u - v) * p0 + u * p1 + v * p2;
  glm::dvec3 n = glm::cross(p1 - p0, p2 - p0);
  const double len = glm::length(n);
  n = len > 0.0 ? n / len : glm::dvec3(0.0, 0.0, 1.0);
  const glm::dvec3 d(rays.dx[i], rays.dy[i], rays.dz[i]);
  if (glm::dot(n, d) > 0.0) n = -n;
  normal = glm::vec3(n);
  origin = glm::vec3(p + static_cast<double>(offset) * n);
}

// (o: a view of the output stream, sized once: a Resize and a view per ray were half of
// trace_bench's frame rows)
void FinishSpawn(const RayStreamView& from, size_t i, const RayStreamView& o, size_t j,
                 RayKind kind) {
  o.pixel[j] = from.pixel ? from.pixel[i] : static_cast<uint32_t>(i);
  o.wr[j] = from.wr ? from.wr[i] : 1.0f;
  o.wg[j] = from.wg ? from.wg[i] : 1.0f;
  o.wb[j] = from.wb ? from.wb[i] : 1.0f;
  o.depth[j] = (from.depth ? from.depth[i] : 0) + (kind == RayKind::kShadow ? 0 : 1);
  o.kind[j] = static_cast<int32_t>(kind);
}

size_t CountHits(const HitStreamView& hits, size_t n) {
  size_t count = 0;
  for (size_t i = 0; i < n; ++i) count += hits.prim[i] >= 0 ? 1 : 0;
  return count;
}

}  // namespace

bool IsRoomScene(const Scene& scene) {
  return scene.name == "sponza" || scene.name == "office-graz" || scene.name == "conference" ||
         scene.name == "sibenik";
}

Camera BenchCamera(const Scene& scene) {
  Camera camera = scene.camera;
  camera.fov_y_deg = kBenchFovDeg;
  if (!IsRoomScene(scene)) return camera;
  glm::vec3 lo, hi;
  scene.Bounds(lo, hi);
  float sign = 1.0f;
  int axis = DominantAxis(scene.camera.up, sign);
  if (axis == 0) {
    axis = 2;
    sign = 1.0f;
  }
  glm::vec3 up(0.0f);
  up[axis] = sign;
  camera.eye = 0.5f * (lo + hi);
  camera.look_at = camera.eye + glm::vec3(std::max(hi.x - lo.x, 1.0f), 0.0f, 0.0f);
  camera.up = up;
  return camera;
}

glm::vec3 BenchLight(const Scene& scene) {
  glm::vec3 lo, hi;
  scene.Bounds(lo, hi);
  float sign = 1.0f;
  const int axis = DominantAxis(BenchCamera(scene).up, sign);
  glm::vec3 light = 0.5f * (lo + hi);
  const float extent = hi[axis] - lo[axis];
  light[axis] = sign > 0.0f ? hi[axis] - 0.05f * extent : lo[axis] + 0.05f * extent;
  return light;
}

float SpawnOffset(const Scene& scene) {
  glm::vec3 lo, hi;
  scene.Bounds(lo, hi);
  const glm::vec3 c = glm::max(glm::abs(lo), glm::abs(hi)), e = hi - lo;
  const float coord = std::max({c.x, c.y, c.z}), extent = std::max({e.x, e.y, e.z});
  const float scale = std::max(coord, extent);
  const float offset = 1e-5f * (scale > 0.0f ? scale : 1.0f);
  // far from the origin: at most 16 ulps of the coordinates (or 1.6e-4 of the extent)
  const float ulps16 = 16.0f * (std::nextafter(coord, INFINITY) - coord);
  return std::min(offset, std::max(1.6e-4f * extent, ulps16));
}

void MakePrimaryRays(const Scene& scene, int width, int height, RayStream& out) {
  const CameraBasis basis = MakeCameraBasis(BenchCamera(scene), width, height);
  out.Clear();
  AppendPrimaryRays(basis, Tile{0, 0, width, height}, RayOrder::kScanline, out);
  out.FillPadding();
}

void MakeShadowRays(const Scene& scene, const RayStreamView& rays, const HitStreamView& hits,
                    const glm::vec3& light, RayStream& out) {
  const float offset = SpawnOffset(scene);
  out.Clear();
  out.Resize(CountHits(hits, rays.size));
  const RayStreamView o = out.view();
  size_t j = 0;
  for (size_t i = 0; i < rays.size; ++i) {
    if (hits.prim[i] < 0) continue;
    glm::vec3 origin, normal;
    SpawnFrame(scene, rays, hits, i, offset, origin, normal);
    const glm::vec3 to = light - origin;
    const float dist = glm::length(to);
    const glm::vec3 d = dist > 0.0f ? to / dist : normal;
    o.ox[j] = origin.x;
    o.oy[j] = origin.y;
    o.oz[j] = origin.z;
    o.dx[j] = d.x;
    o.dy[j] = d.y;
    o.dz[j] = d.z;
    o.tmin[j] = 0.0f;
    o.tmax[j] = dist;
    FinishSpawn(rays, i, o, j++, RayKind::kShadow);
  }
  out.FillPadding();
}

void MakeLightRays(const RayStreamView& shadow, const glm::vec3& light, RayStream& out) {
  out.Clear();
  out.Reserve(shadow.size);
  out.Resize(shadow.size);
  RayStreamView o = out.view();
  for (size_t i = 0; i < shadow.size; ++i) {
    o.ox[i] = light.x;
    o.oy[i] = light.y;
    o.oz[i] = light.z;
    o.dx[i] = shadow.ox[i] - light.x;
    o.dy[i] = shadow.oy[i] - light.y;
    o.dz[i] = shadow.oz[i] - light.z;
    o.tmin[i] = 0.0f;
    o.tmax[i] = 1.0f;
    if (shadow.pixel != nullptr) o.pixel[i] = shadow.pixel[i];
  }
  out.FillPadding();
}

void MakeDiffuseRays(const Scene& scene, const RayStreamView& rays, const HitStreamView& hits,
                     uint64_t seed, RayStream& out) {
  const float offset = SpawnOffset(scene);
  out.Clear();
  out.Resize(CountHits(hits, rays.size));
  const RayStreamView o = out.view();
  size_t j = 0;
  for (size_t i = 0; i < rays.size; ++i) {
    if (hits.prim[i] < 0) continue;
    glm::vec3 origin, n;
    SpawnFrame(scene, rays, hits, i, offset, origin, n);
    // Orthonormal basis around n (Duff et al. 2017, branchless).
    const float s = std::copysign(1.0f, n.z);
    const float a = -1.0f / (s + n.z);
    const float b = n.x * n.y * a;
    const glm::vec3 t1(1.0f + s * n.x * n.x * a, s * b, -s * n.x);
    const glm::vec3 t2(b, s + n.y * n.y * a, -n.y);
    // Cosine-weighted: uniform point on the disc, lifted to the hemisphere.
    const uint64_t key = rays.pixel ? rays.pixel[i] : i;
    const float u1 = Uniform(seed, key, 0);
    const float u2 = Uniform(seed, key, 1);
    const float r = std::sqrt(u1);
    const float phi = 2.0f * std::numbers::pi_v<float> * u2;
    const float z = std::sqrt(std::max(0.0f, 1.0f - u1));
    const glm::vec3 d = glm::normalize(r * std::cos(phi) * t1 + r * std::sin(phi) * t2 + z * n);
    o.ox[j] = origin.x;
    o.oy[j] = origin.y;
    o.oz[j] = origin.z;
    o.dx[j] = d.x;
    o.dy[j] = d.y;
    o.dz[j] = d.z;
    o.tmin[j] = 0.0f;
    o.tmax[j] = kInf;
    FinishSpawn(rays, i, o, j++, RayKind::kReflection);
  }
  out.FillPadding();
}

void MakeRandomRays(const Scene& scene, size_t n, uint64_t seed, RayStream& out) {
  glm::vec3 lo, hi;
  scene.Bounds(lo, hi);
  const glm::vec3 grow = 0.05f * (hi - lo);
  lo -= grow;
  hi += grow;
  out.Clear();
  out.Reserve(n);
  const size_t num_tris = scene.triangles.size();
  for (size_t i = 0; i < n; ++i) {
    const glm::vec3 o(lo.x + Uniform(seed, i, 0) * (hi.x - lo.x),
                      lo.y + Uniform(seed, i, 1) * (hi.y - lo.y),
                      lo.z + Uniform(seed, i, 2) * (hi.z - lo.z));
    glm::vec3 d;
    if (i % 2 == 0 && num_tris > 0) {
      const size_t t = std::min(
          num_tris - 1, static_cast<size_t>(Uniform(seed, i, 3) * static_cast<float>(num_tris)));
      float a = Uniform(seed, i, 4);
      float b = Uniform(seed, i, 5);
      if (a + b > 1.0f) {
        a = 1.0f - a;
        b = 1.0f - b;
      }
      const glm::uvec3 tri = scene.triangles[t];
      const glm::vec3 target = (1.0f - a - b) * scene.positions[tri.x] +
                               a * scene.positions[tri.y] + b * scene.positions[tri.z];
      d = target - o;
    } else {
      const float z = 1.0f - 2.0f * Uniform(seed, i, 3);
      const float r = std::sqrt(std::max(0.0f, 1.0f - z * z));
      const float phi = 2.0f * std::numbers::pi_v<float> * Uniform(seed, i, 4);
      d = glm::vec3(r * std::cos(phi), r * std::sin(phi), z);
    }
    const float len = glm::length(d);
    if (!(len > 0.0f)) {
      d = glm::vec3(0.0f, 0.0f, 1.0f);
    } else {
      d /= len;
    }
    out.Push(o.x, o.y, o.z, d.x, d.y, d.z, 0.0f, kInf, static_cast<uint32_t>(i), 1.0f, 1.0f, 1.0f,
             0, RayKind::kPrimary);
  }
  out.FillPadding();
}

RayStream& RaySets::rays(RaySet set) {
  switch (set) {
    case RaySet::kPrimary: return primary;
    case RaySet::kShadow: return shadow;
    case RaySet::kDiffuse: return diffuse;
    case RaySet::kLight: return from_light;
  }
  return primary;
}

RaySets MakeRaySets(const Scene& scene, const EmbreePeer& embree, int width, int height,
                    uint64_t seed) {
  RaySets sets;
  sets.width = width;
  sets.height = height;
  sets.camera = BenchCamera(scene);
  sets.light = BenchLight(scene);
  MakePrimaryRays(scene, width, height, sets.primary);
  sets.primary_hits.Resize(sets.primary.size());
  sets.primary_hits.Reset();
  embree.Intersect(EmbreeMode::kStream, sets.primary.view(), sets.primary_hits.view(),
                   Coherence::kCoherent);
  sets.primary_hit_count = CountHits(sets.primary_hits.view(), sets.primary.size());
  MakeShadowRays(scene, sets.primary.view(), sets.primary_hits.view(), sets.light, sets.shadow);
  MakeDiffuseRays(scene, sets.primary.view(), sets.primary_hits.view(), seed, sets.diffuse);
  MakeLightRays(sets.shadow.view(), sets.light, sets.from_light);
  return sets;
}

std::vector<std::string> BenchScenes(const std::vector<std::string>& fallback) {
  const char* env = std::getenv("RS_BENCH_SCENES");
  if (env == nullptr) return fallback;
  std::vector<std::string> parts;
  std::stringstream in(env);
  std::string part;
  while (std::getline(in, part, ',')) {
    if (!part.empty()) parts.push_back(part);
  }
  return parts;
}

bool BenchSize(const char* who, int* width, int* height) {
  const char* size = std::getenv("RS_BENCH_SIZE");
  if (size == nullptr) return false;
  int w = 0, h = 0;
  if (std::sscanf(size, "%dx%d", &w, &h) == 2 && w > 0 && h > 0) {
    *width = w;
    *height = h;
    return true;
  }
  std::fprintf(stderr, "[%s] ignoring RS_BENCH_SIZE=%s (want WxH)\n", who, size);
  return false;
}

BuildOptions BenchBuildOptions(const char* who) {
  BuildOptions o;
  if (const char* g = std::getenv("RS_BENCH_GRID")) {
    const std::string kind = g;
    if (kind == "uniform") {
      o.grid = GridKind::kUniform;
    } else if (kind == "two-level") {
      o.grid = GridKind::kTwoLevel;
    } else if (kind == "irregular") {
      o.grid = GridKind::kIrregular;
    } else if (kind != "auto") {
      std::fprintf(stderr, "[%s] RS_BENCH_GRID=%s: expected auto, uniform, two-level or "
                   "irregular\n", who, g);
      std::exit(2);
    }
  }
  if (const char* l = std::getenv("RS_BENCH_LAMBDA")) {
    char* end = nullptr;
    o.lambda = std::strtof(l, &end);
    if (end == l || *end != '\0' || !(o.lambda >= 0.0f) || !std::isfinite(o.lambda)) {
      std::fprintf(stderr, "[%s] RS_BENCH_LAMBDA=%s: expected a number >= 0\n", who, l);
      std::exit(2);
    }
  }
  return o;
}

}  // namespace rs::bench
