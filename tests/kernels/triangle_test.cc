// Scalar ray/triangle tests: watertight (shared edges and vertices never leak), degenerate
// triangles, parallel/+-0/NaN/Inf rays, (tmin, tmax] bounds, agreement with the double
// reference on random rays at unit, huge-offset and tiny scales, and no self-hit of rays
// spawned from large triangles (the t bound, pbrt-v4 6.8.7).
#include "kernels/triangle.h"

#include <doctest/doctest.h>

#include <algorithm>
#include <array>
#include <cfloat>
#include <cmath>
#include <limits>
#include <string>
#include <vector>

#include "kernels/reference.h"
#include "tests/kernels/geometry_util.h"
#include "tests/kernels/spawn_util.h"

namespace rs {
namespace {

using test::F;
using test::Rng;

constexpr float kInf = std::numeric_limits<float>::infinity();
constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();

bool Watertight(const float* p0, const float* p1, const float* p2, const float o[3],
                const float d[3], TriHit* h, float tmin = 0.0f, float tmax = kInf) {
  return IntersectTriangle(p0, p1, p2, o[0], o[1], o[2], d[0], d[1], d[2], tmin, tmax, h);
}
bool Moller(const float* p0, const float* p1, const float* p2, const float o[3], const float d[3],
            TriHit* h, float tmin = 0.0f, float tmax = kInf) {
  return IntersectMollerTrumbore(p0, p1, p2, o[0], o[1], o[2], d[0], d[1], d[2], tmin, tmax, h);
}

// Both tests agree on a plain hit, and u, v are the barycentrics of vertices 1 and 2.
TEST_CASE("hit at an interior point: t, u, v; both windings; both tests") {
  const float p0[3] = {0, 0, 0}, p1[3] = {1, 0, 0}, p2[3] = {0, 1, 0};
  const float o[3] = {0.25f, 0.5f, 2.0f}, d[3] = {0, 0, -1};
  TriHit h;
  REQUIRE(Watertight(p0, p1, p2, o, d, &h));
  CHECK(h.t == doctest::Approx(2.0f).epsilon(1e-6));
  CHECK(h.u == doctest::Approx(0.25f).epsilon(1e-6));  // weight of p1 = x
  CHECK(h.v == doctest::Approx(0.5f).epsilon(1e-6));   // weight of p2 = y
  // the other winding, and from below: no culling
  TriHit h2;
  REQUIRE(Watertight(p0, p2, p1, o, d, &h2));
  CHECK(h2.u == doctest::Approx(0.5f).epsilon(1e-6));
  CHECK(h2.v == doctest::Approx(0.25f).epsilon(1e-6));
  const float o_below[3] = {0.25f, 0.5f, -3.0f}, d_up[3] = {0, 0, 0.5f};
  TriHit h3;
  REQUIRE(Watertight(p0, p1, p2, o_below, d_up, &h3));
  CHECK(h3.t == doctest::Approx(6.0f).epsilon(1e-6));  // t in units of |d|
  TriHit hm;
  REQUIRE(Moller(p0, p1, p2, o, d, &hm));
  CHECK(hm.t == doctest::Approx(2.0f).epsilon(1e-6));
  CHECK(hm.u == doctest::Approx(0.25f).epsilon(1e-6));
  CHECK(hm.v == doctest::Approx(0.5f).epsilon(1e-6));
  // a ray beside the triangle misses
  const float o_out[3] = {0.75f, 0.5f, 2.0f};
  CHECK_FALSE(Watertight(p0, p1, p2, o_out, d, &h));
  CHECK_FALSE(Moller(p0, p1, p2, o_out, d, &h));
}

TEST_CASE("points exactly on edges and vertices of one triangle are hit (closed triangle)") {
  const float p[3][3] = {{0, 0, 0}, {1, 0, 0}, {0, 1, 0}};
  const float targets[][2] = {{0.5f, 0.0f}, {0.0f, 0.5f}, {0.5f, 0.5f}, {0.0f, 0.0f},
                              {1.0f, 0.0f}, {0.0f, 1.0f}, {0.25f, 0.0f}, {0.0f, 0.75f}};
  const float dirs[][3] = {{0, 0, -1}, {0.5f, 0.25f, -1}, {-0.25f, 0.5f, -1}, {1, 1, -2}};
  for (const auto& tg : targets) {
    for (const auto& d : dirs) {
      // origin = target - 2 d: exact in float, so the ray passes exactly through the target
      const float o[3] = {tg[0] - 2 * d[0], tg[1] - 2 * d[1], 0.0f - 2 * d[2]};
      TriHit h;
      INFO("target ", tg[0], ", ", tg[1], " dir ", d[0], ", ", d[1], ", ", d[2]);
      CHECK(Watertight(p[0], p[1], p[2], o, d, &h));
      CHECK(h.t == doctest::Approx(2.0f).epsilon(1e-6));
      // a nudge outward of the edge/vertex misses
      const float o_out[3] = {o[0] - 1e-3f, o[1] - 1e-3f, o[2]};
      if (tg[0] == 0.0f || tg[1] == 0.0f) CHECK_FALSE(Watertight(p[0], p[1], p[2], o_out, d, &h));
    }
  }
}

// A closed, welded mesh: a UV sphere with jittered radii whose coordinates are multiples of
// 2^-12, so that d = v - o is exact for origins on the same lattice and the ray passes exactly
// through vertex v (or an edge midpoint). The poles are fans of `lon` triangles.
struct ClosedSphere {
  std::vector<std::array<float, 3>> v;
  std::vector<std::array<int, 3>> tri;
};

float Lattice(double x) { return F(std::round(x * 4096.0) / 4096.0); }

ClosedSphere MakeClosedSphere(Rng& rng, int lat, int lon) {
  ClosedSphere s;
  s.v.push_back({0.0f, 0.0f, Lattice(rng.Uniform(0.8, 1.2))});  // north pole
  for (int i = 1; i < lat; ++i) {
    for (int j = 0; j < lon; ++j) {
      const double th = 3.141592653589793 * i / lat, ph = 6.283185307179586 * j / lon;
      const double r = rng.Uniform(0.8, 1.2);
      s.v.push_back({Lattice(r * std::sin(th) * std::cos(ph)),
                     Lattice(r * std::sin(th) * std::sin(ph)), Lattice(r * std::cos(th))});
    }
  }
  s.v.push_back({0.0f, 0.0f, Lattice(-rng.Uniform(0.8, 1.2))});  // south pole
  const int south = int(s.v.size()) - 1;
  auto ring = [&](int i, int j) { return 1 + (i - 1) * lon + (j % lon); };
  for (int j = 0; j < lon; ++j) {
    s.tri.push_back({0, ring(1, j), ring(1, j + 1)});
    for (int i = 1; i + 1 < lat; ++i) {
      s.tri.push_back({ring(i, j), ring(i + 1, j), ring(i + 1, j + 1)});
      s.tri.push_back({ring(i, j), ring(i + 1, j + 1), ring(i, j + 1)});
    }
    s.tri.push_back({south, ring(lat - 1, j + 1), ring(lat - 1, j)});
  }
  return s;
}

// Rays from inside a closed mesh must cross it (Jordan): aimed exactly at vertices (the pole
// fans included) and edge midpoints, and aimed in float at random edge points.
TEST_CASE("watertight: rays from inside a closed mesh through vertices and edges never leak") {
  Rng rng(7);
  size_t rays = 0, exact = 0, leaks = 0, moller_leaks = 0, outside = 0;
  for (int mesh = 0; mesh < 20; ++mesh) {
    // (sizes drawn in separate statements: argument evaluation order differs between compilers)
    const int lat = 3 + int(rng.Below(8));
    const int lon = 3 + int(rng.Below(10));
    const ClosedSphere s = MakeClosedSphere(rng, lat, lon);
    auto trace = [&](const float o[3], const float d[3]) {
      int hits = 0, moller = 0;
      for (const auto& t : s.tri) {
        TriHit h;
        hits += Watertight(s.v[t[0]].data(), s.v[t[1]].data(), s.v[t[2]].data(), o, d, &h);
        moller += Moller(s.v[t[0]].data(), s.v[t[1]].data(), s.v[t[2]].data(), o, d, &h);
      }
      ++rays;
      leaks += hits == 0;
      moller_leaks += moller == 0;
    };
    for (int k = 0; k < 1000; ++k) {
      const float o[3] = {Lattice(rng.Uniform(-0.3, 0.3)), Lattice(rng.Uniform(-0.3, 0.3)),
                          Lattice(rng.Uniform(-0.3, 0.3))};
      // The mesh is star-shaped around the centre: o is inside iff the segment centre -> o
      // crosses no triangle (checked with the double reference). Coarse meshes have faces
      // close to the centre; origins outside could legitimately graze a silhouette.
      const ref::Ray to_o = ref::MakeRay(0.0f, 0.0f, 0.0f, o[0], o[1], o[2], -1e-3f, 1.001f);
      bool inside = true;
      for (const auto& t : s.tri) {
        double p[3][3];
        for (int q = 0; q < 3; ++q) {
          for (int a = 0; a < 3; ++a) p[q][a] = s.v[t[q]][a];
        }
        ref::Hit h;
        inside = inside && !ref::IntersectTriangle(to_o, p[0], p[1], p[2], to_o.tmax, &h);
      }
      if (!inside) {
        ++outside;
        continue;
      }
      // exactly through a vertex (the poles get extra weight: they are the big fans)
      const int vi = k % 4 == 0 ? (k % 8 == 0 ? 0 : int(s.v.size()) - 1)
                                : int(rng.Below(uint32_t(s.v.size())));
      const auto& v = s.v[vi];
      const float d[3] = {v[0] - o[0], v[1] - o[1], v[2] - o[2]};
      REQUIRE((o[0] + d[0] == v[0] && o[1] + d[1] == v[1] && o[2] + d[2] == v[2]));
      trace(o, d);
      // exactly through an edge midpoint (coordinates / 2 stay exact)
      const auto& t = s.tri[rng.Below(uint32_t(s.tri.size()))];
      const int e = int(rng.Below(3));
      const auto& a = s.v[t[e]];
      const auto& b = s.v[t[(e + 1) % 3]];
      const float mid[3] = {(a[0] + b[0]) * 0.5f, (a[1] + b[1]) * 0.5f, (a[2] + b[2]) * 0.5f};
      const float dm[3] = {mid[0] - o[0], mid[1] - o[1], mid[2] - o[2]};
      if (o[0] + dm[0] == mid[0] && o[1] + dm[1] == mid[1] && o[2] + dm[2] == mid[2]) ++exact;
      trace(o, dm);
      // aimed at a random point of the edge, rounded to float
      const double u = rng.Uniform(0, 1);
      const float pt[3] = {F(a[0] + u * (b[0] - a[0])), F(a[1] + u * (b[1] - a[1])),
                           F(a[2] + u * (b[2] - a[2]))};
      const float dp[3] = {pt[0] - o[0], pt[1] - o[1], pt[2] - o[2]};
      trace(o, dp);
    }
  }
  MESSAGE("rays from inside closed meshes: ", rays, " (", exact,
          " exactly through edge midpoints, 1/3 exactly through vertices); watertight leaks: ",
          leaks, ", Moller-Trumbore leaks: ", moller_leaks, "; origins outside, skipped: ", outside);
  CHECK(exact > 15000);
  CHECK(leaks == 0);
}

// A flat fan around a vertex: rays exactly through the shared vertex hit (>= 1 triangle).
TEST_CASE("watertight: rays exactly through the shared vertex of a flat fan") {
  Rng rng(11);
  const float apex[3] = {0.25f, -0.5f, 0.0f};
  for (int n = 3; n <= 12; ++n) {
    std::vector<std::array<float, 3>> ring(n);
    for (int i = 0; i < n; ++i) {
      const double a = 6.283185307179586 * (i + rng.Uniform(-0.2, 0.2)) / n;
      ring[i] = {Lattice(apex[0] + std::cos(a)), Lattice(apex[1] + std::sin(a)), 0.0f};
    }
    for (int k = 0; k < 500; ++k) {
      const float o[3] = {Lattice(rng.Uniform(-3, 3)), Lattice(rng.Uniform(-3, 3)),
                          Lattice(rng.Uniform(-3, 3))};
      if (o[2] == 0.0f) continue;
      const float d[3] = {apex[0] - o[0], apex[1] - o[1], apex[2] - o[2]};
      int hits = 0;
      for (int i = 0; i < n; ++i) {
        TriHit h;
        if (Watertight(apex, ring[i].data(), ring[(i + 1) % n].data(), o, d, &h)) {
          ++hits;
          CHECK(h.t == doctest::Approx(1.0f).epsilon(1e-6));
        }
      }
      INFO("n = ", n, " o = ", o[0], ", ", o[1], ", ", o[2]);
      CHECK(hits >= 1);
    }
  }
}

TEST_CASE("watertight: exact rays along the shared diagonal of a quad hit one or both") {
  // Quad split along (0,0,0)-(1,1,0); the rays pass exactly through diagonal points.
  const float a[3] = {0, 0, 0}, b[3] = {1, 0, 0}, c[3] = {1, 1, 0}, e[3] = {0, 1, 0};
  int rays = 0;
  for (int i = 0; i <= 64; ++i) {
    const float s = float(i) / 64.0f;  // exact
    for (int j = 0; j < 27; ++j) {
      const float d[3] = {float(j % 3) - 1.0f + 0.125f * float(j % 5), float((j / 3) % 3) - 1.0f,
                          -1.0f - float(j / 9)};
      const float o[3] = {s - d[0], s - d[1], -d[2]};  // o + d = (s, s, 0) exactly
      REQUIRE(o[0] + d[0] == s);
      TriHit h;
      const bool h1 = Watertight(a, b, c, o, d, &h);
      const bool h2 = Watertight(a, c, e, o, d, &h);
      INFO("s = ", s, " j = ", j);
      CHECK((h1 || h2));
      ++rays;
    }
  }
  CHECK(rays == 65 * 27);
}

TEST_CASE("degenerate triangles never hit and are flagged") {
  const float o[3] = {0.5f, 0.5f, 3.0f}, d[3] = {0, 0, -1};
  const float z[3] = {0, 0, 0}, x1[3] = {1, 1, 0}, x2[3] = {2, 2, 0};
  const float corner[3] = {1, 0, 0};
  TriHit h;
  // repeated vertex
  CHECK(IsDegenerateTriangle(z, z, corner));
  CHECK_FALSE(Watertight(z, z, corner, o, d, &h));
  CHECK_FALSE(Moller(z, z, corner, o, d, &h));
  // all three equal
  CHECK(IsDegenerateTriangle(x1, x1, x1));
  // collinear, ray exactly through the segment
  CHECK(IsDegenerateTriangle(z, x1, x2));
  const float o2[3] = {0.5f, 0.5f, 3.0f}, d2[3] = {0.0f, 0.0f, -1.0f};
  CHECK_FALSE(Watertight(z, x1, x2, o2, d2, &h));
  CHECK_FALSE(Moller(z, x1, x2, o2, d2, &h));
  // collinear in 3D (not axis aligned), many rays through points of the line
  const float l0[3] = {0.5f, 1.0f, -2.0f}, l1[3] = {1.5f, 3.0f, 0.0f}, l2[3] = {3.5f, 7.0f, 4.0f};
  CHECK(IsDegenerateTriangle(l0, l1, l2));
  Rng rng(3);
  for (int k = 0; k < 1000; ++k) {
    const float s = F(rng.Uniform(0, 1));
    const float target[3] = {l0[0] + s * 3.0f, l0[1] + s * 6.0f, l0[2] + s * 6.0f};
    const float oo[3] = {rng.UniformF(-5, 5), rng.UniformF(-5, 5), rng.UniformF(-5, 5)};
    const float dd[3] = {target[0] - oo[0], target[1] - oo[1], target[2] - oo[2]};
    CHECK_FALSE(Watertight(l0, l1, l2, oo, dd, &h));
    CHECK_FALSE(Moller(l0, l1, l2, oo, dd, &h));
  }
  // non-finite vertices are degenerate; a tiny but real triangle is not
  const float bad[3] = {kNaN, 0, 0}, inf[3] = {kInf, 0, 0};
  CHECK(IsDegenerateTriangle(bad, x1, corner));
  CHECK(IsDegenerateTriangle(z, inf, corner));
  const float t0[3] = {0, 0, 0}, t1[3] = {1e-20f, 0, 0}, t2[3] = {0, 1e-20f, 0};
  CHECK_FALSE(IsDegenerateTriangle(t0, t1, t2));
}

TEST_CASE("parallel rays, rays in the plane, and +-0 direction components") {
  const float p0[3] = {0, 0, 0}, p1[3] = {1, 0, 0}, p2[3] = {0, 1, 0};
  TriHit h;
  // parallel above the plane
  const float o_above[3] = {-1, 0.25f, 1}, d_x[3] = {1, 0, 0};
  CHECK_FALSE(Watertight(p0, p1, p2, o_above, d_x, &h));
  CHECK_FALSE(Moller(p0, p1, p2, o_above, d_x, &h));
  // in the plane, crossing the triangle: coplanar rays do not hit (det = 0)
  const float o_in[3] = {-1, 0.25f, 0};
  CHECK_FALSE(Watertight(p0, p1, p2, o_in, d_x, &h));
  CHECK_FALSE(Moller(p0, p1, p2, o_in, d_x, &h));
  // signed zeros in the direction and origin
  const float zeros[][3] = {{0.0f, 0.0f, -1.0f}, {-0.0f, 0.0f, -1.0f}, {0.0f, -0.0f, -1.0f},
                            {-0.0f, -0.0f, -1.0f}};
  for (const auto& d : zeros) {
    const float o[3] = {0.25f, -0.0f + 0.25f, 1.0f};
    CHECK(Watertight(p0, p1, p2, o, d, &h));
    CHECK(h.t == 1.0f);
    CHECK(Moller(p0, p1, p2, o, d, &h));
    // through the vertex at the origin with -0 origin components
    const float o0[3] = {-0.0f, -0.0f, 2.0f};
    CHECK(Watertight(p0, p1, p2, o0, d, &h));
    CHECK(h.t == 2.0f);
  }
  // along -z from below with +-0 (backface)
  const float o_b[3] = {0.1f, 0.1f, -1.0f}, d_b[3] = {-0.0f, 0.0f, 1.0f};
  CHECK(Watertight(p0, p1, p2, o_b, d_b, &h));
  CHECK(h.t == 1.0f);
}

TEST_CASE("NaN and Inf rays, zero directions and NaN bounds never hit") {
  const float p0[3] = {0, 0, 0}, p1[3] = {1, 0, 0}, p2[3] = {0, 1, 0};
  const float good_o[3] = {0.25f, 0.25f, 1.0f}, good_d[3] = {0, 0, -1};
  TriHit h;
  REQUIRE(Watertight(p0, p1, p2, good_o, good_d, &h));
  for (int comp = 0; comp < 6; ++comp) {
    for (const float bad : {kNaN, kInf, -kInf}) {
      float o[3] = {good_o[0], good_o[1], good_o[2]}, d[3] = {good_d[0], good_d[1], good_d[2]};
      (comp < 3 ? o[comp] : d[comp - 3]) = bad;
      INFO("component ", comp, " = ", bad);
      CHECK_FALSE(Watertight(p0, p1, p2, o, d, &h));
      CHECK_FALSE(Moller(p0, p1, p2, o, d, &h));
    }
  }
  const float zero[3] = {0.0f, -0.0f, 0.0f}, tiny[3] = {0.0f, 0.0f, -1e-31f};
  CHECK_FALSE(Watertight(p0, p1, p2, good_o, zero, &h));
  CHECK_FALSE(Moller(p0, p1, p2, good_o, zero, &h));
  CHECK_FALSE(Watertight(p0, p1, p2, good_o, tiny, &h));
  CHECK_FALSE(Watertight(p0, p1, p2, good_o, good_d, &h, kNaN, kInf));
  CHECK_FALSE(Watertight(p0, p1, p2, good_o, good_d, &h, 0.0f, kNaN));
  CHECK_FALSE(Moller(p0, p1, p2, good_o, good_d, &h, kNaN, kInf));
  CHECK_FALSE(Moller(p0, p1, p2, good_o, good_d, &h, 0.0f, kNaN));
  // small but valid direction still hits
  const float small_d[3] = {0.0f, 0.0f, -1e-20f};
  REQUIRE(Watertight(p0, p1, p2, good_o, small_d, &h));
  CHECK(h.t == doctest::Approx(1e20f).epsilon(1e-6));
}

TEST_CASE("t in (tmin, tmax]: tmax inclusive, tmin exclusive, negative segments") {
  const float p0[3] = {0, 0, 0}, p1[3] = {1, 0, 0}, p2[3] = {0, 1, 0};
  const float o[3] = {0.25f, 0.25f, 1.0f}, d[3] = {0, 0, -1};
  const float below1 = std::nextafter(1.0f, 0.0f);
  TriHit h;
  CHECK(Watertight(p0, p1, p2, o, d, &h, 0.0f, 1.0f));
  CHECK_FALSE(Watertight(p0, p1, p2, o, d, &h, 0.0f, below1));
  CHECK_FALSE(Watertight(p0, p1, p2, o, d, &h, 1.0f, 5.0f));
  CHECK(Watertight(p0, p1, p2, o, d, &h, below1, 5.0f));
  CHECK(Moller(p0, p1, p2, o, d, &h, 0.0f, 1.0f));
  CHECK_FALSE(Moller(p0, p1, p2, o, d, &h, 0.0f, below1));
  CHECK_FALSE(Moller(p0, p1, p2, o, d, &h, 1.0f, 5.0f));
  // behind the origin: only with a negative tmin
  const float d_up[3] = {0, 0, 1};
  CHECK_FALSE(Watertight(p0, p1, p2, o, d_up, &h));
  REQUIRE(Watertight(p0, p1, p2, o, d_up, &h, -2.0f, kInf));
  CHECK(h.t == -1.0f);
  // empty interval
  CHECK_FALSE(Watertight(p0, p1, p2, o, d, &h, 1.0f, 1.0f));
}

// Regression (conference): shadow rays leaving the big floor quad from OffsetRayOrigin's origin,
// 3.05e-5 above it, were reported hitting the floor at t ~ 1e-7 (the rounding of the t
// numerator with vertices ~1650 away exceeds the offset). With the t bound: no hit, for the
// literal rays, for their normalised directions (reflection rays) and at tmin = 0 or 1e-30;
// the same rays reversed from 1 above the floor still hit it.
TEST_CASE("regression: conference floor, rays 3.05e-5 above it pointing away never hit it") {
  using test::kFloorA, test::kFloorB, test::kFloorC, test::kFloorD;
  const float* tri[2][3] = {{kFloorA, kFloorB, kFloorC}, {kFloorB, kFloorD, kFloorC}};
  for (const test::FloorRay& r : test::kFloorRays) {
    const double len =
        std::sqrt(double(r.d[0]) * r.d[0] + double(r.d[1]) * r.d[1] + double(r.d[2]) * r.d[2]);
    const float unit[3] = {F(r.d[0] / len), F(r.d[1] / len), F(r.d[2] / len)};
    INFO("o ", r.o[0], " ", r.o[1], " ", r.o[2], " d ", r.d[0], " ", r.d[1], " ", r.d[2]);
    for (int k = 0; k < 2; ++k) {
      TriHit h;
      CHECK_FALSE(
          Watertight(tri[k][0], tri[k][1], tri[k][2], r.o, r.d, &h, 0.0f, test::kFloorRayTmax));
      CHECK_FALSE(Watertight(tri[k][0], tri[k][1], tri[k][2], r.o, r.d, &h, 0.0f, kInf));
      CHECK_FALSE(Watertight(tri[k][0], tri[k][1], tri[k][2], r.o, r.d, &h, 1e-30f, kInf));
      CHECK_FALSE(Watertight(tri[k][0], tri[k][1], tri[k][2], r.o, unit, &h, 0.0f, kInf));
    }
    // without the bound (tmin < 0 keeps hits behind the origin) the rounding shows: the old
    // false hit at t > 0, on the triangle the renderer reported
    TriHit behind;
    const float* const* t = tri[r.tri];
    REQUIRE(Watertight(t[0], t[1], t[2], r.o, r.d, &behind, -1e-30f, kInf));
    CHECK(behind.t > 0.0f);
    CHECK(behind.t < 2e-7f);
    // the reversed rays from h above the floor hit it at t = h / |d_y|, also when h is far
    // inside the float bound (~1.5e-5 in t for these |d| ~ 1e3 rays, 0.02 for the unit ones):
    // such hits are decided in double, not dropped
    for (const float* dir : {r.d, static_cast<const float*>(unit)}) {
      for (const double h : {1.0, 1e-2, 1e-3, 1e-4}) {
        const float above[3] = {r.o[0], F(double(test::kFloorA[1]) + h), r.o[2]};
        const float down[3] = {-dir[0], -dir[1], -dir[2]};
        const double want = (double(above[1]) - test::kFloorA[1]) / dir[1];
        INFO("h ", h, " |d| ", std::sqrt(dir[0] * dir[0] + dir[1] * dir[1] + dir[2] * dir[2]));
        TriHit h0, h1;
        const bool hit0 = Watertight(tri[0][0], tri[0][1], tri[0][2], above, down, &h0);
        const bool hit1 = Watertight(tri[1][0], tri[1][1], tri[1][2], above, down, &h1);
        REQUIRE((hit0 || hit1));
        CHECK((hit0 ? h0.t : h1.t) == doctest::Approx(want).epsilon(1e-3));
      }
    }
  }
  // kernels/shared_scenes_test ray 52617 (conference, random origin 0.0102 above the floor,
  // pointing down): the float bound (t <= 0.020) cannot decide its hit at t = 0.0158; the
  // double decision keeps it, as the double reference and Embree do
  const float o[3] = {-601.581f, -1.56192f, -590.431f}, d[3] = {-0.952621f, -0.646831f, 0.866388f};
  TriHit h;
  REQUIRE(Watertight(kFloorA, kFloorB, kFloorC, o, d, &h));
  CHECK(h.t == doctest::Approx(0.015837).epsilon(1e-3));
}

// pbrt's Reintersect idea: rays spawned as the shader spawns them (point from barycentrics,
// OffsetRayOrigin along the normal, direction away from the plane) from large and
// far-from-origin triangles never hit their own triangle; without the bound (tmin < 0) many
// of them do, so the test is not vacuous.
TEST_CASE("no self-hit: rays spawned from large, far-from-origin triangles pointing away") {
  struct Config {
    double size, offset;
  };
  const Config configs[] = {{1e3, 0.0}, {1e3, 1e4}, {1e4, 0.0}, {1e4, 3e4},
                            {2e3, 1e5}, {1.0, 0.0}, {1.0, 1e3}};
  const int n = 50000;
  Rng rng(2026);
  for (const Config& c : configs) {
    size_t rehits = 0, unbounded = 0, skipped = 0;
    std::string first;
    for (int i = 0; i < n; ++i) {
      const test::SpawnTriangle tri = test::MakeSpawnTriangle(rng, c.size, c.offset);
      const test::SpawnedRay s = test::SpawnRay(rng, tri, c.size);
      if (!s.above) {
        ++skipped;
        continue;
      }
      const auto& p = tri.p;
      TriHit h;
      if (Watertight(p[0], p[1], p[2], s.o, s.d, &h)) {
        if (rehits++ == 0)
          first = "o " + std::to_string(s.o[0]) + " " + std::to_string(s.o[1]) + " " +
                  std::to_string(s.o[2]) + " t " + std::to_string(h.t);
      }
      TriHit hb;
      unbounded += Watertight(p[0], p[1], p[2], s.o, s.d, &hb, -1e-30f, kInf) && hb.t > 0;
    }
    MESSAGE("size ", c.size, " offset ", c.offset, ": ", n, " spawned rays, self-hits ", rehits,
            " (without the t bound: ", unbounded, "), origin not above the plane (skipped) ",
            skipped);
    INFO("size ", c.size, " offset ", c.offset, " first: ", first);
    CHECK(rehits == 0);
    CHECK(skipped <= size_t(n) / 1000);
    if (c.size >= 1e3) CHECK(unbounded > 0);
  }
}

struct AgreementCounts {
  int rays = 0, both_hit = 0, both_miss = 0, edge_disagree = 0, disagree = 0, t_bad = 0;
  int moller_disagree = 0;
  int grazing_widened = 0;
  int uv_widened = 0;  // u, v within the conditioning bound but beyond 1e-4  // t within the grazing-ray bound but beyond 1e-5 relative
  double worst_rel = 0.0;
};

// Random triangles of size `size` around `offset`, rays from random origins aimed at random
// points near each triangle (half inside); float watertight vs ref::IntersectTriangle.
AgreementCounts RandomAgreement(uint32_t seed, int count, double offset, double size) {
  Rng rng(seed);
  AgreementCounts r;
  for (int i = 0; i < count; ++i) {
    float p[3][3];
    double pd[3][3];
    for (int k = 0; k < 3; ++k) {
      for (int a = 0; a < 3; ++a) {
        p[k][a] = F(offset + rng.Uniform(-size, size));
        pd[k][a] = p[k][a];
      }
    }
    if (IsDegenerateTriangle(p[0], p[1], p[2])) continue;
    const double b1 = rng.Uniform(-0.2, 1.0), b2 = rng.Uniform(-0.2, 1.0 - b1 + 0.2);
    double target[3];
    for (int a = 0; a < 3; ++a) target[a] = pd[0][a] + b1 * (pd[1][a] - pd[0][a]) + b2 * (pd[2][a] - pd[0][a]);
    float d[3];
    rng.Direction(d);
    const double dist = rng.Uniform(0.2, 4.0) * size;
    const float o[3] = {F(target[0] - dist * d[0]), F(target[1] - dist * d[1]),
                        F(target[2] - dist * d[2])};
    ++r.rays;
    TriHit h;
    const bool hit = Watertight(p[0], p[1], p[2], o, d, &h);
    TriHit hm;
    const bool hit_m = Moller(p[0], p[1], p[2], o, d, &hm);
    const ref::Ray ray = ref::MakeRay(o[0], o[1], o[2], d[0], d[1], d[2], 0.0f, kInf);
    ref::Hit rh;
    const bool ref_hit = ref::IntersectTriangle(ray, pd[0], pd[1], pd[2], HUGE_VAL, &rh);
    r.moller_disagree += hit_m != ref_hit;
    if (hit && ref_hit) {
      ++r.both_hit;
      const double rel = std::fabs(h.t - rh.t) / std::fabs(rh.t);
      r.worst_rel = std::max(r.worst_rel, rel);
      const double tol = test::TTolerance(ray, pd, rh);
      if (!(std::fabs(h.t - rh.t) <= tol)) ++r.t_bad;
      r.grazing_widened += tol > 1e-5 * std::fabs(rh.t) && rel > 1e-5;
      const double uv_tol = test::UvTolerance(ray, pd, rh);
      if (!(std::fabs(h.u - rh.u) <= uv_tol && std::fabs(h.v - rh.v) <= uv_tol)) ++r.t_bad;
      r.uv_widened += std::fabs(h.u - rh.u) > 1e-4 || std::fabs(h.v - rh.v) > 1e-4;
    } else if (!hit && !ref_hit) {
      ++r.both_miss;
    } else {
      const double od[3] = {o[0], o[1], o[2]}, dd[3] = {d[0], d[1], d[2]};
      double t_plane = 0.0, min_bary = 1.0;
      if (!test::PlaneHitDouble(od, dd, pd, &t_plane, &min_bary) || std::fabs(min_bary) < 1e-4) {
        ++r.edge_disagree;
      } else {
        ++r.disagree;
      }
    }
  }
  return r;
}

void CheckAgreement(const AgreementCounts& r, const std::string& what) {
  MESSAGE(what, ": rays ", r.rays, ", both hit ", r.both_hit, ", both miss ", r.both_miss,
          ", disagree within 1e-4 of an edge ", r.edge_disagree, ", other disagreements ",
          r.disagree, ", t/u/v out of tolerance ", r.t_bad, ", worst t rel err ", r.worst_rel,
          " (ill-conditioned, beyond 1e-5: ", r.grazing_widened, "; u, v beyond 1e-4: ",
          r.uv_widened, ")",
          ", Moller-Trumbore hit/miss differs from ref on ", r.moller_disagree);
  CHECK(r.both_hit > r.rays / 5);
  CHECK(r.both_miss > r.rays / 5);
  CHECK(r.disagree == 0);
  CHECK(r.edge_disagree <= r.rays / 1000);
  CHECK(r.t_bad == 0);
}

TEST_CASE("agreement with the double reference: 100k random rays and triangles") {
  CheckAgreement(RandomAgreement(101, 100000, 0.0, 1.0), "unit scale");
}

TEST_CASE("agreement with the double reference: huge offset (1e5) and tiny scale (1e-4)") {
  CheckAgreement(RandomAgreement(202, 20000, 1e5, 1.0), "offset 1e5");
  CheckAgreement(RandomAgreement(303, 20000, 0.0, 1e-4), "scale 1e-4");
  CheckAgreement(RandomAgreement(404, 20000, 1e5, 30.0), "offset 1e5, size 30");
}

}  // namespace
}  // namespace rs
