// Workloads shared by the DDA benchmarks (bench/kernels/dda_bench.cc) and the callgrind driver
// (bench/kernels/kernel_counts.cc): the almost empty "corners" scene and uniformly random rays.
#pragma once

#include <cstddef>
#include <cstdint>
#include <glm/glm.hpp>
#include <limits>
#include <random>

#include "scenes/scene.h"
#include "streams/ray_stream.h"

namespace rs::bench {

// "corners": one tiny triangle in each corner of the unit cube, for an almost empty grid whose
// rays step through ~100 empty cells each: the cost of a ray-cell step alone.
inline Scene CornersScene() {
  Scene s;
  s.name = "corners";
  for (int c = 0; c < 8; ++c) {
    const glm::vec3 p(float(c & 1), float((c >> 1) & 1), float((c >> 2) & 1));
    const glm::vec3 in = 0.5f - p;  // towards the centre
    const uint32_t base = uint32_t(s.positions.size());
    s.positions.push_back(p);
    s.positions.push_back(p + 0.001f * glm::vec3(in.x, 0.0f, 0.0f));
    s.positions.push_back(p + 0.001f * glm::vec3(0.0f, in.y, 0.0f));
    s.triangles.push_back(glm::uvec3(base, base + 1, base + 2));
  }
  s.materials.push_back(Material{});
  s.material_ids.assign(s.triangles.size(), 0);
  return s;
}

// Appends n rays with origins uniform in [lo, hi] and directions uniform in the unit ball (not
// normalised), from a fixed seed; pixel = index. Pads the stream.
inline void AppendRandomRays(const glm::vec3& lo, const glm::vec3& hi, size_t n, RayStream& rays) {
  std::mt19937 gen(12345);
  std::uniform_real_distribution<float> u(0.0f, 1.0f);
  for (size_t i = 0; i < n; ++i) {
    float o[3], d[3], len2;
    for (int a = 0; a < 3; ++a) o[a] = lo[a] + (hi[a] - lo[a]) * u(gen);
    do {
      for (float& c : d) c = 2.0f * u(gen) - 1.0f;
      len2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
    } while (len2 < 1e-4f || len2 > 1.0f);
    rays.Push(o[0], o[1], o[2], d[0], d[1], d[2], 0.0f, std::numeric_limits<float>::infinity(),
              uint32_t(i), 1, 1, 1, 0, RayKind::kPrimary);
  }
  rays.FillPadding();
}

}  // namespace rs::bench
