// Scalar 3D-DDA: every traced ray must give exactly (bit for bit) what a float brute force
// with the same watertight test and tie rule gives, and agree with the double reference up to
// ties and grazing tolerance. Covers axis rays with +-0, cell-boundary origins, origins inside
// and outside, grazing the grid and the geometry, misses, NaN/Inf (never hit, never hang).
#include <doctest/doctest.h>

#include <cfloat>
#include <cmath>
#include <cstring>
#include <limits>
#include <tuple>
#include <string>
#include <vector>

#include "kernels/dda.h"
#include "kernels/grid.h"
#include "kernels/irregular.h"
#include "kernels/reference.h"
#include "kernels/triangle.h"
#include "tests/kernels/geometry_util.h"

namespace rs {
namespace {

using test::F;
using test::Rng;
using test::Soup;

using test::kInf;
using test::kNaN;
using test::Ray;

// The uniform grid, and two irregular grids over the same triangles (the default options, and
// a finer one with more merges), which must give the uniform grid's results bit for bit.
struct World {
  Soup soup;
  TriangleSoA tris;
  Grid grid;
  IrregularGrid irregular[2];
  explicit World(Soup s, float lambda = 4.0f, int max_res = 512) : soup(std::move(s)) {
    BuildTriangleSoA(soup.view(), &tris);
    BuildGrid(tris, lambda, max_res, &grid);
    const GridBounds bounds = ComputeGridBounds(tris);
    BuildIrregularGrid(tris, bounds, IrregularOptions{}, max_res, &irregular[0]);
    IrregularOptions fine;
    fine.top_lambda = 1.0f;
    fine.sub_lambda = 8.0f;
    BuildIrregularGrid(tris, bounds, fine, max_res, &irregular[1]);
  }
};

// The float oracle: every non-degenerate triangle, the same watertight test, the same tie rule.
bool FloatBrute(const TriangleSoA& tris, const Ray& r, RayHit* hit) {
  hit->t = kInf;
  hit->prim = -1;
  if (!RayIsValid(r.o[0], r.o[1], r.o[2], r.d[0], r.d[1], r.d[2])) return false;
  const float tmax = r.tmax > FLT_MAX ? FLT_MAX : r.tmax;
  if (!(r.tmin < tmax)) return false;
  const WatertightRay w = PrepareWatertightRay(r.o[0], r.o[1], r.o[2], r.d[0], r.d[1], r.d[2]);
  float best = tmax;
  for (size_t i = 0; i < tris.size; ++i) {
    if (tris.degenerate[i]) continue;
    TriHit h;
    if (IntersectWatertight(w, tris, i, r.tmin, best, &h) &&
        (h.t < best || hit->prim < 0 || int32_t(i) < hit->prim)) {
      best = h.t;
      *hit = {h.t, h.u, h.v, int32_t(i)};
    }
  }
  return hit->prim >= 0;
}

using test::SameBits;

struct Counts {
  int rays = 0, hits = 0, exact_mismatch = 0, any_mismatch = 0;
  int ref_ties = 0, ref_edge = 0, ref_bad = 0, ref_t_bad = 0;
  uint64_t steps = 0, tests = 0;
  int irregular_mismatch = 0;
  uint64_t irregular_steps = 0;
};

// Traces r through the grid; checks it against the float brute force (must be identical) and
// the double reference (same id, or a tie within 1e-5 relative in the reference's t, or a
// float/double disagreement within 1e-4 of an edge of the triangle concerned).
void Check(const World& w, const Ray& r, Counts* c) {
  ++c->rays;
  TraceStats stats;
  RayHit g;
  const bool hit = TraceClosest(w.grid, w.tris, r.o[0], r.o[1], r.o[2], r.d[0], r.d[1], r.d[2],
                                r.tmin, r.tmax, &g, &stats);
  c->steps += stats.cell_steps;
  c->tests += stats.triangle_tests;
  CHECK(stats.cell_steps <= uint64_t(w.grid.res[0] + w.grid.res[1] + w.grid.res[2]));
  RayHit b;
  const bool bhit = FloatBrute(w.tris, r, &b);
  c->hits += bhit;
  const bool same = hit == bhit && g.prim == b.prim &&
                    (!hit || (SameBits(g.t, b.t) && SameBits(g.u, b.u) && SameBits(g.v, b.v)));
  if (!same) {
    ++c->exact_mismatch;
    INFO("o ", r.o[0], " ", r.o[1], " ", r.o[2], " d ", r.d[0], " ", r.d[1], " ", r.d[2],
         " grid prim ", g.prim, " t ", g.t, " brute prim ", b.prim, " t ", b.t);
    CHECK(same);
  }
  if (!hit) CHECK(g.prim == -1);
  if (!hit) CHECK(g.t == kInf);
  for (const IrregularGrid& irr : w.irregular) {
    TraceStats is;
    RayHit ih;
    const bool ihit = TraceClosestIrregular(irr, w.tris, r.o[0], r.o[1], r.o[2], r.d[0], r.d[1],
                                            r.d[2], r.tmin, r.tmax, &ih, &is);
    const bool isame = ihit == hit && ih.prim == g.prim && SameBits(ih.t, g.t) &&
                       SameBits(ih.u, g.u) && SameBits(ih.v, g.v);
    if (!isame) {
      ++c->irregular_mismatch;
      INFO("irregular: o ", r.o[0], " ", r.o[1], " ", r.o[2], " d ", r.d[0], " ", r.d[1], " ",
           r.d[2], " grid prim ", g.prim, " t ", g.t, " irregular prim ", ih.prim, " t ", ih.t);
      CHECK(isame);
    }
    c->irregular_steps += is.cell_steps;
    CHECK(is.cell_steps <= uint64_t(irr.vres[0] + irr.vres[1] + irr.vres[2]));
    const bool iany = TraceAnyIrregular(irr, w.tris, r.o[0], r.o[1], r.o[2], r.d[0], r.d[1],
                                        r.d[2], r.tmin, r.tmax, nullptr);
    if (iany != bhit) {
      ++c->irregular_mismatch;
      CHECK(iany == bhit);
    }
  }
  const bool any = TraceAny(w.grid, w.tris, r.o[0], r.o[1], r.o[2], r.d[0], r.d[1], r.d[2],
                            r.tmin, r.tmax, nullptr);
  if (any != bhit) {
    ++c->any_mismatch;
    CHECK(any == bhit);
  }
  // against the double reference
  const MeshView mesh = w.soup.view();
  const ref::Ray rr = ref::MakeRay(r.o[0], r.o[1], r.o[2], r.d[0], r.d[1], r.d[2], r.tmin, r.tmax);
  const ref::Hit rh = ref::IntersectClosest(mesh, rr);
  if (rh.prim == g.prim) {
    if (hit) {
      double p[3][3];
      ref::TriangleVertices(mesh, size_t(g.prim), p);
      const double tol = test::TTolerance(rr, p, rh);
      if (!(std::fabs(g.t - rh.t) <= tol)) {
        ++c->ref_t_bad;
        CHECK(std::fabs(g.t - rh.t) <= tol);
      }
    }
    return;
  }
  // different answers: the reference's t for the grid's triangle must tie with its best, or
  // the difference is a float/double edge decision
  if (hit && rh.prim >= 0) {
    double p[3][3];
    ref::TriangleVertices(mesh, size_t(g.prim), p);
    ref::Hit mine;
    if (ref::IntersectTriangle(rr, p[0], p[1], p[2], HUGE_VAL, &mine) &&
        std::fabs(mine.t - rh.t) <= 1e-5 * std::fabs(rh.t)) {
      ++c->ref_ties;
      return;
    }
  }
  // Otherwise a float/double decision on one triangle: the reference's best when the grid
  // missed it or ordered it differently, else the grid's. It must lie within 1e-4
  // (barycentric) of an edge of that triangle, or its t within 1e-5 of tmin or tmax.
  const int32_t id = rh.prim >= 0 ? rh.prim : g.prim;
  double p[3][3];
  ref::TriangleVertices(mesh, size_t(id), p);
  const double od[3] = {r.o[0], r.o[1], r.o[2]}, dd[3] = {r.d[0], r.d[1], r.d[2]};
  double t_plane = 0.0, min_bary = 0.0;
  const bool decision =
      !test::PlaneHitDouble(od, dd, p, &t_plane, &min_bary) || std::fabs(min_bary) < 1e-4 ||
      std::fabs(t_plane - r.tmin) <= 1e-5 * std::fabs(t_plane) ||
      std::fabs(t_plane - r.tmax) <= 1e-5 * std::fabs(t_plane);
  if (decision) {
    ++c->ref_edge;
  } else {
    ++c->ref_bad;
    INFO("o ", r.o[0], " ", r.o[1], " ", r.o[2], " d ", r.d[0], " ", r.d[1], " ", r.d[2],
         " tmin ", r.tmin, " tmax ", r.tmax, " grid prim ", g.prim, " t ", g.t, " ref prim ",
         rh.prim, " t ", rh.t, " min bary ", min_bary);
    CHECK(decision);
  }
}

void Report(const Counts& c, const std::string& what, int max_decisions_per_1000 = 1) {
  MESSAGE(what, ": rays ", c.rays, ", hits ", c.hits, ", cell steps ", c.steps,
          ", triangle tests ", c.tests, "; vs float brute force: mismatches ", c.exact_mismatch,
          ", any-hit mismatches ", c.any_mismatch, "; vs double ref: ties ", c.ref_ties,
          ", edge/bound decisions ", c.ref_edge, ", other ", c.ref_bad, ", t out of tolerance ",
          c.ref_t_bad, "; irregular grids: cell steps ", c.irregular_steps, ", mismatches ",
          c.irregular_mismatch);
  CHECK(c.exact_mismatch == 0);
  CHECK(c.irregular_mismatch == 0);
  CHECK(c.any_mismatch == 0);
  CHECK(c.ref_bad == 0);
  CHECK(c.ref_t_bad == 0);
  CHECK(c.ref_edge <= max_decisions_per_1000 * c.rays / 1000 + 1);
}

Soup MixedSoup(Rng& rng, int small, int big) {
  Soup s = test::RandomSoup(rng, size_t(small), -1.0, 1.0, 0.15);
  const Soup b = test::RandomSoup(rng, size_t(big), -1.0, 1.0, 1.2);
  const uint32_t base = uint32_t(s.positions.size() / 3);
  s.positions.insert(s.positions.end(), b.positions.begin(), b.positions.end());
  for (const uint32_t i : b.indices) s.indices.push_back(i + base);
  return s;
}

// Random origin within the grid bounds grown by `grow` (fraction of the extent).
void RandomPoint(Rng& rng, const Grid& g, double grow, float o[3]) {
  for (int a = 0; a < 3; ++a) {
    const double ext = double(g.hi[a]) - g.lo[a];
    o[a] = rng.UniformF(g.lo[a] - grow * ext, g.hi[a] + grow * ext);
  }
}

// A ray from `o` aimed at a random point of a random triangle (so most rays hit something).
void AimAtTriangle(Rng& rng, const World& w, const float o[3], float d[3]) {
  const uint32_t i = rng.Below(uint32_t(w.tris.size));
  const double b1 = rng.Uniform(0, 1), b2 = rng.Uniform(0, 1 - b1);
  for (int a = 0; a < 3; ++a) {
    const double p0 = w.tris.p[0][a][i], p1 = w.tris.p[1][a][i], p2 = w.tris.p[2][a][i];
    d[a] = F(p0 + b1 * (p1 - p0) + b2 * (p2 - p0) - o[a]);
  }
}

TEST_CASE("random rays on random soups: identical to float brute force, consistent with ref") {
  Rng rng(1);
  for (const auto& [small, big, lambda] :
       {std::tuple{300, 10, 4.0f}, std::tuple{1000, 30, 4.0f}, std::tuple{1000, 30, 1.0f},
        std::tuple{200, 50, 16.0f}, std::tuple{3000, 0, 4.0f}}) {
    const World w(MixedSoup(rng, small, big), lambda);
    Counts c;
    for (int k = 0; k < 4000; ++k) {
      Ray r;
      RandomPoint(rng, w.grid, k % 2 ? 0.0 : 0.5, r.o);
      if (k % 3 == 0) {
        rng.Direction(r.d);
      } else {
        AimAtTriangle(rng, w, r.o, r.d);
      }
      if (k % 7 == 0) r.tmin = rng.UniformF(-0.5, 0.5);
      if (k % 11 == 0) r.tmax = rng.UniformF(0.0, 2.0);
      Check(w, r, &c);
    }
    Report(c, "soup " + std::to_string(small) + "+" + std::to_string(big) + " lambda " +
                  std::to_string(lambda) + " res " + std::to_string(w.grid.res[0]) + "x" +
                  std::to_string(w.grid.res[1]) + "x" + std::to_string(w.grid.res[2]));
    CHECK(c.hits > c.rays / 3);
  }
}

TEST_CASE("rays along each axis (+ and -) with +-0 components, from inside and outside") {
  Rng rng(2);
  const World w(MixedSoup(rng, 800, 20));
  Counts c;
  const float zeros[2] = {0.0f, -0.0f};
  for (int k = 0; k < 3000; ++k) {
    Ray r;
    RandomPoint(rng, w.grid, k % 2 ? 0.0 : 0.3, r.o);
    const int axis = k % 3;
    const float sign = (k / 3) % 2 ? 1.0f : -1.0f;
    for (int a = 0; a < 3; ++a) r.d[a] = zeros[(k / 6 + a) % 2];
    r.d[axis] = sign * rng.UniformF(0.5, 2.0);
    Check(w, r, &c);
  }
  Report(c, "axis rays");
  CHECK(c.hits > 100);
}

TEST_CASE("rays starting exactly on cell boundaries, corners and grid faces") {
  Rng rng(3);
  const World w(MixedSoup(rng, 600, 10));
  const Grid& g = w.grid;
  Counts c;
  for (int k = 0; k < 3000; ++k) {
    Ray r;
    for (int a = 0; a < 3; ++a) {
      // boundary i in [0, res]: i = 0 and i = res are the grid faces
      const int i = int(rng.Below(uint32_t(g.res[a] + 1)));
      const bool on_boundary = (k + a) % 3 != 0;  // some coordinates free, some on a boundary
      r.o[a] = on_boundary ? g.lo[a] + float(i) * g.cell_size[a]
                           : rng.UniformF(g.lo[a], g.hi[a]);
    }
    if (k % 4 == 0) {
      // axis-aligned along a boundary plane (+-0 in the other components)
      for (float& x : r.d) x = (k / 4) % 2 ? 0.0f : -0.0f;
      r.d[k % 3] = (k / 8) % 2 ? 1.0f : -1.0f;
    } else if (k % 4 == 1) {
      rng.Direction(r.d);
    } else {
      AimAtTriangle(rng, w, r.o, r.d);
    }
    Check(w, r, &c);
  }
  Report(c, "boundary origins");
  CHECK(c.hits > 500);
}

TEST_CASE("grazing the grid faces and edges, and rays that miss the grid") {
  Rng rng(4);
  const World w(MixedSoup(rng, 500, 10));
  const Grid& g = w.grid;
  Counts c;
  for (int k = 0; k < 2000; ++k) {
    Ray r;
    RandomPoint(rng, g, 0.0, r.o);
    const int a = k % 3, b = (k + 1) % 3;
    // in a face plane (lo or hi), moving parallel to it (d[a] = 0), or along an edge line
    r.o[a] = k % 2 ? g.lo[a] : g.hi[a];
    if (k % 5 == 0) r.o[b] = (k / 2) % 2 ? g.lo[b] : g.hi[b];
    rng.Direction(r.d);
    r.d[a] = (k / 3) % 2 ? 0.0f : -0.0f;
    if (k % 5 == 0) r.d[b] = 0.0f;
    Check(w, r, &c);
  }
  // just outside a face, parallel: misses the grid without stepping
  for (int k = 0; k < 300; ++k) {
    Ray r;
    RandomPoint(rng, g, 0.0, r.o);
    const int a = k % 3;
    r.o[a] = k % 2 ? std::nextafter(g.lo[a], -kInf) : std::nextafter(g.hi[a], kInf);
    rng.Direction(r.d);
    r.d[a] = 0.0f;
    TraceStats stats;
    RayHit h;
    CHECK_FALSE(TraceClosest(g, w.tris, r.o[0], r.o[1], r.o[2], r.d[0], r.d[1], r.d[2], 0.0f, kInf,
                             &h, &stats));
    CHECK(stats.cell_steps == 0);
    Check(w, r, &c);
  }
  // from outside, pointing away
  for (int k = 0; k < 300; ++k) {
    Ray r;
    RandomPoint(rng, g, 0.0, r.o);
    const int a = k % 3;
    const float ext = g.hi[a] - g.lo[a];
    r.o[a] = k % 2 ? g.lo[a] - ext : g.hi[a] + ext;
    rng.Direction(r.d);
    r.d[a] = std::fabs(r.d[a]) * (k % 2 ? -1.0f : 1.0f);
    TraceStats stats;
    RayHit h;
    CHECK_FALSE(TraceClosest(g, w.tris, r.o[0], r.o[1], r.o[2], r.d[0], r.d[1], r.d[2], 0.0f, kInf,
                             &h, &stats));
    CHECK(stats.cell_steps == 0);
  }
  Report(c, "grazing the grid");
}

TEST_CASE("grazing the geometry: rays in and just beside the faces of a box of triangles") {
  // An axis-aligned cube of 12 triangles plus clutter inside; rays in the face planes and one
  // ulp beside them, parallel to the faces.
  Soup s;
  const float v[8][3] = {{0, 0, 0}, {1, 0, 0}, {1, 1, 0}, {0, 1, 0},
                         {0, 0, 1}, {1, 0, 1}, {1, 1, 1}, {0, 1, 1}};
  const int faces[6][4] = {{0, 1, 2, 3}, {4, 5, 6, 7}, {0, 1, 5, 4},
                           {3, 2, 6, 7}, {0, 3, 7, 4}, {1, 2, 6, 5}};
  for (const auto& f : faces) {
    s.AddTriangle(v[f[0]], v[f[1]], v[f[2]]);
    s.AddTriangle(v[f[0]], v[f[2]], v[f[3]]);
  }
  Rng rng(6);
  const Soup inner = test::RandomSoup(rng, 200, 0.1, 0.9, 0.1);
  const uint32_t base = uint32_t(s.positions.size() / 3);
  s.positions.insert(s.positions.end(), inner.positions.begin(), inner.positions.end());
  for (const uint32_t i : inner.indices) s.indices.push_back(i + base);
  const World w(std::move(s));
  Counts c;
  int inside_rays = 0;
  for (int k = 0; k < 3000; ++k) {
    Ray r;
    const int a = k % 3;
    for (int b = 0; b < 3; ++b) r.o[b] = rng.UniformF(-0.5, 1.5);
    const float plane = (k / 3) % 2 ? 1.0f : 0.0f;
    const int shift = (k / 6) % 3;  // in the plane, one ulp inside, one ulp outside
    r.o[a] = shift == 0 ? plane : std::nextafter(plane, shift == 1 ? 0.5f : (plane - 0.5f) * kInf);
    rng.Direction(r.d);
    r.d[a] = (k / 18) % 2 ? 0.0f : -0.0f;
    Check(w, r, &c);
    // from inside the closed cube (one ulp inside a face, parallel to it), a ray must hit
    bool inside = shift == 1;
    for (int q = 0; q < 3; ++q) inside = inside && r.o[q] > 0.0f && r.o[q] < 1.0f;
    if (inside) {
      ++inside_rays;
      RayHit h;
      CHECK(TraceClosest(w.grid, w.tris, r.o[0], r.o[1], r.o[2], r.d[0], r.d[1], r.d[2], 0.0f,
                         kInf, &h, nullptr));
    }
  }
  // one ray in three runs one ulp beside a face: float and double decide its edges differently
  Report(c, "grazing the geometry", 20);
  CHECK(inside_rays > 100);
  CHECK(c.hits > 300);
}

TEST_CASE("NaN and infinite components never hit and never hang") {
  Rng rng(8);
  const World w(MixedSoup(rng, 500, 10));
  const float bad[] = {kNaN, kInf, -kInf};
  int traced = 0;
  for (int comp = 0; comp < 8; ++comp) {
    for (const float x : bad) {
      for (int k = 0; k < 50; ++k) {
        Ray r;
        RandomPoint(rng, w.grid, 0.2, r.o);
        AimAtTriangle(rng, w, r.o, r.d);
        if (comp < 3) r.o[comp] = x;
        else if (comp < 6) r.d[comp - 3] = x;
        else if (comp == 6) r.tmin = x == kInf ? 0.5f : x;  // NaN tmin, -inf tmin (valid)
        else r.tmax = x == -kInf ? kNaN : x;               // NaN or +inf tmax (valid)
        TraceStats stats;
        RayHit h;
        const bool hit = TraceClosest(w.grid, w.tris, r.o[0], r.o[1], r.o[2], r.d[0], r.d[1],
                                      r.d[2], r.tmin, r.tmax, &h, &stats);
        const bool any = TraceAny(w.grid, w.tris, r.o[0], r.o[1], r.o[2], r.d[0], r.d[1],
                                  r.d[2], r.tmin, r.tmax, nullptr);
        const bool valid_inf = (comp == 6 && x != kNaN && !std::isnan(x)) || (comp == 7 && x == kInf);
        if (!valid_inf) {
          INFO("component ", comp, " value ", x);
          CHECK_FALSE(hit);
          CHECK_FALSE(any);
          CHECK(h.prim == -1);
        } else {
          Counts c;
          Check(w, r, &c);
        }
        ++traced;
      }
    }
  }
  // zero and denormal directions, tmin >= tmax
  for (const float dz : {0.0f, -0.0f, 1e-38f, 1e-44f}) {
    RayHit h;
    CHECK_FALSE(TraceClosest(w.grid, w.tris, 0, 0, 0, 0.0f, -0.0f, dz, 0.0f, kInf, &h, nullptr));
    CHECK_FALSE(TraceAny(w.grid, w.tris, 0, 0, 0, 0.0f, -0.0f, dz, 0.0f, kInf, nullptr));
  }
  RayHit h;
  CHECK_FALSE(TraceClosest(w.grid, w.tris, 0, 0, 0, 0, 0, 1, 1.0f, 1.0f, &h, nullptr));
  CHECK_FALSE(TraceClosest(w.grid, w.tris, 0, 0, 0, 0, 0, 1, 2.0f, 1.0f, &h, nullptr));
  CHECK(traced == 8 * 3 * 50);  // reaching here proves no ray looped forever
}

TEST_CASE("flat scene, single triangle, empty grid, huge offset") {
  Rng rng(10);
  {
    Soup s;
    for (int i = 0; i < 400; ++i) {
      const double cx = rng.Uniform(-3, 3), cy = rng.Uniform(-3, 3);
      const float a[3] = {F(cx), F(cy), 0.0f}, b[3] = {F(cx + rng.Uniform(0.05, 0.4)), F(cy), 0.0f},
                  c3[3] = {F(cx), F(cy + rng.Uniform(0.05, 0.4)), 0.0f};
      s.AddTriangle(a, b, c3);
    }
    const World w(std::move(s));
    REQUIRE(w.grid.res[2] == 1);
    Counts c;
    for (int k = 0; k < 3000; ++k) {
      Ray r;
      RandomPoint(rng, w.grid, 0.2, r.o);
      r.o[2] = rng.UniformF(-2, 2);
      if (k % 2) AimAtTriangle(rng, w, r.o, r.d);
      else rng.Direction(r.d);
      Check(w, r, &c);
    }
    Report(c, "flat scene");
  }
  {
    Soup s;
    const float a[3] = {-1, -1, 0.5f}, b[3] = {1, -1, -0.5f}, c3[3] = {0, 1, 0.25f};
    s.AddTriangle(a, b, c3);
    const World w(std::move(s));
    Counts c;
    for (int k = 0; k < 1000; ++k) {
      Ray r;
      RandomPoint(rng, w.grid, 1.0, r.o);
      AimAtTriangle(rng, w, r.o, r.d);
      Check(w, r, &c);
    }
    Report(c, "single triangle");
    CHECK(c.hits > 900);
  }
  {
    const World w{Soup()};
    RayHit h;
    TraceStats stats;
    CHECK_FALSE(TraceClosest(w.grid, w.tris, 0, 0, 0, 1, 0, 0, 0.0f, kInf, &h, &stats));
    CHECK_FALSE(TraceAny(w.grid, w.tris, 0, 0, 0, 1, 0, 0, 0.0f, kInf, &stats));
    CHECK(stats.cell_steps == 0);
  }
  {
    Soup s = test::RandomSoup(rng, 500, 1e5, 1e5 + 10.0, 0.5);
    const World w(std::move(s));
    Counts c;
    for (int k = 0; k < 2000; ++k) {
      Ray r;
      RandomPoint(rng, w.grid, 0.3, r.o);
      if (k % 2) AimAtTriangle(rng, w, r.o, r.d);
      else rng.Direction(r.d);
      Check(w, r, &c);
    }
    Report(c, "offset 1e5");
  }
}

TEST_CASE("mailbox and candidate hits: a big triangle is tested once and its hit is kept") {
  // One big triangle in the plane z = 0.1 x, spanning the grid, plus clutter.
  Soup s;
  const float a[3] = {-10, -10, -1}, b[3] = {10, -10, 1}, c3[3] = {0, 10, 0};
  s.AddTriangle(a, b, c3);
  Rng rng(12);
  const Soup clutter = test::RandomSoup(rng, 300, -10.0, 10.0, 0.3);
  const uint32_t base = uint32_t(s.positions.size() / 3);
  s.positions.insert(s.positions.end(), clutter.positions.begin(), clutter.positions.end());
  for (const uint32_t i : clutter.indices) s.indices.push_back(i + base);
  const World w(std::move(s));
  // Rays skimming above the big triangle over many cells and crossing it near their end: the
  // triangle is listed in every cell on the way, tested in the first one (t beyond that cell:
  // kept as the candidate), skipped by the mailbox afterwards, and must be the answer.
  int checked = 0;
  for (int k = 0; k < 200; ++k) {
    Ray r;
    r.o[0] = rng.UniformF(-7, -5);
    r.o[1] = rng.UniformF(-8, -6);
    r.o[2] = F(0.1 * r.o[0] + 0.2);  // 0.2 above the plane
    const float target[3] = {rng.UniformF(4, 7), rng.UniformF(-8, -6), 0.0f};
    const float tz = F(0.1 * target[0] - 0.02);  // 0.02 below it: crossing at ~90 %
    r.d[0] = target[0] - r.o[0];
    r.d[1] = target[1] - r.o[1];
    r.d[2] = tz - r.o[2];
    TraceStats stats;
    RayHit h;
    const bool hit = TraceClosest(w.grid, w.tris, r.o[0], r.o[1], r.o[2], r.d[0], r.d[1],
                                  r.d[2], 0.0f, kInf, &h, &stats);
    RayHit bh;
    FloatBrute(w.tris, r, &bh);
    CHECK(hit);
    CHECK(h.prim == bh.prim);
    if (bh.prim == 0) {
      ++checked;
      CHECK(stats.cell_steps >= 4);  // many cells crossed before the hit cell
    }
    Counts c;
    Check(w, r, &c);
  }
  CHECK(checked > 100);
  // The big triangle alone near the ray (fillers far above make the grid 3D): every test on
  // this ray is the big triangle, and the mailbox makes it exactly one.
  Soup one;
  one.AddTriangle(a, b, c3);
  for (int i = 0; i < 50; ++i) {
    const float p[3] = {rng.UniformF(-10, 10), rng.UniformF(-10, 10), rng.UniformF(6, 10)};
    const float q[3] = {p[0] + 0.01f, p[1], p[2]}, u[3] = {p[0], p[1] + 0.01f, p[2]};
    one.AddTriangle(p, q, u);
  }
  const World w1(std::move(one));
  TraceStats stats;
  RayHit h;
  // gap above the plane 0.3 at x = -9, closing by 0.02 per unit x: hit at x = 6
  REQUIRE(TraceClosest(w1.grid, w1.tris, -9.0f, -4.0f, -0.6f, 1.0f, 0.0f, 0.08f, 0.0f, kInf, &h,
                       &stats));
  CHECK(h.prim == 0);
  CHECK(h.t == doctest::Approx(15.0f).epsilon(1e-5));
  MESSAGE("big triangle ray: cell steps ", stats.cell_steps, ", triangle tests ",
          stats.triangle_tests, " (grid ", w1.grid.res[0], "x", w1.grid.res[1], "x",
          w1.grid.res[2], ")");
  CHECK(stats.cell_steps >= 3);
  CHECK(stats.triangle_tests == 1);
}

}  // namespace
}  // namespace rs
