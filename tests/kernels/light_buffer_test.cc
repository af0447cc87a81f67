// rs::LightBuffer (kernels/light_buffer.h) on every compiled target against Accel::Occluded on
// the same rays (itself the exact watertight any-hit, checked against the scalar walk in
// packet_dda_test): the same occlusion for every ray. Rays from the light to the vertices, edge
// midpoints and random points of every triangle, with tmax 1, just below 1, 0.5 and +inf, and in
// random directions; lights inside and outside the scenes, at a mesh vertex, on a triangle's
// plane and on face-diagonal directions; scenes at 1.5e5 and scaled by 1e-3; NaN, Inf and zero
// directions, tmin < 0 and rays not from the light in the same stream; an empty mesh; reference
// budgets for 10,000 identical triangles and a 30,000-triangle fan; a small sphere 10 and 1e3
// away from the light, whose cells must go where it is (the longest list well below its size).
// The built lists themselves: each in ascending reach, each reach at most its triangle's
// distance from the light (the early stop's premise).
#include <doctest/doctest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "include/raystream/raystream.h"
#include "kernels/light_buffer.h"
#include "kernels/triangle.h"
#include "scenes/icosphere.h"
#include "scenes/load.h"
#include "streams/ray_stream.h"
#include "tests/kernels/dda_util.h"
#include "tests/kernels/geometry_util.h"
#include "tests/test_util.h"

namespace rs {
namespace {

using test::F;
using test::kInf;
using test::kNaN;
using test::MakeStream;
using test::Ray;
using test::Rng;
using test::Soup;

// Rays from `light` to points of every triangle of `mesh` (vertices, edge midpoints, a random
// interior point, each with several tmax) and in random directions.
std::vector<Ray> LightRays(const MeshView& mesh, const float light[3], Rng& rng, size_t max_tris) {
  std::vector<Ray> rays;
  const size_t step = std::max<size_t>(1, mesh.num_triangles / max_tris);
  const float tmaxes[] = {1.0f, F(1.0 - 1e-6), 0.5f, kInf};
  for (size_t i = 0; i < mesh.num_triangles; i += step) {
    double p[3][3];
    for (int k = 0; k < 3; ++k) {
      const float* v = mesh.positions + size_t{mesh.indices[3 * i + k]} * mesh.stride;
      for (int a = 0; a < 3; ++a) p[k][a] = v[a];
    }
    double targets[7][3];
    const double u = rng.Uniform(0, 1), w = rng.Uniform(0, 1 - u);
    for (int a = 0; a < 3; ++a) {
      for (int k = 0; k < 3; ++k) targets[k][a] = p[k][a];
      targets[3][a] = 0.5 * (p[0][a] + p[1][a]);
      targets[4][a] = 0.5 * (p[1][a] + p[2][a]);
      targets[5][a] = 0.5 * (p[2][a] + p[0][a]);
      targets[6][a] = (1 - u - w) * p[0][a] + u * p[1][a] + w * p[2][a];
    }
    for (int t = 0; t < 7; ++t) {
      Ray r;
      for (int a = 0; a < 3; ++a) {
        r.o[a] = light[a];
        r.d[a] = F(targets[t][a] - double(light[a]));
      }
      r.tmin = 0.0f;
      r.tmax = tmaxes[(i + size_t(t)) % 4];
      rays.push_back(r);
    }
    Ray r;
    for (int a = 0; a < 3; ++a) r.o[a] = light[a];
    rng.Direction(r.d);
    r.tmin = 0.0f;
    r.tmax = kInf;
    rays.push_back(r);
  }
  return rays;
}

// LightBuffer::Occluded equals Accel::Occluded on `rays`, on every target; returns the
// occluded count.
size_t CheckSame(const Accel& accel, const LightBuffer& lb, const std::vector<Ray>& rays,
                 const std::string& what) {
  RayStream s = MakeStream(rays);
  std::vector<int32_t> want(rays.size() + 16, -7);
  accel.Occluded(s.view(), want.data());
  size_t occluded = 0;
  for (size_t i = 0; i < rays.size(); ++i) occluded += want[i] != 0;
  test::ForEachTarget([&](const char* target) {
    std::vector<int32_t> got(rays.size() + 16, -7);
    TraceStats st;
    lb.Occluded(s.view(), got.data(), &st);
    size_t differ = 0, first = rays.size();
    for (size_t i = 0; i < rays.size(); ++i) {
      if (got[i] != want[i]) {
        if (differ++ == 0) first = i;
      }
    }
    INFO(what, " on ", target, ": first differing ray ", first);
    CHECK(differ == 0);
    CHECK(got[rays.size()] == -7);  // nothing written past the end
  });
  return occluded;
}

void CheckScene(const MeshView& mesh, const std::vector<std::array<float, 3>>& lights,
                const std::string& what, size_t max_tris = 4000) {
  const Accel accel(mesh);
  Rng rng(7);
  for (const auto& l : lights) {
    const LightBuffer lb(accel, l.data());
    const LightBufferInfo info = lb.Info();
    CHECK(info.references <= 8 * mesh.num_triangles + (size_t{1} << 16) + info.always);
    const std::vector<Ray> rays = LightRays(mesh, l.data(), rng, max_tris);
    const size_t occluded = CheckSame(accel, lb, rays, what);
    MESSAGE(what, ": light (", l[0], ", ", l[1], ", ", l[2], "): ", rays.size(), " rays, ",
            occluded, " occluded, resolution ", info.resolution, ", ", info.references,
            " references, ", info.always, " always");
  }
}

std::vector<float> Positions(const Scene& scene) {
  const MeshView m = scene.mesh();
  std::vector<float> p(m.num_vertices * 3);
  for (size_t v = 0; v < m.num_vertices; ++v) {
    for (int a = 0; a < 3; ++a) p[3 * v + a] = m.positions[v * m.stride + a];
  }
  return p;
}

TEST_CASE("light buffer: built-in scenes, lights inside, outside, at a vertex, on a plane") {
  for (const char* name : {"erw6", "cornell", "spherebox"}) {
    const Scene scene = LoadScene(name);
    const MeshView mesh = scene.mesh();
    float lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
    for (size_t v = 0; v < mesh.num_vertices; ++v) {
      for (int a = 0; a < 3; ++a) {
        lo[a] = std::min(lo[a], mesh.positions[v * mesh.stride + a]);
        hi[a] = std::max(hi[a], mesh.positions[v * mesh.stride + a]);
      }
    }
    std::vector<std::array<float, 3>> lights;
    const float* v0 = mesh.positions + size_t{mesh.indices[0]} * mesh.stride;
    const float* v1 = mesh.positions + size_t{mesh.indices[1]} * mesh.stride;
    lights.push_back({F(0.5 * (lo[0] + hi[0])), F(lo[1] + 0.95 * (hi[1] - lo[1])),
                      F(0.5 * (lo[2] + hi[2]))});                       // inside, near the top
    lights.push_back({F(0.3 * lo[0] + 0.7 * hi[0]), F(0.5 * (lo[1] + hi[1])),
                      F(0.6 * lo[2] + 0.4 * hi[2])});                   // inside
    lights.push_back({F(hi[0] + 2.0 * (hi[0] - lo[0])), F(hi[1] + 1.0), F(lo[2] - 3.0)});  // out
    lights.push_back({v0[0], v0[1], v0[2]});                            // at a vertex
    lights.push_back({F(0.5 * (double(v0[0]) + v1[0])), F(0.5 * (double(v0[1]) + v1[1])),
                      F(0.5 * (double(v0[2]) + v1[2]))});               // on an edge
    CheckScene(mesh, lights, name);
  }
}

TEST_CASE("light buffer: a closed sphere around and beside the light, at the origin and at 1.5e5") {
  for (const double cx : {0.0, 148376.0}) {
    const Icosphere s = MakeIcosphere(4, 1.0, {cx, cx == 0.0 ? 0.0 : 1234.0, -cx}, cx == 0 ? 0 : 64);
    Soup soup;
    for (const auto& t : s.tri) soup.AddTriangle(s.v[t[0]].data(), s.v[t[1]].data(), s.v[t[2]].data());
    const float y = cx == 0.0 ? 0.0f : 1234.0f;
    // inside: every ray from the centre is blocked (closed mesh: no leaks); outside
    std::vector<std::array<float, 3>> lights = {{F(cx), y, F(-cx)},
                                                {F(cx + 0.25), F(y + 0.125), F(-cx)},
                                                {F(cx + 3.0), F(y + 2.0), F(-cx - 1.0)}};
    CheckScene(soup.view(), lights, cx == 0 ? "sphere at 0" : "sphere at 1.5e5");
    // from the centre, rays towards every vertex and edge midpoint with tmax = 2: all blocked
    const Accel accel(soup.view());
    const LightBuffer lb(accel, lights[0].data());
    std::vector<Ray> rays;
    Rng rng(3);
    for (size_t k = 0; k < 4000; ++k) {
      Ray r;
      for (int a = 0; a < 3; ++a) r.o[a] = lights[0][a];
      if (k < s.v.size()) {
        for (int a = 0; a < 3; ++a) r.d[a] = F(double(s.v[k][a]) - double(lights[0][a]));
      } else {
        rng.Direction(r.d);
      }
      r.tmin = 0.0f;
      r.tmax = 4.0f;
      rays.push_back(r);
    }
    CHECK(CheckSame(accel, lb, rays, "sphere centre") == rays.size());
  }
}

TEST_CASE("light buffer: a small mesh far from the light gets cells over the window it covers") {
  // a sphere of radius 0.1 seen from 10 (and from 1e3) away covers a few thousandths of a cube
  // face: cells uniform over the face would put all its triangles into one or four cells
  for (const double far : {10.0, 1000.0}) {
    const Icosphere s = MakeIcosphere(4, 0.1, {0.0, 0.0, 0.0}, 0);
    Soup soup;
    for (const auto& t : s.tri) soup.AddTriangle(s.v[t[0]].data(), s.v[t[1]].data(), s.v[t[2]].data());
    const size_t n = s.tri.size();
    const std::vector<std::array<float, 3>> lights = {
        {F(far), F(0.3 * far), F(-0.2 * far)}, {0.0f, F(far), 0.0f}, {F(-far), F(far), F(far)}};
    CheckScene(soup.view(), lights, far == 10.0 ? "sphere 10 away" : "sphere 1e3 away", 2000);
    const Accel accel(soup.view());
    for (const auto& l : lights) {
      const LightBufferInfo info = LightBuffer(accel, l.data()).Info();
      INFO("light (", l[0], ", ", l[1], ", ", l[2], "): ", info.cells, " cells, longest list ",
           info.longest, " of ", n, " triangles");
      CHECK(info.always == 0);
      CHECK(info.resolution >= 8);
      CHECK(info.longest * 8 <= n);  // one cell over a whole face held all 5120
    }
  }
}

TEST_CASE("light buffer: axis and face-diagonal directions, tiny scale") {
  // a box of quads around the light, scaled by 1e-3: rays along the axes and along |dx| = |dy|
  // (the edges between cube faces) and |dx| = |dy| = |dz| (the corners)
  Soup soup;
  const double s = 1e-3;
  for (int axis = 0; axis < 3; ++axis) {
    for (const double side : {-1.0, 1.0}) {
      for (int i = 0; i < 8; ++i) {
        for (int j = 0; j < 8; ++j) {
          float q[4][3];
          for (int c = 0; c < 4; ++c) {
            const double u = -1.0 + 0.25 * (i + (c == 1 || c == 2)), w = -1.0 + 0.25 * (j + (c >= 2));
            q[c][axis] = F(side * s);
            q[c][(axis + 1) % 3] = F(u * s);
            q[c][(axis + 2) % 3] = F(w * s);
          }
          soup.AddTriangle(q[0], q[1], q[2]);
          soup.AddTriangle(q[0], q[2], q[3]);
        }
      }
    }
  }
  const Accel accel(soup.view());
  const float light[3] = {0.0f, 0.0f, 0.0f};
  const LightBuffer lb(accel, light);
  std::vector<Ray> rays;
  const float e = 1e-3f;
  for (int x = -1; x <= 1; ++x) {
    for (int y = -1; y <= 1; ++y) {
      for (int z = -1; z <= 1; ++z) {
        if (x == 0 && y == 0 && z == 0) continue;
        for (const float len : {1.0f, 0.5f, 2.0f}) {
          for (const float tmax : {0.999f, 1.0f, kInf}) {
            Ray r;
            r.o[0] = r.o[1] = r.o[2] = 0.0f;
            r.d[0] = x * e * len, r.d[1] = y * e * len, r.d[2] = z * e * len;
            r.tmax = tmax;
            rays.push_back(r);
            // just off the diagonal, both ways
            Ray q = r;
            q.d[0] = std::nextafter(q.d[0], 1.0f);
            rays.push_back(q);
            q.d[0] = std::nextafter(r.d[0], -1.0f);
            rays.push_back(q);
          }
        }
      }
    }
  }
  Rng rng(11);
  const std::vector<Ray> more = LightRays(soup.view(), light, rng, 1000);
  rays.insert(rays.end(), more.begin(), more.end());
  const size_t occluded = CheckSame(accel, lb, rays, "box of quads");
  CHECK(occluded > rays.size() / 2);
}

TEST_CASE("light buffer: triangles that end on the edge between two cube faces") {
  // seen from the light at the origin, the plane x = y separates faces +x and +y: triangles
  // whose vertices lie on it or within 1e-7 .. 1e-3 of it on either side, and rays through
  // their vertices, edges and interiors, along the edge and one float step off it
  Soup soup;
  const double offsets[] = {0.0, 1e-7, -1e-7, 1e-6, -1e-6, 1e-5, -1e-5, 1e-4, -1e-4, 1e-3, -1e-3};
  for (const double off : offsets) {
    for (int k = 0; k < 8; ++k) {
      const double z = -0.4 + 0.1 * k, x = 2.0 + 0.05 * k;
      const float a[3] = {F(x), F(x * (1.0 + off)), F(z)};
      const float b[3] = {F(x + 0.3), F((x + 0.3) * (1.0 + off) + 0.2), F(z + 0.05)};
      const float c[3] = {F(x - 0.1), F((x - 0.1) * (1.0 + off) + 0.15), F(z + 0.1)};
      soup.AddTriangle(a, b, c);
      const float e[3] = {F(x * (1.0 + off) + 0.2), F(x + 0.3), F(z + 0.05)};  // x > y side
      soup.AddTriangle(a, e, c);
    }
  }
  const Accel accel(soup.view());
  const float light[3] = {0.0f, 0.0f, 0.0f};
  const LightBuffer lb(accel, light);
  Rng rng(17);
  std::vector<Ray> rays = LightRays(soup.view(), light, rng, 1000);
  for (int k = 0; k < 2000; ++k) {  // directions on and next to the x = y plane
    Ray r;
    r.o[0] = r.o[1] = r.o[2] = 0.0f;
    r.d[0] = rng.UniformF(1.5, 3.0);
    r.d[1] = r.d[0];
    r.d[2] = rng.UniformF(-0.6, 0.6);
    if (k % 3 == 1) r.d[1] = std::nextafter(r.d[1], 10.0f);
    if (k % 3 == 2) r.d[1] = std::nextafter(r.d[1], -10.0f);
    r.tmax = kInf;
    rays.push_back(r);
  }
  // towards each vertex, moved onto the plane (|dx| = |dy|: the ray picks face +x) and one and
  // two float steps either side
  const MeshView m = soup.view();
  for (size_t v = 0; v < m.num_vertices; ++v) {
    const float* p = m.positions + 3 * v;
    for (int step = -2; step <= 2; ++step) {
      Ray r;
      r.o[0] = r.o[1] = r.o[2] = 0.0f;
      r.d[0] = p[0];
      r.d[1] = p[0];
      for (int k = 0; k < std::abs(step); ++k) r.d[1] = std::nextafter(r.d[1], step > 0 ? 10.0f : -10.0f);
      r.d[2] = p[2];
      r.tmax = kInf;
      rays.push_back(r);
      r.d[0] = p[1];  // and onto the plane the other way
      r.d[1] = p[1];
      for (int k = 0; k < std::abs(step); ++k) r.d[0] = std::nextafter(r.d[0], step > 0 ? 10.0f : -10.0f);
      rays.push_back(r);
    }
  }
  const size_t occluded = CheckSame(accel, lb, rays, "face edge");
  CHECK(occluded > 0);
}

// Coherent rays (a vector's worth in a row, so a walk's box of face coordinates is small) aimed
// at points on every edge and at every vertex of `mesh`, moved off the edge by a relative
// offset of 0 to 1e-3 both ways, with tmax 1 (the target) and +inf: where the edge-plane cull
// (light_buffer.h) decides hardest.
std::vector<Ray> EdgeRays(const MeshView& mesh, const float light[3], size_t max_tris) {
  std::vector<Ray> rays;
  const size_t step = std::max<size_t>(1, mesh.num_triangles / max_tris);
  const double offsets[] = {0.0, 1e-7, -1e-7, 1e-6, -1e-6, 1e-5, -1e-5, 1e-3, -1e-3};
  for (size_t i = 0; i < mesh.num_triangles; i += step) {
    double p[3][3];
    for (int k = 0; k < 3; ++k) {
      const float* v = mesh.positions + size_t{mesh.indices[3 * i + k]} * mesh.stride;
      for (int a = 0; a < 3; ++a) p[k][a] = v[a];
    }
    double centre[3];
    for (int a = 0; a < 3; ++a) centre[a] = (p[0][a] + p[1][a] + p[2][a]) / 3.0;
    for (int e = 0; e < 3; ++e) {
      const double* a = p[e];
      const double* b = p[(e + 1) % 3];
      for (const double off : offsets) {
        for (int k = 0; k <= 3; ++k) {  // the vertex, points along the edge
          const double s = k / 4.0;
          Ray r;
          for (int c = 0; c < 3; ++c) {
            const double on = a[c] + s * (b[c] - a[c]);
            r.o[c] = light[c];
            r.d[c] = F(on + off * (on - centre[c]) - double(light[c]));  // off > 0: outside
          }
          r.tmin = 0.0f;
          r.tmax = (k & 1) ? 1.0f : kInf;
          rays.push_back(r);
        }
      }
    }
  }
  return rays;
}

TEST_CASE("light buffer: coherent rays at edges and vertices (the edge-plane cull)") {
  // small triangles far from the light (the planes' scale R_b R_c is large against their
  // normals), the same sphere at 1.5e5, and large triangles around the light that cross cube
  // faces (clipped rectangles: planes with the 2 R bound)
  struct Case {
    const char* what;
    double radius, distance, offset;
    int levels;
  };
  const Case cases[] = {{"small sphere 10 away", 0.1, 10.0, 0.0, 3},
                        {"small sphere 1e3 away", 0.1, 1e3, 0.0, 3},
                        {"sphere at 1.5e5, light 2 away", 1.0, 2.0, 1.5e5, 2},
                        {"sphere around the light", 3.0, 0.0, 0.0, 1}};
  for (const Case& c : cases) {
    const Icosphere s = MakeIcosphere(c.levels, c.radius, {c.offset, c.offset, c.offset}, 0);
    Soup soup;
    for (const auto& t : s.tri) soup.AddTriangle(s.v[t[0]].data(), s.v[t[1]].data(), s.v[t[2]].data());
    const Accel accel(soup.view());
    const float light[3] = {F(c.offset + c.distance), F(c.offset + 0.3 * c.distance),
                            F(c.offset - 0.2 * c.distance + 0.01)};
    const LightBuffer lb(accel, light);
    const std::vector<Ray> rays = EdgeRays(soup.view(), light, 400);
    const size_t occluded = CheckSame(accel, lb, rays, c.what);
    MESSAGE(std::string(c.what), ": ", rays.size(), " rays, ", occluded, " occluded");
    CHECK(occluded > 0);
    CHECK(occluded < rays.size());
  }
}

TEST_CASE("light buffer: the edge-plane cull skips rays inside a rectangle but off the triangle") {
  // one right triangle on face +z: rays into the half of its rectangle beyond the hypotenuse
  // pass the rectangle test; the planes must reject them without a triangle test, and rays
  // into the triangle must still be tested and hit
  Soup soup;
  const float a[3] = {-1.0f, -1.0f, 5.0f}, b[3] = {1.0f, -1.0f, 5.0f}, c[3] = {-1.0f, 1.0f, 5.0f};
  soup.AddTriangle(a, b, c);
  const Accel accel(soup.view());
  const float light[3] = {0.0f, 0.0f, 0.0f};
  const LightBuffer lb(accel, light);
  const auto rays_at = [&](double x0, double y0) {
    std::vector<Ray> rays;
    for (int i = 0; i < 64; ++i) {  // a patch of 8 x 8 directions
      Ray r;
      r.o[0] = r.o[1] = r.o[2] = 0.0f;
      r.d[0] = F(x0 + 0.01 * (i % 8)), r.d[1] = F(y0 + 0.01 * (i / 8)), r.d[2] = 10.0f;
      r.tmax = kInf;
      rays.push_back(r);
    }
    return rays;
  };
  const std::vector<Ray> off = rays_at(0.5, 0.5), on = rays_at(-0.9, -0.9);
  for (const auto* set : {&off, &on}) {
    RayStream st = MakeStream(*set);
    test::ForEachTarget([&](const char* target) {
      std::vector<int32_t> got(set->size() + 16, -7);
      TraceStats stats;
      lb.Occluded(st.view(), got.data(), &stats);
      size_t hits = 0;
      for (size_t i = 0; i < set->size(); ++i) hits += got[i] != 0;
      INFO(target);
      if (set == &off) {
        CHECK(hits == 0);
        CHECK(stats.triangle_tests == 0);
      } else {
        CHECK(hits == set->size());
        CHECK(stats.triangle_tests == set->size());
      }
    });
  }
  CheckSame(accel, lb, off, "off the triangle");
  CheckSame(accel, lb, on, "on the triangle");
}

TEST_CASE("light buffer: built on several threads at once (one build scratch per thread)") {
  // four lights built and rebuilt concurrently give the buffers built one after another: the
  // same sizes and the same occlusion on the same rays
  const Scene scene = LoadScene("cornell");
  const Accel accel(scene.mesh());
  const std::vector<float> p = Positions(scene);
  std::vector<std::array<float, 3>> lights;
  for (int l = 0; l < 4; ++l) {
    lights.push_back({F(0.5 * (p[0] + p[3]) + 0.01 * l), F(0.5 * (p[1] + p[4]) + 0.01),
                      F(p[2] + 0.01 + 0.02 * l)});
  }
  std::vector<LightBuffer> serial;
  for (const auto& l : lights) serial.emplace_back(accel, l.data());
  std::vector<std::optional<LightBuffer>> parallel(lights.size());
  std::vector<std::thread> threads;
  for (size_t t = 0; t < lights.size(); ++t) {
    threads.emplace_back([&, t] {
      parallel[t].emplace(accel, lights[(t + 1) % lights.size()].data());  // another light first
      parallel[t]->Rebuild(accel, lights[t].data());
    });
  }
  for (std::thread& th : threads) th.join();
  Rng rng(23);
  for (size_t l = 0; l < lights.size(); ++l) {
    const LightBufferInfo a = serial[l].Info(), b = parallel[l]->Info();
    CHECK(a.cells == b.cells);
    CHECK(a.references == b.references);
    CHECK(a.longest == b.longest);
    const std::vector<Ray> rays = LightRays(scene.mesh(), lights[l].data(), rng, 200);
    RayStream st = MakeStream(rays);
    std::vector<int32_t> want(rays.size() + 16), got(rays.size() + 16);
    serial[l].Occluded(st.view(), want.data());
    parallel[l]->Occluded(st.view(), got.data());
    CHECK(std::equal(want.begin(), want.begin() + long(rays.size()), got.begin()));
  }
}

TEST_CASE("light buffer: concurrent first buffers and buffers rebuilt after Accel::Rebuild") {
  // the references hold triangle ids into the Accel's interleaved vertices (TriangleSoA::verts):
  // four first buffers built at once read them (TSan runs this) and add nothing to the Accel's
  // bytes; Accel::Rebuild of a moved mesh makes the rebuilt buffers test the moved triangles
  const Scene scene = LoadScene("cornell");
  const MeshView mesh = scene.mesh();
  std::vector<float> p = Positions(scene);
  MeshView view = mesh;
  view.positions = p.data();
  view.stride = 3;
  Accel accel(view);
  const size_t bare = accel.Info().bytes;
  std::vector<std::array<float, 3>> lights;
  for (int l = 0; l < 4; ++l) {
    lights.push_back({F(0.5 * (p[0] + p[3]) + 0.01 * l), F(0.5 * (p[1] + p[4]) + 0.01),
                      F(p[2] + 0.01 + 0.02 * l)});
  }
  std::vector<std::optional<LightBuffer>> buffers(lights.size());
  std::vector<std::thread> threads;
  for (size_t t = 0; t < lights.size(); ++t) {
    threads.emplace_back([&, t] { buffers[t].emplace(accel, lights[t].data()); });
  }
  for (std::thread& th : threads) th.join();
  CHECK(accel.Info().bytes == bare);
  Rng rng(29);
  for (size_t l = 0; l < lights.size(); ++l) {
    CheckSame(accel, *buffers[l], LightRays(view, lights[l].data(), rng, 300), "concurrent first");
  }
  for (size_t i = 0; i < p.size(); i += 3) p[i] += 0.125f;  // the mesh moves along x
  accel.Rebuild(view);
  CHECK(accel.Info().bytes == bare);
  for (size_t l = 0; l < lights.size(); ++l) {
    buffers[l]->Rebuild(accel, lights[l].data());
    CheckSame(accel, *buffers[l], LightRays(view, lights[l].data(), rng, 300), "moved mesh");
  }
}

TEST_CASE("light buffer: invalid rays, tmin < 0, rays not from the light, empty mesh") {
  const Scene scene = LoadScene("cornell");
  const Accel accel(scene.mesh());
  const std::vector<float> p = Positions(scene);
  const float light[3] = {F(0.5 * (p[0] + p[3])), F(0.5 * (p[1] + p[4]) + 0.01), F(p[2] + 0.01)};
  const LightBuffer lb(accel, light);
  Rng rng(5);
  std::vector<Ray> rays = LightRays(scene.mesh(), light, rng, 300);
  const size_t n = rays.size();
  for (size_t i = 0; i < n; i += 3) {
    Ray r = rays[i];
    switch (i % 7) {
      case 0: r.d[1] = kNaN; break;
      case 1: r.d[0] = r.d[1] = r.d[2] = 0.0f; break;
      case 2: r.d[2] = kInf; break;
      case 3: r.tmin = -1.0f; break;              // behind the light too: the Accel's
      case 4: r.o[0] = std::nextafter(r.o[0], kInf); break;  // not from the light
      case 5: r.o[1] = kNaN; break;
      default: r.tmin = kNaN; break;
    }
    rays.push_back(r);
    rays.insert(rays.begin() + long(i), r);  // mixed into runs of light rays
  }
  CheckSame(accel, lb, rays, "invalid and foreign rays");
  // an unaligned, unpadded stream of 37 rays (the public contract: any alignment, exact size)
  std::vector<float> a[8];
  for (auto& v : a) v.resize(38);
  for (size_t i = 0; i < 37; ++i) {
    const Ray& r = rays[i];
    const float f[8] = {r.o[0], r.o[1], r.o[2], r.d[0], r.d[1], r.d[2], r.tmin, r.tmax};
    for (int c = 0; c < 8; ++c) a[c][i + 1] = f[c];
  }
  RayStreamView v{};
  v.ox = a[0].data() + 1, v.oy = a[1].data() + 1, v.oz = a[2].data() + 1;
  v.dx = a[3].data() + 1, v.dy = a[4].data() + 1, v.dz = a[5].data() + 1;
  v.tmin = a[6].data() + 1, v.tmax = a[7].data() + 1;
  v.size = 37;
  std::vector<int32_t> got(38, -7), want(38, -7);
  lb.Occluded(v, got.data());
  accel.Occluded(v, want.data());
  CHECK(got == want);
  // errors
  CHECK_THROWS_AS(lb.Occluded(v, nullptr), Error);
  const float bad[3] = {0.0f, kNaN, 0.0f};
  CHECK_THROWS_AS(LightBuffer(accel, bad), Error);
  // an empty mesh never occludes
  const Accel none(MeshView{});
  const LightBuffer empty(none, light);
  CHECK(empty.Info().resolution == 0);
  std::vector<int32_t> out(rays.size() + 16, -7);
  RayStream s = MakeStream(rays);
  empty.Occluded(s.view(), out.data());
  for (size_t i = 0; i < rays.size(); ++i) CHECK(out[i] == 0);
}

TEST_CASE("light buffer: Rebuild for another light and another Accel, in place") {
  const Scene erw6 = LoadScene("erw6"), box = LoadScene("spherebox");
  const Accel a(erw6.mesh()), b(box.mesh());
  const float l1[3] = {0.0f, 2.5f, 0.0f}, l2[3] = {1.0f, 1.0f, -0.5f}, l3[3] = {0.0f, 9.0f, 0.0f};
  LightBuffer lb(a, l1);
  Rng rng(23);
  const std::vector<Ray> r1 = LightRays(erw6.mesh(), l1, rng, 2000);
  const std::vector<Ray> r2 = LightRays(erw6.mesh(), l2, rng, 2000);
  const std::vector<Ray> r3 = LightRays(box.mesh(), l3, rng, 2000);
  CheckSame(a, lb, r1, "built");
  lb.Rebuild(a, l2);  // another light, same Accel
  CheckSame(a, lb, r2, "rebuilt for another light");
  CHECK(lb.Info().references == LightBuffer(a, l2).Info().references);
  lb.Rebuild(b, l3);  // a larger scene: the arrays grow
  CheckSame(b, lb, r3, "rebuilt for another Accel");
  lb.Rebuild(a, l1);  // smaller again: the arrays are kept
  CheckSame(a, lb, r1, "rebuilt back");
  const float bad[3] = {kNaN, 0.0f, 0.0f};
  CHECK_THROWS_AS(lb.Rebuild(a, bad), Error);
  CheckSame(a, lb, r1, "after a refused rebuild");  // the checks come first: still valid
  LightBuffer moved = std::move(lb);
  CHECK_THROWS_AS(lb.Rebuild(a, l1), Error);  // NOLINT(bugprone-use-after-move)
  CheckSame(a, moved, r1, "moved");
}

TEST_CASE("light buffer: references within budget for identical triangles and a long fan") {
  Soup same, fan;
  const float a[3] = {0.0f, 0.0f, 0.0f}, b[3] = {1.0f, 0.0f, 0.0f}, c[3] = {0.0f, 1.0f, 0.0f};
  for (int i = 0; i < 10000; ++i) same.AddTriangle(a, b, c);
  const int corners = 30000;
  const float centre[3] = {0.0f, 0.0f, 0.0f};
  for (int i = 0; i < corners; ++i) {
    const double t0 = 2 * M_PI * i / corners, t1 = 2 * M_PI * (i + 1) / corners;
    const float p[3] = {F(std::cos(t0)), F(std::sin(t0)), 0.0f};
    const float q[3] = {F(std::cos(t1)), F(std::sin(t1)), 0.0f};
    fan.AddTriangle(centre, p, q);
  }
  const std::vector<std::array<float, 3>> lights = {{0.25f, 0.25f, 0.5f}, {0.1f, 0.2f, -3.0f}};
  CheckScene(same.view(), lights, "10,000 identical triangles", 50);
  CheckScene(fan.view(), lights, "30,000-triangle fan", test::kSlowBuild ? 100 : 3000);
}

// Distance from p to triangle (a, b, c), in double: the closest point by the regions of the
// triangle's vertices, edges and face (Ericson, Real-Time Collision Detection, 5.1.5).
double PointTriangleDistance(const double p[3], const double a[3], const double b[3],
                             const double c[3]) {
  const auto sub = [](const double* x, const double* y, double* out) {
    for (int k = 0; k < 3; ++k) out[k] = x[k] - y[k];
  };
  const auto dot = [](const double* x, const double* y) {
    return x[0] * y[0] + x[1] * y[1] + x[2] * y[2];
  };
  const auto at = [&](double s, double t) {  // distance to a + s (b - a) + t (c - a)
    double q[3];
    for (int k = 0; k < 3; ++k) q[k] = a[k] + s * (b[k] - a[k]) + t * (c[k] - a[k]) - p[k];
    return std::sqrt(dot(q, q));
  };
  double ab[3], ac[3], ap[3], bp[3], cp[3];
  sub(b, a, ab), sub(c, a, ac), sub(p, a, ap), sub(p, b, bp), sub(p, c, cp);
  const double d1 = dot(ab, ap), d2 = dot(ac, ap);
  if (d1 <= 0 && d2 <= 0) return at(0, 0);
  const double d3 = dot(ab, bp), d4 = dot(ac, bp);
  if (d3 >= 0 && d4 <= d3) return at(1, 0);
  const double vc = d1 * d4 - d3 * d2;
  if (vc <= 0 && d1 >= 0 && d3 <= 0) return at(d1 / (d1 - d3), 0);
  const double d5 = dot(ab, cp), d6 = dot(ac, cp);
  if (d6 >= 0 && d5 <= d6) return at(0, 1);
  const double vb = d5 * d2 - d1 * d6;
  if (vb <= 0 && d2 >= 0 && d6 <= 0) return at(0, d2 / (d2 - d6));
  const double va = d3 * d6 - d5 * d4;
  if (va <= 0 && d4 - d3 >= 0 && d5 - d6 >= 0) {
    const double w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
    return at(1 - w, w);
  }
  const double denom = 1 / (va + vb + vc);
  return at(vb * denom, vc * denom);
}

TEST_CASE("light buffer: every list ascends in reach, every reach is at most its distance") {
  Rng rng(11);
  const Soup soup = test::RandomSoup(rng, 3000, -1.0, 1.0, 0.2);
  const Scene erw6 = LoadScene("erw6");
  struct Case {
    const char* name;
    MeshView mesh;
    std::vector<std::array<float, 3>> lights;
  };
  const Case cases[] = {
      {"random soup", soup.view(), {{0.0f, 0.0f, 0.0f}, {0.3f, -2.0f, 0.7f}, {5.0f, 5.0f, 5.0f}}},
      {"erw6", erw6.mesh(), {{F(erw6.lights[0].position.x), F(erw6.lights[0].position.y),
                              F(erw6.lights[0].position.z)}}},
  };
  for (const Case& c : cases) {
    TriangleSoA tris;
    BuildTriangleSoA(c.mesh, &tris);
    for (const auto& light : c.lights) {
      LightBufferData lb;
      BuildLightBuffer(tris, light.data(), kLightCellsPerTriangle, &lb);
      REQUIRE(!lb.empty());
      const double l[3] = {light[0], light[1], light[2]};
      size_t unsorted = 0, beyond = 0;
      for (size_t cell = 0; cell <= lb.num_cells; ++cell) {  // num_cells: the list every ray reads
        for (uint32_t j = lb.cell_begin[cell]; j < lb.cell_begin[cell + 1]; ++j) {
          if (j + 1 < lb.cell_begin[cell + 1] && lb.reach[j + 1] < lb.reach[j]) ++unsorted;
          const float* v = lb.Vertices(j);
          const double a[3] = {v[0], v[1], v[2]}, b[3] = {v[3], v[4], v[5]};
          const double cc[3] = {v[6], v[7], v[8]};
          if (double(lb.reach[j]) > PointTriangleDistance(l, a, b, cc)) ++beyond;
        }
      }
      INFO(c.name, ", light (", light[0], ", ", light[1], ", ", light[2], "): ", lb.num_refs,
           " references in ", lb.num_cells, " cells");
      CHECK(lb.num_refs > 0);
      CHECK(unsorted == 0);
      CHECK(beyond == 0);
    }
  }
}

TEST_CASE("light buffer: shared scenes, the benchmark light") {
  for (const char* name : {"bunny", "sponza"}) {
    if (!test::HaveSharedScene(name == std::string("bunny") ? "bunny/bun_zipper.ply"
                                                             : "sponza/sponza.obj")) {
      continue;
    }
    const Scene scene = LoadScene(name);
    const MeshView mesh = scene.mesh();
    float lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
    for (size_t v = 0; v < mesh.num_vertices; ++v) {
      for (int k = 0; k < 3; ++k) {
        lo[k] = std::min(lo[k], mesh.positions[v * mesh.stride + k]);
        hi[k] = std::max(hi[k], mesh.positions[v * mesh.stride + k]);
      }
    }
    const std::vector<std::array<float, 3>> lights = {
        {F(0.5 * (lo[0] + hi[0])), F(lo[1] + 0.95 * (hi[1] - lo[1])), F(0.5 * (lo[2] + hi[2]))}};
    CheckScene(mesh, lights, name, test::kSlowBuild ? 2000 : 20000);
  }
}

}  // namespace
}  // namespace rs
