// Closed icospheres for robustness tests and benchmarks: an icosahedron subdivided `levels` times
// with shared (welded) vertices, optionally snapped to a lattice so that edge midpoints and ray
// directions aimed at them are exact floats; and the watertightness workload built on it, rays
// from inside aimed exactly at every vertex and edge midpoint (tests/kernels/tri_simd_test.cc,
// bench/robust_bench.cc). Also used for the hand-made test scenes (tests/sched/hand_scenes.h).
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <limits>
#include <map>
#include <random>
#include <string>
#include <utility>
#include <vector>

#include "include/raystream/raystream.h"
#include "kernels/grid.h"
#include "kernels/tri_packets.h"
#include "kernels/triangle.h"
#include "streams/ray_stream.h"

namespace rs::bench {

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

// Miss counts of one tracer, split by what the rays aim at.
struct Misses {
  size_t vertex = 0;
  size_t edge = 0;
  size_t total() const { return vertex + edge; }
};

struct WatertightSetup {
  Icosphere ico;
  std::vector<float> positions;  // xyz, for MeshView
  std::vector<uint32_t> indices;
  TriangleSoA tris;
  TriPackets packets;  // "cells": each vertex's fan, then the two triangles of each edge
  size_t num_vertex_cells = 0;
  RayStream rays;                                    // in cell order; rays.pixel[i] = cell
  std::vector<std::pair<size_t, size_t>> cell_rays;  // [first, end) per cell
  size_t vertex_rays = 0;  // rays [0, vertex_rays) aim at vertices, the rest at edge midpoints

  MeshView mesh() const {
    return MeshView{positions.data(), positions.size() / 3, 3, indices.data(), indices.size() / 3};
  }
  bool IsVertexRay(size_t i) const { return i < vertex_rays; }
};

// An icosphere subdivided `levels` times (20 * 4^levels triangles, levels <= 6) of radius 100
// centred at (1e5, 1e5, 1e5), snapped to 2^-6; at least `n` rays, split evenly between vertices and
// edge midpoints (the same count per vertex and per edge), origins on the 2^-7 lattice within half
// the radius of the centre, so that o + d == target exactly: the ray crosses the surface exactly at
// the vertex or midpoint. Returns "" or the reason the construction is not exact.
inline std::string MakeWatertightSetup(int levels, size_t n, WatertightSetup* s) {
  constexpr double kCentre = 1e5, kRadius = 100.0;
  s->ico = MakeIcosphere(levels, kRadius, {kCentre, kCentre, kCentre}, 64.0);
  const Icosphere& ico = s->ico;
  for (const auto& v : ico.v) s->positions.insert(s->positions.end(), {v[0], v[1], v[2]});
  for (const auto& t : ico.tri) s->indices.insert(s->indices.end(), {t[0], t[1], t[2]});
  BuildTriangleSoA(s->mesh(), &s->tris);
  if (s->tris.num_degenerate != 0) return "degenerate triangles after snapping";
  std::vector<std::vector<uint32_t>> fans(ico.v.size());
  std::map<std::pair<uint32_t, uint32_t>, std::vector<uint32_t>> edges;
  for (uint32_t t = 0; t < ico.tri.size(); ++t) {
    for (int k = 0; k < 3; ++k) {
      fans[ico.tri[t][k]].push_back(t);
      edges[std::minmax(ico.tri[t][k], ico.tri[t][(k + 1) % 3])].push_back(t);
    }
  }
  // Cells as a hand-made Grid (CSR lists only), packed by BuildTriPackets.
  std::vector<std::array<float, 3>> targets;
  Grid grid;
  grid.num_cells = fans.size() + edges.size();
  grid.cell_begin = hwy::AllocateAligned<uint32_t>(grid.num_cells + 1);
  std::vector<uint32_t> lists;
  grid.cell_begin[0] = 0;
  size_t cell = 0;
  for (size_t v = 0; v < fans.size(); ++v) {
    lists.insert(lists.end(), fans[v].begin(), fans[v].end());
    grid.cell_begin[++cell] = static_cast<uint32_t>(lists.size());
    targets.push_back(ico.v[v]);
  }
  s->num_vertex_cells = fans.size();
  for (const auto& [e, tris] : edges) {
    if (tris.size() != 2) return "mesh not closed: an edge with " + std::to_string(tris.size());
    lists.insert(lists.end(), tris.begin(), tris.end());
    grid.cell_begin[++cell] = static_cast<uint32_t>(lists.size());
    const auto& a = ico.v[e.first];
    const auto& b = ico.v[e.second];
    targets.push_back({(a[0] + b[0]) * 0.5f, (a[1] + b[1]) * 0.5f, (a[2] + b[2]) * 0.5f});
  }
  grid.num_refs = lists.size();
  grid.tri_ids = hwy::AllocateAligned<uint32_t>(lists.size());
  std::copy(lists.begin(), lists.end(), grid.tri_ids.get());
  BuildTriPackets(grid, s->tris, &s->packets);

  const size_t num_edges = edges.size();
  const size_t per_vertex = (n / 2 + fans.size() - 1) / fans.size();
  const size_t per_edge = (n - std::min(n, per_vertex * fans.size()) + num_edges - 1) / num_edges;
  std::mt19937_64 rng(0x5eed0001);
  std::uniform_real_distribution<double> unit(-1.0, 1.0);
  s->rays.Reserve(per_vertex * fans.size() + per_edge * num_edges);
  for (uint32_t c = 0; c < grid.num_cells; ++c) {
    const size_t per = c < fans.size() ? per_vertex : per_edge;
    const size_t first = s->rays.size();
    for (size_t k = 0; k < per; ++k) {
      double q[3], len2;
      do {
        for (double& x : q) x = unit(rng);
        len2 = q[0] * q[0] + q[1] * q[1] + q[2] * q[2];
      } while (len2 > 1.0);
      float o[3], d[3];
      for (int a = 0; a < 3; ++a) {
        const double x = std::round((kCentre + 0.5 * kRadius * q[a]) * 128.0) / 128.0;
        volatile float rounded = static_cast<float>(x);
        o[a] = rounded;  // volatile: see MakeIcosphere
        d[a] = targets[c][a] - o[a];
        if (o[a] + d[a] != targets[c][a]) return "o + d != target: not exact";
      }
      s->rays.Push(o[0], o[1], o[2], d[0], d[1], d[2], 0.0f, std::numeric_limits<float>::infinity(),
                   c, 1.0f, 1.0f, 1.0f, 0, RayKind::kPrimary);
    }
    s->cell_rays.push_back({first, s->rays.size()});
    if (c + 1 == fans.size()) s->vertex_rays = s->rays.size();
  }
  s->rays.FillPadding();
  return "";
}

}  // namespace rs::bench
