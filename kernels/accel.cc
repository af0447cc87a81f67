// rs::Accel: validates the caller's mesh, gathers its triangles, builds the uniform grid, and
// traces ray streams with the scalar DDA (the SIMD stream kernels will plug in here).
#include <hwy/base.h>

#include <chrono>
#include <cmath>
#include <limits>
#include <sstream>
#include <string>

#include "include/raystream/raystream.h"
#include "kernels/accel_impl.h"
#include "kernels/dda.h"

namespace rs {
namespace {

std::string FormatFloat(float x) {
  std::ostringstream s;
  s << x;
  return s.str();
}

// Throws rs::Error naming the first bad element. Only vertices that triangles reference must
// be finite.
void ValidateMesh(const MeshView& mesh, const BuildOptions& options) {
  if (!(options.lambda > 0.0f) || !std::isfinite(options.lambda)) {
    throw Error("BuildOptions: lambda must be a positive finite number, got " +
                FormatFloat(options.lambda));
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

}  // namespace

Accel::Accel(const MeshView& mesh, const BuildOptions& options) : impl_(std::make_unique<Impl>()) {
  ValidateMesh(mesh, options);
  const auto start = std::chrono::steady_clock::now();
  // GridKind is not used yet: only the uniform grid exists.
  BuildTriangleSoA(mesh, &impl_->triangles);
  BuildGrid(impl_->triangles, options.lambda, options.max_resolution, &impl_->grid);
  impl_->build_seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
}

Accel::~Accel() = default;
Accel::Accel(Accel&&) noexcept = default;
Accel& Accel::operator=(Accel&&) noexcept = default;

void Accel::Intersect(const RayStreamView& rays, const HitStreamView& hits,
                      TraceStats* stats) const {
  HWY_ASSERT(hits.size == rays.size);
  const Impl& m = *impl_;
  TraceStats local;
  for (size_t i = 0; i < rays.size; ++i) {
    RayHit h;
    TraceClosest(m.grid, m.triangles, rays.ox[i], rays.oy[i], rays.oz[i], rays.dx[i],
                 rays.dy[i], rays.dz[i], rays.tmin[i], rays.tmax[i], &h, &local);
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

void Accel::Occluded(const RayStreamView& rays, int32_t* occluded, TraceStats* stats) const {
  const Impl& m = *impl_;
  TraceStats local;
  for (size_t i = 0; i < rays.size; ++i) {
    occluded[i] = TraceAny(m.grid, m.triangles, rays.ox[i], rays.oy[i], rays.oz[i], rays.dx[i],
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

AccelInfo Accel::Info() const {
  const Impl& m = *impl_;
  AccelInfo info;
  info.triangles = m.triangles.size;
  info.degenerate_triangles = m.triangles.num_degenerate;
  for (int a = 0; a < 3; ++a) {
    info.bounds_lo[a] = m.grid.lo[a];
    info.bounds_hi[a] = m.grid.hi[a];
    info.resolution[a] = m.grid.res[a];
  }
  info.cells = m.grid.num_cells;
  info.occupied_cells = m.grid.occupied_cells;
  info.references = m.grid.num_refs;
  info.max_per_cell = m.grid.max_per_cell;
  info.build_seconds = m.build_seconds;
  info.bytes = m.triangles.Bytes() + m.grid.Bytes();
  info.kind = "uniform";
  return info;
}

}  // namespace rs
