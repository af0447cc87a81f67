// Test helpers for shading and rendering (tests/kernels and tests/sched): tiny scenes built by
// hand, a brute-force watertight ray/triangle oracle (Woop, Benthin, Wald 2013) and an icosphere
// for self-intersection tests.
#pragma once

#include <glm/glm.hpp>

#include <algorithm>
#include <cmath>
#include <limits>
#include <map>
#include <utility>
#include <vector>

#include "include/raystream/raystream.h"
#include "scenes/icosphere.h"
#include "scenes/scene.h"
#include "streams/ray_stream.h"

namespace rs::test {

// SceneFeatures as documented in scenes/scene.h, computed here so these tests do not depend on
// the loaders (the real ComputeFeatures is tested in tests/scenes).
inline void SetFeatures(Scene& s) {
  SceneFeatures f;
  f.lights = !s.lights.empty();
  for (const Material& m : s.materials) {
    f.specular |= m.shininess > 0.0f && (m.specular.x > 0 || m.specular.y > 0 || m.specular.z > 0);
    f.reflection |= m.reflectivity > 0.0f;
    f.transmission |= m.transmission > 0.0f;
    f.textures |= m.texture >= 0 && !s.uvs.empty();
  }
  f.triangles = s.triangles.size();
  f.large = f.triangles > kLargeSceneTriangles;
  s.features = f;
}

inline MeshView MeshOf(const Scene& s) {
  MeshView m;
  m.positions = s.positions.empty() ? nullptr : &s.positions[0].x;
  m.num_vertices = s.positions.size();
  m.stride = 3;
  m.indices = s.triangles.empty() ? nullptr : &s.triangles[0].x;
  m.num_triangles = s.triangles.size();
  return m;
}

// Appends the quad a, b, c, d (counter-clockwise seen from the front) as two triangles.
inline void AddQuad(Scene& s, glm::vec3 a, glm::vec3 b, glm::vec3 c, glm::vec3 d,
                    uint32_t material) {
  const uint32_t i = static_cast<uint32_t>(s.positions.size());
  s.positions.insert(s.positions.end(), {a, b, c, d});
  s.triangles.push_back(glm::uvec3(i, i + 1, i + 2));
  s.triangles.push_back(glm::uvec3(i, i + 2, i + 3));
  s.material_ids.push_back(material);
  s.material_ids.push_back(material);
}

// Watertight ray/triangle test in float (Woop et al. 2013, with the double fallback for zero
// edge functions). Two-sided. Returns true and t (in units of |d|) for a hit in [tmin, tmax].
inline bool IntersectWatertight(glm::vec3 o, glm::vec3 d, glm::vec3 p0, glm::vec3 p1,
                                glm::vec3 p2, float tmin, float tmax, float* t_out,
                                float* u_out = nullptr, float* v_out = nullptr) {
  const glm::vec3 ad = glm::abs(d);
  int kz = ad.x > ad.y ? (ad.x > ad.z ? 0 : 2) : (ad.y > ad.z ? 1 : 2);
  int kx = (kz + 1) % 3;
  int ky = (kx + 1) % 3;
  if (d[kz] < 0.0f) std::swap(kx, ky);
  if (d[kz] == 0.0f) return false;
  const float sx = d[kx] / d[kz], sy = d[ky] / d[kz], sz = 1.0f / d[kz];
  const glm::vec3 a = p0 - o, b = p1 - o, c = p2 - o;
  const float ax = a[kx] - sx * a[kz], ay = a[ky] - sy * a[kz];
  const float bx = b[kx] - sx * b[kz], by = b[ky] - sy * b[kz];
  const float cx = c[kx] - sx * c[kz], cy = c[ky] - sy * c[kz];
  float U = cx * by - cy * bx;
  float V = ax * cy - ay * cx;
  float W = bx * ay - by * ax;
  if (U == 0.0f || V == 0.0f || W == 0.0f) {
    U = static_cast<float>(static_cast<double>(cx) * by - static_cast<double>(cy) * bx);
    V = static_cast<float>(static_cast<double>(ax) * cy - static_cast<double>(ay) * cx);
    W = static_cast<float>(static_cast<double>(bx) * ay - static_cast<double>(by) * ax);
  }
  if ((U < 0 || V < 0 || W < 0) && (U > 0 || V > 0 || W > 0)) return false;
  float det = U + V + W;
  if (det == 0.0f) return false;
  float T = U * (sz * a[kz]) + V * (sz * b[kz]) + W * (sz * c[kz]);
  if (det < 0) {
    det = -det;
    T = -T;
    U = -U;
    V = -V;
    W = -W;
  }
  if (T < tmin * det || T > tmax * det) return false;
  *t_out = T / det;
  if (u_out) *u_out = V / det;  // barycentric of p1
  if (v_out) *v_out = W / det;  // barycentric of p2
  return true;
}

// Closest hit over all triangles (ties: lowest index), the oracle the shading tests use.
inline void BruteForceIntersect(const Scene& s, const RayStreamView& rays,
                                const HitStreamView& hits) {
  for (size_t i = 0; i < rays.size; ++i) {
    const glm::vec3 o(rays.ox[i], rays.oy[i], rays.oz[i]);
    const glm::vec3 d(rays.dx[i], rays.dy[i], rays.dz[i]);
    float best = rays.tmax[i];
    hits.t[i] = std::numeric_limits<float>::infinity();
    hits.u[i] = hits.v[i] = 0.0f;
    hits.prim[i] = -1;
    for (size_t k = 0; k < s.triangles.size(); ++k) {
      const glm::uvec3 tri = s.triangles[k];
      float t, u, v;
      if (IntersectWatertight(o, d, s.positions[tri.x], s.positions[tri.y], s.positions[tri.z],
                              rays.tmin[i], best, &t, &u, &v) &&
          (hits.prim[i] < 0 || t < best)) {
        best = t;
        hits.t[i] = t;
        hits.u[i] = u;
        hits.v[i] = v;
        hits.prim[i] = static_cast<int32_t>(k);
      }
    }
  }
}

// Icosphere (subdivided `levels` times, scenes/icosphere.h) of radius r around c, wound outwards.
inline void AddIcosphere(Scene& s, glm::vec3 c, float r, int levels, uint32_t material) {
  const Icosphere ico = MakeIcosphere(levels, r, {c.x, c.y, c.z}, 0.0);
  const uint32_t base = static_cast<uint32_t>(s.positions.size());
  for (const auto& p : ico.v) s.positions.push_back({p[0], p[1], p[2]});
  for (const auto& t : ico.tri) {
    s.triangles.push_back(glm::uvec3(t[0], t[1], t[2]) + base);
    s.material_ids.push_back(material);
  }
}

// A little room: floor, back wall, a mirror icosphere, a glass icosphere, a blocker, two lights
// (one with falloff), a background colour, phong highlights on the wall.
inline Scene HandScene() {
  Scene s;
  s.name = "hand";
  Material floor;
  floor.diffuse = glm::vec3(0.7f, 0.7f, 0.6f);
  Material wall;
  wall.diffuse = glm::vec3(0.8f, 0.2f, 0.2f);
  wall.specular = glm::vec3(0.4f);
  wall.shininess = 20.0f;
  Material mirror;
  mirror.diffuse = glm::vec3(0.1f);
  mirror.reflectivity = 0.8f;
  Material glass;
  glass.diffuse = glm::vec3(0.1f, 0.3f, 0.1f);
  glass.transmission = 0.85f;
  glass.reflectivity = 0.1f;
  glass.ior = 1.5f;
  Material block;
  block.diffuse = glm::vec3(0.2f, 0.4f, 0.9f);
  s.materials = {floor, wall, mirror, glass, block};
  AddQuad(s, {-6, 0, 6}, {6, 0, 6}, {6, 0, -6}, {-6, 0, -6}, 0);
  AddQuad(s, {-6, 0, -3}, {6, 0, -3}, {6, 6, -3}, {-6, 6, -3}, 1);
  AddIcosphere(s, {-1.3f, 1.0f, 0.0f}, 1.0f, 2, 2);
  AddIcosphere(s, {1.4f, 0.8f, 0.8f}, 0.8f, 2, 3);
  AddQuad(s, {2.5f, 0.01f, -1}, {4, 0.01f, -1}, {4, 1.5f, -2}, {2.5f, 1.5f, -2}, 4);
  PointLight a;
  a.position = glm::vec3(2, 5, 4);
  a.color = glm::vec3(0.8f, 0.8f, 0.7f);
  PointLight b;
  b.position = glm::vec3(-4, 3, 2);
  b.color = glm::vec3(6.0f, 6.0f, 8.0f);
  b.falloff = 0.3f;
  s.lights = {a, b};
  s.background = glm::vec3(0.05f, 0.1f, 0.2f);
  s.ambient = 0.15f;
  s.camera.eye = glm::vec3(0.5f, 3.0f, 8.0f);
  s.camera.look_at = glm::vec3(0, 1, 0);
  s.camera.fov_y_deg = 50.0f;
  SetFeatures(s);
  return s;
}

}  // namespace rs::test
