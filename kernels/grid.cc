// Uniform grid build: bounds, resolution heuristic, conservative triangle binning
// (kernels/grid_binning.h: float cell ranges, exact 2D/3D separating-axis tests only where the
// box spans several cells), counts taken while binning, CSR lists filled in one more pass; the
// resolution coarsened to the reference budget and the coordinates' precision (grid.h).
#include "kernels/grid.h"

#include <algorithm>
#include <bit>
#include <cfloat>
#include <cmath>
#include <cstring>
#include <string>
#include <vector>

#include <unistd.h>  // sysconf: physical memory

#include "kernels/build_threads.h"
#include "kernels/grid_binning.h"

namespace rs {
namespace {

// double -> float through a volatile: GCC 12.2's SLP vectorizer can drop the rounding in
// (double)(float)x at -O2/-O3 (TOOLCHAIN.md), which changed the binning between -O0 and -O3.
// Every float the grid stores and later reads back as double goes through here.
inline float RoundToFloat(double x) {
  volatile float f = static_cast<float>(x);
  return f;
}

// Grows the reference array to hold at least `used + more` entries (doubling, but not past
// `limit` unless `used + more` needs it), keeping `used`.
void Grow(hwy::AlignedFreeUniquePtr<uint32_t[]>* refs, size_t used, size_t* capacity,
          size_t more, size_t limit) {
  const size_t grown = std::max(std::min(2 * *capacity, limit), used + more);
  auto bigger = AllocateBuildArray<uint32_t>(grown, "cell references");
  std::copy(refs->get(), refs->get() + used, bigger.get());
  *refs = std::move(bigger);
  *capacity = grown;
}

// Physical memory in bytes (0 if unknown): a grid whose cell arrays alone exceed it is refused
// up front instead of being killed by the system halfway through the build.
double PhysicalMemoryBytes() {
#if defined(_SC_PHYS_PAGES) && defined(_SC_PAGE_SIZE)
  const long pages = sysconf(_SC_PHYS_PAGES), page = sysconf(_SC_PAGE_SIZE);
  if (pages > 0 && page > 0) return double(pages) * double(page);
#endif
  return 0.0;
}

// Bytes per cell of the arrays sized by the cell count: the grid's offsets (4) and occupancy
// bits, the traversal's bits and empty-space rings (dda_simd.h: 1), the second level's leaf
// offsets (4), rounded up.
constexpr double kBytesPerCell = 10.0;

// The geometry of a grid of (at most) res cells per axis over `bounds`: axes whose cells would be
// shorter than kMinCellMargins x the margin's ulp term get fewer cells (grid.h); throws
// rs::Error if the cells cannot be held. Precondition: bounds.num_valid > 0, res >= 1.
void SetResolution(const GridBounds& bounds, const int res[3], Grid* grid) {
  *grid = Grid();
  double extent[3], max_abs = 0.0;
  for (int a = 0; a < 3; ++a) {
    grid->lo[a] = bounds.lo[a];
    grid->hi[a] = bounds.hi[a];
    extent[a] = double(bounds.hi[a]) - double(bounds.lo[a]);
    max_abs = std::max({max_abs, std::fabs(double(bounds.lo[a])), std::fabs(double(bounds.hi[a]))});
  }
  const double ulp_margin = 4.0 * FLT_EPSILON * max_abs;
  const double min_cell = kMinCellMargins * ulp_margin;
  for (int a = 0; a < 3; ++a) {
    grid->res[a] = res[a];
    if (res[a] > 1 && extent[a] / res[a] < min_cell) {
      grid->res[a] = std::max(1, int(std::floor(extent[a] / min_cell)));
    }
  }
  const double cells = double(grid->res[0]) * double(grid->res[1]) * double(grid->res[2]);
  const double memory = PhysicalMemoryBytes();
  if (cells > double(kMaxGridCells) || (memory > 0.0 && cells * kBytesPerCell > memory)) {
    throw Error("grid build: a " + std::to_string(grid->res[0]) + "x" +
                std::to_string(grid->res[1]) + "x" + std::to_string(grid->res[2]) + " grid (" +
                std::to_string(size_t(cells)) + " cells, about " +
                BytesText(cells * kBytesPerCell) + " of cell arrays) " +
                (cells > double(kMaxGridCells)
                     ? std::string("exceeds the limit of 2^32 - 2 cells")
                     : "does not fit in the physical memory (" + BytesText(memory) + ")") +
                "; lower BuildOptions::lambda or max_resolution");
  }
  for (int a = 0; a < 3; ++a) {
    grid->cell_size[a] = RoundToFloat(extent[a] / grid->res[a]);
    grid->inv_cell_size[a] = RoundToFloat(grid->res[a] / extent[a]);
    grid->margin[a] = 1e-3 * double(grid->cell_size[a]) + ulp_margin;
  }
  grid->num_cells = size_t(cells);
}

// SetGridGeometry for a cell budget of lambda * num_valid (lambda in double: BuildGrid's
// coarsening steps go below float's useful range for large scenes).
void SetGeometry(const GridBounds& bounds, double lambda, int max_resolution, Grid* grid) {
  if (bounds.num_valid == 0) {
    *grid = Grid();  // empty grid: never hit
    return;
  }
  double extent[3];
  for (int a = 0; a < 3; ++a) extent[a] = double(bounds.hi[a]) - double(bounds.lo[a]);
  int res[3];
  ComputeGridResolution(extent, bounds.num_valid, lambda, max_resolution, res);
  SetResolution(bounds, res, grid);
}

// Pass 1 of BuildGrid: the cells of each triangle appended to one flat array (ref_begin[i] ..
// [i+1]), counted per cell on the way (begin[c] = the count of cell c). Returns false, leaving
// the arrays unusable, as soon as more than `limit` references are listed; *num_refs then holds
// a count > limit.
// Triangles [first_tri, last_tri) only; ref_begin is indexed from first_tri (ref_begin[0] is
// triangle first_tri's, ref_begin[last_tri - first_tri] the end).
bool BinReferences(const TriangleSoA& tris, const Grid& grid, const BinGeometry& geo,
                   size_t first_tri, size_t last_tri, size_t limit, uint32_t* begin,
                   hwy::AlignedFreeUniquePtr<uint32_t[]>* ref_cells, size_t* capacity,
                   uint32_t* ref_begin, size_t* num_refs_out) {
  const size_t n = last_tri;
  size_t num_refs = 0;
  BinScratch scratch;
  const size_t stride_y = size_t(grid.res[0]), stride_z = stride_y * size_t(grid.res[1]);
  const size_t strides[3] = {1, stride_y, stride_z};
  const float* p[3][3];
  for (int k = 0; k < 3; ++k) {
    for (int a = 0; a < 3; ++a) p[k][a] = tris.p[k][a].data();
  }
  RangeBlock block;
  uint16_t quad_js[kRangeBlock];
  uint8_t quad_masks[kRangeBlock];
  for (size_t first = first_tri; first < n; first += kRangeBlock) {
    const size_t count = std::min(kRangeBlock, n - first);
    SimdTriangleCellRanges(tris, geo, first, count, &block, /*bin_flags=*/true);
    // room for the block's one-cell and line triangles (all their box cells are emitted) at
    // once; each triangle tested by BinTriangleCells makes room for its box plus that reserve
    // below (the line triangles after it in the block still need theirs)
    // (flagged triangles have box 0); the 2 x 2-cell triangles are edge-tested here, a vector
    // of triangles at a time
    size_t lines = block.line_sum, quads = 0;
    for (size_t j = 0; j < count; ++j) {
      if (block.flags[j] & kRangeQuad) quad_js[quads++] = uint16_t(j);
    }
    if (quads > 0) SimdQuadCellMasks(tris, geo, first, block, quad_js, quads, quad_masks);
    size_t next_quad = 0;
    if (num_refs + lines > limit) {
      *num_refs_out = num_refs + lines;
      return false;
    }
    if (num_refs + lines > *capacity) Grow(ref_cells, num_refs, capacity, lines, limit);
    uint32_t* cells_out = ref_cells->get();
    // room for a triangle of at most `room` cells and the block's line triangles after it;
    // past the budget, exact() counts its cells; false (*num_refs_out set) if they pass it
    const auto make_room = [&](size_t room, const auto& exact) {
      if (num_refs + room + lines > limit) {
        room = exact();
        if (num_refs + room + lines > limit) {
          *num_refs_out = num_refs + room + lines;
          return false;
        }
      }
      if (num_refs + room + lines > *capacity) {
        Grow(ref_cells, num_refs, capacity, room + lines, limit);
        cells_out = ref_cells->get();
      }
      return true;
    };
    for (size_t j = 0; j < count; ++j) {
      const uint32_t i = uint32_t(first + j);
      ref_begin[i - first_tri] = uint32_t(num_refs);
      const int32_t flags = block.flags[j];
      // degenerate, or outside (cannot happen: the bounds contain every triangle)
      if (flags & (kRangeDegenerate | kRangeOutside)) continue;
      size_t c = block.cell[j];  // the corner's cell index (SIMD pass)
      const int spans_mask = flags & 7;
      if (flags & kRangeLine) {
        // one cell (the common case at low lambda), or a line of cells along one axis: the
        // triangle crosses them all (BinTriangleCells)
        const int a = spans_mask == 4 ? 2 : spans_mask >> 1;  // 0 -> axis 0, a 1-cell range
        const size_t stride = strides[a];
        const size_t cells = size_t(block.box[j]);  // the box is that line
        for (size_t k = 0; k < cells; ++k, c += stride) {
          cells_out[num_refs++] = uint32_t(c);
          ++begin[c];
        }
        lines -= cells;
        continue;
      }
      if (flags & kRangeQuad) {
        // a 2 x 2-cell triangle: its cells from the SIMD edge tests, in BinTriangleCells' order
        // (axis i fastest), with the same room and budget checks as below
        const uint32_t mask = quad_masks[next_quad++];
        if (!make_room(4, [&] { return size_t(std::popcount(mask)); })) return false;
        const size_t si = strides[spans_mask == 6 ? 1 : 0], sj = strides[spans_mask == 3 ? 1 : 2];
        const size_t offset[4] = {0, si, sj, si + sj};
        for (uint32_t m = mask; m != 0; m &= m - 1) {
          const size_t cell = c + offset[std::countr_zero(m)];
          cells_out[num_refs++] = uint32_t(cell);
          ++begin[cell];
        }
        continue;
      }
      const int c0[3] = {block.c0[0][j], block.c0[1][j], block.c0[2][j]};
      const int c1[3] = {block.c1[0][j], block.c1[1][j], block.c1[2][j]};
      const bool span[3] = {(flags & 1) != 0, (flags & 2) != 0, (flags & 4) != 0};
      const int spans = int(span[0]) + int(span[1]) + int(span[2]);
      const float v[3][3] = {{p[0][0][i], p[0][1][i], p[0][2][i]},
                             {p[1][0][i], p[1][1][i], p[1][2][i]},
                             {p[2][0][i], p[2][1][i], p[2][2][i]}};
      // its box, and what the block's line triangles after it still need; a box larger than
      // the budget left (a huge or long thin triangle) is counted first, so the array never
      // grows far past the budget
      if (!make_room(size_t(block.box[j]), [&] {
            size_t exact = 0;
            BinTriangleCells(geo, v, c0, c1, span, spans, &scratch,
                             [&](int, int, int) { ++exact; });
            return exact;
          })) {
        return false;
      }
      BinTriangleCells(geo, v, c0, c1, span, spans, &scratch, [&](int x, int y, int z) {
        const size_t cell = size_t(x) + stride_y * size_t(y) + stride_z * size_t(z);
        cells_out[num_refs++] = uint32_t(cell);
        ++begin[cell];
      });
    }
  }
  ref_begin[n - first_tri] = uint32_t(num_refs);
  *num_refs_out = num_refs;
  return true;
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

void ChooseFrameShift(const GridBounds& bounds, float shift[3]) {
  for (int a = 0; a < 3; ++a) {
    shift[a] = 0.0f;
    if (bounds.num_valid == 0) continue;
    const double lo = bounds.lo[a], hi = bounds.hi[a];
    const double nearest = lo > 0.0 ? lo : (hi < 0.0 ? -hi : 0.0);  // 0: the bounds hold 0
    if (nearest > 0.0 && hi - lo <= nearest) shift[a] = RoundToFloat(0.5 * (lo + hi));
  }
}

void SetGridGeometry(const GridBounds& bounds, float lambda, int max_resolution, Grid* grid) {
  SetGeometry(bounds, double(lambda), max_resolution, grid);
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

namespace {

// mark[0, len) = 1 for 1 <= len <= 64 (a box row of MarkGridBoxes): overlapping word stores
// instead of a memset call per row (rows are short: boxes of at most 64 cells).
// Out of line: inlined, it changed the code of the small-box loop around it (+2 % there).
[[gnu::noinline]] void MarkRow(uint8_t* mark, size_t len) {
  constexpr uint64_t kOnes8 = 0x0101010101010101ull;
  constexpr uint32_t kOnes4 = 0x01010101u;
  if (len >= 8) {
    for (size_t k = 0; k + 8 < len; k += 8) std::memcpy(mark + k, &kOnes8, 8);
    std::memcpy(mark + len - 8, &kOnes8, 8);
  } else if (len >= 4) {
    std::memcpy(mark, &kOnes4, 4);
    std::memcpy(mark + len - 4, &kOnes4, 4);
  } else {
    mark[0] = mark[len >> 1] = mark[len - 1] = 1;  // len 1, 2 or 3
  }
}

// CountGridBoxes over triangles [first, last): marks the cells of small boxes in `mark` (one
// byte per cell, plus the spare byte at num_cells), adds big boxes' corners to *diff (allocated
// at the first big box) and returns the sum of the box cell counts.
size_t MarkGridBoxes(const TriangleSoA& tris, const Grid& geometry, const BinGeometry& geo,
                     size_t first_tri, size_t last_tri, uint8_t* mark, std::vector<int32_t>* diff) {
  // one byte per cell: boxes of at most 2 cells per axis (nearly all at the lambdas tried) mark
  // their corners with 8 unconditional stores (repeats on 1-cell axes), no loop to mispredict;
  // flagged triangles (box 0, range [0, 0]) mark the spare byte at num_cells instead. Boxes of
  // more than kBigBox cells go into a 3D difference array instead (8 corner updates, one prefix
  // sum per axis at the end), so the count stays O(triangles + cells) when many triangles span
  // much of the grid (identical or overlapping triangles: the fill was O(triangles x cells)).
  constexpr size_t kBigBox = 64;
  const size_t num_cells = geometry.num_cells;
  const int res[3] = {geometry.res[0], geometry.res[1], geometry.res[2]};
  const size_t stride_y = size_t(res[0]);
  const size_t stride_z = stride_y * size_t(res[1]);
  size_t refs = 0;
  RangeBlock block;
  for (size_t first = first_tri; first < last_tri; first += kRangeBlock) {
    const size_t count = std::min(kRangeBlock, last_tri - first);
    SimdTriangleCellRanges(tris, geo, first, count, &block);
    refs += block.box_sum;
    for (size_t j = 0; j < count; ++j) {
      // the corner's index (num_cells for flagged triangles) and the index steps of the box,
      // from the SIMD pass
      const size_t cell = block.cell[j];
      if (block.flags[j] & kRangeSmall) {
        const size_t dx = block.step[0][j], dy = block.step[1][j], dz = block.step[2][j];
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
      const int x0 = block.c0[0][j], y0 = block.c0[1][j], z0 = block.c0[2][j];
      const int ex = block.c1[0][j] - x0, ey = block.c1[1][j] - y0, ez = block.c1[2][j] - z0;
      if (size_t(block.box[j]) > kBigBox) {
        if (diff->empty()) diff->assign(num_cells, 0);
        // +1 at the low corner, alternating signs at the corners one past the high end (those
        // outside the grid are dropped: the prefix sums never reach them)
        const int lo[3] = {x0, y0, z0};
        const int hi[3] = {x0 + ex + 1, y0 + ey + 1, z0 + ez + 1};
        for (int corner = 0; corner < 8; ++corner) {
          int q[3];
          int sign = 1;
          bool inside = true;
          for (int a = 0; a < 3; ++a) {
            const bool high = (corner >> a) & 1;
            q[a] = high ? hi[a] : lo[a];
            sign = high ? -sign : sign;
            inside &= q[a] < res[a];
          }
          if (inside) {
            (*diff)[size_t(q[0]) + stride_y * size_t(q[1]) + stride_z * size_t(q[2])] += sign;
          }
        }
        continue;
      }
      for (int z = 0; z <= ez; ++z) {
        for (int y = 0; y <= ey; ++y) {
          MarkRow(mark + cell + stride_y * size_t(y) + stride_z * size_t(z), size_t(ex) + 1);
        }
      }
    }
  }
  return refs;
}

}  // namespace

GridBoxCounts CountGridBoxes(const TriangleSoA& tris, const Grid& geometry, int threads) {
  GridBoxCounts c;
  if (geometry.num_cells == 0) return c;
  c.cells = geometry.num_cells;
  const BinGeometry geo = GridBinGeometry(geometry);
  const size_t num_cells = geometry.num_cells;
  const int res[3] = {geometry.res[0], geometry.res[1], geometry.res[2]};
  const size_t stride_y = size_t(res[0]);
  const size_t stride_z = stride_y * size_t(res[1]);
  // parts of whole range blocks; each part marks its own bytes and difference array, merged
  // below (an OR and a sum: the counts do not depend on the split)
  const int parts = int(std::max<size_t>(
      1, std::min<size_t>(size_t(BuildThreadCount(threads)), tris.size / (2 * kRangeBlock))));
  std::vector<std::vector<uint8_t>> marks(size_t(std::max(parts, 1)));
  std::vector<std::vector<int32_t>> diffs(marks.size());
  std::vector<size_t> refs(marks.size(), 0);
  RunParts(parts, [&](int t) {
    marks[size_t(t)].assign(num_cells + 1, 0);
    refs[size_t(t)] = MarkGridBoxes(tris, geometry, geo, PartBegin(tris.size, parts, t, kRangeBlock),
                                    PartBegin(tris.size, parts, t + 1, kRangeBlock),
                                    marks[size_t(t)].data(), &diffs[size_t(t)]);
  });
  uint8_t* mark = marks[0].data();
  std::vector<int32_t>& diff = diffs[0];
  for (size_t t = 1; t < marks.size(); ++t) {
    if (!diffs[t].empty() && diff.empty()) diff.assign(num_cells, 0);
  }
  RunParts(parts, [&](int k) {  // the merge, by ranges of cells
    const size_t c0 = PartBegin(num_cells, parts, k, 64), c1 = PartBegin(num_cells, parts, k + 1, 64);
    for (size_t t = 1; t < marks.size(); ++t) {
      const uint8_t* m = marks[t].data();
      for (size_t c = c0; c < c1; ++c) mark[c] |= m[c];
      if (!diffs[t].empty()) {
        const int32_t* dt = diffs[t].data();
        for (size_t c = c0; c < c1; ++c) diff[c] += dt[c];
      }
    }
  });
  for (const size_t r : refs) c.refs += r;
  if (!diff.empty()) {
    // prefix sums along x, y, z turn the corner updates into the number of big boxes per cell
    int32_t* d = diff.data();
    for (size_t row = 0; row < num_cells; row += stride_y) {
      for (int x = 1; x < res[0]; ++x) d[row + x] += d[row + x - 1];
    }
    for (int z = 0; z < res[2]; ++z) {
      for (int y = 1; y < res[1]; ++y) {
        int32_t* row = d + stride_z * size_t(z) + stride_y * size_t(y);
        const int32_t* below = row - stride_y;
        for (int x = 0; x < res[0]; ++x) row[x] += below[x];
      }
    }
    for (size_t k = stride_z; k < num_cells; ++k) d[k] += d[k - stride_z];
    for (size_t k = 0; k < num_cells; ++k) mark[k] |= uint8_t(d[k] != 0);
  }
  std::vector<size_t> occupied(size_t(parts), 0);
  RunParts(parts, [&](int k) {
    const size_t c0 = PartBegin(num_cells, parts, k, 64), c1 = PartBegin(num_cells, parts, k + 1, 64);
    size_t n = 0;
    for (size_t c = c0; c < c1; ++c) n += mark[c];
    occupied[size_t(k)] = n;
  });
  for (const size_t n : occupied) c.occupied += n;
  return c;
}

size_t EstimateGridRefs(const TriangleSoA& tris, const Grid& geometry, size_t limit) {
  if (geometry.num_cells == 0) return 0;
  const BinGeometry geo = GridBinGeometry(geometry);
  const size_t n = tris.size;
  std::vector<uint32_t> boxes(n);
  size_t total = 0;
  RangeBlock block;
  for (size_t first = 0; first < n; first += kRangeBlock) {
    const size_t count = std::min(kRangeBlock, n - first);
    SimdTriangleCellRanges(tris, geo, first, count, &block);
    for (size_t j = 0; j < count; ++j) {
      boxes[first + j] = block.box[j];
      total += size_t(block.box[j]);
    }
  }
  if (total <= limit) return total;
  // systematic sample with probability proportional to the box: sample k is the triangle whose
  // box holds position (k + 1/2) total / kSamples of the running box sum; the estimate is
  // total x the mean of exact / box over the samples
  constexpr size_t kSamples = 256;
  const double step = double(total) / double(kSamples);
  BinScratch scratch;
  double ratio_sum = 0.0, ratio = 0.0, before = 0.0;  // box sum of triangles before `i`
  size_t i = 0, measured = n;
  for (size_t k = 0; k < kSamples; ++k) {
    const double at = (double(k) + 0.5) * step;
    while (i + 1 < n && before + double(boxes[i]) <= at) before += double(boxes[i++]);
    if (i != measured) {
      measured = i;
      float v[3][3];
      int c0[3], c1[3];
      bool span[3];
      const int spans = TriangleCellRange(geo, tris, i, v, c0, c1, span);
      size_t exact = 0, box = 1;
      if (spans >= 0) {
        BinTriangleCells(geo, v, c0, c1, span, spans, &scratch, [&](int, int, int) { ++exact; });
        for (int a = 0; a < 3; ++a) box *= size_t(c1[a] - c0[a] + 1);
      }
      ratio = double(exact) / double(box);
    }
    ratio_sum += ratio;
  }
  return size_t(std::ceil(double(total) * ratio_sum / double(kSamples)));
}

namespace {

// Pass 1 (BinReferences), then the CSR lists and occupancy bits. False if the references
// passed `limit` (*num_refs > limit then; the grid's arrays are not complete).
bool BuildLists(const TriangleSoA& tris, size_t limit, Grid* grid, size_t* num_refs_out) {
  const size_t n = tris.size;
  const size_t num_cells = grid->num_cells;
  const BinGeometry geo = GridBinGeometry(*grid);
  // cell_begin[c] holds the count of cell c during pass 1. Temporary arrays are left
  // uninitialised: every element read is written first.
  grid->cell_begin = AllocateBuildArray<uint32_t>(num_cells + 1, "cell offsets");
  uint32_t* begin = grid->cell_begin.get();
  std::fill(begin, begin + num_cells + 1, 0u);
  size_t capacity = std::min(n * 3 + 64, limit + 1);
  auto ref_cells = AllocateBuildArray<uint32_t>(capacity, "cell references");
  auto ref_begin = AllocateBuildArray<uint32_t>(n + 1, "per-triangle reference offsets");
  size_t num_refs = 0;
  const bool fits = BinReferences(tris, *grid, geo, 0, n, limit, begin, &ref_cells, &capacity,
                                  ref_begin.get(), &num_refs);
  *num_refs_out = num_refs;
  if (!fits) return false;

  // Inclusive prefix sum -> end of each cell (occupancy bits and statistics on the way), then
  // fill backwards with pre-decrement so cell_begin[c] ends at the start of cell c and the ids
  // in each cell come out ascending.
  const size_t words = (num_cells + 63) / 64;
  grid->occupancy = AllocateBuildArray<uint64_t>(words, "occupancy bits");
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
  grid->tri_ids = AllocateBuildArray<uint32_t>(num_refs, "cell triangle ids");
  uint32_t* ids = grid->tri_ids.get();
  const uint32_t* cells_in = ref_cells.get();
  for (size_t i = n; i-- > 0;) {
    for (size_t r = ref_begin[i + 1]; r-- > ref_begin[i];) ids[--begin[cells_in[r]]] = uint32_t(i);
  }
  grid->num_refs = num_refs;
  grid->occupied_cells = occupied;
  grid->max_per_cell = max_per_cell;
  return true;
}

// BuildLists on `parts` threads, the same grid bit for bit: each part bins a contiguous range
// of triangles (whole range blocks) into its own per-cell counts and reference array; the cell
// offsets are the sums of the parts' counts, and part t fills its ids into cell c after those
// of parts 0 .. t-1, so every cell lists its ids ascending exactly as the serial fill does. Over
// the budget, the serial BuildLists runs again for its exact *num_refs (the coarsening in
// BuildGrid depends on it).
bool BuildListsThreaded(const TriangleSoA& tris, size_t limit, int parts, Grid* grid,
                        size_t* num_refs_out) {
  const size_t n = tris.size;
  const size_t num_cells = grid->num_cells;
  const BinGeometry geo = GridBinGeometry(*grid);
  struct Part {
    size_t first = 0, last = 0;
    hwy::AlignedFreeUniquePtr<uint32_t[]> counts;  // per cell, then the fill cursors
    hwy::AlignedFreeUniquePtr<uint32_t[]> cells;   // the part's references (cell ids)
    hwy::AlignedFreeUniquePtr<uint32_t[]> ref_begin;
    size_t capacity = 0;
    size_t refs = 0;
    bool fits = false;
  };
  std::vector<Part> part(static_cast<size_t>(parts));
  RunParts(parts, [&](int t) {
    Part& p = part[size_t(t)];
    p.first = PartBegin(n, parts, t, kRangeBlock);
    p.last = PartBegin(n, parts, t + 1, kRangeBlock);
    const size_t count = p.last - p.first;
    p.counts = AllocateBuildArray<uint32_t>(num_cells + 1, "cell offsets");
    std::fill(p.counts.get(), p.counts.get() + num_cells + 1, 0u);
    p.capacity = std::min(count * 3 + 64, limit + 1);
    p.cells = AllocateBuildArray<uint32_t>(p.capacity, "cell references");
    p.ref_begin = AllocateBuildArray<uint32_t>(count + 1, "per-triangle reference offsets");
    p.fits = BinReferences(tris, *grid, geo, p.first, p.last, limit, p.counts.get(), &p.cells,
                           &p.capacity, p.ref_begin.get(), &p.refs);
  });
  size_t num_refs = 0;
  bool fits = true;
  for (const Part& p : part) {
    num_refs += p.refs;
    fits &= p.fits;
  }
  if (!fits || num_refs > limit) {
    part.clear();
    return BuildLists(tris, limit, grid, num_refs_out);
  }
  *num_refs_out = num_refs;

  // cell offsets, occupancy bits and statistics over chunks of cells (whole 64-bit words): the
  // chunks' totals first, then each chunk from its start
  grid->cell_begin = AllocateBuildArray<uint32_t>(num_cells + 1, "cell offsets");
  const size_t words = (num_cells + 63) / 64;
  grid->occupancy = AllocateBuildArray<uint64_t>(words, "occupancy bits");
  uint32_t* begin = grid->cell_begin.get();
  uint64_t* occ = grid->occupancy.get();
  std::vector<uint32_t> chunk_sum(size_t(parts) + 1, 0);
  std::vector<size_t> chunk_max(size_t(parts), 0), chunk_occupied(size_t(parts), 0);
  RunParts(parts, [&](int k) {
    const size_t c0 = PartBegin(num_cells, parts, k, 64), c1 = PartBegin(num_cells, parts, k + 1, 64);
    uint32_t sum = 0;
    for (const Part& p : part) {
      const uint32_t* cnt = p.counts.get();
      for (size_t c = c0; c < c1; ++c) sum += cnt[c];
    }
    chunk_sum[size_t(k) + 1] = sum;
  });
  for (int k = 0; k < parts; ++k) chunk_sum[size_t(k) + 1] += chunk_sum[size_t(k)];
  RunParts(parts, [&](int k) {
    const size_t c0 = PartBegin(num_cells, parts, k, 64), c1 = PartBegin(num_cells, parts, k + 1, 64);
    uint32_t at = chunk_sum[size_t(k)];
    size_t max_per_cell = 0, occupied = 0;
    for (size_t w = c0 / 64; w < (c1 + 63) / 64; ++w) {
      const size_t end = std::min(c1, 64 * w + 64);
      uint64_t bits = 0;
      for (size_t c = 64 * w; c < end; ++c) {
        begin[c] = at;
        for (Part& p : part) {
          at += p.counts[c];
          p.counts[c] = at;  // the end of part p's ids in cell c: its fill cursor
        }
        const uint32_t count = at - begin[c];
        max_per_cell = std::max<size_t>(max_per_cell, count);
        bits |= uint64_t{count != 0} << (c & 63);
      }
      occ[w] = bits;
      occupied += size_t(std::popcount(bits));
    }
    chunk_max[size_t(k)] = max_per_cell;
    chunk_occupied[size_t(k)] = occupied;
  });
  begin[num_cells] = uint32_t(num_refs);
  grid->tri_ids = AllocateBuildArray<uint32_t>(num_refs, "cell triangle ids");
  uint32_t* ids = grid->tri_ids.get();
  RunParts(parts, [&](int t) {
    Part& p = part[size_t(t)];
    uint32_t* cursor = p.counts.get();
    const uint32_t* cells_in = p.cells.get();
    const uint32_t* rb = p.ref_begin.get();
    for (size_t j = p.last - p.first; j-- > 0;) {
      const uint32_t i = uint32_t(p.first + j);
      for (size_t r = rb[j + 1]; r-- > rb[j];) ids[--cursor[cells_in[r]]] = i;
    }
  });
  grid->num_refs = num_refs;
  grid->occupied_cells = 0;
  grid->max_per_cell = 0;
  for (int k = 0; k < parts; ++k) {
    grid->occupied_cells += chunk_occupied[size_t(k)];
    grid->max_per_cell = std::max(grid->max_per_cell, chunk_max[size_t(k)]);
  }
  return true;
}

// BuildLists, threaded when that pays (at least two range blocks per part).
bool BuildListsOn(const TriangleSoA& tris, size_t limit, int threads, Grid* grid,
                  size_t* num_refs_out) {
  const int parts = int(std::min<size_t>(size_t(BuildThreadCount(threads)),
                                         tris.size / (2 * kRangeBlock)));
  if (parts <= 1) return BuildLists(tris, limit, grid, num_refs_out);
  return BuildListsThreaded(tris, limit, parts, grid, num_refs_out);
}

}  // namespace

void BuildGrid(const TriangleSoA& tris, float lambda, int max_resolution, Grid* grid,
               int threads) {
  BuildGrid(tris, ComputeGridBounds(tris), lambda, max_resolution, grid, threads);
}

void BuildGrid(const TriangleSoA& tris, const GridBounds& bounds, float lambda, int max_resolution,
               Grid* grid, int threads) {
  SetGeometry(bounds, double(lambda), max_resolution, grid);
  if (grid->num_cells == 0) return;
  const size_t limit = GridRefBudget(bounds.num_valid);
  const double num_valid = double(bounds.num_valid);
  // The common case in one pass: the lists at the asked resolution, which stop as soon as they
  // pass the budget (O(budget) work and memory at most).
  size_t refs = 0;
  if (BuildListsOn(tris, limit, threads, grid, &refs)) return;
  // Over the budget: search the finest resolution whose estimate fits (EstimateGridRefs, no
  // lists), then build it; if its lists still pass the budget, search again below it.
  refs = std::max(refs, EstimateGridRefs(tris, *grid, limit));
  for (;;) {
    size_t fail = grid->num_cells;  // the fewest cells known to exceed the budget
    // coarsen until the estimate fits: references fall at least like cells^(2/3) (triangles
    // larger than a cell cover areas), so cells x (limit / refs)^(3/2) should fit; at least
    // halve the cells per step. One cell lists every valid triangle once: the loop ends.
    while (refs > limit) {
      HWY_ASSERT(grid->num_cells > 1);
      fail = std::min(fail, grid->num_cells);
      const double factor = std::min(0.5, std::pow(double(limit) / double(refs), 1.5));
      const size_t cells = grid->num_cells;
      const int res[3] = {grid->res[0], grid->res[1], grid->res[2]};
      SetGeometry(bounds, double(cells) * factor / num_valid, max_resolution, grid);
      if (grid->num_cells >= cells) {
        // rounding kept the cell count (tiny grids): halve the finest axis instead
        const int a = res[0] >= res[1] ? (res[0] >= res[2] ? 0 : 2) : (res[1] >= res[2] ? 1 : 2);
        int halved[3] = {res[0], res[1], res[2]};
        halved[a] = std::max(1, halved[a] / 2);
        SetResolution(bounds, halved, grid);
      }
      refs = EstimateGridRefs(tris, *grid, limit);
    }
    // the coarsening may overshoot by up to its step: up to 3 bisections (geometric mean of the
    // cell counts) between the fitting resolution and the failing one
    for (int step = 0; step < 3 && double(fail) > 1.5 * double(grid->num_cells); ++step) {
      const int fit[3] = {grid->res[0], grid->res[1], grid->res[2]};
      const size_t fit_cells = grid->num_cells;
      SetGeometry(bounds, std::sqrt(double(fail) * double(fit_cells)) / num_valid, max_resolution,
                  grid);
      if (grid->num_cells <= fit_cells || grid->num_cells >= fail) {
        SetResolution(bounds, fit, grid);  // no resolution in between
        break;
      }
      if (EstimateGridRefs(tris, *grid, limit) > limit) {
        fail = grid->num_cells;
        SetResolution(bounds, fit, grid);
      }
    }
    if (BuildListsOn(tris, limit, threads, grid, &refs)) return;
  }
}

}  // namespace rs
