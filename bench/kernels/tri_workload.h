// The fixed ray/triangle workload of tri_bench (rdtsc ticks per test) and kernel_counts
// (callgrind instructions per test): one "cell" of random triangles as 4-wide bundles and rays
// through it, so both benchmarks measure the same work. Deterministic for a fixed seed.
#pragma once

#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <random>
#include <vector>

#include "include/raystream/raystream.h"
#include "kernels/tri_bundles.h"
#include "kernels/tri_intersect.h"
#include "kernels/triangle.h"
#include "streams/ray_stream.h"

namespace rs::bench {

// `num_tris` triangles (a multiple of 4: no padding lanes, so every lane is a test) with
// vertices in the unit cube [0, 1]^3 around random centres, edges up to 0.5, as one cell of
// bundles; `num_rays` rays from random points on the sphere of radius 2 around the cube's centre
// to random points in the cube (21 % of them hit one of 16 triangles). Rays are kept
// both as a stream (N x 1 kernel) and as PreparedRays (1 x 4 kernels: in a traversal
// the per-ray setup is done once per ray, not per cell, so it is left out of the per-test cost).
struct TriWorkload {
  std::vector<float> positions;
  std::vector<uint32_t> indices;
  TriangleSoA tris;
  TriBundles bundles;  // Cell(0): all triangles in id order
  RayStream rays;
  std::vector<PreparedRay> prepared_rays;

  TriBundleSpan span() const { return bundles.Cell(0); }
  size_t tests_per_pass() const { return rays.size() * tris.size; }
};

inline void MakeTriWorkload(size_t num_tris, size_t num_rays, uint32_t seed, TriWorkload* w) {
  std::mt19937 gen(seed);
  std::uniform_real_distribution<float> u(0.0f, 1.0f);
  w->positions.clear();
  w->indices.clear();
  for (size_t t = 0; t < num_tris; ++t) {
    const float c[3] = {0.25f + 0.5f * u(gen), 0.25f + 0.5f * u(gen), 0.25f + 0.5f * u(gen)};
    for (int k = 0; k < 3; ++k) {
      for (int a = 0; a < 3; ++a) w->positions.push_back(c[a] + 0.5f * (u(gen) - 0.5f));
      w->indices.push_back(static_cast<uint32_t>(w->indices.size()));
    }
  }
  MeshView mesh;
  mesh.positions = w->positions.data();
  mesh.num_vertices = w->positions.size() / 3;
  mesh.stride = 3;
  mesh.indices = w->indices.data();
  mesh.num_triangles = num_tris;
  BuildTriangleSoA(mesh, &w->tris);
  std::vector<uint32_t> ids(num_tris);
  for (size_t t = 0; t < num_tris; ++t) ids[t] = static_cast<uint32_t>(t);
  BuildTriBundleList(w->tris, ids.data(), ids.size(), &w->bundles);
  w->rays.Clear();
  w->prepared_rays.clear();
  std::normal_distribution<float> g(0.0f, 1.0f);
  for (size_t i = 0; i < num_rays; ++i) {
    float o[3], len2 = 0.0f;
    do {
      len2 = 0.0f;
      for (float& x : o) {
        x = g(gen);
        len2 += x * x;
      }
    } while (len2 < 1e-4f);
    const float scale = 2.0f / std::sqrt(len2);
    float d[3];
    for (int a = 0; a < 3; ++a) {
      o[a] = 0.5f + scale * o[a];
      d[a] = u(gen) - o[a];
    }
    w->rays.Push(o[0], o[1], o[2], d[0], d[1], d[2], 0.0f, std::numeric_limits<float>::infinity(),
                 static_cast<uint32_t>(i), 1.0f, 1.0f, 1.0f, 0, RayKind::kPrimary);
    w->prepared_rays.push_back(PrepareRay(o[0], o[1], o[2], d[0], d[1], d[2]));
  }
  w->rays.FillPadding();
}

}  // namespace rs::bench
