// SIMD stream traversal of the irregular grid (contracts in kernels/irregular_simd.h). Per
// iteration of the lane loop: free lanes take the next rays (the scalar prologue, BeginDdaRay
// and IrregularStartVoxel, lane by lane); one vector pass looks up every lane's cell (top entry,
// then sub-cell entry: two gathers); lanes whose cell lists triangles test them (bundle kernel,
// inlined); a second vector pass gathers the boxes, takes the exit t and the next voxel with the
// arithmetic of IrregularFaceT / IrregularNextVoxel, and retires the lanes that are done.
// Per-target code; foreach_target re-includes this file.
#include "kernels/irregular_simd.h"

#include <algorithm>
#include <cfloat>
#include <cmath>
#include <limits>

#include "streams/ray_stream.h"  // SubView, AllocateAlignedOrThrow

#undef HWY_TARGET_INCLUDE
#define HWY_TARGET_INCLUDE "kernels/irregular_stream.cc"
#include <hwy/foreach_target.h>  // IWYU pragma: keep
#include <hwy/highway.h>         // must follow foreach_target.h

#include <hwy/cache_control.h>

#include "kernels/ray_setup-inl.h"
#include "kernels/tri_intersect-inl.h"

HWY_BEFORE_NAMESPACE();
namespace rs {
namespace HWY_NAMESPACE {
namespace hn = hwy::HWY_NAMESPACE;

inline constexpr size_t kIrrMaxLanes = HWY_MAX_BYTES / sizeof(float);

struct IrrLanes {
  HWY_ALIGN int32_t ray[kIrrMaxLanes];  // ray index, -1 = free
  HWY_ALIGN int32_t v[3][kIrrMaxLanes];
  HWY_ALIGN int32_t step[3][kIrrMaxLanes];
  HWY_ALIGN int32_t cell[kIrrMaxLanes];
  HWY_ALIGN float o[3][kIrrMaxLanes];
  HWY_ALIGN float d[3][kIrrMaxLanes];
  HWY_ALIGN float inv[3][kIrrMaxLanes];
  HWY_ALIGN float t1[kIrrMaxLanes];
  HWY_ALIGN float best[kIrrMaxLanes];
  HWY_ALIGN float t_enter[kIrrMaxLanes];
  float tmin[kIrrMaxLanes];
  float tmax[kIrrMaxLanes];
  int32_t prim[kIrrMaxLanes];
  PreparedRay prepared[kIrrMaxLanes];
};

// Sets up rays [first, first + Lanes) into st's slots 0..Lanes-1 with the scalar prologue's
// arithmetic a vector at a time (ValidRayLanes, ClipRayLanes: BeginDdaRay; the start voxel:
// IrregularStartVoxel; PrepareRay lane by lane), and writes the miss result of each ray. Rays
// past the stream's end, invalid or missing the box get ray = -1.
template <bool kAny, class D>
HWY_INLINE void SetupRays(D d, const IrregularGrid& g, const RayStreamView& rays, size_t first,
                          const HitStreamView* hits, int32_t* occluded, IrrLanes* st) {
  using V = hn::Vec<D>;
  const hn::RebindToSigned<D> di;
  const size_t N = hn::Lanes(d);
  const size_t count = std::min(N, rays.size - first);
  const auto live = hn::FirstN(d, count);
  // lanes past the end read from `first` (always a ray), and are masked off
  V o[3], dir[3];
  const float* const src_o[3] = {rays.ox, rays.oy, rays.oz};
  const float* const src_d[3] = {rays.dx, rays.dy, rays.dz};
  for (int a = 0; a < 3; ++a) {
    o[a] = hn::IfThenElse(live, hn::LoadU(d, src_o[a] + first), hn::Set(d, src_o[a][first]));
    dir[a] = hn::IfThenElse(live, hn::LoadU(d, src_d[a] + first), hn::Set(d, src_d[a][first]));
  }
  const V tmin = hn::IfThenElse(live, hn::LoadU(d, rays.tmin + first), hn::Set(d, rays.tmin[first]));
  const V tmax_f = FiniteTmax(
      d, hn::IfThenElse(live, hn::LoadU(d, rays.tmax + first), hn::Set(d, rays.tmax[first])));
  auto valid = ValidRayLanes(d, o, dir, tmin, tmax_f, live);
  V t0 = tmin, t1 = tmax_f, inv[3];
  hn::Mask<D> parallel[3];
  valid = ClipRayLanes(d, g.lo, g.hi, o, dir, valid, &t0, &t1, inv, parallel);
  const auto vi = hn::RebindMask(di, valid);
  for (int a = 0; a < 3; ++a) {
    // IrregularStartVoxel: c = f >= 0 ? (f < vres ? int(f) : vres - 1) : 0, NaN -> 0
    const V p = hn::Add(o[a], hn::Mul(t0, dir[a]));
    const V f = hn::Mul(hn::Sub(p, hn::Set(d, g.lo[a])), hn::Set(d, g.inv_voxel_size[a]));
    const V res = hn::Set(d, float(g.vres[a]));
    const auto in_range = hn::Lt(f, res);
    const auto c = hn::IfThenElse(
        hn::RebindMask(di, hn::Ge(f, hn::Zero(d))),
        hn::IfThenElse(hn::RebindMask(di, in_range), hn::ConvertTo(di, hn::IfThenElse(in_range, f, hn::Zero(d))),
                       hn::Set(di, g.vres[a] - 1)),
        hn::Zero(di));
    // int(f) of a float just below vres can round to vres: clamp as the scalar code does
    hn::Store(hn::Min(c, hn::Set(di, g.vres[a] - 1)), di, st->v[a]);
    const auto pos = hn::RebindMask(di, hn::Gt(dir[a], hn::Zero(d)));
    hn::Store(hn::IfThenElse(hn::RebindMask(di, parallel[a]), hn::Zero(di),
                             hn::IfThenElse(pos, hn::Set(di, 1), hn::Set(di, -1))),
              di, st->step[a]);
    hn::Store(o[a], d, st->o[a]);
    hn::Store(dir[a], d, st->d[a]);
    hn::Store(inv[a], d, st->inv[a]);
  }
  hn::Store(t1, d, st->t1);
  hn::Store(tmax_f, d, st->best);
  hn::Store(t0, d, st->t_enter);
  hn::Store(tmin, d, st->tmin);
  hn::Store(tmax_f, d, st->tmax);
  hn::Store(hn::IfThenElse(vi, hn::Add(hn::Iota(di, 0), hn::Set(di, int32_t(first))),
                           hn::Set(di, -1)),
            di, st->ray);
  for (size_t l = 0; l < count; ++l) {
    const size_t i = first + l;
    if constexpr (kAny) {
      occluded[i] = 0;
    } else {
      hits->t[i] = std::numeric_limits<float>::infinity();
      hits->u[i] = hits->v[i] = 0.0f;
      hits->prim[i] = -1;
    }
    st->prim[l] = -1;
    if (st->ray[l] >= 0) {
      st->prepared[l] = PrepareRay(st->o[0][l], st->o[1][l], st->o[2][l], st->d[0][l],
                                   st->d[1][l], st->d[2][l]);
    }
  }
}

inline void CopyLane(const IrrLanes& from, size_t j, IrrLanes* to, size_t l) {
  to->ray[l] = from.ray[j];
  for (int a = 0; a < 3; ++a) {
    to->v[a][l] = from.v[a][j];
    to->step[a][l] = from.step[a][j];
    to->o[a][l] = from.o[a][j];
    to->d[a][l] = from.d[a][j];
    to->inv[a][l] = from.inv[a][j];
  }
  to->t1[l] = from.t1[j];
  to->best[l] = from.best[j];
  to->t_enter[l] = from.t_enter[j];
  to->tmin[l] = from.tmin[j];
  to->tmax[l] = from.tmax[j];
  to->prim[l] = -1;
  to->prepared[l] = from.prepared[j];
  to->cell[l] = from.cell[j];
}

// The cell of voxels v (lanes of `live`; others get cell 0): the top entry, then the sub-cell
// entry (IrregularGrid::Lookup).
template <class DI, class VI = hn::Vec<DI>>
HWY_INLINE VI LookupCells(DI di, const IrregularGrid& g, hn::Mask<DI> live, const VI v_in[3]) {
  const int32_t* top = reinterpret_cast<const int32_t*>(g.top.get());
  const int32_t* fine = reinterpret_cast<const int32_t*>(g.fine.get());
  const VI vD = hn::Set(di, g.depth), vmask = hn::Set(di, (1 << g.depth) - 1);
  VI v[3];
  for (int a = 0; a < 3; ++a) v[a] = hn::IfThenElseZero(live, v_in[a]);
  const VI tc = hn::Add(
      hn::Shr(v[0], vD),
      hn::Mul(hn::Set(di, g.top_res[0]),
              hn::Add(hn::Shr(v[1], vD), hn::Mul(hn::Set(di, g.top_res[1]), hn::Shr(v[2], vD)))));
  const VI e = hn::GatherIndex(di, top, tc);
  const VI s = hn::And(e, hn::Set(di, 3));
  const VI q = hn::Sub(vD, s);
  const VI local = hn::Add(hn::Shr(hn::And(v[0], vmask), q),
                           hn::Add(hn::Shl(hn::Shr(hn::And(v[1], vmask), q), s),
                                   hn::Shl(hn::Shr(hn::And(v[2], vmask), q), hn::Add(s, s))));
  const hn::RebindToUnsigned<DI> du;
  return hn::GatherIndex(di, fine,
                         hn::Add(hn::BitCast(di, hn::ShiftRight<2>(hn::BitCast(du, e))), local));
}

template <bool kAny>
void StreamIrregular(const IrregularDda& gd, const RayStreamView& rays, const HitStreamView* hits,
                     int32_t* occluded, TraceStats* stats) {
  const IrregularGrid& g = *gd.grid;
  const hn::ScalableTag<float> d;
  const hn::RebindToSigned<decltype(d)> di;
  using VF = hn::Vec<decltype(d)>;
  using VI = hn::Vec<decltype(di)>;
  const size_t N = hn::Lanes(d);
  IrrLanes ls, st;
  for (size_t l = 0; l < N; ++l) ls.ray[l] = -1;
  const int32_t* cells = gd.cells.get();
  const float* bundle_data = gd.bundles.data.get();
  const int32_t* bundle_ids = gd.bundles.ids.get();
  const VF inf = hn::Set(d, std::numeric_limits<float>::infinity());
  const VI zero = hn::Zero(di), one = hn::Set(di, 1), minus1 = hn::Set(di, -1);
  const hn::RebindToUnsigned<decltype(di)> du;
  VF glo[3], gvs[3], ginv[3];
  VI gres_m1[3];
  for (int a = 0; a < 3; ++a) {
    glo[a] = hn::Set(d, g.lo[a]);
    gvs[a] = hn::Set(d, g.voxel_size[a]);
    ginv[a] = hn::Set(d, g.inv_voxel_size[a]);
    gres_m1[a] = hn::Set(di, g.vres[a] - 1);
  }
  HWY_ALIGN float t_exit_lanes[kIrrMaxLanes];
  HWY_ALIGN int32_t leave_lanes[kIrrMaxLanes];
  HWY_ALIGN int32_t span_first[kIrrMaxLanes];
  HWY_ALIGN int32_t span_count[kIrrMaxLanes];
  uint64_t cell_steps = 0, tests = 0;
  size_t next = 0;               // next ray to stage
  size_t staged = 0, taken = 0;  // staging slots filled / used
  const size_t n = rays.size;
  for (;;) {
    // 1. free lanes take staged rays (set up, and their start cells looked up, a vector at a
    //    time)
    size_t active = 0;
    for (size_t l = 0; l < N; ++l) {
      while (ls.ray[l] < 0) {
        if (taken == staged) {
          if (next >= n) break;
          SetupRays<kAny>(d, g, rays, next, hits, occluded, &st);
          const VI sv[3] = {hn::Load(di, st.v[0]), hn::Load(di, st.v[1]), hn::Load(di, st.v[2])};
          hn::Store(LookupCells(di, g, hn::Gt(hn::Load(di, st.ray), minus1), sv), di, st.cell);
          staged = std::min(N, n - next);
          next += staged;
          taken = 0;
        }
        const size_t j = taken++;
        if (st.ray[j] >= 0) CopyLane(st, j, &ls, l);
      }
      active += ls.ray[l] >= 0;
    }
    if (active == 0) break;
    cell_steps += active;
    // 2. the current cells' records (box, bundle span); their triangles are fetched while the
    //    lanes find the next cells
    const auto live = hn::Gt(hn::Load(di, ls.ray), minus1);  // (no integer Ge in Highway 1.0.3)
    const VI cell4 = hn::ShiftLeft<2>(hn::IfThenElseZero(live, hn::Load(di, ls.cell)));
    VI blo[3], bhi[3];
    const VI low16 = hn::Set(di, 0xFFFF);
    for (int a = 0; a < 3; ++a) {
      const VI packed = hn::GatherIndex(di, cells, hn::Add(cell4, hn::Set(di, a)));
      blo[a] = hn::And(packed, low16);
      bhi[a] = hn::BitCast(di, hn::ShiftRight<16>(hn::BitCast(du, packed)));
    }
    const VI first = hn::GatherIndex(di, cells, hn::Add(cell4, hn::Set(di, 3)));
    const VI count = hn::IfThenElseZero(
        live, hn::Sub(hn::GatherIndex(di, cells, hn::Add(cell4, hn::Set(di, 7))), first));
    hn::Store(first, di, span_first);
    hn::Store(count, di, span_count);
    const uint64_t visit = LaneBits(di, hn::Gt(count, zero));
    for (uint64_t bits = visit; bits != 0; bits &= bits - 1) {
      const float* p = bundle_data + kBundleFloats * size_t(span_first[LowestLane(bits)]);
      hwy::Prefetch(p);
      hwy::Prefetch(p + 16);
    }
    // 3. exit t of the box and the next voxel (independent of the tests below)
    VI stp[3], v[3];
    VF tf[3], o[3], dir[3];
    for (int a = 0; a < 3; ++a) {
      v[a] = hn::Load(di, ls.v[a]);
      stp[a] = hn::Load(di, ls.step[a]);
      o[a] = hn::Load(d, ls.o[a]);
      dir[a] = hn::Load(d, ls.d[a]);
      const auto up = hn::Gt(stp[a], zero);
      const VI face = hn::IfThenElse(up, bhi[a], blo[a]);
      const VF t = hn::Mul(hn::Sub(hn::Add(glo[a], hn::Mul(hn::ConvertTo(d, face), gvs[a])), o[a]),
                           hn::Load(d, ls.inv[a]));
      tf[a] = hn::IfThenElse(hn::RebindMask(d, hn::Eq(stp[a], zero)), inf, t);
    }
    const VF t_exit = hn::Max(hn::Load(d, ls.t_enter), hn::Min(tf[0], hn::Min(tf[1], tf[2])));
    // exit axis, ties to the last: tf0 < tf1 ? (tf0 < tf2 ? 0 : 2) : (tf1 < tf2 ? 1 : 2)
    const auto is_x = hn::And(hn::Lt(tf[0], tf[1]), hn::Lt(tf[0], tf[2]));
    const auto is_y = hn::And(hn::Not(hn::Lt(tf[0], tf[1])), hn::Lt(tf[1], tf[2]));
    const auto ax = hn::RebindMask(di, is_x), ay = hn::RebindMask(di, is_y);
    const hn::Mask<decltype(di)> axis[3] = {ax, ay, hn::Not(hn::Or(ax, ay))};
    auto leave = hn::Not(live);
    VI nv[3];
    for (int b = 0; b < 3; ++b) {
      // other axes: the voxel of o + t_exit d clamped into the box, never behind v
      const VF p = hn::Add(o[b], hn::Mul(t_exit, dir[b]));
      const VF f = hn::Mul(hn::Sub(p, glo[b]), ginv[b]);
      const VI hi_m1 = hn::Sub(bhi[b], one);
      const VF flo = hn::ConvertTo(d, blo[b]), fhi = hn::ConvertTo(d, hi_m1);
      const auto below_hi = hn::Lt(f, fhi);
      const VI trunc = hn::ConvertTo(di, hn::IfThenElse(below_hi, f, fhi));
      const VI c = hn::IfThenElse(hn::RebindMask(di, hn::Ge(f, flo)),
                                  hn::IfThenElse(hn::RebindMask(di, below_hi), trunc, hi_m1),
                                  blo[b]);
      const auto pos = hn::Gt(stp[b], zero), neg = hn::Lt(stp[b], zero);
      nv[b] = hn::IfThenElse(pos, hn::Max(c, v[b]), hn::IfThenElse(neg, hn::Min(c, v[b]), v[b]));
      // exit axis: the face's neighbour, which may leave the lattice
      const VI across = hn::IfThenElse(pos, bhi[b], hn::Sub(blo[b], one));
      nv[b] = hn::IfThenElse(axis[b], across, nv[b]);
      leave = hn::Or(leave, hn::And(axis[b], hn::Or(hn::Lt(nv[b], zero), hn::Gt(nv[b], gres_m1[b]))));
      hn::Store(nv[b], di, ls.v[b]);
    }
    // the next cells (looked up now, used next iteration): their records are prefetched
    const VI next_cell = LookupCells(di, g, hn::Not(leave), nv);
    hn::Store(t_exit, d, t_exit_lanes);
    hn::Store(hn::VecFromMask(di, leave), di, leave_lanes);
    // 4. the current cells' triangles
    for (uint64_t bits = visit; bits != 0; bits &= bits - 1) {
      const size_t l = LowestLane(bits);
      TriBundleSpan span;
      span.vertices = bundle_data + kBundleFloats * size_t(span_first[l]);
      span.ids = bundle_ids + kBundleLanes * size_t(span_first[l]);
      span.count = size_t(span_count[l]);
      tests += SpanTriangles(span);
      if constexpr (kAny) {
        if (BundlesWidth<TriTest::kWatertight, true>(ls.prepared[l], span, ls.tmin[l],
                                                     ls.tmax[l], BundleWidth::kAuto, nullptr)) {
          occluded[ls.ray[l]] = 1;
          ls.ray[l] = -1;
        }
      } else {
        ClosestHit h;
        h.t = ls.best[l];
        h.prim = ls.prim[l];
        if (BundlesWidth<TriTest::kWatertight, false>(ls.prepared[l], span, ls.tmin[l],
                                                      ls.tmax[l], BundleWidth::kAuto, &h)) {
          ls.best[l] = h.t;
          ls.prim[l] = h.prim;
          const size_t i = size_t(ls.ray[l]);
          hits->t[i] = h.t;
          hits->u[i] = h.u;
          hits->v[i] = h.v;
          hits->prim[i] = h.prim;
        }
      }
    }
    hn::Store(next_cell, di, ls.cell);
    // 5. retire the lanes whose candidate or segment end lies before the exit, or that left
    const VF te = hn::Load(d, t_exit_lanes);
    const auto done = hn::Or(hn::Le(hn::Load(d, ls.best), te), hn::Le(hn::Load(d, ls.t1), te));
    const auto retire = hn::Or(hn::RebindMask(di, done), hn::MaskFromVec(hn::Load(di, leave_lanes)));
    hn::Store(te, d, ls.t_enter);
    hn::Store(hn::IfThenElse(retire, minus1, hn::Load(di, ls.ray)), di, ls.ray);
  }
  if (stats != nullptr) {
    stats->cell_steps += cell_steps;
    stats->triangle_tests += tests;
  }
}

void IntersectStreamIrregular(const IrregularDda& g, const RayStreamView& rays,
                              const HitStreamView& hits, TraceStats* stats) {
  StreamIrregular<false>(g, rays, &hits, nullptr, stats);
}
void OccludedStreamIrregular(const IrregularDda& g, const RayStreamView& rays, int32_t* occluded,
                             TraceStats* stats) {
  StreamIrregular<true>(g, rays, nullptr, occluded, stats);
}

}  // namespace HWY_NAMESPACE
}  // namespace rs
HWY_AFTER_NAMESPACE();

#if HWY_ONCE
namespace rs {

HWY_EXPORT(IntersectStreamIrregular);
HWY_EXPORT(OccludedStreamIrregular);

namespace {
constexpr size_t kMaxChunk = size_t{1} << 30;  // int32 ray indices in the lanes
}  // namespace

void BuildIrregularDda(const IrregularGrid& grid, const TriangleSoA& tris, IrregularDda* out,
                       int threads) {
  out->grid = &grid;
  out->tris = &tris;
  if (grid.empty()) {
    out->bundles = TriBundles();
    return;
  }
  BuildTriBundles(grid.lists, tris, &out->bundles, threads);
  out->cells = AllocateAlignedOrThrow<int32_t>(4 * (grid.num_cells + 1), "irregular cells");
  for (size_t k = 0; k <= grid.num_cells; ++k) {
    int32_t* c = out->cells.get() + 4 * k;
    for (int a = 0; a < 3; ++a) {
      c[a] = k == grid.num_cells ? 0
                                 : int32_t(uint32_t(grid.Box(uint32_t(k))[a]) |
                                           (uint32_t(grid.Box(uint32_t(k))[3 + a]) << 16));
    }
    c[3] = int32_t(out->bundles.cell_begin[k]);
  }
}

void IntersectStreamIrregular(const IrregularDda& g, const RayStreamView& rays,
                              const HitStreamView& hits, TraceStats* stats) {
  if (stats != nullptr) stats->rays += rays.size;
  if (g.empty()) {
    for (size_t i = 0; i < rays.size; ++i) {
      hits.t[i] = std::numeric_limits<float>::infinity();
      hits.u[i] = hits.v[i] = 0.0f;
      hits.prim[i] = -1;
    }
    return;
  }
  for (size_t first = 0; first < rays.size; first += kMaxChunk) {
    const RayStreamView part = SubView(rays, first, std::min(kMaxChunk, rays.size - first));
    HWY_DYNAMIC_DISPATCH(IntersectStreamIrregular)(g, part, SubView(hits, first, part.size),
                                                   stats);
  }
}

void OccludedStreamIrregular(const IrregularDda& g, const RayStreamView& rays, int32_t* occluded,
                             TraceStats* stats) {
  if (stats != nullptr) stats->rays += rays.size;
  if (g.empty()) {
    std::fill(occluded, occluded + rays.size, 0);
    return;
  }
  for (size_t first = 0; first < rays.size; first += kMaxChunk) {
    const RayStreamView part = SubView(rays, first, std::min(kMaxChunk, rays.size - first));
    HWY_DYNAMIC_DISPATCH(OccludedStreamIrregular)(g, part, occluded + first, stats);
  }
}

}  // namespace rs
#endif  // HWY_ONCE
