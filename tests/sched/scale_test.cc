// Scenes far from unit size: the hand scene (two quads, two icospheres, a block, two lights, one
// without falloff) scaled by 1e-15 .. 1e14 about the origin, prepared as the loader prepares
// every scene (NormalizeScale), renders like the unscaled one: shading offsets are relative to
// the triangle hit (OffsetUnit) and scenes outside [2^-20, 2^20] are brought into the kernels'
// exact range by a power of two. Face normals of triangles whose edge cross product leaves the
// float range (FaceNormal) keep every lit pixel lit. Scaling by a factor that is not a power of
// two rounds every coordinate, so a few pixels on silhouettes and shadow edges may differ.
#include <doctest/doctest.h>

#include <cmath>
#include <cstdio>
#include <vector>

#include <fmt/format.h>

#include "scenes/load.h"
#include "sched/render.h"
#include "tests/support/hand_scenes.h"

namespace rs {
namespace {

Scene Scaled(float k) {
  Scene s = test::HandScene();
  for (glm::vec3& p : s.positions) p *= k;
  for (PointLight& l : s.lights) {
    l.position *= k;
    l.falloff /= k * k;  // the same attenuation at the scaled distances
  }
  s.camera.eye *= k;
  s.camera.look_at *= k;
  NormalizeScale(s);
  test::SetFeatures(s);
  return s;
}

std::vector<float> Render(const Scene& s) {
  RenderOptions o;
  o.width = 64;
  o.height = 48;
  o.max_depth = 3;
  const Accel accel(test::MeshOf(s));
  return RenderImage(s, accel, s.camera, o).rgb;
}

TEST_CASE("scaled scenes: 1e-15 .. 1e14 match the unscaled image") {
  const std::vector<float> want = Render(Scaled(1.0f));
  for (const float k : {1e-15f, 1e-12f, 1e-6f, 1e-3f, 1e3f, 1e6f, 1e12f, 1e14f}) {
    CAPTURE(k);
    const std::vector<float> got = Render(Scaled(k));
    REQUIRE(got.size() == want.size());
    size_t nan = 0, went_dark = 0, differ = 0;
    const size_t pixels = got.size() / 3;
    for (size_t i = 0; i < pixels; ++i) {
      float lum_got = 0, lum_want = 0, diff = 0;
      for (int c = 0; c < 3; ++c) {
        nan += !std::isfinite(got[3 * i + c]);
        lum_got += got[3 * i + c];
        lum_want += want[3 * i + c];
        diff = std::fmax(diff, std::fabs(got[3 * i + c] - want[3 * i + c]));
      }
      went_dark += lum_want > 0.3f && lum_got < 0.05f;
      differ += diff > 0.02f;
    }
    std::printf("scale %g: %zu of %zu pixels differ by more than 0.02\n", double(k), differ, pixels);
    CHECK(nan == 0);
    CHECK(went_dark == 0);
    CHECK(differ <= pixels / 100);
  }
}

// Hostile-input row 11: a scene file's sphere of radius 1e-15 .. 1e14 (on a floor, default view
// and light) renders the image of radius 1: before, from 1e14 or 1e-15 on the image was black.
TEST_CASE("scene files: spheres of radius 1e-15 .. 1e14 render like radius 1") {
  const auto load = [](float r) {
    const std::string c = fmt::format("{:.9g}", double(r));
    const std::string text = fmt::format(
        R"({{"meshes": [{{"sphere": {{"center": [0, {0}, 0], "radius": {0}}}}},
                        {{"quad": [[-{1}, 0, -{1}], [-{1}, 0, {1}], [{1}, 0, {1}], [{1}, 0, -{1}]]}}],
            "lights": [{{"position": [{2}, {3}, {2}]}}]}})",
        c, fmt::format("{:.9g}", 4.0 * r), fmt::format("{:.9g}", 2.0 * r),
        fmt::format("{:.9g}", 5.0 * r));
    return LoadSceneJson(text, "sphere.json", "");
  };
  const Scene unit = load(1.0f);
  const std::vector<float> want = Render(unit);
  const auto lit_pixels = [](const std::vector<float>& img) {
    size_t lit = 0;
    for (size_t i = 0; i < img.size() / 3; ++i) lit += img[3 * i] + img[3 * i + 1] + img[3 * i + 2] > 0.1f;
    return lit;
  };
  const size_t want_lit = lit_pixels(want);
  REQUIRE(want_lit > 100);
  for (const float r : {1e-15f, 1e-12f, 1e12f, 1e14f}) {
    CAPTURE(r);
    const Scene s = load(r);
    const std::vector<float> got = Render(s);
    REQUIRE(got.size() == want.size());
    size_t differ = 0;
    for (size_t i = 0; i < got.size() / 3; ++i) {
      float diff = 0;
      for (int c = 0; c < 3; ++c) diff = std::fmax(diff, std::fabs(got[3 * i + c] - want[3 * i + c]));
      differ += diff > 0.02f;
    }
    CHECK(lit_pixels(got) + got.size() / 3 / 100 >= want_lit);
    CHECK(differ <= got.size() / 3 / 100);
  }
}

TEST_CASE("NormalizeScale: a power of two into [1, 2) outside [2^-20, 2^20], errors outside the range") {
  Scene unit = Scaled(1.0f);
  CHECK(unit.coordinate_scale == 1.0f);
  Scene big = test::HandScene();
  Scene tiny = test::HandScene();
  for (Scene* s : {&big, &tiny}) {
    const float k = s == &big ? 0x1p40f : 0x1p-40f;
    for (glm::vec3& p : s->positions) p *= k;
    for (PointLight& l : s->lights) {
      l.position *= k;
      l.falloff /= k * k;
    }
    s->camera.eye *= k;
    s->camera.look_at *= k;
    NormalizeScale(*s);
    // exactly the unscaled scene times 2^-3 (its largest coordinate, 8, lies in [8, 16)): a
    // power of two changes no rounding
    const float back = s->coordinate_scale * k;
    CHECK(back == 0.125f);
    REQUIRE(s->positions.size() == unit.positions.size());
    for (size_t i = 0; i < unit.positions.size(); ++i) {
      CHECK(s->positions[i] == unit.positions[i] * back);
    }
    CHECK(s->camera.eye == unit.camera.eye * back);
    for (size_t i = 0; i < unit.lights.size(); ++i) {
      CHECK(s->lights[i].position == unit.lights[i].position * back);
      CHECK(s->lights[i].falloff == unit.lights[i].falloff / (back * back));
    }
  }
  for (const float k : {1e-20f, 1e20f}) {
    CAPTURE(k);
    Scene s = test::HandScene();
    for (glm::vec3& p : s.positions) p *= k;
    s.lights.clear();
    s.camera.eye *= k;
    s.camera.look_at *= k;
    s.path.keys.clear();
    CHECK_THROWS_WITH_AS(NormalizeScale(s), doctest::Contains("outside the supported range"),
                         Error);
  }
}

}  // namespace
}  // namespace rs
