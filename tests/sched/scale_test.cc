// Scenes far from unit size: the hand scene (two quads, two icospheres, a block, two lights, one
// without falloff) scaled by 1e-15 .. 1e14 about the origin renders like the unscaled one where
// the renderer's arithmetic is scale-invariant: face normals of triangles whose edge cross product
// leaves the float range (FaceNormal) keep every lit pixel lit; no pixel is NaN or black where the
// unscaled one is lit. What is not scale-invariant yet is printed, not hidden: the shadow rays'
// near-origin offset is absolute (OffsetRayOrigin within 1/32 of 0), so below about 1e-3 shadows
// thin out (~14 % of the pixels differ), and at 1e12 and above most pixels differ in brightness
// (cause not found yet); the image equals the unscaled one within 1 % of its pixels from 1e-3 to
// 1e6.
#include <doctest/doctest.h>

#include <cmath>
#include <cstdio>
#include <vector>

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

TEST_CASE("scaled scenes: no NaN, every lit pixel stays lit, 1e-3 .. 1e6 match the unscaled image") {
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
    if (k >= 1e-3f && k <= 1e6f) CHECK(differ <= pixels / 100);
  }
}

}  // namespace
}  // namespace rs
