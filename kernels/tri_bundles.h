// Per-cell triangle bundles for the SIMD ray/triangle kernels (kernels/tri_intersect.h): each
// grid cell's triangles re-laid out as 4-wide SoA bundles (the Cell paper, section 3.6, always
// tests a ray against four triangles at once), built in one pass from the grid's CSR lists.
#pragma once

#include <hwy/aligned_allocator.h>

#include <cstddef>
#include <cstdint>

#include "kernels/grid.h"
#include "kernels/triangle.h"

namespace rs {

inline constexpr size_t kBundleLanes = 4;                                  // triangles per bundle
inline constexpr size_t kBundleComponents = 9;                             // 3 vertices x (x, y, z)
inline constexpr size_t kBundleFloats = kBundleComponents * kBundleLanes;  // 144 B per bundle

// The bundles of one cell (or of one list), as the kernels read them. Layout ("cell block"):
// the `count` bundles of a cell are stored component-major, so component c = 3 * vertex + axis
// of lane l of bundle k is vertices[c * stride() + 4 * k + l], stride() = 4 * count. A bundle is
// still 4 x 9 floats, but bundles k and k+1 (k..k+3) of one component are 8 (16) contiguous
// floats: AVX2 (AVX-512) loads 2 (4) bundles with one unaligned load and no shuffles, and the
// whole cell (144 B per bundle, plus 16 B of ids elsewhere) is contiguous for the prefetcher.
// Vertices are the raw float vertices (not edges): the watertight test needs them bit for bit,
// and Moller-Trumbore's edges p1 - p0 are the same float subtraction whether done here or there.
// Padding lanes (past the cell's last triangle) and degenerate triangles hold NaN vertices,
// which no test can hit (NaN fails every comparison, and is never an exact-zero edge function,
// so it never triggers the double-precision fallback); padding lanes have id -1.
struct TriBundleSpan {
  const float* vertices = nullptr;  // 16-B aligned, 36 * count floats
  const int32_t* ids = nullptr;     // 4 * count triangle ids; ascending within a grid cell
  size_t count = 0;                 // bundles

  size_t stride() const { return kBundleLanes * count; }
  // First lane of component (vertex, axis): stride() floats, one per triangle of the span.
  const float* Component(int vertex, int axis) const {
    return vertices + size_t(3 * vertex + axis) * stride();
  }
  size_t lanes() const { return kBundleLanes * count; }
};

// Triangles (not padding lanes) in a span's bundles.
inline size_t SpanTriangles(const TriBundleSpan& s) {
  if (s.count == 0) return 0;
  const int32_t* last = s.ids + kBundleLanes * (s.count - 1);
  return kBundleLanes * (s.count - 1) + size_t(last[0] >= 0) + size_t(last[1] >= 0) +
         size_t(last[2] >= 0) + size_t(last[3] >= 0);
}

// All cells' bundles: cell c owns bundles [cell_begin[c], cell_begin[c + 1]); its block starts
// at data[kBundleFloats * cell_begin[c]] and its ids at ids[kBundleLanes * cell_begin[c]].
// Empty cells own no bundle. Arrays are 64-B aligned; total size about (refs + 1.5 * occupied
// cells) * 40 B.
struct TriBundles {
  hwy::AlignedFreeUniquePtr<float[]> data;           // kBundleFloats per bundle
  hwy::AlignedFreeUniquePtr<int32_t[]> ids;          // kBundleLanes per bundle
  hwy::AlignedFreeUniquePtr<uint32_t[]> cell_begin;  // num_cells + 1 bundle offsets
  size_t num_cells = 0;
  size_t num_bundles = 0;
  size_t num_triangles = 0;  // triangle references (lanes that are not padding)

  TriBundleSpan Cell(size_t cell) const {
    const size_t first = cell_begin[cell];
    TriBundleSpan s;
    s.vertices = data.get() + kBundleFloats * first;
    s.ids = ids.get() + kBundleLanes * first;
    s.count = cell_begin[cell + 1] - first;
    return s;
  }
  size_t Bytes() const {
    return num_bundles * (kBundleFloats * sizeof(float) + kBundleLanes * sizeof(int32_t)) +
           (num_cells + 1) * sizeof(uint32_t);
  }

  // Capacities of the arrays (in bundles and cells), kept for reuse by the next build.
  size_t bundle_capacity = 0;
  size_t cell_capacity = 0;
};

// Re-lays out every cell of `grid` (built over `tris`) into bundles: one pass over the CSR
// lists, keeping each cell's id order. Reuses `out`'s arrays when they are large enough.
// Degenerate triangles (tris.degenerate, never binned by BuildGrid) would get NaN vertices.
// An empty grid gives num_cells = 0. Never throws (allocation failure aborts, as in Highway).
// threads (BuildOptions::build_threads): parts of the cells filled on that many threads (the
// same bundles for any count).
void BuildTriBundles(const Grid& grid, const TriangleSoA& tris, TriBundles* out, int threads = 1);

// Bundles for one list of triangle ids (any order, duplicates allowed): out becomes a single
// cell, out->Cell(0). For tests, benchmarks and N rays x M triangles streams. Ids must be
// < tris.size; degenerate triangles get NaN vertices (never hit) but keep their id.
void BuildTriBundleList(const TriangleSoA& tris, const uint32_t* ids, size_t n, TriBundles* out);

}  // namespace rs
