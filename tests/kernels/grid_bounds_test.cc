// Grids that cannot explode: on inputs that made the uniform grid grow with the
// square of their size (a small sphere far from the origin, thousands of identical triangles, a
// fan of long thin triangles) the references and bytes of every structure stay within a fixed
// factor of the triangle count, the build stays fast, and the grids stay watertight and give the
// scalar oracle's hits bit for bit on every target; absurd resolutions fail with rs::Error.
#include <doctest/doctest.h>

#include <algorithm>
#include <array>
#include <cfloat>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <map>
#include <string>
#include <utility>
#include <vector>

#include "include/raystream/raystream.h"
#include "kernels/accel_impl.h"
#include "kernels/grid.h"
#include "kernels/grid_binning.h"
#include "kernels/reference.h"
#include "scenes/icosphere.h"
#include "streams/ray_stream.h"
#include "tests/kernels/geometry_util.h"
#include "tests/test_util.h"

namespace rs {
namespace {

using test::F;
using test::kInf;
using test::Rng;
using test::SameBits;
using test::Soup;

// Bounds every structure must meet (kernels/grid.h): the top-level grid lists at most 8
// references per non-degenerate triangle plus 65536 (so small scenes are never coarsened), the
// sub-cells of the second level at most as many again; the whole Accel (triangles, grid, second
// level, triangle bundles) takes at most 1 KiB per triangle plus 16 MiB. Literal here, so a
// change of the library's constants has to change this contract too.
constexpr double kRefsPerTriangle = 8.0;
constexpr double kRefSlack = 65536.0;
constexpr double kBytesPerTriangle = 1024.0;
constexpr double kBytesSlack = 16.0 * 1024 * 1024;

struct Rays {
  RayStream rays;
  std::vector<uint8_t> must_hit;  // 1: the ray crosses the surface at a vertex or an edge
  void Push(const float o[3], const float d[3], bool hit) {
    rays.Push(o[0], o[1], o[2], d[0], d[1], d[2], 0.0f, kInf, 0, 1, 1, 1, 0, RayKind::kPrimary);
    must_hit.push_back(hit ? 1 : 0);
  }
};

std::string KindName(GridKind kind) {
  return kind == GridKind::kAuto        ? "auto"
         : kind == GridKind::kUniform   ? "uniform"
         : kind == GridKind::kTwoLevel  ? "two-level"
                                        : "irregular";
}

// Builds `mesh` with `kind`, checks the bounds and the build time, then traces `rays` with the
// scalar oracle (ref::AccelIntersect / AccelOccluded) and on every target (Accel::Intersect /
// Occluded): identical hits bit for bit, no miss among the rays marked must_hit. Returns the info.
AccelInfo CheckBoundedAndExact(const std::string& what, const MeshView& mesh, GridKind kind,
                               Rays& r) {
  INFO(what, ", grid ", KindName(kind));
  BuildOptions options;
  options.grid = kind;
  const auto start = std::chrono::steady_clock::now();
  const Accel accel(mesh, options);
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  const AccelInfo info = accel.Info();
  const double n = double(mesh.num_triangles);
  MESSAGE(what, " (", KindName(kind), "): ", std::string(info.kind), " ", info.resolution[0], "x",
          info.resolution[1], "x", info.resolution[2], ", lambda ", info.lambda, ", ",
          info.references, " refs (", double(info.references) / n, " per triangle), ",
          info.sub_references, " sub-cell refs (", double(info.sub_references) / n,
          " per triangle), ", info.irregular_references, " irregular refs in ",
          info.irregular_cells, " cells, ", info.max_per_cell, " max per cell, ", info.bytes, " B (",
          double(info.bytes) / n, " per triangle), build ", seconds, " s");
  CHECK(double(info.references) <= kRefsPerTriangle * n + kRefSlack);
  CHECK(double(info.sub_references) <= kRefsPerTriangle * n + kRefSlack);
  CHECK(double(info.irregular_references) <= kRefsPerTriangle * n + kRefSlack);
  CHECK((kind == GridKind::kIrregular) == (info.irregular_cells > 0 || mesh.num_triangles == 0));
  CHECK(double(info.bytes) <= kBytesPerTriangle * n + kBytesSlack);
  // generous (sanitizers, a shared machine): the unbounded build took 6-11 s or hung
  CHECK(seconds < (test::kSlowBuild ? 60.0 : 10.0));

  r.rays.FillPadding();
  const RayStreamView rv = r.rays.view();
  const size_t count = rv.size;
  HitStream want(count), got(count);
  want.Resize(count);
  got.Resize(count);
  want.Reset();
  std::vector<int32_t> want_occluded(count), got_occluded(count);
  ref::AccelIntersect(AccelImpl(accel), rv, want.view());
  ref::AccelOccluded(AccelImpl(accel), rv, want_occluded.data());
  size_t misses = 0, occluded_misses = 0;
  for (size_t i = 0; i < count; ++i) {
    if (!r.must_hit[i]) continue;
    misses += want.view().prim[i] < 0;
    occluded_misses += want_occluded[i] == 0;
  }
  CHECK(misses == 0);
  CHECK(occluded_misses == 0);
  // the double brute force (kernels/reference.h), independent of the grid: the same hits at the
  // same t; on rays through a vertex or an edge several triangles share that t, so the prims
  // may differ. Rays grazing an open edge (not must_hit) may round to a hit in one and a miss in
  // the other.
  const ref::ChunkedMesh chunked(mesh);
  size_t status_bad = 0, must_status_bad = 0, t_bad = 0;
  for (size_t i = 0; i < count; ++i) {
    const ref::Hit h = chunked.IntersectClosest(
        ref::MakeRay(rv.ox[i], rv.oy[i], rv.oz[i], rv.dx[i], rv.dy[i], rv.dz[i], 0.0f, kInf));
    const HitStreamView w = want.view();
    if ((h.prim >= 0) != (w.prim[i] >= 0)) {
      ++status_bad;
      must_status_bad += r.must_hit[i];
      continue;
    }
    // 1e-4: the float watertight t of a long sliver is off by ~2e-5 (tests/kernels/geometry_util.h)
    if (h.prim >= 0 && !(std::fabs(h.t - double(w.t[i])) <= 1e-4 * std::max(1.0, h.t))) {
      if (++t_bad <= 3) {
        INFO("ray ", i, ": grid prim ", w.prim[i], " t ", w.t[i], ", double prim ", h.prim,
             " t ", h.t);
        CHECK(false);
      }
    }
  }
  MESSAGE(what, ": ", count, " rays, hit or miss differs from the double brute force on ",
          status_bad, " (all exactly on an open edge)");
  CHECK(must_status_bad == 0);
  CHECK(t_bad == 0);
  test::ForEachTarget([&](const char* target) {
    INFO("target: ", target);
    got.Reset();
    accel.Intersect(rv, got.view());
    accel.Occluded(rv, got_occluded.data());
    size_t bad = 0;
    for (size_t i = 0; i < count; ++i) {
      const HitStreamView w = want.view(), g = got.view();
      const bool same = w.prim[i] == g.prim[i] && SameBits(w.t[i], g.t[i]) &&
                        SameBits(w.u[i], g.u[i]) && SameBits(w.v[i], g.v[i]) &&
                        want_occluded[i] == got_occluded[i];
      if (!same && ++bad <= 3) {
        INFO("ray ", i, ": oracle prim ", w.prim[i], " t ", w.t[i], ", simd prim ", g.prim[i],
             " t ", g.t[i]);
        CHECK(same);
      }
    }
    CHECK(bad == 0);
  });
  return info;
}

// An icosphere as a mesh with rays from origins on the `lattice` within `spread` of the centre
// per axis (0.3: inside, so each ray crosses the closed surface) aimed exactly at `per_kind`
// vertices and `per_kind` edge midpoints: o + d = target in real arithmetic.
struct SphereCase {
  Icosphere ico;
  std::vector<float> positions;
  std::vector<uint32_t> indices;
  Rays r;
  MeshView mesh() const {
    return MeshView{positions.data(), positions.size() / 3, 3, indices.data(), indices.size() / 3};
  }
};

void MakeSphereCase(const std::array<double, 3>& c, double snap, double lattice, size_t per_kind,
                    SphereCase* s, double spread = 0.3) {
  s->ico = MakeIcosphere(6, 1.0, c, snap);
  for (const auto& v : s->ico.v) s->positions.insert(s->positions.end(), {v[0], v[1], v[2]});
  for (const auto& t : s->ico.tri) s->indices.insert(s->indices.end(), {t[0], t[1], t[2]});
  std::vector<std::pair<uint32_t, uint32_t>> edges;
  std::map<std::pair<uint32_t, uint32_t>, int> seen;
  for (const auto& t : s->ico.tri) {
    for (int k = 0; k < 3; ++k) {
      const auto e = std::minmax(t[k], t[(k + 1) % 3]);
      if (seen[e]++ == 0) edges.push_back(e);
    }
  }
  Rng rng(13);
  auto origin = [&](float o[3]) {
    for (int a = 0; a < 3; ++a) {
      o[a] = F(std::round((c[a] + rng.Uniform(-spread, spread)) * lattice) / lattice);
    }
  };
  for (size_t k = 0; k < per_kind; ++k) {
    float o[3], d[3];
    origin(o);
    const auto& v = s->ico.v[rng.Below(uint32_t(s->ico.v.size()))];
    for (int a = 0; a < 3; ++a) {
      d[a] = F(double(v[a]) - double(o[a]));
      REQUIRE(double(o[a]) + double(d[a]) == double(v[a]));  // exact: the ray meets the vertex
    }
    s->r.Push(o, d, true);
    origin(o);
    const auto& e = edges[rng.Below(uint32_t(edges.size()))];
    for (int a = 0; a < 3; ++a) {
      const double mid = 0.5 * (double(s->ico.v[e.first][a]) + double(s->ico.v[e.second][a]));
      d[a] = F(mid - double(o[a]));
      REQUIRE(double(o[a]) + double(d[a]) == mid);  // exact: the ray meets the edge
    }
    s->r.Push(o, d, true);
  }
}

TEST_CASE("icosphere of 81920 triangles at the origin: bounded references, watertight") {
  for (const GridKind kind :
       {GridKind::kAuto, GridKind::kUniform, GridKind::kTwoLevel, GridKind::kIrregular}) {
    SphereCase s;
    // vertices on the 2^-16 lattice, origins on 2^-8: every direction is an exact float
    MakeSphereCase({0.0, 0.0, 0.0}, 65536.0, 256.0, test::kSlowBuild ? 500 : 2000, &s);
    REQUIRE(s.ico.tri.size() == 81920);
    CheckBoundedAndExact("sphere r=1 at the origin", s.mesh(), kind, s.r);
  }
}

TEST_CASE("icosphere of 81920 triangles of radius 1 at (148376, 1234, -223423): bounded, watertight") {
  for (const GridKind kind :
       {GridKind::kAuto, GridKind::kUniform, GridKind::kTwoLevel, GridKind::kIrregular}) {
    SphereCase s;
    // float rounding only: x and z are multiples of 1/64 there, many triangles are slivers or
    // degenerate; origins on the 1/64 lattice keep every direction exact. 2,600 rays: Accel's
    // translated pieces of 1,024 rays, a shorter one and a padded tail (ForEachFramePiece)
    MakeSphereCase({148376.0, 1234.0, -223423.0}, 0.0, 64.0, test::kSlowBuild ? 100 : 1300, &s);
    const AccelInfo info = CheckBoundedAndExact("sphere r=1 at (148376, 1234, -223423)",
                                                s.mesh(), kind, s.r);
    // built as at the origin (the Accel's frame, kernels/grid.h ChooseFrameShift): the same
    // resolution and about as many references. In world coordinates the DDA's rounding allowed
    // no cells below 0.22 here: 8 references per triangle, 295 triangle tests per ray.
    SphereCase at0;
    MakeSphereCase({0.0, 0.0, 0.0}, 65536.0, 256.0, 0, &at0);
    BuildOptions options;
    options.grid = kind;
    const AccelInfo want = Accel(at0.mesh(), options).Info();
    for (int a = 0; a < 3; ++a) CHECK(info.resolution[a] == want.resolution[a]);
    CHECK(double(info.references) <= 1.05 * double(want.references));
    CHECK(double(info.irregular_references) <= 1.05 * double(want.irregular_references));
    CHECK(info.bounds_lo[0] <= 148375.0f);  // reported in world coordinates
    CHECK(info.bounds_hi[2] >= -223422.0f);
  }
}

// Rays from outside, up to 64 units away (about 2,000 of the uniform grid's cells; the frame's
// margin covers about 5,000, kernels/grid.h ChooseFrameShift): the grid finds exactly what the
// float watertight test finds over all triangles, same triangle, same t. (They are no
// must-hit rays: on a sphere rounded to 1/64 a ray aimed at a vertex from outside may only touch
// it, and the float test then misses it in both.)
TEST_CASE("sphere at 1.5e5, rays from up to 64 away: the hits of a float brute force") {
  SphereCase s;
  MakeSphereCase({148376.0, 1234.0, -223423.0}, 0.0, 64.0, test::kSlowBuild ? 50 : 500, &s, 64.0);
  BuildOptions options;
  options.grid = GridKind::kUniform;
  const Accel accel(s.mesh(), options);
  const Accel::Impl& m = AccelImpl(accel);
  REQUIRE(m.Shifted());
  s.r.rays.FillPadding();
  const RayStreamView rv = s.r.rays.view();
  HitStream want(rv.size), got(rv.size);
  want.Resize(rv.size);
  got.Resize(rv.size);
  ref::AccelIntersect(m, rv, want.view());
  accel.Intersect(rv, got.view());
  size_t differ = 0, simd_differ = 0, hits = 0;
  for (size_t i = 0; i < rv.size; ++i) {
    const float o[3] = {rv.ox[i] - m.shift[0], rv.oy[i] - m.shift[1], rv.oz[i] - m.shift[2]};
    const WatertightRay w = PrepareWatertightRay(o[0], o[1], o[2], rv.dx[i], rv.dy[i], rv.dz[i]);
    float best = FLT_MAX;
    int32_t prim = -1;
    for (size_t t = 0; t < m.triangles.size; ++t) {  // ascending ids: the lower wins on equal t
      TriHit h;
      if (!m.triangles.degenerate[t] && IntersectWatertight(w, m.triangles, t, 0.0f, best, &h) &&
          (prim < 0 || h.t < best)) {
        best = h.t;
        prim = int32_t(t);
      }
    }
    hits += prim >= 0;
    differ += prim != want.view().prim[i] || (prim >= 0 && !SameBits(best, want.view().t[i]));
    simd_differ += got.view().prim[i] != want.view().prim[i] ||
                   !SameBits(got.view().t[i], want.view().t[i]);
  }
  MESSAGE(rv.size, " rays from up to 64 away, ", hits, " hit; grid vs float brute force differ on ",
          differ, ", SIMD vs scalar on ", simd_differ);
  CHECK(hits > rv.size / 2);
  CHECK(differ == 0);
  CHECK(simd_differ == 0);
}

// `copies` copies of one triangle (same vertices, separate vertex entries), with rays through
// its vertices, edges and interior; every hit is triangle 0 (equal t: the lowest id wins).
void CheckIdenticalTriangles(size_t copies, size_t num_rays) {
  const float a[3] = {0.125f, 0.25f, 0.375f}, b[3] = {1.25f, 0.5f, -0.25f},
              c[3] = {0.25f, 1.125f, 0.875f};
  Soup soup;
  for (size_t i = 0; i < copies; ++i) soup.AddTriangle(a, b, c);
  for (const GridKind kind :
       {GridKind::kAuto, GridKind::kUniform, GridKind::kTwoLevel, GridKind::kIrregular}) {
    Rays r;
    Rng rng{uint32_t(copies)};
    for (size_t k = 0; k < num_rays; ++k) {
      // target: a vertex, an edge point or an interior point (barycentrics on a 2^-4 lattice)
      double w1 = rng.Below(17) / 16.0, w2 = rng.Below(17) / 16.0;
      if (w1 + w2 > 1.0) {
        w1 = 1.0 - w1;
        w2 = 1.0 - w2;
      }
      if (k % 3 == 0) w2 = 1.0 - w1;  // on the edge b-c
      float o[3], d[3];
      for (int q = 0; q < 3; ++q) {
        const double target = (1.0 - w1 - w2) * a[q] + w1 * b[q] + w2 * c[q];
        o[q] = F(std::round(rng.Uniform(-2.0, 2.0) * 16.0) / 16.0 + (q == 2 ? 3.0 : 0.0));
        d[q] = F(target - double(o[q]));
      }
      r.Push(o, d, w1 > 0.0 && w2 > 0.0 && w1 + w2 < 1.0);  // inside: must hit
    }
    CheckBoundedAndExact(std::to_string(copies) + " identical triangles", soup.view(), kind, r);
    // every ray that hits the plane inside the triangle reports id 0
    const Accel accel(soup.view());
    HitStream hits(r.rays.size());
    hits.Resize(r.rays.size());
    hits.Reset();
    accel.Intersect(r.rays.view(), hits.view());
    size_t hit = 0;
    for (size_t i = 0; i < r.rays.size(); ++i) {
      if (hits.view().prim[i] < 0) continue;
      ++hit;
      CHECK(hits.view().prim[i] == 0);
    }
    CHECK(hit * 2 > r.rays.size());
  }
}

TEST_CASE("10,000 identical triangles: bounded references, lowest id wins") {
  CheckIdenticalTriangles(10000, test::kSlowBuild ? 100 : 600);
}

TEST_CASE("100,000 identical triangles: bounded references, no abort, no hang") {
  CheckIdenticalTriangles(100000, test::kSlowBuild ? 20 : 100);
}

// One convex face of 30,000 corners (on a circle in a tilted plane, snapped to 2^-16) fanned from
// corner 0 into 29,998 long thin triangles, as the OBJ loader fans a face. Rays from above aim
// exactly at the fan's inner edges (corner 0 to corner i) and at its corners.
TEST_CASE("30,000-corner fan of long thin triangles: bounded references, watertight") {
  constexpr int kCorners = 30000;
  Soup soup;
  auto snap = [](double x) { return F(std::round(x * 65536.0) / 65536.0); };
  std::vector<std::array<float, 3>> corner(kCorners);
  for (int i = 0; i < kCorners; ++i) {
    const double phi = 2.0 * M_PI * i / kCorners;
    const double x = std::cos(phi), y = std::sin(phi);
    corner[i] = {snap(x + 0.5), snap(0.8 * y + 0.25), snap(0.6 * y + 0.3 * x - 0.125)};
    soup.AddVertex(corner[i][0], corner[i][1], corner[i][2]);
  }
  for (int i = 1; i + 1 < kCorners; ++i) {
    soup.indices.insert(soup.indices.end(), {0u, uint32_t(i), uint32_t(i + 1)});
  }
  for (const GridKind kind :
       {GridKind::kAuto, GridKind::kUniform, GridKind::kTwoLevel, GridKind::kIrregular}) {
    Rays r;
    Rng rng(30000);
    const size_t num_rays = test::kSlowBuild ? 200 : 1000;
    for (size_t k = 0; k < num_rays; ++k) {
      // not the edges next to corner 0, whose sliver triangles snap to zero area
      const int i = 1000 + int(rng.Below(kCorners - 2000));
      // a point of the edge corner 0 - corner i at parameter s (a multiple of 1/4): exact in
      // double, so o + d = target holds for the float direction below
      const double s = k % 4 == 0 ? 1.0 : rng.Below(4) / 4.0 + 0.125;
      float o[3], d[3];
      for (int q = 0; q < 3; ++q) {
        const double target = double(corner[0][q]) + s * (double(corner[i][q]) - corner[0][q]);
        o[q] = F(std::round((0.5 + rng.Uniform(-0.5, 0.5)) * 256.0) / 256.0 + (q == 2 ? 2.0 : 0.0));
        d[q] = F(target - double(o[q]));
        REQUIRE(double(o[q]) + double(d[q]) == target);
      }
      r.Push(o, d, s < 1.0);  // inner edge points must hit; corners on the rim may graze
    }
    CheckBoundedAndExact("30,000-corner fan", soup.view(), kind, r);
  }
}

// Many overlapping boxes: CountGridBoxes (its difference array for boxes of more than 64 cells)
// against marking every box cell one by one, and EstimateGridRefs against the lists BuildGrid
// makes on the same geometry (sampling forced with limit 0).
TEST_CASE("box counts and the reference estimate on overlapping large triangles") {
  Rng rng(1313);
  for (int round = 0; round < 4; ++round) {
    Soup soup = test::RandomSoup(rng, 2000, -1.0, 1.0, 0.05);
    const Soup big = test::RandomSoup(rng, 200, -1.0, 1.0, round < 2 ? 0.6 : 1.6);
    for (size_t t = 0; t < big.triangles(); ++t) {
      const float* p = big.positions.data() + 9 * t;
      for (int copy = 0; copy < (round % 2 ? 5 : 1); ++copy) soup.AddTriangle(p, p + 3, p + 6);
    }
    TriangleSoA tris;
    BuildTriangleSoA(soup.view(), &tris);
    const GridBounds bounds = ComputeGridBounds(tris);
    Grid geometry;
    SetGridGeometry(bounds, 2.0f, 512, &geometry);
    const BinGeometry geo = GridBinGeometry(geometry);
    std::vector<uint8_t> marked(geometry.num_cells, 0);
    size_t box_refs = 0;
    for (size_t i = 0; i < tris.size; ++i) {
      const float v[3][3] = {{tris.p[0][0][i], tris.p[0][1][i], tris.p[0][2][i]},
                             {tris.p[1][0][i], tris.p[1][1][i], tris.p[1][2][i]},
                             {tris.p[2][0][i], tris.p[2][1][i], tris.p[2][2][i]}};
      int c0[3], c1[3];
      bool span[3];
      if (tris.degenerate[i] || TriangleCellRange(geo, v, c0, c1, span) < 0) continue;
      for (int z = c0[2]; z <= c1[2]; ++z) {
        for (int y = c0[1]; y <= c1[1]; ++y) {
          for (int x = c0[0]; x <= c1[0]; ++x) {
            marked[geometry.CellIndex(x, y, z)] = 1;
            ++box_refs;
          }
        }
      }
    }
    size_t occupied = 0;
    for (const uint8_t m : marked) occupied += m;
    const GridBoxCounts counts = CountGridBoxes(tris, geometry);
    INFO("round ", round, ", ", tris.size, " triangles, ", geometry.num_cells, " cells");
    CHECK(counts.refs == box_refs);
    CHECK(counts.occupied == occupied);
    CHECK(EstimateGridRefs(tris, geometry, box_refs) == box_refs);  // within the limit: exact
    Grid grid;
    BuildGrid(tris, bounds, 2.0f, 512, &grid);
    REQUIRE(grid.num_cells == geometry.num_cells);  // within the budget: not coarsened
    const double estimate = double(EstimateGridRefs(tris, geometry, 0));
    MESSAGE("round ", round, ": ", grid.num_refs, " references, ", box_refs,
            " bounding-box cells, estimate ", estimate);
    CHECK(estimate > 0.75 * double(grid.num_refs));
    CHECK(estimate < 1.33 * double(grid.num_refs));
  }
}

TEST_CASE("a resolution that cannot be held is refused with rs::Error naming cells and bytes") {
  Rng rng(7);
  const Soup soup = test::RandomSoup(rng, 1000, -1.0, 1.0, 0.1);
  BuildOptions options;
  options.grid = GridKind::kUniform;
  options.lambda = 1e12f;
  options.max_resolution = 1 << 22;
  bool threw = false;
  try {
    const Accel accel(soup.view(), options);
  } catch (const Error& e) {
    threw = true;
    const std::string message = e.what();
    MESSAGE(message);
    CHECK(message.find("cells") != std::string::npos);
    CHECK(message.find("bytes") != std::string::npos);
  }
  CHECK(threw);
}

}  // namespace
}  // namespace rs
