// SIMD stream DDA and single-ray DDA (kernels/dda_simd.h) on every compiled target against the
// scalar DDA (kernels/dda.h, kernels/two_level.h): same triangle, t/u/v bit for bit, same cell
// steps, for closest and any hit, on random soups, procedural and shared scenes, stream sizes
// around the vector width, padding sentinels, and numerical edge cases (axis rays with +-0, cell
// boundaries, grazing, NaN/Inf, 1e5 offsets, 1e-4 scales). The two-level grid: 128-byte records,
// conservative sub-cell binning, identical hits to the flat grid, cost-model choice; the
// micro-cache never changes a result.
#include <doctest/doctest.h>

#include <algorithm>
#include <cfloat>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <memory>
#include <string>
#include <tuple>
#include <utility>
#include <vector>

#include "include/raystream/raystream.h"
#include "kernels/accel_impl.h"
#include "kernels/dda.h"
#include "kernels/dda_simd.h"
#include "kernels/grid.h"
#include "kernels/irregular.h"
#include "kernels/irregular_simd.h"
#include "kernels/triangle.h"
#include "kernels/two_level.h"
#include "scenes/load.h"
#include "streams/ray_stream.h"
#include "tests/kernels/dda_util.h"
#include "tests/kernels/geometry_util.h"
#include "tests/test_util.h"

namespace rs {
namespace {

using test::F;
using test::Rng;
using test::Soup;

using test::Built;
using test::kInf;
using test::kNaN;
using test::MakeStream;
using test::Ray;
using test::SameBits;

constexpr float kSentinelT = -1234.5f;
constexpr int32_t kSentinelPrim = 0x5a5a5a5a;

// Scalar oracle results of one ray set on one structure.
struct Oracle {
  std::vector<RayHit> hit;
  std::vector<int32_t> any;
  uint64_t closest_steps = 0, any_steps = 0, closest_tests = 0;
  size_t hits = 0;
};

Oracle RunOracle(const Built& b, const std::vector<Ray>& rays) {
  Oracle o;
  o.hit.resize(rays.size());
  o.any.resize(rays.size());
  TraceStats sc, sa;
  for (size_t i = 0; i < rays.size(); ++i) {
    const Ray& r = rays[i];
    TraceClosestTwoLevel(b.grid, b.two, b.tris, r.o[0], r.o[1], r.o[2], r.d[0], r.d[1], r.d[2],
                         r.tmin, r.tmax, &o.hit[i], &sc);
    o.any[i] = TraceAnyTwoLevel(b.grid, b.two, b.tris, r.o[0], r.o[1], r.o[2], r.d[0], r.d[1],
                                r.d[2], r.tmin, r.tmax, &sa)
                   ? 1
                   : 0;
    o.hits += o.hit[i].prim >= 0;
  }
  o.closest_steps = sc.cell_steps;
  o.closest_tests = sc.triangle_tests;
  o.any_steps = sa.cell_steps;
  return o;
}

bool SameHit(const RayHit& a, float t, float u, float v, int32_t prim) {
  return a.prim == prim && SameBits(a.t, t) && SameBits(a.u, u) && SameBits(a.v, v);
}

// Every target: stream closest/any and single-ray closest/any against the oracle, bit for bit,
// with identical cell steps; padding lanes of the hit stream and the slot after the occluded
// array keep their sentinels. Returns the oracle.
Oracle CheckAllTargets(const Built& b, const std::vector<Ray>& rays, const std::string& what,
                       int micro_cache = 8) {
  const Oracle o = RunOracle(b, rays);
  const size_t n = rays.size();
  RayStream stream = MakeStream(rays);
  DdaOptions options;
  options.micro_cache = micro_cache;
  // The irregular grid over the same triangles: the same hits; its SIMD kernel takes the cell
  // steps of its scalar traversal.
  IrregularGrid irr;
  BuildIrregularGrid(b.tris, ComputeGridBounds(b.tris), IrregularOptions{}, 512, &irr);
  IrregularDda irr_dda;
  BuildIrregularDda(irr, b.tris, &irr_dda);
  TraceStats irr_closest, irr_any;
  size_t irr_scalar_bad = 0;
  for (size_t i = 0; i < n; ++i) {
    const Ray& r = rays[i];
    RayHit h;
    TraceClosestIrregular(irr, b.tris, r.o[0], r.o[1], r.o[2], r.d[0], r.d[1], r.d[2], r.tmin,
                          r.tmax, &h, &irr_closest);
    irr_scalar_bad += !SameHit(o.hit[i], h.t, h.u, h.v, h.prim);
    irr_scalar_bad += TraceAnyIrregular(irr, b.tris, r.o[0], r.o[1], r.o[2], r.d[0], r.d[1],
                                        r.d[2], r.tmin, r.tmax, &irr_any) != (o.any[i] != 0);
  }
  CHECK(irr_scalar_bad == 0);
  test::ForEachTarget([&](const char* target) {
    {
      INFO(what, ": irregular grid, target ", std::string(target), ", rays ", n);
      HitStream ih(n);
      ih.Resize(n);
      const HitStreamView iv = ih.view();
      for (size_t i = 0; i < n; ++i) {
        iv.t[i] = 7.0f;
        iv.prim[i] = 3;
      }
      TraceStats ic, ia;
      IntersectStreamIrregular(irr_dda, stream.view(), iv, &ic);
      size_t bad = 0;
      for (size_t i = 0; i < n; ++i) {
        if (SameHit(o.hit[i], iv.t[i], iv.u[i], iv.v[i], iv.prim[i])) continue;
        if (++bad <= 3) {
          const Ray& r = rays[i];
          INFO("ray ", i, " o ", r.o[0], " ", r.o[1], " ", r.o[2], " d ", r.d[0], " ", r.d[1],
               " ", r.d[2], ": irregular prim ", iv.prim[i], " t ", iv.t[i], ", scalar prim ",
               o.hit[i].prim, " t ", o.hit[i].t);
          CHECK(SameHit(o.hit[i], iv.t[i], iv.u[i], iv.v[i], iv.prim[i]));
        }
      }
      CHECK(bad == 0);
      CHECK(ic.rays == n);
      CHECK(ic.cell_steps == irr_closest.cell_steps);
      std::vector<int32_t> occluded(n + 1, 77);
      OccludedStreamIrregular(irr_dda, stream.view(), occluded.data(), &ia);
      size_t any_bad = 0;
      for (size_t i = 0; i < n; ++i) any_bad += occluded[i] != o.any[i];
      CHECK(any_bad == 0);
      CHECK(occluded[n] == 77);
      CHECK(ia.cell_steps == irr_any.cell_steps);
    }
    INFO(what, ": target ", std::string(target), ", rays ", n, ", micro-cache ", micro_cache);
    HitStream hits(n);
    hits.Resize(n);
    hits.Reset();
    const HitStreamView hv = hits.view();
    for (size_t i = n; i < PaddedSize(n); ++i) {
      hv.t[i] = hv.u[i] = hv.v[i] = kSentinelT;
      hv.prim[i] = kSentinelPrim;
    }
    // empty-space skipping off: the scalar DDA's cells exactly; on: the same results from
    // fewer cell steps (the last pass leaves sc / sa of the default, skipping on)
    TraceStats sc, sa;
    for (const bool skip : {false, true}) {
    INFO("empty_skip ", skip);
    options.empty_skip = skip;
    sc = TraceStats();
    sa = TraceStats();
    for (size_t i = 0; i < n; ++i) {  // garbage that must be overwritten
      hv.t[i] = 7.0f;
      hv.prim[i] = 3;
    }
    IntersectStreamDda(b.dda, stream.view(), hv, options, &sc);
    size_t bad = 0;
    for (size_t i = 0; i < n; ++i) {
      if (SameHit(o.hit[i], hv.t[i], hv.u[i], hv.v[i], hv.prim[i])) continue;
      if (++bad <= 3) {
        const Ray& r = rays[i];
        INFO("ray ", i, " o ", r.o[0], " ", r.o[1], " ", r.o[2], " d ", r.d[0], " ", r.d[1], " ",
             r.d[2], " tmin ", r.tmin, " tmax ", r.tmax, ": simd prim ", hv.prim[i], " t ",
             hv.t[i], ", scalar prim ", o.hit[i].prim, " t ", o.hit[i].t);
        CHECK(SameHit(o.hit[i], hv.t[i], hv.u[i], hv.v[i], hv.prim[i]));
      }
    }
    CHECK(bad == 0);
    CHECK(sc.rays == n);
    if (skip) {
      CHECK(sc.cell_steps <= o.closest_steps);
    } else {
      CHECK(sc.cell_steps == o.closest_steps);
      CHECK(sc.empty_skips == 0);
    }
    CHECK(sc.cache_hits <= sc.cache_lookups);
    if (micro_cache == 0) CHECK(sc.cache_lookups == 0);
    size_t padding_bad = 0;
    for (size_t i = n; i < PaddedSize(n); ++i) {
      padding_bad += !(SameBits(hv.t[i], kSentinelT) && SameBits(hv.u[i], kSentinelT) &&
                       SameBits(hv.v[i], kSentinelT) && hv.prim[i] == kSentinelPrim);
    }
    CHECK(padding_bad == 0);

    std::vector<int32_t> occluded(n + 1, 77);  // exactly n + a guard: no padding needed
    OccludedStreamDda(b.dda, stream.view(), occluded.data(), options, &sa);
    size_t any_bad = 0;
    for (size_t i = 0; i < n; ++i) any_bad += occluded[i] != o.any[i];
    CHECK(any_bad == 0);
    CHECK(occluded[n] == 77);
    if (skip) {
      CHECK(sa.cell_steps <= o.any_steps);
    } else {
      CHECK(sa.cell_steps == o.any_steps);
    }
    }

    TraceStats ss, sas;
    size_t single_bad = 0, single_any_bad = 0;
    for (size_t i = 0; i < n; ++i) {
      const Ray& r = rays[i];
      RayHit h;
      const bool hit = IntersectSingleDda(b.dda, r.o[0], r.o[1], r.o[2], r.d[0], r.d[1], r.d[2],
                                          r.tmin, r.tmax, &h, &ss);
      single_bad += !SameHit(o.hit[i], h.t, h.u, h.v, h.prim) || hit != (o.hit[i].prim >= 0);
      single_any_bad += OccludedSingleDda(b.dda, r.o[0], r.o[1], r.o[2], r.d[0], r.d[1], r.d[2],
                                          r.tmin, r.tmax, &sas) != (o.any[i] != 0);
    }
    CHECK(single_bad == 0);
    CHECK(single_any_bad == 0);
    CHECK(ss.cell_steps == o.closest_steps);
    CHECK(sas.cell_steps == o.any_steps);
    // the two SIMD forms test the same leaves (no mailbox in either): same triangle count, so
    // they step through the same cells in the same order, ties included (the scalar DDA's
    // mailbox makes its count smaller)
    // (on SCALAR the single-ray form is the scalar DDA, mailbox included)
    if (std::string(target) != "SCALAR") CHECK(ss.triangle_tests == sc.triangle_tests);
    CHECK(sc.triangle_tests >= o.closest_tests);
  });
  return o;
}

// Random rays: origins in the bounds grown by `grow`, half aimed at a random point of a random
// triangle, half in random directions; some with a finite tmax or a positive tmin.
std::vector<Ray> RandomRays(Rng& rng, const Built& b, size_t n, double grow = 0.2) {
  std::vector<Ray> rays(n);
  for (size_t i = 0; i < n; ++i) {
    Ray& r = rays[i];
    for (int a = 0; a < 3; ++a) {
      const double ext = double(b.grid.hi[a]) - b.grid.lo[a];
      r.o[a] = rng.UniformF(b.grid.lo[a] - grow * ext, b.grid.hi[a] + grow * ext);
    }
    if (i % 2 == 0 && b.tris.size > 0) {
      uint32_t id = rng.Below(uint32_t(b.tris.size));
      const double b1 = rng.Uniform(0, 1), b2 = rng.Uniform(0, 1 - b1);
      for (int a = 0; a < 3; ++a) {
        const double p0 = b.tris.p[0][a][id], p1 = b.tris.p[1][a][id], p2 = b.tris.p[2][a][id];
        r.d[a] = F(p0 + b1 * (p1 - p0) + b2 * (p2 - p0) - r.o[a]);
      }
      if (r.d[0] == 0.0f && r.d[1] == 0.0f && r.d[2] == 0.0f) r.d[0] = 1.0f;
    } else {
      rng.Direction(r.d);
    }
    if (i % 7 == 3) r.tmax = rng.UniformF(0.1, 1.5);   // shadow-like segment
    if (i % 11 == 5) r.tmin = rng.UniformF(0.05, 0.6);  // starts part-way
  }
  return rays;
}

Soup MixedSoup(Rng& rng, int small, int big, double lo = -1.0, double hi = 1.0) {
  Soup s = test::RandomSoup(rng, size_t(small), lo, hi, 0.15 * (hi - lo) / 2);
  const Soup bs = test::RandomSoup(rng, size_t(big), lo, hi, 1.2 * (hi - lo) / 2);
  const uint32_t base = uint32_t(s.positions.size() / 3);
  s.positions.insert(s.positions.end(), bs.positions.begin(), bs.positions.end());
  for (const uint32_t i : bs.indices) s.indices.push_back(i + base);
  return s;
}

// Exact-as-double triangle / closed box overlap (13 separating axes), for the sub-cell binning.
bool TriBoxOverlap(const double v[3][3], const double lo[3], const double hi[3]) {
  for (int a = 0; a < 3; ++a) {
    if (std::min({v[0][a], v[1][a], v[2][a]}) > hi[a]) return false;
    if (std::max({v[0][a], v[1][a], v[2][a]}) < lo[a]) return false;
  }
  double c[3], h[3], w[3][3], e[3][3];
  for (int a = 0; a < 3; ++a) {
    c[a] = 0.5 * (lo[a] + hi[a]);
    h[a] = 0.5 * (hi[a] - lo[a]);
  }
  for (int k = 0; k < 3; ++k) {
    for (int a = 0; a < 3; ++a) w[k][a] = v[k][a] - c[a];
  }
  for (int k = 0; k < 3; ++k) {
    for (int a = 0; a < 3; ++a) e[k][a] = w[(k + 1) % 3][a] - w[k][a];
  }
  auto separated = [&](const double ax[3]) {
    double p[3];
    for (int k = 0; k < 3; ++k) p[k] = ax[0] * w[k][0] + ax[1] * w[k][1] + ax[2] * w[k][2];
    const double r = h[0] * std::fabs(ax[0]) + h[1] * std::fabs(ax[1]) + h[2] * std::fabs(ax[2]);
    return std::min({p[0], p[1], p[2]}) > r || std::max({p[0], p[1], p[2]}) < -r;
  };
  const double n[3] = {e[0][1] * e[1][2] - e[0][2] * e[1][1], e[0][2] * e[1][0] - e[0][0] * e[1][2],
                       e[0][0] * e[1][1] - e[0][1] * e[1][0]};
  if (separated(n)) return false;
  for (int k = 0; k < 3; ++k) {
    for (int a = 0; a < 3; ++a) {
      double ax[3] = {0, 0, 0};
      ax[(a + 1) % 3] = -e[k][(a + 2) % 3];
      ax[(a + 2) % 3] = e[k][(a + 1) % 3];
      if (separated(ax)) return false;
    }
  }
  return true;
}

// Records, ranks and leaf lists of a two-level grid: every triangle of a refined cell is listed
// in every sub-cell it touches (exact test, sub-cell box not grown), and only in sub-cells it
// touches when grown by 1 % of a sub-cell plus 16 ulps; ids ascending; Leaf() matches a count.
void CheckTwoLevel(const Built& b) {
  const TwoLevelGrid& two = b.two;
  REQUIRE(!two.empty());
  CHECK(sizeof(SubGridRecord) == 128);
  CHECK(reinterpret_cast<uintptr_t>(two.records.get()) % 64 == 0);  // two whole cache lines
  double max_abs = 0.0;
  for (int a = 0; a < 3; ++a) {
    max_abs = std::max({max_abs, std::fabs(double(b.grid.lo[a])), std::fabs(double(b.grid.hi[a]))});
  }
  size_t missing = 0, far = 0, refined = 0, order_bad = 0, sub_refs = 0;
  uint32_t expected_leaf = uint32_t(b.grid.num_cells);
  for (size_t cell = 0; cell < b.grid.num_cells; ++cell) {
    if (!two.Refined(cell)) {
      // unrefined cells keep the top-level list as their leaf
      CHECK(two.leaves.cell_begin[cell + 1] - two.leaves.cell_begin[cell] ==
            b.grid.cell_begin[cell + 1] - b.grid.cell_begin[cell]);
      continue;
    }
    ++refined;
    CHECK(two.leaves.cell_begin[cell + 1] == two.leaves.cell_begin[cell]);  // emptied
    const SubGridRecord& rec = two.Record(cell);
    CHECK(rec.parent == cell);
    CHECK(rec.first_leaf == expected_leaf);
    uint32_t count = 0;
    for (int z = 0; z < kSubRes; ++z) {
      for (int y = 0; y < kSubRes; ++y) {
        for (int x = 0; x < kSubRes; ++x) {
          std::vector<char> listed(b.tris.size, 0);
          if (rec.Occupied(x, y, z)) {
            const uint32_t leaf = rec.Leaf(x, y, z);
            CHECK(leaf == rec.first_leaf + count);
            ++count;
            const uint32_t lb = two.leaves.cell_begin[leaf], le = two.leaves.cell_begin[leaf + 1];
            CHECK(le > lb);
            for (uint32_t k = lb; k < le; ++k) {
              listed[two.leaves.tri_ids[k]] = 1;
              if (k > lb && !(two.leaves.tri_ids[k - 1] < two.leaves.tri_ids[k])) ++order_bad;
            }
            sub_refs += le - lb;
          }
          double lo[3], hi[3], glo[3], ghi[3];
          const int c[3] = {x, y, z};
          for (int a = 0; a < 3; ++a) {
            const double cs = rec.cell_size[a];
            lo[a] = double(rec.lo[a]) + c[a] * cs;
            hi[a] = lo[a] + cs;
            const double pad = 0.01 * cs + 16 * 1.1920929e-7 * max_abs;
            glo[a] = lo[a] - pad;
            ghi[a] = hi[a] + pad;
          }
          for (uint32_t k = b.grid.cell_begin[cell]; k < b.grid.cell_begin[cell + 1]; ++k) {
            const uint32_t id = b.grid.tri_ids[k];
            double v[3][3];
            for (int q = 0; q < 3; ++q) {
              for (int a = 0; a < 3; ++a) v[q][a] = b.tris.p[q][a][id];
            }
            if (!listed[id] && TriBoxOverlap(v, lo, hi)) ++missing;
            if (listed[id] && !TriBoxOverlap(v, glo, ghi)) ++far;
          }
        }
      }
    }
    expected_leaf += count;
  }
  CHECK(refined == two.num_records);
  CHECK(expected_leaf == two.leaves.num_cells);
  CHECK(sub_refs == two.sub_refs);
  CHECK(missing == 0);
  CHECK(far == 0);
  CHECK(order_bad == 0);
}

TEST_CASE("random soups, flat and two-level: every target equals the scalar DDA") {
  Rng rng(101);
  for (const auto& params :
       {std::tuple{400, 10, 4.0f}, std::tuple{1500, 40, 2.0f}, std::tuple{200, 60, 8.0f}}) {
    // plain copies: clang 14 cannot capture structured bindings in INFO's lambda
    const int small = std::get<0>(params), big = std::get<1>(params);
    const float lambda = std::get<2>(params);
    const Soup soup = MixedSoup(rng, small, big);
    const Built flat(soup.view(), lambda, -1);
    const Built two(soup.view(), lambda * 0.1f, 4);  // coarse top, most cells refined
    INFO("soup ", small, " + ", big, " lambda ", lambda);
    REQUIRE(!two.two.empty());
    CheckTwoLevel(two);
    const std::vector<Ray> rays = RandomRays(rng, flat, 1500);
    const Oracle of = CheckAllTargets(flat, rays, "flat");
    const Oracle ot = CheckAllTargets(two, rays, "two-level");
    CHECK(of.hits > rays.size() / 4);  // the comparisons are not vacuous
    // two-level and flat grids give identical hits (both equal the float brute force)
    size_t diff = 0, any_diff = 0;
    for (size_t i = 0; i < rays.size(); ++i) {
      diff += !SameHit(of.hit[i], ot.hit[i].t, ot.hit[i].u, ot.hit[i].v, ot.hit[i].prim);
      any_diff += of.any[i] != ot.any[i];
    }
    CHECK(diff == 0);
    CHECK(any_diff == 0);
  }
}

// Shadow rays as the renderer spawns them: from a closest hit, offset along the geometric
// normal to the incoming side, towards a point light, tmax = the distance to it. Their origins
// lie next to triangles (their own surface and its neighbours pass the edge tests behind them),
// and most cells they cross are shared with many other lanes (micro-cache hits). The kernels are
// also run without stats (stats = nullptr, the renderer's and benchmarks' path, which counts no
// triangle tests): occlusion flags and closest hits equal the scalar oracle bit for bit.
TEST_CASE("shadow rays spawned on surfaces, stats off: every target equals the scalar DDA") {
  Rng rng(313);
  const Soup soup = MixedSoup(rng, 1200, 30);
  const Built flat(soup.view(), 2.0f, -1);
  const Built two(soup.view(), 0.2f, 4);
  REQUIRE(!two.two.empty());
  const std::vector<Ray> primary = RandomRays(rng, flat, 3000);
  const Oracle po = RunOracle(flat, primary);
  const float light[3] = {0.5f * (flat.grid.lo[0] + flat.grid.hi[0]), flat.grid.hi[1],
                          0.5f * (flat.grid.lo[2] + flat.grid.hi[2])};
  std::vector<Ray> shadow;
  for (size_t i = 0; i < primary.size(); ++i) {
    const RayHit& h = po.hit[i];
    if (h.prim < 0) continue;
    const Ray& r = primary[i];
    double e1[3], e2[3], n[3], p[3];
    for (int a = 0; a < 3; ++a) {
      e1[a] = double(flat.tris.p[1][a][h.prim]) - flat.tris.p[0][a][h.prim];
      e2[a] = double(flat.tris.p[2][a][h.prim]) - flat.tris.p[0][a][h.prim];
      p[a] = double(r.o[a]) + double(h.t) * r.d[a];
    }
    n[0] = e1[1] * e2[2] - e1[2] * e2[1];
    n[1] = e1[2] * e2[0] - e1[0] * e2[2];
    n[2] = e1[0] * e2[1] - e1[1] * e2[0];
    const double len = std::sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
    if (!(len > 0.0)) continue;
    const double side = n[0] * r.d[0] + n[1] * r.d[1] + n[2] * r.d[2] > 0.0 ? -1.0 : 1.0;
    Ray s;
    double dist2 = 0.0;
    for (int a = 0; a < 3; ++a) {
      s.o[a] = F(p[a] + side * 1e-4 * n[a] / len);
      s.d[a] = light[a] - s.o[a];
      dist2 += double(s.d[a]) * s.d[a];
    }
    s.tmax = F(std::sqrt(dist2));
    for (int a = 0; a < 3; ++a) s.d[a] = F(s.d[a] / double(s.tmax));
    shadow.push_back(s);
  }
  REQUIRE(shadow.size() > 500);
  for (const Built* b : {&flat, &two}) {
    const std::string what = b == &flat ? "flat" : "two-level";
    const Oracle o = RunOracle(*b, shadow);
    size_t blocked = 0;
    for (const int32_t a : o.any) blocked += a != 0;
    CHECK(blocked > shadow.size() / 20);  // neither vacuous way
    CHECK(blocked < shadow.size() - shadow.size() / 20);
    RayStream stream = MakeStream(shadow);
    const size_t n = shadow.size();
    test::ForEachTarget([&](const char* target) {
      INFO(what, ": target ", std::string(target), ", rays ", n);
      std::vector<int32_t> occluded(n + 1, 77);
      OccludedStreamDda(b->dda, stream.view(), occluded.data(), DdaOptions(), nullptr);
      size_t any_bad = 0;
      for (size_t i = 0; i < n; ++i) any_bad += occluded[i] != o.any[i];
      CHECK(any_bad == 0);
      CHECK(occluded[n] == 77);
      HitStream hits(n);
      hits.Resize(n);
      hits.Reset();
      const HitStreamView hv = hits.view();
      IntersectStreamDda(b->dda, stream.view(), hv, DdaOptions(), nullptr);
      size_t bad = 0;
      for (size_t i = 0; i < n; ++i) {
        bad += !SameHit(o.hit[i], hv.t[i], hv.u[i], hv.v[i], hv.prim[i]);
      }
      CHECK(bad == 0);
    });
  }
}

TEST_CASE("stream sizes around the vector widths; padding untouched; micro-cache sizes") {
  Rng rng(7);
  const Soup soup = MixedSoup(rng, 600, 20);
  const Built flat(soup.view(), 4.0f, -1);
  const Built two(soup.view(), 0.5f, 3);
  const std::vector<Ray> all = RandomRays(rng, flat, 1000);
  for (const size_t n : {size_t{1}, size_t{2}, size_t{3}, size_t{5}, size_t{7}, size_t{9},
                         size_t{15}, size_t{16}, size_t{17}, size_t{31}, size_t{33}, size_t{1000}}) {
    const std::vector<Ray> rays(all.begin(), all.begin() + long(n));
    CheckAllTargets(flat, rays, "flat n=" + std::to_string(n));
    CheckAllTargets(two, rays, "two-level n=" + std::to_string(n));
  }
  // the micro-cache never changes a result (each size is checked against the same oracle)
  for (const int cache : {0, 1, 3, 8, 16}) {
    CheckAllTargets(flat, all, "flat cache", cache);
    CheckAllTargets(two, all, "two-level cache", cache);
  }
  // an empty stream writes nothing
  RayStream empty;
  empty.FillPadding();
  HitStream hits(1);
  hits.Resize(0);
  hits.Reset();
  hits.view().t[0] = kSentinelT;
  TraceStats st;
  IntersectStreamDda(flat.dda, empty.view(), hits.view(), DdaOptions{}, &st);
  CHECK(SameBits(hits.view().t[0], kSentinelT));
  CHECK(st.rays == 0);
}

// Rays along the axes (+-0 in the other components), from inside and outside, starting on cell
// boundaries, grid faces and corners, grazing the grid's faces, and pointing away.
std::vector<Ray> EdgeRays(Rng& rng, const Built& b) {
  std::vector<Ray> rays;
  const Grid& g = b.grid;
  auto boundary = [&](int a, int k) { return F(double(g.lo[a]) + double(k) * g.cell_size[a]); };
  auto inside = [&](int a) { return rng.UniformF(g.lo[a], g.hi[a]); };
  for (int axis = 0; axis < 3; ++axis) {
    for (const float sign : {1.0f, -1.0f}) {
      for (const float zero : {0.0f, -0.0f}) {
        for (int i = 0; i < 24; ++i) {
          Ray r;
          for (int a = 0; a < 3; ++a) {
            r.d[a] = a == axis ? sign * rng.UniformF(0.5, 2.0) : zero;
            r.o[a] = inside(a);
          }
          if (i % 3 == 0) {  // from outside the grid along the axis
            r.o[axis] = sign > 0 ? g.lo[axis] - 1.0f : g.hi[axis] + 1.0f;
          }
          if (i % 4 == 1) {  // on a cell boundary plane (in the other axes)
            const int a = (axis + 1) % 3;
            r.o[a] = boundary(a, int(rng.Below(uint32_t(g.res[a] + 1))));
          }
          if (i % 4 == 2) {  // on a cell edge (two boundaries)
            const int a = (axis + 1) % 3, c = (axis + 2) % 3;
            r.o[a] = boundary(a, int(rng.Below(uint32_t(g.res[a] + 1))));
            r.o[c] = boundary(c, int(rng.Below(uint32_t(g.res[c] + 1))));
          }
          if (i % 5 == 4) {  // grazing a face of the grid: on its plane, parallel to it
            const int a = (axis + 1) % 3;
            r.o[a] = rng.Below(2) ? g.lo[a] : g.hi[a];
          }
          rays.push_back(r);
        }
      }
    }
  }
  for (int i = 0; i < 200; ++i) {  // random directions from boundaries, corners and outside
    Ray r;
    rng.Direction(r.d);
    for (int a = 0; a < 3; ++a) {
      const int k = int(rng.Below(uint32_t(g.res[a] + 1)));
      r.o[a] = i % 3 == 0 ? boundary(a, k) : (i % 3 == 1 ? (k % 2 ? g.lo[a] : g.hi[a]) : inside(a));
    }
    if (i % 10 == 7) {  // start outside, pointing away
      r.o[0] = g.hi[0] + 0.5f;
      r.d[0] = std::fabs(r.d[0]) + 0.1f;
    }
    rays.push_back(r);
  }
  return rays;
}

// Rays that never hit: NaN/Inf in any component, zero and denormal directions, empty or NaN
// (tmin, tmax] ranges.
std::vector<Ray> InvalidRays(const Built& b) {
  std::vector<Ray> rays;
  const float c[3] = {0.5f * (b.grid.lo[0] + b.grid.hi[0]), 0.5f * (b.grid.lo[1] + b.grid.hi[1]),
                      0.5f * (b.grid.lo[2] + b.grid.hi[2])};
  for (int k = 0; k < 6; ++k) {
    for (const float bad : {kNaN, kInf, -kInf}) {
      Ray r{{c[0], c[1], c[2]}, {0.3f, -0.5f, 0.8f}};
      (k < 3 ? r.o[k] : r.d[k - 3]) = bad;
      rays.push_back(r);
    }
  }
  rays.push_back(Ray{{c[0], c[1], c[2]}, {0.0f, -0.0f, 0.0f}});
  rays.push_back(Ray{{c[0], c[1], c[2]}, {1e-31f, -1e-32f, 1e-40f}});
  Ray r{{c[0], c[1], c[2]}, {0.3f, 0.2f, 0.9f}};
  for (const auto& [tmin, tmax] : {std::pair{kNaN, kInf}, std::pair{0.0f, kNaN}, std::pair{1.0f, 0.5f},
                                   std::pair{0.5f, 0.5f}, std::pair{kInf, kInf}, std::pair{-kInf, -kInf}}) {
    r.tmin = tmin;
    r.tmax = tmax;
    rays.push_back(r);
  }
  return rays;
}

TEST_CASE("edge cases: axis rays with +-0, cell boundaries, grid faces, grazing, outside") {
  Rng rng(23);
  // a box of triangles (faces exactly on float coordinates) plus a soup inside
  Soup soup = MixedSoup(rng, 300, 10, -0.8, 0.8);
  const float p[8][3] = {{-1, -1, -1}, {1, -1, -1}, {1, 1, -1}, {-1, 1, -1},
                         {-1, -1, 1},  {1, -1, 1},  {1, 1, 1},  {-1, 1, 1}};
  const int faces[6][4] = {{0, 1, 2, 3}, {4, 5, 6, 7}, {0, 1, 5, 4},
                           {2, 3, 7, 6}, {0, 3, 7, 4}, {1, 2, 6, 5}};
  for (const auto& f : faces) {
    soup.AddTriangle(p[f[0]], p[f[1]], p[f[2]]);
    soup.AddTriangle(p[f[0]], p[f[2]], p[f[3]]);
  }
  const Built flat(soup.view(), 4.0f, -1);
  const Built two(soup.view(), 0.4f, 2);
  std::vector<Ray> rays = EdgeRays(rng, flat);
  // grazing the box faces: in the plane z = 1 and just beside it, and through edges/corners
  for (int i = 0; i < 60; ++i) {
    const float z = i % 3 == 0 ? 1.0f : (i % 3 == 1 ? std::nextafter(1.0f, 2.0f) : std::nextafter(1.0f, 0.0f));
    rays.push_back(Ray{{-2.0f, rng.UniformF(-1.2, 1.2), z}, {1.0f, rng.UniformF(-0.2, 0.2), 0.0f}});
    rays.push_back(Ray{{-2.0f, -2.0f, -2.0f}, {1.0f, 1.0f, i % 2 ? 1.0f : 0.999f}});
    rays.push_back(Ray{{1.0f, 1.0f, 3.0f}, {0.0f, -0.0f, -1.0f}});  // along the edge x = y = 1
  }
  const std::vector<Ray> invalid = InvalidRays(flat);
  rays.insert(rays.end(), invalid.begin(), invalid.end());
  const Oracle of = CheckAllTargets(flat, rays, "edge rays, flat");
  const Oracle ot = CheckAllTargets(two, rays, "edge rays, two-level");
  CHECK(of.hits > rays.size() / 3);
  size_t diff = 0;
  for (size_t i = 0; i < rays.size(); ++i) {
    diff += !SameHit(of.hit[i], ot.hit[i].t, ot.hit[i].u, ot.hit[i].v, ot.hit[i].prim);
  }
  CHECK(diff == 0);
  // the invalid rays at the end never hit (and the call returned: no hang)
  for (size_t i = rays.size() - invalid.size(); i < rays.size(); ++i) {
    CHECK(of.hit[i].prim == -1);
    CHECK(of.any[i] == 0);
  }
}

TEST_CASE("huge offsets (1e5) and tiny scales (1e-4)") {
  Rng rng(41);
  for (const auto& range : {std::pair{1e5, 1e5 + 20.0}, std::pair{-1e-4, 1e-4},
                            std::pair{-1e5 - 3.0, -1e5 + 3.0}}) {
    const double lo = range.first, hi = range.second;
    INFO("range ", lo, " .. ", hi);
    const Soup soup = MixedSoup(rng, 300, 10, lo, hi);
    const Built flat(soup.view(), 4.0f, -1);
    const Built two(soup.view(), 0.3f, 3);
    std::vector<Ray> rays = RandomRays(rng, flat, 500);
    for (Ray& r : rays) {  // the generator's absolute tmax / tmin make no sense at this scale
      r.tmin = 0.0f;
      r.tmax = kInf;
    }
    const std::vector<Ray> edge = EdgeRays(rng, flat);
    rays.insert(rays.end(), edge.begin(), edge.end());
    const Oracle of = CheckAllTargets(flat, rays, "flat");
    CHECK(of.hits > rays.size() / 5);
    if (!two.two.empty()) CheckAllTargets(two, rays, "two-level");
  }
}

// Procedural scenes through the public Accel (auto, uniform, two-level, irregular): Intersect / Occluded
// (SIMD) against rs::ref::AccelIntersect / AccelOccluded (scalar), every target.
void CheckAccel(const MeshView& mesh, const std::string& name, size_t n, uint32_t seed) {
  for (const GridKind kind :
       {GridKind::kAuto, GridKind::kUniform, GridKind::kTwoLevel, GridKind::kIrregular}) {
    BuildOptions options;
    options.grid = kind;
    const Accel accel(mesh, options);
    const AccelInfo info = accel.Info();
    INFO(name, " kind ", int(kind), " -> ", std::string(info.kind), " lambda ", info.lambda, " subgrids ",
         info.subgrids);
    if (kind == GridKind::kUniform) CHECK(std::string(info.kind) == "uniform");
    CHECK((std::string(info.kind) == "two-level") == (info.subgrids > 0));
    // kAuto refines only where the model predicts a gain (forced kTwoLevel may cost more)
    if (kind == GridKind::kAuto) CHECK(info.cost_estimate <= info.flat_cost_estimate);
    if (kind == GridKind::kTwoLevel) CHECK(info.lambda == 4.0f);
    CHECK((kind == GridKind::kIrregular) == (info.irregular_cells > 0));
    Rng rng(seed);
    Built probe(mesh, 4.0f, -1);  // only for the ray generator's bounds and triangles
    const std::vector<Ray> rays = RandomRays(rng, probe, n);
    RayStream stream = MakeStream(rays);
    HitStream ref(n), got(n);
    ref.Resize(n);
    got.Resize(n);
    ref.Reset();
    std::vector<int32_t> ref_any(n), got_any(n);
    TraceStats rs;
    ref::AccelIntersect(AccelImpl(accel), stream.view(), ref.view(), &rs);
    ref::AccelOccluded(AccelImpl(accel), stream.view(), ref_any.data());
    size_t hits = 0;
    for (size_t i = 0; i < n; ++i) hits += ref.view().prim[i] >= 0;
    CHECK(hits > n / 5);
    test::ForEachTarget([&](const char* target) {
      INFO("target ", std::string(target));
      got.Reset();
      TraceStats st;
      accel.Intersect(stream.view(), got.view(), &st);
      accel.Occluded(stream.view(), got_any.data());
      size_t bad = 0, any_bad = 0;
      for (size_t i = 0; i < n; ++i) {
        const HitStreamView a = ref.view(), b = got.view();
        bad += !(a.prim[i] == b.prim[i] && SameBits(a.t[i], b.t[i]) && SameBits(a.u[i], b.u[i]) &&
                 SameBits(a.v[i], b.v[i]));
        any_bad += ref_any[i] != got_any[i];
      }
      CHECK(bad == 0);
      CHECK(any_bad == 0);
      CHECK(st.cell_steps <= rs.cell_steps);  // empty-space skipping is on by default
      CHECK(st.rays == n);
    });
  }
}

TEST_CASE("procedural scenes: spherebox, erw6, amphitheater:1 through Accel") {
  uint32_t seed = 5;
  for (const char* name : {"spherebox", "erw6", "amphitheater:1"}) {
    const Scene scene = LoadScene(name);
    CheckAccel(scene.mesh(), name, 1500, seed++);
    // and the raw kernels with a forced two-level grid (cells above 16 triangles)
    const Built two(scene.mesh(), 1.0f, 16);
    Rng rng(seed++);
    if (!two.two.empty()) {
      CheckTwoLevel(two);
      CheckAllTargets(two, RandomRays(rng, two, 800), std::string(name) + " two-level");
    }
  }
}

TEST_CASE("shared scenes (bunny, conference): every target equals the scalar DDA") {
  uint32_t seed = 50;
  for (const auto& [file, name] : {std::pair{"bunny/bun_zipper.ply", "bunny"},
                                   std::pair{"conference/conference.obj", "conference"}}) {
    if (!test::HaveSharedScene(file)) continue;
    const Scene scene = LoadScene(name);
    CheckAccel(scene.mesh(), name, 1000, seed++);
  }
}

TEST_CASE("cost model: a dense cluster in a big sparse scene gets sub-grids, a soup does not") {
  Rng rng(77);
  // "teapot in a stadium": 3000 small triangles in a 3-wide cluster, 200 spread over 100 units
  Soup soup = test::RandomSoup(rng, 3000, 0.0, 3.0, 0.1);
  const Soup sparse = test::RandomSoup(rng, 200, -50.0, 50.0, 2.0);
  const uint32_t base = uint32_t(soup.positions.size() / 3);
  soup.positions.insert(soup.positions.end(), sparse.positions.begin(), sparse.positions.end());
  for (const uint32_t i : sparse.indices) soup.indices.push_back(i + base);
  const Accel clustered(soup.view());
  const AccelInfo ci = clustered.Info();
  INFO("clustered: kind ", std::string(ci.kind), " lambda ", ci.lambda, " subgrids ", ci.subgrids, " cost ",
       ci.cost_estimate, " flat ", ci.flat_cost_estimate);
  CHECK(std::string(ci.kind) == "two-level");
  CHECK(ci.subgrids >= 1);
  CHECK(ci.cost_estimate < kTwoLevelMinGain * ci.flat_cost_estimate);
  CHECK(ci.sub_references > 0);
  // forcing the kind is honoured
  BuildOptions uniform;
  uniform.grid = GridKind::kUniform;
  CHECK(std::string(Accel(soup.view(), uniform).Info().kind) == "uniform");
  CHECK(Accel(soup.view(), uniform).Info().lambda == 4.0f);

  const Soup even = test::RandomSoup(rng, 4000, -1.0, 1.0, 0.1);
  const AccelInfo ei = Accel(even.view()).Info();
  INFO("even soup: kind ", std::string(ei.kind), " lambda ", ei.lambda);
  CHECK(std::string(ei.kind) == "uniform");
  CHECK(ei.lambda >= 0.5f);
  CHECK(ei.lambda <= 8.0f);

  // the clustered scene traces identically through both structures
  CheckAccel(soup.view(), "clustered", 800, 78);
}

TEST_CASE("options: micro-cache bounds are validated, counters move") {
  Rng rng(3);
  const Soup soup = MixedSoup(rng, 500, 5);
  BuildOptions bad;
  bad.micro_cache = kMaxMicroCache + 1;
  CHECK_THROWS_AS(Accel(soup.view(), bad), Error);
  bad.micro_cache = -1;
  CHECK_THROWS_AS(Accel(soup.view(), bad), Error);
  bad.micro_cache = 8;
  bad.grid = static_cast<GridKind>(9);
  CHECK_THROWS_AS(Accel(soup.view(), bad), Error);

  // coherent rays (a fan from one point) hit the micro-cache; with it off there are no lookups
  // (the micro-cache belongs to the per-ray walk: packets off, else these rays are one packet)
  std::vector<Ray> fan;
  for (int i = 0; i < 400; ++i) {
    fan.push_back(Ray{{0.0f, 0.0f, -3.0f}, {F(-0.2 + 0.001 * i), 0.01f, 1.0f}});
  }
  RayStream stream = MakeStream(fan);
  HitStream a(fan.size()), b(fan.size());
  a.Resize(fan.size());
  b.Resize(fan.size());
  BuildOptions on, off;
  on.grid = off.grid = GridKind::kUniform;
  on.packets = off.packets = false;
  off.micro_cache = 0;
  TraceStats son, soff;
  Accel(soup.view(), on).Intersect(stream.view(), a.view(), &son);
  Accel(soup.view(), off).Intersect(stream.view(), b.view(), &soff);
  CHECK(son.cache_lookups > 0);
  CHECK(son.cache_hits > 0);
  CHECK(soff.cache_lookups == 0);
  CHECK(son.cell_steps == soff.cell_steps);
  for (size_t i = 0; i < fan.size(); ++i) {
    CHECK(a.view().prim[i] == b.view().prim[i]);
    CHECK(SameBits(a.view().t[i], b.view().t[i]));
  }
  MESSAGE("fan: micro-cache hit rate ", double(son.cache_hits) / double(son.cache_lookups));
}

TEST_CASE("empty-space skipping: ring counts equal a brute-force search, steps drop") {
  // a 23 x 17 x 29 grid with a few occupied cells (corners, faces, interior) and none
  Grid grid;
  grid.res[0] = 23;
  grid.res[1] = 17;
  grid.res[2] = 29;
  grid.num_cells = size_t(23) * 17 * 29;
  const size_t words = (grid.num_cells + 63) / 64;
  grid.occupancy = hwy::AllocateAligned<uint64_t>(words);
  for (int pass = 0; pass < 3; ++pass) {
    std::fill_n(grid.occupancy.get(), words, uint64_t{0});
    std::vector<int> occ;  // occupied cell coordinates, 3 per cell
    Rng rng(900 + uint32_t(pass));
    const int count = pass == 0 ? 0 : pass == 1 ? 1 : 12;
    for (int i = 0; i < count; ++i) {
      const int c[3] = {int(rng.Below(23)), int(rng.Below(17)), int(rng.Below(29))};
      occ.insert(occ.end(), c, c + 3);
      const size_t idx = grid.CellIndex(c[0], c[1], c[2]);
      grid.occupancy[idx >> 6] |= uint64_t{1} << (idx & 63);
    }
    if (pass == 2) {  // the corner cell too
      occ.insert(occ.end(), {0, 0, 0});
      grid.occupancy[0] |= 1u;
    }
    std::vector<uint8_t> rings(grid.num_cells, 99);
    BuildSkipRings(grid, rings.data());
    size_t bad = 0;
    for (int z = 0; z < 29; ++z) {
      for (int y = 0; y < 17; ++y) {
        for (int x = 0; x < 23; ++x) {
          int dist = 1000;
          for (size_t i = 0; i < occ.size(); i += 3) {
            dist = std::min(dist, std::max({std::abs(x - occ[i]), std::abs(y - occ[i + 1]),
                                            std::abs(z - occ[i + 2])}));
          }
          const int want = dist == 0 ? 0 : std::min(dist - 1, kMaxSkipRings);
          bad += rings[grid.CellIndex(x, y, z)] != want;
        }
      }
    }
    INFO("pass ", pass, " occupied cells ", occ.size() / 3);
    CHECK(bad == 0);
  }

  // spherebox has empty space around its spheres: skipping jumps, the results stay equal
  const Scene scene = LoadScene("spherebox");
  for (const int threshold : {-1, 16}) {
    const Built b(scene.mesh(), 4.0f, threshold);
    Rng rng(31);
    std::vector<Ray> rays(2000);
    const float* lo = b.grid.lo;
    const float* hi = b.grid.hi;
    for (Ray& r : rays) {
      for (int a = 0; a < 3; ++a) r.o[a] = rng.UniformF(lo[a], hi[a]);
      rng.Direction(r.d);
    }
    RayStream stream = MakeStream(rays);
    HitStream on(rays.size()), off(rays.size());
    on.Resize(rays.size());
    off.Resize(rays.size());
    TraceStats s_on, s_off;
    DdaOptions options;
    IntersectStreamDda(b.dda, stream.view(), on.view(), options, &s_on);
    options.empty_skip = false;
    IntersectStreamDda(b.dda, stream.view(), off.view(), options, &s_off);
    size_t bad = 0;
    for (size_t i = 0; i < rays.size(); ++i) {
      bad += !(on.view().prim[i] == off.view().prim[i] && SameBits(on.view().t[i], off.view().t[i]));
    }
    INFO("threshold ", threshold);
    CHECK(bad == 0);
    CHECK(s_on.empty_skips > 0);
    CHECK(s_off.empty_skips == 0);
    CHECK(s_on.cell_steps < s_off.cell_steps);
    MESSAGE("spherebox threshold ", threshold, ": cell steps ", s_off.cell_steps, " -> ",
            s_on.cell_steps, " with ", s_on.empty_skips, " jumps");
  }

  // Accel turns skipping on by itself for a sparse grid (a tiny triangle in each corner of a
  // cube, a fine grid), and off when asked; the hits equal the scalar oracle's either way
  std::vector<float> pos;
  std::vector<uint32_t> idx;
  for (int c = 0; c < 8; ++c) {
    const float p[3] = {float(c & 1), float((c >> 1) & 1), float((c >> 2) & 1)};
    for (int v = 0; v < 3; ++v) {
      for (int a = 0; a < 3; ++a) pos.push_back(p[a] + (v == a + 1 ? 0.01f * (0.5f - p[a]) : 0.0f));
      idx.push_back(uint32_t(idx.size()));
    }
  }
  MeshView mesh;
  mesh.positions = pos.data();
  mesh.num_vertices = pos.size() / 3;
  mesh.indices = idx.data();
  mesh.num_triangles = idx.size() / 3;
  BuildOptions options;
  options.grid = GridKind::kUniform;
  options.lambda = 20000.0f;
  const Accel sparse(mesh, options);
  options.empty_skip = false;
  const Accel dense(mesh, options);
  CHECK(sparse.Info().empty_skip);
  CHECK(sparse.Info().empty_block_share > 0.75);
  CHECK_FALSE(dense.Info().empty_skip);
  Rng rng(5);
  std::vector<Ray> rays(3000);
  for (Ray& r : rays) {
    for (int a = 0; a < 3; ++a) r.o[a] = rng.UniformF(-0.2, 1.2);
    if (rng.Below(2) == 0) {  // half aimed at a corner triangle
      const size_t t = rng.Below(8);
      for (int a = 0; a < 3; ++a) r.d[a] = pos[9 * t + a] * 0.998f + 0.001f - r.o[a];
    } else {
      rng.Direction(r.d);
    }
  }
  RayStream stream = MakeStream(rays);
  HitStream want(rays.size()), got(rays.size());
  want.Resize(rays.size());
  got.Resize(rays.size());
  ref::AccelIntersect(AccelImpl(sparse), stream.view(), want.view());
  size_t hits = 0;
  for (size_t i = 0; i < rays.size(); ++i) hits += want.view().prim[i] >= 0;
  CHECK(hits > rays.size() / 8);
  for (const Accel* accel : {&sparse, &dense}) {
    TraceStats st;
    accel->Intersect(stream.view(), got.view(), &st);
    size_t bad = 0;
    for (size_t i = 0; i < rays.size(); ++i) {
      bad += !(want.view().prim[i] == got.view().prim[i] &&
               SameBits(want.view().t[i], got.view().t[i]));
    }
    CHECK(bad == 0);
    CHECK((st.empty_skips > 0) == (accel == &sparse));
  }
}

}  // namespace
}  // namespace rs
