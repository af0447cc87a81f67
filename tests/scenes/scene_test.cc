// Scene model: mesh view, bounds, camera-path interpolation (incl. 2x speed and clamping),
// features, and ValidateScene's error messages (checked by content).
#include "scenes/scene.h"

#include <doctest/doctest.h>

#include <cmath>
#include <limits>
#include <string>

namespace rs {
namespace {

constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();
constexpr float kInf = std::numeric_limits<float>::infinity();

// Two triangles sharing an edge, one material, camera looking at them.
Scene TwoTriangles() {
  Scene s;
  s.name = "two";
  s.source = "two.obj";
  s.positions = {{0, 0, 0}, {1, 0, 0}, {1, 1, 0}, {0, 1, 0}};
  s.triangles = {{0, 1, 2}, {0, 2, 3}};
  s.material_ids = {0, 0};
  s.materials.resize(1);
  s.camera.eye = {0.5f, 0.5f, 3.0f};
  s.camera.look_at = {0.5f, 0.5f, 0.0f};
  return s;
}

// Validation must throw and the message must contain every fragment.
void CheckThrows(const Scene& s, std::initializer_list<std::string> fragments) {
  try {
    ValidateScene(s);
    FAIL("ValidateScene accepted a broken scene");
  } catch (const Error& e) {
    const std::string what = e.what();
    for (const std::string& f : fragments) {
      INFO("message: ", what);
      CHECK(what.find(f) != std::string::npos);
    }
  }
}

Camera Key(glm::vec3 eye, glm::vec3 look_at) {
  Camera c;
  c.eye = eye;
  c.look_at = look_at;
  return c;
}

TEST_CASE("mesh view points at positions and triangles") {
  const Scene s = TwoTriangles();
  const MeshView m = s.mesh();
  CHECK(m.num_vertices == 4);
  CHECK(m.num_triangles == 2);
  CHECK(m.stride == 3);
  REQUIRE(m.positions != nullptr);
  REQUIRE(m.indices != nullptr);
  CHECK(m.positions[3 * 2 + 1] == 1.0f);  // vertex 2, y
  CHECK(m.indices[3 * 1 + 2] == 3u);      // triangle 1, corner 2
  const Scene empty;
  CHECK(empty.mesh().positions == nullptr);
  CHECK(empty.mesh().num_triangles == 0);
}

TEST_CASE("bounds cover all finite vertices; empty scene gives zero bounds") {
  Scene s = TwoTriangles();
  s.positions.push_back({-2.0f, 5.0f, 0.25f});
  glm::vec3 lo, hi;
  s.Bounds(lo, hi);
  CHECK(lo == glm::vec3(-2.0f, 0.0f, 0.0f));
  CHECK(hi == glm::vec3(1.0f, 5.0f, 0.25f));
  s.positions.push_back({kNaN, 100.0f, 0.0f});  // skipped, not poisoning the box
  s.Bounds(lo, hi);
  CHECK(hi.y == 5.0f);
  Scene empty;
  empty.Bounds(lo, hi);
  CHECK(lo == glm::vec3(0.0f));
  CHECK(hi == glm::vec3(0.0f));
}

TEST_CASE("camera path: fallback, single key, linear interpolation, clamping") {
  Camera fallback = Key({9, 9, 9}, {0, 0, 0});
  CameraPath path;
  CHECK(path.At(5, 1.0f, fallback).eye == fallback.eye);  // no keys: stand still
  path.keys = {Key({0, 0, 10}, {0, 0, 0})};
  path.frames = 50;
  CHECK(path.At(7, 1.0f, fallback).eye == glm::vec3(0, 0, 10));
  // Three keys over 5 frames: keys at path times 0, 2, 4.
  path.keys = {Key({0, 0, 10}, {0, 0, 0}), Key({4, 0, 10}, {0, 2, 0}), Key({4, 8, 10}, {0, 2, 6})};
  path.frames = 5;
  const Camera f0 = path.At(0, 1.0f, fallback);
  CHECK(f0.eye == glm::vec3(0, 0, 10));
  const Camera f1 = path.At(1, 1.0f, fallback);
  CHECK(f1.eye.x == doctest::Approx(2.0f).epsilon(1e-6));
  CHECK(f1.look_at.y == doctest::Approx(1.0f).epsilon(1e-6));
  const Camera f2 = path.At(2, 1.0f, fallback);
  CHECK(f2.eye == glm::vec3(4, 0, 10));
  const Camera f3 = path.At(3, 1.0f, fallback);
  CHECK(f3.eye.y == doctest::Approx(4.0f).epsilon(1e-6));
  CHECK(f3.look_at.z == doctest::Approx(3.0f).epsilon(1e-6));
  CHECK(path.At(4, 1.0f, fallback).eye == glm::vec3(4, 8, 10));
  // Past the end and before the start: clamped.
  CHECK(path.At(100, 1.0f, fallback).eye == glm::vec3(4, 8, 10));
  CHECK(path.At(-3, 1.0f, fallback).eye == glm::vec3(0, 0, 10));
  CHECK(path.At(3, kNaN, fallback).eye == glm::vec3(0, 0, 10));
  // frames == 1: the first key.
  path.frames = 1;
  CHECK(path.At(3, 1.0f, fallback).eye == glm::vec3(0, 0, 10));
}

TEST_CASE("camera path at 2x speed covers the same path in half the frames") {
  CameraPath path;
  path.frames = 61;
  for (int k = 0; k < 7; ++k) {
    const float a = static_cast<float>(k) * 0.5f;
    path.keys.push_back(Key({10 * std::cos(a), 1.0f + k, 10 * std::sin(a)}, {0, 0.5f * k, 0}));
  }
  const Camera fallback;
  for (int f = 0; f <= 30; ++f) {
    const Camera fast = path.At(f, 2.0f, fallback);
    const Camera slow = path.At(2 * f, 1.0f, fallback);
    INFO("frame ", f);
    CHECK(fast.eye.x == doctest::Approx(slow.eye.x).epsilon(1e-6));
    CHECK(fast.eye.y == doctest::Approx(slow.eye.y).epsilon(1e-6));
    CHECK(fast.look_at.y == doctest::Approx(slow.look_at.y).epsilon(1e-6));
  }
  // After frame 30 the fast walk has arrived and stays at the last key.
  CHECK(path.At(45, 2.0f, fallback).eye == path.keys.back().eye);
  // Half speed: frame 2f at 0.5x equals frame f at 1x.
  CHECK(path.At(40, 0.5f, fallback).eye.x ==
        doctest::Approx(path.At(20, 1.0f, fallback).eye.x).epsilon(1e-6));
  // Motion between consecutive frames doubles at 2x (same segment, linear).
  const float step1 = glm::length(path.At(3, 1.0f, fallback).eye - path.At(2, 1.0f, fallback).eye);
  const float step2 = glm::length(path.At(2, 2.0f, fallback).eye - path.At(1, 2.0f, fallback).eye);
  CHECK(step2 == doctest::Approx(2.0f * step1).epsilon(1e-4));
}

TEST_CASE("features: each flag needs what it says") {
  Scene s = TwoTriangles();
  SceneFeatures f = ComputeFeatures(s);
  CHECK_FALSE(f.lights);
  CHECK_FALSE(f.specular);
  CHECK_FALSE(f.reflection);
  CHECK_FALSE(f.transmission);
  CHECK_FALSE(f.textures);
  CHECK(f.triangles == 2);
  CHECK_FALSE(f.large);

  s.lights.push_back(PointLight{});
  CHECK(ComputeFeatures(s).lights);

  s.materials[0].specular = glm::vec3(0.5f);  // Ks without shininess: no highlight
  CHECK_FALSE(ComputeFeatures(s).specular);
  s.materials[0].shininess = 20.0f;
  CHECK(ComputeFeatures(s).specular);
  s.materials[0].specular = glm::vec3(0.0f);  // shininess without Ks: none either
  CHECK_FALSE(ComputeFeatures(s).specular);

  // A reflective or transmissive material that no triangle uses does not count.
  Material unused;
  unused.reflectivity = 0.5f;
  unused.transmission = 0.5f;
  s.materials.push_back(unused);
  f = ComputeFeatures(s);
  CHECK_FALSE(f.reflection);
  CHECK_FALSE(f.transmission);
  s.material_ids[1] = 1;
  f = ComputeFeatures(s);
  CHECK(f.reflection);
  CHECK(f.transmission);

  // Textures need a valid texture index AND uvs.
  s.materials[0].texture = 0;
  CHECK_FALSE(ComputeFeatures(s).textures);  // index 0 but no textures
  Texture t;
  t.width = 1;
  t.height = 1;
  t.rgb = {1, 1, 1};
  s.textures.push_back(t);
  CHECK_FALSE(ComputeFeatures(s).textures);  // no uvs
  s.uvs.assign(s.positions.size(), glm::vec2(0.5f));
  CHECK(ComputeFeatures(s).textures);
}

TEST_CASE("features: large means more than kLargeSceneTriangles") {
  Scene s = TwoTriangles();
  s.triangles.assign(kLargeSceneTriangles, glm::uvec3(0, 1, 2));
  s.material_ids.assign(kLargeSceneTriangles, 0);
  CHECK_FALSE(ComputeFeatures(s).large);
  s.triangles.push_back(glm::uvec3(0, 2, 3));
  s.material_ids.push_back(0);
  const SceneFeatures f = ComputeFeatures(s);
  CHECK(f.large);
  CHECK(f.triangles == kLargeSceneTriangles + 1);
}

TEST_CASE("validation accepts a good scene, zero-area triangles and an empty mesh") {
  Scene s = TwoTriangles();
  CHECK_NOTHROW(ValidateScene(s));
  s.triangles.push_back({1, 1, 2});  // two equal corners: legal, the grid skips it
  s.triangles.push_back({0, 1, 1});
  s.material_ids.resize(s.triangles.size(), 0);
  CHECK_NOTHROW(ValidateScene(s));
  Scene empty;
  empty.materials.resize(1);
  CHECK_NOTHROW(ValidateScene(empty));  // loaders reject empty files, the model does not
}

TEST_CASE("validation errors name the source and the element") {
  SUBCASE("index out of range") {
    Scene s = TwoTriangles();
    s.source = "bunny.ply";
    s.triangles[1].z = 99;
    try {
      ValidateScene(s);
      FAIL("accepted");
    } catch (const Error& e) {
      CHECK(std::string(e.what()) ==
            "bunny.ply: triangle 1: vertex index 99 out of range (4 vertices)");
    }
  }
  SUBCASE("NaN and infinite vertices") {
    Scene s = TwoTriangles();
    s.positions[2].y = kNaN;
    CheckThrows(s, {"two.obj", "vertex 2", "not finite"});
    s.positions[2].y = kInf;
    CheckThrows(s, {"two.obj", "vertex 2", "not finite"});
    s.positions[2].y = -1e30f;
    CheckThrows(s, {"vertex 2", "too large"});
  }
  SUBCASE("material ids") {
    Scene s = TwoTriangles();
    s.material_ids[1] = 5;
    CheckThrows(s, {"two.obj: triangle 1: material id 5 out of range (1 materials)"});
    s.material_ids.pop_back();
    CheckThrows(s, {"1 material ids for 2 triangles"});
    Scene none = TwoTriangles();
    none.materials.clear();
    CheckThrows(none, {"two.obj", "no materials"});
  }
  SUBCASE("uvs and normals: none or one per vertex") {
    Scene s = TwoTriangles();
    s.uvs.resize(3);
    CheckThrows(s, {"3 uvs for 4 vertices"});
    s.uvs.resize(4);
    s.uvs[1].x = kNaN;
    CheckThrows(s, {"vertex 1: uv", "not finite"});
    Scene n = TwoTriangles();
    n.normals.assign(5, glm::vec3(0, 0, 1));
    CheckThrows(n, {"5 normals for 4 vertices"});
    n.normals.resize(4);
    n.normals[3].z = kInf;
    CheckThrows(n, {"vertex 3: normal", "not finite"});
  }
  SUBCASE("textures and materials") {
    Scene s = TwoTriangles();
    Texture t;
    t.path = "wood.png";
    t.width = 2;
    t.height = 2;
    t.rgb.resize(11);
    s.textures.push_back(t);
    CheckThrows(s, {"texture 0 ('wood.png')", "11 floats", "expected 12"});
    s.textures[0].rgb.resize(12);
    s.materials[0].texture = 1;
    CheckThrows(s, {"material 0", "texture index 1 out of range (1 textures)"});
    s.materials[0].texture = 0;
    CHECK_NOTHROW(ValidateScene(s));
    s.materials[0].name = "glass";
    s.materials[0].transmission = 1.5f;
    CheckThrows(s, {"material 0 ('glass')", "transmission 1.5"});
    s.materials[0].transmission = 0.5f;
    s.materials[0].reflectivity = -0.1f;
    CheckThrows(s, {"reflectivity -0.1"});
    s.materials[0].reflectivity = 0.0f;
    s.materials[0].ior = 0.0f;
    CheckThrows(s, {"ior 0"});
    s.materials[0].ior = 1.5f;
    s.materials[0].diffuse.g = kNaN;
    CheckThrows(s, {"material 0", "non-finite"});
  }
  SUBCASE("lights, camera and path") {
    Scene s = TwoTriangles();
    PointLight l;
    l.position.x = kNaN;
    s.lights.push_back(l);
    CheckThrows(s, {"light 0"});
    s.lights.clear();
    s.camera.look_at = s.camera.eye;
    CheckThrows(s, {"camera", "eye equals look_at"});
    s = TwoTriangles();
    s.camera.up = glm::vec3(0, 0, 1);  // parallel to the view direction
    CheckThrows(s, {"camera", "parallel"});
    s = TwoTriangles();
    s.camera.fov_y_deg = 180.0f;
    CheckThrows(s, {"camera", "fov 180"});
    s = TwoTriangles();
    s.path.keys = {s.camera, s.camera};
    s.path.keys[1].eye.x = kInf;
    CheckThrows(s, {"path key 1"});
    s.path.keys.pop_back();
    s.path.frames = 0;
    CheckThrows(s, {"frames 0"});
  }
}

}  // namespace
}  // namespace rs
