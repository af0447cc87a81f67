// Uniform grid build: resolution heuristic values, CSR/occupancy consistency, conservative
// binning checked against an independent double-precision triangle/box overlap, flat scenes,
// single triangles, empty meshes and degenerate triangles; the SIMD build passes (degenerate
// flags, edge tables, box counts) against their scalar definitions.
#include <doctest/doctest.h>

#include <algorithm>
#include <atomic>
#include <bit>
#include <chrono>
#include <cmath>
#include <cstring>
#include <limits>
#include <stdexcept>
#include <thread>
#include <vector>

#include "kernels/build_threads.h"
#include "kernels/dda_grid.h"
#include "kernels/grid.h"
#include "kernels/grid_binning.h"
#include "kernels/triangle.h"
#include "tests/kernels/geometry_util.h"
#include "tests/test_util.h"

namespace rs {
namespace {

using test::F;
using test::Rng;
using test::Soup;

struct Built {
  TriangleSoA tris;
  Grid grid;
};

void Build(const Soup& soup, Built* b, float lambda = 4.0f, int max_res = 512) {
  BuildTriangleSoA(soup.view(), &b->tris);
  BuildGrid(b->tris, lambda, max_res, &b->grid);
}

void Res(double ex, double ey, double ez, size_t n, double lambda, int max_res, int rx, int ry,
         int rz) {
  const double e[3] = {ex, ey, ez};
  int r[3] = {-1, -1, -1};
  ComputeGridResolution(e, n, lambda, max_res, r);
  INFO("extent ", ex, " ", ey, " ", ez, " n ", n, " lambda ", lambda);
  CHECK(r[0] == rx);
  CHECK(r[1] == ry);
  CHECK(r[2] == rz);
}

TEST_CASE("resolution heuristic: res = extent * cbrt(lambda N / V), flat axes, caps") {
  Res(1, 1, 1, 1000, 4, 512, 16, 16, 16);      // cbrt(4000) = 15.87
  Res(2, 1, 1, 1000, 4, 512, 25, 13, 13);      // cbrt(2000) = 12.6
  Res(10, 10, 10, 1000, 4, 512, 16, 16, 16);   // scale-invariant
  Res(1, 1, 1, 1, 4, 512, 2, 2, 2);            // cbrt(4) = 1.59
  Res(1, 1, 0, 1000, 4, 512, 63, 63, 1);       // flat: sqrt(4000) = 63.2 per unit
  Res(1, 1, 1e-6, 1000, 4, 512, 63, 63, 1);    // thin axis drops out, area density
  Res(4, 1, 1e-6, 1000, 4, 512, 126, 32, 1);   // sqrt(1000) = 31.6 per unit
  Res(1, 0, 0, 1000, 4, 512, 512, 1, 1);       // a line: 4000 cells, capped
  Res(1, 0, 0, 1000, 4, 8192, 4000, 1, 1);
  Res(1, 1e-9, 1e-9, 1000, 4, 8192, 4000, 1, 1);
  Res(1, 1, 1, 1000000000, 4, 512, 512, 512, 512);  // cap per axis
  Res(1, 1, 1, 1000, 4, 8, 8, 8, 8);
  Res(1, 1, 1, 0, 4, 512, 1, 1, 1);            // no triangles
  Res(1, 1, 1, 1000, 0, 512, 1, 1, 1);         // lambda 0
  Res(0, 0, 0, 1000, 4, 512, 1, 1, 1);         // a point
  Res(1000, 1, 1, 10, 1, 512, 10, 1, 1);       // long box: 10 cells along x only
}

// Independent exact-as-double triangle / closed box overlap: the 13 axes of the separating
// axis theorem (3 box normals, triangle normal, 9 edge crosses), closed intervals.
bool TriBoxOverlap(const double v[3][3], const double lo[3], const double hi[3]) {
  for (int a = 0; a < 3; ++a) {
    const double mn = std::min({v[0][a], v[1][a], v[2][a]});
    const double mx = std::max({v[0][a], v[1][a], v[2][a]});
    if (mn > hi[a] || mx < lo[a]) return false;
  }
  double c[3], h[3], w[3][3];
  for (int a = 0; a < 3; ++a) {
    c[a] = 0.5 * (lo[a] + hi[a]);
    h[a] = 0.5 * (hi[a] - lo[a]);
  }
  for (int k = 0; k < 3; ++k) {
    for (int a = 0; a < 3; ++a) w[k][a] = v[k][a] - c[a];
  }
  auto separated = [&](const double ax[3]) {
    const double p0 = ax[0] * w[0][0] + ax[1] * w[0][1] + ax[2] * w[0][2];
    const double p1 = ax[0] * w[1][0] + ax[1] * w[1][1] + ax[2] * w[1][2];
    const double p2 = ax[0] * w[2][0] + ax[1] * w[2][1] + ax[2] * w[2][2];
    const double r = h[0] * std::fabs(ax[0]) + h[1] * std::fabs(ax[1]) + h[2] * std::fabs(ax[2]);
    return std::min({p0, p1, p2}) > r || std::max({p0, p1, p2}) < -r;
  };
  double e[3][3];
  for (int k = 0; k < 3; ++k) {
    for (int a = 0; a < 3; ++a) e[k][a] = w[(k + 1) % 3][a] - w[k][a];
  }
  const double n[3] = {e[0][1] * e[1][2] - e[0][2] * e[1][1], e[0][2] * e[1][0] - e[0][0] * e[1][2],
                       e[0][0] * e[1][1] - e[0][1] * e[1][0]};
  if (separated(n)) return false;
  for (int k = 0; k < 3; ++k) {
    for (int a = 0; a < 3; ++a) {
      double unit[3] = {0, 0, 0};
      unit[a] = 1;
      const double ax[3] = {unit[1] * e[k][2] - unit[2] * e[k][1],
                            unit[2] * e[k][0] - unit[0] * e[k][2],
                            unit[0] * e[k][1] - unit[1] * e[k][0]};
      if (separated(ax)) return false;
    }
  }
  return true;
}

// Box of cell (x, y, z), grown by `grow` cells plus `ulps` float ulps of the largest
// coordinate magnitude of the grid.
void CellBox(const Grid& g, int x, int y, int z, double grow, double ulps, double lo[3],
             double hi[3]) {
  const int c[3] = {x, y, z};
  double max_abs = 0.0;
  for (int a = 0; a < 3; ++a) max_abs = std::max({max_abs, std::fabs(double(g.lo[a])), std::fabs(double(g.hi[a]))});
  for (int a = 0; a < 3; ++a) {
    const double cs = g.cell_size[a];
    const double pad = grow * cs + ulps * 1.1920929e-7 * max_abs;
    lo[a] = double(g.lo[a]) + c[a] * cs - pad;
    hi[a] = double(g.lo[a]) + (c[a] + 1) * cs + pad;
  }
}

// Structural invariants plus the binning check against TriBoxOverlap for every (cell, triangle)
// pair. Returns the number of (cell, triangle) pairs whose bounding boxes overlap but whose
// triangle does not touch the cell (what the SAT filter saved).
size_t CheckGrid(const Soup& soup, const Built& b) {
  const Grid& g = b.grid;
  const TriangleSoA& t = b.tris;
  REQUIRE(!g.empty());
  REQUIRE(g.num_cells == size_t(g.res[0]) * g.res[1] * g.res[2]);
  // CSR: monotone offsets, ascending ids, occupancy bit iff non-empty, no degenerate ids
  REQUIRE(g.cell_begin[0] == 0);
  REQUIRE(g.cell_begin[g.num_cells] == g.num_refs);
  size_t occupied = 0, max_per_cell = 0;
  std::vector<std::vector<char>> listed(g.num_cells);
  for (size_t c = 0; c < g.num_cells; ++c) {
    REQUIRE(g.cell_begin[c] <= g.cell_begin[c + 1]);
    const size_t count = g.cell_begin[c + 1] - g.cell_begin[c];
    CHECK(g.Occupied(c) == (count > 0));
    occupied += count > 0;
    max_per_cell = std::max(max_per_cell, count);
    listed[c].assign(t.size, 0);
    for (uint32_t k = g.cell_begin[c]; k < g.cell_begin[c + 1]; ++k) {
      const uint32_t id = g.tri_ids[k];
      REQUIRE(id < t.size);
      CHECK(t.degenerate[id] == 0);
      if (k > g.cell_begin[c]) CHECK(g.tri_ids[k - 1] < id);
      listed[c][id] = 1;
    }
  }
  CHECK(occupied == g.occupied_cells);
  CHECK(max_per_cell == g.max_per_cell);
  // padding bits past num_cells are clear
  for (size_t c = g.num_cells; c < (g.num_cells + 63) / 64 * 64; ++c) CHECK_FALSE(g.Occupied(c));

  size_t missing = 0, far = 0, saved = 0;
  for (size_t i = 0; i < t.size; ++i) {
    if (t.degenerate[i]) continue;
    double v[3][3];
    const MeshView m = soup.view();
    for (int k = 0; k < 3; ++k) {
      for (int a = 0; a < 3; ++a) v[k][a] = m.positions[3 * m.indices[3 * i + k] + a];
    }
    for (int z = 0; z < g.res[2]; ++z) {
      for (int y = 0; y < g.res[1]; ++y) {
        for (int x = 0; x < g.res[0]; ++x) {
          const size_t c = g.CellIndex(x, y, z);
          double lo[3], hi[3];
          CellBox(g, x, y, z, 0.0, 0.0, lo, hi);
          const bool touches = TriBoxOverlap(v, lo, hi);
          if (touches && !listed[c][i]) ++missing;
          // listed cells must at least touch the cell grown by 1% and 16 ulps (the grid's
          // margin is 0.1% and 4 ulps)
          double glo[3], ghi[3];
          CellBox(g, x, y, z, 0.01, 16.0, glo, ghi);
          if (listed[c][i] && !TriBoxOverlap(v, glo, ghi)) ++far;
          // bounding-box-only overlap that the SAT removed
          bool bbox = true;
          for (int a = 0; a < 3; ++a) {
            bbox = bbox && std::min({v[0][a], v[1][a], v[2][a]}) <= hi[a] &&
                   std::max({v[0][a], v[1][a], v[2][a]}) >= lo[a];
          }
          saved += bbox && !listed[c][i];
        }
      }
    }
  }
  CHECK(missing == 0);
  CHECK(far == 0);
  return saved;
}

TEST_CASE("random soups: every triangle is listed in every cell it touches, and only near ones") {
  Rng rng(17);
  size_t saved = 0;
  for (int round = 0; round < 6; ++round) {
    // small and large triangles mixed, so many triangles span several cells diagonally
    Soup soup = test::RandomSoup(rng, 150, -1.0, 1.0, 0.1);
    const Soup big = test::RandomSoup(rng, 30, -1.0, 1.0, 1.0);
    soup.positions.insert(soup.positions.end(), big.positions.begin(), big.positions.end());
    for (const uint32_t i : big.indices) soup.indices.push_back(i + uint32_t(150 * 3));
    Built b;
    Build(soup, &b, round % 2 ? 4.0f : 12.0f);
    INFO("round ", round, " res ", b.grid.res[0], " ", b.grid.res[1], " ", b.grid.res[2]);
    saved += CheckGrid(soup, b);
  }
  MESSAGE("bounding-box cells rejected by the separating-axis filter: ", saved);
  CHECK(saved > 1000);  // the SAT filter really filters
}

TEST_CASE("triangles lying on cell boundaries are listed on both sides") {
  // First build a grid over a box to learn its cell boundaries, then put triangles exactly on
  // (float-rounded) boundary planes, edges and corners, rebuild over the same bounds.
  Rng rng(5);
  Soup soup = test::RandomSoup(rng, 200, 0.0, 8.0, 0.5);
  // two placeholder triangles (same count, inside the bounds), replaced below
  const float d0[3] = {4, 4, 4}, d1[3] = {4.1f, 4, 4}, d2[3] = {4, 4.1f, 4};
  soup.AddTriangle(d0, d1, d2);
  soup.AddTriangle(d0, d1, d2);
  Built probe;
  Build(soup, &probe);
  const Grid& g = probe.grid;
  REQUIRE(g.res[0] >= 4);
  REQUIRE(g.res[1] >= 4);
  const float bx = F(double(g.lo[0]) + 2.0 * g.cell_size[0]);  // plane x = boundary 2|3... 1|2
  const float by = F(double(g.lo[1]) + 3.0 * g.cell_size[1]);
  const float z0 = F(double(g.lo[2]) + 0.5 * (double(g.hi[2]) - g.lo[2]));
  // in the plane x = bx
  const float a[3] = {bx, by - 0.3f * g.cell_size[1], z0}, b2[3] = {bx, by + 0.2f * g.cell_size[1], z0},
              c[3] = {bx, by, z0 + 0.25f * g.cell_size[2]};
  auto replace = [&](uint32_t id, const float* u, const float* v, const float* w) {
    const float* src[3] = {u, v, w};
    for (int k = 0; k < 3; ++k) {
      for (int ax = 0; ax < 3; ++ax) soup.positions[3 * soup.indices[3 * id + k] + ax] = src[k][ax];
    }
  };
  replace(200, a, b2, c);
  // touching the grid line (bx, by) only with one vertex, from the -x -y quadrant
  const float p[3] = {bx, by, z0}, q[3] = {bx - 0.4f * g.cell_size[0], by - 0.1f * g.cell_size[1], z0},
              r[3] = {bx - 0.1f * g.cell_size[0], by - 0.4f * g.cell_size[1], z0 + 0.1f};
  replace(201, p, q, r);
  Built b;
  Build(soup, &b);
  for (int ax = 0; ax < 3; ++ax) {  // same bounds and resolution as the probe
    REQUIRE(b.grid.res[ax] == g.res[ax]);
    REQUIRE(b.grid.lo[ax] == g.lo[ax]);
    REQUIRE(b.grid.cell_size[ax] == g.cell_size[ax]);
  }
  CheckGrid(soup, b);
  const uint32_t plane_id = 200, corner_id = 201;
  auto listed_in = [&](uint32_t id, int x, int y, int z) {
    const size_t cell = b.grid.CellIndex(x, y, z);
    for (uint32_t k = b.grid.cell_begin[cell]; k < b.grid.cell_begin[cell + 1]; ++k) {
      if (b.grid.tri_ids[k] == id) return true;
    }
    return false;
  };
  const int zc = std::min(int((z0 - g.lo[2]) * g.inv_cell_size[2]), g.res[2] - 1);
  CHECK(listed_in(plane_id, 1, 2, zc));
  CHECK(listed_in(plane_id, 2, 2, zc));
  CHECK(listed_in(plane_id, 1, 3, zc));  // the top vertex and edge reach y = by
  CHECK(listed_in(plane_id, 2, 3, zc));
  // the corner triangle touches all four cells around the grid line
  CHECK(listed_in(corner_id, 1, 2, zc));
  CHECK(listed_in(corner_id, 2, 2, zc));
  CHECK(listed_in(corner_id, 1, 3, zc));
  CHECK(listed_in(corner_id, 2, 3, zc));
  CHECK_FALSE(listed_in(corner_id, 3, 3, zc));
}

TEST_CASE("flat scene (all z = 0) builds with one cell along z") {
  Rng rng(9);
  Soup soup;
  for (int i = 0; i < 500; ++i) {
    const double cx = rng.Uniform(-5, 5), cy = rng.Uniform(-5, 5);
    const float a[3] = {F(cx), F(cy), 0.0f}, b[3] = {F(cx + rng.Uniform(0.05, 0.3)), F(cy), 0.0f},
                c[3] = {F(cx), F(cy + rng.Uniform(0.05, 0.3)), 0.0f};
    soup.AddTriangle(a, b, c);
  }
  Built b;
  Build(soup, &b);
  CHECK(b.grid.res[2] == 1);
  CHECK(b.grid.res[0] > 10);
  CHECK(b.grid.res[1] > 10);
  CHECK(b.grid.lo[2] < 0.0f);  // padded around the plane
  CHECK(b.grid.hi[2] > 0.0f);
  // about lambda * N cells in 2D
  CHECK(b.grid.num_cells > 1000);
  CHECK(b.grid.num_cells < 4000);
  CheckGrid(soup, b);
}

TEST_CASE("single triangle, empty mesh, all-degenerate mesh") {
  Soup one;
  const float a[3] = {0, 0, 0}, b[3] = {1, 0, 0}, c[3] = {0, 1, 1};
  one.AddTriangle(a, b, c);
  Built b1;
  Build(one, &b1);
  CHECK(b1.grid.num_refs >= 1);
  CHECK(b1.grid.occupied_cells >= 1);
  CheckGrid(one, b1);
  for (int k = 0; k < 3; ++k) {
    CHECK(b1.grid.lo[k] < std::min({a[k], b[k], c[k]}));
    CHECK(b1.grid.hi[k] > std::max({a[k], b[k], c[k]}));
  }

  Soup empty;
  Built b0;
  Build(empty, &b0);
  CHECK(b0.grid.empty());
  CHECK(b0.grid.num_refs == 0);
  CHECK(b0.grid.Bytes() == 0);

  Soup degenerate;
  degenerate.AddTriangle(a, a, b);
  degenerate.AddTriangle(a, b, b);
  const float l2[3] = {2, 0, 0};
  degenerate.AddTriangle(a, b, l2);
  Built bd;
  Build(degenerate, &bd);
  CHECK(bd.tris.num_degenerate == 3);
  CHECK(bd.grid.empty());
}

TEST_CASE("degenerate triangles are skipped: not binned, not in the bounds") {
  Rng rng(21);
  Soup soup = test::RandomSoup(rng, 100, -1.0, 1.0, 0.3);
  // zero-area triangles, one far outside the others
  const float far0[3] = {1000, 1000, 1000}, far1[3] = {1001, 1000, 1000};
  soup.AddTriangle(far0, far0, far1);
  const float z[3] = {0, 0, 0}, x1[3] = {0.5f, 0.5f, 0.5f}, x2[3] = {1, 1, 1};
  soup.AddTriangle(z, x1, x2);
  Built b;
  Build(soup, &b);
  CHECK(b.tris.num_degenerate == 2);
  CHECK(b.tris.degenerate[100] == 1);
  CHECK(b.tris.degenerate[101] == 1);
  CHECK(b.grid.hi[0] < 2.0f);
  CheckGrid(soup, b);
}

TEST_CASE("huge coordinate offset (1e5) builds conservatively") {
  Rng rng(33);
  Soup soup = test::RandomSoup(rng, 200, 1e5, 1e5 + 20.0, 1.0);
  Built b;
  Build(soup, &b);
  CHECK(b.grid.lo[0] < 1e5f + 1.0f);
  CheckGrid(soup, b);
}

TEST_CASE("ChooseFrameShift: far bounds move to their midpoint, exactly; others stay") {
  auto bounds = [](float lo, float hi) {
    GridBounds b;
    for (int a = 0; a < 3; ++a) b.lo[a] = lo, b.hi[a] = hi;
    b.num_valid = 1;
    return b;
  };
  float shift[3];
  ChooseFrameShift(bounds(-1.0f, 5.0f), shift);  // holds 0
  CHECK(shift[0] == 0.0f);
  ChooseFrameShift(bounds(1.0f, 3.5f), shift);  // closer to 0 than its extent
  CHECK(shift[0] == 0.0f);
  GridBounds empty = bounds(1e5f, 1e5f + 1.0f);
  empty.num_valid = 0;
  ChooseFrameShift(empty, shift);
  CHECK(shift[0] == 0.0f);
  ChooseFrameShift(bounds(148370.0f, 148382.0f), shift);
  CHECK(shift[0] == 148376.0f);
  ChooseFrameShift(bounds(-223429.0f, -223417.0f), shift);
  CHECK(shift[0] == -223423.0f);
  // every float inside far bounds (at their ends and random ones, extents up to the distance,
  // normal and subnormal magnitudes) translates exactly
  Rng rng(71);
  size_t inexact = 0, shifted = 0;
  for (int k = 0; k < 2000; ++k) {
    const double m = std::ldexp(1.0 + rng.Uniform(0.0, 1.0), int(rng.Below(300)) - 150);
    const float lo = float(m), hi = float(m + m * rng.Uniform(0.0, 1.0));
    const float sign = k % 2 == 0 ? 1.0f : -1.0f;
    const GridBounds b = sign > 0 ? bounds(lo, hi) : bounds(-hi, -lo);
    ChooseFrameShift(b, shift);
    if (!(lo > 0.0f) || !(double(hi) - double(lo) <= double(lo))) continue;
    shifted += shift[0] != 0.0f;
    for (int j = 0; j < 50; ++j) {
      const double f = j == 0 ? 0.0 : j == 1 ? 1.0 : rng.Uniform(0.0, 1.0);
      const float v = float(double(b.lo[0]) + f * (double(b.hi[0]) - double(b.lo[0])));
      const float moved = v - shift[0];
      inexact += double(moved) != double(v) - double(shift[0]) || moved + shift[0] != v;
    }
  }
  CHECK(shifted > 1000);
  CHECK(inexact == 0);
}

// Regression: GCC 12.2's SLP vectorizer dropped the float rounding of the cell size where the
// build reads it back as double (-O3 only), so the margin and the bounding-box cell ranges came
// from a slightly different cell size than the stored one (office-graz had 47 more references
// at -O0 than at -O3). Everything derived must come from the stored floats.
TEST_CASE("regression: derived grid parameters use the stored float cell size and bounds") {
  Soup s;
  const float a[3] = {-0.3f, 0.1f, 2.7f}, b[3] = {1.9f, -0.7f, 0.3f}, c[3] = {0.7f, 2.3f, -1.1f};
  const float d[3] = {1.3f, 1.7f, 0.9f}, e[3] = {-0.9f, 0.3f, -0.5f}, f[3] = {0.1f, -0.9f, 1.3f};
  s.AddTriangle(a, b, c);
  s.AddTriangle(d, e, f);
  s.AddTriangle(a, e, d);
  Built bt;
  Build(s, &bt, 7.0f);
  const Grid& g = bt.grid;
  double max_abs = 0.0;
  for (int k = 0; k < 3; ++k) {
    max_abs = std::max({max_abs, std::fabs(double(g.lo[k])), std::fabs(double(g.hi[k]))});
  }
  for (int k = 0; k < 3; ++k) {
    INFO("axis ", k);
    const double cs = g.cell_size[k];
    CHECK(g.margin[k] == 1e-3 * cs + 4.0 * 1.1920928955078125e-7 * max_abs);
    // the float cell size is the rounded extent / res
    CHECK(double(g.cell_size[k]) ==
          double(F((double(g.hi[k]) - double(g.lo[k])) / g.res[k])));
    // bounds strictly enclose the vertices
    CHECK(double(g.lo[k]) < std::min({a[k], b[k], c[k], d[k], e[k], f[k]}));
    CHECK(double(g.hi[k]) > std::max({a[k], b[k], c[k], d[k], e[k], f[k]}));
  }
  CheckGrid(s, bt);
}

TEST_CASE("SIMD degenerate flags equal IsDegenerateTriangle, non-finite triangles counted") {
  Rng rng(41);
  // 37 triangles (not a multiple of any vector width): random ones and every kind of degenerate
  Soup s = test::RandomSoup(rng, 30, -1.0, 1.0, 0.5);
  const float nan = std::numeric_limits<float>::quiet_NaN();
  const float inf = std::numeric_limits<float>::infinity();
  const float a[3] = {0, 0, 0}, b[3] = {1, 0, 0}, c[3] = {2, 0, 0}, d[3] = {0, 1e-30f, 0};
  const float n0[3] = {nan, 0, 0}, i0[3] = {0, 0, inf}, m0[3] = {0, -inf, 0};
  s.AddTriangle(a, a, b);    // repeated vertex
  s.AddTriangle(a, b, c);    // collinear
  s.AddTriangle(a, b, d);    // tiny but not zero area
  s.AddTriangle(n0, b, d);   // NaN
  s.AddTriangle(a, i0, d);   // +inf
  s.AddTriangle(a, b, m0);   // -inf
  s.AddTriangle(b, b, b);    // a point
  TriangleSoA tris;
  BuildTriangleSoA(s.view(), &tris);
  REQUIRE(tris.size == 37);
  size_t degenerate = 0;
  for (size_t i = 0; i < tris.size; ++i) {
    float p[3][3];
    for (int k = 0; k < 3; ++k) {
      for (int ax = 0; ax < 3; ++ax) p[k][ax] = s.positions[3 * s.indices[3 * i + k] + ax];
    }
    INFO("triangle ", i);
    CHECK(tris.degenerate[i] == (IsDegenerateTriangle(p[0], p[1], p[2]) ? 1 : 0));
    degenerate += tris.degenerate[i];
  }
  CHECK(degenerate == 6);
  CHECK(tris.num_degenerate == 6);
  CHECK(tris.num_nonfinite == 3);
  CHECK(tris.degenerate[32] == 0);  // the tiny one
  // rebuilding into the same arrays from a smaller mesh resets the counts
  Soup small = test::RandomSoup(rng, 5, -1.0, 1.0, 0.5);
  BuildTriangleSoA(small.view(), &tris);
  CHECK(tris.size == 5);
  CHECK(tris.num_degenerate == 0);
  CHECK(tris.num_nonfinite == 0);
}

TEST_CASE("SIMD edge tables equal the scalar sums and comparisons, ties included") {
  Rng rng(43);
  size_t cells = 0, passed = 0, ties = 0;
  for (int trial = 0; trial < 300; ++trial) {
    EdgeSet e;
    e.n = trial % 4;
    const int ci0 = int(rng.Below(600)) - 3, cj0 = int(rng.Below(600)) - 3;
    const int ni = 1 + int(rng.Below(trial % 3 == 0 ? 40 : 9)), nj = 1 + int(rng.Below(6));
    auto sum = [&](int k, int ci, int cj) {
      return (e.base[k] + double(cj) * e.sj[k]) + double(ci) * e.si[k];
    };
    for (int k = 0; k < e.n; ++k) {
      e.base[k] = rng.Uniform(-10.0, 10.0);
      e.si[k] = rng.Uniform(-0.2, 0.2);
      e.sj[k] = rng.Uniform(-0.2, 0.2);
      // an interval around some cell's value, its ends often exactly on other cells' values
      const double mid = sum(k, ci0 + int(rng.Below(uint32_t(ni))), cj0 + int(rng.Below(uint32_t(nj))));
      e.lo[k] = rng.Below(2) ? sum(k, ci0 + int(rng.Below(uint32_t(ni))), cj0) : mid - rng.Uniform(0, 1);
      e.hi[k] = rng.Below(2) ? sum(k, ci0 + int(rng.Below(uint32_t(ni))), cj0 + nj - 1)
                             : mid + rng.Uniform(0, 1);
    }
    std::vector<uint8_t> table(size_t(ni) * size_t(nj) + 8, 7);
    SimdEdgeTable(e, ci0, ni, cj0, nj, table.data());
    for (int r = 0; r < nj; ++r) {
      for (int m = 0; m < ni; ++m) {
        bool ok = true;
        for (int k = 0; k < e.n; ++k) {
          const double c = sum(k, ci0 + m, cj0 + r);
          ok = ok && !(c < e.lo[k] || c > e.hi[k]);
          ties += c == e.lo[k] || c == e.hi[k];
        }
        INFO("trial ", trial, " cell ", m, " ", r);
        CHECK(table[size_t(r) * size_t(ni) + size_t(m)] == (ok ? 1 : 0));
        ++cells;
        passed += ok;
      }
    }
    CHECK(table[size_t(ni) * size_t(nj)] == 7);  // nothing written past the table
  }
  MESSAGE("edge-table cells ", cells, ", passing ", passed, ", on an interval end ", ties);
  CHECK(ties > 50);
  CHECK(passed > cells / 10);
  CHECK(passed < cells);
}

TEST_CASE("BuildTriangleSoA gathers the mesh's vertices: every size, stride and target") {
  Rng rng(61);
  test::ForEachTarget([&](const char* target) {
    INFO("target: ", target);
    for (size_t n = 0; n <= 45; n += (n < 20 ? 1 : 7)) {
      for (const size_t stride : {size_t{3}, size_t{4}, size_t{7}}) {
        // exactly sized arrays (ASan: no read past them); vertices shared and in any order
        const size_t vertices = 2 * n + 1;
        std::vector<float> positions(vertices * stride);
        for (float& x : positions) x = rng.UniformF(-100.0, 100.0);
        std::vector<uint32_t> indices(3 * n);
        for (uint32_t& i : indices) i = uint32_t(rng.Below(uint32_t(vertices)));
        MeshView mesh;
        mesh.positions = positions.data();
        mesh.num_vertices = vertices;
        mesh.stride = stride;
        mesh.indices = indices.data();
        mesh.num_triangles = n;
        for (const int threads : {1, 3}) {
          TriangleSoA tris;
          BuildTriangleSoA(mesh, &tris, threads);
          REQUIRE(tris.size == n);
          for (size_t t = 0; t < n; ++t) {
            for (int k = 0; k < 3; ++k) {
              for (int a = 0; a < 3; ++a) {
                INFO("n ", n, " stride ", stride, " triangle ", t, " vertex ", k, " axis ", a);
                CHECK(tris.p[k][a][t] == positions[indices[3 * t + k] * stride + a]);
              }
            }
          }
        }
      }
    }
  });
}

TEST_CASE("SimdMinMaxOffset equals the scalar min-max update: every size, every target") {
  Rng rng(67);
  test::ForEachTarget([&](const char* target) {
    INFO("target: ", target);
    for (size_t n = 0; n <= 200; n += (n < 70 ? 1 : 13)) {
      std::vector<uint8_t> in(n), out(n);  // exactly n bytes (ASan: nothing past them)
      for (size_t i = 0; i < n; ++i) {
        in[i] = uint8_t(rng.Below(20));
        out[i] = uint8_t(rng.Below(20));
      }
      const uint8_t d = uint8_t(1 + rng.Below(15));
      std::vector<uint8_t> expect(out);
      for (size_t i = 0; i < n; ++i) expect[i] = std::min(expect[i], std::max(d, in[i]));
      SimdMinMaxOffset(out.data(), in.data(), n, d);
      INFO("n ", n);
      CHECK(out == expect);
    }
  });
}

TEST_CASE("BuildTriangleSoA's interleaved records match its SoA arrays; GatherListed: every size") {
  Rng rng(73);
  const Soup soup = test::RandomSoup(rng, 300, -1.0, 1.0, 0.3);
  for (const int threads : {1, 2}) {
    TriangleSoA tris;
    BuildTriangleSoA(soup.view(), &tris, threads);
    REQUIRE(tris.size == soup.view().num_triangles);
    for (size_t t = 0; t < tris.size; ++t) {
      for (int c = 0; c < 9; ++c) {
        INFO("threads ", threads, " t ", t, " c ", c);
        CHECK(std::bit_cast<uint32_t>(tris.Vertices(t)[c]) ==
              std::bit_cast<uint32_t>(tris.p[c / 3][c % 3][t]));
      }
    }
  }
  TriangleSoA tris;
  BuildTriangleSoA(soup.view(), &tris);
  TriangleSoA out;  // reused: grown and overwritten
  for (size_t n = 0; n <= 60; ++n) {
    std::vector<uint32_t> ids(n);  // exactly n ids (ASan: nothing read past them)
    for (uint32_t& id : ids) id = uint32_t(rng.Below(uint32_t(tris.size)));
    GatherListed(tris, ids.data(), n, &out);
    REQUIRE(out.size == n);
    for (size_t t = 0; t < n; ++t) {
      CHECK(out.degenerate[t] == 0);
      for (int k = 0; k < 3; ++k) {
        for (int a = 0; a < 3; ++a) {
          INFO("n ", n, " t ", t);
          CHECK(out.p[k][a][t] == tris.p[k][a][ids[t]]);
        }
      }
    }
  }
}

TEST_CASE("SimdMaxIndex: the largest index of unpadded arrays, every size and position") {
  test::ForEachTarget([&](const char* target) {
    INFO("target: ", target);
    for (size_t n = 0; n <= 70; ++n) {
      // exactly n elements on the heap (ASan: no read past them), the largest at every position,
      // values above 2^31 (unsigned order)
      for (size_t at = 0; at < std::max<size_t>(n, 1); ++at) {
        std::vector<uint32_t> v(n);
        for (size_t i = 0; i < n; ++i) v[i] = uint32_t(i * 2654435761u) >> 1;
        if (n > 0) v[at] = 0x80000000u + uint32_t(at);
        const uint32_t expect = n == 0 ? 0 : *std::max_element(v.begin(), v.end());
        INFO("n ", n, " at ", at);
        CHECK(SimdMaxIndex(v.data(), n) == expect);
      }
    }
  });
}

TEST_CASE("box sums of the cell ranges: boxes of more than 2^16 cells, every target") {
  // one triangle across a dense grid (a box of ~10^6 cells: the high 16 bits of the sums) and
  // small ones, degenerate ones among them
  Rng rng(79);
  Soup soup = test::RandomSoup(rng, 600, -1.0, 1.0, 0.05);
  const float a[3] = {-1.0f, -1.0f, -1.0f}, b[3] = {1.0f, 1.0f, -1.0f}, c[3] = {1.0f, -1.0f, 1.0f};
  soup.AddTriangle(a, b, c);
  soup.AddTriangle(a, a, b);
  TriangleSoA tris;
  BuildTriangleSoA(soup.view(), &tris);
  Grid geometry;
  SetGridGeometry(ComputeGridBounds(tris), 2000.0f, 512, &geometry);
  const BinGeometry geo = GridBinGeometry(geometry);
  test::ForEachTarget([&](const char* target) {
    INFO("target: ", target);
    size_t largest = 0;
    for (const bool bin_flags : {false, true}) {
      RangeBlock block;
      for (size_t first = 0; first < tris.size; first += kRangeBlock) {
        const size_t count = std::min(kRangeBlock, tris.size - first);
        SimdTriangleCellRanges(tris, geo, first, count, &block, bin_flags);
        size_t sum = 0, lines = 0;
        for (size_t j = 0; j < count; ++j) {
          sum += block.box[j];
          lines += (block.flags[j] & kRangeLine) ? block.box[j] : 0;
          largest = std::max<size_t>(largest, block.box[j]);
        }
        CHECK(block.box_sum == sum);
        if (bin_flags) CHECK(block.line_sum == lines);
      }
    }
    CHECK(largest > (size_t{1} << 20));
  });
}

TEST_CASE("SIMD 2 x 2-cell masks equal BinTriangleCells on every target") {
  // triangles about a cell wide at random positions (many straddle a cell corner on two axes:
  // 2 x 2 boxes), some on cell planes and with an edge along an axis (an edge of projected
  // normal (0, 0)), on grids of several resolutions and offsets, huge and tiny coordinates
  Rng rng(59);
  size_t quads = 0, partial = 0;
  for (int round = 0; round < 8; ++round) {
    const double scale = round == 6 ? 1e-30 : (round == 7 ? 1e30 : 1.0);
    const double offset = round == 5 ? 1e4 : 0.0;
    Soup soup;
    for (int t = 0; t < 700; ++t) {
      const Soup one = test::RandomSoup(rng, 1, -1.0, 1.0, round % 2 ? 0.12 : 0.3);
      float p[9];
      for (int k = 0; k < 9; ++k) p[k] = F((double(one.positions[k]) + offset) * scale);
      if (t % 7 == 0) p[3] = p[0];  // edge 0 -> 1 along the axes y, z only
      if (t % 11 == 0) p[5] = p[2] = p[8];  // in a z plane
      soup.AddTriangle(p, p + 3, p + 6);
    }
    TriangleSoA tris;
    BuildTriangleSoA(soup.view(), &tris);
    Grid geometry;
    SetGridGeometry(ComputeGridBounds(tris), float(1 + round), 512, &geometry);
    const BinGeometry geo = GridBinGeometry(geometry);
    test::ForEachTarget([&](const char* target) {
      INFO("target: ", target, " round ", round);
      BinScratch scratch;
      RangeBlock block;
      for (size_t first = 0; first < tris.size; first += kRangeBlock) {
        const size_t count = std::min(kRangeBlock, tris.size - first);
        SimdTriangleCellRanges(tris, geo, first, count, &block, /*bin_flags=*/true);
        std::vector<uint16_t> js;
        size_t box_sum = 0, line_sum = 0;
        for (size_t j = 0; j < count; ++j) {
          box_sum += block.box[j];
          line_sum += (block.flags[j] & kRangeLine) ? block.box[j] : 0;
        }
        CHECK(block.box_sum == box_sum);
        CHECK(block.line_sum == line_sum);
        for (size_t j = 0; j < count; ++j) {
          // kRangeQuad: two spanning axes of extent 1, one cell on the third; kRangeLine: at
          // most one spanning axis
          const int s = block.flags[j] & 7;
          bool quad = block.box[j] == 4 && (s == 3 || s == 5 || s == 6);
          const int a = s == 6 ? 1 : 0, b = s == 3 ? 1 : 2;
          quad = quad && block.c1[a][j] - block.c0[a][j] == 1 &&
                 block.c1[b][j] - block.c0[b][j] == 1;
          CHECK(((block.flags[j] & kRangeQuad) != 0) == quad);
          CHECK(((block.flags[j] & kRangeLine) != 0) == ((s & (s - 1)) == 0));
          if (quad) js.push_back(uint16_t(j));
        }
        std::vector<uint8_t> masks(js.size() + 1, 0xee);
        SimdQuadCellMasks(tris, geo, first, block, js.data(), js.size(), masks.data());
        CHECK(masks[js.size()] == 0xee);  // nothing written past the masks
        for (size_t q = 0; q < js.size(); ++q) {
          const size_t j = js[q], i = first + j;
          float v[3][3];
          int c0[3], c1[3];
          bool span[3];
          const int spans = TriangleCellRange(geo, tris, i, v, c0, c1, span);
          REQUIRE(spans == 2);
          const int k = !span[0] ? 0 : (!span[1] ? 1 : 2);
          const int ai = k == 0 ? 1 : 0, aj = k == 2 ? 1 : 2;
          uint32_t expect = 0;
          BinTriangleCells(geo, v, c0, c1, span, spans, &scratch, [&](int x, int y, int z) {
            const int c[3] = {x, y, z};
            expect |= 1u << ((c[ai] - c0[ai]) + 2 * (c[aj] - c0[aj]));
          });
          INFO("triangle ", i);
          CHECK(uint32_t(masks[q]) == expect);
          partial += expect != 15;
        }
        quads += js.size();
      }
    });
  }
  MESSAGE("2 x 2-cell triangles ", quads, ", not in all four cells ", partial);
  CHECK(quads > 1000);
  CHECK(partial > 100);
}

TEST_CASE("CountGridBoxes equals counting the bounding-box cells one by one") {
  Rng rng(47);
  for (int round = 0; round < 4; ++round) {
    // small triangles (boxes of 1-2 cells per axis) and large ones (bigger boxes), plus
    // degenerate triangles, which are not counted
    Soup soup = test::RandomSoup(rng, 300, -1.0, 1.0, 0.15);
    const Soup big = test::RandomSoup(rng, 20, -1.0, 1.0, 1.0);
    for (size_t t = 0; t < big.triangles(); ++t) {
      const float* p = big.positions.data() + 9 * t;
      soup.AddTriangle(p, p + 3, p + 6);
    }
    const float a[3] = {0.1f, 0.2f, 0.3f}, b[3] = {0.4f, 0.2f, 0.3f};
    soup.AddTriangle(a, a, b);
    TriangleSoA tris;
    BuildTriangleSoA(soup.view(), &tris);
    Grid geometry;
    SetGridGeometry(ComputeGridBounds(tris), round % 2 ? 0.5f : 8.0f, 512, &geometry);
    const BinGeometry geo = GridBinGeometry(geometry);
    std::vector<uint8_t> marked(geometry.num_cells, 0);
    size_t refs = 0;
    for (size_t i = 0; i < tris.size; ++i) {
      if (tris.degenerate[i]) continue;
      const float v[3][3] = {{tris.p[0][0][i], tris.p[0][1][i], tris.p[0][2][i]},
                             {tris.p[1][0][i], tris.p[1][1][i], tris.p[1][2][i]},
                             {tris.p[2][0][i], tris.p[2][1][i], tris.p[2][2][i]}};
      int c0[3], c1[3];
      bool span[3];
      if (TriangleCellRange(geo, v, c0, c1, span) < 0) continue;
      for (int z = c0[2]; z <= c1[2]; ++z) {
        for (int y = c0[1]; y <= c1[1]; ++y) {
          for (int x = c0[0]; x <= c1[0]; ++x) {
            marked[geometry.CellIndex(x, y, z)] = 1;
            ++refs;
          }
        }
      }
    }
    size_t occupied = 0;
    for (const uint8_t m : marked) occupied += m;
    const GridBoxCounts counts = CountGridBoxes(tris, geometry);
    INFO("round ", round, " cells ", geometry.num_cells);
    CHECK(counts.cells == geometry.num_cells);
    CHECK(counts.refs == refs);
    CHECK(counts.occupied == occupied);
    CHECK(refs > tris.size);  // some boxes span several cells
  }
}

TEST_CASE("reference arrays grow past their first guess: SAT and line triangles mixed") {
  // far more references than the build's initial room (3 per triangle), from small triangles
  // about a cell wide (separating-axis tested) mixed in every block of triangles with one-cell
  // and line triangles, at several densities: the reference arrays grow many times (an
  // overrun there shows under ASan; the hash check of every shared scene caught one)
  Rng rng(53);
  size_t refs = 0, tris = 0;
  for (int round = 0; round < 10; ++round) {
    Soup soup;
    for (int t = 0; t < 1500; ++t) {
      const float y = rng.UniformF(-1.0, 1.0), z = rng.UniformF(-1.0, 1.0);
      if (t % 3 == 0) {  // a sliver along x over a few cells
        const float x = rng.UniformF(-1.0, 0.8);
        const float a[3] = {x, y, z}, b[3] = {F(x + 0.2), y, z}, c[3] = {F(x + 0.2), F(y + 1e-5), z};
        soup.AddTriangle(a, b, c);
      } else {
        const Soup one = test::RandomSoup(rng, 1, -1.0, 1.0, 0.15);
        const float* p = one.positions.data();
        soup.AddTriangle(p, p + 3, p + 6);
      }
    }
    Built b;
    Build(soup, &b, float(12 + 6 * round));
    INFO("round ", round, " res ", b.grid.res[0], " ", b.grid.res[1], " ", b.grid.res[2]);
    refs += b.grid.num_refs;
    tris += soup.triangles();
    if (round == 0) {
      CheckGrid(soup, b);  // the full check is slow at these densities: once
    } else {
      CHECK(b.grid.cell_begin[b.grid.num_cells] == b.grid.num_refs);
    }
  }
  CHECK(refs > 6 * tris);
}


// The grids of two builds are the same bit for bit: geometry, offsets, ids, bits, statistics.
void CheckSameGrid(const Grid& a, const Grid& b) {
  for (int k = 0; k < 3; ++k) {
    CHECK(a.res[k] == b.res[k]);
    CHECK(a.lo[k] == b.lo[k]);
    CHECK(a.cell_size[k] == b.cell_size[k]);
  }
  REQUIRE(a.num_cells == b.num_cells);
  REQUIRE(a.num_refs == b.num_refs);
  CHECK(a.occupied_cells == b.occupied_cells);
  CHECK(a.max_per_cell == b.max_per_cell);
  if (a.num_cells == 0) return;
  CHECK(std::equal(a.cell_begin.get(), a.cell_begin.get() + a.num_cells + 1, b.cell_begin.get()));
  CHECK(std::equal(a.tri_ids.get(), a.tri_ids.get() + a.num_refs, b.tri_ids.get()));
  const size_t words = (a.num_cells + 63) / 64;
  CHECK(std::equal(a.occupancy.get(), a.occupancy.get() + words, b.occupancy.get()));
}

TEST_CASE("RunParts: each part runs once, for calls back to back and calls after the pool sleeps") {
  // the pool's threads spin between calls, then sleep (build_threads.cc): calls in a row reach
  // spinning threads, calls after a pause sleeping ones; parts counts vary, so the pool holds
  // more threads than some calls use
  std::vector<std::atomic<int>> ran(6);
  for (int call = 0; call < 3000; ++call) {
    const int parts = 1 + call % 5;
    if (call % 500 == 499) std::this_thread::sleep_for(std::chrono::milliseconds(2));
    for (auto& r : ran) r.store(0);
    std::atomic<int> total{0};
    RunParts(parts, [&](int t) {
      ran[size_t(t)].fetch_add(1);
      total.fetch_add(1);
    });
    INFO("call ", call, " parts ", parts);
    REQUIRE(total.load() == parts);
    for (int t = 0; t < 6; ++t) REQUIRE(ran[size_t(t)].load() == (t < parts ? 1 : 0));
  }
  // an exception in a part reaches the caller after every part ran
  std::atomic<int> finished{0};
  CHECK_THROWS_AS(RunParts(3,
                           [&](int t) {
                             finished.fetch_add(1);
                             if (t == 1) throw std::runtime_error("part 1");
                           }),
                  std::runtime_error);
  CHECK(finished.load() == 3);
}

TEST_CASE("threaded build (BuildOptions::build_threads): the same grid and box counts for 1-5 threads") {
  Rng rng(71);
  for (int round = 0; round < 4; ++round) {
    // enough triangles for several parts (2 range blocks each), small and large mixed; round 3:
    // 3,000 copies of one triangle among them, over the reference budget at lambda 64 (the
    // threaded lists fall back to the serial pass and coarsen the same way)
    const size_t n = 2000 + 1500 * size_t(round);
    Soup soup = test::RandomSoup(rng, n, -1.0, 1.0, round == 1 ? 0.4 : 0.05);
    if (round == 3) {
      const float a[3] = {-0.9f, -0.9f, -0.9f}, b[3] = {0.9f, 0.9f, -0.9f}, c[3] = {0.9f, -0.9f, 0.9f};
      for (int k = 0; k < 3000; ++k) soup.AddTriangle(a, b, c);
    }
    TriangleSoA tris;
    BuildTriangleSoA(soup.view(), &tris);
    const float lambda = round == 3 ? 64.0f : float(2 << round);
    Grid one;
    BuildGrid(tris, lambda, 512, &one, 1);
    const GridBoxCounts counts = CountGridBoxes(tris, one, 1);
    for (int threads = 2; threads <= 5; ++threads) {
      INFO("round ", round, " threads ", threads);
      Grid many;
      BuildGrid(tris, lambda, 512, &many, threads);
      CheckSameGrid(one, many);
      const GridBoxCounts c = CountGridBoxes(tris, one, threads);
      CHECK(c.cells == counts.cells);
      CHECK(c.refs == counts.refs);
      CHECK(c.occupied == counts.occupied);
    }
  }
}

TEST_CASE(
    "threaded build: the same triangles, bundles, occupancy words and skip rings for 1-4 threads") {
  Rng rng(73);
  for (const bool bunched : {false, true}) {
    CAPTURE(bunched);
    // 20,000 small triangles (several parts of every pass), every 97th degenerate; bunched: all
    // but 50 in one corner of the bounds, so that the bundle fill's parts (split by bundles)
    // end at other cells than an even split of the cells would
    Soup soup = bunched ? test::RandomSoup(rng, 19950, -1.0, -0.6, 0.01)
                        : test::RandomSoup(rng, 20000, -1.0, 1.0, 0.05);
    if (bunched) {
      const Soup spread = test::RandomSoup(rng, 50, -1.0, 1.0, 0.05);
      for (size_t t = 0; t < spread.triangles(); ++t) {
        float v[3][3];
        for (int k = 0; k < 3; ++k) {
          for (int a = 0; a < 3; ++a) {
            v[k][a] = spread.positions[3 * size_t(spread.indices[3 * t + size_t(k)]) + size_t(a)];
          }
        }
        soup.AddTriangle(v[0], v[1], v[2]);
      }
    }
    for (size_t t = 0; t < soup.triangles(); t += 97) soup.indices[3 * t + 2] = soup.indices[3 * t];
    TriangleSoA one;
    BuildTriangleSoA(soup.view(), &one, 1);
    Grid grid;
    BuildGrid(one, 4.0f, 512, &grid, 1);
    DdaGrid dda_one;
    BuildDdaGrid(grid, nullptr, one, &dda_one, 1);
    REQUIRE(one.num_degenerate > 200);
    for (int threads = 2; threads <= 4; ++threads) {
      INFO("threads ", threads);
      TriangleSoA tris;
      BuildTriangleSoA(soup.view(), &tris, threads);
      CHECK(tris.num_degenerate == one.num_degenerate);
      CHECK(tris.num_nonfinite == one.num_nonfinite);
      CHECK(std::equal(one.degenerate.data(), one.degenerate.data() + one.size,
                       tris.degenerate.data()));
      for (int k = 0; k < 3; ++k) {
        for (int a = 0; a < 3; ++a) {
          CHECK(std::equal(one.p[k][a].data(), one.p[k][a].data() + one.size, tris.p[k][a].data()));
        }
      }
      DdaGrid dda;
      BuildDdaGrid(grid, nullptr, one, &dda, threads);
      REQUIRE(dda.bundles.num_bundles == dda_one.bundles.num_bundles);
      const TriBundles& p = dda.bundles;
      const TriBundles& q = dda_one.bundles;
      CHECK(std::equal(p.cell_begin.get(), p.cell_begin.get() + p.num_cells + 1,
                       q.cell_begin.get()));
      CHECK(std::equal(p.ids.get(), p.ids.get() + kBundleLanes * p.num_bundles, q.ids.get()));
      // NaN padding: compare the bits
      CHECK(std::memcmp(p.data.get(), q.data.get(),
                        kBundleFloats * p.num_bundles * sizeof(float)) == 0);
      CHECK(dda.top_words32 == dda_one.top_words32);
      CHECK(std::equal(dda.bits.get(), dda.bits.get() + dda.top_words32, dda_one.bits.get()));
      CHECK(std::equal(dda.skip.get(), dda.skip.get() + (grid.num_cells + 3) / 4,
                       dda_one.skip.get()));
      CHECK(dda.empty_block_share == dda_one.empty_block_share);
    }
  }
}

}  // namespace
}  // namespace rs
