// Closed icospheres: an icosahedron subdivided `levels` times with shared (welded) vertices,
// optionally snapped to a lattice so that edge midpoints and ray directions aimed at them are
// exact floats. Used by the watertightness workload (tests/support/watertight.h), the hand-made
// test scenes (tests/support/hand_scenes.h), kernel tests and bench/kernels/robust_bench.cc.
// Header-only, standard library only.
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <map>
#include <utility>
#include <vector>

namespace rs {

struct Icosphere {
  std::vector<std::array<float, 3>> v;       // welded vertices
  std::vector<std::array<uint32_t, 3>> tri;  // 20 * 4^levels triangles, outward winding
};

// Icosahedron subdivided `levels` times, vertices projected to radius r around c in
// double and rounded to float; if snap > 0, each coordinate is first rounded to a multiple of
// 1 / snap. With |coordinates| in [2^16, 2^17) and snap = 64, every edge midpoint is then an
// exact float, and so is target - o for origins on the 2^-7 lattice. The mesh is closed: every
// edge belongs to exactly two triangles.
inline Icosphere MakeIcosphere(int levels, double r, const std::array<double, 3>& c,
                               double snap) {
  std::vector<std::array<double, 3>> p;
  const double g = (1.0 + std::sqrt(5.0)) / 2.0;
  const double base[12][3] = {{-1, g, 0}, {1, g, 0}, {-1, -g, 0}, {1, -g, 0},
                              {0, -1, g}, {0, 1, g}, {0, -1, -g}, {0, 1, -g},
                              {g, 0, -1}, {g, 0, 1}, {-g, 0, -1}, {-g, 0, 1}};
  for (const auto& b : base) p.push_back({b[0], b[1], b[2]});
  std::vector<std::array<uint32_t, 3>> tri = {
      {0, 11, 5},  {0, 5, 1},  {0, 1, 7},  {0, 7, 10}, {0, 10, 11}, {1, 5, 9}, {5, 11, 4},
      {11, 10, 2}, {10, 7, 6}, {7, 1, 8},  {3, 9, 4},  {3, 4, 2},   {3, 2, 6}, {3, 6, 8},
      {3, 8, 9},   {4, 9, 5},  {2, 4, 11}, {6, 2, 10}, {8, 6, 7},   {9, 8, 1}};
  for (int l = 0; l < levels; ++l) {
    std::map<std::pair<uint32_t, uint32_t>, uint32_t> mid;
    auto midpoint = [&](uint32_t a, uint32_t b) {
      const auto key = std::minmax(a, b);
      const auto it = mid.find(key);
      if (it != mid.end()) return it->second;
      p.push_back({(p[a][0] + p[b][0]) / 2, (p[a][1] + p[b][1]) / 2, (p[a][2] + p[b][2]) / 2});
      const uint32_t m = static_cast<uint32_t>(p.size() - 1);
      mid.emplace(key, m);
      return m;
    };
    std::vector<std::array<uint32_t, 3>> next;
    next.reserve(tri.size() * 4);
    for (const auto& t : tri) {
      const uint32_t a = midpoint(t[0], t[1]), b = midpoint(t[1], t[2]), m = midpoint(t[2], t[0]);
      next.push_back({t[0], a, m});
      next.push_back({t[1], b, a});
      next.push_back({t[2], m, b});
      next.push_back({a, b, m});
    }
    tri = std::move(next);
  }
  Icosphere s;
  s.v.reserve(p.size());
  for (const auto& q : p) {
    const double len = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2]);
    std::array<float, 3> f;
    for (int a = 0; a < 3; ++a) {
      const double x = c[a] + r * q[a] / len;
      volatile float rounded = static_cast<float>(snap > 0 ? std::round(x * snap) / snap : x);
      f[a] = rounded;  // volatile: a real float rounding (GCC 12 SLP bug, TOOLCHAIN.md)
    }
    s.v.push_back(f);
  }
  s.tri = std::move(tri);
  return s;
}

}  // namespace rs
