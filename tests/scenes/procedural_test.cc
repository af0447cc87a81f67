// Procedural scenes: triangle counts (PBT paper Table 2 for the amphitheaters), determinism,
// features, consistent outward winding, rooms seen from inside, and parameter errors.
#include <doctest/doctest.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <string>

#include "scenes/load.h"
#include "scenes/mesh_builder.h"

namespace rs {
namespace {

glm::vec3 GeometricNormal(const Scene& s, size_t t) {
  const glm::uvec3 tri = s.triangles[t];
  return glm::cross(s.positions[tri.y] - s.positions[tri.x],
                    s.positions[tri.z] - s.positions[tri.x]);
}

// memcmp must not see a null pointer, even for 0 bytes (empty vectors have data() == nullptr).
bool SameBits(const void* a, const void* b, size_t bytes) {
  return bytes == 0 || std::memcmp(a, b, bytes) == 0;
}

void CheckEqual(const Scene& a, const Scene& b) {
  REQUIRE(a.positions.size() == b.positions.size());
  REQUIRE(a.triangles.size() == b.triangles.size());
  REQUIRE(a.normals.size() == b.normals.size());
  CHECK(SameBits(a.positions.data(), b.positions.data(), a.positions.size() * sizeof(glm::vec3)));
  CHECK(SameBits(a.normals.data(), b.normals.data(), a.normals.size() * sizeof(glm::vec3)));
  CHECK(a.triangles == b.triangles);
  CHECK(a.material_ids == b.material_ids);
  REQUIRE(a.materials.size() == b.materials.size());
  for (size_t m = 0; m < a.materials.size(); ++m) {
    CHECK(a.materials[m].name == b.materials[m].name);
    CHECK(a.materials[m].diffuse == b.materials[m].diffuse);
    CHECK(a.materials[m].reflectivity == b.materials[m].reflectivity);
  }
  REQUIRE(a.lights.size() == b.lights.size());
  for (size_t l = 0; l < a.lights.size(); ++l) CHECK(a.lights[l].position == b.lights[l].position);
  REQUIRE(a.path.keys.size() == b.path.keys.size());
  for (size_t k = 0; k < a.path.keys.size(); ++k) CHECK(a.path.keys[k].eye == b.path.keys[k].eye);
}

bool Inside(const glm::vec3& p, const glm::vec3& lo, const glm::vec3& hi) {
  return glm::all(glm::greaterThan(p, lo)) && glm::all(glm::lessThan(p, hi));
}

TEST_CASE("triangle counts are in the intended ranges") {
  CHECK(LoadScene("cornell").triangles.size() < 100);
  const size_t erw6 = LoadScene("erw6").triangles.size();
  CHECK(erw6 >= 800);
  CHECK(erw6 <= 1300);
  const size_t spherebox = LoadScene("spherebox").triangles.size();
  CHECK(spherebox >= 45000);
  CHECK(spherebox <= 55000);
}

TEST_CASE("amphitheater:N scales like the PBT paper's Table 2") {
  const size_t one = LoadScene("amphitheater").triangles.size();
  CHECK(one == 29759);  // "1 Amphitheater": 29,759
  CHECK(LoadScene("amphitheater:1").triangles.size() == one);
  const struct {
    int n;
    double paper;
  } table[] = {{4, 119026}, {16, 476098}, {32, 952130}};
  for (const auto& row : table) {
    const Scene s = LoadScene("amphitheater:" + std::to_string(row.n));
    INFO("N = ", row.n);
    // Copies plus one shared ground quad.
    CHECK(s.triangles.size() == static_cast<size_t>(row.n) * (one - 2) + 2);
    CHECK(std::fabs(static_cast<double>(s.triangles.size()) / row.paper - 1.0) < 0.01);
    CHECK(s.features.large);
    glm::vec3 lo, hi;
    s.Bounds(lo, hi);
    CHECK(hi.x - lo.x > 100.0f);  // spread on a grid, not stacked
  }
  // Two copies side by side: the second is the first, moved.
  const Scene two = LoadScene("amphitheater:2");
  CHECK(two.triangles.size() == 2 * (one - 2) + 2);
}

TEST_CASE("procedural scenes are deterministic") {
  for (const std::string name : {"erw6", "spherebox", "cornell", "amphitheater:4"}) {
    INFO("scene: ", name);
    CheckEqual(LoadScene(name), LoadScene(name));
  }
  // The hash behind the jitter is fixed integer arithmetic (golden values).
  CHECK(detail::SceneHash64(0) == 0xE220A8397B1DCDAFull);
  CHECK(detail::SceneHash64(1) == 0x910A2DEC89025CC1ull);
  const float u = detail::SceneHashUnit(1, 2);
  CHECK(u >= 0.0f);
  CHECK(u < 1.0f);
  CHECK(detail::SceneHashUnit(1, 2) == u);
  CHECK(detail::SceneHashUnit(2, 1) != u);
}

TEST_CASE("features are what each scene is for") {
  const Scene erw6 = LoadScene(kDefaultScene);
  CHECK(std::string(kDefaultScene) == "erw6");
  CHECK(erw6.features.lights);
  CHECK(erw6.features.reflection);  // table, chairs, floor
  CHECK(erw6.features.specular);
  CHECK_FALSE(erw6.features.transmission);
  CHECK_FALSE(erw6.features.textures);
  CHECK_FALSE(erw6.features.large);

  const Scene box = LoadScene("spherebox");
  CHECK(box.features.reflection);
  CHECK(box.features.transmission);
  CHECK(box.lights.size() >= 1);
  CHECK(box.lights.size() <= 4);
  bool has_glass = false;
  for (const Material& m : box.materials) has_glass |= m.transmission > 0 && m.ior == 1.5f;
  CHECK(has_glass);

  const Scene amph = LoadScene("amphitheater");
  CHECK(amph.features.lights);
  CHECK_FALSE(amph.features.reflection);  // simple diffuse materials
  CHECK_FALSE(amph.features.transmission);
  CHECK_FALSE(amph.features.specular);
  CHECK_FALSE(amph.features.large);

  const Scene cornell = LoadScene("cornell");
  CHECK(cornell.lights.size() == 1);
  CHECK(cornell.features.reflection);
  CHECK(cornell.features.transmission);
}

TEST_CASE("windings are consistent: geometric normals agree with the shading normals") {
  for (const std::string name : {"erw6", "spherebox", "cornell"}) {
    const Scene s = LoadScene(name);
    INFO("scene: ", name);
    REQUIRE(s.normals.size() == s.positions.size());
    size_t disagree = 0;
    size_t degenerate = 0;
    for (size_t t = 0; t < s.triangles.size(); ++t) {
      const glm::vec3 ng = GeometricNormal(s, t);
      if (glm::dot(ng, ng) == 0.0f) {
        ++degenerate;
        continue;
      }
      const glm::uvec3 tri = s.triangles[t];
      const glm::vec3 ns = s.normals[tri.x] + s.normals[tri.y] + s.normals[tri.z];
      if (glm::dot(ng, ns) <= 0.0f) ++disagree;
    }
    CHECK(disagree == 0);
    CHECK(degenerate == 0);
  }
}

TEST_CASE("rooms are seen from inside: walls face the camera, lights near the ceiling") {
  const Scene s = LoadScene("erw6");
  glm::vec3 lo, hi;
  s.Bounds(lo, hi);
  CHECK(Inside(s.camera.eye, lo, hi));
  REQUIRE(s.lights.size() == 4);
  for (const PointLight& l : s.lights) {
    CHECK(Inside(l.position, lo, hi));
    CHECK(l.position.y > lo.y + 0.85f * (hi.y - lo.y));
  }
  // Every wall, floor and ceiling triangle faces the camera (it is inside the room).
  size_t walls = 0;
  for (size_t t = 0; t < s.triangles.size(); ++t) {
    const std::string& m = s.materials[s.material_ids[t]].name;
    if (m.rfind("wall_", 0) != 0 && m.rfind("floor_", 0) != 0 && m != "ceiling") continue;
    ++walls;
    const glm::vec3 c = s.positions[s.triangles[t].x];
    CHECK(glm::dot(GeometricNormal(s, t), s.camera.eye - c) > 0.0f);
  }
  CHECK(walls > 100);
  // The walk-through stays inside, moves in all three directions and turns.
  REQUIRE(s.path.keys.size() >= 4);
  CHECK(s.path.frames >= 50);
  glm::vec3 eye_lo(1e9f), eye_hi(-1e9f);
  float max_turn = 0.0f;
  const glm::vec3 d0 = glm::normalize(s.path.keys[0].look_at - s.path.keys[0].eye);
  for (const Camera& k : s.path.keys) {
    CHECK(Inside(k.eye, lo, hi));
    eye_lo = glm::min(eye_lo, k.eye);
    eye_hi = glm::max(eye_hi, k.eye);
    const glm::vec3 d = glm::normalize(k.look_at - k.eye);
    max_turn = std::max(max_turn, std::acos(std::clamp(glm::dot(d0, d), -1.0f, 1.0f)));
  }
  CHECK(eye_hi.x - eye_lo.x > 1.0f);
  CHECK(eye_hi.y - eye_lo.y > 0.3f);
  CHECK(eye_hi.z - eye_lo.z > 1.0f);
  CHECK(max_turn > 1.0f);  // radians
  // Spherebox: the camera is inside the closed box.
  const Scene box = LoadScene("spherebox");
  box.Bounds(lo, hi);
  for (const Camera& k : box.path.keys) CHECK(Inside(k.eye, lo, hi));
}

TEST_CASE("every procedural name loads; bad parameters are rejected") {
  for (const std::string& name : ProceduralSceneNames()) {
    INFO("scene: ", name);
    const Scene s = LoadScene(name);
    CHECK(s.name == name);
    CHECK(s.source == "procedural");
    CHECK(s.features.triangles == s.triangles.size());
    CHECK_NOTHROW(ValidateScene(s));
  }
  for (const char* bad :
       {"amphitheater:0", "amphitheater:x", "amphitheater:", "amphitheater:65", "amphitheater:-1",
        "amphitheater:1.5", "amphitheater:4x", "erw6:2", "cornell:1", "spherebox:"}) {
    INFO("name: ", bad);
    try {
      LoadScene(bad);
      FAIL("accepted ", bad);
    } catch (const Error& e) {
      CHECK(std::string(e.what()).find(bad) != std::string::npos);
    }
  }
}

}  // namespace
}  // namespace rs
