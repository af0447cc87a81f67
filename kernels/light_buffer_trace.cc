// Light buffer query (kernels/light_buffer.h), per Highway target, a vector of rays at a time:
// validity, the watertight setup and each ray's cube cell in SIMD; then, per distinct cell among
// the vector's rays, that cell's list front to back, one triangle broadcast against the rays of
// that cell (N rays x 1 triangle, the watertight test of kernels/tri_intersect-inl.h); a lane
// stops at its first hit or at the first reference beyond its reach. Per-target code;
// foreach_target re-includes this file.
#include "kernels/light_buffer.h"

#include <cfloat>
#include <cmath>
#include <cstring>
#include <limits>

#undef HWY_TARGET_INCLUDE
#define HWY_TARGET_INCLUDE "kernels/light_buffer_trace.cc"
#include <hwy/foreach_target.h>  // IWYU pragma: keep
#include <hwy/highway.h>         // must follow foreach_target.h
#include <hwy/cache_control.h>  // Prefetch

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
// stops at its first hit or at the first reference whose reach passes its limit. A vector of
// references at a time is culled against the lanes' box of face coordinates (u, v) and their
// largest limit; a lane whose (u, v) falls outside a remaining reference's rectangle (the one
// the triangle was binned by) cannot hit it and skips its test. kUniform: all lanes share the
// permutation of `perm` (the triangle's components in (kx, ky, kz) order are broadcast), else
// each lane picks its own with blends. Returns the lanes hit.
template <bool kUniform>
HWY_INLINE M WalkList(D d, const LightBufferData& lb, const StreamRays<D>& r, const int perm[9],
                      M lanes, V u, V v, V limit, V tmin, V tmax, size_t b, size_t e,
                      uint64_t* tests) {
  const size_t n = hn::Lanes(d);
  M live = lanes, hit = hn::Not(hn::FirstN(d, n));  // none
  const V big = hn::Set(d, FLT_MAX), nbig = hn::Set(d, -FLT_MAX);
  const V most = hn::MaxOfLanes(d, hn::IfThenElseZero(live, limit));
  const V umin = hn::MinOfLanes(d, hn::IfThenElse(live, u, big));
  const V umax = hn::MaxOfLanes(d, hn::IfThenElse(live, u, nbig));
  const V vmin = hn::MinOfLanes(d, hn::IfThenElse(live, v, big));
  const V vmax = hn::MaxOfLanes(d, hn::IfThenElse(live, v, nbig));
  const float* const reach = lb.reach.get();
  const V w_ulps = hn::Set(d, float(32.0 * kLightPlaneUlp));
  const V m_ulps = hn::Set(d, float(16.0 * kLightPlaneUlp));
  const V tiny = hn::Set(d, float(0x1p-40));
  for (size_t j0 = b; j0 < e; j0 += n) {
    // the padding after the last reference makes whole-vector loads safe
    const V rv = hn::LoadU(d, reach + j0);
    const V ru0 = hn::LoadU(d, lb.u0.get() + j0), ru1 = hn::LoadU(d, lb.u1.get() + j0);
    const V rv0 = hn::LoadU(d, lb.v0.get() + j0), rv1 = hn::LoadU(d, lb.v1.get() + j0);
    M cand = hn::And(hn::FirstN(d, e - j0), hn::Le(rv, most));
    cand = hn::And(cand, hn::And(hn::Le(ru0, umax), hn::Ge(ru1, umin)));
    cand = hn::And(cand, hn::And(hn::Le(rv0, vmax), hn::Ge(rv1, vmin)));
    if (!hn::AllFalse(d, cand)) {
      // the edge-plane cull (light_buffer.h, kLightPlaneFloats): a reference whose edge
      // functions take opposite signs, beyond tau, over the whole box of the lanes' (u, v)
      const V w = hn::Max(hn::Sub(hn::Max(umax, ru1), hn::Min(umin, ru0)),
                          hn::Sub(hn::Max(vmax, rv1), hn::Min(vmin, rv0)));
      const V tau = hn::MulAdd(w, w_ulps,
                               hn::MulAdd(hn::LoadU(d, lb.Plane(9) + j0), m_ulps, tiny));
      const V ntau = hn::Neg(tau);
      M below = hn::Not(hn::FirstN(d, n)), above = below;  // none
      for (int edge = 0; edge < 3; ++edge) {
        const V pa = hn::LoadU(d, lb.Plane(3 * edge) + j0);
        const V pb = hn::LoadU(d, lb.Plane(3 * edge + 1) + j0);
        const V pc = hn::LoadU(d, lb.Plane(3 * edge + 2) + j0);
        const V bu0 = hn::Mul(pb, umin), bu1 = hn::Mul(pb, umax);
        const V cv0 = hn::Mul(pc, vmin), cv1 = hn::Mul(pc, vmax);
        const V gmax = hn::Add(hn::Add(pa, hn::Max(bu0, bu1)), hn::Max(cv0, cv1));
        const V gmin = hn::Add(hn::Add(pa, hn::Min(bu0, bu1)), hn::Min(cv0, cv1));
        below = hn::Or(below, hn::Lt(gmax, ntau));
        above = hn::Or(above, hn::Gt(gmin, tau));
      }
      cand = hn::AndNot(hn::And(below, above), cand);
    }
    uint8_t bytes[8] = {};
    hn::StoreMaskBits(d, cand, bytes);
    uint64_t bits = 0;
    std::memcpy(&bits, bytes, sizeof bits);
    for (; bits != 0; bits &= bits - 1) {
      const size_t j = j0 + size_t(hwy::Num0BitsBelowLS1Bit_Nonzero64(bits));
      live = hn::And(live, hn::Le(hn::Set(d, reach[j]), limit));
      if (hn::AllFalse(d, live)) return hit;
      const M in = hn::And(
          hn::And(live, hn::And(hn::Ge(u, hn::Set(d, lb.u0[j])), hn::Le(u, hn::Set(d, lb.u1[j])))),
          hn::And(hn::Ge(v, hn::Set(d, lb.v0[j])), hn::Le(v, hn::Set(d, lb.v1[j]))));
      if (hn::AllFalse(d, in)) continue;
      const float* tri = lb.Vertices(j);
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
      const M m = hn::And(in, WatertightTest<false>(d, p[0], p[1], p[2], p[3], p[4], p[5], p[6],
                                                    p[7], p[8], r.o0, r.o1, r.o2, r.sx, r.sy,
                                                    r.sz, tmin, tmax, load, &wt));
      *tests += hn::CountTrue(d, in);
      if (hn::AllFalse(d, m)) continue;
      hit = hn::Or(hit, m);
      live = hn::AndNot(m, live);
      if (hn::AllFalse(d, live)) return hit;
    }
    if (hn::GetLane(hn::MaxOfLanes(d, rv)) > hn::GetLane(most)) break;  // ascending: done
  }
  return hit;
}

// rays: any alignment, readable (and occluded writable) to PaddedSize(size); size <= kLightChunk.
// Pass 1 finds every ray's cell and prefetches the head of each new cell's list, so the walks of
// pass 2 find their first records in the caches (a list is read front to back from there).
void OccludedLightBufferT(const LightBufferData& lb, const RayStreamView& rays, int32_t* occluded,
                          uint32_t* far, size_t* num_far, TraceStats* stats) {
  const D d;
  const DI di;
  const size_t n = hn::Lanes(d);
  HWY_DASSERT(rays.size <= kLightChunk);
  size_t nfar = 0, at_light = 0, cells = 0;
  uint64_t tests = 0;
  const V lx = hn::Set(d, lb.light[0]), ly = hn::Set(d, lb.light[1]), lz = hn::Set(d, lb.light[2]);
  const V fx = hn::Set(d, lb.frame_light[0]), fy = hn::Set(d, lb.frame_light[1]);
  const V fz = hn::Set(d, lb.frame_light[2]);
  const V zero = hn::Zero(d), one = hn::Set(d, 1.0f), flt_max = hn::Set(d, FLT_MAX);
  const V slack = hn::Set(d, 1.0f + 1e-5f);
  const auto izero = hn::Zero(di);
  const LightFaces& fc = lb.faces;
  const auto none = hn::Set(di, -1);
  const uint32_t* begin = lb.cell_begin.get();
  HWY_ALIGN int32_t cell_of[kLightChunk + HWY_MAX_BYTES / sizeof(float)];
  HWY_ALIGN float u_of[kLightChunk + HWY_MAX_BYTES / sizeof(float)];
  HWY_ALIGN float v_of[kLightChunk + HWY_MAX_BYTES / sizeof(float)];
  int32_t last = -1;
  for (size_t i = 0; i < rays.size; i += n) {
    const M live = hn::FirstN(d, rays.size - i);
    const V ox = hn::LoadU(d, rays.ox + i), oy = hn::LoadU(d, rays.oy + i);
    const V oz = hn::LoadU(d, rays.oz + i), dx = hn::LoadU(d, rays.dx + i);
    const V dy = hn::LoadU(d, rays.dy + i), dz = hn::LoadU(d, rays.dz + i);
    const V tmin = hn::LoadU(d, rays.tmin + i), tmax = hn::LoadU(d, rays.tmax + i);
    // from the light with tmin >= 0; the others (NaN origins too, and rays reaching behind
    // the light: the opposite cell) are the Accel's
    const M at = hn::And(live, hn::And(hn::And(hn::Eq(ox, lx), hn::Eq(oy, ly)),
                                       hn::And(hn::Eq(oz, lz), hn::Ge(tmin, zero))));
    if (!hn::AllTrue(d, hn::Or(at, hn::Not(live)))) {
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
    // the cell of each direction: face axis kz (the largest |d|, first on ties: the watertight
    // kz), u, v axes kz + 1, kz + 2
    M kz0, kz1;
    LargestAxis(d, dx, dy, dz, &kz0, &kz1);
    const V dk = PickAxis(kz0, kz1, dx, dy, dz);
    const V du = PickAxis(kz0, kz1, dy, dz, dx);
    const V dv = PickAxis(kz0, kz1, dz, dx, dy);
    const V inv = hn::Div(one, hn::Abs(dk));
    const V fu = hn::Mul(du, inv), fv = hn::Mul(dv, inv);  // in [-1, 1]
    hn::Store(fu, d, u_of + i);
    hn::Store(fv, d, v_of + i);
    const auto kz = hn::IfThenElse(hn::RebindMask(di, kz0), izero,
                                   hn::IfThenElse(hn::RebindMask(di, kz1), hn::Set(di, 1),
                                                  hn::Set(di, 2)));
    const auto face = hn::Add(
        hn::Add(kz, kz), hn::IfThenElseZero(hn::RebindMask(di, hn::Lt(dk, zero)), hn::Set(di, 1)));
    // the cell in the face's window (LightFaces); face < 6 on every lane. The face's seven
    // table entries are broadcast when every valid lane has the same face (coherent rays: a
    // gather each was 40 % of the query on office-graz), else gathered per lane.
    const auto cell_in = [&](auto top_u, auto lo_u, auto scale_u, auto top_v, auto lo_v,
                             auto scale_v, auto base, auto res_u) {
      const auto cx = hn::Min(
          top_u, hn::Max(izero, hn::ConvertTo(di, hn::Mul(hn::Sub(fu, lo_u), scale_u))));
      const auto cy = hn::Min(
          top_v, hn::Max(izero, hn::ConvertTo(di, hn::Mul(hn::Sub(fv, lo_v), scale_v))));
      return hn::Add(base, hn::Add(hn::Mul(cy, res_u), cx));
    };
    const auto vmask = hn::RebindMask(di, valid);
    const int32_t f0 =
        hn::AllFalse(d, valid) ? 0 : hn::ExtractLane(face, size_t(hn::FindKnownFirstTrue(d, valid)));
    const auto cell =
        hn::AllTrue(di, hn::Or(hn::Eq(face, hn::Set(di, f0)), hn::Not(vmask)))
            ? cell_in(hn::Set(di, fc.top_u[f0]), hn::Set(d, fc.lo_u[f0]),
                      hn::Set(d, fc.scale_u[f0]), hn::Set(di, fc.top_v[f0]),
                      hn::Set(d, fc.lo_v[f0]), hn::Set(d, fc.scale_v[f0]),
                      hn::Set(di, fc.base[f0]), hn::Set(di, fc.res_u[f0]))
            : cell_in(hn::GatherIndex(di, fc.top_u, face), hn::GatherIndex(d, fc.lo_u, face),
                      hn::GatherIndex(d, fc.scale_u, face), hn::GatherIndex(di, fc.top_v, face),
                      hn::GatherIndex(d, fc.lo_v, face), hn::GatherIndex(d, fc.scale_v, face),
                      hn::GatherIndex(di, fc.base, face), hn::GatherIndex(di, fc.res_u, face));
    hn::Store(hn::IfThenElse(hn::RebindMask(di, valid), cell, none), di, cell_of + i);
    for (size_t j = 0; j < n; ++j) {
      const int32_t c = cell_of[i + j];
      if (c < 0 || c == last) continue;
      last = c;
      hwy::Prefetch(lb.reach.get() + begin[c]);
      hwy::Prefetch(lb.tri.get() + begin[c]);
    }
  }
  for (size_t i = 0; i < rays.size; i += n) {
    const auto cell = hn::Load(di, cell_of + i);
    const M valid = hn::RebindMask(d, hn::Gt(cell, none));
    if (hn::AllFalse(d, valid)) {
      hn::StoreU(hn::Zero(di), di, occluded + i);
      continue;
    }
    // the valid lanes start at the light: their origin in the triangles' frame is frame_light
    const V dx = hn::LoadU(d, rays.dx + i);
    const V dy = hn::LoadU(d, rays.dy + i), dz = hn::LoadU(d, rays.dz + i);
    const V tmin = hn::LoadU(d, rays.tmin + i);
    const V tmax_f = hn::Min(hn::LoadU(d, rays.tmax + i), flt_max);  // valid: not NaN
    StreamRays<D> r;
    int k[3];
    const bool uniform = SetupStreamRays(d, fx, fy, fz, dx, dy, dz, valid, &r, k);
    int perm[9] = {};  // offsets of the components in (kx, ky, kz) order
    if (uniform) {
      for (int vtx = 0; vtx < 3; ++vtx) {
        for (int a = 0; a < 3; ++a) perm[3 * vtx + a] = 3 * vtx + k[a];
      }
    }
    // reach bound tmax |d|, rounded up (the float products and root are within 4 ulps)
    const V len = hn::Sqrt(hn::Add(hn::Add(hn::Mul(dx, dx), hn::Mul(dy, dy)), hn::Mul(dz, dz)));
    const V limit = hn::Mul(hn::Mul(tmax_f, len), slack);
    const V fu = hn::Load(d, u_of + i), fv = hn::Load(d, v_of + i);
    const auto walk = [&](M lanes, size_t b, size_t e) {
      return uniform ? WalkList<true>(d, lb, r, perm, lanes, fu, fv, limit, tmin, tmax_f, b, e,
                                      &tests)
                     : WalkList<false>(d, lb, r, perm, lanes, fu, fv, limit, tmin, tmax_f, b, e,
                                       &tests);
    };
    M hit = hn::Lt(one, zero);  // none
    if (lb.num_always != 0) {
      ++cells;
      hit = walk(valid, begin[lb.num_cells], begin[lb.num_cells + 1]);
    }
    // one walk per distinct cell among the lanes
    M todo = hn::AndNot(hit, valid);
    while (!hn::AllFalse(d, todo)) {
      const int32_t c = cell_of[i + size_t(hn::FindFirstTrue(d, todo))];
      const M same = hn::And(todo, hn::RebindMask(d, hn::Eq(cell, hn::Set(di, c))));
      ++cells;
      hit = hn::Or(hit, walk(same, begin[c], begin[c + 1]));
      todo = hn::AndNot(same, todo);
    }
    hn::StoreU(hn::IfThenElseZero(hn::RebindMask(di, hit), hn::Set(di, 1)), di, occluded + i);
  }
  *num_far = nfar;
  if (stats != nullptr) {
    stats->rays += at_light;
    stats->cell_steps += cells;
    stats->triangle_tests += tests;
  }
}

// The projections of `count` triangles, vertex a of corner c of the j-th read by
// load(c, a, j) (a vector of lanes j..j + Lanes - 1). kPlanes: also the edge planes.
template <bool kPlanes, class Load, class Out>
HWY_INLINE void ProjectLightTriangles(const float light[3], size_t count, const Load& load,
                                      Out* out) {
  const D d;
  const DI di;
  const size_t n = hn::Lanes(d);
  const V zero = hn::Zero(d), one = hn::Set(d, 1.0f), none = hn::Set(d, -1.0f);
  const V margin = hn::Set(d, float(kLightMargin)), inside = hn::Set(d, float(1.0 - kLightMargin));
  const V slack_near = hn::Set(d, float(1.0 - kLightReachSlack));
  const V slack_far = hn::Set(d, float(kLightReachSlack));
  const V touch = hn::Set(d, 1e-6f), limit = hn::Set(d, 1073741824.0f);  // 2^30
  const V l[3] = {hn::Set(d, light[0]), hn::Set(d, light[1]), hn::Set(d, light[2])};
  for (size_t j = 0; j < count; j += n) {
    V q[3][3];
    for (int c = 0; c < 3; ++c) {
      for (int a = 0; a < 3; ++a) q[c][a] = hn::Sub(load(c, a, j), l[a]);
    }
    // each vertex's face: the axis of the largest |q| (first on ties) and its sign
    M ok = hn::FirstN(d, count - j);
    V axis[3], sign[3];
    for (int c = 0; c < 3; ++c) {
      M k0, k1;
      LargestAxis(d, q[c][0], q[c][1], q[c][2], &k0, &k1);
      axis[c] = hn::IfThenElse(k0, zero, hn::IfThenElse(k1, one, hn::Set(d, 2.0f)));
      const V qk = PickAxis(k0, k1, q[c][0], q[c][1], q[c][2]);
      sign[c] = hn::IfThenElse(hn::Lt(qk, zero), none, one);
      ok = hn::And(ok, hn::Lt(hn::Abs(qk), limit));  // the largest |q|
    }
    ok = hn::And(ok, hn::And(hn::Eq(axis[0], axis[1]), hn::Eq(axis[0], axis[2])));
    ok = hn::And(ok, hn::And(hn::Eq(sign[0], sign[1]), hn::Eq(sign[0], sign[2])));
    const M k0 = hn::Eq(axis[0], zero), k1 = hn::Eq(axis[0], one);
    V u_lo = hn::Set(d, FLT_MAX), u_hi = hn::Set(d, -FLT_MAX), v_lo = u_lo, v_hi = u_hi;
    V farthest = zero;
    for (int c = 0; c < 3; ++c) {
      // (k, u, v) = (0, 1, 2), (1, 2, 0) or (2, 0, 1)
      const V z = hn::Mul(sign[0], PickAxis(k0, k1, q[c][0], q[c][1], q[c][2]));
      const V qu = PickAxis(k0, k1, q[c][1], q[c][2], q[c][0]);
      const V qv = PickAxis(k0, k1, q[c][2], q[c][0], q[c][1]);
      ok = hn::And(ok, hn::Gt(z, zero));
      const V inv = hn::Div(one, z);
      const V pu = hn::Mul(qu, inv), pv = hn::Mul(qv, inv);
      // at least a margin inside the face: no ray of a neighbouring face can reach it
      ok = hn::And(ok, hn::And(hn::Le(hn::Abs(pu), inside), hn::Le(hn::Abs(pv), inside)));
      u_lo = hn::Min(u_lo, pu), u_hi = hn::Max(u_hi, pu);
      v_lo = hn::Min(v_lo, pv), v_hi = hn::Max(v_hi, pv);
      farthest = hn::Max(farthest, hn::Sqrt(hn::Add(hn::Add(hn::Mul(q[c][0], q[c][0]),
                                                            hn::Mul(q[c][1], q[c][1])),
                                                    hn::Mul(q[c][2], q[c][2]))));
    }
    // distance bound: the plane's and the bounding box's
    V e1[3], e2[3];
    for (int a = 0; a < 3; ++a) {
      e1[a] = hn::Sub(q[1][a], q[0][a]);
      e2[a] = hn::Sub(q[2][a], q[0][a]);
    }
    const V nx = hn::Sub(hn::Mul(e1[1], e2[2]), hn::Mul(e1[2], e2[1]));
    const V ny = hn::Sub(hn::Mul(e1[2], e2[0]), hn::Mul(e1[0], e2[2]));
    const V nz = hn::Sub(hn::Mul(e1[0], e2[1]), hn::Mul(e1[1], e2[0]));
    const V nn = hn::Add(hn::Add(hn::Mul(nx, nx), hn::Mul(ny, ny)), hn::Mul(nz, nz));
    const V dot = hn::Add(hn::Add(hn::Mul(nx, q[0][0]), hn::Mul(ny, q[0][1])), hn::Mul(nz, q[0][2]));
    ok = hn::And(ok, hn::Gt(nn, zero));
    const V plane = hn::Div(hn::Abs(dot), hn::Sqrt(hn::IfThenElse(hn::Gt(nn, zero), nn, one)));
    V box2 = zero;
    for (int a = 0; a < 3; ++a) {
      const V lo = hn::Min(hn::Min(q[0][a], q[1][a]), q[2][a]);
      const V hi = hn::Max(hn::Max(q[0][a], q[1][a]), q[2][a]);
      const V gap = hn::Max(zero, hn::Max(lo, hn::Neg(hi)));
      box2 = hn::Add(box2, hn::Mul(gap, gap));
    }
    const V near = hn::Max(plane, hn::Sqrt(box2));
    ok = hn::And(ok, hn::Gt(near, hn::Mul(touch, farthest)));
    const V reach = hn::Max(zero, hn::Sub(hn::Mul(near, slack_near), hn::Mul(slack_far, farthest)));
    const auto face = hn::Add(hn::Add(hn::ConvertTo(di, axis[0]), hn::ConvertTo(di, axis[0])),
                              hn::IfThenElseZero(hn::RebindMask(di, hn::Lt(sign[0], zero)),
                                                 hn::Set(di, 1)));
    hn::StoreU(hn::IfThenElse(hn::RebindMask(di, ok), face, hn::Set(di, -1)), di, out->face + j);
    hn::StoreU(hn::Max(none, hn::Sub(u_lo, margin)), d, out->u0 + j);
    hn::StoreU(hn::Min(one, hn::Add(u_hi, margin)), d, out->u1 + j);
    hn::StoreU(hn::Max(none, hn::Sub(v_lo, margin)), d, out->v0 + j);
    hn::StoreU(hn::Min(one, hn::Add(v_hi, margin)), d, out->v1 + j);
    hn::StoreU(reach, d, out->reach + j);
    if constexpr (kPlanes) {
      // the edge planes (light_buffer.h): n = q_b x q_c over R_b R_c on the face's (k, u, v) axes,
      // in float; lanes not ok are the scalar path's
      V r[3];
      for (int c = 0; c < 3; ++c) {
        r[c] = hn::Max(hn::Max(hn::Abs(q[c][0]), hn::Abs(q[c][1])), hn::Abs(q[c][2]));
      }
      V most = zero;
      for (int e = 0; e < 3; ++e) {
        const V* p = q[kLightPlaneEdges[e][0]];
        const V* t = q[kLightPlaneEdges[e][1]];
        const V n0 = hn::Sub(hn::Mul(p[1], t[2]), hn::Mul(p[2], t[1]));
        const V n1 = hn::Sub(hn::Mul(p[2], t[0]), hn::Mul(p[0], t[2]));
        const V n2 = hn::Sub(hn::Mul(p[0], t[1]), hn::Mul(p[1], t[0]));
        const V scale = hn::Mul(r[kLightPlaneEdges[e][0]], r[kLightPlaneEdges[e][1]]);
        // a normal, finite scale (else no planes: zeros are never culled)
        const M fine =
            hn::And(hn::Ge(scale, hn::Set(d, FLT_MIN)), hn::Le(scale, hn::Set(d, FLT_MAX)));
        const V inv = hn::IfThenElseZero(fine, hn::Div(one, hn::IfThenElse(fine, scale, one)));
        const V pa = hn::Mul(hn::Mul(sign[0], PickAxis(k0, k1, n0, n1, n2)), inv);
        const V pb = hn::Mul(PickAxis(k0, k1, n1, n2, n0), inv);
        const V pc = hn::Mul(PickAxis(k0, k1, n2, n0, n1), inv);
        hn::StoreU(pa, d, out->planes[3 * e] + j);
        hn::StoreU(pb, d, out->planes[3 * e + 1] + j);
        hn::StoreU(pc, d, out->planes[3 * e + 2] + j);
        most = hn::Max(most, hn::Add(hn::Add(hn::Abs(pa), hn::Abs(pb)), hn::Abs(pc)));
      }
      // M + 1, rounded up (float planes)
      hn::StoreU(hn::Mul(hn::Add(most, one), hn::Set(d, 1.0f + 1e-6f)), d, out->planes[9] + j);
    }
  }
}

// Triangles [first, first + count) from the SoA arrays; without the planes.
void ProjectLightBlockT(const TriangleSoA& tris, const float light[3], size_t first,
                        size_t count, LightProjection* out) {
  const D d;
  ProjectLightTriangles<false>(
      light, count,
      [&](int c, int a, size_t j) { return hn::LoadU(d, tris.p[c][a].data() + first + j); }, out);
}

// Triangles ids[0, count) from their interleaved records (TriangleSoA::verts), planes included:
// the records (in any order: a cache miss each, fetched 16 ahead) copied to SoA first.
void ProjectLightListT(const TriangleSoA& tris, const float light[3], const uint32_t* ids,
                       size_t count, const LightProjectionOut& out) {
  const D d;
  HWY_ALIGN float soa[9][kLightProjectBlock + HWY_MAX_BYTES / sizeof(float)];
  constexpr size_t kAhead = 16;
  for (size_t j = 0; j < count; ++j) {
    if (j + kAhead < count) hwy::Prefetch(tris.Vertices(ids[j + kAhead]));
    const float* v = tris.Vertices(ids[j]);
    for (int k = 0; k < 9; ++k) soa[k][j] = v[k];
  }
  for (int k = 0; k < 9; ++k) {  // lanes past count: finite values, results unused
    for (size_t j = count; j < hwy::RoundUpTo(count, hn::Lanes(d)); ++j) soa[k][j] = 1.0f;
  }
  LightProjectionOut at = out;
  ProjectLightTriangles<true>(
      light, count, [&](int c, int a, size_t j) { return hn::Load(d, soa[3 * c + a] + j); }, &at);
}

}  // namespace HWY_NAMESPACE
}  // namespace rs
HWY_AFTER_NAMESPACE();

#if HWY_ONCE
namespace rs {

HWY_EXPORT(OccludedLightBufferT);
HWY_EXPORT(ProjectLightBlockT);
HWY_EXPORT(ProjectLightListT);

void ProjectLightBlock(const TriangleSoA& tris, const float light[3], size_t first, size_t count,
                       LightProjection* out) {
  HWY_DYNAMIC_DISPATCH(ProjectLightBlockT)(tris, light, first, count, out);
}

void ProjectLightList(const TriangleSoA& tris, const float light[3], const uint32_t* ids,
                      size_t count, const LightProjectionOut& out) {
  HWY_DYNAMIC_DISPATCH(ProjectLightListT)(tris, light, ids, count, out);
}

void OccludedLightBuffer(const LightBufferData& lb, const RayStreamView& rays, int32_t* occluded,
                         uint32_t* far, size_t* num_far, TraceStats* stats) {
  HWY_DYNAMIC_DISPATCH(OccludedLightBufferT)(lb, rays, occluded, far, num_far, stats);
}

}  // namespace rs
#endif  // HWY_ONCE
