// rs::Accel: validates the caller's mesh, gathers its triangles, builds the uniform grid (and,
// if it pays off or is asked for, the two-level grid), and traces ray streams with the SIMD
// stream DDA (kernels/dda_simd.h); the scalar DDA stays as the oracle (rs::ref::AccelIntersect).
#include <hwy/base.h>

#include <algorithm>
#include <cfloat>
#include <chrono>
#include <cmath>
#include <limits>
#include <sstream>
#include <string>

#include "include/raystream/raystream.h"
#include "kernels/accel_impl.h"
#include "kernels/packet_dda.h"
#include "kernels/dda.h"
#include "kernels/dda_simd.h"
#include "kernels/grid_binning.h"  // SimdMaxIndex
#include "kernels/two_level.h"

namespace rs {
namespace {

// Empty-space skipping is used on grids with at least this share of their cells inside empty
// 5x5x5 blocks (see Accel::Accel).
constexpr double kEmptySkipMinShare = 0.75;
// BuildOptions::lambda 0 with a fixed grid kind: the Cleary/Wyvill density.
constexpr float kDefaultLambda = 4.0f;

std::string FormatFloat(float x) {
  std::ostringstream s;
  s << x;
  return s.str();
}

// Throws rs::Error for bad options or mesh arrays; the per-triangle checks are ValidateTriangles.
void ValidateOptionsAndArrays(const MeshView& mesh, const BuildOptions& options) {
  if (!(options.lambda >= 0.0f) || !std::isfinite(options.lambda)) {
    throw Error("BuildOptions: lambda must be 0 (chosen by the grid cost model) or a positive "
                "finite number, got " + FormatFloat(options.lambda));
  }
  if (options.grid != GridKind::kAuto && options.grid != GridKind::kUniform &&
      options.grid != GridKind::kTwoLevel && options.grid != GridKind::kIrregular) {
    throw Error("BuildOptions: unknown grid kind " + std::to_string(int(options.grid)));
  }
  if (options.micro_cache < 0 || options.micro_cache > kMaxMicroCache) {
    throw Error("BuildOptions: micro_cache must be within 0.." + std::to_string(kMaxMicroCache) +
                ", got " + std::to_string(options.micro_cache));
  }
  if (options.max_resolution < 1) {
    throw Error("BuildOptions: max_resolution must be >= 1, got " +
                std::to_string(options.max_resolution));
  }
  if (mesh.num_triangles == 0) return;
  if (mesh.stride < 3) {
    throw Error("mesh: position stride " + std::to_string(mesh.stride) +
                " is less than 3 floats");
  }
  if (mesh.indices == nullptr) throw Error("mesh: " + std::to_string(mesh.num_triangles) +
                                           " triangles but no index array");
  if (mesh.positions == nullptr && mesh.num_vertices > 0) {
    throw Error("mesh: " + std::to_string(mesh.num_vertices) + " vertices but no position array");
  }
  if (mesh.num_triangles > size_t{std::numeric_limits<int32_t>::max()}) {
    throw Error("mesh: " + std::to_string(mesh.num_triangles) +
                " triangles exceed the limit of 2^31 - 1 (hit ids are int32)");
  }
}

// The per-triangle checks (indices in range, referenced vertices finite): throws rs::Error
// naming the first bad element, or returns if there is none.
void ValidateTriangles(const MeshView& mesh) {
  for (size_t i = 0; i < mesh.num_triangles; ++i) {
    for (int k = 0; k < 3; ++k) {
      const uint32_t index = mesh.indices[3 * i + k];
      if (size_t{index} >= mesh.num_vertices) {
        throw Error("triangle " + std::to_string(i) + ": vertex index " + std::to_string(index) +
                    " out of range (" + std::to_string(mesh.num_vertices) + " vertices)");
      }
      const float* p = mesh.positions + size_t{index} * mesh.stride;
      if (!std::isfinite(p[0]) || !std::isfinite(p[1]) || !std::isfinite(p[2])) {
        throw Error("triangle " + std::to_string(i) + ": vertex " + std::to_string(k) +
                    " (index " + std::to_string(index) + ") has a non-finite position (" +
                    FormatFloat(p[0]) + ", " + FormatFloat(p[1]) + ", " + FormatFloat(p[2]) +
                    ")");
      }
    }
  }
}

// True iff every index is < num_vertices (one pass over the index array, no position read;
// SIMD: without -march the compiler has no unsigned 32-bit max to vectorize the scalar loop).
bool IndicesInRange(const MeshView& mesh) {
  const size_t count = 3 * mesh.num_triangles;
  return count == 0 || size_t{SimdMaxIndex(mesh.indices, count)} < mesh.num_vertices;
}

}  // namespace

namespace {

// Builds into `m`, whose structures are empty, allocating through m->cache.
void Build(const MeshView& mesh, const BuildOptions& options, Accel::Impl* impl) {
  const BlockCacheScope scope(&impl->cache);
  const auto start = std::chrono::steady_clock::now();
  // Validation without a pass of its own over the positions: the indices are checked first (the
  // gather must not read out of range), then the gather's degenerate pass counts non-finite
  // triangles; either problem reruns the full per-triangle checks, which throw naming the first
  // bad element exactly as checking everything up front would.
  ValidateOptionsAndArrays(mesh, options);
  if (!IndicesInRange(mesh)) ValidateTriangles(mesh);
  Accel::Impl& m = *impl;
  BuildTriangleSoA(mesh, &m.triangles, options.build_threads);
  if (m.triangles.num_nonfinite != 0) ValidateTriangles(mesh);
  const GridCostModel model;
  m.lambda = options.lambda > 0.0f ? options.lambda : kDefaultLambda;
  GridBounds bounds = ComputeGridBounds(m.triangles);  // shared by the lambda choice
  ChooseFrameShift(bounds, m.shift);
  if (m.Shifted()) {  // a scene far from the origin: build it near the origin
    TranslateTriangleSoA(m.shift, &m.triangles);
    bounds = ComputeGridBounds(m.triangles);
  }
  const bool auto_grid = options.grid == GridKind::kAuto || options.grid == GridKind::kIrregular;
  if (auto_grid && options.lambda == 0.0f) {
    m.lambda = ChooseLambda(m.triangles, bounds, options.max_resolution, model, nullptr,
                            options.build_threads);
  }
  BuildGrid(m.triangles, bounds, m.lambda, options.max_resolution, &m.grid,
            options.build_threads);
  const bool may_refine =
      options.grid == GridKind::kTwoLevel ||
      (auto_grid &&
       TwoLevelCostBound(m.grid, options.subgrid_threshold, model) <
           kTwoLevelMinGain * FlatGridCost(m.grid, model));
  if (may_refine) {
    BuildTwoLevel(m.grid, m.triangles, options.subgrid_threshold,
                  /*by_cost=*/auto_grid, model, &m.two_level, options.build_threads);
    if (auto_grid && !m.two_level.empty() &&
        !(TwoLevelGridCost(m.grid, m.two_level, model) <
          kTwoLevelMinGain * FlatGridCost(m.grid, model))) {
      m.two_level = TwoLevelGrid();  // not worth it: stay flat
    }
  }
  BuildDdaGrid(m.grid, &m.two_level, m.triangles, &m.dda, options.build_threads);
  if (options.grid == GridKind::kIrregular) {
    BuildIrregularGrid(m.triangles, bounds, IrregularOptions{}, options.max_resolution,
                       &m.irregular);
    BuildIrregularDda(m.irregular, m.triangles, &m.irregular_dda, options.build_threads);
    m.dda.irregular = &m.irregular_dda;
  }
  m.dda_options.micro_cache = options.micro_cache;
  m.packets = options.packets;
  // A jump costs a gather and the exact boundary search (dda_stream.cc: JumpEmpty), several
  // plain steps' worth, and steps are not what bounds the stream kernel on real scenes (the
  // triangle tests and lane refills are): bench/kernels/dda_bench.cc (Dda vs DdaNoSkip) measured
  // 6-20 % slower with skipping on bunny (49 % of cells in empty blocks) and spherebox (12 %) in
  // spite of 2-4x fewer steps, no change on conference, and 2.7x faster on the sparse "corners"
  // grid.
  m.dda_options.empty_skip = options.empty_skip && m.dda.empty_block_share >= kEmptySkipMinShare;
  m.flat_cost_estimate = FlatGridCost(m.grid, model);
  m.cost_estimate = TwoLevelGridCost(m.grid, m.two_level, model);
  m.build_seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  m.built = true;
}

}  // namespace

Accel::Accel(const MeshView& mesh, const BuildOptions& options) : impl_(std::make_unique<Impl>()) {
  Build(mesh, options, impl_.get());
  impl_->cache.EndBuild(/*keep_freed=*/false);  // a one-off build keeps no temporaries
}

void Accel::Rebuild(const MeshView& mesh, const BuildOptions& options) {
  if (!impl_) impl_ = std::make_unique<Impl>();
  Impl& m = *impl_;
  m.built = false;
  // Free every structure into the cache (the blocks stay mapped), then build taking them back.
  m.triangles = TriangleSoA();
  m.grid = Grid();
  m.two_level = TwoLevelGrid();
  m.irregular = IrregularGrid();
  m.irregular_dda = IrregularDda();
  m.dda = DdaGrid();
  m.dda_options = DdaOptions();
  m.cache.BeginBuild();
  try {
    Build(mesh, options, &m);
  } catch (...) {
    m.cache.EndBuild(/*keep_freed=*/false);
    throw;
  }
  m.cache.EndBuild(/*keep_freed=*/true);  // the build's temporaries serve the next Rebuild
}

Accel::~Accel() = default;
Accel::Accel(Accel&&) noexcept = default;
Accel& Accel::operator=(Accel&&) noexcept = default;

namespace {

// The checks of the public entry points (the kernels assume them).
const Accel::Impl& Checked(const std::unique_ptr<Accel::Impl>& impl, const char* what) {
  if (!impl) throw Error(std::string(what) + ": the Accel was moved from");
  if (!impl->built) throw Error(std::string(what) + ": the Accel's last Rebuild failed");
  return *impl;
}

}  // namespace

const Accel::Impl& AccelImpl(const Accel& accel) { return Checked(accel.impl_, "Accel"); }

namespace {

void CheckRays(const RayStreamView& rays, const char* what) {
  if (rays.size == 0) return;
  const float* arrays[] = {rays.ox, rays.oy, rays.oz, rays.dx, rays.dy, rays.dz, rays.tmin,
                           rays.tmax};
  const char* names[] = {"ox", "oy", "oz", "dx", "dy", "dz", "tmin", "tmax"};
  for (int i = 0; i < 8; ++i) {
    if (arrays[i] == nullptr) {
      throw Error(std::string("Accel::") + what + ": rays." + names[i] + " is null for " +
                  std::to_string(rays.size) + " rays");
    }
  }
}

// The kernels load and store whole vectors up to PaddedSize(size) elements. Callers' arrays may
// hold exactly `size`: the rays before the last multiple of kStreamPad are traced in place (then
// PaddedSize is their count), the rest through padded copies on the stack. The split changes no
// result (each ray's trace is independent) and no packet (a packet is 64 consecutive rays from
// the start; the tail is shorter than any packet).
struct PaddedTail {
  alignas(kStreamAlign) float f[8][kStreamPad];
  alignas(kStreamAlign) float t[kStreamPad], u[kStreamPad], v[kStreamPad];
  alignas(kStreamAlign) int32_t prim[kStreamPad];
  RayStreamView rays;
  HitStreamView hits;

  // rays[first, first + n), n < kStreamPad, copied (origins in the Accel's frame,
  // FrameOrigins); the padding never hits (zero direction).
  PaddedTail(const Accel::Impl& m, const RayStreamView& from, size_t first, size_t n) {
    float* const dst[8] = {f[0], f[1], f[2], f[3], f[4], f[5], f[6], f[7]};
    const float* const src[8] = {from.ox, from.oy, from.oz, from.dx, from.dy, from.dz, from.tmin,
                                 from.tmax};
    FrameOrigins(m, from, first, n, dst);
    for (int a = 3; a < 8; ++a) {
      std::fill(dst[a], dst[a] + kStreamPad, 0.0f);
      std::copy(src[a] + first, src[a] + first + n, dst[a]);
    }
    rays.ox = f[0], rays.oy = f[1], rays.oz = f[2];
    rays.dx = f[3], rays.dy = f[4], rays.dz = f[5];
    rays.tmin = f[6], rays.tmax = f[7];
    rays.size = n;
    hits = HitStreamView{t, u, v, prim, n};
  }
};

}  // namespace

void Accel::Intersect(const RayStreamView& rays, const HitStreamView& hits,
                      TraceStats* stats) const {
  const Impl& m = Checked(impl_, "Accel::Intersect");
  if (hits.size != rays.size) {
    throw Error("Accel::Intersect: hits.size " + std::to_string(hits.size) +
                " differs from rays.size " + std::to_string(rays.size));
  }
  CheckRays(rays, "Intersect");
  if (rays.size > 0 && (!hits.t || !hits.u || !hits.v || !hits.prim)) {
    throw Error("Accel::Intersect: a hit array (t, u, v or prim) is null for " +
                std::to_string(rays.size) + " rays");
  }
  const auto trace = [&](const RayStreamView& r, const HitStreamView& h) {
    if (m.packets) return IntersectCoherent(m.dda, r, h, m.dda_options, stats);
    IntersectStreamDda(m.dda, r, h, m.dda_options, stats);
  };
  const size_t body = rays.size / kStreamPad * kStreamPad, tail = rays.size - body;
  if (body > 0) {
    ForEachFramePiece(m, rays, body, [&](const RayStreamView& piece, size_t first) {
      trace(piece, SubView(hits, first, piece.size));
    });
  }
  if (tail == 0) return;
  PaddedTail p(m, rays, body, tail);
  trace(p.rays, p.hits);
  std::copy(p.t, p.t + tail, hits.t + body);
  std::copy(p.u, p.u + tail, hits.u + body);
  std::copy(p.v, p.v + tail, hits.v + body);
  std::copy(p.prim, p.prim + tail, hits.prim + body);
}

void Accel::Occluded(const RayStreamView& rays, int32_t* occluded, TraceStats* stats) const {
  const Impl& m = Checked(impl_, "Accel::Occluded");
  CheckRays(rays, "Occluded");
  if (rays.size > 0 && occluded == nullptr) {
    throw Error("Accel::Occluded: occluded is null for " + std::to_string(rays.size) + " rays");
  }
  const auto trace = [&](const RayStreamView& r, int32_t* out) {
    if (m.packets) return OccludedCoherent(m.dda, r, out, m.dda_options, stats);
    OccludedStreamDda(m.dda, r, out, m.dda_options, stats);
  };
  const size_t body = rays.size / kStreamPad * kStreamPad, tail = rays.size - body;
  if (body > 0) {
    ForEachFramePiece(m, rays, body, [&](const RayStreamView& piece, size_t first) {
      trace(piece, occluded + first);
    });
  }
  if (tail == 0) return;
  PaddedTail p(m, rays, body, tail);
  trace(p.rays, p.prim);
  std::copy(p.prim, p.prim + tail, occluded + body);
}

namespace ref {

void AccelIntersect(const Accel::Impl& m, const RayStreamView& rays, const HitStreamView& hits,
                    TraceStats* stats) {
  HWY_ASSERT(hits.size == rays.size);
  TraceStats local;
  for (size_t i = 0; i < rays.size; ++i) {
    RayHit h;
    TraceClosestTwoLevel(m.grid, m.two_level, m.triangles, rays.ox[i] - m.shift[0],
                         rays.oy[i] - m.shift[1], rays.oz[i] - m.shift[2], rays.dx[i], rays.dy[i],
                         rays.dz[i], rays.tmin[i], rays.tmax[i], &h, &local);
    hits.t[i] = h.t;
    hits.u[i] = h.u;
    hits.v[i] = h.v;
    hits.prim[i] = h.prim;
  }
  if (stats != nullptr) {
    stats->rays += rays.size;
    stats->cell_steps += local.cell_steps;
    stats->triangle_tests += local.triangle_tests;
  }
}

void AccelOccluded(const Accel::Impl& m, const RayStreamView& rays, int32_t* occluded,
                   TraceStats* stats) {
  TraceStats local;
  for (size_t i = 0; i < rays.size; ++i) {
    occluded[i] = TraceAnyTwoLevel(m.grid, m.two_level, m.triangles, rays.ox[i] - m.shift[0],
                                   rays.oy[i] - m.shift[1], rays.oz[i] - m.shift[2], rays.dx[i],
                                   rays.dy[i], rays.dz[i], rays.tmin[i], rays.tmax[i], &local)
                      ? 1
                      : 0;
  }
  if (stats != nullptr) {
    stats->rays += rays.size;
    stats->cell_steps += local.cell_steps;
    stats->triangle_tests += local.triangle_tests;
  }
}

}  // namespace ref

AccelInfo Accel::Info() const {
  const Impl& m = Checked(impl_, "Accel::Info");
  AccelInfo info;
  info.triangles = m.triangles.size;
  info.degenerate_triangles = m.triangles.num_degenerate;
  for (int a = 0; a < 3; ++a) {  // in world coordinates, rounded outwards
    const double lo = double(m.grid.lo[a]) + m.shift[a], hi = double(m.grid.hi[a]) + m.shift[a];
    const float flo = float(lo), fhi = float(hi);
    info.bounds_lo[a] = double(flo) > lo ? std::nextafter(flo, -FLT_MAX) : flo;
    info.bounds_hi[a] = double(fhi) < hi ? std::nextafter(fhi, FLT_MAX) : fhi;
    info.resolution[a] = m.grid.res[a];
    info.frame_shift[a] = m.shift[a];
  }
  info.cells = m.grid.num_cells;
  info.occupied_cells = m.grid.occupied_cells;
  info.references = m.grid.num_refs;
  info.max_per_cell = m.grid.max_per_cell;
  info.build_seconds = m.build_seconds;
  info.bytes = m.triangles.Bytes() + m.grid.Bytes() + m.two_level.Bytes() + m.dda.Bytes() +
               m.irregular.Bytes() + m.irregular_dda.Bytes();
  info.irregular_cells = m.irregular.num_cells;
  info.irregular_references = m.irregular.lists.num_refs;
  info.kind = m.two_level.empty() ? "uniform" : "two-level";
  info.lambda = m.lambda;
  info.subgrids = m.two_level.num_records;
  info.sub_references = m.two_level.sub_refs;
  info.cost_estimate = m.cost_estimate;
  info.flat_cost_estimate = m.flat_cost_estimate;
  info.simd_target = DdaTargetName();
  info.empty_block_share = m.dda.empty_block_share;
  info.empty_skip = m.dda_options.empty_skip;
  return info;
}

}  // namespace rs
