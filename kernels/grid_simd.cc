// SIMD passes of the grid build (kernels/grid_binning.h): triangle bounds and bounding-box cell
// ranges, a vector of triangles at a time. Per-target code; foreach_target re-includes this file.
#include <cfloat>
#include <cstddef>
#include <cstdint>

#include "kernels/grid_binning.h"

#undef HWY_TARGET_INCLUDE
#define HWY_TARGET_INCLUDE "kernels/grid_simd.cc"
#include <hwy/foreach_target.h>  // IWYU pragma: keep
#include <hwy/highway.h>         // must follow foreach_target.h

HWY_BEFORE_NAMESPACE();
namespace rs {
namespace HWY_NAMESPACE {
namespace hn = hwy::HWY_NAMESPACE;

// Lanes [i, i + Lanes) that are real (below size) and not degenerate.
template <class D>
HWY_INLINE hn::Mask<D> ValidLanes(D d, const TriangleSoA& tris, size_t i) {
  const hn::RebindToSigned<D> di;
  const hn::Rebind<uint8_t, D> d8;
  // the degenerate flags are padded like the vertex arrays (AlignedArray), so a full load is safe
  const auto flag = hn::PromoteTo(di, hn::LoadU(d8, tris.degenerate.data() + i));
  return hn::And(hn::FirstN(d, tris.size - i), hn::RebindMask(d, hn::Eq(flag, hn::Zero(di))));
}

void SimdTriangleBounds(const TriangleSoA& tris, float lo[3], float hi[3], size_t* num_valid) {
  const hn::ScalableTag<float> d;
  const auto big = hn::Set(d, FLT_MAX), small = hn::Set(d, -FLT_MAX);
  hn::Vec<decltype(d)> vlo[3] = {big, big, big}, vhi[3] = {small, small, small};
  size_t valid = 0;
  for (size_t i = 0; i < tris.size; i += hn::Lanes(d)) {
    const auto ok = ValidLanes(d, tris, i);
    valid += hn::CountTrue(d, ok);
    for (int a = 0; a < 3; ++a) {
      const auto x0 = hn::Load(d, tris.p[0][a].data() + i);
      const auto x1 = hn::Load(d, tris.p[1][a].data() + i);
      const auto x2 = hn::Load(d, tris.p[2][a].data() + i);
      vlo[a] = hn::Min(vlo[a], hn::IfThenElse(ok, hn::Min(x0, hn::Min(x1, x2)), big));
      vhi[a] = hn::Max(vhi[a], hn::IfThenElse(ok, hn::Max(x0, hn::Max(x1, x2)), small));
    }
  }
  for (int a = 0; a < 3; ++a) {
    lo[a] = hn::GetLane(hn::MinOfLanes(d, vlo[a]));
    hi[a] = hn::GetLane(hn::MaxOfLanes(d, vhi[a]));
  }
  *num_valid = valid;
}

void SimdTriangleCellRanges(const TriangleSoA& tris, const BinGeometry& g, size_t first,
                            size_t count, RangeBlock* out) {
  const hn::ScalableTag<float> d;
  const hn::RebindToSigned<decltype(d)> di;
  const auto minus1 = hn::Set(d, -1.0f), one = hn::Set(d, 1.0f);
  const auto one_i = hn::Set(di, 1), zero_i = hn::Zero(di);
  for (size_t k = 0; k < count; k += hn::Lanes(d)) {
    const size_t i = first + k;
    const auto ok = ValidLanes(d, tris, i);
    auto flags = hn::IfThenZeroElse(hn::RebindMask(di, ok), hn::Set(di, kRangeDegenerate));
    for (int a = 0; a < 3; ++a) {
      const auto x0 = hn::Load(d, tris.p[0][a].data() + i);
      const auto x1 = hn::Load(d, tris.p[1][a].data() + i);
      const auto x2 = hn::Load(d, tris.p[2][a].data() + i);
      const auto mn = hn::Min(x0, hn::Min(x1, x2)), mx = hn::Max(x0, hn::Max(x1, x2));
      const auto lo = hn::Set(d, g.lo_f[a]), inv = hn::Set(d, g.inv_f[a]);
      const auto reach = hn::Set(d, g.reach[a]), res_f = hn::Set(d, float(g.res[a]));
      // binning::RawCell: floor(f) clamped to [-1, res] as trunc(clamp(f) + 1) - 1 (unfused,
      // as the scalar code)
      const auto f0 = hn::Sub(hn::Mul(hn::Sub(mn, lo), inv), reach);
      const auto f1 = hn::Add(hn::Mul(hn::Sub(mx, lo), inv), reach);
      const auto r0 = hn::Sub(
          hn::ConvertTo(di, hn::Add(hn::Min(hn::Max(f0, minus1), res_f), one)), one_i);
      const auto r1 = hn::Sub(
          hn::ConvertTo(di, hn::Add(hn::Min(hn::Max(f1, minus1), res_f), one)), one_i);
      const auto c0 = hn::Max(r0, zero_i);
      const auto c1 = hn::Min(r1, hn::Set(di, g.res[a] - 1));
      flags = hn::Or(flags, hn::IfThenElseZero(hn::Gt(r1, r0), hn::Set(di, 1 << a)));
      flags = hn::Or(flags, hn::IfThenElseZero(hn::Gt(c0, c1), hn::Set(di, kRangeOutside)));
      hn::StoreU(c0, di, out->c0[a] + k);
      hn::StoreU(c1, di, out->c1[a] + k);
    }
    hn::StoreU(flags, di, out->flags + k);
  }
}

}  // namespace HWY_NAMESPACE
}  // namespace rs
HWY_AFTER_NAMESPACE();

#if HWY_ONCE
namespace rs {

HWY_EXPORT(SimdTriangleBounds);
HWY_EXPORT(SimdTriangleCellRanges);

void SimdTriangleBounds(const TriangleSoA& tris, float lo[3], float hi[3], size_t* num_valid) {
  HWY_DYNAMIC_DISPATCH(SimdTriangleBounds)(tris, lo, hi, num_valid);
}

void SimdTriangleCellRanges(const TriangleSoA& tris, const BinGeometry& g, size_t first,
                            size_t count, RangeBlock* out) {
  HWY_DYNAMIC_DISPATCH(SimdTriangleCellRanges)(tris, g, first, count, out);
}

}  // namespace rs
#endif  // HWY_ONCE
