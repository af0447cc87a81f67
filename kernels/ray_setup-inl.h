// Per-target setup of a vector of rays shared by the SIMD traversals (the stream DDA in
// kernels/dda_stream.cc, the coherent packets in kernels/packet_dda.cc): validity, the slab clip
// to the grid box and the watertight test's shear, each lane rounding exactly as the scalar code
// (RayIsValid, ClipRayToGrid, PrepareWatertightRay), so every traversal tests the same rays;
// and the lane-bit loops of the per-lane stages (LaneBits, LowestLane).
#if defined(RS_KERNELS_RAY_SETUP_INL_H_) == defined(HWY_TARGET_TOGGLE)
#ifdef RS_KERNELS_RAY_SETUP_INL_H_
#undef RS_KERNELS_RAY_SETUP_INL_H_
#else
#define RS_KERNELS_RAY_SETUP_INL_H_
#endif

#include <hwy/highway.h>

#include <cfloat>
#include <limits>

#include "kernels/triangle.h"

HWY_BEFORE_NAMESPACE();
namespace rs {
namespace HWY_NAMESPACE {
namespace hn = hwy::HWY_NAMESPACE;

// v's first `count` lanes stored at p: the whole vector when it has no more lanes (the common
// case), else hn::BlendedStore, which is vmaskmovps on AVX2: 10-11 TSC ticks a store on AMD
// Zen 4 against 1.5 for a load, a blend and a store (a loop of 4 M stores; this host, load 0.6).
template <class D>
HWY_INLINE void StoreFirstN(hn::Vec<D> v, D d, size_t count, hn::TFromD<D>* HWY_RESTRICT p) {
  if (count >= hn::Lanes(d)) {
    hn::StoreU(v, d, p);
  } else {
    hn::BlendedStore(v, hn::FirstN(d, count), d, p);
  }
}

// RayIsValid per lane (all six components finite: NaN fails Lt; some |d| >= kMinDirection) and
// a non-empty (tmin, tmax_f], among the lanes of `live`.
template <class D, class V = hn::Vec<D>>
HWY_INLINE hn::Mask<D> ValidRayLanes(D d, const V o[3], const V dir[3], V tmin, V tmax_f,
                                     hn::Mask<D> live) {
  const V inf = hn::Set(d, std::numeric_limits<float>::infinity());
  const V min_dir = hn::Set(d, kMinDirection);
  auto valid = live;
  for (int a = 0; a < 3; ++a) {
    valid = hn::And(valid, hn::And(hn::Lt(hn::Abs(o[a]), inf), hn::Lt(hn::Abs(dir[a]), inf)));
  }
  valid = hn::And(valid, hn::Or(hn::Or(hn::Ge(hn::Abs(dir[0]), min_dir),
                                       hn::Ge(hn::Abs(dir[1]), min_dir)),
                                hn::Ge(hn::Abs(dir[2]), min_dir)));
  return hn::And(valid, hn::Lt(tmin, tmax_f));
}

// +inf tmax -> FLT_MAX as in the scalar tests; NaN stays NaN (and fails every bound).
template <class D, class V = hn::Vec<D>>
HWY_INLINE V FiniteTmax(D d, V tmax) {
  const V flt_max = hn::Set(d, FLT_MAX);
  return hn::IfThenElse(hn::Gt(tmax, flt_max), flt_max, tmax);
}

// Slab clip of the lanes to the box [lo, hi] (ClipRayToGrid): narrows [t0, t1]; axes with
// d = +-0 or 1/d not finite are parallel (inv = 0, origin must lie in the slab). Returns `valid`
// without the lanes that miss the box.
template <class D, class V = hn::Vec<D>>
HWY_INLINE hn::Mask<D> ClipRayLanes(D d, const float lo[3], const float hi[3], const V o[3],
                                    const V dir[3], hn::Mask<D> valid, V* t0, V* t1, V inv[3],
                                    hn::Mask<D> parallel[3]) {
  const V zero = hn::Zero(d), one = hn::Set(d, 1.0f);
  const V inf = hn::Set(d, std::numeric_limits<float>::infinity());
  for (int a = 0; a < 3; ++a) {
    const V vlo = hn::Set(d, lo[a]), vhi = hn::Set(d, hi[a]);
    const V r = hn::Div(one, dir[a]);
    parallel[a] = hn::Not(hn::And(hn::Ne(dir[a], zero), hn::Lt(hn::Abs(r), inf)));
    const auto inside = hn::And(hn::Ge(o[a], vlo), hn::Le(o[a], vhi));
    valid = hn::And(valid, hn::Or(hn::Not(parallel[a]), inside));
    inv[a] = hn::IfThenZeroElse(parallel[a], r);
    const V ta = hn::Mul(hn::Sub(vlo, o[a]), r), tb = hn::Mul(hn::Sub(vhi, o[a]), r);
    const auto swap = hn::Gt(ta, tb);
    const V near = hn::IfThenElse(swap, tb, ta), far = hn::IfThenElse(swap, ta, tb);
    *t0 = hn::IfThenElse(parallel[a], *t0, hn::IfThenElse(hn::Gt(near, *t0), near, *t0));
    *t1 = hn::IfThenElse(parallel[a], *t1, hn::IfThenElse(hn::Lt(far, *t1), far, *t1));
  }
  return hn::And(valid, hn::Le(*t0, *t1));
}

// The watertight shear per lane (PrepareWatertightRay): kz = axis of the largest |d| (first on
// ties), kx = kz + 1, ky = kx + 1 (mod 3), swapped where d[kz] < 0 to keep the winding.
template <class D>
struct WatertightSetupLanes {
  hn::Vec<hn::RebindToSigned<D>> k[3];  // kx, ky, kz
  hn::Vec<D> shear[3];                  // sx, sy, sz
  hn::Vec<D> o[3];                      // origin in (kx, ky, kz) order
};

template <class D, class V = hn::Vec<D>>
HWY_INLINE WatertightSetupLanes<D> SetupWatertightLanes(D d, const V o[3], const V dir[3]) {
  const hn::RebindToSigned<D> di;
  using VI = hn::Vec<decltype(di)>;
  const V zero = hn::Zero(d), one = hn::Set(d, 1.0f);
  const V ax = hn::Abs(dir[0]), ay = hn::Abs(dir[1]), az = hn::Abs(dir[2]);
  const auto y_gt_x = hn::Gt(ay, ax);
  const auto kz2 = hn::Gt(az, hn::IfThenElse(y_gt_x, ay, ax));
  const auto kz1 = hn::AndNot(kz2, y_gt_x);
  const VI kz = hn::IfThenElse(hn::RebindMask(di, kz2), hn::Set(di, 2),
                               hn::IfThenElseZero(hn::RebindMask(di, kz1), hn::Set(di, 1)));
  const V dkz = hn::IfThenElse(kz2, dir[2], hn::IfThenElse(kz1, dir[1], dir[0]));
  const VI kx0 =
      hn::IfThenElse(hn::Eq(kz, hn::Set(di, 2)), hn::Zero(di), hn::Add(kz, hn::Set(di, 1)));
  const VI ky0 =
      hn::IfThenElse(hn::Eq(kx0, hn::Set(di, 2)), hn::Zero(di), hn::Add(kx0, hn::Set(di, 1)));
  const auto swap = hn::RebindMask(di, hn::Lt(dkz, zero));
  const VI kx = hn::IfThenElse(swap, ky0, kx0), ky = hn::IfThenElse(swap, kx0, ky0);
  auto pick = [&](const VI& k, const V* v) {
    return hn::IfThenElse(hn::RebindMask(d, hn::Eq(k, hn::Zero(di))), v[0],
                          hn::IfThenElse(hn::RebindMask(d, hn::Eq(k, hn::Set(di, 1))), v[1], v[2]));
  };
  WatertightSetupLanes<D> s;
  s.k[0] = kx;
  s.k[1] = ky;
  s.k[2] = kz;
  s.shear[0] = hn::Div(pick(kx, dir), dkz);
  s.shear[1] = hn::Div(pick(ky, dir), dkz);
  s.shear[2] = hn::Div(one, dkz);
  s.o[0] = pick(kx, o);
  s.o[1] = pick(ky, o);
  s.o[2] = pick(kz, o);
  return s;
}

// The lanes set in `mask` as bits (lane l = bit l), for the scalar loops over lanes: they pick
// lanes with tzcnt instead of reading back a CompressStore'd lane list. Such a list goes through
// memory, and a compress store does not forward to the loads that read it back (they wait for
// the store to retire); AVX2 has no compress instruction at all, and Highway 1.0.3 builds its
// 1 KiB index table on the stack at every call (callgrind: 16 % of the instructions and 3/4 of
// the branches of the any-hit kernel on AVX2).
template <class D>
HWY_INLINE uint64_t LaneBits(D d, hn::Mask<D> mask) {
  constexpr size_t kMaxLanes = HWY_MAX_BYTES / sizeof(float);
  static_assert(kMaxLanes <= 64, "lane bits must fit a uint64_t");
  uint8_t bytes[(kMaxLanes + 7) / 8] = {};
  hn::StoreMaskBits(d, mask, bytes);
  uint64_t bits = 0;
  for (size_t i = 0; i < sizeof(bytes); ++i) bits |= uint64_t{bytes[i]} << (8 * i);
  return bits;
}

// Index of the lowest set bit of bits != 0 (the next lane of a LaneBits loop).
HWY_INLINE size_t LowestLane(uint64_t bits) { return hwy::Num0BitsBelowLS1Bit_Nonzero64(bits); }

}  // namespace HWY_NAMESPACE
}  // namespace rs
HWY_AFTER_NAMESPACE();

#endif  // RS_KERNELS_RAY_SETUP_INL_H_
