// Shading: exact phong/ambient/background values, shadow rays (lit vs shadowed), mirror and
// Snell directions, total internal reflection, stage skipping by SceneFeatures, textures, and
// the robust-origin property: 1e6 secondary rays never re-hit their own triangle.
#include "kernels/shade.h"

#include <doctest/doctest.h>

#include <cmath>
#include <limits>
#include <random>
#include <vector>

#include "sched/framebuffer.h"
#include "tests/support/hand_scenes.h"

namespace rs {
namespace {

constexpr float kInf = std::numeric_limits<float>::infinity();

// Floor: the square [-10, 10]^2 at y = 0, facing +y, material 0 (diffuse 0.5, 0.6, 0.7).
Scene FloorScene() {
  Scene s;
  s.name = "floor";
  Material m;
  m.diffuse = glm::vec3(0.5f, 0.6f, 0.7f);
  s.materials.push_back(m);
  test::AddQuad(s, {-10, 0, 10}, {10, 0, 10}, {10, 0, -10}, {-10, 0, -10}, 0);
  s.ambient = 0.2f;
  s.background = glm::vec3(0.1f, 0.2f, 0.3f);
  test::SetFeatures(s);
  return s;
}

struct Shaded {
  Framebuffer fb;
  ContributionStream contributions;
  RayStream secondary;
  ShadeStats stats;
  std::vector<float> rgb;
};

// Traces `rays` against the scene with the brute-force oracle, shades them and adds the
// contributions to a 4-pixel framebuffer.
Shaded ShadeRays(const Scene& s, RayStream& rays, const ShadeOptions& options = {}) {
  Shaded out{Framebuffer(2, 2), ContributionStream(), RayStream(), ShadeStats(), {}};
  HitStream hits(rays.size());
  hits.Resize(rays.size());
  hits.Reset();
  test::BruteForceIntersect(s, rays.view(), hits.view());
  Shade(s, options, rays.view(), hits.view(), out.contributions, out.secondary, &out.stats);
  out.fb.Add(out.contributions.view());
  out.rgb = out.fb.ToRgb();
  return out;
}

void PushRay(RayStream& r, glm::vec3 o, glm::vec3 d, uint32_t pixel = 0,
             glm::vec3 w = glm::vec3(1.0f), int depth = 0,
             RayKind kind = RayKind::kPrimary) {
  r.Push(o.x, o.y, o.z, d.x, d.y, d.z, 0.0f, kInf, pixel, w.x, w.y, w.z, depth, kind);
}

glm::vec3 Dir(const RayStreamView& v, size_t i) { return {v.dx[i], v.dy[i], v.dz[i]}; }
glm::vec3 Org(const RayStreamView& v, size_t i) { return {v.ox[i], v.oy[i], v.oz[i]}; }
glm::vec3 Weight(const RayStreamView& v, size_t i) { return {v.wr[i], v.wg[i], v.wb[i]}; }

void CheckVec(glm::vec3 got, glm::vec3 want, double eps) {
  CHECK(got.x == doctest::Approx(want.x).epsilon(eps));
  CHECK(got.y == doctest::Approx(want.y).epsilon(eps));
  CHECK(got.z == doctest::Approx(want.z).epsilon(eps));
}

TEST_CASE("miss adds weight * background; hit adds ambient * kd * weight") {
  Scene s = FloorScene();
  RayStream rays;
  PushRay(rays, {0, 1, 0}, {0, 1, 0}, 1, glm::vec3(0.5f, 1.0f, 2.0f));  // up: miss
  PushRay(rays, {0, 1, 0}, {0, -1, 0}, 2, glm::vec3(1.0f, 0.5f, 0.25f));  // down: floor
  Shaded r = ShadeRays(s, rays);
  CHECK(r.stats.rays == 2);
  CHECK(r.stats.misses == 1);
  CHECK(r.stats.shading_calls == 1);
  CHECK(r.rgb[3] == doctest::Approx(0.05f).epsilon(1e-6));
  CHECK(r.rgb[4] == doctest::Approx(0.2f).epsilon(1e-6));
  CHECK(r.rgb[5] == doctest::Approx(0.6f).epsilon(1e-6));
  CHECK(r.rgb[6] == doctest::Approx(0.2f * 0.5f * 1.0f).epsilon(1e-6));
  CHECK(r.rgb[7] == doctest::Approx(0.2f * 0.6f * 0.5f).epsilon(1e-6));
  CHECK(r.rgb[8] == doctest::Approx(0.2f * 0.7f * 0.25f).epsilon(1e-6));
  CHECK(r.rgb[0] == 0.0f);  // pixel 0 untouched
  CHECK(r.secondary.size() == 0);  // no lights, no mirrors: nothing spawned
  // The stream itself: one contribution per ray, background for pixel 1, ambient for pixel 2.
  const ContributionView c = r.contributions.view();
  REQUIRE(c.size == 2);
  const size_t miss = c.pixel[0] == 1 ? 0 : 1;
  CHECK(c.pixel[miss] == 1);
  CHECK(c.pixel[1 - miss] == 2);
  CHECK(c.r[miss] == 0.5f * 0.1f);
  CHECK(c.g[miss] == 1.0f * 0.2f);
  CHECK(c.b[miss] == 2.0f * 0.3f);
}

TEST_CASE("no shadow rays without lights; no light loop at all") {
  Scene s = FloorScene();
  RayStream rays;
  for (int i = 0; i < 10; ++i) PushRay(rays, {0.3f * i - 1.0f, 2, 0.1f * i}, {0.1f, -1, 0});
  Shaded r = ShadeRays(s, rays);
  CHECK(r.stats.shading_calls == 10);
  CHECK(r.stats.light_tests == 0);
  CHECK(r.stats.spawned[static_cast<int>(RayKind::kShadow)] == 0);
  CHECK(r.secondary.size() == 0);

  // Control: the same rays with a light spawn one shadow ray each.
  PointLight light;
  light.position = glm::vec3(0, 5, 0);
  s.lights.push_back(light);
  test::SetFeatures(s);
  Shaded lit = ShadeRays(s, rays);
  CHECK(lit.stats.light_tests == 10);
  CHECK(lit.stats.spawned[static_cast<int>(RayKind::kShadow)] == 10);
  CHECK(lit.secondary.size() == 10);
}

TEST_CASE("shadow ray: origin above the floor, aimed at the light, phong weight, lit vs shadowed") {
  Scene s = FloorScene();
  s.materials[0].specular = glm::vec3(0.3f, 0.2f, 0.1f);
  s.materials[0].shininess = 8.0f;
  PointLight light;
  light.position = glm::vec3(0, 4, 0);
  light.color = glm::vec3(2.0f, 1.0f, 0.5f);
  s.lights.push_back(light);
  // A blocker square at y = 2 over x in [-10, -1]: shadows the floor for x < -1 (roughly).
  Material blocker;
  blocker.diffuse = glm::vec3(0.0f);
  s.materials.push_back(blocker);
  test::AddQuad(s, {-10, 2, 1}, {-1, 2, 1}, {-1, 2, -1}, {-10, 2, -1}, 1);
  test::SetFeatures(s);

  // Eye at (3, 3, 0) looking at the floor point (0, 0, 0): the highlight direction is the
  // mirror of the light direction (0, 1, 0) about n: rv = dot((0,1,0), view).
  RayStream rays;
  const glm::vec3 eye(3, 3, 0);
  PushRay(rays, eye, glm::normalize(glm::vec3(0, 0, 0) - eye), 0, glm::vec3(0.5f));
  PushRay(rays, {-3, 1, 0}, {0, -1, 0}, 1);  // hits the floor at (-3, 0, 0): in shadow
  Shaded r = ShadeRays(s, rays);
  REQUIRE(r.secondary.size() == 2);
  RayStream& sec = r.secondary;
  const RayStreamView v = sec.view();
  CHECK(v.kind[0] == static_cast<int32_t>(RayKind::kShadow));
  CHECK(v.pixel[0] == 0);
  CHECK(v.depth[0] == 0);
  CHECK(v.tmin[0] == kShadowTmin);
  CHECK(v.tmax[0] == 1.0f);
  CHECK(Org(v, 0) == light.position);  // from the light
  const glm::vec3 o = Org(v, 0) + Dir(v, 0);  // to the offset hit point, at t = 1
  CHECK(o.y > 0.0f);  // offset to the lit side
  // the floor's OffsetUnit is 8 (|x| <= 10), the light's 4 (4 above the point): 16 ulps of 8
  // plus 32 of 4, 2^-15, up to the rounding of front - light and back (ulp(4) = 2^-21)
  CHECK(std::fabs(o.y - 0x1p-15f) <= 0x1p-20f);
  // Weight: (kd cos + ks rv^n) * colour * w, cos = 1, rv = dot((0,1,0), view) = 1/sqrt(2).
  const float rv = 1.0f / std::sqrt(2.0f);
  const glm::vec3 want = (glm::vec3(0.5f, 0.6f, 0.7f) * 1.0f +
                          glm::vec3(0.3f, 0.2f, 0.1f) * std::pow(rv, 8.0f)) *
                         light.color * 0.5f;
  CheckVec(Weight(v, 0), want, 1e-5);

  // Lit vs shadowed: the oracle's any-hit on the two shadow rays.
  int blocked[2];
  for (size_t i = 0; i < 2; ++i) {
    HitStream h(1);
    h.Resize(1);
    h.Reset();
    RayStream one;
    one.PushFrom(v, i);
    test::BruteForceIntersect(s, one.view(), h.view());
    blocked[i] = h.view().prim[0] >= 0 ? 1 : 0;
  }
  CHECK(blocked[0] == 0);
  CHECK(blocked[1] == 1);
}

TEST_CASE("lights below the surface, behind the shading normal, and falloff") {
  Scene s = FloorScene();
  PointLight below;
  below.position = glm::vec3(0, -3, 0);
  PointLight far;
  far.position = glm::vec3(0, 3, 0);
  far.falloff = 0.5f;
  s.lights = {below, far};
  test::SetFeatures(s);
  RayStream rays;
  PushRay(rays, {0, 1, 0}, {0, -1, 0});
  Shaded r = ShadeRays(s, rays);
  CHECK(r.stats.light_tests == 2);
  REQUIRE(r.secondary.size() == 1);  // only the light above
  RayStream& sec = r.secondary;
  // kd * cos(0) / (1 + 0.5 * 9)
  CheckVec(Weight(sec.view(), 0), glm::vec3(0.5f, 0.6f, 0.7f) / 5.5f, 1e-6);

  // Seen from below, the floor's geometric normal flips to -y: now only `below` lights it.
  RayStream from_below;
  PushRay(from_below, {0, -1, 0}, {0, 1, 0});
  Shaded b = ShadeRays(s, from_below);
  REQUIRE(b.secondary.size() == 1);
  RayStream& bsec = b.secondary;
  CHECK(bsec.view().oy[0] < 0.0f);
  CheckVec(Weight(bsec.view(), 0), glm::vec3(0.5f, 0.6f, 0.7f), 1e-6);
}

TEST_CASE("mirror reflection: exact direction, weight, depth, cutoff and max depth") {
  Scene s = FloorScene();
  s.materials[0].reflectivity = 0.75f;
  s.materials[0].specular = glm::vec3(1.0f, 0.5f, 0.25f);  // tints the mirror
  test::SetFeatures(s);
  RayStream rays;
  PushRay(rays, {-1, 1, 0}, glm::vec3(1, -1, 0) / std::sqrt(2.0f), 3, glm::vec3(0.8f), 1,
          RayKind::kReflection);
  ShadeOptions opt;
  opt.max_depth = 2;
  Shaded r = ShadeRays(s, rays, opt);
  REQUIRE(r.secondary.size() == 1);
  RayStream& sec = r.secondary;
  const RayStreamView v = sec.view();
  CHECK(v.kind[0] == static_cast<int32_t>(RayKind::kReflection));
  CHECK(v.depth[0] == 2);
  CHECK(v.pixel[0] == 3);
  CHECK(v.tmax[0] == kInf);
  CheckVec(Dir(v, 0), glm::vec3(1, 1, 0) / std::sqrt(2.0f), 1e-6);
  CHECK(v.dz[0] == 0.0f);
  CHECK(v.oy[0] > 0.0f);
  CHECK(v.ox[0] == doctest::Approx(0.0f).epsilon(1e-6));
  CheckVec(Weight(v, 0), 0.8f * 0.75f * glm::vec3(1.0f, 0.5f, 0.25f), 1e-6);
  // Local term scaled by 1 - reflectivity.
  CHECK(r.rgb[9] == doctest::Approx(0.8f * 0.25f * 0.2f * 0.5f).epsilon(1e-5));

  opt.max_depth = 1;  // depth 1 rays may not bounce further
  Shaded capped = ShadeRays(s, rays, opt);
  CHECK(capped.secondary.size() == 0);
  opt.max_depth = 4;
  opt.weight_cutoff = 0.7f;  // max weight 0.8 * 0.75 = 0.6 < 0.7
  Shaded culled = ShadeRays(s, rays, opt);
  CHECK(culled.secondary.size() == 0);
  CHECK(culled.stats.culled == 1);
}

// A glass slab y in [-1, 0] (top face +y, bottom face -y), ior 1.5.
Scene GlassSlab() {
  Scene s;
  Material glass;
  glass.diffuse = glm::vec3(0.5f);  // nonzero: proves the local term is scaled away
  glass.transmission = 1.0f;
  glass.ior = 1.5f;
  s.materials.push_back(glass);
  test::AddQuad(s, {-10, 0, 10}, {10, 0, 10}, {10, 0, -10}, {-10, 0, -10}, 0);       // top
  test::AddQuad(s, {-10, -1, -10}, {10, -1, -10}, {10, -1, 10}, {-10, -1, 10}, 0);   // bottom
  test::SetFeatures(s);
  return s;
}

TEST_CASE("refraction: Snell's law entering and leaving, origin on the far side") {
  Scene s = GlassSlab();
  const float sin45 = std::sqrt(0.5f);
  RayStream rays;
  PushRay(rays, {-1, 1, 0}, glm::vec3(sin45, -sin45, 0), 0, glm::vec3(0.9f));  // enters top
  // From inside at 30 degrees to the bottom normal: leaves (sin t = 1.5 * 0.5 = 0.75).
  PushRay(rays, {0, -0.5f, 0}, glm::vec3(0.5f, -std::sqrt(0.75f), 0), 1, glm::vec3(1.0f), 0,
          RayKind::kRefraction);
  Shaded r = ShadeRays(s, rays);
  REQUIRE(r.secondary.size() == 2);
  RayStream& sec = r.secondary;
  const RayStreamView v = sec.view();
  // Entering: sin t = sin 45 / 1.5.
  const float st = sin45 / 1.5f;
  CHECK(v.kind[0] == static_cast<int32_t>(RayKind::kRefraction));
  CheckVec(Dir(v, 0), glm::vec3(st, -std::sqrt(1 - st * st), 0), 1e-6);
  CHECK(v.oy[0] < 0.0f);  // went through: origin below the top face
  CHECK(v.oy[0] > -2e-4f);  // OffsetUnit of the slab's face, times 2^-16
  CheckVec(Weight(v, 0), glm::vec3(0.9f), 1e-6);
  CHECK(v.depth[0] == 1);
  // Leaving the bottom: sin t = 0.75, going down.
  CHECK(v.kind[1] == static_cast<int32_t>(RayKind::kRefraction));
  CheckVec(Dir(v, 1), glm::vec3(0.75f, -std::sqrt(1 - 0.75f * 0.75f), 0), 1e-6);
  CHECK(v.oy[1] < -1.0f);
  // Transmission 1: no local term at all (diffuse is 0.5).
  for (const float x : r.rgb) CHECK(x == 0.0f);
}

TEST_CASE("total internal reflection becomes a reflection ray with the transmission weight") {
  Scene s = GlassSlab();
  s.materials[0].transmission = 0.5f;
  test::SetFeatures(s);
  // From inside at 60 degrees to the bottom normal: sin t = 1.5 * sin 60 > 1.
  const glm::vec3 d(std::sqrt(0.75f), -0.5f, 0);
  RayStream rays;
  PushRay(rays, {0, -0.5f, 0}, d, 2, glm::vec3(1.0f, 0.5f, 0.25f), 0, RayKind::kRefraction);
  Shaded r = ShadeRays(s, rays);
  REQUIRE(r.secondary.size() == 1);
  RayStream& sec = r.secondary;
  const RayStreamView v = sec.view();
  CHECK(v.kind[0] == static_cast<int32_t>(RayKind::kReflection));
  CheckVec(Dir(v, 0), glm::vec3(d.x, -d.y, 0), 1e-6);
  CHECK(v.oy[0] > -1.0f);  // stays inside the slab
  CHECK(v.oy[0] < -1.0f + 1e-4f);
  CheckVec(Weight(v, 0), 0.5f * glm::vec3(1.0f, 0.5f, 0.25f), 1e-6);
  // Just below the critical angle (41.81 deg) it refracts: 41 degrees.
  const float a = 41.0f * 3.14159265f / 180.0f;
  RayStream below;
  PushRay(below, {0, -0.5f, 0}, glm::vec3(std::sin(a), -std::cos(a), 0), 0, glm::vec3(1.0f), 0,
          RayKind::kRefraction);
  Shaded rb = ShadeRays(s, below);
  REQUIRE(rb.secondary.size() == 1);
  CHECK(rb.secondary.view().kind[0] ==
        static_cast<int32_t>(RayKind::kRefraction));
}

TEST_CASE("Refract and Reflect helpers on literal values") {
  glm::vec3 t;
  // Normal incidence passes straight through for any eta.
  REQUIRE(Refract(glm::vec3(0, -1, 0), glm::vec3(0, 1, 0), 1.0f / 1.5f, &t));
  CheckVec(t, glm::vec3(0, -1, 0), 1e-7);
  // Grazing incidence from the dense side: TIR.
  CHECK_FALSE(Refract(glm::normalize(glm::vec3(1, -0.01f, 0)), glm::vec3(0, 1, 0), 1.5f, &t));
  // eta = 1: no bending.
  const glm::vec3 d = glm::normalize(glm::vec3(0.3f, -0.8f, 0.2f));
  REQUIRE(Refract(d, glm::vec3(0, 1, 0), 1.0f, &t));
  CheckVec(t, d, 1e-6);
  CheckVec(Reflect(glm::vec3(1, -2, 3), glm::vec3(0, 1, 0)), glm::vec3(1, 2, 3), 1e-7);
}

TEST_CASE("smooth shading normal: interpolated, kept in the geometric hemisphere") {
  Scene s = FloorScene();
  // Vertex normals tilted towards +x at every corner: ns = normalize(1, 1, 0).
  s.normals.assign(s.positions.size(), glm::normalize(glm::vec3(1, 1, 0)));
  PointLight light;
  light.position = glm::vec3(0, 5, 0);
  s.lights.push_back(light);
  test::SetFeatures(s);
  RayStream rays;
  PushRay(rays, {0, 1, 0}, {0, -1, 0});
  Shaded r = ShadeRays(s, rays);
  REQUIRE(r.secondary.size() == 1);
  RayStream& sec = r.secondary;
  // cos = dot(ns, up) = 1/sqrt(2)
  CheckVec(Weight(sec.view(), 0), glm::vec3(0.5f, 0.6f, 0.7f) / std::sqrt(2.0f), 1e-6);
  // Normals pointing down (wrong hemisphere) are flipped up: the same value.
  s.normals.assign(s.positions.size(), -glm::normalize(glm::vec3(1, 1, 0)));
  Shaded f = ShadeRays(s, rays);
  REQUIRE(f.secondary.size() == 1);
  CheckVec(Weight(f.secondary.view(), 0),
           glm::vec3(0.5f, 0.6f, 0.7f) / std::sqrt(2.0f), 1e-6);
}

Texture Checker2x2() {
  Texture t;
  t.path = "checker";
  t.width = 2;
  t.height = 2;
  // row 0 (top): red, green; row 1 (bottom): blue, white
  t.rgb = {1, 0, 0, 0, 1, 0, 0, 0, 1, 1, 1, 1};
  return t;
}

TEST_CASE("SampleTexture: texel centres, bilinear, wrap, non-finite uv") {
  const Texture t = Checker2x2();
  CheckVec(SampleTexture(t, {0.25f, 0.75f}), {1, 0, 0}, 1e-6);  // top-left texel centre
  CheckVec(SampleTexture(t, {0.75f, 0.75f}), {0, 1, 0}, 1e-6);
  CheckVec(SampleTexture(t, {0.25f, 0.25f}), {0, 0, 1}, 1e-6);  // v = 0 is the bottom
  CheckVec(SampleTexture(t, {0.5f, 0.75f}), {0.5f, 0.5f, 0}, 1e-6);
  CheckVec(SampleTexture(t, {1.25f, -0.25f}), {1, 0, 0}, 1e-6);  // wraps to (0.25, 0.75)
  CheckVec(SampleTexture(t, {0.0f, 0.75f}), {0.5f, 0.5f, 0}, 1e-6);  // edge: wraps around
  const glm::vec3 n = SampleTexture(t, {std::numeric_limits<float>::quiet_NaN(), 0.75f});
  CHECK(std::isfinite(n.x));
  CheckVec(SampleTexture(Texture{}, {0.3f, 0.3f}), {1, 1, 1}, 1e-7);
}

TEST_CASE("texture fetched only when the scene has textures and UVs") {
  Scene s = FloorScene();
  s.textures.push_back(Checker2x2());
  s.materials[0].texture = 0;
  s.materials[0].diffuse = glm::vec3(1.0f);
  test::SetFeatures(s);  // no UVs: features.textures is false
  REQUIRE_FALSE(s.features.textures);
  RayStream rays;
  PushRay(rays, {0, 1, 0}, {0, -1, 0});
  Shaded plain = ShadeRays(s, rays);
  CHECK(plain.stats.texture_fetches == 0);
  CHECK(plain.rgb[0] == doctest::Approx(0.2f).epsilon(1e-6));  // ambient * 1
  CHECK(plain.rgb[1] == doctest::Approx(0.2f).epsilon(1e-6));

  // UVs: the quad's corners (x, z) = (-10,10), (10,10), (10,-10), (-10,-10) get (0,0) (1,0)
  // (1,1) (0,1): the hit at (5, 0, 5) has uv (0.75, 0.25), the centre of the bottom-right
  // texel (white); (-5, 0, -5) has uv (0.25, 0.75), the top-left texel (red).
  s.uvs = {{0, 0}, {1, 0}, {1, 1}, {0, 1}};
  test::SetFeatures(s);
  REQUIRE(s.features.textures);
  RayStream at;
  PushRay(at, {5, 1, 5}, {0, -1, 0});
  PushRay(at, {-5, 1, -5}, {0, -1, 0}, 1);  // uv (0.25, 0.75): red
  Shaded tex = ShadeRays(s, at);
  CHECK(tex.stats.texture_fetches == 2);
  CheckVec({tex.rgb[0], tex.rgb[1], tex.rgb[2]}, glm::vec3(0.2f), 1e-5);
  CheckVec({tex.rgb[3], tex.rgb[4], tex.rgb[5]}, glm::vec3(0.2f, 0, 0), 1e-5);
}

TEST_CASE("OffsetRayOrigin: 16 ulps of the triangle's unit plus 32 of the light's, along n") {
  const glm::vec3 n(0, 1, 0);
  const glm::vec3 p(1000.0f, 1000.0f, -1000.0f);
  const glm::vec3 o = OffsetRayOrigin(p, n, 512.0f);
  CHECK(o.x == p.x);
  CHECK(o.z == p.z);
  CHECK(o.y - p.y == 512.0f / 524288.0f);  // 16 ulps of 512 (1 ulp of 1000: 2^-13 = 64 x 2^-19)
  const glm::vec3 neg = OffsetRayOrigin(glm::vec3(0, -1000.0f, 0), n, 512.0f);
  CHECK(neg.y == -1000.0f + 512.0f / 524288.0f);  // negative coordinates move along n too
  const glm::vec3 z = OffsetRayOrigin(glm::vec3(0.0f), glm::vec3(0, -1, 0), 1.0f, 4.0f);
  CHECK(z.y == -(1.0f / 524288.0f + 4.0f / 262144.0f));
  CHECK(z.x == 0.0f);
  // far from the origin the step stays a few ulps of the coordinates: at 1.5e5 (ulp 1/64) a
  // quarter unit, not Waechter and Binder's 256 ulps (4 units)
  const glm::vec3 far = OffsetRayOrigin(glm::vec3(148376.0f, 1233.0f, -223423.0f), n, 131072.0f,
                                        LightOffsetUnit({148376.0f, 1233.0f, -223423.0f}, {}));
  CHECK(far.y - 1233.0f == 0.25f);
  PointLight l;
  l.position = glm::vec3(148378.0f, 1238.0f, -223420.5f);
  CHECK(LightOffsetUnit({148376.0f, 1233.0f, -223423.0f}, std::span(&l, 1)) == 4.0f);
  CHECK(LightOffsetUnit(glm::vec3(0.0f), std::span(&l, 1)) == 131072.0f);
}

TEST_CASE("OffsetUnit: the power of two of the triangle's largest coordinate; offsets scale with it") {
  const glm::vec3 a(0.0f), b(10.0f, 0.0f, 0.0f), c(0.0f, 0.0f, -3.0f);
  CHECK(OffsetUnit(a, b, c) == 8.0f);
  CHECK(OffsetUnit(a, a * 2.0f, c) == 2.0f);
  CHECK(OffsetUnit(a, a, a) == std::ldexp(1.0f, -126));  // clamped to the smallest normal
  CHECK(OffsetUnit(b * 1e30f, c, a) == std::ldexp(1.0f, 102));
  // A scene scaled by a power of two gets exactly the scaled origins, near 0 and away from it.
  const glm::vec3 n = glm::normalize(glm::vec3(0.3f, 1.0f, -0.2f));
  const glm::vec3 p(0.01f, 0.0f, 5.0f);
  for (const int e : {-40, -12, 12, 40}) {
    CAPTURE(e);
    const float k = std::ldexp(1.0f, e);
    const glm::vec3 o = OffsetRayOrigin(p, n, OffsetUnit(a, b, c));
    const glm::vec3 ok = OffsetRayOrigin(p * k, n, OffsetUnit(a * k, b * k, c * k));
    for (int i = 0; i < 3; ++i) CHECK(ok[i] == o[i] * k);
  }
}

// Random points on random triangles, random directions on the side the ray leaves toward:
// the offset origin must never see its own triangle (a plain hit point does, often).
TEST_CASE("no self-hit: 1e6 secondary rays from random points of a sphere and a soup") {
  Scene s;
  s.materials.push_back(Material{});
  test::AddIcosphere(s, {0, 0, 0}, 1.0f, 3, 0);           // around the origin
  test::AddIcosphere(s, {0.01f, -0.02f, 0}, 0.03f, 2, 0);  // inside the |p| < 1/32 zone
  test::AddIcosphere(s, {1000, -200, 50}, 10.0f, 3, 0);   // far away, large ulps
  std::mt19937 rng(99);
  std::uniform_real_distribution<float> unit(0.0f, 1.0f);
  std::normal_distribution<float> gauss(0.0f, 1.0f);
  for (int i = 0; i < 300; ++i) {  // a soup of thin and large triangles anywhere
    const glm::vec3 c(gauss(rng) * 300, gauss(rng) * 300, gauss(rng) * 300);
    const float scale = std::exp2(unit(rng) * 12 - 6);
    const uint32_t b = static_cast<uint32_t>(s.positions.size());
    for (int k = 0; k < 3; ++k) {
      s.positions.push_back(c + scale * glm::vec3(gauss(rng), gauss(rng), gauss(rng)));
    }
    s.triangles.push_back(glm::uvec3(b, b + 1, b + 2));
    s.material_ids.push_back(0);
  }

  size_t self_hits = 0, plain_hits = 0, tested = 0;
  const int kRays = 1000000;
  for (int i = 0; i < kRays; ++i) {
    const glm::uvec3 tri = s.triangles[rng() % s.triangles.size()];
    const glm::vec3 p0 = s.positions[tri.x], p1 = s.positions[tri.y], p2 = s.positions[tri.z];
    const glm::vec3 nf = glm::cross(p1 - p0, p2 - p0);
    if (!(glm::length(nf) > 0.0f)) continue;
    const glm::vec3 n = glm::normalize(nf) * (rng() % 2 ? 1.0f : -1.0f);  // front or back
    float u = unit(rng), v = unit(rng);
    if (u + v > 1.0f) {
      u = 1.0f - u;
      v = 1.0f - v;
    }
    const float b0 = 1.0f - u - v;
    const glm::vec3 p = b0 * p0 + u * p1 + v * p2;  // as Shade computes it
    glm::vec3 d(gauss(rng), gauss(rng), gauss(rng));
    if (glm::dot(d, n) < 0.0f) d = -d;
    if (!(glm::dot(d, n) > 0.0f)) continue;
    ++tested;
    float t;
    if (test::IntersectWatertight(OffsetRayOrigin(p, n, OffsetUnit(p0, p1, p2)), d, p0, p1, p2,
                                  0.0f, kInf, &t)) {
      ++self_hits;
    }
    if (i % 10 == 0 && test::IntersectWatertight(p, d, p0, p1, p2, 0.0f, kInf, &t)) {
      ++plain_hits;
    }
  }
  CHECK(tested > kRays * 99 / 100);
  CHECK(self_hits == 0);
  // Control: without the offset a sizeable share of rays re-hit their own triangle.
  CHECK(plain_hits > tested / 10 / 20);
  MESSAGE("self-hits without offset: ", plain_hits, " of ", tested / 10);
}

// Through the real Accel, on closed convex spheres: a ray leaving outward from an offset origin
// can hit nothing at all (the sphere lies behind the plane of the start triangle), and a ray
// going inward (refraction) must exit through another triangle.
TEST_CASE("no self-hit through Accel: convex spheres near and far from the origin") {
  struct Sphere {
    glm::vec3 centre;
    float radius;
  };
  for (const Sphere& sphere : {Sphere{glm::vec3(0.0f), 1.0f},
                               Sphere{glm::vec3(0.01f, 0.0f, -0.01f), 0.02f},
                               Sphere{glm::vec3(1000, -200, 50), 10.0f}}) {
    const glm::vec3 centre = sphere.centre;
    const float radius = sphere.radius;
    INFO("sphere at ", centre.x, ",", centre.y, ",", centre.z, " r ", radius);
    Scene s;
    s.materials.push_back(Material{});
    test::AddIcosphere(s, centre, radius, 3, 0);
    const Accel accel(test::MeshOf(s));
    std::mt19937 rng(5);
    std::uniform_real_distribution<float> unit(0.0f, 1.0f);
    std::normal_distribution<float> gauss(0.0f, 1.0f);
    const size_t kRays = 100000;
    for (const bool outward : {true, false}) {
      RayStream rays;
      std::vector<int32_t> own;
      for (size_t i = 0; i < kRays; ++i) {
        const uint32_t k = static_cast<uint32_t>(rng() % s.triangles.size());
        const glm::uvec3 tri = s.triangles[k];
        const glm::vec3 p0 = s.positions[tri.x], p1 = s.positions[tri.y],
                        p2 = s.positions[tri.z];
        const glm::vec3 n_out = glm::normalize(glm::cross(p1 - p0, p2 - p0));
        const glm::vec3 n = outward ? n_out : -n_out;
        float u = unit(rng), v = unit(rng);
        if (u + v > 1.0f) {
          u = 1.0f - u;
          v = 1.0f - v;
        }
        const glm::vec3 p = (1.0f - u - v) * p0 + u * p1 + v * p2;
        glm::vec3 d(gauss(rng), gauss(rng), gauss(rng));
        if (glm::dot(d, n) < 0.0f) d = -d;
        if (!(glm::dot(d, n) > 0.0f)) continue;
        PushRay(rays, OffsetRayOrigin(p, n, OffsetUnit(p0, p1, p2)), d);
        own.push_back(static_cast<int32_t>(k));
      }
      rays.FillPadding();
      HitStream hits(rays.size());
      hits.Resize(rays.size());
      hits.Reset();
      accel.Intersect(rays.view(), hits.view());
      size_t hit = 0, self = 0;
      for (size_t i = 0; i < rays.size(); ++i) {
        hit += hits.view().prim[i] >= 0 ? 1 : 0;
        self += hits.view().prim[i] == own[i] ? 1 : 0;
      }
      INFO("direction: ", (outward ? "outward" : "inward"));
      CHECK(self == 0);
      if (outward) {
        CHECK(hit == 0);
      } else {
        CHECK(hit == rays.size());  // closed sphere: every inward ray exits somewhere
      }
    }
  }
}

TEST_CASE("stats: spawned rays by kind") {
  Scene s = FloorScene();
  s.materials[0].reflectivity = 0.3f;
  s.materials[0].transmission = 0.3f;
  PointLight a, b;
  a.position = glm::vec3(1, 3, 0);
  b.position = glm::vec3(-1, 3, 0);
  s.lights = {a, b};
  test::SetFeatures(s);
  RayStream rays;
  for (int i = 0; i < 5; ++i) PushRay(rays, {0.1f * i, 1, 0}, {0, -1, 0.1f});
  PushRay(rays, {0, 1, 0}, {0, 1, 0});  // miss
  Shaded r = ShadeRays(s, rays);
  CHECK(r.stats.rays == 6);
  CHECK(r.stats.misses == 1);
  CHECK(r.stats.shading_calls == 5);
  CHECK(r.stats.light_tests == 10);
  CHECK(r.stats.spawned[static_cast<int>(RayKind::kShadow)] == 10);
  CHECK(r.stats.spawned[static_cast<int>(RayKind::kReflection)] == 5);
  CHECK(r.stats.spawned[static_cast<int>(RayKind::kRefraction)] == 5);
  CHECK(r.stats.spawned[static_cast<int>(RayKind::kPrimary)] == 0);
  CHECK(r.secondary.size() == 20);
}

// Shadow rays from point lights 2^-4 to 2^10 triangle sizes away to the offset origins of
// random points on random triangles (a third in axis planes, no slivers) at 0, 10, 1e3 and 1e5
// from the origin, traced from the light as Shade emits them (t in [kShadowTmin, 1]): none
// may stop at its own triangle. Lights within 64 ulps of the coordinates from the plane are
// not counted: no offset can tell their side (the rounding of the light's position decides
// it). Control: from the plain point p, most do.
TEST_CASE("no self-shadowing: shadow rays from near and distant lights to offset origins") {
  std::mt19937 rng(7);
  std::uniform_real_distribution<float> unit(0.0f, 1.0f);
  std::normal_distribution<float> gauss(0.0f, 1.0f);
  for (const double off : {0.0, 10.0, 1e3, 1e5}) {
    size_t self = 0, plain = 0, tested = 0, near_plane = 0;
    for (int i = 0; i < 250000; ++i) {
      const float s = std::exp2(unit(rng) * 8 - 4);
      const glm::vec3 c = glm::vec3(gauss(rng), gauss(rng), gauss(rng)) * float(off);
      glm::vec3 p0 = c + s * glm::vec3(gauss(rng), gauss(rng), gauss(rng));
      glm::vec3 p1 = c + s * glm::vec3(gauss(rng), gauss(rng), gauss(rng));
      glm::vec3 p2 = c + s * glm::vec3(gauss(rng), gauss(rng), gauss(rng));
      if (i % 3 == 0) {  // in an axis plane
        const int ax = int(rng() % 3);
        p1[ax] = p2[ax] = p0[ax];
      }
      const glm::vec3 nf = glm::cross(p1 - p0, p2 - p0);
      if (!(glm::length(nf) > 1e-3f * s * s)) continue;
      glm::vec3 n = FaceNormal(p0, p1, p2);
      float u = unit(rng), v = unit(rng);
      if (u + v > 1.0f) {
        u = 1.0f - u;
        v = 1.0f - v;
      }
      const glm::vec3 p = (1.0f - u - v) * p0 + u * p1 + v * p2;  // as Shade computes it
      glm::vec3 dir(gauss(rng), gauss(rng), gauss(rng));
      dir = glm::normalize(dir);
      if (glm::dot(dir, n) < 0) n = -n;
      if (glm::dot(dir, n) < 1e-3f) continue;
      const float dist = s * std::exp2(unit(rng) * 14 - 4);
      PointLight light;
      light.position = p + dist * dir;
      const glm::vec3 L = light.position;
      const glm::vec3 to = L - p;
      if (!(glm::dot(n, to / std::sqrt(glm::dot(to, to))) > 0.0f)) continue;  // as Shade
      const glm::dvec3 q0(p0);
      const glm::dvec3 nd = glm::normalize(glm::cross(glm::dvec3(p1) - q0, glm::dvec3(p2) - q0));
      const double light_side = glm::dot(nd, glm::dvec3(L) - q0);
      const float mag =
          std::max({std::fabs(L.x), std::fabs(L.y), std::fabs(L.z), OffsetUnit(p0, p1, p2)});
      if (std::fabs(light_side) < 64.0 * mag / 8388608.0) {
        ++near_plane;
        continue;
      }
      ++tested;
      const glm::vec3 front = OffsetRayOrigin(p, n, OffsetUnit(p0, p1, p2),
                                              LightOffsetUnit(p, std::span(&light, 1)));
      float t;
      if (test::IntersectWatertight(L, front - L, p0, p1, p2, kShadowTmin, 1.0f, &t)) ++self;
      if (test::IntersectWatertight(L, p - L, p0, p1, p2, kShadowTmin, 1.0f, &t)) ++plain;
    }
    MESSAGE("triangles at ", off, ": ", self, " of ", tested,
            " shadow rays self-shadowed (from the plain point: ", plain,
            "); lights near the plane, not counted: ", near_plane);
    CHECK(self == 0);
    CHECK(plain > tested / 2);
    CHECK(tested > 150000);
  }
}

}  // namespace
}  // namespace rs
