// Per-target ray/triangle kernels over triangle bundles (contracts in kernels/tri_intersect.h).
// In an -inl.h so that a SIMD traversal in its own foreach_target file can inline them per cell
// instead of paying a dynamic dispatch per cell: include it after <hwy/highway.h>.
#if defined(RS_KERNELS_TRI_INTERSECT_INL_H_) == defined(HWY_TARGET_TOGGLE)
#ifdef RS_KERNELS_TRI_INTERSECT_INL_H_
#undef RS_KERNELS_TRI_INTERSECT_INL_H_
#else
#define RS_KERNELS_TRI_INTERSECT_INL_H_
#endif

#include <hwy/highway.h>

#include <cfloat>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>

#include "kernels/tri_intersect.h"

HWY_BEFORE_NAMESPACE();
namespace rs {
namespace HWY_NAMESPACE {
namespace hn = hwy::HWY_NAMESPACE;

// Lanes of the widest float vector of this target (array bounds for the rare scalar paths).
inline constexpr size_t kTriMaxLanes = HWY_MAX_BYTES / sizeof(float);

// Edge functions U, V, W redone in double, for the lanes where one of them is exactly 0.0f: the
// scalar test's fallback (paper section 3.3), verbatim per lane, so results stay bit-identical.
// Only reached when some lane has an exact zero (rays through edges and vertices, NaN never),
// so a scalar loop over the lanes costs nothing in the common path.
template <class D, class V = hn::Vec<D>>
HWY_NOINLINE void WatertightEdgesInDouble(D d, V ax, V ay, V bx, V by, V cx, V cy, V* u, V* v,
                                          V* w) {
  HWY_ALIGN float x[9][kTriMaxLanes];
  hn::Store(ax, d, x[0]);
  hn::Store(ay, d, x[1]);
  hn::Store(bx, d, x[2]);
  hn::Store(by, d, x[3]);
  hn::Store(cx, d, x[4]);
  hn::Store(cy, d, x[5]);
  hn::Store(*u, d, x[6]);
  hn::Store(*v, d, x[7]);
  hn::Store(*w, d, x[8]);
  for (size_t i = 0; i < hn::Lanes(d); ++i) {
    if (!(x[6][i] == 0.0f || x[7][i] == 0.0f || x[8][i] == 0.0f)) continue;
    const double dax = x[0][i], day = x[1][i], dbx = x[2][i], dby = x[3][i];
    const double dcx = x[4][i], dcy = x[5][i];
    x[6][i] = static_cast<float>(dcx * dby - dcy * dbx);
    x[7][i] = static_cast<float>(dax * dcy - day * dcx);
    x[8][i] = static_cast<float>(dbx * day - dby * dax);
  }
  *u = hn::Load(d, x[6]);
  *v = hn::Load(d, x[7]);
  *w = hn::Load(d, x[8]);
}

// max(|a|, |b|, |c|) per lane, as rs::Max3Abs (kernels/triangle.h); inputs are never NaN on
// the lanes that use it.
template <class V>
HWY_INLINE V Max3Abs(V a, V b, V c) {
  return hn::Max(hn::Max(hn::Abs(a), hn::Abs(b)), hn::Abs(c));
}

// The scalar test's decision for hits near the origin (kernels/triangle.h, pbrt-v4 6.8.7), for
// the lanes of `straddles` (hits with tmin >= 0 on triangles not strictly ahead): returns the
// lanes it rejects, those with |T| <= DeltaT (WatertightDeltaT, op for op) that are not ahead
// in double (rs::WatertightAheadInDouble, verbatim per lane). The raw vertices come from
// `reload` (fills V[9] in the ray's (kx, ky, kz) order), and the translated and sheared ones
// are recomputed with the test's own operations (same values): keeping them live across the
// test cost 12 spills per vector in the common path (and `reload` is taken by value: by
// reference, its captures were stored on every call). Out of line: only vectors with a hit
// near the origin's plane get here (rays spawned on a triangle, big triangles near the origin).
template <bool kFma, class D, class Reload, class V = hn::Vec<D>>
HWY_NOINLINE hn::Mask<D> WatertightRejectNearOrigin(D d, hn::Mask<D> straddles, Reload reload, V o0,
                                                    V o1, V o2, V sx, V sy, V sz, V det, V tz) {
  V p[9];
  reload(p);
  const V az = hn::Sub(p[2], o2), bz = hn::Sub(p[5], o2), cz = hn::Sub(p[8], o2);
  V ax, ay, bx, by, cx, cy;
  if constexpr (kFma) {
    ax = hn::NegMulAdd(sx, az, hn::Sub(p[0], o0));
    ay = hn::NegMulAdd(sy, az, hn::Sub(p[1], o1));
    bx = hn::NegMulAdd(sx, bz, hn::Sub(p[3], o0));
    by = hn::NegMulAdd(sy, bz, hn::Sub(p[4], o1));
    cx = hn::NegMulAdd(sx, cz, hn::Sub(p[6], o0));
    cy = hn::NegMulAdd(sy, cz, hn::Sub(p[7], o1));
  } else {
    ax = hn::Sub(hn::Sub(p[0], o0), hn::Mul(sx, az));
    ay = hn::Sub(hn::Sub(p[1], o1), hn::Mul(sy, az));
    bx = hn::Sub(hn::Sub(p[3], o0), hn::Mul(sx, bz));
    by = hn::Sub(hn::Sub(p[4], o1), hn::Mul(sy, bz));
    cx = hn::Sub(hn::Sub(p[6], o0), hn::Mul(sx, cz));
    cy = hn::Sub(hn::Sub(p[7], o1), hn::Mul(sy, cz));
  }
  // DeltaT = max_zs (kE |det| + kM m^2); t > tmin >= 0, so t |det| <= DeltaT is |T| <= DeltaT
  const V max_z = Max3Abs(az, bz, cz);
  const V max_xyz = hn::Max(hn::Max(Max3Abs(ax, bx, cx), Max3Abs(ay, by, cy)), max_z);
  const V max_zs = hn::Mul(hn::Abs(sz), max_z);
  const V delta_t = hn::Mul(
      max_zs, hn::Add(hn::Mul(hn::Set(d, kWatertightBoundE<float>), hn::Abs(det)),
                      hn::Mul(hn::Set(d, kWatertightBoundM<float>), hn::Mul(max_xyz, max_xyz))));
  const auto unsure = hn::And(straddles, hn::Le(hn::Abs(tz), delta_t));
  if (hn::AllFalse(d, unsure)) return unsure;
  // the undecided lanes in double, as the scalar code
  const hn::RebindToSigned<D> di;
  HWY_ALIGN float x[15][kTriMaxLanes];
  for (int k = 0; k < 9; ++k) hn::Store(p[k], d, x[k]);
  const V ray[6] = {o0, o1, o2, sx, sy, sz};
  for (int k = 0; k < 6; ++k) hn::Store(ray[k], d, x[9 + k]);
  HWY_ALIGN int32_t lanes[kTriMaxLanes];
  hn::Store(hn::VecFromMask(di, hn::RebindMask(di, unsure)), di, lanes);  // -1: undecided
  for (size_t i = 0; i < hn::Lanes(d); ++i) {
    if (lanes[i] == 0) continue;
    const bool ahead = WatertightAheadInDouble(x[0][i], x[1][i], x[2][i], x[3][i], x[4][i], x[5][i],
                                               x[6][i], x[7][i], x[8][i], x[9][i], x[10][i],
                                               x[11][i], x[12][i], x[13][i], x[14][i]);
    lanes[i] = ahead ? 0 : -1;  // -1: behind (or at) the origin
  }
  return hn::RebindMask(d, hn::Ne(hn::Load(di, lanes), hn::Zero(di)));
}

// What the closest-hit code needs from a vector of watertight tests: t, and det, V, W for the
// barycentrics u = V / det, v = W / det of the winning lane only (deferred division).
template <class D>
struct WatertightLanes {
  hn::Vec<D> t, det, v, w;
};

// The watertight test (kernels/triangle.h, IntersectWatertightPermuted) on Lanes(d) pairs of
// ray and triangle, operation for operation, so each lane rounds exactly like the scalar code.
// a*, b*, c*: vertex components in the ray's (kx, ky, kz) order; o*: ray origin in that order;
// sx, sy, sz: shear; reload(V out[9]) gives a0..c2 again (only called for hits near the
// origin: recomputing beats keeping them live). Returns the hit mask for t in (tmin, tmax],
// without the hits the scalar test rejects as not certainly ahead of the origin (tmin >= 0,
// triangle not strictly ahead, t within the float bound WatertightDeltaT and not ahead in
// double); *out is valid only if the mask has a lane set.
// kFma fuses the shear and the t products (never the edge functions: U(b, c)
// must be the exact negation of U(c, b) for the triangle on the other side of an edge).
// The exported kernels use kFma = false: fusing saved only 4-8% per ray/triangle test on AVX2
// and AVX3 (bunny cells, 2 bundles per vector) and would make t, u, v differ from the scalar
// oracle in the last bits; without it every target is bit-identical to the scalar code.
template <bool kFma, class D, class Reload, class V = hn::Vec<D>>
HWY_INLINE hn::Mask<D> WatertightTest(D d, V a0, V a1, V a2, V b0, V b1, V b2, V c0, V c1, V c2,
                                      V o0, V o1, V o2, V sx, V sy, V sz, V tmin, V tmax,
                                      Reload reload, WatertightLanes<D>* out) {
  // vertices relative to the ray origin
  const V az = hn::Sub(a2, o2), bz = hn::Sub(b2, o2), cz = hn::Sub(c2, o2);
  // shear and scale: the ray becomes the +z axis through the origin
  V ax, ay, bx, by, cx, cy;
  if constexpr (kFma) {
    ax = hn::NegMulAdd(sx, az, hn::Sub(a0, o0));
    ay = hn::NegMulAdd(sy, az, hn::Sub(a1, o1));
    bx = hn::NegMulAdd(sx, bz, hn::Sub(b0, o0));
    by = hn::NegMulAdd(sy, bz, hn::Sub(b1, o1));
    cx = hn::NegMulAdd(sx, cz, hn::Sub(c0, o0));
    cy = hn::NegMulAdd(sy, cz, hn::Sub(c1, o1));
  } else {
    ax = hn::Sub(hn::Sub(a0, o0), hn::Mul(sx, az));
    ay = hn::Sub(hn::Sub(a1, o1), hn::Mul(sy, az));
    bx = hn::Sub(hn::Sub(b0, o0), hn::Mul(sx, bz));
    by = hn::Sub(hn::Sub(b1, o1), hn::Mul(sy, bz));
    cx = hn::Sub(hn::Sub(c0, o0), hn::Mul(sx, cz));
    cy = hn::Sub(hn::Sub(c1, o1), hn::Mul(sy, cz));
  }
  // scaled barycentrics: 2D edge functions of the projected edges (never fused)
  V u = hn::Sub(hn::Mul(cx, by), hn::Mul(cy, bx));
  V v = hn::Sub(hn::Mul(ax, cy), hn::Mul(ay, cx));
  V w = hn::Sub(hn::Mul(bx, ay), hn::Mul(by, ax));
  const V zero = hn::Zero(d);
  // an exact 0 may be a rounding artifact: those lanes are redone in double (rare branch)
  const auto any_zero = hn::Or(hn::Or(hn::Eq(u, zero), hn::Eq(v, zero)), hn::Eq(w, zero));
  if (HWY_UNLIKELY(!hn::AllFalse(d, any_zero))) {
    WatertightEdgesInDouble(d, ax, ay, bx, by, cx, cy, &u, &v, &w);
  }
  // inside iff the signs do not disagree (either winding); det = 0: parallel or degenerate
  const auto neg = hn::Or(hn::Or(hn::Lt(u, zero), hn::Lt(v, zero)), hn::Lt(w, zero));
  const auto pos = hn::Or(hn::Or(hn::Gt(u, zero), hn::Gt(v, zero)), hn::Gt(w, zero));
  const V det = hn::Add(hn::Add(u, v), w);
  auto hit = hn::AndNot(hn::And(neg, pos), hn::Ne(det, zero));
  if (hn::AllFalse(d, hit)) return hit;  // most pairs miss: skip the division
  // scaled z of the vertices -> T = U Az + V Bz + W Cz; t = T / det (NaN fails both bounds)
  const V saz = hn::Mul(sz, az), sbz = hn::Mul(sz, bz), scz = hn::Mul(sz, cz);
  V tz;
  if constexpr (kFma) {
    tz = hn::MulAdd(w, scz, hn::MulAdd(v, sbz, hn::Mul(u, saz)));
  } else {
    tz = hn::Add(hn::Add(hn::Mul(u, saz), hn::Mul(v, sbz)), hn::Mul(w, scz));
  }
  const V t = hn::Div(tz, det);
  hit = hn::And(hit, hn::And(hn::Gt(t, tmin), hn::Le(t, tmax)));
  // conservative at the origin (pbrt-v4 6.8.7), as the scalar test: where tmin >= 0 and the
  // triangle is not strictly ahead (some Sz z <= 0; these signs are exact), a hit within the
  // bound may lie behind the origin and is decided out of line. Most hits have every vertex
  // ahead: 4 ops and a branch here.
  const auto straddles =
      hn::And(hit, hn::And(hn::Ge(tmin, zero), hn::Le(hn::Min(hn::Min(saz, sbz), scz), zero)));
  if (HWY_UNLIKELY(!hn::AllFalse(d, straddles))) {
    hit = hn::AndNot(
        WatertightRejectNearOrigin<kFma>(d, straddles, reload, o0, o1, o2, sx, sy, sz, det, tz),
        hit);
  }
  out->t = t;
  out->det = det;
  out->v = v;
  out->w = w;
  return hit;
}

template <class D>
struct MollerLanes {
  hn::Vec<D> t, u, v;
};

// Moller-Trumbore (kernels/triangle.h, IntersectMollerTrumbore) on Lanes(d) pairs, operation
// for operation (one Div per vector for 1/det, as the scalar code). p*: vertex 0; e1*, e2*:
// p1 - p0, p2 - p0. The ray's validity is the caller's business (RayIsValid).
template <class D, class V = hn::Vec<D>>
HWY_INLINE hn::Mask<D> MollerTest(D d, V p0x, V p0y, V p0z, V e1x, V e1y, V e1z, V e2x, V e2y,
                                  V e2z, V ox, V oy, V oz, V dx, V dy, V dz, V tmin, V tmax,
                                  MollerLanes<D>* out) {
  const V zero = hn::Zero(d), one = hn::Set(d, 1.0f);
  // pvec = d x e2; det = e1 . pvec; 0, +-inf or NaN: no hit
  const V px = hn::Sub(hn::Mul(dy, e2z), hn::Mul(dz, e2y));
  const V py = hn::Sub(hn::Mul(dz, e2x), hn::Mul(dx, e2z));
  const V pz = hn::Sub(hn::Mul(dx, e2y), hn::Mul(dy, e2x));
  const V det = hn::Add(hn::Add(hn::Mul(e1x, px), hn::Mul(e1y, py)), hn::Mul(e1z, pz));
  auto hit = hn::And(hn::Ne(det, zero),
                     hn::Lt(hn::Abs(det), hn::Set(d, std::numeric_limits<float>::infinity())));
  // s = o - p0; u = (s . pvec) / det in [0, 1]
  const V inv_det = hn::Div(one, det);
  const V sx = hn::Sub(ox, p0x), sy = hn::Sub(oy, p0y), sz = hn::Sub(oz, p0z);
  const V u = hn::Mul(hn::Add(hn::Add(hn::Mul(sx, px), hn::Mul(sy, py)), hn::Mul(sz, pz)), inv_det);
  hit = hn::And(hit, hn::And(hn::Ge(u, zero), hn::Le(u, one)));
  if (hn::AllFalse(d, hit)) return hit;
  // q = s x e1; v = (d . q) / det >= 0, u + v <= 1; t = (e2 . q) / det in (tmin, tmax]
  const V qx = hn::Sub(hn::Mul(sy, e1z), hn::Mul(sz, e1y));
  const V qy = hn::Sub(hn::Mul(sz, e1x), hn::Mul(sx, e1z));
  const V qz = hn::Sub(hn::Mul(sx, e1y), hn::Mul(sy, e1x));
  const V v = hn::Mul(hn::Add(hn::Add(hn::Mul(dx, qx), hn::Mul(dy, qy)), hn::Mul(dz, qz)), inv_det);
  hit = hn::And(hit, hn::And(hn::Ge(v, zero), hn::Le(hn::Add(u, v), one)));
  const V t =
      hn::Mul(hn::Add(hn::Add(hn::Mul(e2x, qx), hn::Mul(e2y, qy)), hn::Mul(e2z, qz)), inv_det);
  hit = hn::And(hit, hn::And(hn::Gt(t, tmin), hn::Le(t, tmax)));
  out->t = t;
  out->u = u;
  out->v = v;
  return hit;
}

// ---------------------------------------------------------------------------------------------
// 1 ray x bundles

// Per-call state of the 1-ray kernels. The watertight test reads the vertex components in the
// ray's (kx, ky, kz) order: the permutation is pure address arithmetic (axis a of vertex v is
// at axis[a] + v * vertex_stride), so there are no per-ray copies of the triangles and no
// shuffles. Three named pointers rather than an array of nine: GCC's SLP vectorizer turned the
// array's address arithmetic into zmm multiplies (vpmullq) in the AVX3 prologue.
struct BundleCall {
  const float* axis0;  // vertex 0, axis kx (Moller-Trumbore: x)
  const float* axis1;  // vertex 0, axis ky (y)
  const float* axis2;  // vertex 0, axis kz (z)
  size_t vertex_stride;
  const int32_t* ids;
  float tmin;
  float upper;  // min(tmax, best t so far), finite
};

// True if lane j (t, id) beats the closest hit so far: t < hit.t, or equal t and a lower id
// (prim -1 = none, counts as +inf through the unsigned compare).
HWY_INLINE bool Beats(float t, int32_t id, const ClosestHit& hit) {
  return t < hit.t || uint32_t(id) < uint32_t(hit.prim);
}

// Tests the Lanes(d) triangles from lane `i` of the span. Closest hit: among the hit lanes, the
// smallest t, then the lowest id, is compared with *hit (Beats); returns true iff *hit changed.
// Any hit: returns true iff some lane hits.
template <TriTest kTest, bool kAny, bool kFma, class D>
HWY_INLINE bool BundleGroup(D d, const PreparedRay& ray, BundleCall* call, size_t i,
                            ClosestHit* hit) {
  using V = hn::Vec<D>;
  const float* p0 = call->axis0 + i;
  const float* p1 = call->axis1 + i;
  const float* p2 = call->axis2 + i;
  const size_t vs = call->vertex_stride;
  const V tmin = hn::Set(d, call->tmin), tmax = hn::Set(d, call->upper);
  hn::Mask<D> m;
  WatertightLanes<D> wt;
  MollerLanes<D> mt;
  if constexpr (kTest == TriTest::kWatertight) {
    // two captures, passed in registers: more (the four pointers) were stored to the stack on
    // every call
    const auto reload = [call, i](V* v) {
      const D dr;
      const size_t stride = call->vertex_stride;
      for (size_t k = 0; k < 3; ++k) {
        v[3 * k + 0] = hn::LoadU(dr, call->axis0 + i + k * stride);
        v[3 * k + 1] = hn::LoadU(dr, call->axis1 + i + k * stride);
        v[3 * k + 2] = hn::LoadU(dr, call->axis2 + i + k * stride);
      }
    };
    m = WatertightTest<kFma>(
        d, hn::LoadU(d, p0), hn::LoadU(d, p1), hn::LoadU(d, p2), hn::LoadU(d, p0 + vs),
        hn::LoadU(d, p1 + vs), hn::LoadU(d, p2 + vs), hn::LoadU(d, p0 + 2 * vs),
        hn::LoadU(d, p1 + 2 * vs), hn::LoadU(d, p2 + 2 * vs), hn::Set(d, ray.wt.o[0]),
        hn::Set(d, ray.wt.o[1]), hn::Set(d, ray.wt.o[2]), hn::Set(d, ray.wt.sx),
        hn::Set(d, ray.wt.sy), hn::Set(d, ray.wt.sz), tmin, tmax, reload, &wt);
  } else {
    const V p0x = hn::LoadU(d, p0), p0y = hn::LoadU(d, p1), p0z = hn::LoadU(d, p2);
    m = MollerTest(d, p0x, p0y, p0z, hn::Sub(hn::LoadU(d, p0 + vs), p0x),
                   hn::Sub(hn::LoadU(d, p1 + vs), p0y), hn::Sub(hn::LoadU(d, p2 + vs), p0z),
                   hn::Sub(hn::LoadU(d, p0 + 2 * vs), p0x), hn::Sub(hn::LoadU(d, p1 + 2 * vs), p0y),
                   hn::Sub(hn::LoadU(d, p2 + 2 * vs), p0z), hn::Set(d, ray.o[0]),
                   hn::Set(d, ray.o[1]), hn::Set(d, ray.o[2]), hn::Set(d, ray.d[0]),
                   hn::Set(d, ray.d[1]), hn::Set(d, ray.d[2]), tmin, tmax, &mt);
  }
  if (hn::AllFalse(d, m)) return false;
  if constexpr (kAny) {
    return true;
  } else {
    const V t = kTest == TriTest::kWatertight ? wt.t : mt.t;
    // smallest t among the hit lanes (at least one, so never the +inf filler: EMU128's
    // MinOfLanes starts from FLT_MAX), then the lowest id among those
    const V t_hit = hn::IfThenElse(m, t, hn::Set(d, std::numeric_limits<float>::infinity()));
    const auto at_min = hn::And(m, hn::Eq(t_hit, hn::MinOfLanes(d, t_hit)));
    const hn::RebindToSigned<D> di;
    const auto id = hn::LoadU(di, call->ids + i);
    const auto id_min = hn::IfThenElse(hn::RebindMask(di, at_min), id,
                                       hn::Set(di, std::numeric_limits<int32_t>::max()));
    const size_t j =
        hn::FindKnownFirstTrue(d, hn::RebindMask(d, hn::Eq(id_min, hn::MinOfLanes(di, id_min))));
    const float tj = hn::ExtractLane(t, j);
    const int32_t idj = hn::ExtractLane(id, j);
    if (!Beats(tj, idj, *hit)) return false;
    hit->t = tj;
    hit->prim = idj;
    if constexpr (kTest == TriTest::kWatertight) {
      const float inv_det = 1.0f / hn::ExtractLane(wt.det, j);  // as the scalar code
      hit->u = hn::ExtractLane(wt.v, j) * inv_det;
      hit->v = hn::ExtractLane(wt.w, j) * inv_det;
    } else {
      hit->u = hn::ExtractLane(mt.u, j);
      hit->v = hn::ExtractLane(mt.v, j);
    }
    call->upper = tj;
    return true;
  }
}

// 1 ray x all bundles of a span: groups of kMaxLanes triangles (capped to the target's vector
// width), then 8, then 4 for the rest (1 at a time on the SCALAR target). Returns true iff
// *hit changed (closest) or some triangle is hit (any; hit may be null).
template <TriTest kTest, bool kAny, bool kFma, size_t kMaxLanes>
HWY_INLINE bool BundlesT(const PreparedRay& ray, const TriBundleSpan& tris, float tmin, float tmax,
                         ClosestHit* hit) {
  if (!ray.valid || tris.count == 0) return false;
  // +inf -> FLT_MAX (an overflowed t = inf is never a hit); NaN stays NaN and fails below
  const float tmax_f = tmax > FLT_MAX ? FLT_MAX : tmax;
  BundleCall call;
  call.tmin = tmin;
  call.upper = (!kAny && hit->t < tmax_f) ? hit->t : tmax_f;
  if (!(tmin < call.upper)) return false;  // empty (tmin, upper]: no t can pass
  call.ids = tris.ids;
  const size_t stride = tris.stride();
  call.vertex_stride = 3 * stride;
  if constexpr (kTest == TriTest::kWatertight) {
    call.axis0 = tris.vertices + size_t(ray.wt.kx) * stride;
    call.axis1 = tris.vertices + size_t(ray.wt.ky) * stride;
    call.axis2 = tris.vertices + size_t(ray.wt.kz) * stride;
  } else {
    call.axis0 = tris.vertices;
    call.axis1 = tris.vertices + stride;
    call.axis2 = tris.vertices + 2 * stride;
  }
  ClosestHit dummy;
  ClosestHit* out = kAny ? &dummy : hit;
  const size_t lanes = tris.lanes();
  bool found = false;
  size_t i = 0;
  if constexpr (kMaxLanes >= 16) {
    const hn::CappedTag<float, 16> d16;
    for (; i + hn::Lanes(d16) <= lanes; i += hn::Lanes(d16)) {
      found |= BundleGroup<kTest, kAny, kFma>(d16, ray, &call, i, out);
      if (kAny && found) return true;
    }
  }
  if constexpr (kMaxLanes >= 8) {
    const hn::CappedTag<float, 8> d8;
    for (; i + hn::Lanes(d8) <= lanes; i += hn::Lanes(d8)) {
      found |= BundleGroup<kTest, kAny, kFma>(d8, ray, &call, i, out);
      if (kAny && found) return true;
    }
  }
  const hn::CappedTag<float, 4> d4;
  for (; i < lanes; i += hn::Lanes(d4)) {
    found |= BundleGroup<kTest, kAny, kFma>(d4, ray, &call, i, out);
    if (kAny && found) return true;
  }
  return found;
}

// The width kAuto picks on this target: the widest vector, up to 4 bundles. Measured on the
// bunny's grid cells (warm caches, ns per ray/triangle test, AVX3 / AVX2): 1 bundle per vector
// 1.9 / 2.0, 2 bundles 1.3 / 1.3, 4 bundles 1.1 / (= 2) in cells of 46 triangles, and
// 3.0 / 3.6, 2.6 / 2.6, 2.5 / (= 2) in cells of 11 (scalar DDA loop: 12-16).
inline constexpr size_t kAutoBundleLanes = HWY_MAX_BYTES >= 64 ? 16 : HWY_MAX_BYTES >= 32 ? 8 : 4;

template <TriTest kTest, bool kAny, bool kFma = false>
HWY_INLINE bool BundlesWidth(const PreparedRay& ray, const TriBundleSpan& tris, float tmin,
                             float tmax, BundleWidth width, ClosestHit* hit) {
  switch (width) {
    case BundleWidth::kOne:
      return BundlesT<kTest, kAny, kFma, 4>(ray, tris, tmin, tmax, hit);
    case BundleWidth::kTwo:
      return BundlesT<kTest, kAny, kFma, 8>(ray, tris, tmin, tmax, hit);
    case BundleWidth::kFour:
      return BundlesT<kTest, kAny, kFma, 16>(ray, tris, tmin, tmax, hit);
    case BundleWidth::kAuto:
      break;
  }
  return BundlesT<kTest, kAny, kFma, kAutoBundleLanes>(ray, tris, tmin, tmax, hit);
}

// ---------------------------------------------------------------------------------------------
// N rays x 1 triangle

// A vector of rays set up for the watertight test: origin and shear in each lane's own
// (kx, ky, kz) order, plus the lane masks that pick a broadcast triangle's components in that
// order (k?0: axis is x, k?1: axis is y, else z).
template <class D>
struct StreamRays {
  using V = hn::Vec<D>;
  using M = hn::Mask<D>;
  V o0, o1, o2, sx, sy, sz;
  M kx0, kx1, ky0, ky1, kz0, kz1;
};

// x, y, z -> the component on the axis given by (is_x, is_y) per lane: 2 blends.
template <class V, class M>
HWY_INLINE V PickAxis(M is_x, M is_y, V x, V y, V z) {
  return hn::IfThenElse(is_x, x, hn::IfThenElse(is_y, y, z));
}

// RayIsValid per lane of `live` (all six finite: NaN fails Lt; some |d| >= kMinDirection), and
// tmin < tmax (else (tmin, tmax] is empty, or NaN).
template <class D, class V = hn::Vec<D>>
HWY_INLINE hn::Mask<D> StreamRayValid(D d, hn::Mask<D> live, V ox, V oy, V oz, V dx, V dy, V dz,
                                      V tmin, V tmax) {
  const V inf = hn::Set(d, std::numeric_limits<float>::infinity());
  const V min_dir = hn::Set(d, kMinDirection);
  const V adx = hn::Abs(dx), ady = hn::Abs(dy), adz = hn::Abs(dz);
  auto valid = hn::And(live, hn::And(hn::And(hn::Lt(hn::Abs(ox), inf), hn::Lt(hn::Abs(oy), inf)),
                                     hn::Lt(hn::Abs(oz), inf)));
  valid = hn::And(valid, hn::And(hn::And(hn::Lt(adx, inf), hn::Lt(ady, inf)), hn::Lt(adz, inf)));
  valid = hn::And(
      valid, hn::Or(hn::Or(hn::Ge(adx, min_dir), hn::Ge(ady, min_dir)), hn::Ge(adz, min_dir)));
  return hn::And(valid, hn::Lt(tmin, tmax));
}

// The axis of the largest |d| per lane (first on ties, as PrepareWatertightRay's kz): *k0,
// *k1 = the lanes where it is x, y (z elsewhere).
template <class D, class V = hn::Vec<D>>
HWY_INLINE void LargestAxis(D d, V dx, V dy, V dz, hn::Mask<D>* k0, hn::Mask<D>* k1) {
  const V adx = hn::Abs(dx), ady = hn::Abs(dy), adz = hn::Abs(dz);
  const auto y_gt_x = hn::Gt(ady, adx);
  const auto k2 = hn::Gt(adz, hn::IfThenElse(y_gt_x, ady, adx));
  *k1 = hn::AndNot(k2, y_gt_x);
  *k0 = hn::Not(hn::Or(y_gt_x, k2));
  (void)d;
}

// The watertight setup of a vector of rays, PrepareWatertightRay lane by lane: kz = axis of the
// largest |d| (first on ties), kx = kz + 1, ky = kx + 1 (mod 3), swapped where d[kz] < 0 to keep
// the winding. Returns true if every lane of `valid` has the same (kx, ky, kz), given in k[3]
// (coherent rays: the triangle can be broadcast without blends).
template <class D, class V = hn::Vec<D>>
HWY_INLINE bool SetupStreamRays(D d, V ox, V oy, V oz, V dx, V dy, V dz, hn::Mask<D> valid,
                                StreamRays<D>* r, int k[3]) {
  const V zero = hn::Zero(d), one = hn::Set(d, 1.0f);
  hn::Mask<D> kz0, kz1;
  LargestAxis(d, dx, dy, dz, &kz0, &kz1);
  const auto kz2 = hn::Not(hn::Or(kz0, kz1));
  const V dkz = PickAxis(kz0, kz1, dx, dy, dz);
  const auto swap = hn::Lt(dkz, zero);
  const auto keep = hn::Not(swap);
  r->kz0 = kz0;
  r->kz1 = kz1;
  // unswapped kx = kz + 1: kz = 2 -> 0, kz = 0 -> 1; swapped kx = kz + 2: kz = 1 -> 0, ...
  r->kx0 = hn::Or(hn::And(kz2, keep), hn::And(kz1, swap));
  r->kx1 = hn::Or(hn::And(kz0, keep), hn::And(kz2, swap));
  r->ky0 = hn::Or(hn::And(kz1, keep), hn::And(kz2, swap));
  r->ky1 = hn::Or(hn::And(kz2, keep), hn::And(kz0, swap));
  const V dkx = PickAxis(r->kx0, r->kx1, dx, dy, dz);
  const V dky = PickAxis(r->ky0, r->ky1, dx, dy, dz);
  r->o0 = PickAxis(r->kx0, r->kx1, ox, oy, oz);
  r->o1 = PickAxis(r->ky0, r->ky1, ox, oy, oz);
  r->o2 = PickAxis(kz0, kz1, ox, oy, oz);
  r->sx = hn::Div(dkx, dkz);
  r->sy = hn::Div(dky, dkz);
  r->sz = hn::Div(one, dkz);
  const auto dead = hn::Not(valid);
  int kz = -1;
  if (hn::AllTrue(d, hn::Or(kz0, dead))) kz = 0;
  if (hn::AllTrue(d, hn::Or(kz1, dead))) kz = 1;
  if (hn::AllTrue(d, hn::Or(kz2, dead))) kz = 2;
  const bool all_swap = hn::AllTrue(d, hn::Or(swap, dead));
  const bool no_swap = hn::AllTrue(d, hn::Or(keep, dead));
  if (kz < 0 || !(all_swap || no_swap)) return false;
  int kx = kz + 1 == 3 ? 0 : kz + 1;
  int ky = kx + 1 == 3 ? 0 : kx + 1;
  if (all_swap) {
    const int tmp = kx;
    kx = ky;
    ky = tmp;
  }
  k[0] = kx;
  k[1] = ky;
  k[2] = kz;
  return true;
}

// Closest hit so far of a vector of rays (registers; stored once per vector of rays).
// Watertight: (a, b, w) = (det, V, W) of the winner, divided once at the end; Moller-Trumbore:
// (a, b) = (u, v). changed: lanes whose hit must be written back.
template <class D>
struct StreamBest {
  hn::Vec<D> t, a, b, w;
  hn::Vec<hn::RebindToSigned<D>> prim;
  hn::Mask<D> changed;
};

// Folds one triangle's hit mask into the running best of a vector of rays (the rule of
// IntersectBundles: t <= best t was already required; equal t needs a lower id).
template <TriTest kTest, class D>
HWY_INLINE void StreamUpdate(D d, hn::Mask<D> m, int32_t id, const WatertightLanes<D>& wt,
                             const MollerLanes<D>& mt, StreamBest<D>* best) {
  const hn::RebindToSigned<D> di;
  const auto t = kTest == TriTest::kWatertight ? wt.t : mt.t;
  const auto idv = hn::Set(di, id);
  const auto lower_id = hn::Or(hn::Lt(best->prim, hn::Zero(di)), hn::Lt(idv, best->prim));
  const auto beats =
      hn::Or(hn::Lt(t, best->t), hn::And(hn::Eq(t, best->t), hn::RebindMask(d, lower_id)));
  m = hn::And(m, beats);
  if (hn::AllFalse(d, m)) return;
  best->t = hn::IfThenElse(m, t, best->t);
  best->prim = hn::IfThenElse(hn::RebindMask(di, m), idv, best->prim);
  if constexpr (kTest == TriTest::kWatertight) {
    best->a = hn::IfThenElse(m, wt.det, best->a);
    best->b = hn::IfThenElse(m, wt.v, best->b);
    best->w = hn::IfThenElse(m, wt.w, best->w);
  } else {
    best->a = hn::IfThenElse(m, mt.u, best->a);
    best->b = hn::IfThenElse(m, mt.v, best->b);
  }
  best->changed = hn::Or(best->changed, m);
}

// The watertight test of one vector of rays against every triangle of the span. kUniform: all
// valid lanes share (kx, ky, kz), so the triangle is broadcast from the permuted component
// pointers `perm`; otherwise each lane picks its components with 6 blends per vertex.
template <bool kUniform, bool kFma, class D>
HWY_INLINE void StreamWatertight(D d, const StreamRays<D>& r, hn::Mask<D> valid, hn::Vec<D> tmin,
                                 hn::Vec<D> tmax, const TriBundleSpan& tris,
                                 const float* const perm[9], StreamBest<D>* best) {
  using V = hn::Vec<D>;
  const size_t lanes = tris.lanes();
  MollerLanes<D> unused;
  for (size_t j = 0; j < lanes; ++j) {
    const int32_t id = tris.ids[j];
    if (id < 0) continue;  // padding lane
    const auto load = [&r, &tris, perm, j](V* p) {
      const D d;
      if constexpr (kUniform) {
        for (int c = 0; c < 9; ++c) p[c] = hn::Set(d, perm[c][j]);
      } else {
        for (int vtx = 0; vtx < 3; ++vtx) {
          const V x = hn::Set(d, tris.Component(vtx, 0)[j]);
          const V y = hn::Set(d, tris.Component(vtx, 1)[j]);
          const V z = hn::Set(d, tris.Component(vtx, 2)[j]);
          p[3 * vtx + 0] = PickAxis(r.kx0, r.kx1, x, y, z);
          p[3 * vtx + 1] = PickAxis(r.ky0, r.ky1, x, y, z);
          p[3 * vtx + 2] = PickAxis(r.kz0, r.kz1, x, y, z);
        }
      }
    };
    V p[9];
    load(p);
    // upper bound: min(tmax, best t); ties are settled by StreamUpdate
    const V upper = hn::IfThenElse(hn::Lt(best->t, tmax), best->t, tmax);
    WatertightLanes<D> wt;
    auto m = WatertightTest<kFma>(d, p[0], p[1], p[2], p[3], p[4], p[5], p[6], p[7], p[8], r.o0,
                                  r.o1, r.o2, r.sx, r.sy, r.sz, tmin, upper, load, &wt);
    m = hn::And(m, valid);
    if (hn::AllFalse(d, m)) continue;
    StreamUpdate<TriTest::kWatertight>(d, m, id, wt, unused, best);
  }
}

// N rays x each triangle of `tris` (see IntersectStream in tri_intersect.h).
template <TriTest kTest, bool kFma = false>
HWY_INLINE void StreamT(const RayStreamView& rays, const TriBundleSpan& tris,
                        const HitStreamView& hits) {
  using D = hn::ScalableTag<float>;
  const D d;
  const hn::RebindToSigned<D> di;
  using V = hn::Vec<D>;
  static_assert(HWY_MAX_BYTES <= kStreamAlign, "stream padding too small");
  HWY_DASSERT(hits.size == rays.size);
  const size_t n = hn::Lanes(d);
  const V zero = hn::Zero(d), one = hn::Set(d, 1.0f);
  const V flt_max = hn::Set(d, FLT_MAX);
  const size_t lanes = tris.lanes();
  for (size_t i = 0; i < rays.size; i += n) {
    const auto live = hn::FirstN(d, rays.size - i);  // padded: whole-vector loads are safe
    const V ox = hn::Load(d, rays.ox + i), oy = hn::Load(d, rays.oy + i);
    const V oz = hn::Load(d, rays.oz + i), dx = hn::Load(d, rays.dx + i);
    const V dy = hn::Load(d, rays.dy + i), dz = hn::Load(d, rays.dz + i);
    const V tmin = hn::Load(d, rays.tmin + i), tmax = hn::Load(d, rays.tmax + i);
    // +inf -> FLT_MAX as in the scalar tests; NaN stays NaN (no hit)
    const V tmax_f = hn::IfThenElse(hn::Gt(tmax, flt_max), flt_max, tmax);
    const auto valid = StreamRayValid(d, live, ox, oy, oz, dx, dy, dz, tmin, tmax_f);
    if (hn::AllFalse(d, valid)) continue;

    StreamBest<D> best;
    best.t = hn::Load(d, hits.t + i);
    best.prim = hn::Load(di, hits.prim + i);
    best.a = best.b = best.w = zero;
    best.changed = hn::Lt(zero, zero);  // all false

    if constexpr (kTest == TriTest::kWatertight) {
      StreamRays<D> r;
      int k[3];
      if (SetupStreamRays(d, ox, oy, oz, dx, dy, dz, valid, &r, k)) {
        const float* perm[9];
        for (int vtx = 0; vtx < 3; ++vtx) {
          for (int a = 0; a < 3; ++a) perm[3 * vtx + a] = tris.Component(vtx, k[a]);
        }
        StreamWatertight<true, kFma>(d, r, valid, tmin, tmax_f, tris, perm, &best);
      } else {
        StreamWatertight<false, kFma>(d, r, valid, tmin, tmax_f, tris, nullptr, &best);
      }
      if (hn::AllFalse(d, best.changed)) continue;
      // deferred division, once per vector of rays: u = V / det, v = W / det (scalar order)
      const V inv_det = hn::Div(one, best.a);
      best.a = hn::Mul(best.b, inv_det);
      best.b = hn::Mul(best.w, inv_det);
    } else {
      WatertightLanes<D> unused;
      const float* p[9];
      for (int vtx = 0; vtx < 3; ++vtx) {
        for (int a = 0; a < 3; ++a) p[3 * vtx + a] = tris.Component(vtx, a);
      }
      for (size_t j = 0; j < lanes; ++j) {
        const int32_t id = tris.ids[j];
        if (id < 0) continue;  // padding lane
        // p0 and the edges once per triangle, in scalar float: the same roundings as the
        // scalar test's e1 = p1 - p0, e2 = p2 - p0
        const float p0[3] = {p[0][j], p[1][j], p[2][j]};
        const V e1x = hn::Set(d, p[3][j] - p0[0]), e1y = hn::Set(d, p[4][j] - p0[1]);
        const V e1z = hn::Set(d, p[5][j] - p0[2]), e2x = hn::Set(d, p[6][j] - p0[0]);
        const V e2y = hn::Set(d, p[7][j] - p0[1]), e2z = hn::Set(d, p[8][j] - p0[2]);
        const V upper = hn::IfThenElse(hn::Lt(best.t, tmax_f), best.t, tmax_f);
        MollerLanes<D> mt;
        auto m = MollerTest(d, hn::Set(d, p0[0]), hn::Set(d, p0[1]), hn::Set(d, p0[2]), e1x, e1y,
                            e1z, e2x, e2y, e2z, ox, oy, oz, dx, dy, dz, tmin, upper, &mt);
        m = hn::And(m, valid);
        if (hn::AllFalse(d, m)) continue;
        StreamUpdate<TriTest::kMollerTrumbore>(d, m, id, unused, mt, &best);
      }
      if (hn::AllFalse(d, best.changed)) continue;
    }
    // write back: changed lanes are live, so padding lanes get their own values again
    const auto changed = best.changed;
    hn::Store(hn::IfThenElse(changed, best.t, hn::Load(d, hits.t + i)), d, hits.t + i);
    hn::Store(hn::IfThenElse(changed, best.a, hn::Load(d, hits.u + i)), d, hits.u + i);
    hn::Store(hn::IfThenElse(changed, best.b, hn::Load(d, hits.v + i)), d, hits.v + i);
    hn::Store(best.prim, di, hits.prim + i);
  }
}

}  // namespace HWY_NAMESPACE
}  // namespace rs
HWY_AFTER_NAMESPACE();

#endif  // RS_KERNELS_TRI_INTERSECT_INL_H_
