// A tracer that links raystream: build a grid over its own quad, trace a 4-ray stream for
// closest hits and occlusion; then a TraceScene of three geometries (32- and 16-bit indices,
// strides, a shared buffer, masks) and an instance, traced from owning RayBuffer / HitBuffer
// storage, updated and traced again; hits (geomID, instID, t, Ng) are checked against the exact
// values. Uses only <raystream/raystream.h>.
#include <raystream/raystream.h>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <vector>

// The scene part: returns the number of wrong results.
int RunScene() {
  // Geometry 0: the unit quad at z = 0 (32-bit indices, packed, copied), mask 1.
  float quad0[] = {0, 0, 0, 1, 0, 0, 1, 1, 0, 0, 1, 0};
  const uint32_t idx32[] = {0, 1, 2, 0, 2, 3};
  // Geometry 1: a quad over x in [2, 3] at z = 0.5 (16-bit indices, stride 16 B, the caller's
  // buffer shared: it outlives the scene), mask 2.
  const float quad1[] = {2, 0, 0.5f, -1, 3, 0, 0.5f, -1, 3, 1, 0.5f, -1, 2, 1, 0.5f, -1};
  const uint16_t idx16[] = {0, 1, 2, 0, 2, 3};
  rs::TraceScene scene;
  rs::GeometryDesc g;
  g.positions = quad0, g.num_vertices = 4, g.indices = idx32, g.num_triangles = 2, g.mask = 1;
  const uint32_t geom0 = scene.AttachGeometry(g);
  g.positions = quad1, g.stride_bytes = 16, g.indices = idx16, g.index_type = rs::IndexType::kUInt16;
  g.mask = 2, g.mode = rs::BufferMode::kShared;
  const uint32_t geom1 = scene.AttachGeometry(g);
  // Geometry 2: the unit quad again, traced only through an instance that scales it by 2 in x
  // and y, by 0.5 in z and moves it to x in [4, 6], z = -1.
  g = rs::GeometryDesc{};
  g.positions = quad0, g.num_vertices = 4, g.indices = idx32, g.num_triangles = 2;
  g.instance_only = true;
  const uint32_t geom2 = scene.AttachGeometry(g);
  const float xfm[12] = {2, 0, 0, 4, 0, 2, 0, 0, 0, 0, 0.5f, -1};
  const uint32_t inst0 = scene.AttachInstance(geom2, xfm);
  scene.Commit();

  // Rays straight down from z = 2: at x = 0.5 (geometry 0), 2.5 (geometry 1) with all mask bits
  // and with mask 1 only (geometry 1 skipped: a miss), 5 (the instance), 7 (a miss).
  constexpr size_t kRays = 5;
  const float xs[kRays] = {0.5f, 2.5f, 2.5f, 5.0f, 7.0f};
  const uint32_t masks[kRays] = {~0u, ~0u, 1u, ~0u, ~0u};
  rs::RayBuffer rays(kRays);  // 64-B aligned, padded; tnear 0, tfar +inf, mask ~0 by default
  rs::HitBuffer hits(kRays);
  for (size_t i = 0; i < kRays; ++i) {
    rays.ox()[i] = xs[i], rays.oy()[i] = 0.25f, rays.oz()[i] = 2.0f;
    rays.dz()[i] = -1.0f;
    rays.mask()[i] = masks[i];
  }
  // Expected: geomID, instID, t, Ng z (exact: axis-aligned quads; Ng = (p1-p0)x(p2-p0), for the
  // instance the inverse transpose of diag(2, 2, 0.5) times (0, 0, 1) = (0, 0, 2)).
  const int32_t want_geom[kRays] = {int32_t(geom0), int32_t(geom1), -1, int32_t(geom2), -1};
  const int32_t want_inst[kRays] = {-1, -1, -1, int32_t(inst0), -1};
  const float want_t[kRays] = {2.0f, 1.5f, INFINITY, 3.0f, INFINITY};
  const float want_ngz[kRays] = {1.0f, 1.0f, 0.0f, 2.0f, 0.0f};
  int failures = 0;
  const auto check = [&](const char* what, float t0) {
    scene.Intersect(rays.View(), hits.View());
    for (size_t i = 0; i < kRays; ++i) {
      const float t = i == 0 ? t0 : want_t[i];
      std::printf("%s ray %zu: geom %d inst %d prim %d t %.3f Ng (%.1f %.1f %.1f)\n", what, i,
                  hits.geom()[i], hits.inst()[i], hits.prim()[i], hits.t()[i], hits.ng_x()[i],
                  hits.ng_y()[i], hits.ng_z()[i]);
      if (hits.geom()[i] != want_geom[i] || hits.inst()[i] != want_inst[i]) ++failures;
      if (!(std::fabs(hits.t()[i] - t) <= 1e-6f * t) && !(std::isinf(t) && std::isinf(hits.t()[i]))) {
        ++failures;
      }
      if (hits.ng_z()[i] != want_ngz[i] || hits.ng_x()[i] != 0.0f || hits.ng_y()[i] != 0.0f) {
        ++failures;
      }
    }
  };
  check("scene", 2.0f);
  // Move geometry 0 down to z = -0.5 (same topology): only its grid is rebuilt.
  for (int v = 0; v < 4; ++v) quad0[3 * v + 2] = -0.5f;
  scene.UpdateGeometry(geom0, quad0, 12);
  scene.Commit();
  check("updated", 2.5f);
  return failures;
}

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
  auto alloc = [=] {
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
  failures += RunScene();
  std::printf("raystream %s: %s\n", rs::Version(), failures == 0 ? "ok" : "WRONG");
  for (float* p : {rays.ox, rays.oy, rays.oz, rays.dx, rays.dy, rays.dz, rays.tmin, rays.tmax,
                   hits.t, hits.u, hits.v}) {
    std::free(p);
  }
  std::free(hits.prim);
  std::free(occluded);
  return failures == 0 ? 0 : 1;
}
