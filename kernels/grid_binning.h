// Conservative triangle -> cell binning shared by the uniform grid (kernels/grid.cc) and the 8x8x8
// sub-grids (kernels/two_level.cc): float bounding-box cell ranges widened by a proven slack,
// then the separating-axis test split into its 2D projections (exact, in double) only where the
// box spans more than one cell on two or three axes. Internal header; build code only.
#pragma once

#include <algorithm>
#include <bit>
#include <cfloat>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <new>
#include <string>
#include <vector>

#include "kernels/grid.h"
#include "streams/block_memory.h"  // AllocateBlockArray

namespace rs {

// "123456789 bytes (117.7 MiB)", for the build's error messages.
inline std::string BytesText(double bytes) {
  char text[64];
  std::snprintf(text, sizeof(text), "%.0f bytes (%.1f MiB)", bytes, bytes / 1048576.0);
  return text;
}

// An aligned array of n elements (at least one) for a build structure; throws rs::Error naming
// `what` and the bytes asked for if they cannot be allocated (never aborts).
template <typename T>
hwy::AlignedFreeUniquePtr<T[]> AllocateBuildArray(size_t n, const char* what) {
  const size_t count = n == 0 ? 1 : n;
  hwy::AlignedFreeUniquePtr<T[]> p;
  if (count <= (size_t{1} << 62) / sizeof(T)) p = AllocateBlockArray<T>(count);
  if (!p) {
    throw Error(std::string("grid build: out of memory: cannot allocate ") + what + " (" +
                std::to_string(count) + " x " + std::to_string(sizeof(T)) + " = " +
                BytesText(double(count) * double(sizeof(T))) +
                "); lower BuildOptions::lambda or max_resolution");
  }
  return p;
}

// One level of cells: cell k along axis a spans [lo + k cs, lo + (k + 1) cs] (in double, from
// the stored floats); a triangle is listed in a cell iff it overlaps that box grown by margin.
struct BinGeometry {
  double lo[3];
  double cs[3];
  double margin[3];
  int res[3];
  // Fast path: f = (x - lo_f) * inv_f in float, in cells. |f - (x - lo) / cs| <= 2^-22 |f| +
  // 2^-23 |f| (two roundings of the product chain plus inv_f = 1 / cs to 2^-23), so widening
  // by reach = margin / cs + slack, slack = 1e-6 + 1e-6 (res + 2), makes the float range
  // contain the exact range near every decision point f ~ [0, res] (res < 2^20).
  float lo_f[3];
  float inv_f[3];
  float reach[3];
};

// Fills the fast-path fields of `g` from lo, cs, margin, res and the float inverse cell size.
inline void FinishBinGeometry(const float lo_f[3], const float inv_f[3], BinGeometry* g) {
  for (int a = 0; a < 3; ++a) {
    g->lo_f[a] = lo_f[a];
    g->inv_f[a] = inv_f[a];
    const double slack = 1e-6 + 1e-6 * (double(g->res[a]) + 2.0);
    // round the reach up so the float value is never below the exact one
    const double reach = g->margin[a] / g->cs[a] + slack;
    float r = static_cast<float>(reach);
    if (double(r) < reach) r = std::nextafter(r, FLT_MAX);
    g->reach[a] = r;
  }
}

// The BinGeometry of a grid's cells (its lo, cell size, margin, res, inverse cell size).
BinGeometry GridBinGeometry(const Grid& grid);

// SIMD passes of the build (kernels/grid_simd.cc, Highway dynamic dispatch).

// tris->degenerate[i] = IsDegenerateTriangle(triangle i) for i < size (the same flags bit for bit),
// num_degenerate and num_nonfinite. Reads the padded vertex arrays (size vertices valid).
void SimdDegenerateFlags(TriangleSoA* tris);
// The same for triangles [first, last) (first a multiple of 8): their flags, and their counts in
// *degenerate and *nonfinite (tris->num_* are not written). Parts of one array may run at once.
void SimdDegenerateFlags(TriangleSoA* tris, size_t first, size_t last, size_t* degenerate,
                         size_t* nonfinite);

// out[i] = min(out[i], max(d, in[i])) for i < n: one offset of the empty-space rings' windowed
// min-max (BuildSkipRings, kernels/dda_grid.cc), a vector of bytes at a time (the compiler
// vectorizes the scalar loop for SSE2 only). out and in do not overlap; unpadded: whole
// vectors, the last one overlapping the one before (the update is idempotent).
void SimdMinMaxOffset(uint8_t* out, const uint8_t* in, size_t n, uint8_t d);

// The largest of p[0, n) (0 if n = 0), a vector at a time: unpadded caller memory (whole
// vectors while they fit, then the rest one by one). The mesh's index check (rs::Accel).
uint32_t SimdMaxIndex(const uint32_t* p, size_t n);

// Float min / max of the vertices of the non-degenerate triangles (+-FLT_MAX if none) and
// their number.
void SimdTriangleBounds(const TriangleSoA& tris, float lo[3], float hi[3], size_t* num_valid);

// TriangleCellRange for a block of triangles, a vector at a time, with the same arithmetic, and
// the corner's cell index and the box's index steps (the grid has res[0] res[1] res[2] < 2^32
// cells, so 32-bit lanes hold them exactly).
inline constexpr size_t kRangeBlock = 256;
inline constexpr int32_t kRangeOutside = 8;      // flags bit: misses the grid (no cells)
inline constexpr int32_t kRangeDegenerate = 16;  // flags bit: degenerate triangle (skip)
inline constexpr int32_t kRangeSmall = 32;       // flags bit: at most 2 cells on every axis
// flags bit (bin_flags only): at most one spanning axis (one cell, or a line of cells:
// BinTriangleCells lists the whole box). Also set on some flagged triangles (their box is 0).
inline constexpr int32_t kRangeLine = 64;
// flags bit (bin_flags only): 2 x 2 cells (box 4, two axes of extent 1) and not spanning on the
// third axis: the triangles SimdQuadCellMasks tests.
inline constexpr int32_t kRangeQuad = 128;
struct RangeBlock {
  int32_t c0[3][kRangeBlock];  // [0, 0] for flagged (degenerate or outside) triangles
  int32_t c1[3][kRangeBlock];
  uint32_t box[kRangeBlock];   // cells in the box [c0, c1] (<= num_cells < 2^32), 0 if flagged
  int32_t flags[kRangeBlock];  // bit a: spans on axis a; kRangeOutside; kRangeDegenerate;
                               // kRangeSmall; kRangeLine; kRangeQuad
  // Cell index of the corner c0, c0[0] + res[0] (c0[1] + res[1] c0[2]); for flagged triangles
  // res[0] res[1] res[2] (one past the last cell).
  uint32_t cell[kRangeBlock];
  // (c1[a] - c0[a]) x the cell-index stride of axis a (1, res[0], res[0] res[1]); 0 if flagged.
  uint32_t step[3][kRangeBlock];
  size_t box_sum = 0;   // sum of box[0, count)
  size_t line_sum = 0;  // bin_flags only: sum of box[j] over the kRangeLine triangles j < count
};
// Fills out for triangles [first, first + count), count <= kRangeBlock, first + count <= size.
// kRangeLine and kRangeQuad are set only with bin_flags (the binning's; the box counts and the
// sub-grids do not read them).
void SimdTriangleCellRanges(const TriangleSoA& tris, const BinGeometry& g, size_t first,
                            size_t count, RangeBlock* out, bool bin_flags = false);

// The 2 x 2-cell triangles of a block (the most common ones after the 1-cell and line
// triangles, kRangeQuad): spanning exactly 2 cells on two axes i < j and one cell on the third.
// For block entries js[0, n) (indices into `block`, triangles first + js[t]), masks[t] gets bit
// m + 2 r
// set iff cell (c0[i] + m, c0[j] + r) passes the 2D edge tests of binning::Edges2D(i, j) on
// that triangle: the same sums, products and comparisons per lane as Edges2D's constructor
// and SimdEdgeTable, so the same cells as BinTriangleCells bit for bit, a vector of triangles
// at a time.
void SimdQuadCellMasks(const TriangleSoA& tris, const BinGeometry& g, size_t first,
                       const RangeBlock& block, const uint16_t* js, size_t n, uint8_t* masks);

// The edge constraints of a triangle's 2D projection (binning::Edges2D): cell (ci, cj) passes
// edge k iff c = (base[k] + double(cj) * sj[k]) + double(ci) * si[k] is within [lo[k], hi[k]].
struct EdgeSet {
  double lo[3], hi[3], base[3], si[3], sj[3];
  int n = 0;  // edges (<= 3)
};
// out[r * ni + m] = 1 iff cell (ci0 + m, cj0 + r) passes every edge of `e`, else 0, for m < ni,
// r < nj; the sums, products and comparisons are the scalar ones above, bit for bit.
void SimdEdgeTable(const EdgeSet& e, int ci0, int ni, int cj0, int nj, uint8_t* out);

// Scratch space reused across triangles (2D projection tables of large triangles, and the
// per-column terms of the plane test).
struct BinScratch {
  std::vector<uint8_t> table[3];
  std::vector<double> terms;
};

namespace binning {

// Cell coordinate of a fast-path value, floor(f) clamped to [-1, res] (-1: below the grid,
// res: above). Branch-free: floor(f) = trunc(f + 1) - 1 for f >= -1. The rounding of f + 1
// (<= 2^-24 (res + 1) cells) is covered by the slack in BinGeometry::reach.
inline int RawCell(float f, float res_f) {
  const float c = std::min(std::max(f, -1.0f), res_f);
  return int(c + 1.0f) - 1;
}

// The 2D separating-axis test of a triangle's projection onto axes (i, j) against the cells'
// rectangles grown by the margin: the 3 edge normals (the rectangle's own axes are covered by
// the bounding-box ranges). Exact in double (products of floats are exact).
class Edges2D {
 public:
  Edges2D(const double v[3][3], const BinGeometry& g, int i, int j) {
    int n = 0;
    for (int e = 0; e < 3; ++e) {
      const double* p = v[e];
      const double* q = v[e == 2 ? 0 : e + 1];
      const double* r = v[e == 0 ? 2 : e - 1];  // the third vertex
      // normal of the projected edge p -> q
      const double ni = -(q[j] - p[j]), nj = q[i] - p[i];
      if (ni == 0.0 && nj == 0.0) continue;  // edge along the third axis: no constraint
      const double pp = ni * p[i] + nj * p[j];
      const double pr = ni * r[i] + nj * r[j];
      const double half = std::fabs(ni) * (0.5 * g.cs[i] + g.margin[i]) +
                          std::fabs(nj) * (0.5 * g.cs[j] + g.margin[j]);
      e_.lo[n] = std::min(pp, pr) - half;
      e_.hi[n] = std::max(pp, pr) + half;
      e_.base[n] = ni * (g.lo[i] + 0.5 * g.cs[i]) + nj * (g.lo[j] + 0.5 * g.cs[j]);
      e_.si[n] = ni * g.cs[i];
      e_.sj[n] = nj * g.cs[j];
      ++n;
    }
    e_.n = n;
  }
  bool Overlaps(int ci, int cj) const {
    for (int k = 0; k < e_.n; ++k) {
      const double c = e_.base[k] + double(ci) * e_.si[k] + double(cj) * e_.sj[k];
      if (c < e_.lo[k] || c > e_.hi[k]) return false;
    }
    return true;
  }
  // out[r * ni + m] = Overlaps(ci0 + m, cj0 + r) for m < ni, r < nj, edge by edge over each row
  // as (base + double(cj) * sj) + double(ci) * si (the sum in another order than Overlaps': the
  // difference, ~1e-16 of the coordinates, is far below the margin). SimdEdgeTable.
  void Table(int ci0, int ni, int cj0, int nj, uint8_t* out) const {
    SimdEdgeTable(e_, ci0, ni, cj0, nj, out);
  }

 private:
  EdgeSet e_;
};

// The plane test: the triangle's plane against the cell boxes grown by the margin.
class Plane3D {
 public:
  Plane3D(const double v[3][3], const BinGeometry& g) {
    const double e0[3] = {v[1][0] - v[0][0], v[1][1] - v[0][1], v[1][2] - v[0][2]};
    const double e1[3] = {v[2][0] - v[1][0], v[2][1] - v[1][1], v[2][2] - v[1][2]};
    const double n[3] = {e0[1] * e1[2] - e0[2] * e1[1], e0[2] * e1[0] - e0[0] * e1[2],
                         e0[0] * e1[1] - e0[1] * e1[0]};
    double r = 0.0, base = 0.0;
    for (int a = 0; a < 3; ++a) {
      r += std::fabs(n[a]) * (0.5 * g.cs[a] + g.margin[a]);
      base += n[a] * (g.lo[a] + 0.5 * g.cs[a]);
      step_[a] = n[a] * g.cs[a];
    }
    const double p0 = n[0] * v[0][0] + n[1] * v[0][1] + n[2] * v[0][2];
    const double p1 = n[0] * v[1][0] + n[1] * v[1][1] + n[2] * v[1][2];
    const double p2 = n[0] * v[2][0] + n[1] * v[2][1] + n[2] * v[2][2];
    lo_ = std::min({p0, p1, p2}) - r;
    hi_ = std::max({p0, p1, p2}) + r;
    base_ = base;
  }
  bool Overlaps(int x, int y, int z) const {
    const double c = base_ + double(x) * step_[0] + double(y) * step_[1] + double(z) * step_[2];
    return c >= lo_ && c <= hi_;
  }
  // Overlaps(x, y, z) == Inside((XTerm(x) + Term(1, y)) + Term(2, z)) bit for bit: the same
  // sums in the same order, with the terms taken once per column, row and layer.
  double XTerm(int x) const { return base_ + double(x) * step_[0]; }
  double Term(int axis, int c) const { return double(c) * step_[axis]; }
  bool Inside(double c) const { return c >= lo_ && c <= hi_; }

 private:
  double step_[3], lo_, hi_, base_;
};

}  // namespace binning

// Calls emit(x, y, z) for every cell of `g` that triangle v (float vertices, finite) overlaps,
// grown by the margin, in x-fastest order, each cell once. Never misses a cell (the float ranges
// contain the exact ones); may add a cell that the bounding box reaches within the slack
// (1e-6 (res + 3) cells) when the box spans one or two cells only on that axis. Cells outside
// [0, res) are clipped (sub-grids bin the lists of their parent cell).
//   spans (axes whose range has > 1 cell, before clipping):
//   0: one cell. 1: every cell of the range (the triangle is connected and lies within one
//   cell on the other two axes, so it crosses them all). 2: the triangle lies within the layer
//   of the third axis, so the 2D test in the plane of the two spanning axes is exact. 3: the
//   full SAT = plane test + the 2D tests of the three coordinate planes (the 9 edge x axis
//   crosses of Akenine-Moller's test are exactly those 2D edge normals).
// Cell ranges of triangle v on the three axes: [c0, c1] clipped to the grid, span[a] = the
// unclipped range has more than one cell. Returns the number of spanning axes, or -1 if the
// triangle (grown by the margin) misses the grid on some axis.
inline int TriangleCellRange(const BinGeometry& g, const float v[3][3], int c0[3], int c1[3],
                             bool span[3]) {
  int spans = 0;
  bool outside = false;
  for (int a = 0; a < 3; ++a) {
    const float mn = std::min(v[0][a], std::min(v[1][a], v[2][a]));
    const float mx = std::max(v[0][a], std::max(v[1][a], v[2][a]));
    const float res_f = float(g.res[a]);
    const int r0 = binning::RawCell((mn - g.lo_f[a]) * g.inv_f[a] - g.reach[a], res_f);
    const int r1 = binning::RawCell((mx - g.lo_f[a]) * g.inv_f[a] + g.reach[a], res_f);
    span[a] = r1 > r0;
    spans += span[a];
    c0[a] = std::max(r0, 0);
    c1[a] = std::min(r1, g.res[a] - 1);
    outside |= c1[a] < c0[a];
  }
  return outside ? -1 : spans;
}

// TriangleCellRange of triangle i of `tris`; its vertices are left in v.
inline int TriangleCellRange(const BinGeometry& g, const TriangleSoA& tris, size_t i,
                             float v[3][3], int c0[3], int c1[3], bool span[3]) {
  for (int k = 0; k < 3; ++k) {
    for (int a = 0; a < 3; ++a) v[k][a] = tris.p[k][a][i];
  }
  return TriangleCellRange(g, v, c0, c1, span);
}

// Calls emit(x, y, z) for every cell of `g` that triangle v (float vertices, finite) overlaps,
// grown by the margin, in x-fastest order, each cell once, given its TriangleCellRange. Never
// misses a cell (the float ranges contain the exact ones); may add a cell that the bounding box
// reaches within the slack (1e-6 (res + 3) cells) when the box spans one or two cells only on
// that axis. Cells outside [0, res) are clipped (sub-grids bin the lists of their parent cell).
//   spans (axes whose range has > 1 cell, before clipping):
//   0: one cell. 1: every cell of the range (the triangle is connected and lies within one
//   cell on the other two axes, so it crosses them all). 2: the triangle lies within the layer
//   of the third axis, so the 2D test in the plane of the two spanning axes is exact. 3: the
//   full SAT = plane test + the 2D tests of the three coordinate planes (the 9 edge x axis
//   crosses of Akenine-Moller's test are exactly those 2D edge normals).
template <class Emit>
inline void BinTriangleCells(const BinGeometry& g, const float v[3][3], const int c0[3],
                             const int c1[3], const bool span[3], int spans, BinScratch* scratch,
                             Emit&& emit) {
  if (spans <= 1) {
    for (int z = c0[2]; z <= c1[2]; ++z) {
      for (int y = c0[1]; y <= c1[1]; ++y) {
        for (int x = c0[0]; x <= c1[0]; ++x) emit(x, y, z);
      }
    }
    return;
  }
  double dv[3][3];
  for (int k = 0; k < 3; ++k) {
    for (int a = 0; a < 3; ++a) dv[k][a] = double(v[k][a]);
  }
  if (spans == 2) {
    const int k = !span[0] ? 0 : (!span[1] ? 1 : 2);  // the single-cell axis
    const int i = k == 0 ? 1 : 0, j = k == 2 ? 1 : 2;
    const binning::Edges2D edges(dv, g, i, j);
    const int ni = c1[i] - c0[i] + 1;
    const int nj = c1[j] - c0[j] + 1;
    std::vector<uint8_t>& table = scratch->table[0];
    if (table.size() < size_t(ni) * size_t(nj)) table.resize(size_t(ni) * size_t(nj));
    edges.Table(c0[i], ni, c0[j], nj, table.data());
    int c[3];
    c[k] = c0[k];
    const uint8_t* row = table.data();
    for (c[j] = c0[j]; c[j] <= c1[j]; ++c[j], row += ni) {
      for (int m = 0; m < ni; ++m) {
        if (!row[m]) continue;
        c[i] = c0[i] + m;
        emit(c[0], c[1], c[2]);
      }
    }
    return;
  }
  // spans == 3: tables of the three 2D projections, then the plane test per cell
  const int n[3] = {c1[0] - c0[0] + 1, c1[1] - c0[1] + 1, c1[2] - c0[2] + 1};
  static constexpr int kPair[3][2] = {{0, 1}, {0, 2}, {1, 2}};  // xy, xz, yz
  if (scratch->terms.size() < size_t(n[0])) scratch->terms.resize(size_t(n[0]));
  uint8_t* table[3];
  for (int p = 0; p < 3; ++p) {
    const int i = kPair[p][0], j = kPair[p][1];
    std::vector<uint8_t>& t = scratch->table[p];
    if (t.size() < size_t(n[i]) * size_t(n[j])) t.resize(size_t(n[i]) * size_t(n[j]));
    table[p] = t.data();
    const binning::Edges2D edges(dv, g, i, j);
    edges.Table(c0[i], n[i], c0[j], n[j], table[p]);
  }
  const binning::Plane3D plane(dv, g);
  double* x_terms = scratch->terms.data();
  for (int x = 0; x < n[0]; ++x) x_terms[x] = plane.XTerm(c0[0] + x);
  for (int z = 0; z < n[2]; ++z) {
    const double z_term = plane.Term(2, c0[2] + z);
    for (int y = 0; y < n[1]; ++y) {
      if (!table[2][size_t(z) * n[1] + y]) continue;
      const double y_term = plane.Term(1, c0[1] + y);
      const uint8_t* xy = table[0] + size_t(y) * n[0];
      const uint8_t* xz = table[1] + size_t(z) * n[0];
      for (int x = 0; x < n[0]; ++x) {
        if (xy[x] && xz[x] && plane.Inside((x_terms[x] + y_term) + z_term)) {
          emit(c0[0] + x, c0[1] + y, c0[2] + z);
        }
      }
    }
  }
}

// TriangleCellRange + BinTriangleCells.
template <class Emit>
inline void BinTriangle(const BinGeometry& g, const float v[3][3], BinScratch* scratch,
                        Emit&& emit) {
  int c0[3], c1[3];
  bool span[3];
  const int spans = TriangleCellRange(g, v, c0, c1, span);
  if (spans >= 0) BinTriangleCells(g, v, c0, c1, span, spans, scratch, emit);
}

// out's triangles [0, n) = the listed triangles ids[0, n) of src, in out's SoA arrays only (out's
// arrays grown as needed, their degenerate flags 0: lists hold no degenerate triangle), for
// BinListed. Each id's floats come from its interleaved record (src.verts: one cache line or
// two, where the nine SoA arrays cost nine).
inline void GatherListed(const TriangleSoA& src, const uint32_t* ids, size_t n, TriangleSoA* out) {
  // (the gather overwrites [0, n): a grown array need not keep earlier triangles)
  for (auto& vertex : out->p) {
    for (auto& axis : vertex) axis.ReserveForOverwrite(n);
  }
  if (out->size < n) {
    out->degenerate.ReserveForOverwrite(n);
    std::fill(out->degenerate.data(), out->degenerate.data() + n, uint8_t{0});
  }
  out->size = n;
  float* dst[9];
  for (int c = 0; c < 9; ++c) dst[c] = out->p[c / 3][c % 3].data();
  for (size_t t = 0; t < n; ++t) {
    const float* v = src.Vertices(ids[t]);
    for (int c = 0; c < 9; ++c) dst[c][t] = v[c];
  }
}

// Scratch of BinListed, reused across calls.
struct ListedBinScratch {
  RangeBlock block;
  uint16_t quad_js[kRangeBlock];  // the block's 2 x 2-cell triangles and their cells
  uint8_t quad_masks[kRangeBlock];
  BinScratch scratch;
};

// The cells BinTriangle gives each of the triangles [0, n) of `tris` (a cell's list, gathered
// by GatherListed: finite, none degenerate), bit for bit, a block of kRangeBlock triangles at a
// time: their cell ranges a vector at a time (SimdTriangleCellRanges), the 2 x 2-cell ones
// edge-tested a vector at a time (SimdQuadCellMasks), one cell or a line of cells emitted
// whole, the rest by BinTriangleCells. geo is a kRes x kRes x kRes grid. Per block,
// reserve(most) first (`most`: the most cells the block emits, its boxes' sum), then
// emit(j, cell) for triangle j and cell index x + kRes (y + kRes z), triangles in order; then
// a false from done_block() stops the binning (returns false). The sub-grids' refinement
// (kernels/two_level.cc, kRes 8) and the irregular grid's octree (kernels/irregular.cc,
// kRes 2) bin their lists with it.
template <int kRes, class Reserve, class Emit, class DoneBlock>
bool BinListed(const TriangleSoA& tris, const BinGeometry& geo, size_t n, ListedBinScratch* s,
               const Reserve& reserve, const Emit& emit, const DoneBlock& done_block) {
  static constexpr uint32_t stride[3] = {1, kRes, kRes * kRes};
  HWY_DASSERT(geo.res[0] == kRes && geo.res[1] == kRes && geo.res[2] == kRes);
  RangeBlock& block = s->block;
  for (size_t first = 0; first < n; first += kRangeBlock) {
    const size_t count = std::min(kRangeBlock, n - first);
    SimdTriangleCellRanges(tris, geo, first, count, &block, /*bin_flags=*/true);
    size_t quads = 0;
    for (size_t j = 0; j < count; ++j) {
      if (block.flags[j] & kRangeQuad) s->quad_js[quads++] = uint16_t(j);
    }
    if (quads > 0) SimdQuadCellMasks(tris, geo, first, block, s->quad_js, quads, s->quad_masks);
    reserve(block.box_sum);
    size_t next_quad = 0;
    for (size_t j = 0; j < count; ++j) {
      const int32_t flags = block.flags[j];
      if (flags & kRangeOutside) continue;
      const size_t t = first + j;
      // block.cell[j]: the cell index of the box's low corner
      if (flags & kRangeLine) {
        // one cell or a line along one axis: every box cell, in order (BinTriangleCells)
        const int spans_mask = flags & 7;
        const uint32_t step = stride[spans_mask == 4 ? 2 : spans_mask >> 1];
        uint32_t c = block.cell[j];
        for (uint32_t k = 0; k < block.box[j]; ++k, c += step) emit(t, c);
        continue;
      }
      if (flags & kRangeQuad) {
        // 2 x 2 cells: those of the SIMD edge tests, axis i fastest (BinTriangleCells' order)
        const int spans_mask = flags & 7;
        const uint32_t si = stride[spans_mask == 6 ? 1 : 0];
        const uint32_t sj = stride[spans_mask == 3 ? 1 : 2];
        const uint32_t offset[4] = {0, si, sj, si + sj};
        for (uint32_t m = s->quad_masks[next_quad++]; m != 0; m &= m - 1) {
          emit(t, block.cell[j] + offset[std::countr_zero(m)]);
        }
        continue;
      }
      const int c0[3] = {block.c0[0][j], block.c0[1][j], block.c0[2][j]};
      const int c1[3] = {block.c1[0][j], block.c1[1][j], block.c1[2][j]};
      const bool span[3] = {(flags & 1) != 0, (flags & 2) != 0, (flags & 4) != 0};
      const int spans = int(span[0]) + int(span[1]) + int(span[2]);
      const float v[3][3] = {{tris.p[0][0][t], tris.p[0][1][t], tris.p[0][2][t]},
                             {tris.p[1][0][t], tris.p[1][1][t], tris.p[1][2][t]},
                             {tris.p[2][0][t], tris.p[2][1][t], tris.p[2][2][t]}};
      BinTriangleCells(geo, v, c0, c1, span, spans, &s->scratch, [&](int x, int y, int z) {
        emit(t, uint32_t(x + kRes * (y + kRes * z)));
      });
    }
    if (!done_block()) return false;
  }
  return true;
}

}  // namespace rs
