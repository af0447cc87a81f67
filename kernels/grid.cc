// Uniform grid build: bounds, resolution heuristic, conservative triangle binning (bounding
// box cells filtered by a double-precision separating-axis test), CSR lists in two passes.
#include "kernels/grid.h"

#include <algorithm>
#include <cfloat>
#include <cmath>
#include <string>
#include <vector>

namespace rs {
namespace {

template <typename T>
hwy::AlignedFreeUniquePtr<T[]> Allocate(size_t n) {
  auto p = hwy::AllocateAligned<T>(n == 0 ? 1 : n);
  HWY_ASSERT(p);
  return p;
}

// double -> float through a volatile: GCC 12.2's SLP vectorizer can drop the rounding in
// (double)(float)x at -O2/-O3 (TOOLCHAIN.md), which changed the binning between -O0 and -O3.
// Every float the grid stores and later reads back as double goes through here.
inline float RoundToFloat(double x) {
  volatile float f = static_cast<float>(x);
  return f;
}

// Cell coordinate of x along one axis, clamped to [0, res); NaN -> 0.
inline int ClampedCell(double x, double lo, double inv_cs, int res) {
  const double f = (x - lo) * inv_cs;
  if (!(f >= 0.0)) return 0;
  if (f >= double(res)) return res - 1;
  return std::min(int(f), res - 1);
}

// Separating-axis test of one triangle against the cells of a grid (Akenine-Moller, "Fast
// 3D Triangle-Box Overlap Testing", 2001). The three box axes are covered by the caller's
// bounding-box cell range; this adds the plane normal and the 9 edge x box-axis crosses. All
// in double, so rounding is far below the margin added to every box.
class TriCellsSat {
 public:
  TriCellsSat(const double v[3][3], const Grid& g) {
    const double e[3][3] = {{v[1][0] - v[0][0], v[1][1] - v[0][1], v[1][2] - v[0][2]},
                            {v[2][0] - v[1][0], v[2][1] - v[1][1], v[2][2] - v[1][2]},
                            {v[0][0] - v[2][0], v[0][1] - v[2][1], v[0][2] - v[2][2]}};
    int n = 0;
    // plane normal e0 x e1
    axis_[n][0] = e[0][1] * e[1][2] - e[0][2] * e[1][1];
    axis_[n][1] = e[0][2] * e[1][0] - e[0][0] * e[1][2];
    axis_[n][2] = e[0][0] * e[1][1] - e[0][1] * e[1][0];
    ++n;
    for (int j = 0; j < 3; ++j) {
      // unit_x x e = (0, -ez, ey); unit_y x e = (ez, 0, -ex); unit_z x e = (-ey, ex, 0)
      const double* ej = e[j];
      const double cand[3][3] = {{0.0, -ej[2], ej[1]}, {ej[2], 0.0, -ej[0]}, {-ej[1], ej[0], 0.0}};
      for (const auto& c : cand) {
        if (c[0] == 0.0 && c[1] == 0.0 && c[2] == 0.0) continue;  // edge along a box axis
        axis_[n][0] = c[0];
        axis_[n][1] = c[1];
        axis_[n][2] = c[2];
        ++n;
      }
    }
    num_axes_ = n;
    for (int k = 0; k < n; ++k) {
      const double* a = axis_[k];
      const double p0 = a[0] * v[0][0] + a[1] * v[0][1] + a[2] * v[0][2];
      const double p1 = a[0] * v[1][0] + a[1] * v[1][1] + a[2] * v[1][2];
      const double p2 = a[0] * v[2][0] + a[1] * v[2][1] + a[2] * v[2][2];
      double r = 0.0, base = 0.0;
      for (int i = 0; i < 3; ++i) {
        const double cs = double(g.cell_size[i]);
        r += std::fabs(a[i]) * (0.5 * cs + g.margin[i]);  // enlarged half extent, projected
        base += a[i] * (double(g.lo[i]) + 0.5 * cs);    // centre of cell (0, 0, 0), projected
        step_[k][i] = a[i] * cs;                          // centre moves by one cell
      }
      lo_[k] = std::min({p0, p1, p2}) - r;
      hi_[k] = std::max({p0, p1, p2}) + r;
      base_[k] = base;
    }
  }

  // True if the triangle overlaps cell (x, y, z) enlarged by the margin.
  bool Overlaps(int x, int y, int z) const {
    for (int k = 0; k < num_axes_; ++k) {
      const double c = base_[k] + double(x) * step_[k][0] + double(y) * step_[k][1] +
                       double(z) * step_[k][2];
      if (c < lo_[k] || c > hi_[k]) return false;
    }
    return true;
  }

 private:
  double axis_[10][3];
  double step_[10][3];
  double lo_[10], hi_[10], base_[10];
  int num_axes_ = 0;
};

}  // namespace

void ComputeGridResolution(const double extent[3], size_t num_triangles, double lambda,
                           int max_resolution, int res[3]) {
  const int max_res = std::max(max_resolution, 1);
  res[0] = res[1] = res[2] = 1;
  const double target = lambda * double(num_triangles);
  if (!(target > 0.0) || !std::isfinite(target)) return;
  bool active[3];
  for (int a = 0; a < 3; ++a) active[a] = extent[a] > 0.0 && std::isfinite(extent[a]);
  double cells_per_unit = 0.0;
  // Axes that would get < 1 cell drop out (1 cell) and the others share the budget; at most
  // 3 rounds, since each round that changes anything removes an axis.
  for (int round = 0; round < 3; ++round) {
    int dims = 0;
    double measure = 1.0;
    for (int a = 0; a < 3; ++a) {
      if (active[a]) {
        ++dims;
        measure *= extent[a];
      }
    }
    if (dims == 0) return;
    cells_per_unit = std::pow(target / measure, 1.0 / dims);
    bool changed = false;
    for (int a = 0; a < 3; ++a) {
      if (active[a] && extent[a] * cells_per_unit < 1.0) {
        active[a] = false;
        changed = true;
      }
    }
    if (!changed) break;
  }
  for (int a = 0; a < 3; ++a) {
    if (!active[a]) continue;
    const double r = std::round(extent[a] * cells_per_unit);
    res[a] = r >= double(max_res) ? max_res : std::max(1, int(r));
  }
}

void BuildGrid(const TriangleSoA& tris, float lambda, int max_resolution, Grid* grid) {
  *grid = Grid();
  const size_t n = tris.size;
  // Bounds of the non-degenerate triangles (exact float min/max).
  float blo[3] = {FLT_MAX, FLT_MAX, FLT_MAX};
  float bhi[3] = {-FLT_MAX, -FLT_MAX, -FLT_MAX};
  size_t num_valid = 0;
  for (size_t i = 0; i < n; ++i) {
    if (tris.degenerate[i]) continue;
    ++num_valid;
    for (int a = 0; a < 3; ++a) {
      const float x0 = tris.p[0][a][i], x1 = tris.p[1][a][i], x2 = tris.p[2][a][i];
      blo[a] = std::min(blo[a], std::min(x0, std::min(x1, x2)));
      bhi[a] = std::max(bhi[a], std::max(x0, std::max(x1, x2)));
    }
  }
  if (num_valid == 0) return;  // empty grid: never hit

  // Pad: relative to the largest extent and to the coordinate magnitude (so it is many ulps
  // even far from the origin). Rounded outwards to float.
  double max_extent = 0.0, max_abs = 0.0;
  for (int a = 0; a < 3; ++a) {
    max_extent = std::max(max_extent, double(bhi[a]) - double(blo[a]));
    max_abs = std::max({max_abs, std::fabs(double(blo[a])), std::fabs(double(bhi[a]))});
  }
  const double pad = 1e-5 * max_extent + 1e-6 * max_abs + 1e-30;
  double extent[3];
  for (int a = 0; a < 3; ++a) {
    const double lo = double(blo[a]) - pad, hi = double(bhi[a]) + pad;
    float flo = RoundToFloat(lo), fhi = RoundToFloat(hi);
    if (double(flo) > lo) flo = std::nextafter(flo, -FLT_MAX);
    if (double(fhi) < hi) fhi = std::nextafter(fhi, FLT_MAX);
    grid->lo[a] = flo;
    grid->hi[a] = fhi;
    extent[a] = double(fhi) - double(flo);
    max_abs = std::max({max_abs, std::fabs(double(flo)), std::fabs(double(fhi))});
  }
  ComputeGridResolution(extent, num_valid, lambda, max_resolution, grid->res);
  double inv_cs_d[3];
  for (int a = 0; a < 3; ++a) {
    grid->cell_size[a] = RoundToFloat(extent[a] / grid->res[a]);
    grid->inv_cell_size[a] = RoundToFloat(grid->res[a] / extent[a]);
    inv_cs_d[a] = 1.0 / double(grid->cell_size[a]);
    grid->margin[a] = 1e-3 * double(grid->cell_size[a]) + 4.0 * FLT_EPSILON * max_abs;
  }
  const size_t num_cells = size_t(grid->res[0]) * size_t(grid->res[1]) * size_t(grid->res[2]);
  grid->num_cells = num_cells;

  // Pass 1: the cells of each triangle, appended to one flat array (ref_begin[i] .. [i+1]).
  std::vector<uint32_t> ref_cells;
  ref_cells.reserve(num_valid * 4);
  std::vector<size_t> ref_begin(n + 1);
  for (size_t i = 0; i < n; ++i) {
    ref_begin[i] = ref_cells.size();
    if (tris.degenerate[i]) continue;
    double v[3][3];
    int c0[3], c1[3];
    for (int k = 0; k < 3; ++k) {
      for (int a = 0; a < 3; ++a) v[k][a] = double(tris.p[k][a][i]);
    }
    for (int a = 0; a < 3; ++a) {
      const double mn = std::min({v[0][a], v[1][a], v[2][a]}) - grid->margin[a];
      const double mx = std::max({v[0][a], v[1][a], v[2][a]}) + grid->margin[a];
      c0[a] = ClampedCell(mn, grid->lo[a], inv_cs_d[a], grid->res[a]);
      c1[a] = ClampedCell(mx, grid->lo[a], inv_cs_d[a], grid->res[a]);
    }
    const int spans = (c1[0] > c0[0]) + (c1[1] > c0[1]) + (c1[2] > c0[2]);
    if (spans == 0) {
      ref_cells.push_back(uint32_t(grid->CellIndex(c0[0], c0[1], c0[2])));
      continue;
    }
    // A 2-cell range along one axis: the (margin-grown) triangle crosses or reaches the shared
    // face inside the single cell column, so it overlaps both cells; the SAT would agree.
    if (spans == 1 && c1[0] - c0[0] + c1[1] - c0[1] + c1[2] - c0[2] == 1) {
      ref_cells.push_back(uint32_t(grid->CellIndex(c0[0], c0[1], c0[2])));
      ref_cells.push_back(uint32_t(grid->CellIndex(c1[0], c1[1], c1[2])));
      continue;
    }
    const TriCellsSat sat(v, *grid);
    for (int z = c0[2]; z <= c1[2]; ++z) {
      for (int y = c0[1]; y <= c1[1]; ++y) {
        for (int x = c0[0]; x <= c1[0]; ++x) {
          if (sat.Overlaps(x, y, z)) ref_cells.push_back(uint32_t(grid->CellIndex(x, y, z)));
        }
      }
    }
  }
  ref_begin[n] = ref_cells.size();
  const size_t num_refs = ref_cells.size();
  if (num_refs >= size_t{UINT32_MAX}) {
    throw Error("grid build: " + std::to_string(num_refs) +
                " cell references exceed the 32-bit limit; lower BuildOptions::lambda");
  }

  // Pass 2: counts (stored at cell_begin[c]), inclusive prefix sum -> end of each cell, then
  // fill backwards with pre-decrement so cell_begin[c] ends at the start of cell c and the
  // ids in each cell come out ascending.
  grid->cell_begin = Allocate<uint32_t>(num_cells + 1);
  uint32_t* begin = grid->cell_begin.get();
  std::fill(begin, begin + num_cells + 1, 0u);
  for (const uint32_t c : ref_cells) ++begin[c];
  uint32_t sum = 0;
  size_t max_per_cell = 0, occupied = 0;
  for (size_t c = 0; c < num_cells; ++c) {
    max_per_cell = std::max<size_t>(max_per_cell, begin[c]);
    occupied += begin[c] != 0;
    sum += begin[c];
    begin[c] = sum;
  }
  begin[num_cells] = sum;
  grid->tri_ids = Allocate<uint32_t>(num_refs);
  uint32_t* ids = grid->tri_ids.get();
  for (size_t i = n; i-- > 0;) {
    for (size_t r = ref_begin[i + 1]; r-- > ref_begin[i];) ids[--begin[ref_cells[r]]] = uint32_t(i);
  }

  // Occupancy bits: one per cell, set iff the cell's list is non-empty.
  const size_t words = (num_cells + 63) / 64;
  grid->occupancy = Allocate<uint64_t>(words);
  uint64_t* occ = grid->occupancy.get();
  std::fill(occ, occ + words, uint64_t{0});
  for (size_t c = 0; c < num_cells; ++c) {
    if (begin[c + 1] != begin[c]) occ[c >> 6] |= uint64_t{1} << (c & 63);
  }
  grid->num_refs = num_refs;
  grid->occupied_cells = occupied;
  grid->max_per_cell = max_per_cell;
}

}  // namespace rs
