// Double-precision test oracle (see reference.h): the watertight test in double, brute force
// over all triangles, and the Morton-chunked variant with identical answers.
#include "kernels/reference.h"

#include <algorithm>
#include <cmath>
#include <utility>

#include "kernels/triangle.h"

namespace rs::ref {

Ray MakeRay(float ox, float oy, float oz, float dx, float dy, float dz, float tmin, float tmax) {
  Ray r;
  // The inputs arrive as float parameters of an out-of-line function, so they are already
  // rounded to float; float -> double is exact.
  r.o[0] = ox;
  r.o[1] = oy;
  r.o[2] = oz;
  r.d[0] = dx;
  r.d[1] = dy;
  r.d[2] = dz;
  r.tmin = tmin;
  r.tmax = tmax;
  r.valid = RayIsValid(ox, oy, oz, dx, dy, dz);
  // Same axis choice as the float test: kz = largest |d| (first on ties).
  const double ax = std::fabs(r.d[0]), ay = std::fabs(r.d[1]), az = std::fabs(r.d[2]);
  int kz = 0;
  if (ay > ax) kz = 1;
  if (az > (kz == 0 ? ax : ay)) kz = 2;
  int kx = kz + 1 == 3 ? 0 : kz + 1;
  int ky = kx + 1 == 3 ? 0 : kx + 1;
  if (r.d[kz] < 0.0) std::swap(kx, ky);
  r.kx = kx;
  r.ky = ky;
  r.kz = kz;
  r.sx = r.d[kx] / r.d[kz];
  r.sy = r.d[ky] / r.d[kz];
  r.sz = 1.0 / r.d[kz];
  return r;
}

bool IntersectTriangle(const Ray& ray, const double p0[3], const double p1[3],
                       const double p2[3], double tmax, Hit* hit) {
  if (!ray.valid) return false;
  const int kx = ray.kx, ky = ray.ky, kz = ray.kz;
  // vertices relative to the origin, sheared so the ray is the +z axis
  const double a[3] = {p0[0] - ray.o[0], p0[1] - ray.o[1], p0[2] - ray.o[2]};
  const double b[3] = {p1[0] - ray.o[0], p1[1] - ray.o[1], p1[2] - ray.o[2]};
  const double c[3] = {p2[0] - ray.o[0], p2[1] - ray.o[1], p2[2] - ray.o[2]};
  const double ax = a[kx] - ray.sx * a[kz], ay = a[ky] - ray.sy * a[kz];
  const double bx = b[kx] - ray.sx * b[kz], by = b[ky] - ray.sy * b[kz];
  const double cx = c[kx] - ray.sx * c[kz], cy = c[ky] - ray.sy * c[kz];
  // edge functions; inside iff all have one sign
  const double u = cx * by - cy * bx;
  const double v = ax * cy - ay * cx;
  const double w = bx * ay - by * ax;
  if ((u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0)) return false;
  const double det = u + v + w;
  if (det == 0.0) return false;
  const double tz = u * (ray.sz * a[kz]) + v * (ray.sz * b[kz]) + w * (ray.sz * c[kz]);
  const double t = tz / det;
  if (!(t > ray.tmin && t <= tmax)) return false;
  hit->t = t;
  hit->u = v / det;
  hit->v = w / det;
  return true;
}

void TriangleVertices(const MeshView& mesh, size_t i, double p[3][3]) {
  for (int k = 0; k < 3; ++k) {
    const float* src = mesh.positions + size_t{mesh.indices[3 * i + k]} * mesh.stride;
    for (int a = 0; a < 3; ++a) p[k][a] = double(src[a]);  // loaded from memory: exact
  }
}

namespace {

bool MeshTriangleDegenerate(const MeshView& mesh, size_t i) {
  const float* q[3];
  for (int k = 0; k < 3; ++k) q[k] = mesh.positions + size_t{mesh.indices[3 * i + k]} * mesh.stride;
  return IsDegenerateTriangle(q[0], q[1], q[2]);
}

// Closest-hit update with the shared tie rule: smaller t, or equal t and smaller id.
inline void Keep(const Hit& h, int32_t id, Hit* best) {
  if (h.t < best->t || (h.t == best->t && (best->prim < 0 || id < best->prim))) {
    *best = h;
    best->prim = id;
  }
}

uint64_t SpreadBits21(uint64_t x) {
  x &= 0x1fffff;
  x = (x | x << 32) & 0x1f00000000ffffULL;
  x = (x | x << 16) & 0x1f0000ff0000ffULL;
  x = (x | x << 8) & 0x100f00f00f00f00fULL;
  x = (x | x << 4) & 0x10c30c30c30c30c3ULL;
  x = (x | x << 2) & 0x1249249249249249ULL;
  return x;
}

constexpr size_t kChunk = 16;
constexpr size_t kGroup = 32;  // chunks per group

}  // namespace

Hit IntersectClosest(const MeshView& mesh, const Ray& ray) {
  Hit best;
  if (!ray.valid) return best;
  for (size_t i = 0; i < mesh.num_triangles; ++i) {
    if (MeshTriangleDegenerate(mesh, i)) continue;
    double p[3][3];
    TriangleVertices(mesh, i, p);
    Hit h;
    if (IntersectTriangle(ray, p[0], p[1], p[2], std::min(ray.tmax, best.t), &h)) {
      Keep(h, int32_t(i), &best);
    }
  }
  return best;
}

bool IntersectAny(const MeshView& mesh, const Ray& ray) {
  if (!ray.valid) return false;
  for (size_t i = 0; i < mesh.num_triangles; ++i) {
    if (MeshTriangleDegenerate(mesh, i)) continue;
    double p[3][3];
    TriangleVertices(mesh, i, p);
    Hit h;
    if (IntersectTriangle(ray, p[0], p[1], p[2], ray.tmax, &h)) return true;
  }
  return false;
}

ChunkedMesh::ChunkedMesh(const MeshView& mesh) {
  std::vector<int32_t> live;
  double lo[3] = {HUGE_VAL, HUGE_VAL, HUGE_VAL}, hi[3] = {-HUGE_VAL, -HUGE_VAL, -HUGE_VAL};
  for (size_t i = 0; i < mesh.num_triangles; ++i) {
    if (MeshTriangleDegenerate(mesh, i)) continue;
    live.push_back(int32_t(i));
    double p[3][3];
    TriangleVertices(mesh, i, p);
    for (const auto& q : p) {
      for (int a = 0; a < 3; ++a) {
        lo[a] = std::min(lo[a], q[a]);
        hi[a] = std::max(hi[a], q[a]);
      }
    }
  }
  if (live.empty()) return;
  double scale = 0.0;
  for (int a = 0; a < 3; ++a) {
    scale = std::max({scale, hi[a] - lo[a], std::fabs(lo[a]), std::fabs(hi[a])});
  }
  const double eps = 1e-9 * scale;
  // Morton order of the centroids (21 bits per axis), ties by id.
  std::vector<std::pair<uint64_t, int32_t>> keyed;
  keyed.reserve(live.size());
  for (const int32_t i : live) {
    double p[3][3];
    TriangleVertices(mesh, size_t(i), p);
    uint64_t code = 0;
    for (int a = 0; a < 3; ++a) {
      const double c = (p[0][a] + p[1][a] + p[2][a]) / 3.0;
      const double ext = hi[a] - lo[a];
      const double f = ext > 0.0 ? (c - lo[a]) / ext : 0.0;
      const uint64_t q = uint64_t(std::clamp(f, 0.0, 1.0) * double((1 << 21) - 1));
      code |= SpreadBits21(q) << a;
    }
    keyed.emplace_back(code, i);
  }
  std::sort(keyed.begin(), keyed.end());
  verts_.resize(keyed.size() * 9);
  ids_.resize(keyed.size());
  for (size_t k = 0; k < keyed.size(); ++k) {
    ids_[k] = keyed[k].second;
    double p[3][3];
    TriangleVertices(mesh, size_t(keyed[k].second), p);
    for (int j = 0; j < 3; ++j) {
      for (int a = 0; a < 3; ++a) verts_[9 * k + 3 * j + a] = p[j][a];
    }
  }
  // Chunk boxes (exact vertex bounds, enlarged by eps), then group boxes over chunk boxes.
  const size_t num_chunks = (ids_.size() + kChunk - 1) / kChunk;
  chunk_boxes_.resize(num_chunks);
  for (size_t c = 0; c < num_chunks; ++c) {
    Box b{{HUGE_VAL, HUGE_VAL, HUGE_VAL}, {-HUGE_VAL, -HUGE_VAL, -HUGE_VAL}};
    for (size_t k = c * kChunk; k < std::min(ids_.size(), (c + 1) * kChunk); ++k) {
      for (int j = 0; j < 3; ++j) {
        for (int a = 0; a < 3; ++a) {
          b.lo[a] = std::min(b.lo[a], verts_[9 * k + 3 * j + a]);
          b.hi[a] = std::max(b.hi[a], verts_[9 * k + 3 * j + a]);
        }
      }
    }
    for (int a = 0; a < 3; ++a) {
      b.lo[a] -= eps;
      b.hi[a] += eps;
    }
    chunk_boxes_[c] = b;
  }
  const size_t num_groups = (num_chunks + kGroup - 1) / kGroup;
  group_boxes_.resize(num_groups);
  for (size_t g = 0; g < num_groups; ++g) {
    Box b{{HUGE_VAL, HUGE_VAL, HUGE_VAL}, {-HUGE_VAL, -HUGE_VAL, -HUGE_VAL}};
    for (size_t c = g * kGroup; c < std::min(num_chunks, (g + 1) * kGroup); ++c) {
      for (int a = 0; a < 3; ++a) {
        b.lo[a] = std::min(b.lo[a], chunk_boxes_[c].lo[a]);
        b.hi[a] = std::max(b.hi[a], chunk_boxes_[c].hi[a]);
      }
    }
    group_boxes_[g] = b;
  }
}

bool ChunkedMesh::SegmentTouches(const Box& box, const Ray& ray, double tmax) {
  double t0 = ray.tmin, t1 = tmax;
  for (int a = 0; a < 3; ++a) {
    if (ray.d[a] == 0.0) {
      if (ray.o[a] < box.lo[a] || ray.o[a] > box.hi[a]) return false;
      continue;
    }
    const double inv = 1.0 / ray.d[a];
    double ta = (box.lo[a] - ray.o[a]) * inv, tb = (box.hi[a] - ray.o[a]) * inv;
    if (ta > tb) std::swap(ta, tb);
    t0 = std::max(t0, ta);
    t1 = std::min(t1, tb);
  }
  return t0 <= t1;
}

template <bool kAnyHit>
bool ChunkedMesh::Trace(const Ray& ray, Hit* hit) const {
  if (!ray.valid || !(ray.tmin < ray.tmax)) return false;
  Hit best;
  for (size_t g = 0; g < group_boxes_.size(); ++g) {
    if (!SegmentTouches(group_boxes_[g], ray, std::min(ray.tmax, best.t))) continue;
    const size_t chunk_end = std::min(chunk_boxes_.size(), (g + 1) * kGroup);
    for (size_t c = g * kGroup; c < chunk_end; ++c) {
      if (!SegmentTouches(chunk_boxes_[c], ray, std::min(ray.tmax, best.t))) continue;
      for (size_t k = c * kChunk; k < std::min(ids_.size(), (c + 1) * kChunk); ++k) {
        const double* p = &verts_[9 * k];
        Hit h;
        if (!IntersectTriangle(ray, p, p + 3, p + 6, std::min(ray.tmax, best.t), &h)) continue;
        if constexpr (kAnyHit) {
          return true;
        } else {
          Keep(h, ids_[k], &best);
        }
      }
    }
  }
  if constexpr (!kAnyHit) *hit = best;
  return best.prim >= 0;
}

Hit ChunkedMesh::IntersectClosest(const Ray& ray) const {
  Hit best;
  Trace<false>(ray, &best);
  return best;
}

bool ChunkedMesh::IntersectAny(const Ray& ray) const { return Trace<true>(ray, nullptr); }

}  // namespace rs::ref
