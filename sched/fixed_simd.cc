// ContributionsToFixed (sched/framebuffer.h): Framebuffer::ToFixed a vector of contributions at
// a time, in double (c and c * 2^32 are exact there, and rounding the exact product to the nearest
// even integer is what the scalar path's float trick does). Per-target code; foreach_target
// re-includes this file.
#include <cstddef>
#include <cstdint>

#include "sched/framebuffer.h"

#undef HWY_TARGET_INCLUDE
#define HWY_TARGET_INCLUDE "sched/fixed_simd.cc"
#include <hwy/foreach_target.h>  // IWYU pragma: keep
#include <hwy/highway.h>         // must follow foreach_target.h

HWY_BEFORE_NAMESPACE();
namespace rs {
namespace HWY_NAMESPACE {
namespace hn = hwy::HWY_NAMESPACE;

void ContributionsToFixedT(const float* r, const float* g, const float* b, const int32_t* skip,
                           size_t n, int64_t* out_r, int64_t* out_g, int64_t* out_b,
                           uint64_t* nan, uint64_t* clamped) {
  const hn::ScalableTag<double> dd;
  const hn::Rebind<float, decltype(dd)> df;
  const hn::Rebind<int32_t, decltype(dd)> di32;
  const hn::RebindToSigned<decltype(dd)> di;
  const size_t lanes = hn::Lanes(dd);
  const auto zero = hn::Zero(dd);
  const auto top = hn::Set(dd, static_cast<double>(kMaxContribution));
  const auto scale = hn::Set(dd, static_cast<double>(kFixedScale));
  // c * 2^32 <= 2^44: adding 1.5 * 2^52 rounds it to the nearest integer (ties to even: the
  // ulp there is 1) and leaves that integer in the low mantissa bits.
  const auto magic = hn::Set(dd, 6755399441055744.0);
  const auto magic_bits = hn::BitCast(di, magic);
  const auto fixed = [&](hn::Vec<decltype(dd)> c) {
    return hn::Sub(hn::BitCast(di, hn::Add(hn::Mul(c, scale), magic)), magic_bits);
  };
  const float* in[3] = {r, g, b};
  int64_t* out[3] = {out_r, out_g, out_b};
  uint64_t nans = 0, clamps = 0;
  size_t i = 0;
  for (; i + lanes <= n; i += lanes) {
    hn::Vec<decltype(dd)> v[3];
    auto ok = hn::Ne(zero, zero);  // all false
    for (int c = 0; c < 3; ++c) {
      v[c] = hn::PromoteTo(dd, hn::LoadU(df, in[c] + i));
      const auto in_range = hn::And(hn::Ge(v[c], zero), hn::Le(v[c], top));  // false for NaN
      ok = c == 0 ? in_range : hn::And(ok, in_range);
    }
    if (skip != nullptr) {
      const auto s = hn::PromoteTo(di, hn::LoadU(di32, skip + i));
      const auto unskipped = hn::RebindMask(dd, hn::Eq(s, hn::Zero(di)));
      if (hn::AllTrue(dd, hn::Or(ok, hn::Not(unskipped)))) {  // every unskipped lane in range
        const auto k = hn::RebindMask(di, unskipped);
        for (int c = 0; c < 3; ++c) hn::StoreU(hn::IfThenElseZero(k, fixed(v[c])), di, out[c] + i);
        continue;
      }
    } else if (hn::AllTrue(dd, ok)) {  // the common case: nothing to clamp or drop
      for (int c = 0; c < 3; ++c) hn::StoreU(fixed(v[c]), di, out[c] + i);
      continue;
    }
    // Some lane has a NaN or out-of-range channel.
    auto bad = hn::Ne(zero, zero);  // a NaN channel
    auto clip = bad;                // a clamped channel
    for (int c = 0; c < 3; ++c) {
      const auto is_nan = hn::IsNaN(v[c]);
      const auto low = hn::Not(hn::Ge(v[c], zero));  // negative or NaN: 0
      bad = hn::Or(bad, is_nan);
      clip = hn::Or(clip, hn::Or(hn::AndNot(is_nan, low), hn::Gt(v[c], top)));
      v[c] = hn::IfThenZeroElse(low, hn::Min(v[c], top));
    }
    auto drop = bad;
    if (skip != nullptr) {
      const auto s = hn::PromoteTo(di, hn::LoadU(di32, skip + i));
      const auto skipped = hn::RebindMask(dd, hn::Ne(s, hn::Zero(di)));
      bad = hn::AndNot(skipped, bad);
      drop = hn::Or(drop, skipped);
    }
    nans += hn::CountTrue(dd, bad);
    clamps += hn::CountTrue(dd, hn::AndNot(drop, clip));
    const auto dropi = hn::RebindMask(di, drop);
    for (int c = 0; c < 3; ++c) hn::StoreU(hn::IfThenZeroElse(dropi, fixed(v[c])), di, out[c] + i);
  }
  for (; i < n; ++i) {  // the tail, lane by lane
    int64_t f[3] = {0, 0, 0};
    if (skip == nullptr || skip[i] == 0) {
      bool clip = false;
      if (ContributionToFixed(r[i], g[i], b[i], f, &clip)) {
        clamps += clip ? 1 : 0;
      } else {
        f[0] = f[1] = f[2] = 0;
        ++nans;
      }
    }
    for (int c = 0; c < 3; ++c) out[c][i] = f[c];
  }
  *nan += nans;
  *clamped += clamps;
}

// NOLINTNEXTLINE(google-readability-namespace-comments)
}  // namespace HWY_NAMESPACE
}  // namespace rs
HWY_AFTER_NAMESPACE();

#if HWY_ONCE
namespace rs {

HWY_EXPORT(ContributionsToFixedT);

void ContributionsToFixed(const float* r, const float* g, const float* b, const int32_t* skip,
                          size_t n, int64_t* out_r, int64_t* out_g, int64_t* out_b, uint64_t* nan,
                          uint64_t* clamped) {
  HWY_DYNAMIC_DISPATCH(ContributionsToFixedT)(r, g, b, skip, n, out_r, out_g, out_b, nan, clamped);
}

}  // namespace rs
#endif  // HWY_ONCE
