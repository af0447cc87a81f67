// Triangle bundles and the SIMD ray/triangle kernels (kernels/tri_intersect.h) on every compiled
// target vs their scalar oracles, bit for bit: random rays at unit, huge-offset and tiny scales,
// shared edges and vertices, degenerate and padding lanes, NaN/Inf rays, (tmin, tmax] bounds,
// stream padding sentinels, a watertightness stress on a closed icosphere at 1e5, and no
// self-hit of rays spawned from large triangles (the conference floor, pbrt's Reintersect).
#include <doctest/doctest.h>

#include <algorithm>
#include <array>
#include <cfloat>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <map>
#include <numeric>
#include <string>
#include <utility>
#include <vector>

#include "include/raystream/raystream.h"
#include "kernels/grid.h"
#include "kernels/tri_bundles.h"
#include "kernels/tri_intersect.h"
#include "kernels/triangle.h"
#include "streams/ray_stream.h"
#include "tests/kernels/geometry_util.h"
#include "tests/kernels/spawn_util.h"
#include "tests/support/watertight.h"
#include "tests/test_util.h"

namespace rs {
namespace {

using test::F;
using test::Rng;
using test::Soup;

using test::kInf;
using test::kNaN;
constexpr TriTest kTests[] = {TriTest::kWatertight, TriTest::kMollerTrumbore};
constexpr BundleWidth kWidths[] = {BundleWidth::kAuto, BundleWidth::kOne, BundleWidth::kTwo,
                                   BundleWidth::kFour};

std::string TestName(TriTest t) { return t == TriTest::kWatertight ? "watertight" : "moller"; }
int WidthLanes(BundleWidth w) { return w == BundleWidth::kAuto ? 0 : int(w) * 4; }

uint32_t Bits(float x) {
  uint32_t b;
  std::memcpy(&b, &x, sizeof(b));
  return b;
}
bool SameHit(const ClosestHit& a, const ClosestHit& b) {
  return Bits(a.t) == Bits(b.t) && Bits(a.u) == Bits(b.u) && Bits(a.v) == Bits(b.v) &&
         a.prim == b.prim;
}
std::string HitString(const ClosestHit& h) {
  return "{t " + std::to_string(h.t) + " u " + std::to_string(h.u) + " v " + std::to_string(h.v) +
         " prim " + std::to_string(h.prim) + "}";
}

// A triangle soup gathered into TriangleSoA, with bundles for id lists.
struct Scene {
  Soup soup;
  TriangleSoA tris;
  void Finish() { BuildTriangleSoA(soup.view(), &tris); }
};

// The scalar watertight test's edge functions of one ray and triangle, in float: true if one
// is exactly 0 (the double fallback runs). Used to prove the fallback path is exercised.
bool HasZeroEdge(const WatertightRay& r, const float p[3][3]) {
  const int k[3] = {r.kx, r.ky, r.kz};
  float x[3], y[3];
  for (int i = 0; i < 3; ++i) {
    const float z = p[i][k[2]] - r.o[2];
    x[i] = (p[i][k[0]] - r.o[0]) - r.sx * z;
    y[i] = (p[i][k[1]] - r.o[1]) - r.sy * z;
  }
  const float u = x[2] * y[1] - y[2] * x[1], v = x[0] * y[2] - y[0] * x[2];
  const float w = x[1] * y[0] - y[1] * x[0];
  return u == 0.0f || v == 0.0f || w == 0.0f;
}

// Mismatch counter with the first failure's description.
struct Mismatches {
  size_t count = 0;
  size_t checked = 0;
  std::string first;
  void Add(bool ok, const std::string& what) {
    ++checked;
    if (ok) return;
    if (count++ == 0) first = what;
  }
};

// Runs IntersectBundles and OccludedBundles with every test and width on the current target and
// compares with ref:: bit for bit. Returns the oracle's closest hits (per test) in *want.
void CompareBundles(const TriBundleSpan& span, const PreparedRay& ray, float tmin, float tmax,
                    const ClosestHit& prior, Mismatches* mm, ClosestHit want[2] = nullptr) {
  for (const TriTest test : kTests) {
    ClosestHit ref_hit = prior;
    const bool ref_changed = ref::IntersectBundles(ray, span, tmin, tmax, test, &ref_hit);
    const bool ref_any = ref::OccludedBundles(ray, span, tmin, tmax, test);
    if (want != nullptr) want[int(test)] = ref_hit;
    for (const BundleWidth width : kWidths) {
      ClosestHit got = prior;
      const bool changed = IntersectBundles(ray, span, tmin, tmax, test, width, &got);
      const bool any = OccludedBundles(ray, span, tmin, tmax, test, width);
      const std::string what =
          std::string(TestName(test)) + " width " + std::to_string(WidthLanes(width)) + " ray o (" +
          std::to_string(ray.o[0]) + ", " + std::to_string(ray.o[1]) + ", " +
          std::to_string(ray.o[2]) + ") got " + HitString(got) + " want " + HitString(ref_hit);
      mm->Add(changed == ref_changed && SameHit(got, ref_hit) && any == ref_any, what);
    }
  }
}

// A random ray through a random point of a random triangle of `s` (origin 0.5..3 sizes
// before it), or with probability 1/4 a random ray near the triangles.
PreparedRay RandomRay(Rng& rng, const Scene& s, double offset, double scale, float* tmin,
                      float* tmax) {
  float d[3];
  rng.Direction(d);
  double p[3];
  if (rng.Below(4) != 0) {
    const uint32_t id = rng.Below(uint32_t(s.tris.size));
    double b1 = rng.Uniform(-0.05, 1.05), b2 = rng.Uniform(-0.05, 1.05);
    if (b1 + b2 > 1.1) {
      b1 = 1.0 - b1;
      b2 = 1.0 - b2;
    }
    for (int a = 0; a < 3; ++a) {
      p[a] = s.tris.p[0][a][id] + b1 * (s.tris.p[1][a][id] - s.tris.p[0][a][id]) +
             b2 * (s.tris.p[2][a][id] - s.tris.p[0][a][id]);
    }
  } else {
    for (double& x : p) x = offset + rng.Uniform(-2, 2) * scale;
  }
  const double back = rng.Uniform(0.5, 3.0) * scale;
  float o[3];
  for (int a = 0; a < 3; ++a) o[a] = F(p[a] - back * d[a]);
  // mostly (0, inf); sometimes a window around the hit
  *tmin = 0.0f;
  *tmax = kInf;
  const uint32_t kind = rng.Below(8);
  if (kind == 0) *tmin = F(back * rng.Uniform(0.5, 1.5));
  if (kind == 1) *tmax = F(back * rng.Uniform(0.5, 1.5));
  if (kind == 2) *tmin = -kInf;
  return PrepareRay(o[0], o[1], o[2], d[0], d[1], d[2]);
}

TEST_CASE("bundles from a grid: per-cell ranges, id order, components, NaN padding lanes") {
  Rng rng(3);
  Scene s;
  s.soup = test::RandomSoup(rng, 500, -10, 10, 2.5);
  // a few degenerate triangles: never binned, so never in a bundle
  const float a[3] = {1, 2, 3}, b[3] = {2, 3, 4}, c[3] = {3, 4, 5};
  s.soup.AddTriangle(a, a, b);
  s.soup.AddTriangle(a, b, c);  // collinear
  s.Finish();
  REQUIRE(s.tris.num_degenerate == 2);
  Grid grid;
  BuildGrid(s.tris, 2.0f, 64, &grid);
  TriBundles bundles;
  BuildTriBundles(grid, s.tris, &bundles);
  REQUIRE(bundles.num_cells == grid.num_cells);
  CHECK(bundles.num_triangles == grid.num_refs);
  size_t total = 0, bad = 0, padding = 0;
  for (size_t cell = 0; cell < grid.num_cells; ++cell) {
    const size_t n = grid.cell_begin[cell + 1] - grid.cell_begin[cell];
    const TriBundleSpan span = bundles.Cell(cell);
    bad += span.count != (n + 3) / 4;
    bad += reinterpret_cast<uintptr_t>(span.vertices) % 16 != 0;
    total += span.count;
    for (size_t j = 0; j < span.lanes(); ++j) {
      if (j < n) {
        const uint32_t id = grid.tri_ids[grid.cell_begin[cell] + j];
        bad += span.ids[j] != int32_t(id);
        for (int v = 0; v < 3; ++v) {
          for (int ax = 0; ax < 3; ++ax) {
            bad += Bits(span.Component(v, ax)[j]) != Bits(s.tris.p[v][ax][id]);
          }
        }
      } else {
        ++padding;
        bad += span.ids[j] != -1;
        for (int v = 0; v < 3; ++v) {
          for (int ax = 0; ax < 3; ++ax) bad += !std::isnan(span.Component(v, ax)[j]);
        }
      }
    }
  }
  CHECK(bad == 0);
  CHECK(total == bundles.num_bundles);
  CHECK(padding > 0);
  CHECK(bundles.cell_begin[grid.num_cells] == bundles.num_bundles);
  MESSAGE("grid ", grid.res[0], "x", grid.res[1], "x", grid.res[2], ": ", grid.num_refs,
          " refs in ", bundles.num_bundles, " bundles (", padding, " padding lanes), ",
          bundles.Bytes(), " B");

  // a list with degenerate ids: NaN vertices (never hit) but the id is kept; rebuild reuses
  const uint32_t ids[] = {500, 3, 501, 3, 7};
  BuildTriBundleList(s.tris, ids, 5, &bundles);
  REQUIRE(bundles.num_cells == 1);
  const TriBundleSpan span = bundles.Cell(0);
  REQUIRE(span.count == 2);
  CHECK(span.ids[0] == 500);
  CHECK(span.ids[3] == 3);
  CHECK(span.ids[5] == -1);
  CHECK(std::isnan(span.Component(1, 2)[0]));
  CHECK(std::isnan(span.Component(0, 0)[2]));
  CHECK(span.Component(2, 1)[1] == s.tris.p[2][1][3]);
  CHECK(span.Component(2, 1)[4] == s.tris.p[2][1][7]);
  // rays exactly through the degenerate triangles' points never report them
  test::ForEachTarget([&](const char* target_name) {
    const std::string target = target_name;
    INFO("target: ", target);
    Rng ray_rng(4);
    size_t bad_hits = 0;
    for (int k = 0; k < 50; ++k) {
      const float o[3] = {F(std::round(ray_rng.Uniform(-4, 4) * 64) / 64),
                          F(std::round(ray_rng.Uniform(-4, 4) * 64) / 64), 8.0f};
      const float* target_point = k % 2 ? a : b;
      const PreparedRay ray = PrepareRay(o[0], o[1], o[2], target_point[0] - o[0],
                                         target_point[1] - o[1], target_point[2] - o[2]);
      for (const TriTest test : kTests) {
        for (const BundleWidth width : kWidths) {
          ClosestHit h;
          IntersectBundles(ray, span, -kInf, kInf, test, width, &h);
          bad_hits += h.prim == 500 || h.prim == 501;
        }
      }
    }
    CHECK(bad_hits == 0);
  });
  // empty grid and empty list
  Grid empty;
  BuildTriBundles(empty, s.tris, &bundles);
  CHECK(bundles.num_cells == 0);
  CHECK(bundles.num_bundles == 0);
  BuildTriBundleList(s.tris, ids, 0, &bundles);
  CHECK(bundles.Cell(0).count == 0);
  test::ForEachTarget([&](const char* target_name) {
    const std::string target = target_name;
    INFO("target: ", target);
    ClosestHit h;
    const PreparedRay ray = PrepareRay(0, 0, 0, 1, 0, 0);
    CHECK_FALSE(IntersectBundles(ray, bundles.Cell(0), 0.0f, kInf, TriTest::kWatertight,
                                 BundleWidth::kAuto, &h));
    CHECK(h.prim == -1);
  });
}

// Random rays against spans of 1..37 triangles (all step-downs of the wide loops), at unit
// scale, a 1e5 offset, a 1e-4 scale and a 1e3 scale at -3e4, with fresh and prior hits.
TEST_CASE("1 ray x bundles: random rays and triangles match the scalar tests bit for bit") {
  struct Config {
    double offset, scale;
  };
  const Config configs[] = {{0.0, 1.0}, {1e5, 1.0}, {0.0, 1e-4}, {-3e4, 1e3}};
  const size_t sizes[] = {1, 2, 3, 4, 5, 7, 8, 9, 12, 15, 16, 17, 20, 31, 37};
  Rng rng(101);
  for (const Config& cfg : configs) {
    INFO("offset ", cfg.offset, " scale ", cfg.scale);
    Scene s;
    s.soup = test::RandomSoup(rng, 37, cfg.offset - 2 * cfg.scale, cfg.offset + 2 * cfg.scale,
                              cfg.scale);
    s.Finish();
    std::vector<TriBundles> spans(std::size(sizes));
    for (size_t k = 0; k < std::size(sizes); ++k) {
      // ids in a shuffled order (a list may hold any order; ties must still pick the lowest id)
      std::vector<uint32_t> ids(sizes[k]);
      for (size_t j = 0; j < ids.size(); ++j) ids[j] = rng.Below(uint32_t(s.tris.size));
      BuildTriBundleList(s.tris, ids.data(), ids.size(), &spans[k]);
    }
    std::vector<PreparedRay> rays;
    std::vector<std::array<float, 2>> bounds;
    size_t zero_edges = 0;
    for (int i = 0; i < 400; ++i) {
      float tmin, tmax;
      rays.push_back(RandomRay(rng, s, cfg.offset, cfg.scale, &tmin, &tmax));
      bounds.push_back({tmin, tmax});
    }
    test::ForEachTarget([&](const char* target_name) {
      const std::string target = target_name;
      INFO("target: ", target);
      Mismatches mm;
      size_t hits = 0;
      for (size_t i = 0; i < rays.size(); ++i) {
        for (const TriBundles& p : spans) {
          ClosestHit want[2];
          CompareBundles(p.Cell(0), rays[i], bounds[i][0], bounds[i][1], ClosestHit{}, &mm, want);
          hits += want[0].prim >= 0;
          // a prior hit from another cell: exactly tied (the lower id must win), or closer
          if (want[0].prim >= 0) {
            ClosestHit tie = want[0];
            tie.prim = rng.Below(4) == 0 ? -1 : tie.prim + 1 - int32_t(rng.Below(3));
            CompareBundles(p.Cell(0), rays[i], bounds[i][0], bounds[i][1], tie, &mm);
            ClosestHit closer = want[0];
            closer.t = want[0].t * 0.999f;
            closer.prim = 1000;
            CompareBundles(p.Cell(0), rays[i], bounds[i][0], bounds[i][1], closer, &mm);
          }
        }
      }
      INFO("first mismatch: ", mm.first);
      CHECK(mm.count == 0);
      CHECK(hits > rays.size());  // the test is not vacuous
    });
    // exact-zero edge functions occur at these scales (the double fallback is exercised below
    // by the edge/vertex cases; here we only report how often)
    for (size_t i = 0; i < rays.size(); ++i) {
      for (size_t id = 0; id < s.tris.size; ++id) {
        float p[3][3];
        for (int v = 0; v < 3; ++v) {
          for (int a = 0; a < 3; ++a) p[v][a] = s.tris.p[v][a][id];
        }
        zero_edges += HasZeroEdge(rays[i].wt, p);
      }
    }
    MESSAGE("offset ", cfg.offset, " scale ", cfg.scale, ": ", zero_edges,
            " ray/triangle pairs with an exact-zero edge function");
  }
}

// Ties inside one vector: duplicated geometry under several ids, listed in descending order.
TEST_CASE("1 ray x bundles: equal t in several lanes -> the lowest id wins, on every width") {
  Scene s;
  const float p0[3] = {0, 0, 0}, p1[3] = {1, 0, 0}, p2[3] = {0, 1, 0};
  for (int k = 0; k < 12; ++k) s.soup.AddTriangle(p0, p1, p2);
  s.Finish();
  const uint32_t ids[] = {11, 10, 9, 8, 7, 6, 5, 4, 3, 2, 1, 0};
  TriBundles bundles;
  for (size_t n : {2, 5, 9, 12}) {
    BuildTriBundleList(s.tris, ids + 12 - n, n, &bundles);  // the n lowest ids, descending
    const PreparedRay ray = PrepareRay(0.25f, 0.25f, 1.0f, 0.0f, 0.0f, -1.0f);
    test::ForEachTarget([&](const char* target_name) {
      const std::string target = target_name;
      INFO("target: ", target, " n ", n);
      for (const TriTest test : kTests) {
        for (const BundleWidth width : kWidths) {
          ClosestHit h;
          CHECK(IntersectBundles(ray, bundles.Cell(0), 0.0f, kInf, test, width, &h));
          CHECK(h.prim == 0);
          CHECK(h.t == 1.0f);
          // a prior hit at the same t with a lower id is kept
          ClosestHit prior;
          prior.t = 1.0f;
          prior.prim = 0;
          CHECK_FALSE(IntersectBundles(ray, bundles.Cell(0), 0.0f, kInf, test, width, &prior));
        }
      }
    });
  }
}

// Two triangles sharing an edge, a fan sharing a vertex: rays exactly through the shared
// points. Watertight: some triangle is hit every time (and the hit matches the scalar test,
// which exercises the double fallback: the edge function of the shared edge is exactly 0).
TEST_CASE("1 ray x bundles: rays through shared edges and vertices never miss (watertight)") {
  Scene s;
  // quad split along its diagonal, and a 6-triangle fan around (0.5, 0.5, 2)
  const float q0[3] = {0, 0, 0}, q1[3] = {1, 0, 0}, q2[3] = {1, 1, 0}, q3[3] = {0, 1, 0};
  s.soup.AddTriangle(q0, q1, q2);
  s.soup.AddTriangle(q0, q2, q3);
  const float apex[3] = {0.5f, 0.5f, 2.0f};
  float ring[6][3];
  for (int i = 0; i < 6; ++i) {
    const double a = 6.283185307179586 * (i + 0.1 * (i % 3)) / 6;
    ring[i][0] = F(std::round((0.5 + std::cos(a)) * 256) / 256);
    ring[i][1] = F(std::round((0.5 + std::sin(a)) * 256) / 256);
    ring[i][2] = 2.0f + 0.25f * float(i % 2);
  }
  for (int i = 0; i < 6; ++i) s.soup.AddTriangle(apex, ring[i], ring[(i + 1) % 6]);
  s.Finish();
  const uint32_t quad[] = {0, 1}, fan[] = {2, 3, 4, 5, 6, 7};
  TriBundles quad_bundles, fan_bundles;
  BuildTriBundleList(s.tris, quad, 2, &quad_bundles);
  BuildTriBundleList(s.tris, fan, 6, &fan_bundles);
  Rng rng(17);
  std::vector<std::pair<PreparedRay, int>> rays;  // ray, 0 = quad diagonal, 1 = fan apex
  size_t zero_edges = 0;
  for (int k = 0; k < 300; ++k) {
    // origins on a 2^-8 lattice, targets exact: o + d hits the target exactly
    const float o[3] = {F(std::round(rng.Uniform(-2, 3) * 256) / 256),
                        F(std::round(rng.Uniform(-2, 3) * 256) / 256),
                        F(std::round(rng.Uniform(1, 4) * 256) / 256)};
    const float along = F(std::round(rng.Uniform(0, 1) * 256) / 256);
    const float diag[3] = {along, along, 0.0f};  // on the shared diagonal q0-q2
    const float dd[3] = {diag[0] - o[0], diag[1] - o[1], diag[2] - o[2]};
    rays.push_back({PrepareRay(o[0], o[1], o[2], dd[0], dd[1], dd[2]), 0});
    const float oa[3] = {o[0], o[1], o[2] + 2.5f};  // above the fan
    const float da[3] = {apex[0] - oa[0], apex[1] - oa[1], apex[2] - oa[2]};
    rays.push_back({PrepareRay(oa[0], oa[1], oa[2], da[0], da[1], da[2]), 1});
  }
  for (const auto& [ray, which] : rays) {
    const auto& list = which == 0 ? quad : fan;
    const size_t n = which == 0 ? 2 : 6;
    for (size_t j = 0; j < n; ++j) {
      float p[3][3];
      for (int v = 0; v < 3; ++v) {
        for (int a = 0; a < 3; ++a) p[v][a] = s.tris.p[v][a][list[j]];
      }
      zero_edges += HasZeroEdge(ray.wt, p);
    }
  }
  MESSAGE(zero_edges, " ray/triangle pairs with an exact-zero edge function");
  CHECK(zero_edges > 100);  // the double fallback really runs
  test::ForEachTarget([&](const char* target_name) {
    const std::string target = target_name;
    INFO("target: ", target);
    Mismatches mm;
    size_t misses = 0, moller_misses = 0;
    for (const auto& [ray, which] : rays) {
      const TriBundleSpan span = which == 0 ? quad_bundles.Cell(0) : fan_bundles.Cell(0);
      ClosestHit want[2];
      CompareBundles(span, ray, 0.0f, kInf, ClosestHit{}, &mm, want);
      for (const BundleWidth width : kWidths) {
        ClosestHit h;
        misses += !IntersectBundles(ray, span, 0.0f, kInf, TriTest::kWatertight, width, &h);
        misses += !OccludedBundles(ray, span, 0.0f, kInf, TriTest::kWatertight, width);
      }
      moller_misses += want[1].prim < 0;
    }
    INFO("first mismatch: ", mm.first);
    CHECK(mm.count == 0);
    CHECK(misses == 0);
    MESSAGE(target, ": Moller-Trumbore misses through shared edges/vertices: ", moller_misses,
            " of ", rays.size());
  });
}

TEST_CASE("1 ray x bundles: NaN/Inf/zero rays, NaN bounds and (tmin, tmax] limits") {
  Scene s;
  const float p0[3] = {0, 0, 0}, p1[3] = {1, 0, 0}, p2[3] = {0, 1, 0};
  s.soup.AddTriangle(p0, p1, p2);
  s.Finish();
  const uint32_t id0 = 0;
  TriBundles bundles;
  BuildTriBundleList(s.tris, &id0, 1, &bundles);
  const TriBundleSpan span = bundles.Cell(0);
  // the hit of (0.25, 0.25, 2) + t (0, 0, -1) is t = 2 exactly
  const float two_below = std::nextafter(2.0f, 0.0f);
  struct Case {
    float o[3], d[3], tmin, tmax;
    bool hit;
  };
  const Case cases[] = {
      {{0.25f, 0.25f, 2}, {0, 0, -1}, 0, kInf, true},
      {{0.25f, 0.25f, 2}, {0, 0, -1}, 0, 2.0f, true},        // tmax inclusive
      {{0.25f, 0.25f, 2}, {0, 0, -1}, 0, two_below, false},  // just short
      {{0.25f, 0.25f, 2}, {0, 0, -1}, 2.0f, kInf, false},    // tmin exclusive
      {{0.25f, 0.25f, 2}, {0, 0, -1}, two_below, 3.0f, true},
      {{0.25f, 0.25f, 2}, {0, 0, -1}, 3.0f, 1.0f, false},  // empty interval
      {{0.25f, 0.25f, 2}, {0, 0, -1}, kNaN, kInf, false},
      {{0.25f, 0.25f, 2}, {0, 0, -1}, 0, kNaN, false},
      {{kNaN, 0.25f, 2}, {0, 0, -1}, 0, kInf, false},
      {{0.25f, kInf, 2}, {0, 0, -1}, 0, kInf, false},
      {{0.25f, 0.25f, 2}, {0, kNaN, -1}, 0, kInf, false},
      {{0.25f, 0.25f, 2}, {0, 0, -kInf}, 0, kInf, false},
      {{0.25f, 0.25f, 2}, {0, 0, 0}, 0, kInf, false},        // zero direction
      {{0.25f, 0.25f, 2}, {0, 0, -1e-31f}, 0, kInf, false},  // |d| < kMinDirection
      {{0.25f, 0.25f, 2}, {0, 0, -1e-20f}, 0, kInf, true},   // tiny but valid: t = 2e20
      {{0.25f, 0.25f, 2}, {0, 0, -1e-38f}, 0, kInf, false},  // t would overflow
      {{0.25f, 0.25f, 2}, {0, 0, 1}, 0, kInf, false},        // pointing away
      {{0.25f, 0.25f, 2}, {0, 0, 1}, -kInf, kInf, true},     // ... but t < 0 allowed
      {{0.25f, 0.25f, 0}, {1, 0, 0}, -kInf, kInf, false},    // in the plane (det = 0)
  };
  test::ForEachTarget([&](const char* target_name) {
    const std::string target = target_name;
    INFO("target: ", target);
    for (const Case& c : cases) {
      INFO("o ", c.o[0], " ", c.o[1], " ", c.o[2], " d ", c.d[0], " ", c.d[1], " ", c.d[2],
           " tmin ", c.tmin, " tmax ", c.tmax);
      const PreparedRay ray = PrepareRay(c.o[0], c.o[1], c.o[2], c.d[0], c.d[1], c.d[2]);
      for (const TriTest test : kTests) {
        INFO(TestName(test));
        for (const BundleWidth width : kWidths) {
          ClosestHit h;
          CHECK(IntersectBundles(ray, span, c.tmin, c.tmax, test, width, &h) == c.hit);
          CHECK(OccludedBundles(ray, span, c.tmin, c.tmax, test, width) == c.hit);
          CHECK((h.prim == 0) == c.hit);
        }
        ClosestHit r;
        CHECK(ref::IntersectBundles(ray, span, c.tmin, c.tmax, test, &r) == c.hit);
      }
    }
  });
}

// Regression: Moller-Trumbore with a finite pvec but det = e1 . pvec overflowing to +inf gives
// inv_det = 0 and u = v = t = 0, a bogus hit at t = 0 unless det is required to be finite.
TEST_CASE("regression: Moller-Trumbore rejects an overflowed det; watertight matches scalar") {
  Scene s;
  const float p0[3] = {0, 0, 0}, p1[3] = {100, 0, 0}, p2[3] = {0, 10, 0};
  s.soup.AddTriangle(p0, p1, p2);
  s.Finish();
  const uint32_t id0 = 0;
  TriBundles bundles;
  BuildTriBundleList(s.tris, &id0, 1, &bundles);
  // pvec = d x e2 = (1e38, 0, 0); det = 100 * 1e38 = inf
  const PreparedRay ray = PrepareRay(0.5f, 0.0f, 1.0f, 0.0f, 0.0f, -1e37f);
  ClosestHit want_wt;
  const bool wt =
      ref::IntersectBundles(ray, bundles.Cell(0), -kInf, kInf, TriTest::kWatertight, &want_wt);
  ClosestHit want_mt;
  CHECK_FALSE(
      ref::IntersectBundles(ray, bundles.Cell(0), -kInf, kInf, TriTest::kMollerTrumbore, &want_mt));
  RayStream rays(1);
  rays.Push(0.5f, 0.0f, 1.0f, 0.0f, 0.0f, -1e37f, -kInf, kInf, 0, 1, 1, 1, 0, RayKind::kPrimary);
  HitStream hits(1);
  hits.Resize(1);
  test::ForEachTarget([&](const char* target_name) {
    const std::string target = target_name;
    INFO("target: ", target);
    for (const BundleWidth width : kWidths) {
      ClosestHit h;
      CHECK_FALSE(
          IntersectBundles(ray, bundles.Cell(0), -kInf, kInf, TriTest::kMollerTrumbore, width, &h));
      CHECK_FALSE(
          OccludedBundles(ray, bundles.Cell(0), -kInf, kInf, TriTest::kMollerTrumbore, width));
      ClosestHit hw;
      CHECK(IntersectBundles(ray, bundles.Cell(0), -kInf, kInf, TriTest::kWatertight, width, &hw) ==
            wt);
      CHECK(SameHit(hw, want_wt));
    }
    hits.Reset();
    IntersectStream(rays.view(), bundles.Cell(0), TriTest::kMollerTrumbore, hits.view());
    CHECK(hits.view().prim[0] == -1);
  });
}

// ---------------------------------------------------------------------------------------------
// N rays x triangles

// Sentinels for the padding lanes of hit streams (dav1d's 0x88 trick): any write shows. The
// t sentinel is beyond every hit and the prim sentinel is negative ("none"), so they do not
// stop a kernel that ignores FirstN from writing there (the padding rays hit, too).
constexpr float kSentinelT = 1.5e38f;
constexpr float kSentinelUv = -777.0f;
constexpr int32_t kSentinelPrim = int32_t(0x88888888u);

struct StreamCase {
  RayStream rays;
  HitStream hits;
  std::vector<float> t0, u0, v0;  // initial hits (copied to the stream before each run)
  std::vector<int32_t> prim0;
};

// n rays: coherent (all d ~ -z: one permutation) or mixed; some rays invalid or with windows.
// Padding rays are copies of ray 0 (valid, hitting): a kernel that ignores FirstN would write.
void MakeStream(Rng& rng, const Scene& s, size_t n, bool coherent, bool prior, StreamCase* c) {
  c->rays = RayStream(n);
  for (size_t i = 0; i < n; ++i) {
    float tmin, tmax;
    PreparedRay r = RandomRay(rng, s, 0.0, 1.0, &tmin, &tmax);
    if (coherent) {
      r = PrepareRay(r.o[0], r.o[1], F(r.o[2] + 3.0), F(0.1 * r.d[0]), F(0.1 * r.d[1]), -1.0f);
    }
    if (rng.Below(16) == 0) r.o[rng.Below(3)] = rng.Below(2) ? kNaN : -kInf;
    if (rng.Below(32) == 0) r.d[0] = r.d[1] = r.d[2] = 0.0f;
    c->rays.Push(r.o[0], r.o[1], r.o[2], r.d[0], r.d[1], r.d[2], tmin, tmax, uint32_t(i), 1, 1, 1,
                 0, RayKind::kPrimary);
  }
  RayStreamView v = c->rays.view();
  const size_t cap = c->rays.capacity();
  for (size_t i = n; i < cap; ++i) {
    v.ox[i] = n > 0 ? v.ox[0] : 0.25f;
    v.oy[i] = n > 0 ? v.oy[0] : 0.25f;
    v.oz[i] = n > 0 ? v.oz[0] : 2.0f;
    v.dx[i] = n > 0 ? v.dx[0] : 0.0f;
    v.dy[i] = n > 0 ? v.dy[0] : 0.0f;
    v.dz[i] = n > 0 ? v.dz[0] : -1.0f;
    v.tmin[i] = 0.0f;
    v.tmax[i] = kInf;
  }
  c->hits = HitStream(n);
  c->hits.Resize(n);
  c->hits.Reset();
  const size_t hcap = PaddedSize(n);
  c->t0.assign(hcap, kSentinelT);
  c->u0.assign(hcap, kSentinelUv);
  c->v0.assign(hcap, kSentinelUv);
  c->prim0.assign(hcap, kSentinelPrim);
  for (size_t i = 0; i < n; ++i) {
    c->t0[i] = kInf;
    c->u0[i] = c->v0[i] = 0.0f;
    c->prim0[i] = -1;
    if (prior && rng.Below(3) == 0) {  // a hit from an earlier cell
      c->t0[i] = F(rng.Uniform(0.5, 3.0));
      c->u0[i] = 0.5f;
      c->prim0[i] = int32_t(rng.Below(40));
    }
  }
}

void LoadHits(StreamCase* c) {
  const HitStreamView h = c->hits.view();
  for (size_t i = 0; i < c->t0.size(); ++i) {
    h.t[i] = c->t0[i];
    h.u[i] = c->u0[i];
    h.v[i] = c->v0[i];
    h.prim[i] = c->prim0[i];
  }
}

TEST_CASE("N rays x triangles: sizes 1, N-1, N+1, coherent and mixed rays, padding sentinels") {
  Rng rng(202);
  Scene s;
  s.soup = test::RandomSoup(rng, 40, -2, 2, 1.0);
  s.Finish();
  std::vector<uint32_t> all(40);
  std::iota(all.begin(), all.end(), 0u);
  TriBundles one, several, everything;
  BuildTriBundleList(s.tris, all.data() + 7, 1, &one);
  BuildTriBundleList(s.tris, all.data() + 3, 6, &several);
  BuildTriBundleList(s.tris, all.data(), 40, &everything);
  const TriBundles* spans[] = {&one, &several, &everything};
  // sizes around every vector width (1 lane on SCALAR, 4, 8, 16), and the empty stream
  const size_t sizes[] = {0, 1, 2, 3, 4, 5, 7, 8, 9, 15, 16, 17, 31, 33, 200};
  for (const size_t n : sizes) {
    for (const bool coherent : {false, true}) {
      for (const int prior : {0, 1, 2}) {  // fresh hits, earlier hits, exact ties
        StreamCase c;
        MakeStream(rng, s, n, coherent, prior == 1, &c);
        for (const TriBundles* p : spans) {
          for (const TriTest test : kTests) {
            const HitStreamView h = c.hits.view();
            if (prior == 2) {
              // priors at exactly the oracle's t, with prim -1 (none: +inf), id - 1, id, id + 1
              for (size_t i = 0; i < n; ++i) {
                c.t0[i] = kInf;
                c.prim0[i] = -1;
              }
              LoadHits(&c);
              ref::IntersectStream(c.rays.view(), p->Cell(0), test, h);
              for (size_t i = 0; i < n; ++i) {
                if (h.prim[i] < 0) continue;
                c.t0[i] = h.t[i];
                c.prim0[i] = h.prim[i] + int32_t(rng.Below(3)) - 1;
                if (rng.Below(4) == 0) c.prim0[i] = -1;
              }
            }
            // the oracle's answers
            LoadHits(&c);
            ref::IntersectStream(c.rays.view(), p->Cell(0), test, h);
            const std::vector<float> want_t(h.t, h.t + c.t0.size());
            const std::vector<float> want_u(h.u, h.u + c.t0.size());
            const std::vector<float> want_v(h.v, h.v + c.t0.size());
            const std::vector<int32_t> want_prim(h.prim, h.prim + c.t0.size());
            size_t changed = 0;
            for (size_t i = 0; i < n; ++i) changed += want_prim[i] != c.prim0[i];
            test::ForEachTarget([&](const char* target_name) {
              const std::string target = target_name;
              INFO("target: ", target, " n ", n, " coherent ", coherent, " prior ", prior,
                   " triangles ", p->num_triangles, " ", TestName(test));
              LoadHits(&c);
              IntersectStream(c.rays.view(), p->Cell(0), test, h);
              size_t bad = 0, bad_padding = 0;
              for (size_t i = 0; i < c.t0.size(); ++i) {
                const bool same = Bits(h.t[i]) == Bits(want_t[i]) &&
                                  Bits(h.u[i]) == Bits(want_u[i]) &&
                                  Bits(h.v[i]) == Bits(want_v[i]) && h.prim[i] == want_prim[i];
                (i < n ? bad : bad_padding) += !same;
                if (i >= n) {
                  bad_padding += h.t[i] != kSentinelT || h.prim[i] != kSentinelPrim ||
                                 h.u[i] != kSentinelUv || h.v[i] != kSentinelUv;
                }
              }
              CHECK(bad == 0);
              CHECK(bad_padding == 0);
            });
            if (n >= 31 && p == &everything && prior != 2) CHECK(changed > 0);  // not vacuous
          }
        }
      }
    }
  }
}

// ---------------------------------------------------------------------------------------------
// Self-hits: the watertight test's t bound (pbrt-v4 6.8.7) on every target and path

// Regression (conference): the literal floor rays (tests/kernels/spawn_util.h) never hit the
// floor quad on any target: 1 ray x bundles at every width (closest and any hit), N rays x 1
// triangle (the stream and its broadcast triangle), and the scalar oracle; bit for bit equal
// to the oracle with tmin < 0 too, where the bound is off and the old false hit shows.
TEST_CASE("regression: conference floor, rays 3.05e-5 above it pointing away, every target") {
  Scene s;
  s.soup.AddTriangle(test::kFloorA, test::kFloorB, test::kFloorC);  // 59
  s.soup.AddTriangle(test::kFloorB, test::kFloorD, test::kFloorC);  // 60
  s.Finish();
  const uint32_t ids[] = {0, 1};
  TriBundles bundles;
  BuildTriBundleList(s.tris, ids, 2, &bundles);
  const TriBundleSpan span = bundles.Cell(0);
  // the literal shadow rays, and the same with unit directions (reflection rays)
  std::vector<std::array<float, 6>> rays;
  for (const test::FloorRay& r : test::kFloorRays) {
    rays.push_back({r.o[0], r.o[1], r.o[2], r.d[0], r.d[1], r.d[2]});
    const double len = std::sqrt(double(r.d[0]) * r.d[0] + double(r.d[1]) * r.d[1] +
                                 double(r.d[2]) * r.d[2]);
    rays.push_back({r.o[0], r.o[1], r.o[2], F(r.d[0] / len), F(r.d[1] / len), F(r.d[2] / len)});
  }
  RayStream stream(rays.size());
  for (const auto& r : rays) {
    stream.Push(r[0], r[1], r[2], r[3], r[4], r[5], 0.0f, test::kFloorRayTmax, 0, 1, 1, 1, 1,
                RayKind::kShadow);
  }
  stream.FillPadding();
  HitStream hits(rays.size());
  hits.Resize(rays.size());
  size_t unbounded = 0;
  for (const auto& r : rays) {
    const PreparedRay ray = PrepareRay(r[0], r[1], r[2], r[3], r[4], r[5]);
    ClosestHit h;
    CHECK_FALSE(ref::IntersectBundles(ray, span, 0.0f, kInf, TriTest::kWatertight, &h));
    CHECK_FALSE(ref::OccludedBundles(ray, span, 0.0f, test::kFloorRayTmax, TriTest::kWatertight));
    ClosestHit hb;
    unbounded += ref::IntersectBundles(ray, span, -1e-30f, kInf, TriTest::kWatertight, &hb);
  }
  CHECK(unbounded >= std::size(test::kFloorRays));  // the literal rays: the old false hits
  test::ForEachTarget([&](const char* target_name) {
    const std::string target = target_name;
    INFO("target: ", target);
    Mismatches mm;
    for (const auto& r : rays) {
      const PreparedRay ray = PrepareRay(r[0], r[1], r[2], r[3], r[4], r[5]);
      for (const BundleWidth width : kWidths) {
        ClosestHit h;
        CHECK_FALSE(IntersectBundles(ray, span, 0.0f, kInf, TriTest::kWatertight, width, &h));
        CHECK(h.prim == -1);
        CHECK_FALSE(
            OccludedBundles(ray, span, 0.0f, test::kFloorRayTmax, TriTest::kWatertight, width));
      }
      CompareBundles(span, ray, 0.0f, test::kFloorRayTmax, ClosestHit{}, &mm);
      CompareBundles(span, ray, -1e-30f, kInf, ClosestHit{}, &mm);
    }
    INFO("first mismatch: ", mm.first);
    CHECK(mm.count == 0);
    hits.Reset();
    IntersectStream(stream.view(), span, TriTest::kWatertight, hits.view());
    for (size_t i = 0; i < rays.size(); ++i) CHECK(hits.view().prim[i] == -1);
  });
}

// pbrt's Reintersect on every target: per triangle (large: edges 1e3..1e4, centres up to 1e5
// from the origin; and unit ones), rays spawned from its points with OffsetRayOrigin, pointing
// away, never hit it: 1 ray x bundles (every width, closest and any), N rays x 1 triangle (the
// triangle's rays as one stream), all bit for bit equal to the scalar oracle.
TEST_CASE("no self-hit: spawned rays never hit their large triangle, every target and path") {
  struct Config {
    double size, offset;
  };
  const Config configs[] = {{1e3, 0.0}, {1e3, 1e4}, {1e4, 3e4}, {2e3, 1e5}, {1.0, 1e2}};
  const size_t num_tris = test::kSlowBuild ? 20 : 100;
  constexpr size_t kRaysPerTri = 37;  // a stream of 37: full vectors and a tail on every width
  Rng rng(4242);
  for (const Config& c : configs) {
    INFO("size ", c.size, " offset ", c.offset);
    Scene s;
    std::vector<std::vector<test::SpawnedRay>> rays(num_tris);
    size_t skipped = 0;
    for (size_t k = 0; k < num_tris; ++k) {
      const test::SpawnTriangle t = test::MakeSpawnTriangle(rng, c.size, c.offset);
      s.soup.AddTriangle(t.p[0], t.p[1], t.p[2]);
      while (rays[k].size() < kRaysPerTri) {
        const test::SpawnedRay r = test::SpawnRay(rng, t, c.size);
        if (r.above) {
          rays[k].push_back(r);
        } else {
          ++skipped;
        }
      }
    }
    s.Finish();
    CHECK(skipped <= num_tris * kRaysPerTri / 1000);
    std::vector<TriBundles> spans(num_tris);
    std::vector<RayStream> streams(num_tris);
    size_t unbounded = 0;
    for (size_t k = 0; k < num_tris; ++k) {
      const uint32_t id = uint32_t(k);
      BuildTriBundleList(s.tris, &id, 1, &spans[k]);
      streams[k] = RayStream(kRaysPerTri);
      for (const test::SpawnedRay& r : rays[k]) {
        streams[k].Push(r.o[0], r.o[1], r.o[2], r.d[0], r.d[1], r.d[2], 0.0f, kInf, 0, 1, 1, 1, 1,
                        RayKind::kShadow);
        ClosestHit hb;
        unbounded +=
            ref::IntersectBundles(PrepareRay(r.o[0], r.o[1], r.o[2], r.d[0], r.d[1], r.d[2]),
                                  spans[k].Cell(0), -1e-30f, kInf, TriTest::kWatertight, &hb) &&
            hb.t > 0.0f;
      }
      streams[k].FillPadding();
    }
    MESSAGE("size ", c.size, " offset ", c.offset, ": ", num_tris * kRaysPerTri,
            " spawned rays; without the t bound ", unbounded, " would hit their own triangle; ",
            skipped, " origins not above the plane (skipped)");
    if (c.size >= 1e3) CHECK(unbounded > 0);  // not vacuous
    HitStream hits(kRaysPerTri);
    hits.Resize(kRaysPerTri);
    test::ForEachTarget([&](const char* target_name) {
      const std::string target = target_name;
      INFO("target: ", target);
      Mismatches mm;
      size_t rehits = 0, stream_rehits = 0;
      for (size_t k = 0; k < num_tris; ++k) {
        const TriBundleSpan span = spans[k].Cell(0);
        for (const test::SpawnedRay& r : rays[k]) {
          const PreparedRay ray = PrepareRay(r.o[0], r.o[1], r.o[2], r.d[0], r.d[1], r.d[2]);
          for (const BundleWidth width : kWidths) {
            ClosestHit h;
            rehits += IntersectBundles(ray, span, 0.0f, kInf, TriTest::kWatertight, width, &h);
            rehits += OccludedBundles(ray, span, 0.0f, kInf, TriTest::kWatertight, width);
          }
          CompareBundles(span, ray, 0.0f, kInf, ClosestHit{}, &mm);
          CompareBundles(span, ray, -1e-30f, kInf, ClosestHit{}, &mm);  // the bound off
        }
        hits.Reset();
        IntersectStream(streams[k].view(), span, TriTest::kWatertight, hits.view());
        for (size_t i = 0; i < kRaysPerTri; ++i) stream_rehits += hits.view().prim[i] >= 0;
      }
      INFO("first mismatch: ", mm.first);
      CHECK(mm.count == 0);
      CHECK(rehits == 0);
      CHECK(stream_rehits == 0);
    });
  }
}

// ---------------------------------------------------------------------------------------------
// Watertightness stress: 1e6 rays (1e5 in debug and sanitizer builds) from
// inside a closed 81920-triangle icosphere at (1e5, 1e5, 1e5), aimed exactly at its vertices and
// edge midpoints (tests/support/watertight.h). Each ray is tested against the triangles around
// its target (the vertex fan or the edge's two triangles) on every target, 1 x bundles at each
// width and N x 1; the watertight kernels never miss and agree with the scalar oracle ray by ray;
// rs::Accel, tracing the whole mesh, never misses either. bench/kernels/robust_bench adds
// Embree's counts beside ours.
TEST_CASE(
    "watertight stress: 1e6 rays from inside a closed icosphere at 1e5 through its "
    "vertices and edge midpoints") {
  const size_t num_rays = test::kSlowBuild ? 100000 : 1000000;
  test::WatertightSetup ws;
  const std::string error = test::MakeWatertightSetup(6, num_rays, &ws);
  REQUIRE(error.empty());
  REQUIRE(ws.ico.tri.size() == 81920);
  const RayStreamView rv = ws.rays.view();
  REQUIRE(rv.size >= num_rays);
  auto prepared_ray = [&](size_t i) {
    return PrepareRay(rv.ox[i], rv.oy[i], rv.oz[i], rv.dx[i], rv.dy[i], rv.dz[i]);
  };
  // the oracle's answers (and Moller-Trumbore's leaks) once
  std::vector<ClosestHit> want[2];
  size_t ref_leaks = 0, moller_leaks = 0, zero_edges = 0;
  for (size_t i = 0; i < rv.size; ++i) {
    const PreparedRay pr = prepared_ray(i);
    const TriBundleSpan span = ws.bundles.Cell(rv.pixel[i]);
    for (const TriTest test : kTests) {
      ClosestHit h;
      ref::IntersectBundles(pr, span, 0.0f, kInf, test, &h);
      want[int(test)].push_back(h);
    }
    ref_leaks += want[0].back().prim < 0;
    moller_leaks += want[1].back().prim < 0;
    for (size_t j = 0; j < span.lanes(); ++j) {
      if (span.ids[j] < 0) continue;
      float p[3][3];
      for (int v = 0; v < 3; ++v) {
        for (int a = 0; a < 3; ++a) p[v][a] = span.Component(v, a)[j];
      }
      zero_edges += HasZeroEdge(pr.wt, p);
    }
  }
  MESSAGE(rv.size, " rays (", ws.vertex_rays,
          " at vertices) through a closed 81920-triangle icosphere at 1e5: scalar watertight "
          "leaks ",
          ref_leaks, ", Moller-Trumbore leaks ", moller_leaks, "; ", zero_edges,
          " pairs took the double fallback");
  CHECK(ref_leaks == 0);
  CHECK(moller_leaks > 0);  // the stress is hard enough to make the non-watertight test leak

  RayStream stream(64);
  HitStream hits(64);
  test::ForEachTarget([&](const char* target_name) {
    const std::string target = target_name;
    INFO("target: ", target);
    for (const TriTest test : kTests) {
      INFO(TestName(test));
      size_t leaks = 0, bad = 0, bad_stream = 0, stream_leaks = 0, occluded_leaks = 0;
      for (size_t i = 0; i < rv.size; ++i) {
        const PreparedRay pr = prepared_ray(i);
        const TriBundleSpan span = ws.bundles.Cell(rv.pixel[i]);
        for (const BundleWidth width : {BundleWidth::kAuto, BundleWidth::kOne}) {
          ClosestHit h;
          IntersectBundles(pr, span, 0.0f, kInf, test, width, &h);
          leaks += h.prim < 0;
          bad += !SameHit(h, want[int(test)][i]);
        }
        occluded_leaks += !OccludedBundles(pr, span, 0.0f, kInf, test, BundleWidth::kAuto);
      }
      // streams: all rays of a cell as one stream against the cell's triangles
      for (const auto& [first, end] : ws.cell_rays) {
        stream.Clear();
        for (size_t i = first; i < end; ++i) stream.PushFrom(rv, i);
        stream.FillPadding();
        hits.Resize(stream.size());
        hits.Reset();
        IntersectStream(stream.view(), ws.bundles.Cell(rv.pixel[first]), test, hits.view());
        const HitStreamView h = hits.view();
        for (size_t i = first; i < end; ++i) {
          ClosestHit got;
          got.t = h.t[i - first];
          got.u = h.u[i - first];
          got.v = h.v[i - first];
          got.prim = h.prim[i - first];
          stream_leaks += got.prim < 0;
          bad_stream += !SameHit(got, want[int(test)][i]);
        }
      }
      CHECK(bad == 0);
      CHECK(bad_stream == 0);
      if (test == TriTest::kWatertight) {
        CHECK(leaks == 0);
        CHECK(stream_leaks == 0);
        CHECK(occluded_leaks == 0);
      } else {
        MESSAGE(target, ": Moller-Trumbore leaks 1x4 ", leaks / 2, ", N x 1 ", stream_leaks,
                ", occluded ", occluded_leaks, " of ", rv.size);
      }
    }
  });

  // the whole mesh through rs::Accel (grid traversal, then the bundles of each cell)
  std::vector<int32_t> occluded(rv.size);
  HitStream accel_hits(rv.size);
  accel_hits.Resize(rv.size);
  const Accel accel(ws.mesh());
  test::ForEachTarget([&](const char* target_name) {
    INFO("target: ", target_name);
    accel_hits.Reset();
    accel.Intersect(rv, accel_hits.view());
    accel.Occluded(rv, occluded.data());
    size_t misses = 0, occluded_misses = 0;
    for (size_t i = 0; i < rv.size; ++i) {
      misses += accel_hits.view().prim[i] < 0;
      occluded_misses += occluded[i] == 0;
    }
    CHECK(misses == 0);
    CHECK(occluded_misses == 0);
  });

  // a subset against the whole sphere (all 20480 bundles in one span): every width
  std::vector<uint32_t> all(ws.ico.tri.size());
  std::iota(all.begin(), all.end(), 0u);
  TriBundles whole;
  BuildTriBundleList(ws.tris, all.data(), all.size(), &whole);
  std::vector<size_t> subset;
  for (size_t i = 0; i < rv.size; i += rv.size / 150) subset.push_back(i);
  std::vector<ClosestHit> whole_want[2];
  for (const size_t i : subset) {
    for (const TriTest test : kTests) {
      ClosestHit h;
      ref::IntersectBundles(prepared_ray(i), whole.Cell(0), 0.0f, kInf, test, &h);
      whole_want[int(test)].push_back(h);
    }
    CHECK(whole_want[0].back().prim >= 0);
    CHECK(std::fabs(whole_want[0].back().t - 1.0f) < 1e-3f);
  }
  test::ForEachTarget([&](const char* target_name) {
    const std::string target = target_name;
    INFO("target: ", target);
    size_t bad = 0;
    for (size_t k = 0; k < subset.size(); ++k) {
      const PreparedRay pr = prepared_ray(subset[k]);
      for (const TriTest test : kTests) {
        for (const BundleWidth width : kWidths) {
          ClosestHit h;
          IntersectBundles(pr, whole.Cell(0), 0.0f, kInf, test, width, &h);
          bad += !SameHit(h, whole_want[int(test)][k]);
        }
      }
    }
    CHECK(bad == 0);
  });
}

}  // namespace
}  // namespace rs
