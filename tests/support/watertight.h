// The watertightness workload on a closed icosphere (scenes/icosphere.h): rays from inside aimed
// exactly at every vertex and edge midpoint, each vertex's fan and each edge's two triangles as
// hand-made grid cells of triangle bundles. Shared by tests/kernels/tri_simd_test.cc and
// bench/kernels/robust_bench.cc (which adds Embree's counts).
#pragma once

#include <algorithm>
#include <array>
#include <cstdint>
#include <limits>
#include <map>
#include <random>
#include <string>
#include <utility>
#include <vector>

#include "include/raystream/raystream.h"
#include "kernels/grid.h"
#include "kernels/tri_bundles.h"
#include "kernels/triangle.h"
#include "scenes/icosphere.h"
#include "streams/ray_stream.h"

namespace rs::test {

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
  TriBundles bundles;  // "cells": each vertex's fan, then the two triangles of each edge
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
  // Cells as a hand-made Grid (CSR lists only), packed by BuildTriBundles.
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
  BuildTriBundles(grid, s->tris, &s->bundles);

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

}  // namespace rs::test
