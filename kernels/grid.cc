// Uniform grid build: bounds, resolution heuristic, conservative triangle binning
// (kernels/grid_binning.h: float cell ranges, exact 2D/3D separating-axis tests only where the
// box spans several cells), counts taken while binning, CSR lists filled in one more pass.
#include "kernels/grid.h"

#include <algorithm>
#include <bit>
#include <cfloat>
#include <cmath>
#include <string>
#include <vector>

#include "kernels/grid_binning.h"

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

// Grows the reference array to hold at least `used + more` entries (doubling), keeping `used`.
// The references are counted in uint32 (CSR offsets): more than that is a user error.
void Grow(hwy::AlignedFreeUniquePtr<uint32_t[]>* refs, size_t used, size_t* capacity,
          size_t more) {
  if (used + more >= size_t{UINT32_MAX}) {
    throw Error("grid build: more than 2^32 - 1 cell references; lower BuildOptions::lambda");
  }
  const size_t grown = std::max(2 * *capacity, used + more);
  auto bigger = Allocate<uint32_t>(grown);
  std::copy(refs->get(), refs->get() + used, bigger.get());
  *refs = std::move(bigger);
  *capacity = grown;
}

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

GridBounds ComputeGridBounds(const TriangleSoA& tris) {
  GridBounds b;
  // Bounds of the non-degenerate triangles (exact float min/max), a vector at a time.
  float blo[3], bhi[3];
  SimdTriangleBounds(tris, blo, bhi, &b.num_valid);
  if (b.num_valid == 0) return b;
  // Pad: relative to the largest extent and to the coordinate magnitude (so it is many ulps
  // even far from the origin). Rounded outwards to float.
  double max_extent = 0.0, max_abs = 0.0;
  for (int a = 0; a < 3; ++a) {
    max_extent = std::max(max_extent, double(bhi[a]) - double(blo[a]));
    max_abs = std::max({max_abs, std::fabs(double(blo[a])), std::fabs(double(bhi[a]))});
  }
  const double pad = 1e-5 * max_extent + 1e-6 * max_abs + 1e-30;
  for (int a = 0; a < 3; ++a) {
    const double lo = double(blo[a]) - pad, hi = double(bhi[a]) + pad;
    float flo = RoundToFloat(lo), fhi = RoundToFloat(hi);
    if (double(flo) > lo) flo = std::nextafter(flo, -FLT_MAX);
    if (double(fhi) < hi) fhi = std::nextafter(fhi, FLT_MAX);
    b.lo[a] = flo;
    b.hi[a] = fhi;
  }
  return b;
}

void SetGridGeometry(const GridBounds& bounds, float lambda, int max_resolution, Grid* grid) {
  *grid = Grid();
  if (bounds.num_valid == 0) return;  // empty grid: never hit
  double extent[3], max_abs = 0.0;
  for (int a = 0; a < 3; ++a) {
    grid->lo[a] = bounds.lo[a];
    grid->hi[a] = bounds.hi[a];
    extent[a] = double(bounds.hi[a]) - double(bounds.lo[a]);
    max_abs = std::max({max_abs, std::fabs(double(bounds.lo[a])), std::fabs(double(bounds.hi[a]))});
  }
  ComputeGridResolution(extent, bounds.num_valid, lambda, max_resolution, grid->res);
  for (int a = 0; a < 3; ++a) {
    grid->cell_size[a] = RoundToFloat(extent[a] / grid->res[a]);
    grid->inv_cell_size[a] = RoundToFloat(grid->res[a] / extent[a]);
    grid->margin[a] = 1e-3 * double(grid->cell_size[a]) + 4.0 * FLT_EPSILON * max_abs;
  }
  grid->num_cells = size_t(grid->res[0]) * size_t(grid->res[1]) * size_t(grid->res[2]);
}

BinGeometry GridBinGeometry(const Grid& grid) {
  BinGeometry geo;
  for (int a = 0; a < 3; ++a) {
    geo.lo[a] = double(grid.lo[a]);
    geo.cs[a] = double(grid.cell_size[a]);
    geo.margin[a] = grid.margin[a];
    geo.res[a] = grid.res[a];
  }
  FinishBinGeometry(grid.lo, grid.inv_cell_size, &geo);
  return geo;
}

GridBoxCounts CountGridBoxes(const TriangleSoA& tris, const Grid& geometry) {
  GridBoxCounts c;
  if (geometry.num_cells == 0) return c;
  c.cells = geometry.num_cells;
  const BinGeometry geo = GridBinGeometry(geometry);
  // one byte per cell: boxes of at most 2 cells per axis (nearly all at the lambdas tried) mark
  // their corners with 8 unconditional stores (repeats on 1-cell axes), no loop to mispredict;
  // flagged triangles (box 0, range [0, 0]) mark the spare byte at num_cells instead
  const size_t num_cells = geometry.num_cells;
  std::vector<uint8_t> marked(num_cells + 1, 0);
  uint8_t* mark = marked.data();
  const size_t stride_y = size_t(geometry.res[0]);
  const size_t stride_z = stride_y * size_t(geometry.res[1]);
  RangeBlock block;
  for (size_t first = 0; first < tris.size; first += kRangeBlock) {
    const size_t count = std::min(kRangeBlock, tris.size - first);
    SimdTriangleCellRanges(tris, geo, first, count, &block);
    for (size_t j = 0; j < count; ++j) c.refs += size_t(block.box[j]);
    for (size_t j = 0; j < count; ++j) {
      const int x0 = block.c0[0][j], y0 = block.c0[1][j], z0 = block.c0[2][j];
      const int ex = block.c1[0][j] - x0, ey = block.c1[1][j] - y0, ez = block.c1[2][j] - z0;
      const size_t at = size_t(x0) + stride_y * size_t(y0) + stride_z * size_t(z0);
      const size_t cell = block.box[j] != 0 ? at : num_cells;
      if ((ex | ey | ez) <= 1) {
        const size_t dx = size_t(ex), dy = stride_y * size_t(ey), dz = stride_z * size_t(ez);
        mark[cell] = 1;
        mark[cell + dx] = 1;
        mark[cell + dy] = 1;
        mark[cell + dx + dy] = 1;
        mark[cell + dz] = 1;
        mark[cell + dz + dx] = 1;
        mark[cell + dz + dy] = 1;
        mark[cell + dz + dx + dy] = 1;
        continue;
      }
      for (int z = 0; z <= ez; ++z) {
        for (int y = 0; y <= ey; ++y) {
          uint8_t* row = mark + cell + stride_y * size_t(y) + stride_z * size_t(z);
          std::fill(row, row + ex + 1, uint8_t{1});
        }
      }
    }
  }
  size_t occupied = 0;
  for (size_t k = 0; k < num_cells; ++k) occupied += mark[k];
  c.occupied = occupied;
  return c;
}

void BuildGrid(const TriangleSoA& tris, float lambda, int max_resolution, Grid* grid) {
  BuildGrid(tris, ComputeGridBounds(tris), lambda, max_resolution, grid);
}

void BuildGrid(const TriangleSoA& tris, const GridBounds& bounds, float lambda, int max_resolution,
               Grid* grid) {
  SetGridGeometry(bounds, lambda, max_resolution, grid);
  if (grid->num_cells == 0) return;
  const size_t n = tris.size;
  const size_t num_valid = bounds.num_valid;
  const size_t num_cells = grid->num_cells;
  const BinGeometry geo = GridBinGeometry(*grid);

  // Pass 1: the cells of each triangle, appended to one flat array (ref_begin[i] .. [i+1]),
  // counted per cell on the way (cell_begin[c] holds the count of cell c). Temporary arrays are
  // left uninitialised: every element read is written first.
  grid->cell_begin = Allocate<uint32_t>(num_cells + 1);
  uint32_t* begin = grid->cell_begin.get();
  std::fill(begin, begin + num_cells + 1, 0u);
  size_t capacity = num_valid * 3 + 64;
  auto ref_cells = Allocate<uint32_t>(capacity);
  auto ref_begin = Allocate<uint32_t>(n + 1);
  size_t num_refs = 0;
  BinScratch scratch;
  const size_t stride_y = size_t(grid->res[0]), stride_z = stride_y * size_t(grid->res[1]);
  const size_t strides[3] = {1, stride_y, stride_z};
  const float* p[3][3];
  for (int k = 0; k < 3; ++k) {
    for (int a = 0; a < 3; ++a) p[k][a] = tris.p[k][a].data();
  }
  RangeBlock block;
  for (size_t first = 0; first < n; first += kRangeBlock) {
    const size_t count = std::min(kRangeBlock, n - first);
    SimdTriangleCellRanges(tris, geo, first, count, &block);
    // room for the block's one-cell and line triangles (all their box cells are emitted) at
    // once; each triangle tested by BinTriangleCells makes room for its box plus that reserve
    // below (the line triangles after it in the block still need theirs)
    size_t lines = 0;
    for (size_t j = 0; j < count; ++j) {
      const int spans_mask = block.flags[j] & 7;
      lines += (spans_mask & (spans_mask - 1)) == 0 ? size_t(block.box[j]) : 0;
    }
    if (num_refs + lines > capacity) Grow(&ref_cells, num_refs, &capacity, lines);
    uint32_t* cells_out = ref_cells.get();
    for (size_t j = 0; j < count; ++j) {
      const uint32_t i = uint32_t(first + j);
      ref_begin[i] = uint32_t(num_refs);
      const int32_t flags = block.flags[j];
      // degenerate, or outside (cannot happen: the bounds contain every triangle)
      if (flags & (kRangeDegenerate | kRangeOutside)) continue;
      const int c0[3] = {block.c0[0][j], block.c0[1][j], block.c0[2][j]};
      size_t c = size_t(c0[0]) + stride_y * size_t(c0[1]) + stride_z * size_t(c0[2]);
      const int spans_mask = flags & 7;
      if ((spans_mask & (spans_mask - 1)) == 0) {
        // one cell (the common case at low lambda), or a line of cells along one axis: the
        // triangle crosses them all (BinTriangleCells)
        const int a = spans_mask == 4 ? 2 : spans_mask >> 1;  // 0 -> axis 0, a 1-cell range
        const size_t stride = strides[a];
        const int cells = block.c1[a][j] - c0[a] + 1;
        for (int k = 0; k < cells; ++k, c += stride) {
          cells_out[num_refs++] = uint32_t(c);
          ++begin[c];
        }
        continue;
      }
      const int c1[3] = {block.c1[0][j], block.c1[1][j], block.c1[2][j]};
      const bool span[3] = {(flags & 1) != 0, (flags & 2) != 0, (flags & 4) != 0};
      const int spans = int(span[0]) + int(span[1]) + int(span[2]);
      const float v[3][3] = {{p[0][0][i], p[0][1][i], p[0][2][i]},
                             {p[1][0][i], p[1][1][i], p[1][2][i]},
                             {p[2][0][i], p[2][1][i], p[2][2][i]}};
      // its box, and what the block's one-cell and line triangles after it may still need
      if (num_refs + size_t(block.box[j]) + lines > capacity) {
        Grow(&ref_cells, num_refs, &capacity, size_t(block.box[j]) + lines);
        cells_out = ref_cells.get();
      }
      BinTriangleCells(geo, v, c0, c1, span, spans, &scratch, [&](int x, int y, int z) {
        const size_t cell = size_t(x) + stride_y * size_t(y) + stride_z * size_t(z);
        cells_out[num_refs++] = uint32_t(cell);
        ++begin[cell];
      });
    }
  }

  // Inclusive prefix sum -> end of each cell (occupancy bits and statistics on the way), then
  // fill backwards with pre-decrement so cell_begin[c] ends at the start of cell c and the ids
  // in each cell come out ascending.
  const size_t words = (num_cells + 63) / 64;
  grid->occupancy = Allocate<uint64_t>(words);
  uint64_t* occ = grid->occupancy.get();
  uint32_t sum = 0;
  size_t max_per_cell = 0, occupied = 0;
  for (size_t w = 0; w < words; ++w) {
    const size_t end = std::min(num_cells, 64 * w + 64);
    uint64_t bits = 0;
    for (size_t c = 64 * w; c < end; ++c) {
      const uint32_t count = begin[c];
      max_per_cell = std::max<size_t>(max_per_cell, count);
      bits |= uint64_t{count != 0} << (c & 63);
      sum += count;
      begin[c] = sum;
    }
    occ[w] = bits;
    occupied += size_t(std::popcount(bits));
  }
  begin[num_cells] = sum;
  grid->tri_ids = Allocate<uint32_t>(num_refs);
  uint32_t* ids = grid->tri_ids.get();
  ref_begin[n] = uint32_t(num_refs);
  const uint32_t* cells_in = ref_cells.get();
  for (size_t i = n; i-- > 0;) {
    for (size_t r = ref_begin[i + 1]; r-- > ref_begin[i];) ids[--begin[cells_in[r]]] = uint32_t(i);
  }
  grid->num_refs = num_refs;
  grid->occupied_cells = occupied;
  grid->max_per_cell = max_per_cell;
}

}  // namespace rs
