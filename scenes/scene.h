// The scene model shared by every backend: one welded triangle mesh with per-triangle
// materials, point lights, a camera and its walk-through path, and what the scene needs.
#pragma once

#include <glm/glm.hpp>

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "include/raystream/raystream.h"

namespace rs {

struct Texture {
  std::string path;  // as given in the scene file or MTL, for messages
  int width = 0;
  int height = 0;
  std::vector<float> rgb;  // width * height * 3, linear, row 0 at the top
};

struct Material {
  std::string name;
  glm::vec3 diffuse{0.8f};   // Kd
  glm::vec3 specular{0.0f};  // Ks, phong highlight colour
  float shininess = 0.0f;    // phong exponent (Ns)
  float reflectivity = 0.0f;  // mirror reflection weight, 0..1
  float transmission = 0.0f;  // refraction weight, 0..1
  float ior = 1.5f;           // index of refraction for transmission
  int texture = -1;           // index into Scene::textures modulating diffuse, or -1
};

struct PointLight {
  glm::vec3 position{0.0f};
  glm::vec3 color{1.0f};  // radiant intensity (rgb); no distance falloff unless set
  float falloff = 0.0f;   // 0: none; 1: intensity / (1 + falloff * d^2)
};

struct Camera {
  glm::vec3 eye{0.0f, 0.0f, 1.0f};
  glm::vec3 look_at{0.0f};
  glm::vec3 up{0.0f, 1.0f, 0.0f};
  float fov_y_deg = 60.0f;
};

// A walk-through: keyframes interpolated linearly (eye, look_at) over `frames` frames at
// speed 1x. At speed s, frame f shows path time min(f * s, frames - 1) (clamped), so a 2x
// walk covers the same path in half the frames with twice the motion between frames.
struct CameraPath {
  std::vector<Camera> keys;  // empty: the camera stands still
  int frames = 1;
  Camera At(int frame, float speed, const Camera& fallback) const;
};

// What a scene needs, recorded at load: selects pipeline stages and the grid before a frame.
struct SceneFeatures {
  bool lights = false;        // any point light => shadow stage
  bool specular = false;      // any phong highlight (Ks > 0 and shininess > 0)
  bool reflection = false;    // any reflectivity > 0
  bool transmission = false;  // any transmission > 0
  bool textures = false;      // any material with a texture and a mesh with UVs
  size_t triangles = 0;
  bool large = false;         // triangles > kLargeSceneTriangles
};
inline constexpr size_t kLargeSceneTriangles = 100000;

struct Scene {
  std::string name;    // "spherebox", "bunny", or the file's path
  std::string source;  // where it came from (file path or "procedural")
  std::vector<glm::vec3> positions;
  std::vector<glm::uvec3> triangles;
  std::vector<uint32_t> material_ids;  // one per triangle, index into materials
  std::vector<glm::vec2> uvs;          // per vertex, or empty
  std::vector<glm::vec3> normals;      // per vertex for smooth shading, or empty (flat)
  std::vector<Material> materials;     // at least one
  std::vector<Texture> textures;
  std::vector<PointLight> lights;
  Camera camera;
  CameraPath path;
  glm::vec3 background{0.0f};
  float ambient = 0.1f;  // ambient term, scales diffuse colour
  SceneFeatures features;
  // The power of two NormalizeScale multiplied every coordinate by (1: the scene as given).
  float coordinate_scale = 1.0f;
  // Non-fatal problems met while loading (missing .mtl or texture, ignored statements), each
  // naming the file; LoadScene also prints them to stderr. Never affects the image silently:
  // every fallback taken (default material, untextured) is listed here.
  std::vector<std::string> warnings;

  MeshView mesh() const;
  void Bounds(glm::vec3& lo, glm::vec3& hi) const;
};

// Scenes render in coordinates whose largest magnitude lies in [2^-20, 2^20]: beyond about
// 2^40 the watertight test's products overflow, below 2^-40 they underflow (and the shading's
// offsets are relative to the triangles, OffsetUnit). A scene outside that band is multiplied
// by the power of two that brings its largest coordinate (vertices, lights, camera, path keys)
// into [1, 2), light falloffs by its inverse square; a power-of-two scale changes no rounding,
// so the image is that of the scene as given. Sets coordinate_scale. The supported range:
// largest coordinate magnitude in [kMinSceneMagnitude, kMaxSceneMagnitude]; outside it (or
// with a non-finite coordinate) throws rs::Error naming scene.source.
inline constexpr float kMinSceneMagnitude = 1e-18f;
inline constexpr float kMaxSceneMagnitude = 1e18f;
void NormalizeScale(Scene& scene);

// Computes scene.features from its contents.
SceneFeatures ComputeFeatures(const Scene& scene);

// Checks indices, finite vertices, material ids, UV/normal array sizes, texture sizes; throws
// rs::Error naming `scene.source` and the element ("triangle 12: index 99 >= 40 vertices").
void ValidateScene(const Scene& scene);

}  // namespace rs
