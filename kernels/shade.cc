// Shading of hit streams (see shade.h): the Highway kernel rs::Shade, compiled per target and per
// stage set, and the scalar oracle rs::ref::Shade. Both evaluate every formula with the same IEEE
// operations in the same order (no FMA: -ffp-contract=off, explicit hn::Mul/hn::Add), so a ray's
// contributions and secondary rays are bit-identical on every target. Per-target code;
// foreach_target re-includes this file.
#include "kernels/shade.h"

#include <algorithm>
#include <array>
#include <bit>
#include <cmath>
#include <cstring>
#include <limits>
#include <utility>

#undef HWY_TARGET_INCLUDE
#define HWY_TARGET_INCLUDE "kernels/shade.cc"
#include <hwy/foreach_target.h>  // IWYU pragma: keep
#include <hwy/highway.h>         // must follow foreach_target.h

#ifndef RS_KERNELS_SHADE_CC_ONCE_
#define RS_KERNELS_SHADE_CC_ONCE_
namespace rs::detail {

// Contribution arrays the kernel appends to (capacity for every contribution it may emit + one
// vector of slack from index begin on).
struct ContributionOut {
  uint32_t* pixel = nullptr;
  float* r = nullptr;
  float* g = nullptr;
  float* b = nullptr;
  size_t begin = 0;
};

// Everything the per-target kernel needs. The shadow rays toward light l are appended to
// *shadow[l * shadow_stride] (stride 0: every light to *shadow[0]), the reflection and
// refraction rays to *bounce; the streams may repeat. Each append grows its stream first when it
// lacks a vector of CompressStore slack (never, when the caller reserved for every ray).
struct ShadeArgs {
  const ShadeScene* scene = nullptr;
  const ShadeOptions* options = nullptr;
  RayStreamView rays;
  HitStreamView hits;
  ContributionOut contrib;
  size_t* contrib_end = nullptr;  // receives the end index of the contributions
  RayStream* const* shadow = nullptr;
  size_t shadow_stride = 0;
  RayStream* bounce = nullptr;
  uint32_t stages = 0;  // normalized (NormalizeStages)
  ShadeStats* stats = nullptr;
};

// The specular stage needs the shadow stage (it is part of the light loop).
constexpr uint32_t NormalizeStages(uint32_t s) {
  s &= kShadeAllStages;
  return (s & kShadeStageShadow) != 0 ? s : (s & ~static_cast<uint32_t>(kShadeStageSpecular));
}

// PhongPow constants, shared by the scalar and the vector version.
// log2(m) = kLog2Scale * f * (1 + s/3 + s^2/5 + ...), f = (m - 1) / (m + 1), s = f^2
// (atanh series; |f| <= 0.1716 for m in [sqrt(1/2), sqrt(2)], so s^5/11 ~ 2e-9 is the last term).
inline constexpr float kLog2Scale = 2.8853900817779268f;  // 2 / ln 2
inline constexpr float kAtanh3 = 1.0f / 3.0f;
inline constexpr float kAtanh5 = 1.0f / 5.0f;
inline constexpr float kAtanh7 = 1.0f / 7.0f;
inline constexpr float kAtanh9 = 1.0f / 9.0f;
inline constexpr float kAtanh11 = 1.0f / 11.0f;
inline constexpr float kSqrt2 = 1.41421356237f;
inline constexpr float kMinNormal = 1.17549435e-38f;  // 2^-126
// 2^r = sum (r ln 2)^k / k!, |r| <= 1/2: the r^9 term is < 5e-10.
inline constexpr float kExp1 = 0.693147180559945f;
inline constexpr float kExp2 = 0.240226506959101f;
inline constexpr float kExp3 = 0.0555041086648216f;
inline constexpr float kExp4 = 0.00961812910762848f;
inline constexpr float kExp5 = 0.00133335581464284f;
inline constexpr float kExp6 = 1.54035303933816e-4f;
inline constexpr float kExp7 = 1.52527338040598e-5f;
inline constexpr float kExp8 = 1.32154867901443e-6f;

// Compress permutations: row `bits` lists the lanes set in `bits` (low lane first), padded with
// lane 0. Static tables shared by every target that emits through TableLookupLanes (see Emit).
template <size_t kRows>
struct CompressTable {
  std::array<std::array<uint8_t, 8>, kRows> rows{};
};
template <size_t kLanes>
constexpr CompressTable<(size_t{1} << kLanes)> MakeCompressTable() {
  CompressTable<(size_t{1} << kLanes)> t{};
  for (size_t bits = 0; bits < (size_t{1} << kLanes); ++bits) {
    size_t k = 0;
    for (size_t lane = 0; lane < kLanes; ++lane) {
      if ((bits >> lane) & 1) t.rows[bits][k++] = static_cast<uint8_t>(lane);
    }
  }
  return t;
}
inline constexpr CompressTable<256> kCompress8 = MakeCompressTable<8>();
inline constexpr CompressTable<16> kCompress4 = MakeCompressTable<4>();

}  // namespace rs::detail
#endif  // RS_KERNELS_SHADE_CC_ONCE_

HWY_BEFORE_NAMESPACE();
namespace rs {
namespace HWY_NAMESPACE {
namespace hn = hwy::HWY_NAMESPACE;

using DF = hn::ScalableTag<float>;
using DI = hn::RebindToSigned<DF>;
using DU = hn::RebindToUnsigned<DF>;
using VF = hn::Vec<DF>;
using VI = hn::Vec<DI>;
using MF = hn::Mask<DF>;

// Three lanes-wide components (x86/NEON/WASM/SCALAR: vectors are sized types; not for SVE/RVV).
struct V3 {
  VF x, y, z;
};

// ---- vec3 helpers: each mirrors the glm expression the oracle uses, operation by operation.

HWY_INLINE V3 Set3(const glm::vec3& a) {
  const DF df;
  return {hn::Set(df, a.x), hn::Set(df, a.y), hn::Set(df, a.z)};
}
HWY_INLINE V3 Add3(const V3& a, const V3& b) {
  return {hn::Add(a.x, b.x), hn::Add(a.y, b.y), hn::Add(a.z, b.z)};
}
HWY_INLINE V3 Sub3(const V3& a, const V3& b) {
  return {hn::Sub(a.x, b.x), hn::Sub(a.y, b.y), hn::Sub(a.z, b.z)};
}
HWY_INLINE V3 Mul3(const V3& a, const V3& b) {  // componentwise
  return {hn::Mul(a.x, b.x), hn::Mul(a.y, b.y), hn::Mul(a.z, b.z)};
}
HWY_INLINE V3 Scale3(const V3& a, VF s) {  // glm vec * scalar
  return {hn::Mul(a.x, s), hn::Mul(a.y, s), hn::Mul(a.z, s)};
}
HWY_INLINE V3 DivS3(const V3& a, VF s) {  // glm vec / scalar: one division per component
  return {hn::Div(a.x, s), hn::Div(a.y, s), hn::Div(a.z, s)};
}
HWY_INLINE V3 Neg3(const V3& a) { return {hn::Neg(a.x), hn::Neg(a.y), hn::Neg(a.z)}; }
HWY_INLINE V3 Select3(MF m, const V3& a, const V3& b) {
  return {hn::IfThenElse(m, a.x, b.x), hn::IfThenElse(m, a.y, b.y), hn::IfThenElse(m, a.z, b.z)};
}
// glm::dot: (x x' + y y') + z z'.
HWY_INLINE VF Dot3(const V3& a, const V3& b) {
  return hn::Add(hn::Add(hn::Mul(a.x, b.x), hn::Mul(a.y, b.y)), hn::Mul(a.z, b.z));
}
// glm::cross.
HWY_INLINE V3 Cross3(const V3& a, const V3& b) {
  return {hn::Sub(hn::Mul(a.y, b.z), hn::Mul(b.y, a.z)),
          hn::Sub(hn::Mul(a.z, b.x), hn::Mul(b.z, a.x)),
          hn::Sub(hn::Mul(a.x, b.y), hn::Mul(b.x, a.y))};
}
// glm::normalize: v * (1 / sqrt(dot(v, v))).
HWY_INLINE V3 Normalize3(const V3& a) {
  const DF df;
  return Scale3(a, hn::Div(hn::Set(df, 1.0f), hn::Sqrt(Dot3(a, a))));
}
// b0 a + u b + v c, evaluated left to right as in the oracle.
HWY_INLINE V3 Bary3(VF b0, VF u, VF v, const V3& a, const V3& b, const V3& c) {
  return {hn::Add(hn::Add(hn::Mul(b0, a.x), hn::Mul(u, b.x)), hn::Mul(v, c.x)),
          hn::Add(hn::Add(hn::Mul(b0, a.y), hn::Mul(u, b.y)), hn::Mul(v, c.y)),
          hn::Add(hn::Add(hn::Mul(b0, a.z), hn::Mul(u, b.z)), hn::Mul(v, c.z))};
}
// std::max(a, b) = a < b ? b : a (NaN handling included).
HWY_INLINE VF MaxStd(VF a, VF b) { return hn::IfThenElse(hn::Lt(a, b), b, a); }
HWY_INLINE VF MaxChannel3(const V3& c) { return MaxStd(c.x, MaxStd(c.y, c.z)); }
// Reflect: d - (2 dot(d, n)) n.
HWY_INLINE V3 Reflect3(const V3& d, const V3& n) {
  const DF df;
  return Sub3(d, Scale3(n, hn::Mul(hn::Set(df, 2.0f), Dot3(d, n))));
}
// Snell (shade.h Refract); returns the lanes without total internal reflection.
HWY_INLINE MF Refract3(const V3& d, const V3& n, VF eta, V3* t) {
  const DF df;
  const VF one = hn::Set(df, 1.0f);
  const VF cos_i = hn::Neg(Dot3(d, n));
  const VF sin2_t = hn::Mul(hn::Mul(eta, eta), hn::Sub(one, hn::Mul(cos_i, cos_i)));
  const MF ok = hn::Not(hn::Gt(sin2_t, one));
  const VF cos_t = hn::Sqrt(hn::Sub(one, sin2_t));  // NaN on TIR lanes: masked by ok
  const VF k = hn::Sub(hn::Mul(eta, cos_i), cos_t);
  *t = Normalize3(Add3(Scale3(d, eta), Scale3(n, k)));
  return ok;
}
// FaceNormal (shade.h), lane by lane the same operations.
HWY_INLINE V3 FaceNormal3(const V3& p0, const V3& p1, const V3& p2) {
  const DF df;
  const DI di;
  const V3 e1 = Sub3(p1, p0), e2 = Sub3(p2, p0);
  const VF m = hn::Max(hn::Max(hn::Max(hn::Abs(e1.x), hn::Abs(e2.x)),
                               hn::Max(hn::Abs(e1.y), hn::Abs(e2.y))),
                       hn::Max(hn::Abs(e1.z), hn::Abs(e2.z)));
  VI e = hn::And(hn::ShiftRight<23>(hn::BitCast(di, m)), hn::Set(di, 0xFF));
  e = hn::Min(hn::Max(e, hn::Set(di, 1)), hn::Set(di, 253));
  const VF scale = hn::BitCast(df, hn::ShiftLeft<23>(hn::Sub(hn::Set(di, 254), e)));
  return Normalize3(Cross3(Scale3(e1, scale), Scale3(e2, scale)));
}
// PowerOfTwoFloor (shade.h), lane by lane.
HWY_INLINE VF PowerOfTwoFloor3(VF m) {
  const DF df;
  const DI di;
  VI e = hn::And(hn::ShiftRight<23>(hn::BitCast(di, m)), hn::Set(di, 0xFF));
  e = hn::Min(hn::Max(e, hn::Set(di, 1)), hn::Set(di, 254));
  return hn::BitCast(df, hn::ShiftLeft<23>(e));
}
// OffsetUnit of the triangles (p0, p1, p2), lane by lane.
HWY_INLINE VF OffsetUnit3(const V3& p0, const V3& p1, const V3& p2) {
  const auto max3 = [](const V3& p) {
    return hn::Max(hn::Abs(p.x), hn::Max(hn::Abs(p.y), hn::Abs(p.z)));
  };
  return PowerOfTwoFloor3(hn::Max(max3(p0), hn::Max(max3(p1), max3(p2))));
}
// OffsetRayOrigin (shade.h), lane by lane the same operations.
HWY_INLINE V3 OffsetRayOrigin3(const V3& p, const V3& n, VF unit, VF light_unit) {
  const DF df;
  const VF step = hn::Add(hn::Mul(unit, hn::Set(df, 1.0f / 524288.0f)),
                          hn::Mul(light_unit, hn::Set(df, 1.0f / 262144.0f)));
  return {hn::Add(p.x, hn::Mul(step, n.x)), hn::Add(p.y, hn::Mul(step, n.y)),
          hn::Add(p.z, hn::Mul(step, n.z))};
}
// LightOffsetUnit (shade.h), lane by lane.
HWY_INLINE VF LightOffsetUnit3(const V3& p, std::span<const PointLight> lights) {
  const DF df;
  if (lights.empty()) return hn::Zero(df);
  VF m = hn::Zero(df);
  for (const PointLight& l : lights) {
    m = hn::Max(m, hn::Abs(hn::Sub(hn::Set(df, l.position.x), p.x)));
    m = hn::Max(m, hn::Abs(hn::Sub(hn::Set(df, l.position.y), p.y)));
    m = hn::Max(m, hn::Abs(hn::Sub(hn::Set(df, l.position.z), p.z)));
  }
  return PowerOfTwoFloor3(m);
}

// PhongPow, lane by lane the same operations as the scalar rs::PhongPow (HWY_ONCE below).
HWY_INLINE VF PhongPowV(VF x, VF e) {
  namespace c = detail;
  const DF df;
  const DI di;
  const VF one = hn::Set(df, 1.0f);
  const MF positive = hn::Gt(x, hn::Zero(df));
  // Subnormal x: scale by 2^24 (exact) so the exponent field is meaningful.
  const MF sub = hn::Lt(x, hn::Set(df, c::kMinNormal));
  const VF xs = hn::IfThenElse(sub, hn::Mul(x, hn::Set(df, 16777216.0f)), x);
  const VI k_adj = hn::IfThenElseZero(hn::RebindMask(di, sub), hn::Set(di, -24));
  const VI bits = hn::BitCast(di, xs);
  VI k = hn::Add(hn::Sub(hn::And(hn::ShiftRight<23>(bits), hn::Set(di, 0xff)), hn::Set(di, 127)),
                 k_adj);
  VF m = hn::BitCast(df, hn::Or(hn::And(bits, hn::Set(di, 0x007fffff)), hn::Set(di, 0x3f800000)));
  const MF big = hn::Gt(m, hn::Set(df, c::kSqrt2));  // m in [1, 2) -> [sqrt(1/2), sqrt(2)]
  m = hn::IfThenElse(big, hn::Mul(m, hn::Set(df, 0.5f)), m);
  k = hn::IfThenElse(hn::RebindMask(di, big), hn::Add(k, hn::Set(di, 1)), k);
  const VF f = hn::Div(hn::Sub(m, one), hn::Add(m, one));
  const VF s = hn::Mul(f, f);
  VF poly = hn::Add(hn::Set(df, c::kAtanh9), hn::Mul(s, hn::Set(df, c::kAtanh11)));
  poly = hn::Add(hn::Set(df, c::kAtanh7), hn::Mul(s, poly));
  poly = hn::Add(hn::Set(df, c::kAtanh5), hn::Mul(s, poly));
  poly = hn::Add(hn::Set(df, c::kAtanh3), hn::Mul(s, poly));
  poly = hn::Add(one, hn::Mul(s, poly));
  const VF log2x =
      hn::Add(hn::ConvertTo(df, k), hn::Mul(hn::Mul(hn::Set(df, c::kLog2Scale), f), poly));
  VF y = hn::Mul(e, log2x);
  y = hn::IfThenElseZero(hn::Eq(y, y), y);  // NaN (1^inf) -> 2^0
  const MF under = hn::Lt(y, hn::Set(df, -126.0f));
  y = hn::IfThenElse(hn::Lt(y, hn::Set(df, 127.0f)), y, hn::Set(df, 127.0f));
  const VF n = hn::Floor(hn::Add(y, hn::Set(df, 0.5f)));
  const VF r = hn::Sub(y, n);
  VF p = hn::Add(hn::Set(df, c::kExp7), hn::Mul(r, hn::Set(df, c::kExp8)));
  p = hn::Add(hn::Set(df, c::kExp6), hn::Mul(r, p));
  p = hn::Add(hn::Set(df, c::kExp5), hn::Mul(r, p));
  p = hn::Add(hn::Set(df, c::kExp4), hn::Mul(r, p));
  p = hn::Add(hn::Set(df, c::kExp3), hn::Mul(r, p));
  p = hn::Add(hn::Set(df, c::kExp2), hn::Mul(r, p));
  p = hn::Add(hn::Set(df, c::kExp1), hn::Mul(r, p));
  p = hn::Add(one, hn::Mul(r, p));
  // 2^n for n in [-126, 127]: exponent field n + 127.
  const VF scale =
      hn::BitCast(df, hn::ShiftLeft<23>(hn::Add(hn::ConvertTo(di, n), hn::Set(di, 127))));
  return hn::IfThenElseZero(hn::AndNot(under, positive), hn::Mul(p, scale));
}

// ---- output streams (contributions and secondary rays)

// Packs the lanes of a mask to the front of whole-vector stores, the same lanes for every
// array of an emission, and counts them. Highway 1.0.3's CompressStore is slow on both x86
// families we target, differently:
// - AVX2/SSE4: it decodes a function-local (non-static) constexpr table that GCC 12 copies to
//   the stack on every call (rep movsq, 1 KiB on AVX2): with 14 arrays per emission AVX2 ran at
//   half the speed of SSE4. Here: one permutation per mask from a static table, applied to
//   every array with TableLookupLanes.
// - AVX3: it is vcompressps with a memory operand, microcoded on AMD Zen 4: 56-61 TSC ticks a
//   store on this project's AVX-512 host, against 3.8 for vcompressps into a register plus a
//   store (a loop of 4 M 16-lane stores with random masks; load 0.56). Here: Compress, then
//   StoreU.
// SCALAR: one lane. Every store may write up to a vector of garbage past the packed lanes,
// which the output streams have room for.
class LanePacker {
 public:
  explicit LanePacker(MF m) : m_(m) {
#if HWY_TARGET == HWY_AVX2 || HWY_TARGET == HWY_SSE4 || HWY_TARGET == HWY_SSSE3
    const DF df;
    const DI di;
    uint8_t bits[8] = {};
    hn::StoreMaskBits(df, m, bits);
#if HWY_TARGET == HWY_AVX2
    const uint8_t* row = detail::kCompress8.rows[bits[0]].data();
#else
    const uint8_t* row = detail::kCompress4.rows[bits[0] & 15].data();
#endif
    count_ = static_cast<size_t>(std::popcount(static_cast<unsigned>(bits[0])));
    const hn::Rebind<uint8_t, DF> d8;
    idx_ = hn::IndicesFromVec(df, hn::PromoteTo(di, hn::LoadU(d8, row)));
#else
    count_ = hn::CountTrue(DF(), m);
#endif
  }
  size_t count() const { return count_; }

  // v (float, int32 or uint32 lanes) packed and stored at p.
  template <class V, typename T>
  void Store(V v, T* p) const {
    static_assert(sizeof(T) == sizeof(float));
    const DF df;
    const VF f = hn::BitCast(df, v);
#if HWY_TARGET == HWY_AVX2 || HWY_TARGET == HWY_SSE4 || HWY_TARGET == HWY_SSSE3
    hn::StoreU(hn::TableLookupLanes(f, idx_), df, reinterpret_cast<float*>(p));
#else
    hn::StoreU(hn::Compress(f, m_), df, reinterpret_cast<float*>(p));
#endif
  }

 private:
  MF m_;
  size_t count_ = 0;
#if HWY_TARGET == HWY_AVX2 || HWY_TARGET == HWY_SSE4 || HWY_TARGET == HWY_SSSE3
  decltype(hn::IndicesFromVec(DF(), hn::Zero(DI()))) idx_;
#endif
};

// One contribution (pixel, c) per lane of m, appended at index pos with the lanes packed to the
// front (lane order); may write up to a vector of garbage past the new end, which `out` has
// room for. Returns the new end.
HWY_INLINE size_t EmitContributions(MF m, const V3& c, hn::Vec<DU> pixel,
                                    const detail::ContributionOut& out, size_t pos) {
  static_assert(HWY_MAX_BYTES <= kStreamPad * sizeof(float), "slack below one vector");
  const LanePacker pack(m);
  pack.Store(pixel, out.pixel + pos);
  pack.Store(c.x, out.r + pos);
  pack.Store(c.y, out.g + pos);
  pack.Store(c.z, out.b + pos);
  return pos + pack.count();
}

// One secondary ray per lane of m, appended at out[pos] with its live lanes packed to the front;
// may write up to a vector of garbage past the new end, which `out` has room for.
HWY_INLINE size_t Emit(MF m, const V3& o, const V3& d, VF tmin, VF tmax, hn::Vec<DU> pixel,
                       const V3& w, VI depth, VI kind, const RayStreamView& out, size_t pos) {
  const LanePacker pack(m);
  pack.Store(o.x, out.ox + pos);
  pack.Store(o.y, out.oy + pos);
  pack.Store(o.z, out.oz + pos);
  pack.Store(d.x, out.dx + pos);
  pack.Store(d.y, out.dy + pos);
  pack.Store(d.z, out.dz + pos);
  pack.Store(tmin, out.tmin + pos);
  pack.Store(tmax, out.tmax + pos);
  pack.Store(pixel, out.pixel + pos);
  pack.Store(w.x, out.wr + pos);
  pack.Store(w.y, out.wg + pos);
  pack.Store(w.z, out.wb + pos);
  pack.Store(depth, out.depth + pos);
  pack.Store(kind, out.kind + pos);
  return pos + pack.count();
}

// Emit at the end of `to`, grown first if it lacks room for a vector; returns the rays added.
HWY_INLINE size_t EmitTo(RayStream& to, MF m, const V3& o, const V3& d, VF tmin, VF tmax,
                         hn::Vec<DU> pixel, const V3& w, VI depth, VI kind) {
  const size_t at = to.size();
  if (at + kStreamPad > to.capacity()) to.Reserve(2 * (at + kStreamPad));
  const size_t end = Emit(m, o, d, tmin, tmax, pixel, w, depth, kind, to.view(), at);
  to.Resize(end);
  return end - at;
}

// ---- textures

// i in [-1, n] wrapped to [0, n): the oracle's ((i % n) + n) % n on that range.
HWY_INLINE VI WrapIndex(VI i, int32_t n) {
  const DI di;
  const VI vn = hn::Set(di, n);
  const VI below = hn::IfThenElse(hn::Lt(i, hn::Zero(di)), hn::Add(i, vn), i);
  return hn::IfThenElse(hn::Gt(below, hn::Set(di, n - 1)), hn::Sub(below, vn), below);
}

HWY_INLINE V3 Texel(const float* rgb, VI row, VI x) {
  const DF df;
  const VI k = hn::Add(row, x);
  const VI idx = hn::Add(hn::Add(k, k), k);
  const DI di;
  return {hn::GatherIndex(df, rgb, idx), hn::GatherIndex(df, rgb, hn::Add(idx, hn::Set(di, 1))),
          hn::GatherIndex(df, rgb, hn::Add(idx, hn::Set(di, 2)))};
}

// SampleTexture (shade.h) for one valid texture with width, height < 2^22 and w h 3 < 2^31.
// Every lane computes in-range indices (u, v are wrapped to [0, 1] first), so lanes that do not
// use this texture are harmless.
HWY_INLINE V3 SampleTextureV(const Texture& t, VF uvx, VF uvy) {
  const DF df;
  const DI di;
  const VF one = hn::Set(df, 1.0f);
  const VF half = hn::Set(df, 0.5f);
  const VF inf = hn::Set(df, std::numeric_limits<float>::infinity());
  const VF u = hn::IfThenElseZero(hn::Lt(hn::Abs(uvx), inf), hn::Sub(uvx, hn::Floor(uvx)));
  const VF v = hn::IfThenElseZero(hn::Lt(hn::Abs(uvy), inf), hn::Sub(uvy, hn::Floor(uvy)));
  const VF x = hn::Sub(hn::Mul(u, hn::Set(df, static_cast<float>(t.width))), half);
  const VF y = hn::Sub(hn::Mul(hn::Sub(one, v), hn::Set(df, static_cast<float>(t.height))), half);
  const VF fx0 = hn::Floor(x);
  const VF fy0 = hn::Floor(y);
  const VF fx = hn::Sub(x, fx0);
  const VF fy = hn::Sub(y, fy0);
  const VI ix = hn::ConvertTo(di, fx0);
  const VI iy = hn::ConvertTo(di, fy0);
  const VI x0 = WrapIndex(ix, t.width);
  const VI x1 = WrapIndex(hn::Add(ix, hn::Set(di, 1)), t.width);
  const VI w = hn::Set(di, t.width);
  const VI row0 = hn::Mul(WrapIndex(iy, t.height), w);
  const VI row1 = hn::Mul(WrapIndex(hn::Add(iy, hn::Set(di, 1)), t.height), w);
  const float* rgb = t.rgb.data();
  const VF omfx = hn::Sub(one, fx);
  const VF omfy = hn::Sub(one, fy);
  const V3 top = Add3(Scale3(Texel(rgb, row0, x0), omfx), Scale3(Texel(rgb, row0, x1), fx));
  const V3 bottom = Add3(Scale3(Texel(rgb, row1, x0), omfx), Scale3(Texel(rgb, row1, x1), fx));
  return Add3(Scale3(top, omfy), Scale3(bottom, fy));
}

// kd *= texture colour on the lanes of `fetch`, one pass per distinct texture among them
// (streams are usually coherent: one or two textures per vector).
HWY_INLINE V3 ApplyTextures(const ShadeScene& scene, MF fetch, VI tex, VF uvx, VF uvy, V3 kd) {
  const DF df;
  const DI di;
  HWY_ALIGN int32_t tex_lane[kStreamPad];
  hn::Store(tex, di, tex_lane);
  MF pending = fetch;
  while (!hn::AllFalse(df, pending)) {
    const int32_t id = tex_lane[hn::FindKnownFirstTrue(df, pending)];
    const MF m = hn::And(pending, hn::RebindMask(df, hn::Eq(tex, hn::Set(di, id))));
    pending = hn::AndNot(m, pending);
    const Texture& t = scene.textures[static_cast<size_t>(id)];
    const size_t texels = static_cast<size_t>(std::max(t.width, 0)) *
                          static_cast<size_t>(std::max(t.height, 0));
    V3 c;
    if (t.width <= 0 || t.height <= 0 || t.rgb.size() < texels * 3) {
      c = Set3(glm::vec3(1.0f));  // SampleTexture's white: kd * 1 == kd
    } else if (t.width < (1 << 22) && t.height < (1 << 22) &&
               texels * 3 < (size_t{1} << 31)) {
      c = SampleTextureV(t, uvx, uvy);
    } else {  // huge texture: the scalar sampler per lane (same result, no int32 overflow)
      HWY_ALIGN float us[kStreamPad], vs[kStreamPad], cr[kStreamPad], cg[kStreamPad],
          cb[kStreamPad];
      hn::Store(uvx, df, us);
      hn::Store(uvy, df, vs);
      for (size_t j = 0; j < hn::Lanes(df); ++j) {
        const glm::vec3 sj = SampleTexture(t, glm::vec2(us[j], vs[j]));
        cr[j] = sj.x;
        cg[j] = sj.y;
        cb[j] = sj.z;
      }
      c = {hn::Load(df, cr), hn::Load(df, cg), hn::Load(df, cb)};
    }
    kd = Select3(m, Mul3(kd, c), kd);
  }
  return kd;
}

// ---- the kernel, one instantiation per (normalized) stage set

template <uint32_t kStages>
HWY_NOINLINE void ShadeBlocks(const detail::ShadeArgs& a) {
  constexpr bool kShadow = (kStages & kShadeStageShadow) != 0;
  constexpr bool kSpecular = (kStages & kShadeStageSpecular) != 0;
  constexpr bool kTexture = (kStages & kShadeStageTexture) != 0;
  constexpr bool kReflection = (kStages & kShadeStageReflection) != 0;
  constexpr bool kRefraction = (kStages & kShadeStageRefraction) != 0;
  const DF df;
  const DI di;
  const DU du;
  const size_t lanes = hn::Lanes(df);
  const ShadeScene& scene = *a.scene;
  const RayStreamView& rays = a.rays;
  const HitStreamView& hits = a.hits;
  ShadeStats& s = *a.stats;
  size_t cpos = a.contrib.begin;

  const bool smooth = !scene.normals.empty();
  const bool textured = kTexture && !scene.uvs.empty();
  const glm::vec3 bg = scene.background;
  const bool background = std::max(bg.x, std::max(bg.y, bg.z)) > 0.0f;
  const V3 background3 = Set3(bg);
  const VF zero = hn::Zero(df);
  const VF one = hn::Set(df, 1.0f);
  const VF inf = hn::Set(df, std::numeric_limits<float>::infinity());
  const VF cutoff = hn::Set(df, a.options->weight_cutoff);
  const VI max_depth = hn::Set(di, a.options->max_depth);

  // Gather bases. Triangles are uvec3, positions/normals vec3, uvs vec2: tightly packed.
  static_assert(sizeof(glm::uvec3) == 3 * sizeof(int32_t) && sizeof(glm::vec3) == 12 &&
                sizeof(glm::vec2) == 8);
  static_assert(sizeof(Material) % sizeof(float) == 0);
  const bool any_triangle = !scene.triangles.empty() && !scene.materials.empty();
  const int32_t* tri_base =
      any_triangle ? reinterpret_cast<const int32_t*>(&scene.triangles[0].x) : nullptr;
  const float* pos_base = scene.positions.empty() ? nullptr : &scene.positions[0].x;
  const float* nrm_base = smooth ? &scene.normals[0].x : nullptr;
  const float* uv_base = textured ? &scene.uvs[0].x : nullptr;
  const int32_t* mid_base =
      any_triangle ? reinterpret_cast<const int32_t*>(scene.material_ids.data()) : nullptr;
  // Material fields are gathered relative to materials[0].diffuse.x with a stride of
  // sizeof(Material) / 4 floats (every field read is a float or an int32).
  const Material* m0 = any_triangle ? &scene.materials[0] : nullptr;
  const float* mat_base = any_triangle ? &m0->diffuse.x : nullptr;
  auto field = [&](const void* f) {
    return static_cast<int32_t>((static_cast<const char*>(f) -
                                 reinterpret_cast<const char*>(mat_base)) / sizeof(float));
  };
  const int32_t off_spec = any_triangle ? field(&m0->specular.x) : 0;
  const int32_t off_shin = any_triangle ? field(&m0->shininess) : 0;
  const int32_t off_refl = any_triangle ? field(&m0->reflectivity) : 0;
  const int32_t off_trans = any_triangle ? field(&m0->transmission) : 0;
  const int32_t off_ior = any_triangle ? field(&m0->ior) : 0;
  const int32_t off_tex = any_triangle ? field(&m0->texture) : 0;
  const int32_t mat_stride = static_cast<int32_t>(sizeof(Material) / sizeof(float));
  const VI num_textures = hn::Set(di, static_cast<int32_t>(scene.textures.size()));
  auto gather_f = [&](const float* base, VI idx, int32_t off) {
    return hn::GatherIndex(df, base, hn::Add(idx, hn::Set(di, off)));
  };
  auto gather3 = [&](const float* base, VI idx3) {
    return V3{gather_f(base, idx3, 0), gather_f(base, idx3, 1), gather_f(base, idx3, 2)};
  };

  for (size_t i = 0; i < rays.size; i += lanes) {
    const MF live = hn::FirstN(df, rays.size - i);
    const VI prim = hn::Load(di, hits.prim + i);
    const MF hit = hn::And(live, hn::RebindMask(df, hn::Gt(prim, hn::Set(di, -1))));
    const MF miss = hn::AndNot(hit, live);
    const V3 w{hn::Load(df, rays.wr + i), hn::Load(df, rays.wg + i), hn::Load(df, rays.wb + i)};
    const hn::Vec<DU> pixel_v = hn::Load(du, rays.pixel + i);

    // miss -> w * background
    if (!hn::AllFalse(df, miss)) {
      s.misses += hn::CountTrue(df, miss);
      if (background) {
        cpos = EmitContributions(miss, Mul3(w, background3), pixel_v, a.contrib, cpos);
      }
    }
    if (hn::AllFalse(df, hit)) continue;  // Embree-style early out: nothing to shade
    ++s.blocks;
    s.shading_calls += hn::CountTrue(df, hit);
    HWY_DASSERT(any_triangle);

    // Triangle vertices by prim id (dead lanes read triangle 0).
    const VI pidx = hn::IfThenElseZero(hn::RebindMask(di, hit), prim);
    const VI p3 = hn::Add(hn::Add(pidx, pidx), pidx);
    const VI t0 = hn::GatherIndex(di, tri_base, p3);
    const VI t1 = hn::GatherIndex(di, tri_base, hn::Add(p3, hn::Set(di, 1)));
    const VI t2 = hn::GatherIndex(di, tri_base, hn::Add(p3, hn::Set(di, 2)));
    const VI v0 = hn::Add(hn::Add(t0, t0), t0);
    const VI v1 = hn::Add(hn::Add(t1, t1), t1);
    const VI v2 = hn::Add(hn::Add(t2, t2), t2);
    const V3 p0 = gather3(pos_base, v0);
    const V3 p1 = gather3(pos_base, v1);
    const V3 p2 = gather3(pos_base, v2);

    // p from barycentrics (error relative to the vertices, which the offset covers).
    const VF u = hn::Load(df, hits.u + i);
    const VF v = hn::Load(df, hits.v + i);
    const VF b0 = hn::Sub(hn::Sub(one, u), v);
    const V3 p = Bary3(b0, u, v, p0, p1, p2);
    const V3 d = Normalize3(
        V3{hn::Load(df, rays.dx + i), hn::Load(df, rays.dy + i), hn::Load(df, rays.dz + i)});

    // Geometric normal by winding, flipped to face the ray.
    const V3 n_face = FaceNormal3(p0, p1, p2);
    const MF entering = hn::Lt(Dot3(d, n_face), zero);
    const V3 ng = Select3(entering, n_face, Neg3(n_face));
    V3 ns = ng;
    if (smooth) {  // interpolated vertex normal, same hemisphere as ng; degenerate -> ng
      const V3 n = Bary3(b0, u, v, gather3(nrm_base, v0), gather3(nrm_base, v1),
                         gather3(nrm_base, v2));
      const VF len2 = Dot3(n, n);
      const MF good = hn::And(hn::Gt(len2, hn::Set(df, 1e-20f)), hn::Lt(len2, inf));
      V3 nn = DivS3(n, hn::Sqrt(len2));
      nn = Select3(hn::Lt(Dot3(nn, ng), zero), Neg3(nn), nn);
      ns = Select3(good, nn, ng);
    }

    // Material by triangle.
    const VI mid = hn::GatherIndex(di, mid_base, pidx);
    const VI midx = hn::Mul(mid, hn::Set(di, mat_stride));
    V3 kd = gather3(mat_base, midx);
    const VF refl = gather_f(mat_base, midx, off_refl);
    const VF trans = gather_f(mat_base, midx, off_trans);
    V3 spec{zero, zero, zero};
    if constexpr (kSpecular || kReflection) {
      spec = V3{gather_f(mat_base, midx, off_spec), gather_f(mat_base, midx, off_spec + 1),
                gather_f(mat_base, midx, off_spec + 2)};
    }
    if constexpr (kTexture) {
      if (textured) {
        const VI tex = hn::GatherIndex(di, reinterpret_cast<const int32_t*>(mat_base),
                                       hn::Add(midx, hn::Set(di, off_tex)));
        const MF fetch = hn::And(
            hit, hn::RebindMask(df, hn::And(hn::Gt(tex, hn::Set(di, -1)), hn::Lt(tex, num_textures))));
        if (!hn::AllFalse(df, fetch)) {
          ++s.stage_runs[2];
          s.texture_fetches += hn::CountTrue(df, fetch);
          // uv = b0 uv0 + u uv1 + v uv2 (glm vec2, left to right).
          auto uv_at = [&](int32_t c) {
            return hn::Add(hn::Add(hn::Mul(b0, gather_f(uv_base, hn::Add(t0, t0), c)),
                                   hn::Mul(u, gather_f(uv_base, hn::Add(t1, t1), c))),
                           hn::Mul(v, gather_f(uv_base, hn::Add(t2, t2), c)));
          };
          kd = ApplyTextures(scene, fetch, tex, uv_at(0), uv_at(1), kd);
        }
      }
    }

    // The origin on the incoming side, shared by shadow and reflection rays.
    const VF unit = OffsetUnit3(p0, p1, p2);
    VF light_unit = hn::Zero(df);  // shadow rays end at front: their lights' distance counts
    if constexpr (kShadow) light_unit = LightOffsetUnit3(p, scene.lights);
    const V3 front = OffsetRayOrigin3(p, ng, unit, light_unit);
    // local = clamp((1 - reflectivity) - transmission, 0, 1), std::clamp's NaN behaviour.
    VF local = hn::Sub(hn::Sub(one, refl), trans);
    local = hn::IfThenElse(hn::Lt(local, zero), zero, hn::IfThenElse(hn::Lt(one, local), one, local));
    const MF lit = hn::And(hit, hn::Gt(local, zero));
    const VI depth = hn::Load(di, rays.depth + i);
    if (!hn::AllFalse(df, lit)) {
      const V3 wl = Scale3(w, local);
      const V3 ambient = Mul3(Scale3(wl, hn::Set(df, scene.ambient)), kd);
      cpos = EmitContributions(hn::And(lit, hn::Gt(MaxChannel3(ambient), zero)), ambient, pixel_v,
                               a.contrib, cpos);

      if constexpr (kShadow) {
        ++s.stage_runs[0];
        const size_t lit_count = hn::CountTrue(df, lit);
        [[maybe_unused]] MF highlight = lit;  // lanes with a phong highlight (kSpecular)
        [[maybe_unused]] VF shininess = zero;
        if constexpr (kSpecular) {
          shininess = gather_f(mat_base, midx, off_shin);
          highlight = hn::And(lit, hn::And(hn::Gt(shininess, zero),
                                           hn::Gt(MaxChannel3(spec), zero)));
        }
        const V3 view = Neg3(d);
        const VF shadow_tmin = hn::Set(df, kShadowTmin), shadow_tmax = hn::Set(df, 1.0f);
        const VI shadow_kind = hn::Set(di, static_cast<int32_t>(RayKind::kShadow));
        for (size_t li = 0; li < scene.lights.size(); ++li) {
          const PointLight& light = scene.lights[li];
          s.light_tests += lit_count;
          const V3 lpos = Set3(light.position);
          const V3 to_light = Sub3(lpos, p);
          const VF dist2 = Dot3(to_light, to_light);
          MF ok = hn::And(lit, hn::Gt(dist2, zero));
          if (hn::AllFalse(df, ok)) continue;
          const V3 l = DivS3(to_light, hn::Sqrt(dist2));
          // Above the surface: incoming side of ng (no crossing) and of ns.
          const VF cos_ns = Dot3(ns, l);
          ok = hn::AndNot(hn::Le(Dot3(ng, l), zero), ok);
          ok = hn::AndNot(hn::Le(cos_ns, zero), ok);
          if (hn::AllFalse(df, ok)) continue;
          V3 c = Scale3(kd, cos_ns);
          if constexpr (kSpecular) {
            const MF hl = hn::And(ok, highlight);
            if (!hn::AllFalse(df, hl)) {
              ++s.stage_runs[1];
              s.highlights += hn::CountTrue(df, hl);
              const VF rv = MaxStd(zero, Dot3(Reflect3(Neg3(l), ns), view));
              const VF pw = PhongPowV(rv, shininess);
              c = Select3(hl, Add3(c, Scale3(spec, pw)), c);
            }
          }
          VF atten = one;
          if (light.falloff > 0.0f) {
            atten = hn::Div(one, hn::Add(one, hn::Mul(hn::Set(df, light.falloff), dist2)));
          }
          const V3 contrib = Mul3(Scale3(Mul3(c, Set3(light.color)), atten), wl);
          const MF spawn = hn::And(ok, hn::Gt(MaxChannel3(contrib), zero));
          if (hn::AllFalse(df, spawn)) continue;
          s.spawned[static_cast<int>(RayKind::kShadow)] +=
              EmitTo(*a.shadow[li * a.shadow_stride], spawn, lpos, Sub3(front, lpos),
                     shadow_tmin, shadow_tmax, pixel_v, contrib, depth, shadow_kind);
        }
      }
    }

    if constexpr (kReflection || kRefraction) {
      const MF bounce = hn::And(hit, hn::RebindMask(df, hn::Lt(depth, max_depth)));
      if (hn::AllFalse(df, bounce)) continue;
      const VI depth1 = hn::Add(depth, hn::Set(di, 1));
      // Mirror direction about ns, or about ng where ns bent it below the surface.
      auto mirror = [&]() {
        const V3 r = Reflect3(d, ns);
        return Select3(hn::Le(Dot3(r, ng), zero), Reflect3(d, ng), r);
      };
      if constexpr (kReflection) {
        const MF rl = hn::And(bounce, hn::Gt(refl, zero));
        if (!hn::AllFalse(df, rl)) {
          ++s.stage_runs[3];
          const V3 tint = Select3(hn::Gt(MaxChannel3(spec), zero), spec, V3{one, one, one});
          const V3 wr = Mul3(Scale3(w, refl), tint);
          const MF pass = hn::Ge(MaxChannel3(wr), cutoff);
          s.culled += hn::CountTrue(df, hn::AndNot(pass, rl));
          const MF go = hn::And(rl, pass);
          if (!hn::AllFalse(df, go)) {
            s.spawned[static_cast<int>(RayKind::kReflection)] +=
                EmitTo(*a.bounce, go, front, mirror(), zero, inf, pixel_v, wr, depth1,
                       hn::Set(di, static_cast<int32_t>(RayKind::kReflection)));
          }
        }
      }
      if constexpr (kRefraction) {
        const MF tl = hn::And(bounce, hn::Gt(trans, zero));
        if (!hn::AllFalse(df, tl)) {
          ++s.stage_runs[4];
          const V3 wt = Scale3(w, trans);
          const MF pass = hn::Ge(MaxChannel3(wt), cutoff);
          s.culled += hn::CountTrue(df, hn::AndNot(pass, tl));
          const MF go = hn::And(tl, pass);
          if (!hn::AllFalse(df, go)) {
            // Entering goes from 1 into ior, leaving from ior into 1.
            const VF ior = gather_f(mat_base, midx, off_ior);
            const VF eta = hn::IfThenElse(entering, hn::Div(one, ior), ior);
            const V3 nr = Select3(hn::Lt(Dot3(d, ns), zero), ns, ng);
            V3 t_ns, t_ng;
            const MF ok_ns = Refract3(d, nr, eta, &t_ns);
            const MF ok_ng = Refract3(d, ng, eta, &t_ng);
            // Bent to the wrong side by ns: refract about ng instead (which may be TIR).
            const MF redo = hn::And(ok_ns, hn::Ge(Dot3(t_ns, ng), zero));
            const MF through = hn::Or(hn::And(redo, ok_ng), hn::AndNot(redo, ok_ns));
            const V3 t = Select3(redo, t_ng, t_ns);
            // Total internal reflection: a reflection ray from the front side.
            const V3 origin =
                Select3(through, OffsetRayOrigin3(p, Neg3(ng), unit, hn::Zero(df)), front);
            const V3 dir = Select3(through, t, mirror());
            const VI kind = hn::IfThenElse(
                hn::RebindMask(di, through), hn::Set(di, static_cast<int32_t>(RayKind::kRefraction)),
                hn::Set(di, static_cast<int32_t>(RayKind::kReflection)));
            s.spawned[static_cast<int>(RayKind::kRefraction)] +=
                hn::CountTrue(df, hn::And(go, through));
            s.spawned[static_cast<int>(RayKind::kReflection)] +=
                hn::CountTrue(df, hn::AndNot(through, go));
            EmitTo(*a.bounce, go, origin, dir, zero, inf, pixel_v, wt, depth1, kind);
          }
        }
      }
    }
  }
  *a.contrib_end = cpos;
}

using ShadeBlocksFn = void (*)(const detail::ShadeArgs&);

template <size_t... kI>
constexpr std::array<ShadeBlocksFn, sizeof...(kI)> MakeShadeTable(std::index_sequence<kI...>) {
  return {{&ShadeBlocks<detail::NormalizeStages(static_cast<uint32_t>(kI))>...}};
}

// Picks the instantiation for the (normalized) stage set: 24 distinct kernels per target.
void ShadeSimd(const detail::ShadeArgs& a) {
  static constexpr std::array<ShadeBlocksFn, kShadeAllStages + 1> kTable =
      MakeShadeTable(std::make_index_sequence<kShadeAllStages + 1>());
  kTable[a.stages & kShadeAllStages](a);
}

}  // namespace HWY_NAMESPACE
}  // namespace rs
HWY_AFTER_NAMESPACE();

#if HWY_ONCE
namespace rs {

HWY_EXPORT(ShadeSimd);

const char* ShadeStageName(int stage_index) {
  static constexpr const char* kNames[kNumShadeStages] = {"shadow", "specular", "texture",
                                                          "reflection", "refraction"};
  return stage_index >= 0 && stage_index < kNumShadeStages ? kNames[stage_index] : "unknown";
}

uint32_t ShadeStagesFor(const ShadeScene& scene, const ShadeOptions& options) {
  const SceneFeatures& f = scene.features;
  uint32_t s = 0;
  if (f.lights && !scene.lights.empty()) {
    s |= kShadeStageShadow;
    if (f.specular) s |= kShadeStageSpecular;
  }
  if (f.textures && !scene.uvs.empty() && !scene.textures.empty()) s |= kShadeStageTexture;
  if (options.max_depth > 0) {
    if (f.reflection) s |= kShadeStageReflection;
    if (f.transmission) s |= kShadeStageRefraction;
  }
  return s;
}

void ShadeStats::Merge(const ShadeStats& o) {
  rays += o.rays;
  shading_calls += o.shading_calls;
  misses += o.misses;
  light_tests += o.light_tests;
  texture_fetches += o.texture_fetches;
  culled += o.culled;
  for (int k = 0; k < kNumRayKinds; ++k) spawned[k] += o.spawned[k];
  highlights += o.highlights;
  blocks += o.blocks;
  for (int k = 0; k < kNumShadeStages; ++k) stage_runs[k] += o.stage_runs[k];
  stages |= o.stages;
}

glm::vec3 SampleTexture(const Texture& texture, glm::vec2 uv) {
  const int w = texture.width;
  const int h = texture.height;
  if (w <= 0 || h <= 0 || texture.rgb.size() < static_cast<size_t>(w) * h * 3) {
    return glm::vec3(1.0f);
  }
  return SampleBilinear(w, h, uv, [&](int tx, int ty) {
    const float* p = texture.rgb.data() + (static_cast<size_t>(ty) * w + tx) * 3;
    return glm::vec3(p[0], p[1], p[2]);
  });
}

float PhongPow(float x, float e) {
  namespace c = detail;
  if (!(x > 0.0f)) return 0.0f;  // 0, negative, NaN
  int32_t k_adj = 0;
  if (x < c::kMinNormal) {  // subnormal: scale by 2^24 (exact)
    x *= 16777216.0f;
    k_adj = -24;
  }
  const int32_t bits = std::bit_cast<int32_t>(x);
  int32_t k = ((bits >> 23) & 0xff) - 127 + k_adj;
  float m = std::bit_cast<float>((bits & 0x007fffff) | 0x3f800000);  // [1, 2)
  if (m > c::kSqrt2) {
    m *= 0.5f;
    k += 1;
  }
  const float f = (m - 1.0f) / (m + 1.0f);
  const float s = f * f;
  float poly = c::kAtanh9 + s * c::kAtanh11;
  poly = c::kAtanh7 + s * poly;
  poly = c::kAtanh5 + s * poly;
  poly = c::kAtanh3 + s * poly;
  poly = 1.0f + s * poly;
  const float log2x = static_cast<float>(k) + (c::kLog2Scale * f) * poly;
  float y = e * log2x;
  if (!(y == y)) y = 0.0f;  // NaN (1^inf) -> 2^0
  if (y < -126.0f) return 0.0f;
  if (!(y < 127.0f)) y = 127.0f;
  const float n = std::floor(y + 0.5f);
  const float r = y - n;
  float p = c::kExp7 + r * c::kExp8;
  p = c::kExp6 + r * p;
  p = c::kExp5 + r * p;
  p = c::kExp4 + r * p;
  p = c::kExp3 + r * p;
  p = c::kExp2 + r * p;
  p = c::kExp1 + r * p;
  p = 1.0f + r * p;
  const float scale = std::bit_cast<float>((static_cast<int32_t>(n) + 127) << 23);
  return p * scale;
}

namespace {

float MaxChannel(const glm::vec3& c) { return std::max(c.x, std::max(c.y, c.z)); }

void PushRay(RayStream& out, const glm::vec3& o, const glm::vec3& d, float tmin, float tmax,
             uint32_t pixel, const glm::vec3& w, int32_t depth, RayKind kind) {
  out.Push(o.x, o.y, o.z, d.x, d.y, d.z, tmin, tmax, pixel, w.x, w.y, w.z, depth, kind);
}

uint32_t EffectiveStages(const ShadeScene& scene, const ShadeOptions& options) {
  const uint32_t s =
      options.stages == kShadeStagesAuto ? ShadeStagesFor(scene, options) : options.stages;
  return detail::NormalizeStages(s);
}

}  // namespace

namespace ref {

void Shade(const ShadeScene& scene, const ShadeOptions& options, const RayStreamView& rays,
           const HitStreamView& hits, ContributionStream& contributions, RayStream& secondary,
           ShadeStats* stats) {
  HWY_DASSERT(hits.size == rays.size);
  const uint32_t stages = EffectiveStages(scene, options);
  const bool shadow_stage = (stages & kShadeStageShadow) != 0;
  const bool specular_stage = (stages & kShadeStageSpecular) != 0;
  const bool reflection_stage = (stages & kShadeStageReflection) != 0;
  const bool refraction_stage = (stages & kShadeStageRefraction) != 0;
  const bool any_bounce = reflection_stage || refraction_stage;
  const bool textured = (stages & kShadeStageTexture) != 0 && !scene.uvs.empty();
  const bool smooth = !scene.normals.empty();
  const bool background = MaxChannel(scene.background) > 0.0f;
  const float inf = std::numeric_limits<float>::infinity();
  ShadeStats s;
  s.rays = rays.size;
  s.stages = stages;

  for (size_t i = 0; i < rays.size; ++i) {
    HWY_DASSERT(rays.kind[i] != static_cast<int32_t>(RayKind::kShadow));
    const glm::vec3 w(rays.wr[i], rays.wg[i], rays.wb[i]);
    const uint32_t pixel = rays.pixel[i];
    const int32_t prim = hits.prim[i];
    if (prim < 0) {
      ++s.misses;
      if (background) {
        const glm::vec3 c = w * scene.background;
        contributions.Push(pixel, c.x, c.y, c.z);
      }
      continue;
    }
    HWY_DASSERT(static_cast<size_t>(prim) < scene.triangles.size());
    ++s.shading_calls;
    ++s.blocks;
    const int32_t depth = rays.depth[i];
    const glm::uvec3 tri = scene.triangles[prim];
    const glm::vec3& p0 = scene.positions[tri.x];
    const glm::vec3& p1 = scene.positions[tri.y];
    const glm::vec3& p2 = scene.positions[tri.z];
    const float u = hits.u[i];
    const float v = hits.v[i];
    const float b0 = 1.0f - u - v;
    // p from barycentrics: its error is relative to the vertices, which OffsetRayOrigin's
    // ulp-scaled step covers (t along the ray would add the error of a long ray).
    const glm::vec3 p = b0 * p0 + u * p1 + v * p2;
    const glm::vec3 d = glm::normalize(glm::vec3(rays.dx[i], rays.dy[i], rays.dz[i]));

    // Geometric normal: the face normal by winding (outward for consistently wound closed
    // meshes), flipped to face the incoming ray. Zero-area triangles are never hit (Accel).
    const glm::vec3 n_face = FaceNormal(p0, p1, p2);
    const bool entering = glm::dot(d, n_face) < 0.0f;
    const glm::vec3 ng = entering ? n_face : -n_face;
    glm::vec3 ns = ng;
    if (smooth) {
      const glm::vec3 n = b0 * scene.normals[tri.x] + u * scene.normals[tri.y] +
                          v * scene.normals[tri.z];
      const float len2 = glm::dot(n, n);
      if (len2 > 1e-20f && std::isfinite(len2)) {
        ns = n / std::sqrt(len2);
        if (glm::dot(ns, ng) < 0.0f) ns = -ns;  // same hemisphere as ng
      }
    }

    const Material& mat = scene.materials[scene.material_ids[prim]];
    glm::vec3 kd = mat.diffuse;
    if (textured && mat.texture >= 0 &&
        static_cast<size_t>(mat.texture) < scene.textures.size()) {
      const glm::vec2 uv = b0 * scene.uvs[tri.x] + u * scene.uvs[tri.y] + v * scene.uvs[tri.z];
      kd *= SampleTexture(scene.textures[mat.texture], uv);
      ++s.texture_fetches;
      ++s.stage_runs[2];
    }

    // The origin on the incoming side, shared by shadow and reflection rays.
    const float unit = OffsetUnit(p0, p1, p2);
    const glm::vec3 front =
        OffsetRayOrigin(p, ng, unit, shadow_stage ? LightOffsetUnit(p, scene.lights) : 0.0f);
    const float local = std::clamp(1.0f - mat.reflectivity - mat.transmission, 0.0f, 1.0f);
    if (local > 0.0f) {
      const glm::vec3 wl = w * local;
      const glm::vec3 ambient = wl * scene.ambient * kd;
      if (MaxChannel(ambient) > 0.0f) contributions.Push(pixel, ambient.x, ambient.y, ambient.z);

      if (shadow_stage) {
        ++s.stage_runs[0];
        const bool highlight = specular_stage && mat.shininess > 0.0f &&
                               MaxChannel(mat.specular) > 0.0f;
        const glm::vec3 view = -d;
        for (const PointLight& light : scene.lights) {
          ++s.light_tests;
          const glm::vec3 to_light = light.position - p;
          const float dist2 = glm::dot(to_light, to_light);
          if (!(dist2 > 0.0f)) continue;
          const glm::vec3 l = to_light / std::sqrt(dist2);
          // Above the surface: on the incoming side of the geometry (else the shadow ray
          // would cross the surface) and of the shading normal.
          const float cos_ns = glm::dot(ns, l);
          if (glm::dot(ng, l) <= 0.0f || cos_ns <= 0.0f) continue;
          glm::vec3 c = kd * cos_ns;
          if (highlight) {
            ++s.stage_runs[1];
            ++s.highlights;
            const float rv = std::max(0.0f, glm::dot(Reflect(-l, ns), view));
            c += mat.specular * PhongPow(rv, mat.shininess);
          }
          const float atten = light.falloff > 0.0f ? 1.0f / (1.0f + light.falloff * dist2) : 1.0f;
          const glm::vec3 contrib = c * light.color * atten * wl;
          if (!(MaxChannel(contrib) > 0.0f)) continue;
          PushRay(secondary, light.position, front - light.position, kShadowTmin, 1.0f, pixel,
                  contrib, depth, RayKind::kShadow);
          ++s.spawned[static_cast<int>(RayKind::kShadow)];
        }
      }
    }

    if (!any_bounce || depth >= options.max_depth) continue;
    if (reflection_stage && mat.reflectivity > 0.0f) {
      ++s.stage_runs[3];
      const glm::vec3 tint = MaxChannel(mat.specular) > 0.0f ? mat.specular : glm::vec3(1.0f);
      const glm::vec3 wr = w * mat.reflectivity * tint;
      if (MaxChannel(wr) >= options.weight_cutoff) {
        glm::vec3 r = Reflect(d, ns);
        if (glm::dot(r, ng) <= 0.0f) r = Reflect(d, ng);  // shading normal bent it below
        PushRay(secondary, front, r, 0.0f, inf, pixel, wr, depth + 1, RayKind::kReflection);
        ++s.spawned[static_cast<int>(RayKind::kReflection)];
      } else {
        ++s.culled;
      }
    }
    if (refraction_stage && mat.transmission > 0.0f) {
      ++s.stage_runs[4];
      const glm::vec3 wt = w * mat.transmission;
      if (MaxChannel(wt) >= options.weight_cutoff) {
        // Entering (the ray meets the face's front) goes from 1 into ior, leaving from ior.
        const float eta = entering ? 1.0f / mat.ior : mat.ior;
        // The shading normal must face the ray too, else refract about the geometric one.
        const glm::vec3 nr = glm::dot(d, ns) < 0.0f ? ns : ng;
        glm::vec3 t;
        bool through = Refract(d, nr, eta, &t);
        if (through && glm::dot(t, ng) >= 0.0f) through = Refract(d, ng, eta, &t);
        if (through) {
          PushRay(secondary, OffsetRayOrigin(p, -ng, unit), t, 0.0f, inf, pixel, wt, depth + 1,
                  RayKind::kRefraction);
          ++s.spawned[static_cast<int>(RayKind::kRefraction)];
        } else {  // total internal reflection
          glm::vec3 r = Reflect(d, ns);
          if (glm::dot(r, ng) <= 0.0f) r = Reflect(d, ng);
          PushRay(secondary, front, r, 0.0f, inf, pixel, wt, depth + 1, RayKind::kReflection);
          ++s.spawned[static_cast<int>(RayKind::kReflection)];
        }
      } else {
        ++s.culled;
      }
    }
  }
  if (stats != nullptr) stats->Merge(s);
}

}  // namespace ref

namespace {

// Both overloads of rs::Shade: shadow rays to *shadow[l * stride], the others to bounce.
void ShadeInto(const ShadeScene& scene, const ShadeOptions& options, const RayStreamView& rays,
               const HitStreamView& hits, ContributionStream& contributions,
               RayStream* const* shadow, size_t stride, RayStream& bounce, ShadeStats* stats) {
  HWY_DASSERT(hits.size == rays.size);
  const uint32_t stages = EffectiveStages(scene, options);
  ShadeStats s;
  s.rays = rays.size;
  s.stages = stages;
  if (rays.size > 0) {
    // Room for every ray the stages can emit (+ one vector of CompressStore slack), reserved
    // up front so the kernel never allocates; grown geometrically. A stream that several
    // outputs share is reserved for all of them (stride 0), or grown by the kernel.
    auto reserve = [&](RayStream& to, size_t per_ray) {
      const size_t need = to.size() + rays.size * per_ray + kStreamPad;
      if (need > to.capacity()) to.Reserve(std::max(need, 2 * to.capacity()));
    };
    const bool shadows = (stages & kShadeStageShadow) != 0 && !scene.lights.empty();
    const size_t bounces = ((stages & kShadeStageReflection) != 0 ? 1 : 0) +
                           ((stages & kShadeStageRefraction) != 0 ? 1 : 0);
    if (shadows && stride == 0) {
      reserve(*shadow[0], scene.lights.size() + (shadow[0] == &bounce ? bounces : 0));
    } else if (shadows) {
      for (size_t l = 0; l < scene.lights.size(); ++l) reserve(*shadow[l * stride], 1);
    }
    if (!shadows || stride != 0 || shadow[0] != &bounce) reserve(bounce, bounces);
    // At most one contribution per ray (background or ambient); the rest arrive as shadow rays.
    const size_t cbegin = contributions.size();
    const size_t cneed = cbegin + rays.size + kStreamPad;
    if (cneed > contributions.capacity()) {
      contributions.Reserve(std::max(cneed, 2 * contributions.capacity()));
    }
    size_t cend = cbegin;
    detail::ShadeArgs args;
    args.scene = &scene;
    args.options = &options;
    args.rays = rays;
    args.hits = hits;
    args.contrib = {contributions.pixel_data(), contributions.r_data(), contributions.g_data(),
                    contributions.b_data(), cbegin};
    args.contrib_end = &cend;
    args.shadow = shadow;
    args.shadow_stride = stride;
    args.bounce = &bounce;
    args.stages = stages;
    args.stats = &s;
    HWY_DYNAMIC_DISPATCH(ShadeSimd)(args);
    contributions.Resize(cend);
  }
  if (stats != nullptr) stats->Merge(s);
}

}  // namespace

void Shade(const ShadeScene& scene, const ShadeOptions& options, const RayStreamView& rays,
           const HitStreamView& hits, ContributionStream& contributions, RayStream& secondary,
           ShadeStats* stats) {
  RayStream* const one = &secondary;
  ShadeInto(scene, options, rays, hits, contributions, &one, 0, secondary, stats);
}

void Shade(const ShadeScene& scene, const ShadeOptions& options, const RayStreamView& rays,
           const HitStreamView& hits, ContributionStream& contributions,
           std::span<RayStream* const> shadow, RayStream& bounce, ShadeStats* stats) {
  HWY_ASSERT(shadow.size() >= scene.lights.size());
  ShadeInto(scene, options, rays, hits, contributions, shadow.data(), 1, bounce, stats);
}

}  // namespace rs
#endif  // HWY_ONCE
