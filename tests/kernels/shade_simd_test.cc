// SIMD shading (rs::Shade) against the scalar oracle (rs::ref::Shade) on every Highway target:
// random scenes, hits, materials, textures and lights; sizes around the vector width; padding
// sentinels; NaN inputs; PhongPow accuracy; and the stage pipeline: skipped stages, per-stage
// counters, and specialized images equal to the general pipeline's bit for bit.
#include "kernels/shade.h"

#include <doctest/doctest.h>

#include <algorithm>
#include <array>
#include <bit>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <random>
#include <string>
#include <vector>

#include "scenes/load.h"
#include "sched/framebuffer.h"
#include "sched/render.h"
#include "tests/support/hand_scenes.h"
#include "tests/test_util.h"

namespace rs {
namespace {

constexpr float kInf = std::numeric_limits<float>::infinity();
constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();
constexpr int kFbSide = 8;  // 64 pixels

// ---------------------------------------------------------------- random scenes and hits

struct SceneOptions {
  bool lights = true;
  bool specular = true;
  bool reflection = true;
  bool transmission = true;
  bool textures = true;
  bool normals = true;
};

Texture RandomTexture(std::mt19937& rng, int w, int h) {
  std::uniform_real_distribution<float> unit(0.0f, 1.0f);
  Texture t;
  t.path = "random";
  t.width = w;
  t.height = h;
  t.rgb.resize(static_cast<size_t>(w) * h * 3);
  for (float& x : t.rgb) x = unit(rng);
  return t;
}

// Random triangles in [-5, 5]^3 (never degenerate in practice), random materials, textures,
// UVs (some far outside [0, 1], a few NaN/inf), vertex normals (some zero: degenerate -> ng),
// and lights (one exactly on vertex 0: dist2 = 0 for hits at that vertex).
Scene RandomScene(uint32_t seed, const SceneOptions& o) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> unit(0.0f, 1.0f);
  std::uniform_real_distribution<float> coord(-5.0f, 5.0f);
  Scene s;
  s.name = "random";
  const int kTriangles = 64;
  for (int i = 0; i < kTriangles * 3; ++i) s.positions.emplace_back(coord(rng), coord(rng), coord(rng));
  for (int i = 0; i < kTriangles; ++i) {
    s.triangles.emplace_back(3 * i, 3 * i + 1, 3 * i + 2);
    s.material_ids.push_back(static_cast<uint32_t>(rng() % 6));
  }
  if (o.textures) {
    s.textures.push_back(RandomTexture(rng, 1, 1));
    s.textures.push_back(RandomTexture(rng, 5, 3));
    s.textures.push_back(RandomTexture(rng, 2, 7));
    s.uvs.resize(s.positions.size());
    for (size_t i = 0; i < s.uvs.size(); ++i) {
      s.uvs[i] = glm::vec2(coord(rng), coord(rng)) * (i % 5 == 0 ? 100.0f : 1.0f);
    }
    s.uvs[7].x = kNaN;
    s.uvs[8].y = kInf;
    s.uvs[9] = glm::vec2(-1e-9f, 1.0f - 1e-8f);  // wraps to u = 1 exactly
  }
  const float shininess[] = {0.0f, 0.5f, 1.0f, 8.0f, 60.0f, 1000.0f};
  for (int m = 0; m < 6; ++m) {
    Material mat;
    static const char* const kNames[] = {"m0", "m1", "m2", "m3", "m4", "m5"};
    mat.name = kNames[m];
    mat.diffuse = glm::vec3(unit(rng), unit(rng), unit(rng));
    if (o.specular) {
      mat.specular = m == 2 ? glm::vec3(0.0f) : glm::vec3(unit(rng), unit(rng), unit(rng));
      mat.shininess = shininess[m];
    }
    if (o.reflection && m % 2 == 1) mat.reflectivity = 0.2f + 0.6f * unit(rng);
    if (o.transmission && m >= 3) mat.transmission = m == 5 ? 1.0f : 0.5f * unit(rng);
    mat.ior = m == 4 ? 1.0f / 1.33f : 1.5f;
    if (o.textures) mat.texture = m < 3 ? m : (m == 3 ? -1 : 1);
    s.materials.push_back(mat);
  }
  if (o.normals) {
    s.normals.resize(s.positions.size());
    for (size_t i = 0; i < s.normals.size(); ++i) {
      s.normals[i] = i % 11 == 0 ? glm::vec3(0.0f)
                                 : glm::vec3(coord(rng), coord(rng), coord(rng));
    }
  }
  if (o.lights) {
    for (int l = 0; l < 3; ++l) {
      PointLight light;
      light.position = glm::vec3(coord(rng), coord(rng), coord(rng)) * 2.0f;
      light.color = glm::vec3(unit(rng), unit(rng), unit(rng)) * 3.0f;
      light.falloff = l == 1 ? 0.05f : 0.0f;
      s.lights.push_back(light);
    }
    PointLight on_vertex;
    on_vertex.position = s.positions[0];
    s.lights.push_back(on_vertex);
  }
  s.background = glm::vec3(0.1f, 0.2f, 0.3f);
  s.ambient = 0.15f;
  test::SetFeatures(s);
  return s;
}

struct Stream {
  RayStream rays;
  HitStream hits;
};

// n random rays with random hits (prim -1..triangles-1), barycentrics inside the triangle (a few
// just outside or on an edge/vertex), depths 0..max_depth, weights down to 0.
Stream RandomHits(const Scene& s, size_t n, uint32_t seed, int max_depth) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> unit(0.0f, 1.0f);
  std::normal_distribution<float> gauss(0.0f, 1.0f);
  Stream st;
  st.hits = HitStream(n);
  st.hits.Resize(n);
  st.hits.Reset();
  const HitStreamView h = st.hits.view();
  for (size_t i = 0; i < n; ++i) {
    const int32_t prim = static_cast<int32_t>(rng() % (s.triangles.size() + 4)) - 4;
    float u = unit(rng), v = unit(rng);
    if (u + v > 1.0f) {
      u = 1.0f - u;
      v = 1.0f - v;
    }
    if (i % 17 == 0) u = v = 0.0f;  // vertex 0 (the light on vertex 0: dist2 = 0)
    if (i % 19 == 0) u = -1e-7f;
    const glm::vec3 d(gauss(rng), gauss(rng), gauss(rng));
    const glm::vec3 o(gauss(rng) * 3, gauss(rng) * 3, gauss(rng) * 3);
    const float wscale = i % 13 == 0 ? 1e-5f : (i % 29 == 0 ? 0.0f : 1.5f);
    const int32_t depth = static_cast<int32_t>(rng() % static_cast<uint32_t>(max_depth + 2));
    st.rays.Push(o.x, o.y, o.z, d.x, d.y, d.z, 0.0f, kInf,
                 static_cast<uint32_t>(rng() % (kFbSide * kFbSide)), wscale * unit(rng),
                 wscale * unit(rng), wscale * unit(rng), depth,
                 depth == 0 ? RayKind::kPrimary
                            : (rng() % 2 ? RayKind::kReflection : RayKind::kRefraction));
    h.prim[i] = prim;
    h.u[i] = prim >= 0 ? u : 0.0f;
    h.v[i] = prim >= 0 ? v : 0.0f;
    h.t[i] = prim >= 0 ? 1.0f + unit(rng) : kInf;
  }
  st.rays.FillPadding();
  return st;
}

// ---------------------------------------------------------------- comparing results

using RayKey = std::array<uint32_t, 14>;

uint32_t Bits(float x, bool merge_nan) {
  if (merge_nan && std::isnan(x)) return 0x7fc00000u;
  return std::bit_cast<uint32_t>(x);
}

// The rays of `s` from index `first` on, as sorted bit patterns (the SIMD kernel emits them in
// a different order than the oracle; the multiset must be identical).
RayKey KeyOf(const RayStreamView& v, size_t i, bool merge_nan = false) {
  return {Bits(v.ox[i], merge_nan), Bits(v.oy[i], merge_nan), Bits(v.oz[i], merge_nan),
          Bits(v.dx[i], merge_nan), Bits(v.dy[i], merge_nan), Bits(v.dz[i], merge_nan),
          Bits(v.tmin[i], merge_nan), Bits(v.tmax[i], merge_nan), v.pixel[i],
          Bits(v.wr[i], merge_nan), Bits(v.wg[i], merge_nan), Bits(v.wb[i], merge_nan),
          static_cast<uint32_t>(v.depth[i]), static_cast<uint32_t>(v.kind[i])};
}

std::vector<RayKey> SortedRays(RayStream& s, size_t first = 0, bool merge_nan = false) {
  const RayStreamView v = s.view();
  std::vector<RayKey> keys;
  for (size_t i = first; i < s.size(); ++i) keys.push_back(KeyOf(v, i, merge_nan));
  std::sort(keys.begin(), keys.end());
  return keys;
}

using ContributionKey = std::array<uint32_t, 4>;

// The contributions of `c` from index `first` on, as sorted bit patterns (pixel, r, g, b): the
// SIMD kernel emits them in another order than the oracle; the multiset must be identical.
std::vector<ContributionKey> SortedContributions(const ContributionStream& c, size_t first = 0,
                                                 bool merge_nan = false) {
  const ContributionView v = c.view();
  std::vector<ContributionKey> keys;
  for (size_t i = first; i < v.size; ++i) {
    keys.push_back({v.pixel[i], Bits(v.r[i], merge_nan), Bits(v.g[i], merge_nan),
                    Bits(v.b[i], merge_nan)});
  }
  std::sort(keys.begin(), keys.end());
  return keys;
}

bool SameSums(const Framebuffer& a, const Framebuffer& b) {
  return a.num_pixels() == b.num_pixels() &&
         std::memcmp(a.sums(), b.sums(), a.num_pixels() * 3 * sizeof(int64_t)) == 0;
}

// fb holds the contributions, added once after the call (as the renderer does).
struct Result {
  Framebuffer fb{kFbSide, kFbSide};
  ContributionStream contributions;
  RayStream secondary;
  ShadeStats stats;
};

Result RunRef(const Scene& s, const ShadeOptions& opt, Stream& st) {
  Result r;
  ref::Shade(s, opt, st.rays.view(), st.hits.view(), r.contributions, r.secondary, &r.stats);
  r.fb.Add(r.contributions.view());
  return r;
}

Result RunSimd(const Scene& s, const ShadeOptions& opt, Stream& st) {
  Result r;
  Shade(s, opt, st.rays.view(), st.hits.view(), r.contributions, r.secondary, &r.stats);
  r.fb.Add(r.contributions.view());
  return r;
}

// Everything the two must agree on: the contributions (as a multiset, and so the framebuffer
// bits and counters), the rays, the per-lane stats.
void CheckSame(Result& simd, Result& want, bool merge_nan = false) {
  CHECK(SortedContributions(simd.contributions, 0, merge_nan) ==
        SortedContributions(want.contributions, 0, merge_nan));
  CHECK(SameSums(simd.fb, want.fb));
  CHECK(simd.fb.dropped_nan() == want.fb.dropped_nan());
  CHECK(simd.fb.clamped() == want.fb.clamped());
  REQUIRE(simd.secondary.size() == want.secondary.size());
  const std::vector<RayKey> a = SortedRays(simd.secondary, 0, merge_nan);
  const std::vector<RayKey> b = SortedRays(want.secondary, 0, merge_nan);
  size_t differ = 0;
  for (size_t i = 0; i < a.size(); ++i) differ += a[i] != b[i] ? 1 : 0;
  CHECK(differ == 0);
  const ShadeStats& x = simd.stats;
  const ShadeStats& y = want.stats;
  CHECK(x.rays == y.rays);
  CHECK(x.shading_calls == y.shading_calls);
  CHECK(x.misses == y.misses);
  CHECK(x.light_tests == y.light_tests);
  CHECK(x.texture_fetches == y.texture_fetches);
  CHECK(x.culled == y.culled);
  CHECK(x.highlights == y.highlights);
  CHECK(x.stages == y.stages);
  for (int k = 0; k < kNumRayKinds; ++k) CHECK(x.spawned[k] == y.spawned[k]);
  // Blocks are vectors here and rays in ref::: a stage ran in one iff it ran in the other.
  CHECK(x.blocks <= y.blocks);
  for (int k = 0; k < kNumShadeStages; ++k) {
    INFO("stage ", ShadeStageName(k));
    CHECK((x.stage_runs[k] > 0) == (y.stage_runs[k] > 0));
    CHECK(x.stage_runs[k] <= y.stage_runs[k]);
  }
}

const size_t kSizes[] = {1, 2, 3, 5, 7, 9, 15, 16, 17, 31, 33, 64, 257, 1000};

// ---------------------------------------------------------------- PhongPow

TEST_CASE("PhongPow: accuracy against double pow, special values") {
  std::mt19937 rng(3);
  std::uniform_real_distribution<float> unit(0.0f, 1.0f);
  const float exps[] = {0.25f, 0.5f, 1.0f, 2.0f, 7.5f, 8.0f, 20.0f, 60.0f, 120.0f, 1000.0f, 1e4f};
  double worst = 0;
  for (const float e : exps) {
    for (int i = 0; i < 20000; ++i) {
      // Bases spread over [1e-6, 1] in log scale, plus a cluster just below 1 (highlight centres).
      const float x = i % 2 ? std::exp2(-20.0f * unit(rng)) : 1.0f - 1e-3f * unit(rng);
      const double y = e * std::log2(static_cast<double>(x));
      if (y < -126) continue;
      const double want = std::pow(static_cast<double>(x), static_cast<double>(e));
      const double got = PhongPow(x, e);
      // e log2 x is rounded to float: its absolute error ~ |y| 2^-23 becomes a relative error.
      const double rel = std::fabs(got - want) / want;
      worst = std::max(worst, rel / (1e-6 + 1.2e-7 * std::fabs(y)));
      if (rel > 1e-6 + 1.2e-7 * std::fabs(y)) {
        INFO("x ", x, " e ", e, " got ", got, " want ", want);
        CHECK(rel <= 1e-6 + 1.2e-7 * std::fabs(y));
      }
    }
  }
  MESSAGE("PhongPow worst error / bound: ", worst);
  // Literal regressions and special values.
  CHECK(PhongPow(1.0f, 60.0f) == 1.0f);
  CHECK(PhongPow(0.5f, 2.0f) == 0.25f);
  CHECK(PhongPow(0.0f, 8.0f) == 0.0f);
  CHECK(PhongPow(-0.5f, 8.0f) == 0.0f);
  CHECK(PhongPow(kNaN, 8.0f) == 0.0f);
  CHECK(PhongPow(1e-30f, 8.0f) == 0.0f);          // 2^-797: flushed
  CHECK(PhongPow(1.0f, kInf) == 1.0f);            // 1^inf
  CHECK(PhongPow(1e-45f, 0.1f) == doctest::Approx(std::pow(1e-45, 0.1)).epsilon(1e-5));  // subnormal
  CHECK(std::isfinite(PhongPow(1.0000001f, 1e30f)));  // saturates near 2^127
  CHECK(PhongPow(0.70710678f, 8.0f) == doctest::Approx(0.0625).epsilon(2e-6));
}

// ---------------------------------------------------------------- SIMD vs ref

TEST_CASE("every target equals ref::Shade on random hits, materials, textures and lights") {
  std::string targets;
  test::ForEachTarget([&](const char* target) { targets += std::string(target) + " "; });
  MESSAGE("targets: ", targets);
  CHECK(hwy::SupportedAndGeneratedTargets().size() >= 2);  // at least one SIMD target + scalar
  for (const uint32_t seed : {1u, 2u, 3u}) {
    const Scene s = RandomScene(seed, SceneOptions{});
    REQUIRE(s.features.lights);
    REQUIRE(s.features.textures);
    REQUIRE(s.features.transmission);
    for (const size_t n : kSizes) {
      for (const float cutoff : {0.0f, 1e-3f, 0.3f}) {
        ShadeOptions opt;
        opt.max_depth = 3;
        opt.weight_cutoff = cutoff;
        Stream st = RandomHits(s, n, seed * 1000 + static_cast<uint32_t>(n), opt.max_depth);
        Result want = RunRef(s, opt, st);
        test::ForEachTarget([&](const char* target) {
          INFO("target ", target, " seed ", seed, " n ", n, " cutoff ", cutoff);
          Result got = RunSimd(s, opt, st);
          CheckSame(got, want);
        });
        if (n == 1000 && cutoff == 1e-3f) {
          // The test exercises every stage and every kind of output.
          CHECK(want.stats.spawned[static_cast<int>(RayKind::kShadow)] > 100);
          CHECK(want.stats.spawned[static_cast<int>(RayKind::kReflection)] > 50);
          CHECK(want.stats.spawned[static_cast<int>(RayKind::kRefraction)] > 50);
          CHECK(want.stats.texture_fetches > 100);
          CHECK(want.stats.highlights > 100);
          CHECK(want.stats.culled > 10);
          CHECK(want.stats.misses > 10);
        }
      }
    }
  }
}

TEST_CASE("every target equals ref::Shade on each stage subset (stages off: terms missing)") {
  const Scene s = RandomScene(11, SceneOptions{});
  ShadeOptions opt;
  opt.max_depth = 2;
  Stream st = RandomHits(s, 333, 77, opt.max_depth);
  for (uint32_t stages = 0; stages <= kShadeAllStages; ++stages) {
    opt.stages = stages;
    Result want = RunRef(s, opt, st);
    test::ForEachTarget([&](const char* target) {
      INFO("target ", target, " stages ", stages);
      Result got = RunSimd(s, opt, st);
      CheckSame(got, want);
      if ((stages & kShadeStageShadow) == 0) {
        CHECK(got.stats.spawned[static_cast<int>(RayKind::kShadow)] == 0);
        CHECK(got.stats.light_tests == 0);
      }
      if ((stages & kShadeStageTexture) == 0) CHECK(got.stats.texture_fetches == 0);
      if ((stages & (kShadeStageShadow | kShadeStageSpecular)) !=
          (kShadeStageShadow | kShadeStageSpecular)) {
        CHECK(got.stats.highlights == 0);
      }
    });
  }
}

TEST_CASE("real hits: Accel on spherebox and erw6 (smooth normals, glass, mirrors)") {
  for (const char* name : {"spherebox", "erw6", "cornell"}) {
    INFO("scene ", name);
    const Scene s = LoadScene(name);
    const Accel accel(s.mesh());
    std::mt19937 rng(5);
    std::normal_distribution<float> gauss(0.0f, 1.0f);
    glm::vec3 lo, hi;
    s.Bounds(lo, hi);
    const glm::vec3 centre = 0.5f * (lo + hi);
    const glm::vec3 extent = 0.25f * (hi - lo);
    Stream st;
    const size_t n = 4000;
    for (size_t i = 0; i < n; ++i) {
      const glm::vec3 o = centre + extent * glm::vec3(gauss(rng), gauss(rng), gauss(rng)) * 0.5f;
      st.rays.Push(o.x, o.y, o.z, gauss(rng), gauss(rng), gauss(rng), 0.0f, kInf,
                   static_cast<uint32_t>(i % (kFbSide * kFbSide)), 1.0f, 0.9f, 0.8f,
                   static_cast<int32_t>(i % 3), RayKind::kPrimary);
    }
    st.rays.FillPadding();
    st.hits = HitStream(n);
    st.hits.Resize(n);
    st.hits.Reset();
    accel.Intersect(st.rays.view(), st.hits.view());
    ShadeOptions opt;
    opt.max_depth = 2;
    Result want = RunRef(s, opt, st);
    CHECK(want.stats.shading_calls > n / 2);
    test::ForEachTarget([&](const char* target) {
      INFO("target ", target);
      Result got = RunSimd(s, opt, st);
      CheckSame(got, want);
    });
  }
}

TEST_CASE("padding lanes: sentinels are never shaded; inputs untouched; appends keep old rays") {
  const Scene s = RandomScene(21, SceneOptions{});
  for (const size_t n : kSizes) {
    ShadeOptions opt;
    opt.max_depth = 3;
    Stream st = RandomHits(s, n, 500 + static_cast<uint32_t>(n), opt.max_depth);
    // Sentinel: padding lanes hold hits on triangle 0 with full weight and pixel 0. A kernel that
    // shaded a padding lane would add to pixel 0 or spawn extra rays.
    const size_t padded = PaddedSize(n);
    const HitStreamView h = st.hits.view();
    const RayStreamView r = st.rays.view();
    for (size_t i = n; i < padded; ++i) {
      h.prim[i] = 0;
      h.u[i] = h.v[i] = 0.25f;
      h.t[i] = 1.0f;
    }
    for (size_t i = n; i < st.rays.capacity(); ++i) {
      r.ox[i] = r.oy[i] = r.oz[i] = 0.5f;
      r.dx[i] = r.dy[i] = 0.0f;
      r.dz[i] = 1.0f;
      r.wr[i] = r.wg[i] = r.wb[i] = 1.0f;
      r.pixel[i] = 0;
      r.depth[i] = 0;
    }
    // Snapshots of the inputs, padding included.
    auto bytes_of = [](const void* p, size_t len) {
      const auto* b = static_cast<const uint8_t*>(p);
      return std::vector<uint8_t>(b, b + len);
    };
    const std::vector<uint8_t> prim0 = bytes_of(h.prim, padded * 4), u0 = bytes_of(h.u, padded * 4),
                               dx0 = bytes_of(r.dx, st.rays.capacity() * 4),
                               w0 = bytes_of(r.wr, st.rays.capacity() * 4);
    Result want = RunRef(s, opt, st);
    test::ForEachTarget([&](const char* target) {
      INFO("target ", target, " n ", n);
      Result got;
      // Two rays already in the output stream must survive the append.
      got.secondary.Push(1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, RayKind::kShadow);
      got.secondary.Push(-1, -2, -3, -4, -5, -6, -7, -8, 99, -10, -11, -12, -13,
                         RayKind::kRefraction);
      const std::vector<RayKey> before = SortedRays(got.secondary);
      // And two contributions: kept, the new ones appended after them.
      got.contributions.Push(3, 0.25f, 0.5f, 0.75f);
      got.contributions.Push(63, kNaN, 1.0f, 2.0f);
      const std::vector<ContributionKey> cbefore = SortedContributions(got.contributions);
      Shade(s, opt, st.rays.view(), st.hits.view(), got.contributions, got.secondary, &got.stats);
      ContributionStream chead;
      const ContributionView cv = got.contributions.view();
      for (size_t i = 0; i < 2; ++i) chead.Push(cv.pixel[i], cv.r[i], cv.g[i], cv.b[i]);
      CHECK(SortedContributions(chead) == cbefore);
      CHECK(SortedContributions(got.contributions, 2) == SortedContributions(want.contributions));
      ContributionView ctail = cv;  // the call's own contributions, into the framebuffer
      ctail.pixel += 2;
      ctail.r += 2;
      ctail.g += 2;
      ctail.b += 2;
      ctail.size -= 2;
      got.fb.Add(ctail);
      RayStream tail;
      const RayStreamView gv = got.secondary.view();
      for (size_t i = 2; i < got.secondary.size(); ++i) tail.PushFrom(gv, i);
      RayStream head;
      for (size_t i = 0; i < 2; ++i) head.PushFrom(gv, i);
      CHECK(SortedRays(head) == before);
      CHECK(SortedRays(tail) == SortedRays(want.secondary));
      CHECK(SameSums(got.fb, want.fb));
      CHECK(got.stats.rays == n);
      CHECK(bytes_of(h.prim, padded * 4) == prim0);
      CHECK(bytes_of(h.u, padded * 4) == u0);
      CHECK(bytes_of(r.dx, st.rays.capacity() * 4) == dx0);
      CHECK(bytes_of(r.wr, st.rays.capacity() * 4) == w0);
    });
  }
}

TEST_CASE("NaN inputs: NaN u/v, direction and weight give the oracle's rays and drops") {
  const Scene s = RandomScene(31, SceneOptions{});
  ShadeOptions opt;
  opt.max_depth = 3;
  opt.weight_cutoff = 0.0f;
  for (const size_t n : {size_t{1}, size_t{15}, size_t{17}, size_t{100}}) {
    Stream st = RandomHits(s, n, 900 + static_cast<uint32_t>(n), opt.max_depth);
    const HitStreamView h = st.hits.view();
    const RayStreamView r = st.rays.view();
    for (size_t i = 0; i < n; ++i) {
      switch (i % 5) {
        case 0: h.u[i] = kNaN; break;
        case 1: r.dx[i] = kNaN; break;
        case 2: r.wg[i] = kNaN; break;
        case 3: h.v[i] = kInf; break;
        default: break;  // ordinary
      }
      if (i % 5 != 4 && h.prim[i] < 0) h.prim[i] = static_cast<int32_t>(i % s.triangles.size());
    }
    Result want = RunRef(s, opt, st);
    if (n == 100) CHECK(want.fb.dropped_nan() > 0);  // the NaNs did reach the framebuffer
    test::ForEachTarget([&](const char* target) {
      INFO("target ", target, " n ", n);
      Result got = RunSimd(s, opt, st);
      CheckSame(got, want, /*merge_nan=*/true);
    });
  }
}

TEST_CASE("regression: literal hit on a lit, textured, specular floor equals ref bit for bit") {
  Scene s;
  Material m;
  m.diffuse = glm::vec3(0.5f, 0.6f, 0.7f);
  m.specular = glm::vec3(0.3f, 0.2f, 0.1f);
  m.shininess = 8.0f;
  m.texture = 0;
  s.materials.push_back(m);
  test::AddQuad(s, {-10, 0, 10}, {10, 0, 10}, {10, 0, -10}, {-10, 0, -10}, 0);
  s.uvs = {{0, 0}, {1, 0}, {1, 1}, {0, 1}};
  Texture t;
  t.width = 2;
  t.height = 2;
  t.rgb = {1, 0, 0, 0, 1, 0, 0, 0, 1, 1, 1, 1};
  s.textures.push_back(t);
  PointLight light;
  light.position = glm::vec3(0, 4, 0);
  light.color = glm::vec3(2.0f, 1.0f, 0.5f);
  s.lights.push_back(light);
  test::SetFeatures(s);
  Stream st;
  st.rays.Push(3, 3, 0, -0.70710677f, -0.70710677f, 0, 0, kInf, 5, 0.5f, 0.5f, 0.5f, 0,
               RayKind::kPrimary);
  st.rays.FillPadding();
  st.hits = HitStream(1);
  st.hits.Resize(1);
  st.hits.Reset();
  test::BruteForceIntersect(s, st.rays.view(), st.hits.view());
  REQUIRE(st.hits.view().prim[0] >= 0);
  Result want = RunRef(s, ShadeOptions{}, st);
  REQUIRE(want.secondary.size() == 1);
  CHECK(want.stats.texture_fetches == 1);
  CHECK(want.stats.highlights == 1);
  test::ForEachTarget([&](const char* target) {
    INFO("target ", target);
    Result got = RunSimd(s, ShadeOptions{}, st);
    CheckSame(got, want);
  });
}

// ---------------------------------------------------------------- the stage pipeline

TEST_CASE("ShadeStagesFor follows the scene features and max_depth") {
  SceneOptions all;
  const Scene full = RandomScene(41, all);
  ShadeOptions opt;
  CHECK(ShadeStagesFor(full, opt) == kShadeAllStages);
  opt.max_depth = 0;
  CHECK(ShadeStagesFor(full, opt) ==
        (kShadeStageShadow | kShadeStageSpecular | kShadeStageTexture));
  SceneOptions dark = all;
  dark.lights = false;
  CHECK(ShadeStagesFor(RandomScene(41, dark), ShadeOptions{}) ==
        (kShadeStageTexture | kShadeStageReflection | kShadeStageRefraction));
  SceneOptions diffuse{false, false, false, false, false, false};
  CHECK(ShadeStagesFor(RandomScene(41, diffuse), ShadeOptions{}) == 0);
  diffuse.lights = true;
  CHECK(ShadeStagesFor(RandomScene(41, diffuse), ShadeOptions{}) == kShadeStageShadow);
  CHECK(std::string(ShadeStageName(0)) == "shadow");
  CHECK(std::string(ShadeStageName(4)) == "refraction");
  CHECK(std::string(ShadeStageName(5)) == "unknown");
}

// Runs the specialized (auto) and the general pipeline on the same hits; both must give the
// same framebuffer and rays on every target; returns the specialized stats.
ShadeStats SpecializedVsGeneral(const Scene& s, ShadeStats* general_stats) {
  ShadeOptions opt;
  opt.max_depth = 3;
  Stream st = RandomHits(s, 500, 4242, opt.max_depth);
  ShadeStats spec_stats;
  test::ForEachTarget([&](const char* target) {
    INFO("target ", target);
    opt.stages = kShadeStagesAuto;
    Result spec = RunSimd(s, opt, st);
    opt.stages = kShadeAllStages;
    Result gen = RunSimd(s, opt, st);
    CHECK(SameSums(spec.fb, gen.fb));
    CHECK(SortedRays(spec.secondary) == SortedRays(gen.secondary));
    CHECK(gen.stats.stages == kShadeAllStages);
    spec_stats = spec.stats;
    *general_stats = gen.stats;
  });
  return spec_stats;
}

TEST_CASE("no lights: no shadow stage, no shadow rays, no light tests") {
  SceneOptions o;
  o.lights = false;
  const Scene s = RandomScene(51, o);
  REQUIRE_FALSE(s.features.lights);
  ShadeStats general;
  const ShadeStats st = SpecializedVsGeneral(s, &general);
  CHECK((st.stages & kShadeStageShadow) == 0);
  CHECK((st.stages & kShadeStageSpecular) == 0);
  CHECK(st.stage_runs[0] == 0);
  CHECK(st.stage_runs[1] == 0);
  CHECK(st.light_tests == 0);
  CHECK(st.spawned[static_cast<int>(RayKind::kShadow)] == 0);
  // Control: the general pipeline does enter the (empty) light stage; the counter can fail.
  CHECK(general.stage_runs[0] > 0);
  CHECK(general.spawned[static_cast<int>(RayKind::kShadow)] == 0);
}

TEST_CASE("no textures: no texture stage, zero fetches") {
  SceneOptions o;
  o.textures = false;
  const Scene s = RandomScene(52, o);
  REQUIRE_FALSE(s.features.textures);
  ShadeStats general;
  const ShadeStats st = SpecializedVsGeneral(s, &general);
  CHECK((st.stages & kShadeStageTexture) == 0);
  CHECK(st.stage_runs[2] == 0);
  CHECK(st.texture_fetches == 0);
  CHECK(general.texture_fetches == 0);  // no UVs: even the general pipeline has nothing to fetch
  // Control: with textures the stage runs and fetches.
  ShadeStats textured_general;
  const ShadeStats textured = SpecializedVsGeneral(RandomScene(52, SceneOptions{}),
                                                   &textured_general);
  CHECK(textured.stage_runs[2] > 0);
  CHECK(textured.texture_fetches > 0);
}

TEST_CASE("purely diffuse: no reflection or refraction stage, no bounce rays") {
  SceneOptions o;
  o.reflection = false;
  o.transmission = false;
  o.specular = false;
  const Scene s = RandomScene(53, o);
  ShadeStats general;
  const ShadeStats st = SpecializedVsGeneral(s, &general);
  CHECK((st.stages & (kShadeStageReflection | kShadeStageRefraction | kShadeStageSpecular)) == 0);
  CHECK(st.stage_runs[1] == 0);
  CHECK(st.stage_runs[3] == 0);
  CHECK(st.stage_runs[4] == 0);
  CHECK(st.highlights == 0);
  CHECK(st.spawned[static_cast<int>(RayKind::kReflection)] == 0);
  CHECK(st.spawned[static_cast<int>(RayKind::kRefraction)] == 0);
  CHECK(st.spawned[static_cast<int>(RayKind::kShadow)] > 0);  // it did shade
  // Control: mirrors and glass do run both bounce stages.
  ShadeStats g2;
  const ShadeStats full = SpecializedVsGeneral(RandomScene(53, SceneOptions{}), &g2);
  CHECK(full.stage_runs[3] > 0);
  CHECK(full.stage_runs[4] > 0);
}

bool SameBits(const std::vector<float>& a, const std::vector<float>& b) {
  return a.size() == b.size() && std::memcmp(a.data(), b.data(), a.size() * sizeof(float)) == 0;
}

// A textured room for the render-level checks (no procedural scene has textures).
Scene TexturedRoom() {
  Scene s;
  s.name = "textured";
  std::mt19937 rng(8);
  Material floor;
  floor.diffuse = glm::vec3(0.9f);
  floor.texture = 0;
  Material wall;
  wall.diffuse = glm::vec3(0.7f, 0.6f, 0.5f);
  wall.texture = 1;
  wall.specular = glm::vec3(0.3f);
  wall.shininess = 30.0f;
  s.materials = {floor, wall};
  test::AddQuad(s, {-6, 0, 6}, {6, 0, 6}, {6, 0, -6}, {-6, 0, -6}, 0);
  test::AddQuad(s, {-6, 0, -3}, {6, 0, -3}, {6, 6, -3}, {-6, 6, -3}, 1);
  s.uvs = {{0, 0}, {3, 0}, {3, 3}, {0, 3}, {0, 0}, {2, 0}, {2, 1}, {0, 1}};
  s.textures.push_back(RandomTexture(rng, 8, 8));
  s.textures.push_back(RandomTexture(rng, 5, 3));
  PointLight l;
  l.position = glm::vec3(1, 5, 3);
  s.lights.push_back(l);
  s.camera.eye = glm::vec3(0.5f, 3.0f, 8.0f);
  s.camera.look_at = glm::vec3(0, 1, 0);
  test::SetFeatures(s);
  return s;
}

TEST_CASE("render: specialized pipeline image == general pipeline image, on every target") {
  std::vector<Scene> scenes;
  for (const char* name : {"erw6", "spherebox", "cornell"}) scenes.push_back(LoadScene(name));
  scenes.push_back(TexturedRoom());
  for (const Scene& s : scenes) {
    const Accel accel(s.mesh());
    RenderOptions ro;
    ro.width = 48;
    ro.height = 36;
    ro.max_depth = 3;
    const FrameContext spec_ctx = MakeFrameContext(s, accel, s.camera, ro);
    FrameContext gen_ctx = spec_ctx;
    gen_ctx.shade.stages = kShadeAllStages;
    CHECK(spec_ctx.shade.stages == ShadeStagesFor(s, spec_ctx.shade));  // chosen per frame
    std::vector<float> first;
    test::ForEachTarget([&](const char* target) {
      INFO("scene ", s.name, " target ", target);
      Framebuffer fs(ro.width, ro.height), fg(ro.width, ro.height);
      const FrameStats ss = RenderSerial(spec_ctx, fs);
      const FrameStats gs = RenderSerial(gen_ctx, fg);
      CHECK(SameSums(fs, fg));
      CHECK(ss.TotalRays() == gs.TotalRays());
      // Per-stage counters in FrameStats: what the scene lacks never ran.
      const SceneFeatures& f = s.features;
      CHECK((ss.shade.stage_runs[0] > 0) == f.lights);
      CHECK((ss.shade.stage_runs[2] > 0) == f.textures);
      CHECK((ss.shade.stage_runs[3] > 0) == f.reflection);
      CHECK((ss.shade.stage_runs[4] > 0) == f.transmission);
      CHECK(ss.shade.stages == spec_ctx.shade.stages);
      // And the image is the same on every target.
      const std::vector<float> rgb = fs.ToRgb();
      if (first.empty()) {
        first = rgb;
      } else {
        CHECK(SameBits(rgb, first));
      }
    });
  }
}

TEST_CASE("contributions of a scene's primary rays, added to a framebuffer: SIMD == ref image") {
  for (const char* name : {"cornell", "spherebox"}) {
    const Scene s = LoadScene(name);
    const Accel accel(s.mesh());
    constexpr int kW = 40, kH = 30;
    RayStream rays;
    AppendPrimaryRays(MakeCameraBasis(s.camera, kW, kH), Tile{0, 0, kW, kH}, RayOrder::kScanline,
                      rays);
    rays.FillPadding();
    HitStream hits(rays.size());
    hits.Resize(rays.size());
    hits.Reset();
    accel.Intersect(rays.view(), hits.view());
    ShadeOptions opt;
    ContributionStream want_c;
    RayStream want_rays;
    ref::Shade(s, opt, rays.view(), hits.view(), want_c, want_rays, nullptr);
    CHECK(want_c.size() > rays.size() / 2);  // background or ambient for most rays
    CHECK(want_c.size() <= rays.size());     // at most one per ray
    Framebuffer want(kW, kH);
    want.Add(want_c.view());
    // The framebuffer is order-independent: the same contributions one by one, backwards.
    Framebuffer backwards(kW, kH);
    const ContributionView wv = want_c.view();
    for (size_t i = wv.size; i-- > 0;) backwards.Add(wv.pixel[i], wv.r[i], wv.g[i], wv.b[i]);
    CHECK(SameSums(backwards, want));
    test::ForEachTarget([&](const char* target) {
      INFO("scene ", name, " target ", target);
      ContributionStream c;
      RayStream secondary;
      Shade(s, opt, rays.view(), hits.view(), c, secondary, nullptr);
      CHECK(SortedContributions(c) == SortedContributions(want_c));
      Framebuffer got(kW, kH);
      got.Add(c.view());
      CHECK(SameSums(got, want));
      CHECK(got.dropped_nan() == want.dropped_nan());
      CHECK(got.clamped() == want.clamped());
      CHECK(SameBits(got.ToRgb(), want.ToRgb()));
    });
  }
}

// The split overload writes the one-stream overload's rays, each to its light's stream or to
// the bounce stream, in the one-stream order within each; streams that repeat get them
// interleaved exactly as one stream would.
TEST_CASE("split output: each light's shadow rays and the bounce rays apart, same rays, same order") {
  const int shadow_kind = static_cast<int>(RayKind::kShadow);
  for (const uint32_t seed : {5u, 6u}) {
    const Scene s = RandomScene(seed, SceneOptions{});
    const size_t lights = s.lights.size();
    REQUIRE(lights >= 2);
    ShadeOptions opt;
    opt.max_depth = 3;
    for (const size_t n : {size_t{1}, size_t{17}, size_t{1000}}) {
      Stream st = RandomHits(s, n, seed * 77 + static_cast<uint32_t>(n), opt.max_depth);
      test::ForEachTarget([&](const char* target) {
        INFO("target ", target, " seed ", seed, " n ", n);
        Result one = RunSimd(s, opt, st);
        // Apart: one stream per light (each holding a ray already, which is kept) and bounce.
        std::vector<RayStream> per_light(lights);
        std::vector<RayStream*> to;
        for (RayStream& l : per_light) {
          l.Push(1, 2, 3, 4, 5, 6, 0, 1, 7, 1, 1, 1, 0, RayKind::kShadow);
          to.push_back(&l);
        }
        Result apart;
        Shade(s, opt, st.rays.view(), st.hits.view(), apart.contributions, to, apart.secondary,
              &apart.stats);
        CHECK(SortedContributions(apart.contributions) == SortedContributions(one.contributions));
        CHECK(apart.stats.spawned[shadow_kind] == one.stats.spawned[shadow_kind]);
        CHECK(apart.stats.light_tests == one.stats.light_tests);
        // Walk the one-stream output: each ray is the next one of its light or of bounce.
        std::vector<size_t> next(lights, 1);
        size_t next_bounce = 0;
        const RayStreamView ov = one.secondary.view();
        const RayStreamView bv = apart.secondary.view();
        bool all_found = true;
        for (size_t i = 0; i < ov.size; ++i) {
          if (ov.kind[i] != shadow_kind) {
            all_found &= next_bounce < bv.size && KeyOf(bv, next_bounce) == KeyOf(ov, i);
            ++next_bounce;
            continue;
          }
          bool found = false;
          for (size_t l = 0; l < lights && !found; ++l) {
            const RayStreamView lv = per_light[l].view();
            if (next[l] < lv.size && KeyOf(lv, next[l]) == KeyOf(ov, i)) {
              // It comes from light l: o is the light's position.
              const glm::vec3 o(lv.ox[next[l]], lv.oy[next[l]], lv.oz[next[l]]);
              CHECK(o == s.lights[l].position);
              ++next[l];
              found = true;
            }
          }
          all_found &= found;
        }
        CHECK(all_found);
        CHECK(next_bounce == bv.size);
        for (size_t l = 0; l < lights; ++l) {
          CHECK(next[l] == per_light[l].size());
          CHECK(per_light[l].view().pixel[0] == 7);  // the ray it held
        }
        // Shared: every light and bounce to one stream is the one-stream overload, bit for bit.
        Result shared;
        std::vector<RayStream*> same(lights, &shared.secondary);
        Shade(s, opt, st.rays.view(), st.hits.view(), shared.contributions, same,
              shared.secondary, &shared.stats);
        REQUIRE(shared.secondary.size() == one.secondary.size());
        const RayStreamView sv = shared.secondary.view();
        bool same_order = true;
        for (size_t i = 0; i < sv.size; ++i) same_order &= KeyOf(sv, i) == KeyOf(ov, i);
        CHECK(same_order);
      });
    }
  }
}

TEST_CASE("a reserved ContributionStream is never reallocated by Shade (SIMD and ref)") {
  const Scene s = RandomScene(61, SceneOptions{});
  ShadeOptions opt;
  opt.max_depth = 2;
  for (const size_t n : {size_t{1}, size_t{17}, size_t{257}}) {
    Stream st = RandomHits(s, n, 700 + static_cast<uint32_t>(n), opt.max_depth);
    constexpr size_t kBefore = 5;  // already in the stream: kept, and counted in the room
    ContributionStream c(kBefore + n + kStreamPad);
    const uint32_t* pixel = c.pixel_data();
    const float* r = c.r_data();
    const float* b = c.b_data();
    const size_t capacity = c.capacity();
    auto run = [&](bool simd) {
      c.Clear();
      for (size_t i = 0; i < kBefore; ++i) c.Push(static_cast<uint32_t>(i), 1.0f, 2.0f, 3.0f);
      RayStream secondary;
      if (simd) {
        Shade(s, opt, st.rays.view(), st.hits.view(), c, secondary, nullptr);
      } else {
        ref::Shade(s, opt, st.rays.view(), st.hits.view(), c, secondary, nullptr);
      }
      CHECK(c.pixel_data() == pixel);
      CHECK(c.r_data() == r);
      CHECK(c.b_data() == b);
      CHECK(c.capacity() == capacity);
      CHECK(c.size() >= kBefore);
      const ContributionView v = c.view();
      for (size_t i = 0; i < kBefore; ++i) {
        CHECK(v.pixel[i] == i);
        CHECK(v.g[i] == 2.0f);
      }
    };
    run(false);
    test::ForEachTarget([&](const char* target) {
      INFO("target ", target, " n ", n);
      run(true);
    });
  }
}

}  // namespace
}  // namespace rs
