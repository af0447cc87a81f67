// PrimaryDirections (streams/raygen.h): PrimaryDirection's float sequence a vector of pixels at a
// time. Every operation is an IEEE one rounded once (no FMA contraction: the build compiles with
// -ffp-contract=off, and this file asks for it too), so each lane is PrimaryDirection's result to
// the bit on every target. Per-target code; foreach_target re-includes this file.
#if defined(__clang__)
#pragma clang fp contract(off)
#elif defined(__GNUC__)
#pragma GCC optimize("fp-contract=off")
#endif

#include <cstddef>
#include <cstdint>

#include "streams/raygen.h"

#undef HWY_TARGET_INCLUDE
#define HWY_TARGET_INCLUDE "streams/raygen_simd.cc"
#include <hwy/foreach_target.h>  // IWYU pragma: keep
#include <hwy/highway.h>         // must follow foreach_target.h

HWY_BEFORE_NAMESPACE();
namespace rs {
namespace HWY_NAMESPACE {
namespace hn = hwy::HWY_NAMESPACE;

void PrimaryDirectionsT(const CameraBasis& b, const int32_t* x, const int32_t* y, size_t n,
                        float* out_x, float* out_y, float* out_z) {
  const hn::ScalableTag<float> d;
  const hn::RebindToSigned<decltype(d)> di;
  const size_t lanes = hn::Lanes(d);
  const auto one = hn::Set(d, 1.0f), two = hn::Set(d, 2.0f);
  const auto fw = hn::Set(d, b.fwidth), fh = hn::Set(d, b.fheight);
  const auto thx = hn::Set(d, b.tan_half_x), thy = hn::Set(d, b.tan_half_y);
  size_t i = 0;
  for (; i + lanes <= n; i += lanes) {
    const auto fx = hn::ConvertTo(d, hn::LoadU(di, x + i));
    const auto fy = hn::ConvertTo(d, hn::LoadU(di, y + i));
    const auto sx = hn::Mul(hn::Sub(hn::Div(hn::Add(hn::Mul(two, fx), one), fw), one), thx);
    const auto sy = hn::Mul(hn::Sub(one, hn::Div(hn::Add(hn::Mul(two, fy), one), fh)), thy);
    hn::Vec<decltype(d)> v[3];
    for (int c = 0; c < 3; ++c) {
      v[c] = hn::Add(hn::Add(hn::Set(d, b.forward[c]), hn::Mul(sx, hn::Set(d, b.right[c]))),
                     hn::Mul(sy, hn::Set(d, b.up[c])));
    }
    const auto len =
        hn::Sqrt(hn::Add(hn::Add(hn::Mul(v[0], v[0]), hn::Mul(v[1], v[1])), hn::Mul(v[2], v[2])));
    hn::StoreU(hn::Div(v[0], len), d, out_x + i);
    hn::StoreU(hn::Div(v[1], len), d, out_y + i);
    hn::StoreU(hn::Div(v[2], len), d, out_z + i);
  }
  for (; i < n; ++i) {
    const glm::vec3 dir = PrimaryDirection(b, x[i], y[i]);
    out_x[i] = dir.x;
    out_y[i] = dir.y;
    out_z[i] = dir.z;
  }
}

// NOLINTNEXTLINE(google-readability-namespace-comments)
}  // namespace HWY_NAMESPACE
}  // namespace rs
HWY_AFTER_NAMESPACE();

#if HWY_ONCE
namespace rs {

HWY_EXPORT(PrimaryDirectionsT);

void PrimaryDirections(const CameraBasis& basis, const int32_t* x, const int32_t* y, size_t n,
                       float* dx, float* dy, float* dz) {
  HWY_DYNAMIC_DISPATCH(PrimaryDirectionsT)(basis, x, y, n, dx, dy, dz);
}

}  // namespace rs
#endif  // HWY_ONCE
