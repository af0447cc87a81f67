// Triangle storage (gathering a MeshView into float SoA arrays, degenerate flags) and the
// non-inline scalar ray/triangle tests (see triangle.h).
#include "kernels/triangle.h"

#include <algorithm>
#include <cfloat>
#include <cmath>
#include <vector>

#include "kernels/build_threads.h"
#include "kernels/grid_binning.h"

namespace rs {

bool IsDegenerateTriangle(const float p0[3], const float p1[3], const float p2[3]) {
  for (int a = 0; a < 3; ++a) {
    if (!std::isfinite(p0[a]) || !std::isfinite(p1[a]) || !std::isfinite(p2[a])) return true;
  }
  // float -> double is exact; the differences of floats and the products below are (nearly)
  // exact in double, so only truly zero-area triangles give the zero vector.
  const double e1[3] = {double(p1[0]) - double(p0[0]), double(p1[1]) - double(p0[1]),
                        double(p1[2]) - double(p0[2])};
  const double e2[3] = {double(p2[0]) - double(p0[0]), double(p2[1]) - double(p0[1]),
                        double(p2[2]) - double(p0[2])};
  const double nx = e1[1] * e2[2] - e1[2] * e2[1];
  const double ny = e1[2] * e2[0] - e1[0] * e2[2];
  const double nz = e1[0] * e2[1] - e1[1] * e2[0];
  return nx == 0.0 && ny == 0.0 && nz == 0.0;
}

void BuildTriangleSoA(const MeshView& mesh, TriangleSoA* out, int threads) {
  const size_t n = mesh.num_triangles;
  // every element below n is written next: no zero fill (it cost as much as the gather)
  for (auto& vertex : out->p) {
    for (auto& axis : vertex) axis.ReserveForOverwrite(n);
  }
  out->verts.ReserveForOverwrite(9 * n);
  out->degenerate.ReserveForOverwrite(n);
  out->size = n;
  // gather (one pass writing the SoA arrays and the interleaved records: on AVX2 hardware
  // gathers, 12 per 8 triangles, cost more than these scalar loads), then the degenerate flags
  // a vector of triangles at a time (kernels/grid_simd.cc); threaded: both per part
  float* dst[3][3];
  for (int k = 0; k < 3; ++k) {
    for (int a = 0; a < 3; ++a) dst[k][a] = out->p[k][a].data();
  }
  const int parts = int(std::min<size_t>(size_t(BuildThreadCount(threads)), n / 4096 + 1));
  std::vector<size_t> degenerate(size_t(parts), 0), nonfinite(size_t(parts), 0);
  RunParts(parts, [&](int t) {
    const size_t first = PartBegin(n, parts, t, 64), last = PartBegin(n, parts, t + 1, 64);
    float* const verts = out->verts.data();
    for (size_t i = first; i < last; ++i) {
      for (int k = 0; k < 3; ++k) {
        const float* src = mesh.positions + size_t{mesh.indices[3 * i + k]} * mesh.stride;
        for (int a = 0; a < 3; ++a) {
          dst[k][a][i] = src[a];
          verts[9 * i + size_t(3 * k + a)] = src[a];
        }
      }
    }
    SimdDegenerateFlags(out, first, last, &degenerate[size_t(t)], &nonfinite[size_t(t)]);
  });
  out->num_degenerate = out->num_nonfinite = 0;
  for (int t = 0; t < parts; ++t) {
    out->num_degenerate += degenerate[size_t(t)];
    out->num_nonfinite += nonfinite[size_t(t)];
  }
}

void TranslateTriangleSoA(const float shift[3], TriangleSoA* tris) {
  for (int k = 0; k < 3; ++k) {
    for (int a = 0; a < 3; ++a) {
      float* const p = tris->p[k][a].data();
      for (size_t i = 0; i < tris->size; ++i) p[i] -= shift[a];
    }
  }
  float* const verts = tris->verts.data();
  for (size_t i = 0; i < 9 * tris->size; ++i) verts[i] -= shift[i % 3];
}

bool WatertightAheadInDouble(float a0, float a1, float a2, float b0, float b1, float b2, float c0,
                             float c1, float c2, float o0, float o1, float o2, float sx, float sy,
                             float sz) {
  const double az = double(a2) - o2, bz = double(b2) - o2, cz = double(c2) - o2;
  const double ax = (double(a0) - o0) - double(sx) * az;
  const double ay = (double(a1) - o1) - double(sy) * az;
  const double bx = (double(b0) - o0) - double(sx) * bz;
  const double by = (double(b1) - o1) - double(sy) * bz;
  const double cx = (double(c0) - o0) - double(sx) * cz;
  const double cy = (double(c1) - o1) - double(sy) * cz;
  const double u = cx * by - cy * bx;
  const double v = ax * cy - ay * cx;
  const double w = bx * ay - by * ax;
  const double det = u + v + w;
  if (!(det != 0.0)) return false;  // parallel in double (or NaN): not certainly ahead
  const double saz = double(sz) * az, sbz = double(sz) * bz, scz = double(sz) * cz;
  const double tz = u * saz + v * sbz + w * scz;
  // the signs of U, V, W may differ in double (near an edge): max |U|, |V|, |W|, not |det|
  const double max_z = Max3Abs(az, bz, cz);
  const double max_xyz = std::fmax(std::fmax(Max3Abs(ax, bx, cx), Max3Abs(ay, by, cy)), max_z);
  const double delta_t = WatertightDeltaT(max_xyz, std::fabs(double(sz)) * max_z, Max3Abs(u, v, w));
  return (det < 0.0 ? -tz : tz) > delta_t;  // t may be < 0 here: the sign counts
}

bool WatertightHitNearOrigin(const WatertightRay& r, float a0, float a1, float a2, float b0,
                             float b1, float b2, float c0, float c1, float c2, float det, float tz,
                             float t, float v, float w, TriHit* hit) {
  // the test's own operations (same values), then DeltaT in its SIMD operation order
  const float az = a2 - r.o[2], bz = b2 - r.o[2], cz = c2 - r.o[2];
  const float ax = (a0 - r.o[0]) - r.sx * az;
  const float ay = (a1 - r.o[1]) - r.sy * az;
  const float bx = (b0 - r.o[0]) - r.sx * bz;
  const float by = (b1 - r.o[1]) - r.sy * bz;
  const float cx = (c0 - r.o[0]) - r.sx * cz;
  const float cy = (c1 - r.o[1]) - r.sy * cz;
  const float max_z = Max3Abs(az, bz, cz);
  const float max_xy = std::max(Max3Abs(ax, bx, cx), Max3Abs(ay, by, cy));
  const float max_xyz = std::max(max_xy, max_z);
  // t > tmin >= 0: T and det share their sign, so t |det| <= DeltaT is |T| <= DeltaT
  const float delta_t = WatertightDeltaT(max_xyz, std::fabs(r.sz) * max_z, std::fabs(det));
  if (std::fabs(tz) <= delta_t &&
      !WatertightAheadInDouble(a0, a1, a2, b0, b1, b2, c0, c1, c2, r.o[0], r.o[1], r.o[2], r.sx,
                               r.sy, r.sz)) {
    return false;  // may be behind the origin
  }
  // the hit, as IntersectWatertightPermuted writes it
  const float inv_det = 1.0f / det;
  hit->t = t;
  hit->u = v * inv_det;
  hit->v = w * inv_det;
  return true;
}

bool IntersectTriangle(const float p0[3], const float p1[3], const float p2[3], float ox,
                       float oy, float oz, float dx, float dy, float dz, float tmin, float tmax,
                       TriHit* hit) {
  if (IsDegenerateTriangle(p0, p1, p2)) return false;
  const WatertightRay r = PrepareWatertightRay(ox, oy, oz, dx, dy, dz);
  const float tmax_finite = tmax > FLT_MAX ? FLT_MAX : tmax;  // NaN stays NaN: no hit
  const int kx = r.kx, ky = r.ky, kz = r.kz;
  return IntersectWatertightPermuted(r, p0[kx], p0[ky], p0[kz], p1[kx], p1[ky], p1[kz], p2[kx],
                                     p2[ky], p2[kz], tmin, tmax_finite, hit);
}

bool IntersectMollerTrumbore(const float p0[3], const float p1[3], const float p2[3], float ox,
                             float oy, float oz, float dx, float dy, float dz, float tmin,
                             float tmax, TriHit* hit) {
  if (!RayIsValid(ox, oy, oz, dx, dy, dz) || IsDegenerateTriangle(p0, p1, p2)) return false;
  // e1, e2: edges from p0; pvec = d x e2; det = e1 . pvec (0 => ray parallel to the plane)
  const float e1x = p1[0] - p0[0], e1y = p1[1] - p0[1], e1z = p1[2] - p0[2];
  const float e2x = p2[0] - p0[0], e2y = p2[1] - p0[1], e2z = p2[2] - p0[2];
  const float px = dy * e2z - dz * e2y;
  const float py = dz * e2x - dx * e2z;
  const float pz = dx * e2y - dy * e2x;
  const float det = e1x * px + e1y * py + e1z * pz;
  if (det == 0.0f || !std::isfinite(det)) return false;
  const float inv_det = 1.0f / det;
  // s = o - p0; u = (s . pvec) / det
  const float sx = ox - p0[0], sy = oy - p0[1], sz = oz - p0[2];
  const float u = (sx * px + sy * py + sz * pz) * inv_det;
  if (!(u >= 0.0f && u <= 1.0f)) return false;
  // q = s x e1; v = (d . q) / det; t = (e2 . q) / det
  const float qx = sy * e1z - sz * e1y;
  const float qy = sz * e1x - sx * e1z;
  const float qz = sx * e1y - sy * e1x;
  const float v = (dx * qx + dy * qy + dz * qz) * inv_det;
  if (!(v >= 0.0f && u + v <= 1.0f)) return false;
  const float t = (e2x * qx + e2y * qy + e2z * qz) * inv_det;
  const float tmax_finite = tmax > FLT_MAX ? FLT_MAX : tmax;  // NaN stays NaN: no hit
  if (!(t > tmin && t <= tmax_finite)) return false;
  hit->t = t;
  hit->u = u;
  hit->v = v;
  return true;
}

}  // namespace rs
