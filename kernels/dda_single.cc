// The Cell paper's single-ray 3D-DDA (section 3.3, Listing 1): one ray, its x y z cell state in
// the lanes of a 4-lane vector, flat and two-level grids. Per-target code; foreach_target
// re-includes this file. Contracts in kernels/dda_simd.h.
#include "kernels/dda_simd.h"

#include <cfloat>
#include <cmath>
#include <limits>

#undef HWY_TARGET_INCLUDE
#define HWY_TARGET_INCLUDE "kernels/dda_single.cc"
#include <hwy/foreach_target.h>  // IWYU pragma: keep
#include <hwy/highway.h>         // must follow foreach_target.h

#include "kernels/tri_intersect-inl.h"
#include "kernels/two_level_dda.h"

HWY_BEFORE_NAMESPACE();
namespace rs {
namespace HWY_NAMESPACE {
namespace hn = hwy::HWY_NAMESPACE;

// The single-ray form (Cell paper, Listing 1): the ray's x y z DDA state in lanes 0..2 of one
// 4-lane vector (lane 3 is inert: t_next = +inf, never selected). The next axis comes from two
// lane rotations and compares instead of branches; cell, index and boundary t are updated with
// the selected lane's mask. Per cell the work is the same as the scalar loop's, so on a CPU with
// good branch prediction this form mostly shows what the SPE needed (it has no scalar unit).
template <bool kAny, bool kTwoLevel>
HWY_INLINE bool SingleT(const DdaGrid& g, float ox, float oy, float oz, float dx, float dy,
                        float dz, float tmin, float tmax, RayHit* hit, TraceStats* stats) {
#if HWY_TARGET == HWY_SCALAR
  // one lane: no room for x y z; the scalar DDA is the single-ray form here
  return kAny ? TraceAnyGrid(*g.grid, g.two_level, *g.tris, ox, oy, oz, dx, dy, dz, tmin, tmax,
                            stats)
              : TraceClosestGrid(*g.grid, g.two_level, *g.tris, ox, oy, oz, dx, dy, dz, tmin,
                                 tmax, hit, stats);
#else
  const Grid& grid = *g.grid;
  // the scalar DDA's prologue and start cell (kernels/dda.h), then its state in lanes 0..2
  DdaRay r;
  float t0, tmax_f;
  if (!BeginDdaRay(grid, ox, oy, oz, dx, dy, dz, tmin, tmax, &r, &t0, &tmax_f)) return false;
  const float t1 = r.t1;
  int cell0[3];
  HWY_ALIGN float tn_a[4];
  int32_t idx = int32_t(DdaStartCell(grid, r, t0, cell0, tn_a));  // simd_ok: < 2^31 cells
  const int32_t stride[3] = {1, grid.res[0], grid.res[0] * grid.res[1]};
  HWY_ALIGN int32_t cell_a[4] = {0, 0, 0, 0}, step_a[4] = {0, 0, 0, 0}, up_a[4] = {0, 0, 0, 0};
  HWY_ALIGN int32_t didx_a[4] = {0, 0, 0, 0};
  HWY_ALIGN int32_t res_m1_a[4] = {0, 0, 0, std::numeric_limits<int32_t>::max()};
  HWY_ALIGN float lo_a[4] = {0, 0, 0, 0}, cs_a[4] = {0, 0, 0, 0};
  HWY_ALIGN float o_a[4] = {0, 0, 0, 0}, inv_a[4] = {0, 0, 0, 0};
  for (int a = 0; a < 3; ++a) {
    cell_a[a] = cell0[a];
    step_a[a] = r.step[a];
    up_a[a] = r.step[a] > 0 ? 1 : 0;
    didx_a[a] = r.step[a] * stride[a];
    res_m1_a[a] = grid.res[a] - 1;
    lo_a[a] = grid.lo[a];
    cs_a[a] = grid.cell_size[a];
    o_a[a] = r.o[a];
    inv_a[a] = r.inv_d[a];
  }
  tn_a[3] = std::numeric_limits<float>::infinity();

  const hn::FixedTag<float, 4> d4;
  const hn::RebindToSigned<decltype(d4)> di4;
  auto tn = hn::Load(d4, tn_a);
  auto cell = hn::Load(di4, cell_a);
  const auto step = hn::Load(di4, step_a), up = hn::Load(di4, up_a), didx = hn::Load(di4, didx_a);
  const auto res_m1 = hn::Load(di4, res_m1_a), zero_i = hn::Zero(di4);
  const auto lo = hn::Load(d4, lo_a), cs = hn::Load(d4, cs_a), o = hn::Load(d4, o_a);
  const auto inv = hn::Load(d4, inv_a);
  // rotations: r1 = (ty, tz, tx, -), r2 = (tz, tx, ty, -)
  HWY_ALIGN static constexpr int32_t kRot1[4] = {1, 2, 0, 3};
  HWY_ALIGN static constexpr int32_t kRot2[4] = {2, 0, 1, 3};
  const auto rot1 = hn::SetTableIndices(d4, kRot1), rot2 = hn::SetTableIndices(d4, kRot2);
  // x wins iff tx < ty && tx < tz; y iff ty < tz && ty <= tx; z iff tz <= tx && tz <= ty (the
  // scalar tie rule); lane 3 compares strictly (inf < inf is false), so it never wins
  HWY_ALIGN static constexpr int32_t kStrict1[4] = {-1, -1, 0, -1};  // vs r1: x <, y <, z <=
  HWY_ALIGN static constexpr int32_t kStrict2[4] = {-1, 0, 0, -1};   // vs r2: x <, y <=, z <=
  const auto strict1 = hn::RebindMask(d4, hn::Lt(hn::Load(di4, kStrict1), zero_i));
  const auto strict2 = hn::RebindMask(d4, hn::Lt(hn::Load(di4, kStrict2), zero_i));

  const PreparedRay pray = PrepareRay(ox, oy, oz, dx, dy, dz);
  ClosestHit best;
  best.t = tmax_f;
  bool found = false;
  uint64_t steps = 0, tests = 0;
  auto visit = [&](uint32_t leaf) {
    const TriBundleSpan span = g.bundles.Cell(leaf);
    tests += SpanTriangles(span);
    if constexpr (kAny) {
      found = BundlesWidth<TriTest::kWatertight, true>(pray, span, tmin, tmax_f,
                                                       BundleWidth::kAuto, nullptr);
      return found;
    } else {
      BundlesWidth<TriTest::kWatertight, false>(pray, span, tmin, tmax_f, BundleWidth::kAuto,
                                                &best);
      return false;
    }
  };
  const uint64_t* occupancy = grid.occupancy.get();
  float t_enter = t0;
  int enter_axis = -1;
  for (;;) {
    ++steps;
    const auto r1 = hn::TableLookupLanes(tn, rot1), r2 = hn::TableLookupLanes(tn, rot2);
    const auto m1 = hn::Or(hn::And(strict1, hn::Lt(tn, r1)), hn::AndNot(strict1, hn::Le(tn, r1)));
    const auto m2 = hn::Or(hn::And(strict2, hn::Lt(tn, r2)), hn::AndNot(strict2, hn::Le(tn, r2)));
    const auto sel = hn::And(m1, m2);  // exactly one of lanes 0..2
    const auto sel_i = hn::RebindMask(di4, sel);
    // t_exit: the selected lane (the others are zeroed; x + 0 = x)
    const float t_exit = hn::GetLane(hn::SumOfLanes(d4, hn::IfThenElseZero(sel, tn)));
    if ((occupancy[uint32_t(idx) >> 6] >> (uint32_t(idx) & 63)) & 1u) {
      bool stop = false;
      if constexpr (kTwoLevel) {
        const TwoLevelGrid& two = *g.two_level;
        if (two.Refined(uint32_t(idx))) {
          stop = TraverseSubGrid(two.Record(uint32_t(idx)), r, t_enter, enter_axis, &best.t,
                                 &steps, visit) != SubExit::kLeft;
        } else {
          stop = visit(uint32_t(idx));
        }
      } else {
        stop = visit(uint32_t(idx));
      }
      if (stop) break;
    }
    if (best.t <= t_exit || t1 <= t_exit) break;
    cell = hn::Add(cell, hn::IfThenElseZero(sel_i, step));
    if (!hn::AllFalse(di4, hn::And(sel_i, hn::Or(hn::Lt(cell, zero_i), hn::Gt(cell, res_m1))))) {
      break;
    }
    idx += hn::GetLane(hn::SumOfLanes(di4, hn::IfThenElseZero(sel_i, didx)));
    const auto boundary = hn::ConvertTo(d4, hn::Add(cell, up));
    tn = hn::IfThenElse(sel, hn::Mul(hn::Sub(hn::Add(lo, hn::Mul(boundary, cs)), o), inv), tn);
    t_enter = t_exit;
    enter_axis = int(hn::FindKnownFirstTrue(d4, sel));
  }
  if (stats != nullptr) {
    stats->cell_steps += steps;
    stats->triangle_tests += tests;
  }
  if constexpr (kAny) {
    return found;
  } else {
    if (best.prim < 0) return false;
    hit->t = best.t;
    hit->u = best.u;
    hit->v = best.v;
    hit->prim = best.prim;
    return true;
  }
#endif
}

bool IntersectSingleDda(const DdaGrid& g, float ox, float oy, float oz, float dx, float dy,
                        float dz, float tmin, float tmax, RayHit* hit, TraceStats* stats) {
  if (g.two_level != nullptr) {
    return SingleT<false, true>(g, ox, oy, oz, dx, dy, dz, tmin, tmax, hit, stats);
  }
  return SingleT<false, false>(g, ox, oy, oz, dx, dy, dz, tmin, tmax, hit, stats);
}

bool OccludedSingleDda(const DdaGrid& g, float ox, float oy, float oz, float dx, float dy,
                       float dz, float tmin, float tmax, TraceStats* stats) {
  if (g.two_level != nullptr) {
    return SingleT<true, true>(g, ox, oy, oz, dx, dy, dz, tmin, tmax, nullptr, stats);
  }
  return SingleT<true, false>(g, ox, oy, oz, dx, dy, dz, tmin, tmax, nullptr, stats);
}

}  // namespace HWY_NAMESPACE
}  // namespace rs
HWY_AFTER_NAMESPACE();

#if HWY_ONCE
namespace rs {

HWY_EXPORT(IntersectSingleDda);
HWY_EXPORT(OccludedSingleDda);

bool IntersectSingleDda(const DdaGrid& g, float ox, float oy, float oz, float dx, float dy,
                        float dz, float tmin, float tmax, RayHit* hit, TraceStats* stats) {
  *hit = RayHit{std::numeric_limits<float>::infinity(), 0.0f, 0.0f, -1};
  if (stats != nullptr) ++stats->rays;
  if (g.empty()) return false;
  if (!g.simd_ok) {
    return TraceClosestGrid(*g.grid, g.two_level, *g.tris, ox, oy, oz, dx, dy, dz, tmin, tmax,
                            hit, stats);
  }
  return HWY_DYNAMIC_DISPATCH(IntersectSingleDda)(g, ox, oy, oz, dx, dy, dz, tmin, tmax, hit,
                                                  stats);
}

bool OccludedSingleDda(const DdaGrid& g, float ox, float oy, float oz, float dx, float dy,
                       float dz, float tmin, float tmax, TraceStats* stats) {
  if (stats != nullptr) ++stats->rays;
  if (g.empty()) return false;
  if (!g.simd_ok) {
    return TraceAnyGrid(*g.grid, g.two_level, *g.tris, ox, oy, oz, dx, dy, dz, tmin, tmax,
                        stats);
  }
  return HWY_DYNAMIC_DISPATCH(OccludedSingleDda)(g, ox, oy, oz, dx, dy, dz, tmin, tmax, stats);
}

}  // namespace rs
#endif  // HWY_ONCE
