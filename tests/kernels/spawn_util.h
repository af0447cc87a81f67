// Self-intersection fixtures of the kernel tests: rays spawned from points on large and
// far-from-origin triangles the way the shader spawns them (barycentric point, OffsetRayOrigin
// along the geometric normal, pointing away: pbrt's Reintersect test), and the literal floor
// rays of the shared scene `conference` that the watertight test re-hit before its t bound.
#pragma once

#include <glm/glm.hpp>

#include <cmath>
#include <cstddef>

#include "kernels/shade.h"
#include "tests/kernels/geometry_util.h"

namespace rs::test {

// A triangle to spawn rays from: vertices p and the double normal n = (p1 - p0) x (p2 - p0)
// (float inputs: only the products round).
struct SpawnTriangle {
  float p[3][3];
  double n[3];
};

// One spawned ray: origin o (OffsetRayOrigin of a point of the triangle along the normal of the
// side it leaves by), direction d pointing away from the plane. above: o is strictly on that
// side of the plane and n . d > 0, evaluated in double (if not, OffsetRayOrigin itself failed
// and a re-hit would be legitimate: such rays are counted, never checked).
struct SpawnedRay {
  float o[3];
  float d[3];
  bool above;
};

// Signed distance (unnormalised: times |n|) of x from the plane of t, in double.
inline double PlaneSide(const SpawnTriangle& t, const float x[3]) {
  return t.n[0] * (double(x[0]) - t.p[0][0]) + t.n[1] * (double(x[1]) - t.p[0][1]) +
         t.n[2] * (double(x[2]) - t.p[0][2]);
}

// A triangle with edges up to ~`size` around a centre within `offset` of the origin: one in
// three lies in an axis-aligned plane (the conference floor: big extent in two axes, and half
// of them a small coordinate in the third), the others are random.
inline SpawnTriangle MakeSpawnTriangle(Rng& rng, double size, double offset) {
  SpawnTriangle t;
  double c[3];
  for (double& x : c) x = rng.Uniform(-offset, offset);
  const int plane_axis = rng.Below(3) == 0 ? int(rng.Below(3)) : -1;
  if (plane_axis >= 0 && rng.Below(2) == 0) c[plane_axis] = rng.Uniform(-2.0, 2.0);
  double len;
  do {
    for (auto& q : t.p) {
      for (int a = 0; a < 3; ++a) q[a] = F(c[a] + rng.Uniform(-size, size));
      if (plane_axis >= 0) q[plane_axis] = F(c[plane_axis]);
    }
    const double e1[3] = {double(t.p[1][0]) - t.p[0][0], double(t.p[1][1]) - t.p[0][1],
                          double(t.p[1][2]) - t.p[0][2]};
    const double e2[3] = {double(t.p[2][0]) - t.p[0][0], double(t.p[2][1]) - t.p[0][1],
                          double(t.p[2][2]) - t.p[0][2]};
    t.n[0] = e1[1] * e2[2] - e1[2] * e2[1];
    t.n[1] = e1[2] * e2[0] - e1[0] * e2[2];
    t.n[2] = e1[0] * e2[1] - e1[1] * e2[0];
    len = std::sqrt(t.n[0] * t.n[0] + t.n[1] * t.n[1] + t.n[2] * t.n[2]);
  } while (len < 1e-3 * size * size);  // no slivers: the float normal points the right way
  return t;
}

// A ray spawned from a random point of t (random float barycentrics, the point computed as
// rs::Shade does: b0 p0 + u p1 + v p2 in float), on a random side, with a random direction in
// that hemisphere of length ~1 or ~`scale` (shadow rays to a light: d = light - o).
inline SpawnedRay SpawnRay(Rng& rng, const SpawnTriangle& t, double scale) {
  float u, v;
  do {
    u = rng.UniformF(0.0, 1.0);
    v = rng.UniformF(0.0, 1.0);
  } while (u + v > 1.0f);
  const glm::vec3 p0(t.p[0][0], t.p[0][1], t.p[0][2]), p1(t.p[1][0], t.p[1][1], t.p[1][2]);
  const glm::vec3 p2(t.p[2][0], t.p[2][1], t.p[2][2]);
  const float b0 = 1.0f - u - v;
  const glm::vec3 p = b0 * p0 + u * p1 + v * p2;
  glm::vec3 ng = glm::normalize(glm::cross(p1 - p0, p2 - p0));
  double side = 1.0;
  if (rng.Below(2) == 0) {
    ng = -ng;
    side = -1.0;
  }
  // the shader's step for a ray leaving away from the plane (no light term), except in axis
  // planes: 16 ulps of the plane's coordinate only (p's error along n is that coordinate's),
  // far smaller than the shader's step on a large triangle, so that the origin is above the
  // plane but within the watertight test's rounding of it: the case the t bound is for
  float unit = OffsetUnit(p0, p1, p2);
  for (int a = 0; a < 3; ++a) {
    if (p0[a] == p1[a] && p0[a] == p2[a] && p0[a] != 0.0f) unit = PowerOfTwoFloor(std::fabs(p0[a]));
  }
  const glm::vec3 o = OffsetRayOrigin(p, ng, unit);
  float d[3];
  do {
    rng.Direction(d);
  } while (glm::dot(glm::vec3(d[0], d[1], d[2]), ng) < 1e-3f);  // away from the plane
  const double len = rng.Below(2) == 0 ? 1.0 : scale;
  SpawnedRay s;
  for (int a = 0; a < 3; ++a) {
    s.o[a] = o[a];
    s.d[a] = F(d[a] * len);
  }
  const double nd = side * (t.n[0] * s.d[0] + t.n[1] * s.d[1] + t.n[2] * s.d[2]);
  s.above = side * PlaneSide(t, s.o) > 0.0 && nd > 0.0;
  return s;
}

// Regression (conference, 64x64, depth 1 shadow rays to the light, tmax = 0.9999): the two
// floor triangles 59 and 60 (plane y = -1.57216, x in [-946.9, 1653.3], z in [-1016.1,
// 668.5]), and shadow rays from floor points offset by OffsetRayOrigin (3.05e-5 above the
// plane) pointing away from it (n . d / |d| = 0.42 .. 0.69). The watertight test without the
// t bound reported them hitting their own triangle at t = 3.5e-8 .. 1.2e-7 (3e-5 .. 1e-4
// along the ray); Embree 3 (robust) reports no hit. Literal floats (hex: exact).
inline constexpr float kFloorA[3] = {-0x1.d971aap+9f, -0x1.927914p+0f, -0x1.fc0cccp+9f};
inline constexpr float kFloorB[3] = {-0x1.d971aap+9f, -0x1.927914p+0f, 0x1.4e3e98p+9f};
inline constexpr float kFloorC[3] = {0x1.9d5p+10f, -0x1.927914p+0f, -0x1.fc0cccp+9f};
inline constexpr float kFloorD[3] = {0x1.9d5p+10f, -0x1.927914p+0f, 0x1.4e3e98p+9f};
// triangle 59 = (A, B, C), 60 = (B, D, C): the mesh's own vertex order
struct FloorRay {
  float o[3], d[3];
  int tri;  // the floor triangle (0: 59, 1: 60) the old test re-hit
};
inline constexpr float kFloorRayTmax = 0x1.fff2e4p-1f;  // 0.9999
inline constexpr FloorRay kFloorRays[] = {
    {{0x1.e2c1c4p+9f, -0x1.927714p+0f, -0x1.94c27cp+8f},
     {0x1.0cf8fp+7f, 0x1.22c93cp+9f, 0x1.60613ep+9f},
     1},  // o (965.514, -1.57213, -404.760), old t 3.46e-8
    {{0x1.8f31e8p+7f, -0x1.927714p+0f, -0x1.678dap+9f},
     {-0x1.2bcc7ap+9f, 0x1.22c93cp+9f, 0x1.dc6dp+6f},
     0},  // o (199.597, -1.57213, -719.106), old t 1.18e-7
    {{0x1.8f31f8p+7f, -0x1.927714p+0f, -0x1.3580fp+9f},
     {-0x1.2bcc7ep+9f, 0x1.22c93cp+9f, 0x1.301ep+4f},
     0},
    {{0x1.aa27c4p+9f, -0x1.927714p+0f, -0x1.e0a282p+8f},
     {-0x1.3913e2p+10f, 0x1.22c93cp+9f, -0x1.dd75f8p+6f},
     1},
    {{0x1.eef4a2p+9f, -0x1.927714p+0f, -0x1.d1ee06p+8f},
     {-0x1.5b7a5p+10f, 0x1.22c93cp+9f, -0x1.0c23f4p+7f},
     1},
};

}  // namespace rs::test
