// Tessellation of simple shapes for procedural scenes and scene-file primitives.
#include "scenes/mesh_builder.h"

#include <cmath>
#include <numbers>
#include <vector>

namespace rs::detail {

uint64_t SceneHash64(uint64_t x) {
  x += 0x9E3779B97F4A7C15ull;
  x = (x ^ (x >> 30)) * 0xBF58476D1CE4E5B9ull;
  x = (x ^ (x >> 27)) * 0x94D049BB133111EBull;
  return x ^ (x >> 31);
}

float SceneHashUnit(uint64_t seed, uint64_t index) {
  // 24 random bits -> exactly representable float in [0, 1).
  const uint64_t h = SceneHash64(seed * 0x100000001B3ull ^ SceneHash64(index));
  return static_cast<float>(h >> 40) * (1.0f / 16777216.0f);
}

MeshBuilder::MeshBuilder(Scene& scene, bool with_normals)
    : scene_(scene), with_normals_(with_normals) {}

uint32_t MeshBuilder::AddMaterial(const Material& material) {
  scene_.materials.push_back(material);
  return static_cast<uint32_t>(scene_.materials.size() - 1);
}

void MeshBuilder::SetTransform(const glm::mat4& transform) {
  transform_ = transform;
  const glm::mat3 linear(transform);
  normal_matrix_ = glm::transpose(glm::inverse(linear));
  flip_ = glm::determinant(linear) < 0.0f;
}

uint32_t MeshBuilder::Vertex(const glm::vec3& p, const glm::vec3& n) {
  scene_.positions.push_back(glm::vec3(transform_ * glm::vec4(p, 1.0f)));
  if (with_normals_) scene_.normals.push_back(glm::normalize(normal_matrix_ * n));
  return static_cast<uint32_t>(scene_.positions.size() - 1);
}

void MeshBuilder::Tri(uint32_t a, uint32_t b, uint32_t c, uint32_t material) {
  scene_.triangles.push_back(flip_ ? glm::uvec3(a, c, b) : glm::uvec3(a, b, c));
  scene_.material_ids.push_back(material);
}

void MeshBuilder::Triangle(const glm::vec3& p0, const glm::vec3& p1, const glm::vec3& p2,
                           uint32_t material) {
  const glm::vec3 n = glm::cross(p1 - p0, p2 - p0);
  const glm::vec3 nn = glm::dot(n, n) > 0.0f ? glm::normalize(n) : glm::vec3(0, 1, 0);
  const uint32_t a = Vertex(p0, nn);
  const uint32_t b = Vertex(p1, nn);
  const uint32_t c = Vertex(p2, nn);
  Tri(a, b, c, material);
}

void MeshBuilder::Quad(const glm::vec3& p0, const glm::vec3& p1, const glm::vec3& p2,
                       const glm::vec3& p3, uint32_t material, int nu, int nv, int64_t checker) {
  const glm::vec3 n = glm::normalize(glm::cross(p1 - p0, p2 - p0));
  std::vector<uint32_t> grid(static_cast<size_t>((nu + 1) * (nv + 1)));
  for (int j = 0; j <= nv; ++j) {
    const float v = static_cast<float>(j) / static_cast<float>(nv);
    for (int i = 0; i <= nu; ++i) {
      const float u = static_cast<float>(i) / static_cast<float>(nu);
      const glm::vec3 p = (1 - v) * ((1 - u) * p0 + u * p1) + v * ((1 - u) * p3 + u * p2);
      grid[static_cast<size_t>(j * (nu + 1) + i)] = Vertex(p, n);
    }
  }
  for (int j = 0; j < nv; ++j) {
    for (int i = 0; i < nu; ++i) {
      const uint32_t m =
          (checker >= 0 && ((i + j) & 1)) ? static_cast<uint32_t>(checker) : material;
      const uint32_t a = grid[static_cast<size_t>(j * (nu + 1) + i)];
      const uint32_t b = grid[static_cast<size_t>(j * (nu + 1) + i + 1)];
      const uint32_t c = grid[static_cast<size_t>((j + 1) * (nu + 1) + i + 1)];
      const uint32_t d = grid[static_cast<size_t>((j + 1) * (nu + 1) + i)];
      Tri(a, b, c, m);
      Tri(a, c, d, m);
    }
  }
}

void MeshBuilder::Box(const glm::vec3& lo, const glm::vec3& hi, uint32_t material) {
  const glm::vec3 c[8] = {{lo.x, lo.y, lo.z}, {hi.x, lo.y, lo.z}, {hi.x, hi.y, lo.z},
                          {lo.x, hi.y, lo.z}, {lo.x, lo.y, hi.z}, {hi.x, lo.y, hi.z},
                          {hi.x, hi.y, hi.z}, {lo.x, hi.y, hi.z}};
  // Faces as corner indices, counter-clockwise seen from outside.
  static constexpr int kFaces[6][4] = {{4, 5, 6, 7},   // +z
                                       {1, 0, 3, 2},   // -z
                                       {5, 1, 2, 6},   // +x
                                       {0, 4, 7, 3},   // -x
                                       {7, 6, 2, 3},   // +y
                                       {0, 1, 5, 4}};  // -y
  if (with_normals_) {
    for (const auto& f : kFaces) Quad(c[f[0]], c[f[1]], c[f[2]], c[f[3]], material);
    return;
  }
  uint32_t v[8];
  for (int i = 0; i < 8; ++i) v[i] = Vertex(c[i], glm::vec3(0, 1, 0));
  for (const auto& f : kFaces) {
    Tri(v[f[0]], v[f[1]], v[f[2]], material);
    Tri(v[f[0]], v[f[2]], v[f[3]], material);
  }
}

void MeshBuilder::Sphere(const glm::vec3& center, float radius, int slices, int stacks,
                         uint32_t material) {
  constexpr float kPi = std::numbers::pi_v<float>;
  const uint32_t top = Vertex(center + glm::vec3(0, radius, 0), glm::vec3(0, 1, 0));
  std::vector<uint32_t> rows;  // (stacks - 1) rings of `slices` vertices
  for (int j = 1; j < stacks; ++j) {
    const float theta = kPi * static_cast<float>(j) / static_cast<float>(stacks);
    for (int i = 0; i < slices; ++i) {
      const float phi = 2.0f * kPi * static_cast<float>(i) / static_cast<float>(slices);
      const glm::vec3 d(std::sin(theta) * std::cos(phi), std::cos(theta),
                        -std::sin(theta) * std::sin(phi));
      rows.push_back(Vertex(center + radius * d, d));
    }
  }
  const uint32_t bottom = Vertex(center - glm::vec3(0, radius, 0), glm::vec3(0, -1, 0));
  auto at = [&](int ring, int i) {
    return rows[static_cast<size_t>(ring * slices + (i % slices))];
  };
  for (int i = 0; i < slices; ++i) Tri(top, at(0, i), at(0, i + 1), material);
  for (int j = 0; j + 1 < stacks - 1; ++j) {
    for (int i = 0; i < slices; ++i) {
      Tri(at(j, i), at(j + 1, i), at(j + 1, i + 1), material);
      Tri(at(j, i), at(j + 1, i + 1), at(j, i + 1), material);
    }
  }
  for (int i = 0; i < slices; ++i) Tri(at(stacks - 2, i), bottom, at(stacks - 2, i + 1), material);
}

void MeshBuilder::Cylinder(const glm::vec3& base, float radius, float height, int segments,
                           uint32_t material, bool caps) {
  constexpr float kPi = std::numbers::pi_v<float>;
  std::vector<uint32_t> lo, hi;
  for (int i = 0; i < segments; ++i) {
    const float a = 2.0f * kPi * static_cast<float>(i) / static_cast<float>(segments);
    const glm::vec3 d(std::cos(a), 0.0f, -std::sin(a));
    lo.push_back(Vertex(base + radius * d, d));
    hi.push_back(Vertex(base + radius * d + glm::vec3(0, height, 0), d));
  }
  const auto n = static_cast<size_t>(segments);
  for (size_t i = 0; i < n; ++i) {
    const size_t k = (i + 1) % n;
    Tri(lo[i], lo[k], hi[k], material);
    Tri(lo[i], hi[k], hi[i], material);
  }
  if (!caps) return;
  // Caps get their own vertices (flat normals) when normals are on.
  std::vector<uint32_t> top_ring = hi, bottom_ring = lo;
  if (with_normals_) {
    top_ring.clear();
    bottom_ring.clear();
    for (int i = 0; i < segments; ++i) {
      const float a = 2.0f * kPi * static_cast<float>(i) / static_cast<float>(segments);
      const glm::vec3 d(std::cos(a), 0.0f, -std::sin(a));
      bottom_ring.push_back(Vertex(base + radius * d, glm::vec3(0, -1, 0)));
      top_ring.push_back(Vertex(base + radius * d + glm::vec3(0, height, 0), glm::vec3(0, 1, 0)));
    }
  }
  const uint32_t ct = Vertex(base + glm::vec3(0, height, 0), glm::vec3(0, 1, 0));
  const uint32_t cb = Vertex(base, glm::vec3(0, -1, 0));
  for (size_t i = 0; i < n; ++i) {
    const size_t k = (i + 1) % n;
    Tri(ct, top_ring[i], top_ring[k], material);
    Tri(cb, bottom_ring[k], bottom_ring[i], material);
  }
}

void MeshBuilder::RingSector(const glm::vec3& center, float r0, float r1, float a0, float a1,
                             int segments, uint32_t material, bool down) {
  const glm::vec3 n(0, down ? -1.0f : 1.0f, 0);
  std::vector<uint32_t> inner, outer;
  for (int i = 0; i <= segments; ++i) {
    const float a = a0 + (a1 - a0) * static_cast<float>(i) / static_cast<float>(segments);
    const glm::vec3 d(std::cos(a), 0.0f, -std::sin(a));
    inner.push_back(Vertex(center + r0 * d, n));
    outer.push_back(Vertex(center + r1 * d, n));
  }
  for (size_t i = 0; i < static_cast<size_t>(segments); ++i) {
    if (down) {
      Tri(inner[i], outer[i + 1], outer[i], material);
      Tri(inner[i], inner[i + 1], outer[i + 1], material);
    } else {
      Tri(inner[i], outer[i], outer[i + 1], material);
      Tri(inner[i], outer[i + 1], inner[i + 1], material);
    }
  }
}

void MeshBuilder::WallSector(const glm::vec3& center, float r, float y0, float y1, float a0,
                             float a1, int segments, uint32_t material, bool inward) {
  std::vector<uint32_t> lo, hi;
  for (int i = 0; i <= segments; ++i) {
    const float a = a0 + (a1 - a0) * static_cast<float>(i) / static_cast<float>(segments);
    const glm::vec3 d(std::cos(a), 0.0f, -std::sin(a));
    const glm::vec3 n = inward ? -d : d;
    lo.push_back(Vertex(glm::vec3(center.x, y0, center.z) + r * d, n));
    hi.push_back(Vertex(glm::vec3(center.x, y1, center.z) + r * d, n));
  }
  for (size_t i = 0; i < static_cast<size_t>(segments); ++i) {
    if (inward) {
      Tri(lo[i], hi[i + 1], lo[i + 1], material);
      Tri(lo[i], hi[i], hi[i + 1], material);
    } else {
      Tri(lo[i], lo[i + 1], hi[i + 1], material);
      Tri(lo[i], hi[i + 1], hi[i], material);
    }
  }
}

}  // namespace rs::detail
