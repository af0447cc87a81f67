// Helpers for the kernels/ tests: an owning triangle soup with a MeshView, fixed-seed random
// numbers, float rounding that the GCC 12 SLP bug cannot drop, and float-ulp steps.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <random>
#include <vector>

#include "include/raystream/raystream.h"
#include "kernels/reference.h"

namespace rs::test {

inline constexpr float kInf = std::numeric_limits<float>::infinity();
inline constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();

// Bitwise equality (distinguishes -0 from +0, equal for identical NaNs).
inline bool SameBits(float a, float b) { return std::memcmp(&a, &b, sizeof a) == 0; }

// One test ray; t in (tmin, tmax].
struct Ray {
  float o[3];
  float d[3];
  float tmin = 0.0f;
  float tmax = kInf;
};

// Rounds to float through a volatile, so a later float -> double conversion really sees the
// float value (GCC 12.2's SLP vectorizer can drop a (double)(float)x rounding; TOOLCHAIN.md).
inline float F(double x) {
  volatile float f = static_cast<float>(x);
  return f;
}

// Fixed-seed generator; uniform draws are produced in double and rounded with F().
class Rng {
 public:
  explicit Rng(uint32_t seed) : gen_(seed) {}
  double Uniform(double lo, double hi) {
    return lo + (hi - lo) * std::uniform_real_distribution<double>(0.0, 1.0)(gen_);
  }
  float UniformF(double lo, double hi) { return F(Uniform(lo, hi)); }
  uint32_t Below(uint32_t n) { return std::uniform_int_distribution<uint32_t>(0, n - 1)(gen_); }
  // A random direction with length in [0.5, 2] (directions need not be normalized).
  void Direction(float d[3]) {
    double v[3], len2;
    do {
      for (double& c : v) c = Uniform(-1.0, 1.0);
      len2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
    } while (len2 < 1e-4 || len2 > 1.0);
    const double scale = Uniform(0.5, 2.0) / std::sqrt(len2);
    for (int a = 0; a < 3; ++a) d[a] = F(v[a] * scale);
  }

 private:
  std::mt19937 gen_;
};

// An owning triangle mesh (positions xyz, stride 3).
struct Soup {
  std::vector<float> positions;
  std::vector<uint32_t> indices;

  uint32_t AddVertex(float x, float y, float z) {
    positions.insert(positions.end(), {x, y, z});
    return uint32_t(positions.size() / 3 - 1);
  }
  void AddTriangle(const float a[3], const float b[3], const float c[3]) {
    const uint32_t i = AddVertex(a[0], a[1], a[2]);
    const uint32_t j = AddVertex(b[0], b[1], b[2]);
    const uint32_t k = AddVertex(c[0], c[1], c[2]);
    indices.insert(indices.end(), {i, j, k});
  }
  size_t triangles() const { return indices.size() / 3; }
  MeshView view() const {
    MeshView m;
    m.positions = positions.data();
    m.num_vertices = positions.size() / 3;
    m.stride = 3;
    m.indices = indices.data();
    m.num_triangles = indices.size() / 3;
    return m;
  }
};

// `count` random triangles with vertices within `lo`..`hi` on each axis and edge lengths up to
// `size` (a soup: no shared vertices).
inline Soup RandomSoup(Rng& rng, size_t count, double lo, double hi, double size) {
  Soup s;
  for (size_t i = 0; i < count; ++i) {
    double c[3];
    for (double& x : c) x = rng.Uniform(lo + size, hi - size);
    float p[3][3];
    for (auto& q : p) {
      for (int a = 0; a < 3; ++a) q[a] = F(c[a] + rng.Uniform(-0.5, 0.5) * size);
    }
    s.AddTriangle(p[0], p[1], p[2]);
  }
  return s;
}

// Error bounds of the float watertight test (kernels/triangle.h), from its operation order:
// the sheared vertex coordinates X, Y carry errors ~ eps * (|p - o|[kx] + |Sx (p - o)[kz]|),
// so each edge function (U = Cx By - Cy Bx ...) is off by ~ eps * m_i with m_i the sum of the
// magnitudes of its products; t = sum U_i z_i / det moves by sum m_i |z_i - t| / |det| plus
// the rounding of z_i. Large for grazing rays, slivers in projection and hits much closer to
// the origin than the vertices; ~1 ulp for well-conditioned hits.
struct WatertightErrors {
  double t;   // absolute, in units of |d|
  double uv;  // absolute, barycentric
};
inline WatertightErrors WatertightErrorBound(const ref::Ray& r, const double p[3][3],
                                             double t_ref, double u_ref, double v_ref) {
  constexpr double kEps = 1.1920929e-7;
  double x[3], y[3], z[3], mx[3], my[3];
  for (int k = 0; k < 3; ++k) {
    const double rx = p[k][r.kx] - r.o[r.kx], ry = p[k][r.ky] - r.o[r.ky];
    const double rz = p[k][r.kz] - r.o[r.kz];
    x[k] = rx - r.sx * rz;
    y[k] = ry - r.sy * rz;
    z[k] = r.sz * rz;
    mx[k] = std::fabs(rx) + std::fabs(r.sx * rz);
    my[k] = std::fabs(ry) + std::fabs(r.sy * rz);
  }
  const double u = x[2] * y[1] - y[2] * x[1], v = x[0] * y[2] - y[0] * x[2];
  const double w = x[1] * y[0] - y[1] * x[0];
  const double det = std::fabs(u + v + w);
  const double m[3] = {mx[2] * my[1] + my[2] * mx[1], mx[0] * my[2] + my[0] * mx[2],
                       mx[1] * my[0] + my[1] * mx[0]};
  const double zmax = std::max({std::fabs(z[0]), std::fabs(z[1]), std::fabs(z[2])});
  WatertightErrors e;
  e.t = kEps * ((m[0] * std::fabs(z[0] - t_ref) + m[1] * std::fabs(z[1] - t_ref) +
                 m[2] * std::fabs(z[2] - t_ref)) / det + zmax);
  const double msum = m[0] + m[1] + m[2];
  e.uv = kEps * (std::max(m[1], m[2]) + std::max(std::fabs(u_ref), std::fabs(v_ref)) * msum) / det;
  return e;
}

// Tolerances for comparing the float test with ref:: : t within 1e-5 relative, u, v within
// 1e-4, each widened to 4x the float error bound above where the problem is ill-conditioned.
inline double TTolerance(const ref::Ray& r, const double p[3][3], const ref::Hit& h) {
  return std::max(1e-5 * std::fabs(h.t), 4.0 * WatertightErrorBound(r, p, h.t, h.u, h.v).t);
}
inline double UvTolerance(const ref::Ray& r, const double p[3][3], const ref::Hit& h) {
  return std::max(1e-4, 4.0 * WatertightErrorBound(r, p, h.t, h.u, h.v).uv);
}

// Where the ray's line meets the triangle's plane, in double (no rejection): t and the smallest
// barycentric coordinate (< 0 outside). Tells float/double edge and bound decisions apart from
// real mismatches. Returns false if the ray is parallel to the plane.
inline bool PlaneHitDouble(const double o[3], const double d[3], const double p[3][3], double* t,
                           double* min_bary) {
  double e1[3], e2[3], s[3];
  for (int a = 0; a < 3; ++a) {
    e1[a] = p[1][a] - p[0][a];
    e2[a] = p[2][a] - p[0][a];
    s[a] = o[a] - p[0][a];
  }
  const double pv[3] = {d[1] * e2[2] - d[2] * e2[1], d[2] * e2[0] - d[0] * e2[2],
                        d[0] * e2[1] - d[1] * e2[0]};
  const double det = e1[0] * pv[0] + e1[1] * pv[1] + e1[2] * pv[2];
  if (det == 0.0) return false;
  const double q[3] = {s[1] * e1[2] - s[2] * e1[1], s[2] * e1[0] - s[0] * e1[2],
                       s[0] * e1[1] - s[1] * e1[0]};
  const double u = (s[0] * pv[0] + s[1] * pv[1] + s[2] * pv[2]) / det;
  const double v = (d[0] * q[0] + d[1] * q[1] + d[2] * q[2]) / det;
  *t = (e2[0] * q[0] + e2[1] * q[1] + e2[2] * q[2]) / det;
  *min_bary = std::min({u, v, 1.0 - u - v});
  return true;
}

// |a - b| <= rel * |b| (b is the reference).
inline bool RelClose(double a, double b, double rel) { return std::fabs(a - b) <= rel * std::fabs(b); }

}  // namespace rs::test
