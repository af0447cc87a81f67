// SIMD ray/triangle tests over triangle bundles (1 ray x bundles, N rays x triangles) with
// dynamic dispatch, and their scalar oracles. Per-target code; foreach_target re-includes this
// file. The kernels themselves are in tri_intersect-inl.h, shared with SIMD traversal code.
#include "kernels/tri_intersect.h"

#include <cfloat>
#include <cstdint>

#undef HWY_TARGET_INCLUDE
#define HWY_TARGET_INCLUDE "kernels/tri_intersect.cc"
#include <hwy/foreach_target.h>  // IWYU pragma: keep
#include <hwy/highway.h>         // must follow foreach_target.h

#include "kernels/tri_intersect-inl.h"

HWY_BEFORE_NAMESPACE();
namespace rs {
namespace HWY_NAMESPACE {

// One out-of-line function per (test, any, width), so the exported function is only a switch
// and each loop is compiled on its own (registers, code layout).
template <TriTest kTest, bool kAny, size_t kLanes>
HWY_NOINLINE bool BundlesEntry(const PreparedRay& ray, const TriBundleSpan& tris, float tmin,
                               float tmax, ClosestHit* hit) {
  return BundlesT<kTest, kAny, /*kFma=*/false, kLanes>(ray, tris, tmin, tmax, hit);
}

template <TriTest kTest, bool kAny>
HWY_INLINE bool BundlesSwitch(const PreparedRay& ray, const TriBundleSpan& tris, float tmin,
                              float tmax, BundleWidth width, ClosestHit* hit) {
  switch (width) {
    case BundleWidth::kOne:
      return BundlesEntry<kTest, kAny, 4>(ray, tris, tmin, tmax, hit);
    case BundleWidth::kTwo:
      return BundlesEntry<kTest, kAny, 8>(ray, tris, tmin, tmax, hit);
    case BundleWidth::kFour:
      return BundlesEntry<kTest, kAny, 16>(ray, tris, tmin, tmax, hit);
    case BundleWidth::kAuto:
      break;
  }
  return BundlesEntry<kTest, kAny, kAutoBundleLanes>(ray, tris, tmin, tmax, hit);
}

bool IntersectBundles(const PreparedRay& ray, const TriBundleSpan& tris, float tmin, float tmax,
                      TriTest test, BundleWidth width, ClosestHit* hit) {
  if (test == TriTest::kWatertight) {
    return BundlesSwitch<TriTest::kWatertight, false>(ray, tris, tmin, tmax, width, hit);
  }
  return BundlesSwitch<TriTest::kMollerTrumbore, false>(ray, tris, tmin, tmax, width, hit);
}

bool OccludedBundles(const PreparedRay& ray, const TriBundleSpan& tris, float tmin, float tmax,
                     TriTest test, BundleWidth width) {
  if (test == TriTest::kWatertight) {
    return BundlesSwitch<TriTest::kWatertight, true>(ray, tris, tmin, tmax, width, nullptr);
  }
  return BundlesSwitch<TriTest::kMollerTrumbore, true>(ray, tris, tmin, tmax, width, nullptr);
}

void IntersectStream(const RayStreamView& rays, const TriBundleSpan& tris, TriTest test,
                     const HitStreamView& hits) {
  if (test == TriTest::kWatertight) {
    StreamT<TriTest::kWatertight>(rays, tris, hits);
  } else {
    StreamT<TriTest::kMollerTrumbore>(rays, tris, hits);
  }
}

}  // namespace HWY_NAMESPACE
}  // namespace rs
HWY_AFTER_NAMESPACE();

#if HWY_ONCE
namespace rs {

HWY_EXPORT(IntersectBundles);
HWY_EXPORT(OccludedBundles);
HWY_EXPORT(IntersectStream);

bool IntersectBundles(const PreparedRay& ray, const TriBundleSpan& tris, float tmin, float tmax,
                      TriTest test, BundleWidth width, ClosestHit* hit) {
  return HWY_DYNAMIC_DISPATCH(IntersectBundles)(ray, tris, tmin, tmax, test, width, hit);
}

bool OccludedBundles(const PreparedRay& ray, const TriBundleSpan& tris, float tmin, float tmax,
                     TriTest test, BundleWidth width) {
  return HWY_DYNAMIC_DISPATCH(OccludedBundles)(ray, tris, tmin, tmax, test, width);
}

void IntersectStream(const RayStreamView& rays, const TriBundleSpan& tris, TriTest test,
                     const HitStreamView& hits) {
  HWY_DYNAMIC_DISPATCH(IntersectStream)(rays, tris, test, hits);
}

namespace ref {
namespace {

// The scalar test of `test` on lane j of the span, t in (tmin, tmax] (tmax finite).
bool TestLane(const PreparedRay& ray, const TriBundleSpan& tris, size_t j, float tmin, float tmax,
              TriTest test, TriHit* th) {
  if (test == TriTest::kWatertight) {
    const WatertightRay& r = ray.wt;
    const int k[3] = {r.kx, r.ky, r.kz};
    float p[3][3];
    for (int v = 0; v < 3; ++v) {
      for (int a = 0; a < 3; ++a) p[v][a] = tris.Component(v, k[a])[j];
    }
    return IntersectWatertightPermuted(r, p[0][0], p[0][1], p[0][2], p[1][0], p[1][1], p[1][2],
                                       p[2][0], p[2][1], p[2][2], tmin, tmax, th);
  }
  float p[3][3];
  for (int v = 0; v < 3; ++v) {
    for (int a = 0; a < 3; ++a) p[v][a] = tris.Component(v, a)[j];
  }
  return IntersectMollerTrumbore(p[0], p[1], p[2], ray.o[0], ray.o[1], ray.o[2], ray.d[0], ray.d[1],
                                 ray.d[2], tmin, tmax, th);
}

}  // namespace

bool IntersectBundles(const PreparedRay& ray, const TriBundleSpan& tris, float tmin, float tmax,
                      TriTest test, ClosestHit* hit) {
  if (!ray.valid) return false;
  const float tmax_f = tmax > FLT_MAX ? FLT_MAX : tmax;  // NaN stays NaN: no hit
  float upper = hit->t < tmax_f ? hit->t : tmax_f;
  bool changed = false;
  for (size_t j = 0; j < tris.lanes(); ++j) {
    const int32_t id = tris.ids[j];
    if (id < 0) continue;
    TriHit th;
    if (!TestLane(ray, tris, j, tmin, upper, test, &th)) continue;
    // th.t <= upper <= hit->t: equal t needs a lower id (prim -1 = none)
    if (!(th.t < hit->t || uint32_t(id) < uint32_t(hit->prim))) continue;
    hit->t = upper = th.t;
    hit->u = th.u;
    hit->v = th.v;
    hit->prim = id;
    changed = true;
  }
  return changed;
}

bool OccludedBundles(const PreparedRay& ray, const TriBundleSpan& tris, float tmin, float tmax,
                     TriTest test) {
  if (!ray.valid) return false;
  const float tmax_f = tmax > FLT_MAX ? FLT_MAX : tmax;
  for (size_t j = 0; j < tris.lanes(); ++j) {
    TriHit th;
    if (tris.ids[j] >= 0 && TestLane(ray, tris, j, tmin, tmax_f, test, &th)) return true;
  }
  return false;
}

void IntersectStream(const RayStreamView& rays, const TriBundleSpan& tris, TriTest test,
                     const HitStreamView& hits) {
  for (size_t i = 0; i < rays.size; ++i) {
    const PreparedRay ray =
        PrepareRay(rays.ox[i], rays.oy[i], rays.oz[i], rays.dx[i], rays.dy[i], rays.dz[i]);
    ClosestHit h;
    h.t = hits.t[i];
    h.u = hits.u[i];
    h.v = hits.v[i];
    h.prim = hits.prim[i];
    if (!IntersectBundles(ray, tris, rays.tmin[i], rays.tmax[i], test, &h)) continue;
    hits.t[i] = h.t;
    hits.u[i] = h.u;
    hits.v[i] = h.v;
    hits.prim[i] = h.prim;
  }
}

}  // namespace ref
}  // namespace rs
#endif  // HWY_ONCE
