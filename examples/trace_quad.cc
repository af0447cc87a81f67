// A tracer that links raystream: build a grid over its own quad, trace a 4-ray stream for
// closest hits and occlusion, print the results. Uses only <raystream/raystream.h>.
#include <raystream/raystream.h>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <vector>

int main() {
  // The caller owns its mesh: a unit quad in the z = 0 plane, two triangles.
  const float positions[] = {0, 0, 0, 1, 0, 0, 1, 1, 0, 0, 1, 0};
  const uint32_t indices[] = {0, 1, 2, 0, 2, 3};
  rs::MeshView mesh;
  mesh.positions = positions;
  mesh.num_vertices = 4;
  mesh.indices = indices;
  mesh.num_triangles = 2;
  const rs::Accel accel(mesh);

  // SoA stream, padded to rs::PaddedSize and aligned to rs::kStreamAlign.
  constexpr size_t kRays = 4;
  const size_t n = rs::PaddedSize(kRays);
  auto alloc = [n] {
    return static_cast<float*>(std::aligned_alloc(rs::kStreamAlign, n * sizeof(float)));
  };
  rs::RayStreamView rays;
  rays.ox = alloc(), rays.oy = alloc(), rays.oz = alloc();
  rays.dx = alloc(), rays.dy = alloc(), rays.dz = alloc();
  rays.tmin = alloc(), rays.tmax = alloc();
  rays.size = kRays;
  const float xs[kRays] = {0.25f, 0.75f, 0.5f, 2.0f};  // the last one misses
  const float ys[kRays] = {0.75f, 0.25f, 0.5f, 2.0f};
  for (size_t i = 0; i < n; ++i) {
    const size_t k = i < kRays ? i : 0;
    rays.ox[i] = xs[k], rays.oy[i] = ys[k], rays.oz[i] = 2.0f;
    rays.dx[i] = 0.0f, rays.dy[i] = 0.0f, rays.dz[i] = -1.0f;
    rays.tmin[i] = 0.0f, rays.tmax[i] = INFINITY;
  }
  rs::HitStreamView hits;
  hits.t = alloc(), hits.u = alloc(), hits.v = alloc();
  hits.prim = static_cast<int32_t*>(std::aligned_alloc(rs::kStreamAlign, n * sizeof(int32_t)));
  hits.size = kRays;
  int32_t* occluded = static_cast<int32_t*>(std::aligned_alloc(rs::kStreamAlign, n * 4));

  accel.Intersect(rays, hits);
  accel.Occluded(rays, occluded);
  int failures = 0;
  for (size_t i = 0; i < kRays; ++i) {
    std::printf("ray %zu: prim %d t %.3f u %.3f v %.3f occluded %d\n", i, hits.prim[i], hits.t[i],
                hits.u[i], hits.v[i], occluded[i]);
    const bool should_hit = i < 3;
    if ((hits.prim[i] >= 0) != should_hit || (occluded[i] != 0) != should_hit) ++failures;
    if (should_hit && std::fabs(hits.t[i] - 2.0f) > 1e-6f) ++failures;
  }
  std::printf("raystream %s: %s\n", rs::Version(), failures == 0 ? "ok" : "WRONG");
  for (float* p : {rays.ox, rays.oy, rays.oz, rays.dx, rays.dy, rays.dz, rays.tmin, rays.tmax,
                   hits.t, hits.u, hits.v}) {
    std::free(p);
  }
  std::free(hits.prim);
  std::free(occluded);
  return failures == 0 ? 0 : 1;
}
