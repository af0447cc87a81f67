// SIMD passes of the grid build (kernels/grid_binning.h): degenerate flags, triangle bounds and
// bounding-box cell ranges, a vector of triangles at a time; the 2D edge tables of the binning
// tests, a vector of cells at a time. Per-target code; foreach_target re-includes this file.
#include <algorithm>
#include <bit>
#include <cfloat>
#include <cstddef>
#include <cstdint>
#include <cstring>

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

void SimdMinMaxOffset(uint8_t* HWY_RESTRICT out, const uint8_t* HWY_RESTRICT in, size_t n,
                      uint8_t d) {
  const hn::ScalableTag<uint8_t> du8;
  const size_t lanes = hn::Lanes(du8);
  if (n < lanes) {
    for (size_t i = 0; i < n; ++i) out[i] = std::min(out[i], std::max(d, in[i]));
    return;
  }
  const auto dv = hn::Set(du8, d);
  const auto update = [&](size_t i) {
    hn::StoreU(hn::Min(hn::LoadU(du8, out + i), hn::Max(dv, hn::LoadU(du8, in + i))), du8,
               out + i);
  };
  for (size_t i = 0; i + lanes < n; i += lanes) update(i);
  update(n - lanes);  // the last vector, overlapping: min(min(o, m), m) = min(o, m)
}

uint32_t SimdMaxIndex(const uint32_t* p, size_t n) {
  const hn::ScalableTag<uint32_t> du;
  const size_t lanes = hn::Lanes(du);
  // two accumulators: the max's latency
  auto m0 = hn::Zero(du), m1 = hn::Zero(du);
  size_t i = 0;
  for (; i + 2 * lanes <= n; i += 2 * lanes) {
    m0 = hn::Max(m0, hn::LoadU(du, p + i));
    m1 = hn::Max(m1, hn::LoadU(du, p + i + lanes));
  }
  uint32_t m = hn::GetLane(hn::MaxOfLanes(du, hn::Max(m0, m1)));
  for (; i < n; ++i) m = std::max(m, p[i]);  // unpadded caller memory: no whole-vector load
  return m;
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

// kBadBytes[b]: byte l = 1 - bit l of b (the degenerate flags of 8 lanes from their "ok" bits,
// little-endian byte order as memcpy stores it).
constexpr auto kBadBytesTable = [] {
  struct Table {
    uint64_t v[256];
  } t{};
  for (int b = 0; b < 256; ++b) {
    uint64_t bytes = 0;
    for (int l = 0; l < 8; ++l) bytes |= uint64_t(((b >> l) & 1) ^ 1) << (8 * l);
    t.v[b] = bytes;
  }
  return t;
}();
HWY_MAYBE_UNUSED constexpr const uint64_t* kBadBytes = kBadBytesTable.v;

// IsDegenerateTriangle a vector of triangles at a time: float -> double is exact and the
// differences and products below round as the scalar code's (no contraction), so the flags are
// the same bit for bit.
void SimdDegenerateFlagsRange(TriangleSoA* tris, size_t first, size_t n, size_t* degenerate_out,
                              size_t* nonfinite_out) {
  const hn::ScalableTag<double> dd;
  const hn::Rebind<float, decltype(dd)> df;
  const auto zero = hn::Zero(dd);
  const size_t lanes = hn::Lanes(dd);
  uint8_t* flags = tris->degenerate.data();
  size_t degenerate = 0, nonfinite = 0;
  for (size_t i = first; i < n; i += lanes) {
    // the vertex arrays are padded (AlignedArray): whole-vector loads are safe
    hn::Vec<decltype(dd)> p[3][3];
    auto finite = hn::FirstN(dd, n - i);
    for (int k = 0; k < 3; ++k) {
      for (int a = 0; a < 3; ++a) {
        p[k][a] = hn::PromoteTo(dd, hn::LoadU(df, tris->p[k][a].data() + i));
        finite = hn::And(finite, hn::IsFinite(p[k][a]));
      }
    }
    const auto e1x = hn::Sub(p[1][0], p[0][0]), e1y = hn::Sub(p[1][1], p[0][1]);
    const auto e1z = hn::Sub(p[1][2], p[0][2]);
    const auto e2x = hn::Sub(p[2][0], p[0][0]), e2y = hn::Sub(p[2][1], p[0][1]);
    const auto e2z = hn::Sub(p[2][2], p[0][2]);
    const auto nx = hn::Sub(hn::Mul(e1y, e2z), hn::Mul(e1z, e2y));
    const auto ny = hn::Sub(hn::Mul(e1z, e2x), hn::Mul(e1x, e2z));
    const auto nz = hn::Sub(hn::Mul(e1x, e2y), hn::Mul(e1y, e2x));
    const auto zero_area = hn::And(hn::Eq(nx, zero), hn::And(hn::Eq(ny, zero), hn::Eq(nz, zero)));
    const auto ok = hn::AndNot(zero_area, finite);  // finite and not zero area
    const size_t live = std::min(lanes, n - i);
    uint8_t bits[8] = {};
    hn::StoreMaskBits(dd, ok, bits);
    if (std::endian::native == std::endian::little && live == lanes && lanes <= 8) {
      // lane l's flag is byte l of kBadBytes[bits]: one store for the vector
      const uint64_t bad = kBadBytes[bits[0]];
      std::memcpy(flags + i, &bad, lanes);
    } else {
      for (size_t l = 0; l < live; ++l) {
        flags[i + l] = uint8_t(((bits[l >> 3] >> (l & 7)) & 1u) ^ 1u);
      }
    }
    degenerate += live - hn::CountTrue(dd, ok);  // ok is false past live (FirstN)
    nonfinite += live - hn::CountTrue(dd, finite);
  }
  *degenerate_out = degenerate;
  *nonfinite_out = nonfinite;
}

template <bool bin_flags>
HWY_INLINE void CellRanges(const TriangleSoA& tris, const BinGeometry& g, size_t first,
                           size_t count, RangeBlock* out) {
  const hn::ScalableTag<float> d;
  const hn::RebindToSigned<decltype(d)> di;
  const auto minus1 = hn::Set(d, -1.0f), one = hn::Set(d, 1.0f);
  const auto one_i = hn::Set(di, 1), zero_i = hn::Zero(di);
  // cell-index strides (exact in 32 bits: res[0] res[1] res[2] < 2^32)
  const uint32_t strides[3] = {1u, uint32_t(g.res[0]), uint32_t(g.res[0]) * uint32_t(g.res[1])};
  const uint32_t num_cells = strides[2] * uint32_t(g.res[2]);
  // box sums of the block, exact: the low and high 16 bits of each box summed apart (a lane
  // adds at most kRangeBlock values below 2^16: no overflow), reduced once at the end
  const hn::RebindToUnsigned<decltype(di)> du;
  const auto low16 = hn::Set(du, 0xffffu);
  auto box_lo = hn::Zero(du), box_hi = hn::Zero(du), line_lo = box_lo, line_hi = box_lo;
  for (size_t k = 0; k < count; k += hn::Lanes(d)) {
    const size_t i = first + k;
    const auto ok = ValidLanes(d, tris, i);
    auto flags = hn::IfThenZeroElse(hn::RebindMask(di, ok), hn::Set(di, kRangeDegenerate));
    hn::Vec<decltype(di)> c0s[3], c1s[3];
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
      c0s[a] = c0;
      c1s[a] = c1;
    }
    // flagged lanes get the range [0, 0] and box 0 (so their values are harmless to use)
    const auto skip = hn::Ne(hn::And(flags, hn::Set(di, kRangeDegenerate | kRangeOutside)), zero_i);
    auto box = hn::BitCast(du, hn::IfThenZeroElse(skip, one_i));
    auto cell = hn::Zero(du);
    auto small = hn::Eq(zero_i, zero_i);  // all lanes
    for (int a = 0; a < 3; ++a) {
      const auto c0 = hn::IfThenZeroElse(skip, c0s[a]), c1 = hn::IfThenZeroElse(skip, c1s[a]);
      const auto extent = hn::Sub(c1, c0);  // >= 0
      box = hn::Mul(box, hn::BitCast(du, hn::Add(extent, one_i)));
      small = hn::And(small, hn::Lt(extent, hn::Set(di, 2)));
      const auto stride = hn::Set(du, strides[a]);
      cell = hn::Add(cell, hn::Mul(hn::BitCast(du, c0), stride));
      hn::StoreU(hn::Mul(hn::BitCast(du, extent), stride), du, out->step[a] + k);
      hn::StoreU(c0, di, out->c0[a] + k);
      hn::StoreU(c1, di, out->c1[a] + k);
    }
    flags = hn::Or(flags, hn::IfThenElseZero(small, hn::Set(di, kRangeSmall)));
    // (lanes past count: triangles of the next block or none)
    const auto counted = hn::IfThenElseZero(hn::RebindMask(du, hn::FirstN(di, count - k)), box);
    box_lo = hn::Add(box_lo, hn::And(counted, low16));
    box_hi = hn::Add(box_hi, hn::ShiftRight<16>(counted));
    if constexpr (bin_flags) {
      // at most one spanning axis: spans & (spans - 1) == 0
      const auto spans = hn::And(flags, hn::Set(di, 7));
      const auto line = hn::Eq(hn::And(spans, hn::Sub(spans, one_i)), zero_i);
      flags = hn::Or(flags, hn::IfThenElseZero(line, hn::Set(di, kRangeLine)));
      // box 4 with every extent <= 1: two axes of extent 1 (both spanning); not spanning on the
      // third (spans != 7, else BinTriangleCells runs the 3D test)
      const auto quad = hn::And(hn::RebindMask(di, hn::Eq(box, hn::Set(du, 4u))),
                                hn::And(small, hn::Ne(spans, hn::Set(di, 7))));
      flags = hn::Or(flags, hn::IfThenElseZero(quad, hn::Set(di, kRangeQuad)));
      const auto lined = hn::IfThenElseZero(hn::RebindMask(du, line), counted);
      line_lo = hn::Add(line_lo, hn::And(lined, low16));
      line_hi = hn::Add(line_hi, hn::ShiftRight<16>(lined));
    }
    cell = hn::IfThenElse(hn::RebindMask(du, skip), hn::Set(du, num_cells), cell);
    hn::StoreU(cell, du, out->cell + k);
    hn::StoreU(box, du, out->box + k);
    hn::StoreU(flags, di, out->flags + k);
  }
  const auto total = [&](hn::Vec<decltype(du)> lo, hn::Vec<decltype(du)> hi) {
    return size_t(hn::GetLane(hn::SumOfLanes(du, lo))) +
           (size_t(hn::GetLane(hn::SumOfLanes(du, hi))) << 16);
  };
  out->box_sum = total(box_lo, box_hi);
  out->line_sum = bin_flags ? total(line_lo, line_hi) : 0;
}

void SimdQuadCellMasks(const TriangleSoA& tris, const BinGeometry& g, size_t first,
                       const RangeBlock& block, const uint16_t* js, size_t n, uint8_t* masks) {
  const hn::ScalableTag<double> dd;
  const hn::Rebind<float, decltype(dd)> df;
  const hn::Rebind<int32_t, decltype(dd)> di;
  constexpr size_t kMax = HWY_MAX_BYTES / sizeof(double);
  const size_t lanes = hn::Lanes(dd);
  // the per-axis terms of Edges2D, rounded as there: 0.5 cs + margin, lo + 0.5 cs
  double hc[3], mid[3];
  for (int a = 0; a < 3; ++a) {
    hc[a] = 0.5 * g.cs[a] + g.margin[a];
    mid[a] = g.lo[a] + 0.5 * g.cs[a];
  }
  HWY_ALIGN int32_t tri[kMax], entry[kMax];
  HWY_ALIGN double single[kMax], out[kMax];
  const auto zero = hn::Zero(dd), one = hn::Set(dd, 1.0), two = hn::Set(dd, 2.0);
  for (size_t s = 0; s < n; s += lanes) {
    const size_t live = std::min(lanes, n - s);
    // each lane's triangle, block entry and single-cell axis k; lanes past n repeat the last
    for (size_t l = 0; l < lanes; ++l) {
      const size_t e = js[s + std::min(l, live - 1)];
      const int32_t flags = block.flags[e];
      tri[l] = int32_t(first + e);
      entry[l] = int32_t(e);
      single[l] = !(flags & 1) ? 0.0 : (!(flags & 2) ? 1.0 : 2.0);
    }
    // projection axes (i, j) = (1, 2), (0, 2), (0, 1) for k = 0, 1, 2: i is axis 1 iff k = 0,
    // j is axis 1 iff k = 2
    const auto k = hn::Load(dd, single);
    const auto i_is_1 = hn::Eq(k, zero), j_is_1 = hn::Eq(k, two);
    const auto t = hn::Load(di, tri), e = hn::Load(di, entry);
    hn::Vec<decltype(dd)> pi[3], pj[3];
    for (int v = 0; v < 3; ++v) {
      hn::Vec<decltype(dd)> x[3];
      for (int a = 0; a < 3; ++a) {
        x[a] = hn::PromoteTo(dd, hn::GatherIndex(df, tris.p[v][a].data(), t));
      }
      pi[v] = hn::IfThenElse(i_is_1, x[1], x[0]);
      pj[v] = hn::IfThenElse(j_is_1, x[1], x[2]);
    }
    const auto pick_i = [&](const double* per_axis) {
      return hn::IfThenElse(i_is_1, hn::Set(dd, per_axis[1]), hn::Set(dd, per_axis[0]));
    };
    const auto pick_j = [&](const double* per_axis) {
      return hn::IfThenElse(j_is_1, hn::Set(dd, per_axis[1]), hn::Set(dd, per_axis[2]));
    };
    const auto hi_c = pick_i(hc), hj_c = pick_j(hc);
    const auto mi = pick_i(mid), mj = pick_j(mid);
    const auto ci_s = pick_i(g.cs), cj_s = pick_j(g.cs);
    hn::Vec<decltype(dd)> c0[3];
    for (int a = 0; a < 3; ++a) c0[a] = hn::PromoteTo(dd, hn::GatherIndex(di, block.c0[a], e));
    const auto col0 = hn::IfThenElse(i_is_1, c0[1], c0[0]);
    const auto row0 = hn::IfThenElse(j_is_1, c0[1], c0[2]);
    const auto col1 = hn::Add(col0, one), row1 = hn::Add(row0, one);  // small integers: exact
    auto ok00 = hn::Eq(zero, zero), ok10 = ok00, ok01 = ok00, ok11 = ok00;
    for (int e = 0; e < 3; ++e) {
      const int q = e == 2 ? 0 : e + 1, r = e == 0 ? 2 : e - 1;  // edge p -> q, third vertex r
      // normal of the projected edge; (0, 0) (an edge along the third axis) constrains nothing
      const auto ni = hn::Neg(hn::Sub(pj[q], pj[e])), nj = hn::Sub(pi[q], pi[e]);
      const auto none = hn::And(hn::Eq(ni, zero), hn::Eq(nj, zero));
      const auto pp = hn::Add(hn::Mul(ni, pi[e]), hn::Mul(nj, pj[e]));
      const auto pr = hn::Add(hn::Mul(ni, pi[r]), hn::Mul(nj, pj[r]));
      const auto half = hn::Add(hn::Mul(hn::Abs(ni), hi_c), hn::Mul(hn::Abs(nj), hj_c));
      // min / max of two finite values; a signed zero tie does not change min - half
      const auto lo = hn::Sub(hn::Min(pp, pr), half), hi = hn::Add(hn::Max(pp, pr), half);
      const auto base = hn::Add(hn::Mul(ni, mi), hn::Mul(nj, mj));
      const auto si = hn::Mul(ni, ci_s), sj = hn::Mul(nj, cj_s);
      // (base + double(cj) * sj) + double(ci) * si, as SimdEdgeTable
      const auto r0 = hn::Add(base, hn::Mul(row0, sj)), r1 = hn::Add(base, hn::Mul(row1, sj));
      const auto t0 = hn::Mul(col0, si), t1 = hn::Mul(col1, si);
      const auto pass = [&](const hn::Vec<decltype(dd)> c) {
        return hn::Or(none, hn::Not(hn::Or(hn::Lt(c, lo), hn::Gt(c, hi))));
      };
      ok00 = hn::And(ok00, pass(hn::Add(r0, t0)));
      ok10 = hn::And(ok10, pass(hn::Add(r0, t1)));
      ok01 = hn::And(ok01, pass(hn::Add(r1, t0)));
      ok11 = hn::And(ok11, pass(hn::Add(r1, t1)));
    }
    // bit m + 2 r per cell (small integers in double: exact)
    auto bits = hn::IfThenElseZero(ok00, one);
    bits = hn::Add(bits, hn::IfThenElseZero(ok10, hn::Set(dd, 2.0)));
    bits = hn::Add(bits, hn::IfThenElseZero(ok01, hn::Set(dd, 4.0)));
    bits = hn::Add(bits, hn::IfThenElseZero(ok11, hn::Set(dd, 8.0)));
    hn::Store(bits, dd, out);
    for (size_t l = 0; l < live; ++l) masks[s + l] = uint8_t(out[l]);
  }
}

void SimdTriangleCellRanges(const TriangleSoA& tris, const BinGeometry& g, size_t first,
                            size_t count, RangeBlock* out) {
  CellRanges<false>(tris, g, first, count, out);
}

void SimdTriangleCellRangesBin(const TriangleSoA& tris, const BinGeometry& g, size_t first,
                               size_t count, RangeBlock* out) {
  CellRanges<true>(tris, g, first, count, out);
}

void SimdEdgeTable(const EdgeSet& e, int ci0, int ni, int cj0, int nj, uint8_t* out) {
  const hn::ScalableTag<double> dd;
  const int lanes = int(hn::Lanes(dd));
  if (ni * nj <= lanes) {
    // The whole table in one vector (most binned triangles cross 2 x 2 cells): lane l is entry l
    // = cell (ci0 + l % ni, cj0 + l / ni). Per lane the same operations as below, (base +
    // double(cj) * sj) + double(ci) * si, so the same table bit for bit.
    HWY_ALIGN double col[HWY_MAX_BYTES / sizeof(double)];
    HWY_ALIGN double row[HWY_MAX_BYTES / sizeof(double)];
    for (int l = 0, m = 0, r = 0; l < lanes; ++l) {  // (m, r) = (l % ni, l / ni)
      col[l] = double(ci0 + m);
      row[l] = double(cj0 + r);
      if (++m == ni) {
        m = 0;
        ++r;
      }
    }
    const auto ci = hn::Load(dd, col), cj = hn::Load(dd, row);
    auto ok = hn::FirstN(dd, size_t(ni * nj));
    for (int k = 0; k < e.n; ++k) {
      const auto r = hn::Add(hn::Set(dd, e.base[k]), hn::Mul(cj, hn::Set(dd, e.sj[k])));
      const auto c = hn::Add(r, hn::Mul(ci, hn::Set(dd, e.si[k])));
      ok = hn::AndNot(hn::Or(hn::Lt(c, hn::Set(dd, e.lo[k])), hn::Gt(c, hn::Set(dd, e.hi[k]))),
                      ok);
    }
    uint8_t bits[8] = {};
    hn::StoreMaskBits(dd, ok, bits);
    for (int l = 0; l < ni * nj; ++l) out[l] = uint8_t((bits[l >> 3] >> (l & 7)) & 1u);
    return;
  }
  for (int m0 = 0; m0 < ni; m0 += lanes) {
    // double(ci0 + m) * si per edge: Iota is exact (small integers), the product rounds as the
    // scalar one
    const auto col = hn::Iota(dd, double(ci0 + m0));
    hn::Vec<decltype(dd)> term[3], lo[3], hi[3];
    for (int k = 0; k < e.n; ++k) {
      term[k] = hn::Mul(col, hn::Set(dd, e.si[k]));
      lo[k] = hn::Set(dd, e.lo[k]);
      hi[k] = hn::Set(dd, e.hi[k]);
    }
    const int live = std::min(lanes, ni - m0);
    for (int r = 0; r < nj; ++r) {
      auto ok = hn::FirstN(dd, size_t(live));
      for (int k = 0; k < e.n; ++k) {
        const double row = e.base[k] + double(cj0 + r) * e.sj[k];
        const auto c = hn::Add(hn::Set(dd, row), term[k]);
        ok = hn::AndNot(hn::Or(hn::Lt(c, lo[k]), hn::Gt(c, hi[k])), ok);
      }
      uint8_t bits[8] = {};
      hn::StoreMaskBits(dd, ok, bits);
      uint8_t* o = out + size_t(r) * size_t(ni) + size_t(m0);
      if (std::endian::native == std::endian::little && live == lanes && lanes <= 8) {
        // byte m = bit m: kBadBytes' bytes flipped, one store of the vector's entries
        const uint64_t entries = kBadBytes[bits[0]] ^ 0x0101010101010101ull;
        std::memcpy(o, &entries, size_t(lanes));
      } else {
        for (int m = 0; m < live; ++m) o[m] = uint8_t((bits[m >> 3] >> (m & 7)) & 1u);
      }
    }
  }
}

}  // namespace HWY_NAMESPACE
}  // namespace rs
HWY_AFTER_NAMESPACE();

#if HWY_ONCE
namespace rs {

HWY_EXPORT(SimdTriangleBounds);
HWY_EXPORT(SimdMaxIndex);
HWY_EXPORT(SimdMinMaxOffset);

void SimdMinMaxOffset(uint8_t* out, const uint8_t* in, size_t n, uint8_t d) {
  HWY_DYNAMIC_DISPATCH(SimdMinMaxOffset)(out, in, n, d);
}

uint32_t SimdMaxIndex(const uint32_t* p, size_t n) { return HWY_DYNAMIC_DISPATCH(SimdMaxIndex)(p, n); }
HWY_EXPORT(SimdTriangleCellRanges);
HWY_EXPORT(SimdTriangleCellRangesBin);
HWY_EXPORT(SimdDegenerateFlagsRange);
HWY_EXPORT(SimdEdgeTable);
HWY_EXPORT(SimdQuadCellMasks);

void SimdQuadCellMasks(const TriangleSoA& tris, const BinGeometry& g, size_t first,
                       const RangeBlock& block, const uint16_t* js, size_t n, uint8_t* masks) {
  HWY_DYNAMIC_DISPATCH(SimdQuadCellMasks)(tris, g, first, block, js, n, masks);
}

void SimdEdgeTable(const EdgeSet& e, int ci0, int ni, int cj0, int nj, uint8_t* out) {
  HWY_DYNAMIC_DISPATCH(SimdEdgeTable)(e, ci0, ni, cj0, nj, out);
}

void SimdDegenerateFlags(TriangleSoA* tris, size_t first, size_t last, size_t* degenerate,
                         size_t* nonfinite) {
  HWY_DYNAMIC_DISPATCH(SimdDegenerateFlagsRange)(tris, first, last, degenerate, nonfinite);
}

void SimdDegenerateFlags(TriangleSoA* tris) {
  SimdDegenerateFlags(tris, 0, tris->size, &tris->num_degenerate, &tris->num_nonfinite);
}

void SimdTriangleBounds(const TriangleSoA& tris, float lo[3], float hi[3], size_t* num_valid) {
  HWY_DYNAMIC_DISPATCH(SimdTriangleBounds)(tris, lo, hi, num_valid);
}

void SimdTriangleCellRanges(const TriangleSoA& tris, const BinGeometry& g, size_t first,
                            size_t count, RangeBlock* out, bool bin_flags) {
  if (bin_flags) {
    HWY_DYNAMIC_DISPATCH(SimdTriangleCellRangesBin)(tris, g, first, count, out);
  } else {
    HWY_DYNAMIC_DISPATCH(SimdTriangleCellRanges)(tris, g, first, count, out);
  }
}

}  // namespace rs
#endif  // HWY_ONCE
