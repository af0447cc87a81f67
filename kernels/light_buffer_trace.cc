// Light buffer query (kernels/light_buffer.h), per Highway target, a vector of rays at a time:
// validity, the watertight setup and each ray's cube cell in SIMD; then, per distinct cell among
// the vector's rays, that cell's list front to back, one triangle broadcast against the rays of
// that cell (N rays x 1 triangle, the watertight test of kernels/tri_intersect-inl.h); a lane
// stops at its first hit or at the first reference beyond its reach. Per-target code;
// foreach_target re-includes this file.
#include "kernels/light_buffer.h"

#include <cfloat>
#include <cmath>
#include <limits>

#undef HWY_TARGET_INCLUDE
#define HWY_TARGET_INCLUDE "kernels/light_buffer_trace.cc"
#include <hwy/foreach_target.h>  // IWYU pragma: keep
#include <hwy/highway.h>         // must follow foreach_target.h

#include "kernels/tri_intersect-inl.h"

HWY_BEFORE_NAMESPACE();
namespace rs {
namespace HWY_NAMESPACE {
namespace hn = hwy::HWY_NAMESPACE;

using D = hn::ScalableTag<float>;
using DI = hn::RebindToSigned<D>;
using V = hn::Vec<D>;
using M = hn::Mask<D>;

// The rays of `lanes` (one vector, set up in r) against the references [b, e) in order: a lane
// stops at its first hit or at the first reference whose reach passes its limit. kUniform: all
// lanes share the permutation of `perm` (the triangle's components in (kx, ky, kz) order are
// broadcast), else each lane picks its own with blends. Returns the lanes hit.
template <bool kUniform>
HWY_INLINE M WalkList(D d, const LightBufferData& lb, const StreamRays<D>& r, const int perm[9],
                      M lanes, V limit, V tmin, V tmax, size_t b, size_t e, uint64_t* tests) {
  const float* reach = lb.reach.get();
  M live = lanes, hit = hn::Not(hn::FirstN(d, hn::Lanes(d)));  // none
  const float most = hn::GetLane(hn::MaxOfLanes(d, hn::IfThenElseZero(live, limit)));
  for (size_t j = b; j < e; ++j) {
    const float rj = reach[j];
    if (rj > most) break;  // ascending: no lane reaches further
    live = hn::And(live, hn::Le(hn::Set(d, rj), limit));
    if (hn::AllFalse(d, live)) break;
    const float* tri = lb.verts.get() + 9 * j;
    const auto load = [&r, tri, perm](V* p) {
      const D dd;
      if constexpr (kUniform) {
        for (int c = 0; c < 9; ++c) p[c] = hn::Set(dd, tri[perm[c]]);
      } else {
        for (int vtx = 0; vtx < 3; ++vtx) {
          const V x = hn::Set(dd, tri[3 * vtx + 0]);
          const V y = hn::Set(dd, tri[3 * vtx + 1]);
          const V z = hn::Set(dd, tri[3 * vtx + 2]);
          p[3 * vtx + 0] = PickAxis(r.kx0, r.kx1, x, y, z);
          p[3 * vtx + 1] = PickAxis(r.ky0, r.ky1, x, y, z);
          p[3 * vtx + 2] = PickAxis(r.kz0, r.kz1, x, y, z);
        }
      }
    };
    V p[9];
    load(p);
    WatertightLanes<D> wt;
    const M m = hn::And(live, WatertightTest<false>(d, p[0], p[1], p[2], p[3], p[4], p[5], p[6],
                                                    p[7], p[8], r.o0, r.o1, r.o2, r.sx, r.sy,
                                                    r.sz, tmin, tmax, load, &wt));
    *tests += hn::CountTrue(d, live);
    if (hn::AllFalse(d, m)) continue;
    hit = hn::Or(hit, m);
    live = hn::AndNot(m, live);
    if (hn::AllFalse(d, live)) break;
  }
  return hit;
}

// rays: 64-B aligned, padded to PaddedSize(size) (the caller's chunk copy).
void OccludedLightBufferT(const LightBufferData& lb, const RayStreamView& rays, int32_t* occluded,
                          uint32_t* far, size_t* num_far, TraceStats* stats) {
  const D d;
  const DI di;
  const size_t n = hn::Lanes(d);
  size_t nfar = 0, at_light = 0, cells = 0;
  uint64_t tests = 0;
  const V lx = hn::Set(d, lb.light[0]), ly = hn::Set(d, lb.light[1]), lz = hn::Set(d, lb.light[2]);
  const V zero = hn::Zero(d), one = hn::Set(d, 1.0f), flt_max = hn::Set(d, FLT_MAX);
  const V half_res = hn::Set(d, lb.half_res), slack = hn::Set(d, 1.0f + 1e-5f);
  const auto res = hn::Set(di, lb.res), top = hn::Set(di, lb.res - 1), izero = hn::Zero(di);
  const uint32_t* begin = lb.cell_begin.get();
  HWY_ALIGN int32_t cell_of[HWY_MAX_BYTES / sizeof(float)];
  for (size_t i = 0; i < rays.size; i += n) {
    const M live = hn::FirstN(d, rays.size - i);
    const V ox = hn::Load(d, rays.ox + i), oy = hn::Load(d, rays.oy + i);
    const V oz = hn::Load(d, rays.oz + i), dx = hn::Load(d, rays.dx + i);
    const V dy = hn::Load(d, rays.dy + i), dz = hn::Load(d, rays.dz + i);
    const V tmin = hn::Load(d, rays.tmin + i), tmax = hn::Load(d, rays.tmax + i);
    // from the light with tmin >= 0; the others (NaN origins too, and rays reaching behind
    // the light: the opposite cell) are the Accel's
    const M at = hn::And(live, hn::And(hn::And(hn::Eq(ox, lx), hn::Eq(oy, ly)),
                                       hn::And(hn::Eq(oz, lz), hn::Ge(tmin, zero))));
    const M away = hn::AndNot(at, live);
    if (!hn::AllFalse(d, away)) {
      for (size_t j = 0; j < n && i + j < rays.size; ++j) {
        const bool here = rays.ox[i + j] == lb.light[0] && rays.oy[i + j] == lb.light[1] &&
                          rays.oz[i + j] == lb.light[2] && rays.tmin[i + j] >= 0.0f;
        if (!here) far[nfar++] = uint32_t(i + j);
      }
    }
    at_light += hn::CountTrue(d, at);
    const V tmax_f = hn::IfThenElse(hn::Gt(tmax, flt_max), flt_max, tmax);  // +inf as scalar
    const M valid = lb.res == 0 ? hn::And(at, hn::Lt(one, zero))
                                : StreamRayValid(d, at, ox, oy, oz, dx, dy, dz, tmin, tmax_f);
    if (hn::AllFalse(d, valid)) {
      hn::Store(hn::Zero(di), di, occluded + i);
      continue;
    }
    StreamRays<D> r;
    int k[3];
    const bool uniform = SetupStreamRays(d, ox, oy, oz, dx, dy, dz, valid, &r, k);
    int perm[9] = {};  // offsets of the components in (kx, ky, kz) order
    if (uniform) {
      for (int vtx = 0; vtx < 3; ++vtx) {
        for (int a = 0; a < 3; ++a) perm[3 * vtx + a] = 3 * vtx + k[a];
      }
    }
    // the cell of each direction: face axis kz (the watertight one), u, v axes kz + 1, kz + 2
    const V dk = PickAxis(r.kz0, r.kz1, dx, dy, dz);
    const V du = PickAxis(r.kz0, r.kz1, dy, dz, dx);
    const V dv = PickAxis(r.kz0, r.kz1, dz, dx, dy);
    const V inv = hn::Div(one, hn::Abs(dk));
    const auto cx = hn::Min(top, hn::Max(izero, hn::ConvertTo(di, hn::Mul(hn::Add(hn::Mul(du, inv), one), half_res))));
    const auto cy = hn::Min(top, hn::Max(izero, hn::ConvertTo(di, hn::Mul(hn::Add(hn::Mul(dv, inv), one), half_res))));
    const auto kz = hn::IfThenElse(hn::RebindMask(di, r.kz0), izero,
                                   hn::IfThenElse(hn::RebindMask(di, r.kz1), hn::Set(di, 1),
                                                  hn::Set(di, 2)));
    const auto face = hn::Add(hn::Add(kz, kz), hn::IfThenElseZero(hn::RebindMask(di, hn::Lt(dk, zero)),
                                                                   hn::Set(di, 1)));
    const auto cell = hn::Add(hn::Mul(hn::Add(hn::Mul(face, res), cy), res), cx);
    // reach bound tmax |d|, rounded up (the float products and root are within 4 ulps)
    const V len = hn::Sqrt(hn::Add(hn::Add(hn::Mul(dx, dx), hn::Mul(dy, dy)), hn::Mul(dz, dz)));
    const V limit = hn::Mul(hn::Mul(tmax_f, len), slack);
    const auto walk = [&](M lanes, size_t b, size_t e) {
      return uniform ? WalkList<true>(d, lb, r, perm, lanes, limit, tmin, tmax_f, b, e, &tests)
                     : WalkList<false>(d, lb, r, perm, lanes, limit, tmin, tmax_f, b, e, &tests);
    };
    M hit = hn::Lt(one, zero);  // none
    if (lb.num_always != 0) {
      ++cells;
      hit = walk(valid, begin[lb.num_cells], begin[lb.num_cells + 1]);
    }
    // one walk per distinct cell among the lanes
    hn::Store(cell, di, cell_of);
    M todo = hn::AndNot(hit, valid);
    while (!hn::AllFalse(d, todo)) {
      const intptr_t first = hn::FindFirstTrue(d, todo);
      const int32_t c = cell_of[first];
      const M same = hn::And(todo, hn::RebindMask(d, hn::Eq(cell, hn::Set(di, c))));
      ++cells;
      hit = hn::Or(hit, walk(same, begin[c], begin[c + 1]));
      todo = hn::AndNot(same, todo);
    }
    hn::Store(hn::IfThenElseZero(hn::RebindMask(di, hit), hn::Set(di, 1)), di, occluded + i);
  }
  *num_far = nfar;
  if (stats != nullptr) {
    stats->rays += at_light;
    stats->cell_steps += cells;
    stats->triangle_tests += tests;
  }
}

}  // namespace HWY_NAMESPACE
}  // namespace rs
HWY_AFTER_NAMESPACE();

#if HWY_ONCE
namespace rs {

HWY_EXPORT(OccludedLightBufferT);

void OccludedLightBuffer(const LightBufferData& lb, const RayStreamView& rays, int32_t* occluded,
                         uint32_t* far, size_t* num_far, TraceStats* stats) {
  HWY_DYNAMIC_DISPATCH(OccludedLightBufferT)(lb, rays, occluded, far, num_far, stats);
}

}  // namespace rs
#endif  // HWY_ONCE
