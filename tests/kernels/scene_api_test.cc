// rs::TraceScene, rs::RayBuffer / rs::HitBuffer (include/raystream/raystream.h) and the scene part
// of the C API: hits of a scene of several geometries (16/32-bit indices, byte strides, shared and
// copied buffers, masks, instances) against a double-precision oracle and bit-identical on every
// Highway target; updates equal a fresh build; an instance equals its geometry pre-transformed;
// every misuse is an rs::Error or an error code.
#include <doctest/doctest.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <random>
#include <string>
#include <vector>

#include "include/raystream/raystream.h"
#include "include/raystream/raystream_c.h"
#include "tests/test_util.h"

namespace rs {
namespace {

constexpr float kInf = std::numeric_limits<float>::infinity();

// Möller-Trumbore in double: t, u, v of the ray's line and the triangle's plane; false if
// parallel. (The oracle: the kernels' watertight float test must agree away from edges.)
bool OracleHit(const double o[3], const double d[3], const double p[3][3], double* t, double* u,
               double* v) {
  double e1[3], e2[3], s[3];
  for (int a = 0; a < 3; ++a) e1[a] = p[1][a] - p[0][a], e2[a] = p[2][a] - p[0][a], s[a] = o[a] - p[0][a];
  const double pv[3] = {d[1] * e2[2] - d[2] * e2[1], d[2] * e2[0] - d[0] * e2[2],
                        d[0] * e2[1] - d[1] * e2[0]};
  const double det = e1[0] * pv[0] + e1[1] * pv[1] + e1[2] * pv[2];
  if (det == 0.0) return false;
  const double q[3] = {s[1] * e1[2] - s[2] * e1[1], s[2] * e1[0] - s[0] * e1[2],
                       s[0] * e1[1] - s[1] * e1[0]};
  *u = (s[0] * pv[0] + s[1] * pv[1] + s[2] * pv[2]) / det;
  *v = (d[0] * q[0] + d[1] * q[1] + d[2] * q[2]) / det;
  *t = (e2[0] * q[0] + e2[1] * q[1] + e2[2] * q[2]) / det;
  return true;
}

void Cross(const double a[3], const double b[3], double c[3]) {
  c[0] = a[1] * b[2] - a[2] * b[1], c[1] = a[2] * b[0] - a[0] * b[2], c[2] = a[0] * b[1] - a[1] * b[0];
}

// A geometry as the test holds it: positions with a stride (floats), 16- or 32-bit indices.
struct TestGeometry {
  std::vector<float> positions;  // stride floats per vertex
  size_t stride = 3;
  std::vector<uint32_t> idx32;
  std::vector<uint16_t> idx16;
  bool use16 = false;
  uint32_t mask = ~0u;
  BufferMode mode = BufferMode::kCopy;
  bool instance_only = false;

  size_t num_vertices() const { return positions.size() / stride; }
  size_t num_triangles() const { return (use16 ? idx16.size() : idx32.size()) / 3; }
  uint32_t Index(size_t i) const { return use16 ? idx16[i] : idx32[i]; }
  void AddVertex(float x, float y, float z) {
    positions.insert(positions.end(), {x, y, z});
    for (size_t k = 3; k < stride; ++k) positions.push_back(-7.0f);  // padding, never read
  }
  void AddTriangle(uint32_t a, uint32_t b, uint32_t c) {
    if (use16) {
      idx16.insert(idx16.end(), {uint16_t(a), uint16_t(b), uint16_t(c)});
    } else {
      idx32.insert(idx32.end(), {a, b, c});
    }
  }
  GeometryDesc Desc() const {
    GeometryDesc d;
    d.positions = positions.data();
    d.num_vertices = num_vertices();
    d.stride_bytes = stride * sizeof(float);
    d.indices = use16 ? static_cast<const void*>(idx16.data()) : idx32.data();
    d.index_type = use16 ? IndexType::kUInt16 : IndexType::kUInt32;
    d.num_triangles = num_triangles();
    d.mask = mask;
    d.mode = mode;
    d.instance_only = instance_only;
    return d;
  }
};

TestGeometry Box(float cx, float cy, float cz, float r, size_t stride, bool use16) {
  TestGeometry g;
  g.stride = stride, g.use16 = use16;
  for (int i = 0; i < 8; ++i) {
    g.AddVertex(cx + (i & 1 ? r : -r), cy + (i & 2 ? r : -r), cz + (i & 4 ? r : -r));
  }
  const uint32_t faces[6][4] = {{0, 1, 3, 2}, {4, 6, 7, 5}, {0, 4, 5, 1},
                                {2, 3, 7, 6}, {0, 2, 6, 4}, {1, 5, 7, 3}};
  for (const auto& f : faces) g.AddTriangle(f[0], f[1], f[2]), g.AddTriangle(f[0], f[2], f[3]);
  return g;
}

TestGeometry Terrain(size_t n, size_t stride, bool use16) {  // z = wavy height over [-4, 4]^2
  TestGeometry g;
  g.stride = stride, g.use16 = use16;
  for (size_t y = 0; y <= n; ++y) {
    for (size_t x = 0; x <= n; ++x) {
      const float fx = -4.f + 8.f * float(x) / float(n), fy = -4.f + 8.f * float(y) / float(n);
      g.AddVertex(fx, fy, -2.f + 0.3f * std::sin(fx) * std::cos(fy));
    }
  }
  for (size_t y = 0; y < n; ++y) {
    for (size_t x = 0; x < n; ++x) {
      const uint32_t a = uint32_t(y * (n + 1) + x), b = a + 1, c = a + uint32_t(n) + 1, d = c + 1;
      g.AddTriangle(a, b, d), g.AddTriangle(a, d, c);
    }
  }
  return g;
}

TestGeometry Soup(std::mt19937& rng, size_t count, size_t stride, bool use16) {
  TestGeometry g;
  g.stride = stride, g.use16 = use16;
  std::uniform_real_distribution<float> c(-2.5f, 2.5f), e(-0.6f, 0.6f);
  for (size_t i = 0; i < count; ++i) {
    const float x = c(rng), y = c(rng), z = c(rng);
    for (int k = 0; k < 3; ++k) g.AddVertex(x + e(rng), y + e(rng), z + e(rng));
    g.AddTriangle(uint32_t(3 * i), uint32_t(3 * i + 1), uint32_t(3 * i + 2));
  }
  return g;
}

struct TestInstance {
  uint32_t geom;
  float m[12];
  uint32_t mask;
};

// A rotation about z by `a`, scaled by (sx, sy, sz), then translated.
TestInstance MakeInstance(uint32_t geom, float a, float sx, float sy, float sz, float tx, float ty,
                          float tz, uint32_t mask) {
  const float c = std::cos(a), s = std::sin(a);
  return TestInstance{geom, {c * sx, -s * sy, 0, tx, s * sx, c * sy, 0, ty, 0, 0, sz, tz}, mask};
}

struct TestScene {
  std::vector<TestGeometry> geoms;
  std::vector<TestInstance> insts;
  TraceScene Build(const BuildOptions& o = {}) const {
    TraceScene s(o);
    for (const auto& g : geoms) s.AttachGeometry(g.Desc());
    for (const auto& i : insts) s.AttachInstance(i.geom, i.m, i.mask);
    s.Commit();
    return s;
  }
};

// Several geometries: a terrain (32-bit indices, stride 12 B, copied, mask 1), a box (16-bit,
// stride 16 B, shared, mask 2), a soup (32-bit, stride 20 B, mask 4), a box only instanced
// (16-bit, stride 24 B) twice, with masks 8 and 16.
TestScene Mixed() {
  std::mt19937 rng(1234);
  TestScene s;
  s.geoms.push_back(Terrain(12, 3, false));
  s.geoms.back().mask = 1;
  s.geoms.push_back(Box(1.5f, -1.0f, 0.0f, 0.75f, 4, true));
  s.geoms.back().mask = 2, s.geoms.back().mode = BufferMode::kShared;
  s.geoms.push_back(Soup(rng, 60, 5, false));
  s.geoms.back().mask = 4;
  s.geoms.push_back(Box(0, 0, 0, 1.0f, 6, true));
  s.geoms.back().instance_only = true;
  s.insts.push_back(MakeInstance(3, 0.6f, 0.5f, 0.8f, 0.4f, -1.5f, 1.5f, 0.5f, 8));
  s.insts.push_back(MakeInstance(3, -1.1f, 0.3f, 0.3f, 0.9f, 2.0f, 2.0f, -0.5f, 16));
  return s;
}

struct Rays {
  std::vector<float> f[8];
  std::vector<uint32_t> mask, id;
  Rays(size_t n, uint32_t seed) : mask(n), id(n) {
    std::mt19937 rng(seed);
    std::uniform_real_distribution<float> u(-1.f, 1.f);
    const uint32_t masks[] = {~0u, 1, 2, 4, 8, 16, 6, 25, 0};
    for (auto& a : f) a.resize(n);
    for (size_t i = 0; i < n; ++i) {
      f[0][i] = 4 * u(rng), f[1][i] = 4 * u(rng), f[2][i] = 5 + u(rng);
      f[3][i] = u(rng) - 0.3f * f[0][i], f[4][i] = u(rng) - 0.3f * f[1][i];
      f[5][i] = -(2 + u(rng));
      f[6][i] = i % 7 == 3 ? 2.0f : 0.0f, f[7][i] = i % 11 == 5 ? 1.5f : kInf;
      mask[i] = masks[i % 9];
      id[i] = uint32_t(i);
    }
  }
  RayView View() const {
    return RayView{f[0].data(), f[1].data(), f[2].data(), f[3].data(), f[4].data(),
                   f[5].data(), f[6].data(), f[7].data(), mask.data(), id.data(), mask.size()};
  }
};

struct Hits {
  std::vector<float> t, u, v, nx, ny, nz;
  std::vector<int32_t> prim, geom, inst;
  explicit Hits(size_t n) : t(n), u(n), v(n), nx(n), ny(n), nz(n), prim(n), geom(n), inst(n) {}
  HitView View() {
    return HitView{t.data(),  u.data(),    v.data(),    nx.data(),   ny.data(),
                   nz.data(), prim.data(), geom.data(), inst.data(), t.size()};
  }
  bool operator==(const Hits& o) const {
    auto same = [](const auto& a, const auto& b) {
      return a.size() == b.size() && std::memcmp(a.data(), b.data(), a.size() * sizeof(a[0])) == 0;
    };
    return same(t, o.t) && same(u, o.u) && same(v, o.v) && same(nx, o.nx) && same(ny, o.ny) &&
           same(nz, o.nz) && same(prim, o.prim) && same(geom, o.geom) && same(inst, o.inst);
  }
};

// The oracle's closest hit of ray i (double, world space; instanced triangles transformed in
// double), and whether it is clear: away from edges (min barycentric >= 1e-3) and ahead of any
// other candidate by 1e-3 relative.
struct OracleResult {
  bool hit = false, clear = true;
  double t = INFINITY, u = 0, v = 0, ng[3] = {0, 0, 0};
  int32_t prim = -1, geom = -1, inst = -1;
};

OracleResult Oracle(const TestScene& s, const Rays& r, size_t i) {
  const double o[3] = {r.f[0][i], r.f[1][i], r.f[2][i]}, d[3] = {r.f[3][i], r.f[4][i], r.f[5][i]};
  const double tnear = r.f[6][i], tfar = r.f[7][i];
  OracleResult best;
  double second = INFINITY;
  bool near_edge_candidate = false;
  auto visit = [&](const TestGeometry& g, int32_t geom, const TestInstance* in, int32_t inst) {
    const uint32_t mask = in != nullptr ? in->mask : g.mask;
    if ((r.mask[i] & mask) == 0) return;
    for (size_t k = 0; k < g.num_triangles(); ++k) {
      double p[3][3], obj[3][3];
      for (int c = 0; c < 3; ++c) {
        const float* q = &g.positions[g.Index(3 * k + c) * g.stride];
        for (int a = 0; a < 3; ++a) obj[c][a] = q[a];
        for (int a = 0; a < 3; ++a) {
          p[c][a] = in == nullptr ? obj[c][a]
                                  : in->m[4 * a] * obj[c][0] + in->m[4 * a + 1] * obj[c][1] +
                                        in->m[4 * a + 2] * obj[c][2] + in->m[4 * a + 3];
        }
      }
      double t, u, v;
      if (!OracleHit(o, d, p, &t, &u, &v)) continue;
      const double mb = std::min({u, v, 1 - u - v});
      if (!(t > tnear && t <= tfar)) continue;
      if (mb < -1e-3) continue;
      if (mb < 1e-3) {
        near_edge_candidate = true;
        continue;
      }
      if (t < best.t) {
        second = best.t;
        best.hit = true, best.t = t, best.u = u, best.v = v;
        best.prim = int32_t(k), best.geom = geom, best.inst = inst;
        double e1[3], e2[3];
        for (int a = 0; a < 3; ++a) e1[a] = obj[1][a] - obj[0][a], e2[a] = obj[2][a] - obj[0][a];
        double n[3];
        Cross(e1, e2, n);
        if (in == nullptr) {
          std::copy(n, n + 3, best.ng);
        } else {  // inverse transpose of the 3x3 part: cofactor matrix / det
          const float* m = in->m;
          const double A[3][3] = {{m[0], m[1], m[2]}, {m[4], m[5], m[6]}, {m[8], m[9], m[10]}};
          double cof[3][3];
          for (int row = 0; row < 3; ++row) {
            for (int col = 0; col < 3; ++col) {
              const int r1 = (row + 1) % 3, r2 = (row + 2) % 3, c1 = (col + 1) % 3, c2 = (col + 2) % 3;
              cof[row][col] = A[r1][c1] * A[r2][c2] - A[r1][c2] * A[r2][c1];
            }
          }
          const double det = A[0][0] * cof[0][0] + A[0][1] * cof[0][1] + A[0][2] * cof[0][2];
          for (int row = 0; row < 3; ++row) {
            best.ng[row] = (cof[row][0] * n[0] + cof[row][1] * n[1] + cof[row][2] * n[2]) / det;
          }
        }
      } else {
        second = std::min(second, t);
      }
    }
  };
  for (size_t g = 0; g < s.geoms.size(); ++g) {
    if (!s.geoms[g].instance_only) visit(s.geoms[g], int32_t(g), nullptr, -1);
  }
  for (size_t k = 0; k < s.insts.size(); ++k) {
    visit(s.geoms[s.insts[k].geom], int32_t(s.insts[k].geom), &s.insts[k], int32_t(k));
  }
  best.clear = !(second - best.t <= 1e-3 * std::fabs(best.t) + 1e-9) &&
               !(near_edge_candidate);
  return best;
}

TEST_CASE("scene of several geometries and instances vs the double oracle, every target") {
  const TestScene ts = Mixed();
  const Rays rays(3000, 77);
  const size_t n = rays.mask.size();
  std::vector<OracleResult> want(n);
  for (size_t i = 0; i < n; ++i) want[i] = Oracle(ts, rays, i);
  Hits first(n);
  std::vector<int32_t> first_occ(n);
  bool have_first = false;
  test::ForEachTarget([&](const char* target) {
    INFO("target: ", target);
    const TraceScene scene = ts.Build();
    Hits h(n);
    scene.Intersect(rays.View(), h.View());
    std::vector<int32_t> occ(n, 7);
    scene.Occluded(rays.View(), occ.data());
    size_t checked = 0, hits = 0, inst_hits = 0, geoms_seen = 0;
    bool seen[4] = {};
    for (size_t i = 0; i < n; ++i) {
      CAPTURE(i);
      CHECK(occ[i] == (h.geom[i] >= 0 ? 1 : 0));
      if (rays.mask[i] == 0) CHECK(h.geom[i] == -1);
      const OracleResult& w = want[i];
      if (!w.clear) continue;
      ++checked;
      REQUIRE(h.geom[i] == w.geom);
      CHECK(h.inst[i] == w.inst);
      CHECK(h.prim[i] == w.prim);
      if (!w.hit) {
        CHECK(h.t[i] == kInf);
        CHECK(h.nx[i] == 0.0f);
        continue;
      }
      ++hits;
      if (w.inst >= 0) ++inst_hits;
      seen[w.geom] = true;
      // Direct geometry: the float test's t within 1e-5 relative; instances add the rounding of
      // the ray transform (1e-4 relative on t, 1e-4 absolute on u, v).
      const double tol = w.inst >= 0 ? 1e-4 : 1e-5;
      CHECK(std::fabs(h.t[i] - w.t) <= tol * w.t);
      CHECK(std::fabs(h.u[i] - w.u) <= 10 * tol);
      CHECK(std::fabs(h.v[i] - w.v) <= 10 * tol);
      const double len = std::sqrt(w.ng[0] * w.ng[0] + w.ng[1] * w.ng[1] + w.ng[2] * w.ng[2]);
      CHECK(std::fabs(h.nx[i] - w.ng[0]) <= 1e-5 * len);
      CHECK(std::fabs(h.ny[i] - w.ng[1]) <= 1e-5 * len);
      CHECK(std::fabs(h.nz[i] - w.ng[2]) <= 1e-5 * len);
    }
    for (const bool b : seen) geoms_seen += b ? 1 : 0;
    CHECK(checked > n * 8 / 10);
    CHECK(hits > n / 5);
    CHECK(inst_hits > 20);
    CHECK(geoms_seen == 4);
    if (!have_first) {
      first = h, first_occ = occ, have_first = true;
    } else {
      CHECK(h == first);  // bit-identical across targets
      CHECK(occ == first_occ);
    }
  });
}

TEST_CASE("RayBuffer / HitBuffer: aligned, padded, defaults; any ray count traces like exact arrays") {
  const TestScene ts = Mixed();
  const TraceScene scene = ts.Build();
  for (size_t n = 0; n <= 70; n += (n < 20 ? 1 : 9)) {
    CAPTURE(n);
    RayBuffer rb(n);
    HitBuffer hb(n);
    CHECK(rb.size() == n);
    for (float* p : {rb.ox(), rb.oy(), rb.oz(), rb.dx(), rb.dy(), rb.dz(), rb.tnear(), rb.tfar()}) {
      CHECK(reinterpret_cast<uintptr_t>(p) % kStreamAlign == 0);
    }
    CHECK(reinterpret_cast<uintptr_t>(rb.mask()) % kStreamAlign == 0);
    CHECK(reinterpret_cast<uintptr_t>(hb.inst()) % kStreamAlign == 0);
    for (size_t i = 0; i < PaddedSize(n); ++i) {
      CHECK(rb.tfar()[i] == kInf);
      CHECK(rb.mask()[i] == ~0u);
      CHECK(rb.id()[i] == i);
      CHECK(hb.geom()[i] == -1);
    }
    const Rays r(n, 5 + uint32_t(n));
    for (size_t i = 0; i < n; ++i) {
      float* dst[8] = {rb.ox(), rb.oy(), rb.oz(), rb.dx(), rb.dy(), rb.dz(), rb.tnear(), rb.tfar()};
      for (int a = 0; a < 8; ++a) dst[a][i] = r.f[a][i];
      rb.mask()[i] = r.mask[i];
    }
    scene.Intersect(rb.View(), hb.View());
    Hits exact(n);
    scene.Intersect(r.View(), exact.View());
    for (size_t i = 0; i < n; ++i) {
      CHECK(std::memcmp(&hb.t()[i], &exact.t[i], 4) == 0);
      CHECK(hb.prim()[i] == exact.prim[i]);
      CHECK(hb.geom()[i] == exact.geom[i]);
      CHECK(hb.inst()[i] == exact.inst[i]);
      CHECK(std::memcmp(&hb.ng_z()[i], &exact.nz[i], 4) == 0);
    }
    RayBuffer moved(std::move(rb));
    CHECK(moved.size() == n);
    CHECK(rb.size() == 0);  // NOLINT(bugprone-use-after-move): documented state
    HitBuffer hmoved;
    hmoved = std::move(hb);
    CHECK(hmoved.size() == n);
    CHECK(hb.size() == 0);  // NOLINT(bugprone-use-after-move)
  }
}

TEST_CASE("UpdateGeometry / ReplaceGeometry: equal to a fresh build of the edited scene") {
  TestScene ts = Mixed();
  const Rays rays(2000, 99);
  const size_t n = rays.mask.size();
  test::ForEachTarget([&](const char* target) {
    INFO("target: ", target);
    TestScene edited = ts;
    TraceScene scene = ts.Build();
    // Move the shared box (geometry 1) and the soup (copied, geometry 2).
    TestGeometry& box = edited.geoms[1];
    for (size_t v = 0; v < box.num_vertices(); ++v) {
      box.positions[v * box.stride + 2] += 0.5f, box.positions[v * box.stride] -= 0.25f;
    }
    TestGeometry& soup = edited.geoms[2];
    for (size_t v = 0; v < soup.num_vertices(); ++v) soup.positions[v * soup.stride + 1] *= 0.5f;
    scene.UpdateGeometry(1, box.positions.data(), box.stride * 4);
    // The soup from a packed copy (another stride than at attach time).
    std::vector<float> packed;
    for (size_t v = 0; v < soup.num_vertices(); ++v) {
      packed.insert(packed.end(), {soup.positions[v * soup.stride], soup.positions[v * soup.stride + 1],
                                   soup.positions[v * soup.stride + 2]});
    }
    scene.UpdateGeometry(2, packed.data(), 12);
    CHECK_THROWS_AS(scene.Intersect(rays.View(), Hits(n).View()), Error);  // not recommitted
    scene.Commit();
    packed.assign(packed.size(), NAN);  // kCopy: the scene holds its own copy
    Hits got(n), want(n);
    scene.Intersect(rays.View(), got.View());
    edited.Build().Intersect(rays.View(), want.View());
    CHECK(got == want);
    // Replace the terrain by a finer one with 16-bit indices.
    edited.geoms[0] = Terrain(20, 4, true);
    edited.geoms[0].mask = 1;
    scene.ReplaceGeometry(0, edited.geoms[0].Desc());
    scene.Commit();
    scene.Intersect(rays.View(), got.View());
    edited.Build().Intersect(rays.View(), want.View());
    CHECK(got == want);
    // A new instance transform.
    edited.insts[1] = MakeInstance(3, 0.2f, 0.6f, 0.6f, 0.6f, 1.0f, -2.0f, 0.0f, 16);
    scene.SetInstanceTransform(1, edited.insts[1].m);
    scene.Commit();
    scene.Intersect(rays.View(), got.View());
    edited.Build().Intersect(rays.View(), want.View());
    CHECK(got == want);
  });
}

TEST_CASE("an instance equals its geometry pre-transformed (within the transform's rounding)") {
  const TestGeometry box = Box(0.2f, -0.1f, 0.3f, 1.0f, 3, false);
  const TestInstance in = MakeInstance(0, 0.7f, 1.3f, 0.7f, 2.1f, 0.5f, -0.25f, -1.0f, ~0u);
  TestScene a;
  a.geoms.push_back(box);
  a.geoms.back().instance_only = true;
  a.insts.push_back(in);
  TestScene b;
  b.geoms.push_back(box);
  TestGeometry& pre = b.geoms.back();
  for (size_t v = 0; v < pre.num_vertices(); ++v) {
    double p[3];
    for (int r = 0; r < 3; ++r) {
      p[r] = double{in.m[4 * r]} * box.positions[3 * v] + double{in.m[4 * r + 1]} * box.positions[3 * v + 1] +
             double{in.m[4 * r + 2]} * box.positions[3 * v + 2] + in.m[4 * r + 3];
    }
    for (int r = 0; r < 3; ++r) pre.positions[3 * v + r] = float(p[r]);
  }
  const double det = in.m[0] * (double{in.m[5]} * in.m[10] - double{in.m[6]} * in.m[9]) -
                     in.m[1] * (double{in.m[4]} * in.m[10] - double{in.m[6]} * in.m[8]) +
                     in.m[2] * (double{in.m[4]} * in.m[9] - double{in.m[5]} * in.m[8]);
  const Rays rays(2000, 3);
  const size_t n = rays.mask.size();
  Hits ha(n), hb(n);
  a.Build().Intersect(rays.View(), ha.View());
  b.Build().Intersect(rays.View(), hb.View());
  size_t compared = 0;
  for (size_t i = 0; i < n; ++i) {
    CAPTURE(i);
    const OracleResult w = Oracle(b, rays, i);
    if (!w.clear) continue;
    ++compared;
    CHECK(ha.geom[i] == hb.geom[i]);
    if (hb.geom[i] < 0) continue;
    CHECK(ha.inst[i] == 0);
    CHECK(hb.inst[i] == -1);
    CHECK(ha.prim[i] == hb.prim[i]);
    // Stated tolerance: t within 1e-5 relative, u, v within 1e-4; Ng: the instance's inverse
    // transpose times det equals the pre-transformed cross product within 1e-5 of its length.
    CHECK(std::fabs(ha.t[i] - hb.t[i]) <= 1e-5 * hb.t[i]);
    CHECK(std::fabs(ha.u[i] - hb.u[i]) <= 1e-4);
    CHECK(std::fabs(ha.v[i] - hb.v[i]) <= 1e-4);
    const double len = std::sqrt(double{hb.nx[i]} * hb.nx[i] + double{hb.ny[i]} * hb.ny[i] +
                                 double{hb.nz[i]} * hb.nz[i]);
    CHECK(std::fabs(det * ha.nx[i] - hb.nx[i]) <= 1e-5 * len);
    CHECK(std::fabs(det * ha.ny[i] - hb.ny[i]) <= 1e-5 * len);
    CHECK(std::fabs(det * ha.nz[i] - hb.nz[i]) <= 1e-5 * len);
  }
  CHECK(compared > n / 2);
}

TEST_CASE("equal t: the lower geomID wins, a geometry beats an instance, then the lower primID") {
  // Two copies of the same quad: geometry 0, geometry 1 and an identity instance of 1.
  const float p[] = {0, 0, 0, 1, 0, 0, 1, 1, 0, 0, 1, 0};
  const uint32_t idx[] = {0, 1, 2, 0, 2, 3};
  GeometryDesc d;
  d.positions = p, d.num_vertices = 4, d.indices = idx, d.num_triangles = 2;
  const float identity[12] = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0};
  const float ox[] = {0.25f}, oy[] = {0.75f}, oz[] = {1}, dx[] = {0}, dy[] = {0}, dz[] = {-1};
  const float tn[] = {0}, tf[] = {kInf};
  const RayView r{ox, oy, oz, dx, dy, dz, tn, tf, nullptr, nullptr, 1};
  Hits h(1);
  {
    TraceScene s;
    s.AttachGeometry(d);
    s.AttachGeometry(d);
    s.AttachInstance(1, identity);
    s.Commit();
    s.Intersect(r, h.View());
    CHECK(h.geom[0] == 0);
    CHECK(h.inst[0] == -1);
    CHECK(h.prim[0] == 1);
    CHECK(h.t[0] == 1.0f);
    CHECK(h.nz[0] == 1.0f);  // (p1-p0)x(p2-p0) of triangle (0, 2, 3): (1,1,0)x(0,1,0)
  }
  {
    TraceScene s;
    d.instance_only = true;
    s.AttachGeometry(d);
    s.AttachInstance(0, identity);
    s.AttachInstance(0, identity);
    s.Commit();
    s.Intersect(r, h.View());
    CHECK(h.geom[0] == 0);
    CHECK(h.inst[0] == 0);
  }
}

TEST_CASE("watertight across geometries and across instances with one transform; NaN rays") {
  // A 16x16 grid of quads over [0, 1]^2 at z = 0: the lower triangles in geometry 0 (16-bit
  // indices), the upper ones in geometry 1 (32-bit, stride 16 B), so every diagonal and every
  // other edge is shared by two geometries.
  constexpr uint32_t kN = 16;
  TestGeometry lower, upper;
  lower.use16 = true, upper.stride = 4;
  for (uint32_t y = 0; y <= kN; ++y) {
    for (uint32_t x = 0; x <= kN; ++x) {
      lower.AddVertex(float(x) / kN, float(y) / kN, 0.0f);
      upper.AddVertex(float(x) / kN, float(y) / kN, 0.0f);
    }
  }
  for (uint32_t y = 0; y < kN; ++y) {
    for (uint32_t x = 0; x < kN; ++x) {
      const uint32_t a = y * (kN + 1) + x, b = a + 1, c = a + kN + 1, d = c + 1;
      lower.AddTriangle(a, b, d), upper.AddTriangle(a, d, c);
    }
  }
  // Rays from random origins above at vertices and points on edges (in float).
  std::mt19937 rng(8);
  std::uniform_real_distribution<float> u(0.0f, 1.0f);
  constexpr size_t kRays = 4000;
  Rays r(kRays, 1);
  for (size_t i = 0; i < kRays; ++i) {
    const float gx = float(1 + rng() % (kN - 1)) / kN, gy = float(1 + rng() % (kN - 1)) / kN;
    const float s = u(rng) / kN;
    float px = gx, py = gy;
    if (i % 3 == 1) px = gx + s, py = gy;       // horizontal edge
    if (i % 3 == 2) px = gx + s, py = gy + s;   // diagonal
    r.f[0][i] = u(rng) * 3 - 1, r.f[1][i] = u(rng) * 3 - 1, r.f[2][i] = 1 + u(rng);
    r.f[3][i] = px - r.f[0][i], r.f[4][i] = py - r.f[1][i], r.f[5][i] = -r.f[2][i];
    r.f[6][i] = 0, r.f[7][i] = kInf, r.mask[i] = ~0u;
  }
  const float xfm[12] = {0.8f, -0.6f, 0.0f, 3.0f, 0.6f, 0.8f, 0.0f, -1.0f, 0.0f, 0.0f, 2.0f, 0.5f};
  test::ForEachTarget([&](const char* target) {
    INFO("target: ", target);
    TestScene direct;
    direct.geoms = {lower, upper};
    Hits h(kRays);
    direct.Build().Intersect(r.View(), h.View());
    size_t misses = 0;
    for (size_t i = 0; i < kRays; ++i) misses += h.geom[i] < 0 ? 1 : 0;
    CHECK(misses == 0);
    // Both halves through instances with the same transform: the same object-space rays.
    TestScene inst;
    inst.geoms = {lower, upper};
    inst.geoms[0].instance_only = inst.geoms[1].instance_only = true;
    inst.insts.push_back(TestInstance{0, {}, ~0u});
    inst.insts.push_back(TestInstance{1, {}, ~0u});
    std::copy(xfm, xfm + 12, inst.insts[0].m), std::copy(xfm, xfm + 12, inst.insts[1].m);
    Rays w = r;  // the rays moved to world space (double, rounded)
    for (size_t i = 0; i < kRays; ++i) {
      for (int a = 0; a < 3; ++a) {
        w.f[a][i] = float(double{xfm[4 * a]} * r.f[0][i] + double{xfm[4 * a + 1]} * r.f[1][i] +
                          double{xfm[4 * a + 2]} * r.f[2][i] + xfm[4 * a + 3]);
        w.f[3 + a][i] = float(double{xfm[4 * a]} * r.f[3][i] + double{xfm[4 * a + 1]} * r.f[4][i] +
                              double{xfm[4 * a + 2]} * r.f[5][i]);
      }
    }
    inst.Build().Intersect(w.View(), h.View());
    misses = 0;
    for (size_t i = 0; i < kRays; ++i) misses += h.geom[i] < 0 ? 1 : 0;
    CHECK(misses == 0);
    // NaN / Inf rays never hit (and return).
    Rays bad = r;
    for (size_t i = 0; i < kRays; ++i) {
      const float v[] = {NAN, INFINITY, -INFINITY};
      bad.f[i % 6][i] = v[i % 3];
    }
    direct.Build().Intersect(bad.View(), h.View());
    std::vector<int32_t> occ(kRays);
    direct.Build().Occluded(bad.View(), occ.data());
    for (size_t i = 0; i < kRays; ++i) {
      CAPTURE(i);
      // An infinite origin or direction component, or NaN: no hit (as rs::Accel).
      CHECK(h.geom[i] == -1);
      CHECK(occ[i] == 0);
    }
  });
}

TEST_CASE("misuse of TraceScene is an rs::Error, never a crash") {
  const TestGeometry box = Box(0, 0, 0, 1, 3, true);
  const Rays rays(5, 1);
  Hits hits(5);
  const float identity[12] = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0};
  TraceScene s;
  CHECK_THROWS_WITH_AS(s.Intersect(rays.View(), hits.View()), doctest::Contains("never committed"), Error);
  std::vector<int32_t> occ(5);
  CHECK_THROWS_AS(s.Occluded(rays.View(), occ.data()), Error);
  const uint32_t g = s.AttachGeometry(box.Desc());
  s.Commit();
  s.Intersect(rays.View(), hits.View());
  s.AttachGeometry(box.Desc());  // attach after commit, no recommit
  CHECK_THROWS_WITH_AS(s.Intersect(rays.View(), hits.View()), doctest::Contains("edited"), Error);
  CHECK_THROWS_AS(s.Occluded(rays.View(), occ.data()), Error);
  s.Commit();
  // Bad ids.
  CHECK_THROWS_WITH_AS(s.UpdateGeometry(9, box.positions.data(), 12), doctest::Contains("no geometry 9"), Error);
  CHECK_THROWS_AS(s.ReplaceGeometry(2, box.Desc()), Error);
  CHECK_THROWS_AS(s.AttachInstance(5, identity), Error);
  CHECK_THROWS_AS(s.SetInstanceTransform(0, identity), Error);
  // Null arrays, bad strides and types, out-of-range indices.
  GeometryDesc d = box.Desc();
  d.positions = nullptr;
  CHECK_THROWS_WITH_AS(s.AttachGeometry(d), doctest::Contains("no positions"), Error);
  d = box.Desc(), d.indices = nullptr;
  CHECK_THROWS_WITH_AS(s.AttachGeometry(d), doctest::Contains("no indices"), Error);
  d = box.Desc(), d.stride_bytes = 8;
  CHECK_THROWS_AS(s.AttachGeometry(d), Error);
  d.stride_bytes = 13;
  CHECK_THROWS_AS(s.AttachGeometry(d), Error);
  d = box.Desc(), d.index_type = static_cast<IndexType>(5);
  CHECK_THROWS_AS(s.AttachGeometry(d), Error);
  d = box.Desc(), d.mode = static_cast<BufferMode>(5);
  CHECK_THROWS_AS(s.AttachGeometry(d), Error);
  d = box.Desc(), d.num_vertices = 7;  // index 7 out of range (16-bit)
  CHECK_THROWS_WITH_AS(s.AttachGeometry(d), doctest::Contains("out of range"), Error);
  const uint32_t big[] = {0, 1, 1u << 30};
  d = box.Desc(), d.indices = big, d.index_type = IndexType::kUInt32, d.num_triangles = 1;
  CHECK_THROWS_WITH_AS(s.AttachGeometry(d), doctest::Contains("out of range"), Error);
  CHECK_THROWS_AS(s.UpdateGeometry(g, nullptr, 12), Error);
  CHECK(s.num_geometries() == 2);  // nothing was attached by the failed calls
  // Transforms: NaN, Inf, singular, null.
  float bad[12] = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0};
  bad[5] = NAN;
  CHECK_THROWS_WITH_AS(s.AttachInstance(g, bad), doctest::Contains("not finite"), Error);
  bad[5] = INFINITY;
  CHECK_THROWS_AS(s.AttachInstance(g, bad), Error);
  bad[5] = 0;
  CHECK_THROWS_WITH_AS(s.AttachInstance(g, bad), doctest::Contains("singular"), Error);
  CHECK_THROWS_AS(s.AttachInstance(g, nullptr), Error);
  const uint32_t inst = s.AttachInstance(g, identity);
  CHECK_THROWS_AS(s.SetInstanceTransform(inst, bad), Error);
  s.Commit();
  // Trace arguments: size mismatch, null ray and hit arrays.
  Hits short_hits(4);
  CHECK_THROWS_WITH_AS(s.Intersect(rays.View(), short_hits.View()), doctest::Contains("hits.size"), Error);
  RayView rv = rays.View();
  rv.tnear = nullptr;
  CHECK_THROWS_WITH_AS(s.Intersect(rv, hits.View()), doctest::Contains("tnear"), Error);
  CHECK_THROWS_AS(s.Occluded(rv, occ.data()), Error);
  HitView hv = hits.View();
  hv.ng_y = nullptr;
  CHECK_THROWS_AS(s.Intersect(rays.View(), hv), Error);
  CHECK_THROWS_AS(s.Occluded(rays.View(), nullptr), Error);
  s.Intersect(RayView{}, HitView{});  // size 0: nothing to do, null arrays allowed
  // A non-finite vertex: Commit names the geometry, the scene stays uncommitted.
  TestGeometry nan_box = box;
  nan_box.positions[4] = NAN;
  s.ReplaceGeometry(g, nan_box.Desc());
  CHECK_THROWS_WITH_AS(s.Commit(), doctest::Contains("geometry 0"), Error);
  CHECK_THROWS_AS(s.Intersect(rays.View(), hits.View()), Error);
  // Bad options.
  BuildOptions o;
  o.lambda = -1;
  CHECK_THROWS_AS(TraceScene{o}, Error);
  // Moved from.
  TraceScene t = std::move(s);
  CHECK_THROWS_WITH_AS(s.AttachGeometry(box.Desc()), doctest::Contains("moved from"), Error);  // NOLINT
  CHECK_THROWS_AS(s.Commit(), Error);                                                         // NOLINT
  CHECK_THROWS_AS(s.Intersect(rays.View(), hits.View()), Error);                              // NOLINT
  CHECK_THROWS_AS(s.Occluded(rays.View(), occ.data()), Error);                                // NOLINT
  CHECK_THROWS_AS(s.UpdateGeometry(0, box.positions.data(), 12), Error);                      // NOLINT
  CHECK_THROWS_AS(s.AttachInstance(0, identity), Error);                                      // NOLINT
  CHECK_THROWS_AS(s.num_geometries(), Error);                                                 // NOLINT
  t.ReplaceGeometry(g, box.Desc());
  t.Commit();
  t.Intersect(rays.View(), hits.View());
}

// Attaches ts's geometries to a C scene through rsSceneAttachGeometry.
void AttachCGeometries(RSScene scene, const TestScene& ts) {
  for (const auto& g : ts.geoms) {
    RSGeometryDesc d;
    rsInitGeometryDesc(&d);
    const GeometryDesc c = g.Desc();
    d.positions = c.positions, d.num_vertices = c.num_vertices, d.stride_bytes = c.stride_bytes;
    d.indices = c.indices, d.index_type = static_cast<RSIndexType>(c.index_type);
    d.num_triangles = c.num_triangles, d.mask = c.mask;
    d.mode = static_cast<RSBufferMode>(c.mode), d.instance_only = c.instance_only ? 1 : 0;
    uint32_t id = 99;
    CHECK(rsSceneAttachGeometry(scene, &d, &id) == RS_ERROR_NONE);
  }
}

// A C scene of ts's geometries and instances built with `options` (committed).
RSScene NewCScene(const TestScene& ts, const RSBuildOptions* options) {
  RSScene scene = rsNewScene(options);
  REQUIRE(scene != nullptr);
  AttachCGeometries(scene, ts);
  for (const auto& in : ts.insts) {
    uint32_t id = 99;
    CHECK(rsSceneAttachInstance(scene, in.geom, in.m, in.mask, &id) == RS_ERROR_NONE);
  }
  CHECK(rsSceneCommit(scene) == RS_ERROR_NONE);
  return scene;
}

TEST_CASE("the C scene API with RS_GRID_IRREGULAR: the hits and occlusion of the default grid") {
  const TestScene ts = Mixed();
  const Rays rays(500, 12);
  const size_t n = rays.mask.size();
  RSBuildOptions irregular;
  rsInitBuildOptions(&irregular);
  irregular.grid = RS_GRID_IRREGULAR;
  RSScene a = NewCScene(ts, nullptr), b = NewCScene(ts, &irregular);
  RSRays r = {rays.f[0].data(), rays.f[1].data(), rays.f[2].data(), rays.f[3].data(),
              rays.f[4].data(), rays.f[5].data(), rays.f[6].data(), rays.f[7].data(),
              rays.mask.data(), rays.id.data(), n};
  Hits ha(n), hb(n);
  RSHits ra = {ha.t.data(),  ha.u.data(),    ha.v.data(),    ha.nx.data(),   ha.ny.data(),
               ha.nz.data(), ha.prim.data(), ha.geom.data(), ha.inst.data(), n};
  RSHits rb = {hb.t.data(),  hb.u.data(),    hb.v.data(),    hb.nx.data(),   hb.ny.data(),
               hb.nz.data(), hb.prim.data(), hb.geom.data(), hb.inst.data(), n};
  test::ForEachTarget([&](const char* target) {
    INFO("target ", std::string(target));
    CHECK(rsSceneIntersect(a, &r, &ra) == RS_ERROR_NONE);
    CHECK(rsSceneIntersect(b, &r, &rb) == RS_ERROR_NONE);
    CHECK(ha == hb);
    std::vector<int32_t> oa(n), ob(n);
    CHECK(rsSceneOccluded(a, &r, oa.data()) == RS_ERROR_NONE);
    CHECK(rsSceneOccluded(b, &r, ob.data()) == RS_ERROR_NONE);
    CHECK(oa == ob);
  });
  size_t hit = 0;
  for (size_t i = 0; i < n; ++i) hit += ha.geom[i] >= 0;
  CHECK(hit > n / 5);
  rsReleaseScene(a);
  rsReleaseScene(b);
}

TEST_CASE("the C scene API: the same hits as C++, error codes for misuse") {
  const TestScene ts = Mixed();
  const Rays rays(500, 11);
  const size_t n = rays.mask.size();
  RSScene scene = rsNewScene(nullptr);
  REQUIRE(scene != nullptr);
  AttachCGeometries(scene, ts);
  RSRays r = {rays.f[0].data(), rays.f[1].data(), rays.f[2].data(), rays.f[3].data(),
              rays.f[4].data(), rays.f[5].data(), rays.f[6].data(), rays.f[7].data(),
              rays.mask.data(), rays.id.data(), n};
  Hits h(n);
  RSHits rh = {h.t.data(),  h.u.data(),    h.v.data(),    h.nx.data(),   h.ny.data(),
               h.nz.data(), h.prim.data(), h.geom.data(), h.inst.data(), n};
  CHECK(rsSceneIntersect(scene, &r, &rh) == RS_ERROR_INVALID_ARGUMENT);  // before commit
  CHECK(std::string(rsGetErrorMessage()).find("never committed") != std::string::npos);
  CHECK(rsGetError() == RS_ERROR_INVALID_ARGUMENT);
  for (const auto& in : ts.insts) {
    uint32_t id = 99;
    CHECK(rsSceneAttachInstance(scene, in.geom, in.m, in.mask, &id) == RS_ERROR_NONE);
  }
  CHECK(rsSceneCommit(scene) == RS_ERROR_NONE);
  CHECK(rsSceneIntersect(scene, &r, &rh) == RS_ERROR_NONE);
  Hits want(n);
  ts.Build().Intersect(rays.View(), want.View());
  CHECK(h == want);
  std::vector<int32_t> occ(n);
  CHECK(rsSceneOccluded(scene, &r, occ.data()) == RS_ERROR_NONE);
  for (size_t i = 0; i < n; ++i) CHECK(occ[i] == (want.geom[i] >= 0 ? 1 : 0));
  // Update through C equals the C++ update.
  TestGeometry moved = ts.geoms[2];
  for (float& x : moved.positions) x *= 0.9f;
  CHECK(rsSceneUpdateGeometry(scene, 2, moved.positions.data(), moved.stride * 4) == RS_ERROR_NONE);
  CHECK(rsSceneIntersect(scene, &r, &rh) == RS_ERROR_INVALID_ARGUMENT);  // edited
  CHECK(rsSceneCommit(scene) == RS_ERROR_NONE);
  CHECK(rsSceneIntersect(scene, &r, &rh) == RS_ERROR_NONE);
  TestScene edited = ts;
  edited.geoms[2] = moved;
  edited.Build().Intersect(rays.View(), want.View());
  CHECK(h == want);
  // Misuse: error codes.
  const float nan_m[12] = {NAN, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0};
  uint32_t id = 0;
  CHECK(rsSceneAttachInstance(scene, 0, nan_m, ~0u, &id) == RS_ERROR_INVALID_ARGUMENT);
  CHECK(rsSceneAttachInstance(scene, 17, ts.insts[0].m, ~0u, &id) == RS_ERROR_INVALID_ARGUMENT);
  CHECK(rsSceneAttachInstance(scene, 0, ts.insts[0].m, ~0u, nullptr) == RS_ERROR_INVALID_ARGUMENT);
  CHECK(rsSceneAttachGeometry(scene, nullptr, &id) == RS_ERROR_INVALID_ARGUMENT);
  CHECK(rsSceneAttachGeometry(nullptr, nullptr, &id) == RS_ERROR_INVALID_ARGUMENT);
  CHECK(rsSceneUpdateGeometry(scene, 42, moved.positions.data(), 12) == RS_ERROR_INVALID_ARGUMENT);
  CHECK(rsSceneReplaceGeometry(scene, 0, nullptr) == RS_ERROR_INVALID_ARGUMENT);
  CHECK(rsSceneSetInstanceTransform(scene, 9, nan_m) == RS_ERROR_INVALID_ARGUMENT);
  CHECK(rsSceneCommit(nullptr) == RS_ERROR_INVALID_ARGUMENT);
  RSHits short_hits = rh;
  short_hits.size = n - 1;
  CHECK(rsSceneIntersect(scene, &r, &short_hits) == RS_ERROR_INVALID_ARGUMENT);
  RSRays no_dx = r;
  no_dx.dx = nullptr;
  CHECK(rsSceneOccluded(scene, &no_dx, occ.data()) == RS_ERROR_INVALID_ARGUMENT);
  CHECK(rsSceneIntersect(scene, nullptr, &rh) == RS_ERROR_INVALID_ARGUMENT);
  RSBuildOptions bad;
  rsInitBuildOptions(&bad);
  bad.packets = 3;
  CHECK(rsNewScene(&bad) == nullptr);
  rsGetError();
  rsReleaseScene(scene);
  rsReleaseScene(nullptr);
}

}  // namespace
}  // namespace rs
