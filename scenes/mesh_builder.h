// Appends simple tessellated shapes (quads, boxes, spheres, cylinders, ring sectors) to a Scene
// with consistent outward winding; used by the procedural scenes and scene-file primitives.
#pragma once

#include <cstdint>
#include <glm/glm.hpp>

#include "scenes/scene.h"

namespace rs::detail {

// Every shape is transformed by the current transform (normals by its inverse transpose; a
// mirroring transform flips the winding so the geometric normal still points outward).
// Winding: the geometric normal cross(p1 - p0, p2 - p0) points out of closed shapes and to the
// front of quads. With normals enabled, flat shapes get per-face vertices and face normals,
// round ones shared vertices and smooth normals; with normals disabled vertices are shared
// where positions coincide within a shape.
class MeshBuilder {
 public:
  MeshBuilder(Scene& scene, bool with_normals);

  uint32_t AddMaterial(const Material& material);
  void SetTransform(const glm::mat4& transform);
  const glm::mat4& transform() const { return transform_; }

  void Triangle(const glm::vec3& p0, const glm::vec3& p1, const glm::vec3& p2, uint32_t material);
  // Planar quad p0 p1 p2 p3 (counter-clockwise seen from the front), split into nu x nv cells.
  // `checker` >= 0 alternates `material` and `checker` between cells.
  void Quad(const glm::vec3& p0, const glm::vec3& p1, const glm::vec3& p2, const glm::vec3& p3,
            uint32_t material, int nu = 1, int nv = 1, int64_t checker = -1);
  // Axis-aligned box [lo, hi] (before the transform): 12 triangles, faces outward.
  void Box(const glm::vec3& lo, const glm::vec3& hi, uint32_t material);
  // UV sphere: 2 * slices * (stacks - 1) triangles.
  void Sphere(const glm::vec3& center, float radius, int slices, int stacks, uint32_t material);
  // Vertical (+y) cylinder from base centre `base` with `height`; caps optional.
  // 2 * segments triangles for the side, + segments per cap.
  void Cylinder(const glm::vec3& base, float radius, float height, int segments, uint32_t material,
                bool caps = true);
  // Horizontal ring sector at height y around `center` (y ignored), radii r0 < r1, angles a0 < a1
  // (radians, measured from +x towards -z), facing up (or down if `down`): 2 * segments tris.
  void RingSector(const glm::vec3& center, float r0, float r1, float a0, float a1, int segments,
                  uint32_t material, bool down = false);
  // Vertical cylindrical wall of radius r from y0 to y1 over angles [a0, a1], facing the axis
  // (inward) or away from it: 2 * segments triangles.
  void WallSector(const glm::vec3& center, float r, float y0, float y1, float a0, float a1,
                  int segments, uint32_t material, bool inward);

 private:
  uint32_t Vertex(const glm::vec3& p, const glm::vec3& n);
  void Tri(uint32_t a, uint32_t b, uint32_t c, uint32_t material);

  Scene& scene_;
  bool with_normals_;
  glm::mat4 transform_{1.0f};
  glm::mat3 normal_matrix_{1.0f};
  bool flip_ = false;
};

// Deterministic integer hash (splitmix64 finaliser) and a float in [0, 1) from it: the same on
// every platform and library, unlike std:: distributions.
uint64_t SceneHash64(uint64_t x);
float SceneHashUnit(uint64_t seed, uint64_t index);

}  // namespace rs::detail
