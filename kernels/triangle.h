// Triangle storage for traversal (float vertices in SoA arrays, degenerate flags) and the scalar
// ray/triangle tests: watertight (Woop, Benthin, Wald, JCGT 2013) and Moller-Trumbore. The
// scalar tests are inline so the DDA loop inlines them; the SIMD versions over triangle bundles
// are in kernels/tri_intersect.h.
#pragma once

#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>

#include "include/raystream/raystream.h"
#include "streams/ray_stream.h"

namespace rs {

// Per-triangle data gathered out of a MeshView, so a test reads no index buffer: the three
// vertices as floats, one 64-B aligned padded array per vertex and axis (p[vertex][axis][id]),
// and the same floats interleaved, 9 per id (verts[9 id + 3 vertex + axis]: x0 y0 z0 x1 ... z2),
// for readers that pick triangles at random (the bundle fill, the light buffers' references):
// one 36-B record per triangle instead of nine loads from nine SoA arrays.
// degenerate[id] = 1 for triangles with zero area (double cross product exactly 0) or a
// non-finite vertex: they are kept (ids stay the mesh's ids) but never binned and never hit.
struct TriangleSoA {
  AlignedArray<float> p[3][3];
  AlignedArray<float> verts;
  AlignedArray<uint8_t> degenerate;
  size_t size = 0;
  size_t num_degenerate = 0;
  size_t num_nonfinite = 0;  // degenerate triangles with a non-finite coordinate

  const float* Vertices(size_t id) const { return verts.data() + 9 * id; }
  size_t Bytes() const { return size * (18 * sizeof(float) + 1); }
};

// True if the triangle can never be hit: a non-finite coordinate, or (p1-p0) x (p2-p0)
// computed in double from the float inputs is exactly the zero vector (repeated vertex,
// collinear vertices). rs::ref uses the same definition.
bool IsDegenerateTriangle(const float p0[3], const float p1[3], const float p2[3]);

// Gathers the mesh's triangles into `out`. Precondition: the mesh is valid (indices in range,
// stride >= 3; see Accel's constructor, which checks and throws). Never throws. threads
// (BuildOptions::build_threads): parts of the triangles gathered on that many threads.
void BuildTriangleSoA(const MeshView& mesh, TriangleSoA* out, int threads = 1);

// Moves every triangle by -shift (p and verts: v - shift in float; exact inside the bounds
// ChooseFrameShift took the shift from, kernels/grid.h). The degenerate flags are kept.
void TranslateTriangleSoA(const float shift[3], TriangleSoA* tris);

// Closest-hit record of the scalar tests: t along the ray (units of |d|), u, v barycentrics of
// vertices 1 and 2.
struct TriHit {
  float t = std::numeric_limits<float>::infinity();
  float u = 0.0f;
  float v = 0.0f;
};

// Per-ray constants of the watertight test (paper section 3): kz = axis of the largest |d|,
// kx, ky the others (swapped when d[kz] < 0 to keep the winding), the shear Sx, Sy, Sz, and
// the origin permuted into (kx, ky, kz) order. Rays failing RayIsValid (NaN/Inf, zero d) get
// sz = NaN, which makes every test below return false (NaN t) without a branch.
struct WatertightRay {
  float o[3];  // origin components kx, ky, kz
  float sx, sy, sz;
  int kx, ky, kz;
};

// Directions whose components are all smaller than this in magnitude count as zero: their
// reciprocals overflow, so neither the DDA nor the shear could be set up. Any component below
// 2.9e-39 (1/d overflows) is treated as 0 by the DDA's stepping, which moves the ray by at
// most 2.9e-39 / kMinDirection = 3e-9 of the grid diagonal: far below the binning margin.
inline constexpr float kMinDirection = 1e-30f;

// A ray can hit anything iff its origin and direction are finite and d is not ~zero.
inline bool RayIsValid(float ox, float oy, float oz, float dx, float dy, float dz) {
  const bool finite = std::isfinite(ox) && std::isfinite(oy) && std::isfinite(oz) &&
                      std::isfinite(dx) && std::isfinite(dy) && std::isfinite(dz);
  return finite && (std::fabs(dx) >= kMinDirection || std::fabs(dy) >= kMinDirection ||
                    std::fabs(dz) >= kMinDirection);
}

inline WatertightRay PrepareWatertightRay(float ox, float oy, float oz, float dx, float dy,
                                          float dz) {
  const float o[3] = {ox, oy, oz};
  const float d[3] = {dx, dy, dz};
  WatertightRay r;
  // kz: dimension where |d| is maximal (first one on ties, so the choice is deterministic)
  const float ax = std::fabs(dx), ay = std::fabs(dy), az = std::fabs(dz);
  int kz = 0;
  if (ay > ax) kz = 1;
  if (az > (kz == 0 ? ax : ay)) kz = 2;
  int kx = kz + 1 == 3 ? 0 : kz + 1;
  int ky = kx + 1 == 3 ? 0 : kx + 1;
  // swap kx and ky to preserve the winding direction of triangles
  if (d[kz] < 0.0f) {
    const int tmp = kx;
    kx = ky;
    ky = tmp;
  }
  r.kx = kx;
  r.ky = ky;
  r.kz = kz;
  r.sx = d[kx] / d[kz];
  r.sy = d[ky] / d[kz];
  r.sz = 1.0f / d[kz];
  r.o[0] = o[kx];
  r.o[1] = o[ky];
  r.o[2] = o[kz];
  if (!RayIsValid(ox, oy, oz, dx, dy, dz)) r.sz = std::numeric_limits<float>::quiet_NaN();
  return r;
}

// max(|a|, |b|, |c|) as the SIMD kernels compute it (Max(Max(|a|, |b|), |c|)); inputs are
// never NaN where it is used (a NaN there makes t NaN, which fails the bounds first).
template <typename T>
inline T Max3Abs(T a, T b, T c) {
  const T ab = std::fabs(a) > std::fabs(b) ? std::fabs(a) : std::fabs(b);
  return ab > std::fabs(c) ? ab : std::fabs(c);
}

// gamma(n) = n u / (1 - n u), u = the unit roundoff of T (2^-24 for float, 2^-53 for double):
// the relative error of n roundings is at most gamma(n) (pbrt-v4 section 6.8.1). Constants, so
// every target compares against the same values.
template <typename T>
inline constexpr T WatertightGamma(int n) {
  constexpr T kUnitRoundoff = T(0.5) * std::numeric_limits<T>::epsilon();
  return (T(n) * kUnitRoundoff) / (T(1) - T(n) * kUnitRoundoff);
}

// Rounding bound of the watertight test's t numerator T = U Az' + V Bz' + W Cz' (pbrt-v4,
// section 6.8.7 "Robust triangle intersections"; Pharr, Jakob, Humphreys): to first order the
// computed t = T / det is within DeltaT / |det| of the exact t of the ray and the triangle.
// pbrt's terms with its three coordinate maxima replaced by one, m = max |x|, |y| (sheared) and
// |z| (translated, unscaled), so deltaX, deltaY = gamma(5) 2m, deltaE = (2 gamma(2) + 8
// gamma(5)) m^2, and DeltaT = 3 max_zs (2 gamma(3) max_e + deltaE) with max_zs = max |Sz z| and
// max_e >= max |U|, |V|, |W| (the float test passes |det|: inside, U, V, W share a sign, so
// |det| >= each). One m costs fewer operations than pbrt's maxXt, maxYt, maxZt (the bound only
// needs to be safe: the hits it cannot decide go to double) and is also safe where pbrt's code
// is not: it bounds the shear's error Sx z with the scaled z, too small when |d[kz]| > 1, as
// for shadow rays d = light - p. In T's precision, this exact operation order, no FMA: the
// SIMD kernels (tri_intersect-inl.h) repeat the float version op for op.
template <typename T>
inline constexpr T kWatertightBoundE = T(6) * WatertightGamma<T>(3);
template <typename T>
inline constexpr T kWatertightBoundM = T(3) * (T(2) * WatertightGamma<T>(2) +
                                               T(8) * WatertightGamma<T>(5));
template <typename T>
inline T WatertightDeltaT(T max_xyz, T max_zs, T max_e) {
  return max_zs * (kWatertightBoundE<T> * max_e + kWatertightBoundM<T> * (max_xyz * max_xyz));
}

// The float bound is loose for big triangles: ~100..1000 eps times the triangle's extent along
// the ray (0.03 in t for a ray 0.01 above the 2600-wide conference floor, whose true hit is at
// t = 0.016), too wide to drop every hit it cannot decide. This function redoes such hits in
// double from the same float inputs (vertices in the ray's (kx, ky, kz) order, origin, shear),
// with the same bound in double: true iff the hit is certainly in front of the origin (t >
// DeltaT / |det| in double, ~1e-9 of the float bound), false for hits behind it, at it, or
// parallel in double. Rare: only hits within the float bound of the
// origin get here (the paper's section 3.3 fallback, for t). Scalar on purpose: the SIMD
// kernels call it per lane, so every target decides alike.
bool WatertightAheadInDouble(float a0, float a1, float a2, float b0, float b1, float b2, float c0,
                             float c1, float c2, float o0, float o1, float o2, float sx, float sy,
                             float sz);

// The near-origin decision of IntersectWatertightPermuted for a hit (t > tmin >= 0) on a
// triangle that is not strictly ahead: recomputes the translated, sheared vertices with the
// test's operations; rejects (returns false) iff |T| <= DeltaT (WatertightDeltaT, with max_e =
// |det|) and the hit is not ahead in double; else writes *hit as the test does and returns
// true. Out of line and called in tail position, so that nothing is live across the call: the
// test keeps its size and register use in the scalar traversal loops.
bool WatertightHitNearOrigin(const WatertightRay& r, float a0, float a1, float a2, float b0,
                             float b1, float b2, float c0, float c1, float c2, float det, float tz,
                             float t, float v, float w, TriHit* hit);

// The watertight test on vertices already permuted into the ray's (kx, ky, kz) order.
// Accepts t in (tmin, tmax]; tmax must be finite (callers clamp +inf to FLT_MAX) so a
// float overflow never reports a hit at infinity. Backfaces are not culled. Exact in the
// paper's sense: a ray through a shared edge or vertex hits at least one of the triangles.
// Conservative at the origin (pbrt-v4 6.8.7): if tmin >= 0, a hit that rounding cannot tell
// from one behind the origin is rejected, so a ray spawned on a large triangle (vertices ~1e3
// away from an origin offset by ~1e-5, kernels/shade.h OffsetRayOrigin) and pointing away
// never re-hits it. Hits on triangles with every vertex strictly ahead of the origin along
// the ray's dominant axis kz, and hits with t > DeltaT / |det| (WatertightDeltaT in float;
// compared as |T| <= DeltaT, no division), are certain and kept as before; the others are
// decided in double (WatertightAheadInDouble), so only hits within ~1e-11 of the triangle's
// extent from the origin are lost, never a hit away from the origin: no holes (rays through
// shared edges and vertices are unaffected). With tmin < 0 (hits behind the origin wanted)
// nothing is rejected. NaN anywhere (ray, tmin, tmax) gives false.
inline bool IntersectWatertightPermuted(const WatertightRay& r, float a0, float a1, float a2,
                                        float b0, float b1, float b2, float c0, float c1,
                                        float c2, float tmin, float tmax, TriHit* hit) {
  // vertices relative to the ray origin
  const float az = a2 - r.o[2], bz = b2 - r.o[2], cz = c2 - r.o[2];
  // shear and scale: the ray becomes the +z axis through the origin
  const float ax = (a0 - r.o[0]) - r.sx * az;
  const float ay = (a1 - r.o[1]) - r.sy * az;
  const float bx = (b0 - r.o[0]) - r.sx * bz;
  const float by = (b1 - r.o[1]) - r.sy * bz;
  const float cx = (c0 - r.o[0]) - r.sx * cz;
  const float cy = (c1 - r.o[1]) - r.sy * cz;
  // scaled barycentrics: 2D edge functions of the projected edges
  float u = cx * by - cy * bx;
  float v = ax * cy - ay * cx;
  float w = bx * ay - by * ax;
  // an edge function of exactly 0 may be a rounding artifact: redo all three in double, where
  // the products of floats are exact (paper section 3.3)
  if (u == 0.0f || v == 0.0f || w == 0.0f) [[unlikely]] {
    u = static_cast<float>(double(cx) * double(by) - double(cy) * double(bx));
    v = static_cast<float>(double(ax) * double(cy) - double(ay) * double(cx));
    w = static_cast<float>(double(bx) * double(ay) - double(by) * double(ax));
  }
  // inside iff all three have the same sign (either winding)
  if ((u < 0.0f || v < 0.0f || w < 0.0f) && (u > 0.0f || v > 0.0f || w > 0.0f)) return false;
  const float det = u + v + w;
  if (det == 0.0f) return false;  // ray parallel to the plane, or a degenerate projection
  // scaled z of the vertices -> hit distance T / det
  const float saz = r.sz * az, sbz = r.sz * bz, scz = r.sz * cz;
  const float tz = u * saz + v * sbz + w * scz;
  const float t = tz / det;
  if (!(t > tmin && t <= tmax)) return false;  // NaN-safe: NaN fails both
  // t <= DeltaT / |det| may be a hit behind the origin (pbrt-v4 6.8.7): decided out of line.
  // Not needed if every vertex is strictly ahead along kz (Sz z > 0; exact signs: a float
  // difference is 0 only for equal inputs): then so is every point of the triangle, and only
  // t > 0 can meet it.
  if (tmin >= 0.0f && !(saz > 0.0f && sbz > 0.0f && scz > 0.0f)) [[unlikely]] {
    return WatertightHitNearOrigin(r, a0, a1, a2, b0, b1, b2, c0, c1, c2, det, tz, t, v, w, hit);
  }
  const float inv_det = 1.0f / det;
  hit->t = t;
  hit->u = v * inv_det;  // barycentric of vertex 1 (b)
  hit->v = w * inv_det;  // barycentric of vertex 2 (c)
  return true;
}

// The watertight test on triangle `id` of `tris` (the degenerate flag is not checked here:
// the grid never lists degenerate triangles; use IntersectTriangle below for that).
inline bool IntersectWatertight(const WatertightRay& r, const TriangleSoA& tris, size_t id,
                                float tmin, float tmax, TriHit* hit) {
  const int kx = r.kx, ky = r.ky, kz = r.kz;
  return IntersectWatertightPermuted(
      r, tris.p[0][kx][id], tris.p[0][ky][id], tris.p[0][kz][id], tris.p[1][kx][id],
      tris.p[1][ky][id], tris.p[1][kz][id], tris.p[2][kx][id], tris.p[2][ky][id],
      tris.p[2][kz][id], tmin, tmax, hit);
}

// Convenience for tests and one-off queries: the watertight test on three vertices given as
// xyz; tmax may be +inf. Degenerate triangles (IsDegenerateTriangle) never hit.
bool IntersectTriangle(const float p0[3], const float p1[3], const float p2[3], float ox,
                       float oy, float oz, float dx, float dy, float dz, float tmin, float tmax,
                       TriHit* hit);

// Moller-Trumbore ("Fast, Minimum Storage Ray/Triangle Intersection", 1997) in float, no
// epsilon: det == 0 rejects. Not watertight (rays through shared edges can miss both
// triangles); kept for comparison counts against the watertight test. t in (tmin, tmax].
bool IntersectMollerTrumbore(const float p0[3], const float p1[3], const float p2[3], float ox,
                             float oy, float oz, float dx, float dy, float dz, float tmin,
                             float tmax, TriHit* hit);

}  // namespace rs
