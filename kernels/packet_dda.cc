// Coherent packet traversal (kernels/packet_dda.h). Per-target code; foreach_target re-includes
// this file.
//
// One packet = 64 consecutive rays, NV = 64 / Lanes vectors (8 on AVX2, 4 on AVX-512):
//   1. setup per vector: validity, slab clip to the grid [t0, t1], the watertight shear (the
//      stream DDA's, kernels/ray_setup-inl.h). The major axis K (largest |sum of d|) must have
//      one sign for every live ray, and the rays' slopes against K must spread by at most about
//      half a cell per slice, else the packet is refused (the stream DDA takes it: diffuse rays);
//   2. slices of the grid along K, in the rays' direction. First the rays whose candidate (or
//      segment end) lies before the slice's near plane are retired: that plane's t is the
//      per-ray DDA's boundary t, bit for bit, so no ray stops before the per-ray walk would.
//      Then each vector's footprint: the box (in the other two axes U, V) of its rays' segments
//      inside the slice, clipped to [t0, min(t1, best t)] and widened by the rounding of
//      o + t d. If the packet's box lies inside a block of empty cells (DdaGrid::skip rings),
//      the slices it cannot leave are jumped. Otherwise each vector marks the cells of its box
//      (a small packet box is taken whole), and every occupied marked cell is visited: its
//      triangles are culled against the boxes of the vectors that marked it (SIMD over 8-16
//      triangles; any hit: also against the K range of each vector's segments, so the surface
//      a shadow ray leaves is not tested when it lies across K) and tested N rays x 1
//      triangle, each vector at most once per triangle (a direct-mapped mailbox); a vector with
//      only 1 or 2 of its rays there tests them with the 1-ray x 4-triangle kernel instead.
//      Refined cells of a two-level grid are visited the same way, one sub-slice at a time. A
//      packet whose vectors' boxes cover more than ~2 cells per ray, or whose footprint
//      outgrows 64 x 64 cells, is abandoned for the stream DDA.
// Why the result is the per-ray walk's: both return the closest watertight hit (ties: lower id)
// over the triangles listed in the cells their walk covers, and every triangle whose hit could
// win is listed in a covered cell: hit points lie inside the cells of the ray's path up to the
// rounding of the walk, which Grid::margin (1e-3 cell plus coordinate ulps) covers. The packet
// covers a superset of each ray's cells up to its termination, and a triangle outside a ray's
// own path cannot beat that ray's true closest hit (it would then be on the path). The culls
// drop a (triangle, vector) pair only if the triangle's bounding box misses the box of the
// vector's segment points (U, W in the slice; K over [t0, t1]) widened by the rounding of
// o + t d, so no lane can hit it there; a dropped pair is not mailboxed.
#include "kernels/packet_dda.h"

#include <cfloat>
#include <cmath>
#include <algorithm>
#include <cstring>
#include <limits>

#undef HWY_TARGET_INCLUDE
#define HWY_TARGET_INCLUDE "kernels/packet_dda.cc"
#include <hwy/foreach_target.h>  // IWYU pragma: keep
#include <hwy/highway.h>         // must follow foreach_target.h

#include "kernels/ray_setup-inl.h"
#include "kernels/tri_intersect-inl.h"

HWY_BEFORE_NAMESPACE();
namespace rs {
namespace HWY_NAMESPACE {
namespace hn = hwy::HWY_NAMESPACE;

inline constexpr size_t kPR = kCoherentPacketRays;
inline constexpr int kMaxFoot = detail::PacketScratch::kMaxFoot;  // cells per axis and slice
// Slice footprints of at most this many cells are visited whole (after checking that one of
// their cells is occupied) rather than marked vector by vector.
inline constexpr int kSmallBox = 4;
// Empty slices ahead are predicted (PacketTracer::PredictEmpty) while the predicted box of the
// packet's rays covers at most this many cells.
inline constexpr int kPredictArea = 24;
// Packets whose footprint widens by more than this many cells per slice are refused, scaled down
// by kDenseCell / (triangles per occupied cell) in grids with denser cells: the wider the
// vectors' boxes, the fewer triangles the culling removes, and in dense cells the per-ray walk's
// 1-ray x 4-triangle tests win (bunny shadow rays: 0.6x the per-ray walk at 0.5, 1.1x at 0.25;
// room scenes prefer 0.5-1). Any hit scales by 2 kDenseCell: with the K cull (CullGroup) its
// packets test fewer triangles (bunny shadow rays, callgrind AVX2: 1506 -> 1359 Ir per ray, the
// other scenes unchanged; 0.75 instead of 0.5 cost sponza 4 %).
inline constexpr float kMaxSpread = 0.5f;
inline constexpr float kDenseCell = 16.0f;
inline constexpr float kAnyDenseScale = 2.0f;
// A vector with at most Lanes / kOneRayShare of its rays in a leaf tests them one by one with the
// 1-ray x 4-triangle kernel (SIMD over the leaf's triangles) instead of N rays x 1 triangle.
inline constexpr size_t kOneRayShare = 4;

// Per-ray state of one packet, SoA.
struct PacketRays {
  HWY_ALIGN float o[3][kPR];
  HWY_ALIGN float d[3][kPR];
  HWY_ALIGN float inv_k[kPR];  // 1 / d[K]
  HWY_ALIGN float t0[kPR];     // segment inside the grid
  HWY_ALIGN float t1[kPR];
  HWY_ALIGN float tmin[kPR];
  HWY_ALIGN float tmax[kPR];   // finite (+inf clamped to FLT_MAX)
  HWY_ALIGN float best[kPR];   // candidate t (starts at tmax)
  HWY_ALIGN float bu[kPR];     // barycentrics of the candidate
  HWY_ALIGN float bv[kPR];
  HWY_ALIGN int32_t prim[kPR];  // candidate (closest) or 1 = occluded (any hit); -1 none
  HWY_ALIGN int32_t live[kPR];  // -1: valid and not done (as a lane mask), 0 otherwise
  // watertight setup: origin in (kx, ky, kz) order, shear, the permutation per ray
  HWY_ALIGN float wo[3][kPR];
  HWY_ALIGN float shear[3][kPR];
  HWY_ALIGN int32_t k[3][kPR];
  // per slice, for the rays in SliceFoot::in: the box of each ray's segment in the slice (U, V;
  // widened by the rounding)
  HWY_ALIGN float flo[2][kPR];
  HWY_ALIGN float fhi[2][kPR];
  int32_t s_start[kPR];  // the slice where the ray's segment starts
  // per vector: the (kx, ky, kz) every live ray shares (k0 | k1 << 2 | k2 << 4), or -1
  int32_t perm[kPR];
  // per vector (any hit): the range along K of its live rays' segments [t0, t1], widened by the
  // rounding err[K] (the third axis of CullGroup's box test; the slice boxes give U and W)
  float k_lo[kPR];
  float k_hi[kPR];
  PreparedRay one[kPR];  // the 1-ray x 4-triangle kernels' setup of each valid ray
};

// Footprint of one slice: the rays in it, per vector the world box of its rays' segments and its
// cell range, and the union cell range.
struct SliceFoot {
  float lo[2][kPR];  // [axis U/V][vector]: world box (filled by Refine)
  float hi[2][kPR];
  int c0[2][kPR];    // [axis U/V][vector]: its cell range, inclusive (filled by Refine)
  int c1[2][kPR];
  uint64_t in = 0;       // rays with a segment in the slice
  uint64_t vectors = 0;  // vectors with such a ray
  int u0 = 0, u1 = -1, v0 = 0, v1 = -1;
  float wlo[2] = {0, 0}, whi[2] = {0, 0};  // the union box in world units (U, V)
};

// Geometry of one grid level along U and W (top-level grid or a sub-grid record).
struct Level {
  float lo[3];
  float inv_cs[3];
  int res[3];
};

template <bool kAny>
struct PacketTracer {
  using D = hn::ScalableTag<float>;
  using DI = hn::RebindToSigned<D>;
  using V = hn::Vec<D>;
  using VI = hn::Vec<DI>;
  using M = hn::Mask<D>;

  const DdaGrid& g;
  const Grid& grid;
  PacketRays& r;
  detail::PacketScratch& sc;
  TraceStats* stats;
  size_t nv = 0;            // vectors in the packet
  int K = 0, U = 1, W = 2;  // major axis and the two others
  bool positive = true;     // d[K] > 0 for every live ray
  float err[3] = {0, 0, 0};  // rounding of o + t d, world units, per axis
  float sigma[2] = {0, 0};   // most cells (U, W) a ray moves per slice
  // least and most motion (world units, U and W) of a ray per slice in the rays' direction:
  // cell_size[K] times the least and the largest slope d[U] / d[K] (negated if d[K] < 0)
  float move_lo[2] = {0, 0}, move_hi[2] = {0, 0};
  // slices where some ray's segment starts, as bits (slice s = bit s), for res[K] <= 1024
  uint64_t starts[16] = {};
  bool starts_ok = false;
  uint64_t cells = 0;
  uint64_t tests = 0;
  uint64_t one_ready = 0;  // rays whose PreparedRay (r.one) is set up
  float k_union_lo = 0.0f, k_union_hi = 0.0f;  // any hit: the K range of every vector's rays
  const uint32_t* skip_rings = nullptr;  // DdaGrid::skip (null: none)

  static size_t Lanes() { return hn::Lanes(D()); }
  static uint64_t LaneMask() {
    return Lanes() >= 64 ? ~uint64_t{0} : (uint64_t{1} << Lanes()) - 1;
  }

  // Cell index of coordinate x on a level's axis a, clamped to [0, res - 1] (NaN -> 0); CellOf1
  // is the same for one value.
  static HWY_INLINE int CellOf1(float x, const Level& lv, int a) {
    const float f = (x - lv.lo[a]) * lv.inv_cs[a];
    // clamped in float, then truncated: the same cell as f > 0 ? (f < res ? int(f) : res - 1)
    // : 0 (res - 1 < 2^24 is exact; for f in [res - 1, res) both give res - 1), without the
    // branches (maxss / minss; 4 cells per vector and slice in Refine)
    const float lo = f > 0.0f ? f : 0.0f;  // NaN -> 0
    const float hi = float(lv.res[a] - 1);
    return int(lo < hi ? lo : hi);
  }
  static HWY_INLINE VI CellOf(D d, V x, const Level& lv, int a) {
    const DI di;
    const V f = hn::Mul(hn::Sub(x, hn::Set(d, lv.lo[a])), hn::Set(d, lv.inv_cs[a]));
    const VI res_m1 = hn::Set(di, lv.res[a] - 1);
    return hn::IfThenElse(
        hn::RebindMask(di, hn::Gt(f, hn::Zero(d))),
        hn::IfThenElse(hn::RebindMask(di, hn::Lt(f, hn::Set(d, float(lv.res[a])))),
                       hn::ConvertTo(di, f), res_m1),
        hn::Zero(di));
  }

  // Where the segments of rays [i, i + Lanes) end: t1, or the candidate if closer. Any hit: the
  // candidate stays tmax >= t1 (an occluded ray is retired instead), so t1 alone.
  HWY_INLINE V SegmentEnd(D d, size_t i) const {
    if constexpr (kAny) {
      return hn::Load(d, r.t1 + i);
    } else {
      return hn::Min(hn::Load(d, r.best + i), hn::Load(d, r.t1 + i));
    }
  }

  // The footprint of the live rays among `filter` whose segment has K in [p0, p1] (p0 < p1),
  // on level `lv`.
  // terminate: first retire the rays whose candidate or segment end lies before the plane K =
  // near (the per-ray DDA's boundary t, bit for bit: no closer hit can lie beyond it); *live_rays
  // gets the rays still live.
  template <bool kTerminate>
  HWY_INLINE void Footprint(float p0, float p1, const Level& lv, uint64_t filter, SliceFoot* f,
                            float near = 0.0f, size_t* live_rays = nullptr) const {
    const D d;
    const DI di;
    const size_t n = Lanes();
    const V big = hn::Set(d, FLT_MAX), nbig = hn::Set(d, -FLT_MAX);
    V plo[2] = {big, big}, phi[2] = {nbig, nbig};
    // the slice's planes in the rays' direction (entry, exit), the rounding pads and the arrays,
    // hoisted: locals the compiler need not reload after the stores below
    const V p_entry = hn::Set(d, positive ? p0 : p1), p_exit = hn::Set(d, positive ? p1 : p0);
    const V near_v = hn::Set(d, near);
    const V e[2] = {hn::Set(d, err[U]), hn::Set(d, err[W])};
    int32_t* const live_p = r.live;
    const float* const ok_p = r.o[K];
    const float* const inv_p = r.inv_k;
    const float* const t0_p = r.t0;
    const float* const o_p[2] = {r.o[U], r.o[W]};
    const float* const d_p[2] = {r.d[U], r.d[W]};
    float* const flo_p[2] = {r.flo[0], r.flo[1]};
    float* const fhi_p[2] = {r.fhi[0], r.fhi[1]};
    uint64_t in_bits = 0, vector_bits = 0;
    size_t live_count = 0;
    for (size_t w = 0; w < nv; ++w) {
      const uint64_t want = (filter >> (w * n)) & LaneMask();
      if (want == 0) continue;
      const size_t i = w * n;
      M live = hn::RebindMask(d, hn::Ne(hn::Load(di, live_p + i), hn::Zero(di)));
      if (hn::AllFalse(d, live)) continue;
      const V ok = hn::Load(d, ok_p + i), inv = hn::Load(d, inv_p + i);
      const V end = SegmentEnd(d, i);
      if constexpr (kTerminate) {
        const V t_near = hn::Mul(hn::Sub(near_v, ok), inv);
        const M done = hn::And(live, hn::Le(end, t_near));
        if (!hn::AllFalse(d, done)) {
          live = hn::AndNot(done, live);
          hn::Store(hn::VecFromMask(di, hn::RebindMask(di, live)), di, live_p + i);
        }
        live_count += hn::CountTrue(d, live);
      }
      if (want != LaneMask()) {
        uint8_t want_bytes[8];
        std::memcpy(want_bytes, &want, sizeof want_bytes);  // little-endian lane bits
        live = hn::And(live, hn::LoadMaskBits(d, want_bytes));
      }
      if (hn::AllFalse(d, live)) continue;
      const V t_in = hn::Max(hn::Mul(hn::Sub(p_entry, ok), inv), hn::Load(d, t0_p + i));
      const V t_out = hn::Min(hn::Mul(hn::Sub(p_exit, ok), inv), end);
      const M in = hn::And(live, hn::Le(t_in, t_out));
      if (hn::AllFalse(d, in)) continue;
      uint8_t bytes[8] = {};
      hn::StoreMaskBits(d, in, bytes);
      uint64_t bits = 0;
      std::memcpy(&bits, bytes, sizeof bits);
      in_bits |= (bits & LaneMask()) << i;
      vector_bits |= uint64_t{1} << w;
      for (int a = 0; a < 2; ++a) {
        const V o = hn::Load(d, o_p[a] + i), dir = hn::Load(d, d_p[a] + i);
        const V pa = hn::Add(o, hn::Mul(t_in, dir)), pb = hn::Add(o, hn::Mul(t_out, dir));
        const V lo = hn::IfThenElse(in, hn::Sub(hn::Min(pa, pb), e[a]), big);
        const V hi = hn::IfThenElse(in, hn::Add(hn::Max(pa, pb), e[a]), nbig);
        hn::Store(lo, d, flo_p[a] + i);
        hn::Store(hi, d, fhi_p[a] + i);
        plo[a] = hn::Min(plo[a], lo);
        phi[a] = hn::Max(phi[a], hi);
      }
    }
    f->in = in_bits;
    f->vectors = vector_bits;
    if constexpr (kTerminate) *live_rays += live_count;
    const int axes[2] = {U, W};
    if (f->vectors == 0) return;
    int c[4];
    for (int a = 0; a < 2; ++a) {
      f->wlo[a] = hn::GetLane(hn::MinOfLanes(d, plo[a]));
      f->whi[a] = hn::GetLane(hn::MaxOfLanes(d, phi[a]));
      c[2 * a] = CellOf1(f->wlo[a], lv, axes[a]);
      c[2 * a + 1] = CellOf1(f->whi[a], lv, axes[a]);
    }
    f->u0 = c[0];
    f->u1 = c[1];
    f->v0 = c[2];
    f->v1 = c[3];
  }

#if HWY_TARGET == HWY_AVX3 || HWY_TARGET == HWY_AVX3_DL
  // The least (kMin) or largest lane of each of a, b, c, e (16 lanes each): in 128-bit block 0,
  // 1, 2, 3 of the result, every lane of the block. The four reductions share their shuffles:
  // halves, then even / odd lanes, then within blocks; no lane mixes two inputs.
  template <bool kMin>
  static HWY_INLINE V Extrema4(D d, V a, V b, V c, V e) {
    const auto op = [](V x, V y) { return kMin ? hn::Min(x, y) : hn::Max(x, y); };
    const V ab = op(hn::ConcatLowerLower(d, b, a), hn::ConcatUpperUpper(d, b, a));
    const V ce = op(hn::ConcatLowerLower(d, e, c), hn::ConcatUpperUpper(d, e, c));
    const V z = op(hn::ConcatEven(d, ce, ab), hn::ConcatOdd(d, ce, ab));
    const V y = op(z, hn::Shuffle2301(z));
    return op(y, hn::Shuffle1032(y));
  }
#endif
#if HWY_TARGET == HWY_AVX2
  // The least (kMin) or largest lane of each of v[0..7] (8 lanes each), in lane w of the result:
  // 128-bit halves, then even / odd lanes twice, the eight reductions sharing their shuffles
  // (15 shuffles and 7 min / max instead of 8 MinOfLanes); no lane mixes two inputs.
  template <bool kMin>
  static HWY_INLINE V Extrema8(D d, const V* v) {
    const auto op = [](V x, V y) { return kMin ? hn::Min(x, y) : hn::Max(x, y); };
    V p[4], q[2];
    for (int k = 0; k < 4; ++k) {
      p[k] = op(hn::ConcatLowerLower(d, v[2 * k + 1], v[2 * k]),
                hn::ConcatUpperUpper(d, v[2 * k + 1], v[2 * k]));
    }
    for (int k = 0; k < 2; ++k) {
      q[k] = op(hn::ConcatEven(d, p[2 * k + 1], p[2 * k]),
                hn::ConcatOdd(d, p[2 * k + 1], p[2 * k]));
    }
    return op(hn::ConcatEven(d, q[1], q[0]), hn::ConcatOdd(d, q[1], q[0]));
  }
#endif

  // The rest of footprint f, needed only where the slice has occupied cells: per vector the box
  // of its rays (triangle culling) and its cell range on level lv.
  HWY_INLINE void Refine(const Level& lv, SliceFoot* f) const {
    const D d;
    const size_t n = Lanes();
    const int axes[2] = {U, W};
#if HWY_TARGET == HWY_AVX3 || HWY_TARGET == HWY_AVX3_DL
    if (n * 4 == kPR) {  // the packet's 4 vectors at once (Extrema4)
      const DI di;
      const V big = hn::Set(d, FLT_MAX), nbig = hn::Set(d, -FLT_MAX);
      const auto get = [&](const float* p, size_t w, V none) {
        return (f->vectors >> w & 1) != 0 ? hn::Load(d, p + w * n) : none;
      };
      HWY_ALIGN float lo[2][16], hi[2][16];
      HWY_ALIGN int32_t c0[2][16], c1[2][16];
      for (int a = 0; a < 2; ++a) {
        const V vlo = Extrema4<true>(d, get(r.flo[a], 0, big), get(r.flo[a], 1, big),
                                     get(r.flo[a], 2, big), get(r.flo[a], 3, big));
        const V vhi = Extrema4<false>(d, get(r.fhi[a], 0, nbig), get(r.fhi[a], 1, nbig),
                                      get(r.fhi[a], 2, nbig), get(r.fhi[a], 3, nbig));
        hn::Store(vlo, d, lo[a]);
        hn::Store(vhi, d, hi[a]);
        // the cells of all boxes at once (CellOf: the same cells as CellOf1)
        hn::Store(CellOf(d, vlo, lv, axes[a]), di, c0[a]);
        hn::Store(CellOf(d, vhi, lv, axes[a]), di, c1[a]);
      }
      for (uint64_t vb = f->vectors; vb != 0; vb &= vb - 1) {
        const size_t w = hwy::Num0BitsBelowLS1Bit_Nonzero64(vb);
        for (int a = 0; a < 2; ++a) {
          f->lo[a][w] = lo[a][4 * w];
          f->hi[a][w] = hi[a][4 * w];
          f->c0[a][w] = c0[a][4 * w];
          f->c1[a][w] = c1[a][4 * w];
        }
      }
      return;
    }
#endif
#if HWY_TARGET == HWY_AVX2
    // the packet's 8 vectors at once (Extrema8, vector w in lane w), where 3 or more have rays
    // in the slice (fewer: sub-slices of a sub-grid, say, are cheaper one by one)
    if (n * 8 == kPR && hwy::PopCount(f->vectors) >= 3) {
      const DI di;
      const V big = hn::Set(d, FLT_MAX), nbig = hn::Set(d, -FLT_MAX);
      for (int a = 0; a < 2; ++a) {
        V lo[8], hi[8];
        for (size_t w = 0; w < 8; ++w) {
          const bool in = (f->vectors >> w & 1) != 0;
          lo[w] = in ? hn::Load(d, r.flo[a] + w * n) : big;
          hi[w] = in ? hn::Load(d, r.fhi[a] + w * n) : nbig;
        }
        const V vlo = Extrema8<true>(d, lo), vhi = Extrema8<false>(d, hi);
        hn::StoreU(vlo, d, f->lo[a]);
        hn::StoreU(vhi, d, f->hi[a]);
        hn::StoreU(CellOf(d, vlo, lv, axes[a]), di, f->c0[a]);
        hn::StoreU(CellOf(d, vhi, lv, axes[a]), di, f->c1[a]);
      }
      return;
    }
#endif
    for (uint64_t vb = f->vectors; vb != 0; vb &= vb - 1) {
      const size_t w = hwy::Num0BitsBelowLS1Bit_Nonzero64(vb);
      const size_t i = w * n;
      for (int a = 0; a < 2; ++a) {
        f->lo[a][w] = hn::GetLane(hn::MinOfLanes(d, hn::Load(d, r.flo[a] + i)));
        f->hi[a][w] = hn::GetLane(hn::MaxOfLanes(d, hn::Load(d, r.fhi[a] + i)));
        f->c0[a][w] = CellOf1(f->lo[a][w], lv, axes[a]);
        f->c1[a][w] = CellOf1(f->hi[a][w], lv, axes[a]);
      }
    }
  }

  // Vector w against one triangle (9 floats, x y z per vertex, component c at p[c * stride]:
  // read in place from the leaf's bundles, broadcast straight from memory): broadcast in the
  // vector's permutation if its rays share one, otherwise each lane picks its own axes.
  HWY_INLINE void TestVector(size_t w, const float* p, size_t stride, int32_t id) {
    const D d;
    const DI di;
    const size_t i = w * Lanes();
    const M live = hn::RebindMask(d, hn::Ne(hn::Load(di, r.live + i), hn::Zero(di)));
    if (kAny && hn::AllFalse(d, live)) return;  // every ray of the vector is occluded
    // the triangle's components in each lane's (kx, ky, kz) order; a function, so that the
    // test's rare near-origin path can recompute them instead of keeping them live
    const auto load = [this, p, stride, w](V* c) {
      const D d;
      const DI di;
      const size_t i = w * Lanes();
      if (r.perm[w] >= 0) {
        const int k[3] = {r.perm[w] & 3, (r.perm[w] >> 2) & 3, (r.perm[w] >> 4) & 3};
        for (int vtx = 0; vtx < 3; ++vtx) {
          for (int a = 0; a < 3; ++a) {
            c[3 * vtx + a] = hn::Set(d, p[size_t(3 * vtx + k[a]) * stride]);
          }
        }
      } else {
        const VI kx = hn::Load(di, r.k[0] + i), ky = hn::Load(di, r.k[1] + i);
        const VI kz = hn::Load(di, r.k[2] + i);
        const VI one = hn::Set(di, 1);
        const M kx0 = hn::RebindMask(d, hn::Eq(kx, hn::Zero(di)));
        const M kx1 = hn::RebindMask(d, hn::Eq(kx, one));
        const M ky0 = hn::RebindMask(d, hn::Eq(ky, hn::Zero(di)));
        const M ky1 = hn::RebindMask(d, hn::Eq(ky, one));
        const M kz0 = hn::RebindMask(d, hn::Eq(kz, hn::Zero(di)));
        const M kz1 = hn::RebindMask(d, hn::Eq(kz, one));
        for (int vtx = 0; vtx < 3; ++vtx) {
          const V x = hn::Set(d, p[size_t(3 * vtx) * stride]);
          const V y = hn::Set(d, p[size_t(3 * vtx + 1) * stride]);
          const V z = hn::Set(d, p[size_t(3 * vtx + 2) * stride]);
          c[3 * vtx + 0] = PickAxis(kx0, kx1, x, y, z);
          c[3 * vtx + 1] = PickAxis(ky0, ky1, x, y, z);
          c[3 * vtx + 2] = PickAxis(kz0, kz1, x, y, z);
        }
      }
    };
    V c[9];
    load(c);
    const V best = hn::Load(d, r.best + i);
    tests += hn::CountTrue(d, live);
    WatertightLanes<D> wt;
    M m = WatertightTest<false>(d, c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7], c[8],
                                hn::Load(d, r.wo[0] + i), hn::Load(d, r.wo[1] + i),
                                hn::Load(d, r.wo[2] + i), hn::Load(d, r.shear[0] + i),
                                hn::Load(d, r.shear[1] + i), hn::Load(d, r.shear[2] + i),
                                hn::Load(d, r.tmin + i), best, load, &wt);
    m = hn::And(m, live);
    if (hn::AllFalse(d, m)) return;
    if constexpr (kAny) {
      // occluded (prim = 1): the lane is done
      hn::Store(hn::IfThenZeroElse(hn::RebindMask(di, m), hn::Load(di, r.live + i)), di,
                r.live + i);
      hn::Store(hn::IfThenElse(hn::RebindMask(di, m), hn::Set(di, 1), hn::Load(di, r.prim + i)),
                di, r.prim + i);
    } else {
      // the rule of IntersectBundles: t <= best was required; equal t needs a lower id
      const VI prim = hn::Load(di, r.prim + i);
      const VI idv = hn::Set(di, id);
      const auto lower_id = hn::Or(hn::Lt(prim, hn::Zero(di)), hn::Lt(idv, prim));
      const M beats =
          hn::Or(hn::Lt(wt.t, best), hn::And(hn::Eq(wt.t, best), hn::RebindMask(d, lower_id)));
      m = hn::And(m, beats);
      if (hn::AllFalse(d, m)) return;
      // u = V / det, v = W / det as the scalar code: V * (1 / det)
      const V inv_det = hn::Div(hn::Set(d, 1.0f), wt.det);
      hn::Store(hn::IfThenElse(m, wt.t, best), d, r.best + i);
      hn::Store(hn::IfThenElse(hn::RebindMask(di, m), idv, prim), di, r.prim + i);
      hn::Store(hn::IfThenElse(m, hn::Mul(wt.v, inv_det), hn::Load(d, r.bu + i)), d, r.bu + i);
      hn::Store(hn::IfThenElse(m, hn::Mul(wt.w, inv_det), hn::Load(d, r.bv + i)), d, r.bv + i);
    }
  }

  // Triangles [j, j + Lanes(dt)) of a leaf's bundles: each against the vectors in `wide` whose
  // slice box meets the triangle's bounding box (SIMD over triangles), then mailboxed per vector.
  template <class DT>
  HWY_INLINE void CullGroup(DT dt, const TriBundleSpan& span, size_t j, uint64_t wide,
                            const SliceFoot& f) {
    using VT = hn::Vec<DT>;
    const size_t stride = span.stride();
    const float* b = span.vertices + j;
    const VT u0 = hn::LoadU(dt, b + size_t(U) * stride);
    const VT u1 = hn::LoadU(dt, b + size_t(3 + U) * stride);
    const VT u2 = hn::LoadU(dt, b + size_t(6 + U) * stride);
    const VT v0 = hn::LoadU(dt, b + size_t(W) * stride);
    const VT v1 = hn::LoadU(dt, b + size_t(3 + W) * stride);
    const VT v2 = hn::LoadU(dt, b + size_t(6 + W) * stride);
    // NaN vertices (padding, degenerate) fail every compare: never tested
    const VT ulo = hn::Min(u0, hn::Min(u1, u2)), uhi = hn::Max(u0, hn::Max(u1, u2));
    const VT vlo = hn::Min(v0, hn::Min(v1, v2)), vhi = hn::Max(v0, hn::Max(v1, v2));
    // any hit: K too (PacketRays::k_lo / k_hi: the vector's segments, not only this slice)
    [[maybe_unused]] VT klo = ulo, khi = uhi;
    if constexpr (kAny) {
      const VT k0 = hn::LoadU(dt, b + size_t(K) * stride);
      const VT k1 = hn::LoadU(dt, b + size_t(3 + K) * stride);
      const VT k2 = hn::LoadU(dt, b + size_t(6 + K) * stride);
      klo = hn::Min(k0, hn::Min(k1, k2));
      khi = hn::Max(k0, hn::Max(k1, k2));
    }
    // the group against the slice's union box first (and any hit: the packet's K range): most
    // triangles of a leaf lie outside the packet's few cells
    {
      auto m = hn::And(
          hn::And(hn::Le(ulo, hn::Set(dt, f.whi[0])), hn::Ge(uhi, hn::Set(dt, f.wlo[0]))),
          hn::And(hn::Le(vlo, hn::Set(dt, f.whi[1])), hn::Ge(vhi, hn::Set(dt, f.wlo[1]))));
      if constexpr (kAny) {
        m = hn::And(m, hn::And(hn::Le(klo, hn::Set(dt, k_union_hi)),
                               hn::Ge(khi, hn::Set(dt, k_union_lo))));
      }
      if (hn::AllFalse(dt, m)) return;
    }
    uint64_t vecs[16] = {};  // per triangle of the group: vectors to test (bit w)
    bool any = false;
    for (uint64_t wb = wide; wb != 0; wb &= wb - 1) {
      const size_t w = hwy::Num0BitsBelowLS1Bit_Nonzero64(wb);
      auto m = hn::And(
          hn::And(hn::Le(ulo, hn::Set(dt, f.hi[0][w])), hn::Ge(uhi, hn::Set(dt, f.lo[0][w]))),
          hn::And(hn::Le(vlo, hn::Set(dt, f.hi[1][w])), hn::Ge(vhi, hn::Set(dt, f.lo[1][w]))));
      if constexpr (kAny) {
        m = hn::And(m, hn::And(hn::Le(klo, hn::Set(dt, r.k_hi[w])),
                               hn::Ge(khi, hn::Set(dt, r.k_lo[w]))));
      }
      if (hn::AllFalse(dt, m)) continue;
      any = true;
      uint8_t bits[8] = {};
      hn::StoreMaskBits(dt, m, bits);
      const uint32_t mb = uint32_t(bits[0]) | uint32_t(bits[1]) << 8;
      for (uint32_t t = mb; t != 0; t &= t - 1) {
        vecs[hwy::Num0BitsBelowLS1Bit_Nonzero32(t)] |= uint64_t{1} << w;
      }
    }
    if (!any) return;
    for (size_t t = 0; t < hn::Lanes(dt); ++t) {
      if (vecs[t] == 0) continue;
      const int32_t id = span.ids[j + t];
      const size_t slot = (uint32_t(id) * 2654435761u) >> 22;  // 10 bits: kMailbox entries
      // the stamp first: an entry of an earlier packet (or never written: InitScratch zeroes
      // the stamps only, and serials start at 1) is not read further
      const bool mine = sc.mb_stamp[slot] == sc.serial && sc.mb_id[slot] == id;
      const uint64_t done = mine ? sc.mb_tested[slot] : 0;
      const uint64_t todo = vecs[t] & ~done;
      if (todo == 0) continue;
      const float* p = span.vertices + j + t;
      for (uint64_t wb = todo; wb != 0; wb &= wb - 1) {
        TestVector(hwy::Num0BitsBelowLS1Bit_Nonzero64(wb), p, stride, id);
      }
      sc.mb_id[slot] = id;
      sc.mb_stamp[slot] = sc.serial;
      sc.mb_tested[slot] = done | todo;
    }
  }

  // Ray l against a leaf's bundles with the 1-ray x 4-triangle kernel (no mailbox: a repeated
  // test changes nothing).
  HWY_INLINE void TestRay(size_t l, const TriBundleSpan& span) {
    if (r.live[l] == 0) return;
    tests += span.lanes();
    if ((one_ready >> l & 1) == 0) {  // the 1-ray kernels' setup, from the same lane values
      const float* const o[3] = {r.o[0], r.o[1], r.o[2]};
      const float* const dd[3] = {r.d[0], r.d[1], r.d[2]};
      const float* const wo[3] = {r.wo[0], r.wo[1], r.wo[2]};
      const float* const shear[3] = {r.shear[0], r.shear[1], r.shear[2]};
      const int32_t* const k[3] = {r.k[0], r.k[1], r.k[2]};
      r.one[l] = PreparedRayFromLanes(o, dd, wo, shear, k, l);
      one_ready |= uint64_t{1} << l;
    }
    if constexpr (kAny) {
      if (BundlesWidth<TriTest::kWatertight, true>(r.one[l], span, r.tmin[l], r.tmax[l],
                                                   BundleWidth::kAuto, nullptr)) {
        r.prim[l] = 1;
        r.live[l] = 0;
      }
    } else {
      ClosestHit h;
      h.t = r.best[l];
      h.prim = r.prim[l];
      if (BundlesWidth<TriTest::kWatertight, false>(r.one[l], span, r.tmin[l], r.tmax[l],
                                                    BundleWidth::kAuto, &h)) {
        r.best[l] = h.t;
        r.prim[l] = h.prim;
        r.bu[l] = h.u;
        r.bv[l] = h.v;
      }
    }
  }

  // The triangles of one leaf against the rays in `rays` (bit i = ray i passes the leaf): a
  // vector with few of its rays there tests them one by one (1 ray x 4 triangles), the others
  // N rays x 1 triangle, each triangle culled by the vector's box in this slice and mailboxed
  // per vector.
  HWY_INLINE void VisitLeaf(uint32_t leaf, uint64_t rays, const SliceFoot& f) {
    const TriBundleSpan span = g.bundles.Cell(leaf);
    if (span.count == 0) return;
    const size_t L = Lanes();
    uint64_t wide = 0;
    for (size_t w = 0; w < nv; ++w) {
      const uint64_t lanes = (rays >> (w * L)) & LaneMask();
      if (lanes == 0) continue;
      if (size_t(hwy::PopCount(lanes)) * kOneRayShare <= L) {
        for (uint64_t b = lanes; b != 0; b &= b - 1) {
          TestRay(w * L + hwy::Num0BitsBelowLS1Bit_Nonzero64(b), span);
        }
      } else {
        wide |= uint64_t{1} << w;
      }
    }
    if (wide == 0) return;
    const size_t lanes = span.lanes();
    size_t j = 0;
    if constexpr (HWY_MAX_BYTES >= 64) {
      const hn::CappedTag<float, 16> d16;
      if (hn::Lanes(d16) == 16) {
        for (; j + 16 <= lanes; j += 16) CullGroup(d16, span, j, wide, f);
      }
    }
    if constexpr (HWY_MAX_BYTES >= 32) {
      const hn::CappedTag<float, 8> d8;
      if (hn::Lanes(d8) == 8) {
        for (; j + 8 <= lanes; j += 8) CullGroup(d8, span, j, wide, f);
      }
    }
    const hn::CappedTag<float, 4> d4;
    for (; j < lanes; j += hn::Lanes(d4)) CullGroup(d4, span, j, wide, f);
  }

  // Marks, for footprint f of a level, the cells each vector's box covers with the vector's rays
  // in the slice (in `marks`, a ray mask per cell of a kStride x kStride window, all zero on
  // entry and on return; `list` holds the marked cells); returns false, marking nothing, if the
  // footprint is wider than the window. Then calls visit(cell (u, v), rays) per marked cell.
  template <int kStride, class Visit>
  HWY_INLINE bool ForMarkedCells(const SliceFoot& f, uint64_t* marks, uint16_t* list,
                                 const Visit& visit) {
    const int wu = f.u1 - f.u0 + 1, wv = f.v1 - f.v0 + 1;
    if (wu > kStride || wv > kStride) return false;
    const size_t L = Lanes();
    size_t n = 0;
    for (uint64_t vb = f.vectors; vb != 0; vb &= vb - 1) {
      const size_t w = hwy::Num0BitsBelowLS1Bit_Nonzero64(vb);
      const uint64_t bits = f.in & (LaneMask() << (w * L));
      for (int cv = f.c0[1][w]; cv <= f.c1[1][w]; ++cv) {
        uint64_t* row = marks + (cv - f.v0) * kStride - f.u0;
        for (int cu = f.c0[0][w]; cu <= f.c1[0][w]; ++cu) {
          if (row[cu] == 0) list[n++] = uint16_t((cv - f.v0) * kStride + (cu - f.u0));
          row[cu] |= bits;
        }
      }
    }
    cells += n;
    for (size_t k = 0; k < n; ++k) {
      const int local = list[k];
      const uint64_t rays = marks[local];
      marks[local] = 0;
      visit(f.u0 + local % kStride, f.v0 + local / kStride, rays);
    }
    return true;
  }

  // A refined top-level cell, entered by `rays`: its 8 sub-slices along K.
  HWY_INLINE bool VisitSubGrid(const SubGridRecord& rec, uint64_t rays) {
    Level lv;
    for (int a = 0; a < 3; ++a) {
      lv.lo[a] = rec.lo[a];
      lv.inv_cs[a] = rec.inv_cell_size[a];
      lv.res[a] = kSubRes;
    }
    SliceFoot f;
    static_assert(sizeof(sc.sub_marks) == kSubRes * kSubRes * sizeof(uint64_t), "sub-slice");
    for (int step = 0; step < kSubRes; ++step) {
      const int k = positive ? step : kSubRes - 1 - step;
      const float p0 = rec.lo[K] + float(k) * rec.cell_size[K];
      const float p1 = rec.lo[K] + float(k + 1) * rec.cell_size[K];
      Footprint<false>(p0 - err[K], p1 + err[K], lv, rays, &f);
      if (f.vectors == 0) continue;
      Refine(lv, &f);
      const auto visit = [&](int cu, int cv, uint64_t in) {
        int c[3];
        c[K] = k;
        c[U] = cu;
        c[W] = cv;
        if (rec.Occupied(c[0], c[1], c[2])) VisitLeaf(rec.Leaf(c[0], c[1], c[2]), in, f);
      };
      const bool ok = ForMarkedCells<kSubRes>(f, sc.sub_marks, sc.sub_list, visit);
      HWY_DASSERT(ok);  // 8 x 8 sub-cells always fit
      (void)ok;
    }
    return true;
  }

  // Empty-space skipping (DdaGrid::skip): slices the packet may jump over from slice s, whose
  // footprint is f: k empty rings around the cell at the centre of f's box mean that every cell
  // within Chebyshev distance k of it is empty. The rays' boxes in slices s .. s + m - 1 lie within
  // f's box grown by i * sigma cells (each ray moves at most sigma cells per slice), so they are
  // all empty if that stays within the rings, and if no ray starts its segment in between.
  // Returns m (0: no jump). Results are unchanged: the slices jumped hold no triangle.
  HWY_INLINE int EmptyJump(const SliceFoot& f, int s, const uint32_t* skip,
                           const int stride[3]) const {
    const int cu = (f.u0 + f.u1) / 2, cv = (f.v0 + f.v1) / 2;
    const size_t cell = size_t(s) * stride[K] + size_t(cv) * stride[W] + size_t(cu) * stride[U];
    const int k = int((skip[cell >> 2] >> (8 * (cell & 3))) & 0xffu);
    if (k < 2) return 0;
    int m = k;
    const int hw[2] = {std::max(cu - f.u0, f.u1 - cu), std::max(cv - f.v0, f.v1 - cv)};
    for (int a = 0; a < 2; ++a) {
      const int e = k - hw[a] - 1;  // - 1: rounding up of i * sigma
      if (e < 0) return 0;
      if (sigma[a] > 0.0f) m = std::min(m, int(float(e) / sigma[a]) + 1);
    }
    // rays whose segment starts in a later slice must find their own cells
    if (!starts_ok) return 0;
    const int next = NextStart(s);
    if (next >= 0) m = std::min(m, positive ? next - s : s - next);
    return m >= 2 ? m : 0;
  }

  // Empty slices ahead of slice s without their footprints. After s the rays only retire or
  // shorten, and no ray enters before the next slice where a segment starts (NextStart, as
  // EmptyJump), so a ray in slice s + i (i >= 1, in the rays' direction) passed the far plane of
  // slice s at a point P of f's world box, and its points in slice s + i lie between (i - 1) and
  // i slices (widened by the err[K] of both footprints) beyond P: at P + t * slope * cell_size[K]
  // along U and W, t in [i - 1, i], slope within [move_lo, move_hi]. So f's box moved by those
  // bounds, widened by the rounding of o + t d in both footprints (2 err) and a margin, holds
  // them. Returns m: slices s + 1 .. s + m (m <= left) whose predicted boxes hold no occupied
  // cell, i.e. no triangle a ray of the packet could meet there: the box's skip rings show it
  // empty (RingsEmpty: one byte, any area), or it has at most kPredictArea cells and none is
  // occupied. Results are unchanged: only empty slices are skipped. A skipped slice costs a few
  // occupancy reads instead of a footprint (most of a shadow packet's walk is empty space that
  // EmptyJump's rings, centred on the packet, are too small to jump).
  HWY_INLINE int PredictEmpty(const SliceFoot& f, int s, int left, const Level& top,
                              const uint64_t* occ, const int stride[3]) {
    if (!starts_ok || left <= 0) return 0;
    const int next = NextStart(s);
    if (next >= 0) left = std::min(left, (positive ? next - s : s - next) - 1);
    const int axes[2] = {U, W};
    float pad[2];
    for (int a = 0; a < 2; ++a) {
      pad[a] = 2.0f * err[axes[a]] + 0.01f * grid.cell_size[axes[a]];
    }
    // err[K] in slices, both footprints
    const float ek = 4.0f * err[K] * grid.inv_cell_size[K];
    int m = 0;
    for (int i = 1; i <= left; ++i) {
      // t range in slices, widened by the K rounding and a relative margin
      const float ta = float(i - 1) - ek - 1e-3f * float(i);
      const float tb = float(i) + ek + 1e-3f * float(i);
      int c0[2], c1[2];
      for (int a = 0; a < 2; ++a) {
        const float lo = std::min(ta * move_lo[a], tb * move_lo[a]);
        const float hi = std::max(ta * move_hi[a], tb * move_hi[a]);
        c0[a] = CellOf1(f.wlo[a] + lo - pad[a], top, axes[a]);
        c1[a] = CellOf1(f.whi[a] + hi + pad[a], top, axes[a]);
      }
      const int sl = positive ? s + i : s - i;
      const size_t row0 = size_t(sl) * stride[K];
      // the skip rings of the box's centre cell first: one byte instead of the box's bits, and
      // no area limit where they cover the box
      if (!RingsEmpty(row0, c0[0], c1[0], c0[1], c1[1], stride)) {
        const int area = (c1[0] - c0[0] + 1) * (c1[1] - c0[1] + 1);
        if (area > kPredictArea) break;
        cells += uint64_t(area);
        if (AnyOccupied(occ, row0, c0[0], c1[0], c0[1], c1[1], stride)) break;
      } else {
        ++cells;
      }
      m = i;
    }
    return m;
  }

  // Whether the skip rings (DdaGrid::skip) show every cell (u, v) in [u0, u1] x [v0, v1] of the
  // slice starting at cell row0 empty: k >= 1 rings around the box's centre cell mean that every
  // cell within Chebyshev distance k of it is empty (k = 0: the centre may be occupied). False
  // when unknown (no rings, or too few).
  HWY_INLINE bool RingsEmpty(size_t row0, int u0, int u1, int v0, int v1,
                             const int stride[3]) const {
    if (skip_rings == nullptr) return false;
    const int cu = (u0 + u1) / 2, cv = (v0 + v1) / 2;
    const int hw = std::max(std::max(cu - u0, u1 - cu), std::max(cv - v0, v1 - cv));
    const size_t cell = row0 + size_t(cv) * stride[W] + size_t(cu) * stride[U];
    const int k = int((skip_rings[cell >> 2] >> (8 * (cell & 3))) & 0xffu);
    return k >= 1 && k >= hw;
  }

  // Whether a cell (u, v) in [u0, u1] x [v0, v1] of the slice starting at cell row0 is occupied.
  // Along x (U = 0) a row of cells is a run of occupancy bits: tested a word at a time.
  HWY_INLINE bool AnyOccupied(const uint64_t* occ, size_t row0, int u0, int u1, int v0, int v1,
                              const int stride[3]) const {
    if (U == 0) {
      for (int cv = v0; cv <= v1; ++cv) {
        const size_t b0 = row0 + size_t(cv) * stride[W] + size_t(u0);
        const size_t b1 = b0 + size_t(u1 - u0);  // inclusive
        const uint64_t head = ~uint64_t{0} << (b0 & 63);
        const uint64_t tail = ~uint64_t{0} >> (63 - (b1 & 63));
        const size_t w0 = b0 >> 6, w1 = b1 >> 6;
        if (w0 == w1) {
          if ((occ[w0] & head & tail) != 0) return true;
          continue;
        }
        if ((occ[w0] & head) != 0 || (occ[w1] & tail) != 0) return true;
        for (size_t w = w0 + 1; w < w1; ++w) {
          if (occ[w] != 0) return true;
        }
      }
      return false;
    }
    for (int cv = v0; cv <= v1; ++cv) {
      for (int cu = u0; cu <= u1; ++cu) {
        const size_t cell = row0 + size_t(cv) * stride[W] + size_t(cu) * stride[U];
        if (((occ[cell >> 6] >> (cell & 63)) & 1u) != 0) return true;
      }
    }
    return false;
  }

  // The nearest slice after s (in the rays' direction) where a segment starts, or -1.
  HWY_INLINE int NextStart(int s) const {
    if (positive) {
      for (int b = s + 1; b < 16 * 64;) {
        const uint64_t word = starts[b >> 6] >> (b & 63);
        if (word != 0) return b + int(hwy::Num0BitsBelowLS1Bit_Nonzero64(word));
        b = (b | 63) + 1;
      }
    } else {
      for (int b = s - 1; b >= 0;) {
        const uint64_t word = starts[b >> 6] << (63 - (b & 63));
        if (word != 0) return b - int(hwy::Num0BitsAboveMS1Bit_Nonzero64(word));
        b = (b & ~63) - 1;
      }
    }
    return -1;
  }

  // Returns false if the packet is refused (not coherent, or too wide to pay); then nothing was
  // written to the output.
  HWY_INLINE bool Trace(const RayStreamView& rays, size_t first, size_t n) {
    const D d;
    const DI di;
    const size_t L = Lanes();
    nv = (n + L - 1) / L;
    if (nv * L > kPR) return false;
    const V zero = hn::Zero(d), one = hn::Set(d, 1.0f);
    Level top;
    for (int a = 0; a < 3; ++a) {
      top.lo[a] = grid.lo[a];
      top.inv_cs[a] = grid.inv_cell_size[a];
      top.res[a] = grid.res[a];
    }

    V sum_d[3] = {zero, zero, zero};
    V omax[3] = {zero, zero, zero};
    V dmax[3] = {zero, zero, zero};
    size_t n_valid = 0;
    for (size_t w = 0; w < nv; ++w) {
      const size_t i = w * L;
      const size_t at = first + i;
      const M in_packet = hn::FirstN(d, n - i);
      V o[3], dir[3];
      o[0] = hn::LoadU(d, rays.ox + at);
      o[1] = hn::LoadU(d, rays.oy + at);
      o[2] = hn::LoadU(d, rays.oz + at);
      dir[0] = hn::LoadU(d, rays.dx + at);
      dir[1] = hn::LoadU(d, rays.dy + at);
      dir[2] = hn::LoadU(d, rays.dz + at);
      const V tmin = hn::LoadU(d, rays.tmin + at), tmax = hn::LoadU(d, rays.tmax + at);
      // RayIsValid, a non-empty (tmin, tmax] and the slab clip (the stream DDA's setup)
      const V tmax_f = FiniteTmax(d, tmax);
      M valid = ValidRayLanes(d, o, dir, tmin, tmax_f, in_packet);
      V t0 = tmin, t1 = tmax_f;
      V inv_d[3];
      M parallel[3];
      valid = ClipRayLanes(d, grid.lo, grid.hi, o, dir, valid, &t0, &t1, inv_d, parallel);
      // zero the invalid lanes' geometry so that sums and bounds stay finite
      for (int a = 0; a < 3; ++a) {
        o[a] = hn::IfThenElseZero(valid, o[a]);
        dir[a] = hn::IfThenElseZero(valid, dir[a]);
        hn::Store(o[a], d, r.o[a] + i);
        hn::Store(dir[a], d, r.d[a] + i);
        sum_d[a] = hn::Add(sum_d[a], dir[a]);
        omax[a] = hn::Max(omax[a], hn::Abs(o[a]));
        dmax[a] = hn::Max(dmax[a], hn::Abs(dir[a]));
      }
      t0 = hn::IfThenElseZero(valid, t0);
      t1 = hn::IfThenElseZero(valid, t1);
      hn::Store(t0, d, r.t0 + i);
      hn::Store(t1, d, r.t1 + i);
      hn::Store(tmin, d, r.tmin + i);
      hn::Store(tmax_f, d, r.tmax + i);
      hn::Store(tmax_f, d, r.best + i);
      hn::Store(hn::Set(di, -1), di, r.prim + i);
      hn::Store(zero, d, r.bu + i);
      hn::Store(zero, d, r.bv + i);
      hn::Store(hn::VecFromMask(di, hn::RebindMask(di, valid)), di, r.live + i);
      n_valid += hn::CountTrue(d, valid);
      // watertight setup (PrepareWatertightRay lane by lane, as the stream DDA)
      const WatertightSetupLanes<D> wt = SetupWatertightLanes(d, o, dir);
      for (int a = 0; a < 3; ++a) {
        hn::Store(wt.k[a], di, r.k[a] + i);
        hn::Store(wt.shear[a], d, r.shear[a] + i);
        hn::Store(wt.o[a], d, r.wo[a] + i);
      }
    }
    if (n_valid == 0) {
      Write(first, n);
      return true;
    }
    // major axis: the largest |sum of d| over the valid rays; every valid ray must step the
    // same way along it (and not be parallel to it)
    float sums[3], omaxs[3];
    for (int a = 0; a < 3; ++a) {
      sums[a] = hn::GetLane(hn::SumOfLanes(d, sum_d[a]));
      omaxs[a] = hn::GetLane(hn::MaxOfLanes(d, omax[a]));
    }
    K = 0;
    for (int a = 1; a < 3; ++a) {
      if (std::abs(sums[a]) > std::abs(sums[K])) K = a;
    }
    U = K == 0 ? 1 : 0;
    W = K == 2 ? 1 : 2;
    positive = sums[K] > 0.0f;
    const V min_k = hn::Set(d, kMinDirection);
    V tfar = zero;
    VI s_min = hn::Set(di, grid.res[K]), s_max = hn::Set(di, -1);
    // slopes of the rays against K, for the coherence test below
    V slo[2] = {hn::Set(d, FLT_MAX), hn::Set(d, FLT_MAX)};
    V shi[2] = {hn::Set(d, -FLT_MAX), hn::Set(d, -FLT_MAX)};
    for (size_t w = 0; w < nv; ++w) {
      const size_t i = w * L;
      const M valid = hn::RebindMask(d, hn::Ne(hn::Load(di, r.live + i), hn::Zero(di)));
      const V dk = hn::Load(d, r.d[K] + i);
      const M ok = positive ? hn::Ge(dk, min_k) : hn::Le(dk, hn::Neg(min_k));
      if (!hn::AllTrue(d, hn::Or(ok, hn::Not(valid)))) return false;
      const V inv = hn::IfThenElse(valid, hn::Div(one, dk), zero);
      hn::Store(inv, d, r.inv_k + i);
      tfar = hn::Max(tfar, hn::IfThenElseZero(valid, hn::Load(d, r.t1 + i)));
      const int axes[2] = {U, W};
      for (int a = 0; a < 2; ++a) {
        const V slope = hn::Mul(hn::Load(d, r.d[axes[a]] + i), inv);
        slo[a] = hn::Min(slo[a], hn::IfThenElse(valid, slope, hn::Set(d, FLT_MAX)));
        shi[a] = hn::Max(shi[a], hn::IfThenElse(valid, slope, hn::Set(d, -FLT_MAX)));
      }
      // one permutation for the whole vector? (the valid lanes' keys all equal)
      const VI key = hn::Or(hn::Load(di, r.k[0] + i),
                            hn::Or(hn::ShiftLeft<2>(hn::Load(di, r.k[1] + i)),
                                   hn::ShiftLeft<4>(hn::Load(di, r.k[2] + i))));
      const auto vi = hn::RebindMask(di, valid);
      const VI kmin = hn::MinOfLanes(di, hn::IfThenElse(vi, key, hn::Set(di, 64)));
      const VI kmax = hn::MaxOfLanes(di, hn::IfThenElse(vi, key, hn::Set(di, -1)));
      r.perm[w] = hn::GetLane(kmin) == hn::GetLane(kmax) ? hn::GetLane(kmin) : -1;
      // the slices where the segment starts and ends
      const V orig_k = hn::Load(d, r.o[K] + i);
      const VI s0 = CellOf(d, hn::Add(orig_k, hn::Mul(hn::Load(d, r.t0 + i), dk)), top, K);
      const VI s1 = CellOf(d, hn::Add(orig_k, hn::Mul(hn::Load(d, r.t1 + i), dk)), top, K);
      hn::Store(s0, di, r.s_start + i);
      s_min = hn::Min(s_min, hn::IfThenElse(vi, hn::Min(s0, s1), s_min));
      s_max = hn::Max(s_max, hn::IfThenElse(vi, hn::Max(s0, s1), s_max));
    }
    // coherence: the footprint of a packet widens per slice by the spread of its slopes; beyond
    // kMaxSpread cells per slice the rays diverge (diffuse rays, say) and are traced one by one
    {
      const float per_cell = float(grid.num_refs) / float(std::max<size_t>(1, grid.occupied_cells));
      const float dense = (kAny ? kAnyDenseScale : 1.0f) * kDenseCell;
      const float max_spread = kMaxSpread * std::min(1.0f, dense / per_cell);
      const int axes[2] = {U, W};
      for (int a = 0; a < 2; ++a) {
        const float lo_slope = hn::GetLane(hn::MinOfLanes(d, slo[a]));
        const float hi_slope = hn::GetLane(hn::MaxOfLanes(d, shi[a]));
        const float to_cells = grid.cell_size[K] * grid.inv_cell_size[axes[a]];
        if (!((hi_slope - lo_slope) * to_cells <= max_spread)) return false;
        sigma[a] = std::max(std::abs(lo_slope), std::abs(hi_slope)) * to_cells;
        move_lo[a] = (positive ? lo_slope : -hi_slope) * grid.cell_size[K];
        move_hi[a] = (positive ? hi_slope : -lo_slope) * grid.cell_size[K];
      }
    }
    // rounding of the footprint: o + t d with |t d| <= t_far |d| (|d| summed: an upper bound)
    const float t_far = hn::GetLane(hn::MaxOfLanes(d, tfar));
    for (int a = 0; a < 3; ++a) {
      const float scale = omaxs[a] + t_far * hn::GetLane(hn::MaxOfLanes(d, dmax[a])) +
                          std::max(std::abs(grid.lo[a]), std::abs(grid.hi[a]));
      err[a] = 4e-7f * scale + 1e-4f * grid.cell_size[a];
    }
    if constexpr (kAny) {
      // each vector's K range: o + t d at t0 and t1 (the segment a lane's hit lies on; o + t d
      // rounds within err[K], as the U and W boxes). Shadow rays leave surfaces: a surface
      // across K (a floor below a light) lies outside its rays' K range and is never tested
      const V ek = hn::Set(d, err[K]);
      for (size_t w = 0; w < nv; ++w) {
        const size_t i = w * L;
        const M valid = hn::RebindMask(d, hn::Ne(hn::Load(di, r.live + i), hn::Zero(di)));
        const V ok = hn::Load(d, r.o[K] + i), dk = hn::Load(d, r.d[K] + i);
        const V ka = hn::Add(ok, hn::Mul(hn::Load(d, r.t0 + i), dk));
        const V kb = hn::Add(ok, hn::Mul(hn::Load(d, r.t1 + i), dk));
        const V lo = hn::IfThenElse(valid, hn::Sub(hn::Min(ka, kb), ek), hn::Set(d, FLT_MAX));
        const V hi = hn::IfThenElse(valid, hn::Add(hn::Max(ka, kb), ek), hn::Set(d, -FLT_MAX));
        r.k_lo[w] = hn::GetLane(hn::MinOfLanes(d, lo));
        r.k_hi[w] = hn::GetLane(hn::MaxOfLanes(d, hi));
      }
      k_union_lo = *std::min_element(r.k_lo, r.k_lo + nv);
      k_union_hi = *std::max_element(r.k_hi, r.k_hi + nv);
    }
    // slices along K covered by some segment, +-1 for the rounding of the entry cells
    int s_lo = hn::GetLane(hn::MinOfLanes(di, s_min));
    int s_hi = hn::GetLane(hn::MaxOfLanes(di, s_max));
    starts_ok = grid.res[K] <= 16 * 64;
    if (starts_ok) {
      for (size_t i = 0; i < nv * L; ++i) {
        if (r.live[i] != 0) starts[r.s_start[i] >> 6] |= uint64_t{1} << (r.s_start[i] & 63);
      }
    }
    s_lo = std::max(0, s_lo - 1);
    s_hi = std::min(grid.res[K] - 1, s_hi + 1);
    ++sc.serial;  // a new mailbox
    const int stride[3] = {1, grid.res[0], grid.res[0] * grid.res[1]};
    const uint64_t* occ = grid.occupancy.get();
    const TwoLevelGrid* two = g.two_level;
    const uint32_t* skip = g.skip.get();
    skip_rings = skip;
    // budget of marked cells before the packet is given to the stream DDA (each ray marks at
    // least one cell per slice it passes: a bound on diverging rays)
    const uint64_t budget = 4 * uint64_t(n_valid) * uint64_t(s_hi - s_lo + 1) + 64;
    SliceFoot f;
    for (int step = 0; step <= s_hi - s_lo; ++step) {
      const int s = positive ? s_lo + step : s_hi - step;
      const float p0 = grid.lo[K] + float(s) * grid.cell_size[K];
      const float p1 = grid.lo[K] + float(s + 1) * grid.cell_size[K];
      // retire the rays done before this slice (their candidate lies before its near plane,
      // which is the previous slice's far plane, bit for bit), then this slice's footprint
      size_t live_rays = 0;
      Footprint<true>(p0 - err[K], p1 + err[K], top, ~uint64_t{0}, &f, positive ? p0 : p1,
                      &live_rays);
      if (live_rays == 0) break;
      if (f.vectors != 0 && skip != nullptr) {
        const int jump = EmptyJump(f, s, skip, stride);
        if (jump > 0) {
          step += jump - 1;  // this slice and the next jump - 1 are empty where the rays pass
          continue;
        }
      }
      if (f.vectors != 0) {
        const size_t row0 = size_t(s) * stride[K];
        auto visit = [&](int cu, int cv, uint64_t in) {
          const size_t cell = row0 + size_t(cv) * stride[W] + size_t(cu) * stride[U];
          if (((occ[cell >> 6] >> (cell & 63)) & 1u) == 0) return;
          if (two != nullptr && two->Refined(cell)) {
            VisitSubGrid(two->Record(cell), in);
          } else {
            VisitLeaf(uint32_t(cell), in, f);
          }
        };
        // a small box: its occupancy first (most slices of a packet are empty), then every
        // cell with all the slice's rays; a larger one: each vector marks the cells of its box
        const int area = (f.u1 - f.u0 + 1) * (f.v1 - f.v0 + 1);
        if (area <= kSmallBox) {
          cells += uint64_t(area);
          if (!RingsEmpty(row0, f.u0, f.u1, f.v0, f.v1, stride) &&
              AnyOccupied(occ, row0, f.u0, f.u1, f.v0, f.v1, stride)) {
            Refine(top, &f);
            for (int cv = f.v0; cv <= f.v1; ++cv) {
              for (int cu = f.u0; cu <= f.u1; ++cu) visit(cu, cv, f.in);
            }
          }
        } else {
          Refine(top, &f);
          // diverging rays: the vectors' boxes cover more than a few cells per ray
          size_t area_sum = 0;
          for (uint64_t vb = f.vectors; vb != 0; vb &= vb - 1) {
            const size_t w = hwy::Num0BitsBelowLS1Bit_Nonzero64(vb);
            area_sum += size_t(f.c1[0][w] - f.c0[0][w] + 1) * size_t(f.c1[1][w] - f.c0[1][w] + 1);
          }
          if (area_sum > 2 * size_t(hwy::PopCount(f.in)) + 8) return false;
          if (!ForMarkedCells<kMaxFoot>(f, sc.marks, sc.list, visit)) return false;
        }
        if (cells > budget) return false;
        step += PredictEmpty(f, s, s_hi - s_lo - step, top, occ, stride);
      }
    }
    Write(first, n);
    return true;
  }

  // Results of rays [first, first + n).
  HWY_INLINE void Write(size_t first, size_t n) {
    const D d;
    const DI di;
    const size_t L = Lanes();
    const V zero = hn::Zero(d);
    const V inf = hn::Set(d, std::numeric_limits<float>::infinity());
    for (size_t w = 0; w < nv; ++w) {
      const size_t i = w * L;
      const VI prim = hn::Load(di, r.prim + i);
      const auto hit = hn::Gt(prim, hn::Set(di, -1));
      if constexpr (kAny) {
        // occluded (prim = 1) -> 1, else 0; whole vectors at once (occluded need not be padded:
        // the last, partial vector lane by lane)
        const VI flag = hn::IfThenElseZero(hn::Gt(prim, hn::Zero(di)), hn::Set(di, 1));
        if (i + L <= n) {
          hn::StoreU(flag, di, occluded + first + i);
        } else {
          for (size_t l = 0; i + l < n; ++l) occluded[first + i + l] = r.prim[i + l] > 0;
        }
      } else {
        const size_t live = n - i;  // (lanes past it are left alone)
        const M hf = hn::RebindMask(d, hit);
        const V u = hn::Load(d, r.bu + i), v = hn::Load(d, r.bv + i);
        StoreFirstN(hn::IfThenElse(hf, hn::Load(d, r.best + i), inf), d, live, hits->t + first + i);
        StoreFirstN(hn::IfThenElse(hf, u, zero), d, live, hits->u + first + i);
        StoreFirstN(hn::IfThenElse(hf, v, zero), d, live, hits->v + first + i);
        StoreFirstN(prim, di, live, hits->prim + first + i);
      }
    }
    if (stats != nullptr) {
      stats->rays += n;
      stats->cell_steps += cells;
      stats->triangle_tests += tests;
    }
  }

  const HitStreamView* hits = nullptr;
  int32_t* occluded = nullptr;
};

// One packet, rays [first, first + n), n <= kCoherentPacketRays. False: refused, nothing
// written (the caller traces it with the stream DDA).
bool IntersectPacket(const DdaGrid& g, const RayStreamView& rays, size_t first, size_t n,
                     const HitStreamView& hits, TraceStats* stats, detail::PacketScratch* sc) {
  PacketRays r;
  PacketTracer<false> tracer{g, *g.grid, r, *sc, stats};
  tracer.hits = &hits;
  return tracer.Trace(rays, first, n);
}

bool OccludedPacket(const DdaGrid& g, const RayStreamView& rays, size_t first, size_t n,
                    int32_t* occluded, TraceStats* stats, detail::PacketScratch* sc) {
  PacketRays r;
  PacketTracer<true> tracer{g, *g.grid, r, *sc, stats};
  tracer.occluded = occluded;
  return tracer.Trace(rays, first, n);
}

}  // namespace HWY_NAMESPACE
}  // namespace rs
HWY_AFTER_NAMESPACE();

#if HWY_ONCE
namespace rs {

HWY_EXPORT(IntersectPacket);
HWY_EXPORT(OccludedPacket);

namespace {


void InitScratch(detail::PacketScratch* sc) {
  std::memset(sc->marks, 0, sizeof sc->marks);
  std::memset(sc->sub_marks, 0, sizeof sc->sub_marks);
  std::memset(sc->mb_stamp, 0, sizeof sc->mb_stamp);
  sc->serial = 0;
}

// Packets of rays[0, size) in order; runs of refused packets go to `rest(first, n)` together,
// so that its lanes stay busy across them. regrouped: the second chance (TraceWithRegroup), whose
// packets count as regrouped and whose refusals are not counted again.
template <class Packet, class Rest>
void ForPackets(size_t size, TraceStats* stats, bool regrouped, const Packet& packet,
                const Rest& rest) {
  size_t run = 0, run_n = 0;
  for (size_t first = 0; first < size; first += kCoherentPacketRays) {
    const size_t n = std::min(kCoherentPacketRays, size - first);
    if (packet(first, n)) {
      if (stats != nullptr) {
        ++stats->packets;
        stats->packet_rays += n;
        stats->packets_regrouped += regrouped ? 1 : 0;
      }
      if (run_n != 0) rest(run, run_n);
      run_n = 0;
    } else {
      if (stats != nullptr && !regrouped) ++stats->packets_refused;
      if (run_n == 0) run = first;
      run_n += n;
    }
  }
  if (run_n != 0) rest(run, run_n);
}

// The second chance of refused packets: their rays, kRegroupRays at a time, sorted by a key of
// direction and origin, so that rays that run together land in one packet (the shadow rays of
// nearby points towards one light that a scanline run split across a depth edge, the shadow
// rays of bounce hits), are traced as packets again; the rest go to the stream DDA. On the
// caller's stack, like PacketScratch (no allocation). Not in grids with dense cells (more than
// kRegroupMaxPerCell references per occupied cell, the packets' kDenseCell), where the packets
// refuse wide rays on purpose: there a regrouped packet that passes is still slower than the
// per-ray walk (bunny shadow rays: 0.9x). Any hit regroups up to twice that density, as its
// packets allow (kAnyDenseScale): bunny shadow rays 1359 -> 954 Ir per ray (callgrind, AVX2).
constexpr size_t kRegroupRays = 1024;
constexpr float kRegroupMaxPerCell = 16.0f;
constexpr float kAnyRegroupScale = 2.0f;  // = kAnyDenseScale

struct Regroup {
  HWY_ALIGN float f[8][kRegroupRays + kStreamPad];  // ox oy oz dx dy dz tmin tmax, sorted
  HWY_ALIGN float hit_f[3][kRegroupRays + kStreamPad];  // t u v (closest hit)
  HWY_ALIGN int32_t result[kRegroupRays + kStreamPad];  // prim (closest) or occluded (any)
  uint64_t order[kRegroupRays];  // sort key << 32 | index into the caller's stream
  size_t size = 0;
  float lo[3], scale[3];  // the grid box, for the origin's Morton code
  bool on = false;

  Regroup(const DdaGrid& g, size_t rays, float max_per_cell) {
    const Grid& grid = *g.grid;
    for (int a = 0; a < 3; ++a) {
      lo[a] = grid.lo[a];
      const float extent = grid.hi[a] - grid.lo[a];
      scale[a] = extent > 0.0f ? 1.0f / extent : 0.0f;
    }
    const float per_cell = float(grid.num_refs) / float(std::max<size_t>(1, grid.occupied_cells));
    on = per_cell <= max_per_cell && rays <= UINT32_MAX;
  }
  RayStreamView Rays() {
    RayStreamView v;
    v.ox = f[0];
    v.oy = f[1];
    v.oz = f[2];
    v.dx = f[3];
    v.dy = f[4];
    v.dz = f[5];
    v.tmin = f[6];
    v.tmax = f[7];
    v.size = size;
    return v;
  }
  HitStreamView Hits() {
    HitStreamView h;
    h.t = hit_f[0];
    h.u = hit_f[1];
    h.v = hit_f[2];
    h.prim = result;
    h.size = size;
    return h;
  }
};

// The 30-bit sort key of a ray: 9 bits of direction (DirectionKey: the major axis of d, its sign,
// and d's two other components over it at 3 bits each), then 21 of origin (OriginKey: the Morton
// code of o in the grid box, 7 bits per axis). Non-finite values give some key: the order never
// changes a result.
inline uint32_t Quantize(float x, float levels) {  // x in [0, 1] -> [0, levels - 1]
  const float c = x * levels;
  return c > 0.0f ? (c < levels ? uint32_t(c) : uint32_t(levels) - 1) : 0u;
}

uint32_t DirectionKey(const RayStreamView& rays, size_t i) {
  const float d[3] = {rays.dx[i], rays.dy[i], rays.dz[i]};
  int a = 0;
  for (int k = 1; k < 3; ++k) {
    if (std::abs(d[k]) > std::abs(d[a])) a = k;
  }
  const float inv = d[a] != 0.0f ? 1.0f / std::abs(d[a]) : 0.0f;
  uint32_t key = uint32_t(a) << 7 | (d[a] < 0.0f ? 1u : 0u) << 6;
  key |= Quantize(0.5f + 0.5f * d[(a + 1) % 3] * inv, 8.0f) << 3;
  return key | Quantize(0.5f + 0.5f * d[(a + 2) % 3] * inv, 8.0f);
}

uint32_t OriginKey(const RayStreamView& rays, size_t i, const Regroup& rg) {
  const float o[3] = {rays.ox[i], rays.oy[i], rays.oz[i]};
  uint32_t morton = 0;
  for (int k = 0; k < 3; ++k) {
    uint32_t c = Quantize((o[k] - rg.lo[k]) * rg.scale[k], 128.0f);
    c = (c | c << 8) & 0x00f00fu;  // 7 bits spread to every third position
    c = (c | c << 4) & 0x0c30c3u;
    c = (c | c << 2) & 0x249249u;
    morton |= c << k;
  }
  return morton;
}

// Packets of `rays` (ForPackets); with rg->on, refused runs are regrouped (sorted, gathered,
// traced as packets where they now pass, by the stream DDA where not, results scattered back),
// otherwise they go to the stream DDA as they are. packet(view, first, n, out) traces a packet of
// `view` into `out` (Out: a HitStreamView or the occluded flags; the caller's or the regrouped
// set's), rest(view, first, n, out) the same rays by the stream DDA; scatter(i, j) copies result
// i of the regrouped set to ray j of the caller's.
template <class Out, class Packet, class Rest, class Scatter>
void TraceWithRegroup(const RayStreamView& rays, const Out& out, Regroup* rg, Out regrouped,
                      TraceStats* stats, const Packet& packet, const Rest& rest,
                      const Scatter& scatter) {
  const auto flush = [&] {
    const size_t n = rg->size;
    if (n == 0) return;
    // Sorting pays only if whole packets can share a direction bin (the key's top 9 bits): with
    // fewer than two packets' worth of rays in bins of half a packet or more (diffuse rays, say),
    // the runs go to the stream DDA as they came (rg->order is still in index order).
    uint16_t bins[512] = {};
    for (size_t i = 0; i < n; ++i) ++bins[rg->order[i] >> 53];
    size_t coherent = 0;
    for (const uint16_t b : bins) coherent += b >= kCoherentPacketRays / 2 ? b : 0;
    if (coherent < 2 * kCoherentPacketRays) {
      for (size_t i = 0; i < n;) {
        const size_t first = uint32_t(rg->order[i]);
        size_t m = 1;
        while (i + m < n && uint32_t(rg->order[i + m]) == first + m) ++m;
        rest(rays, first, m, out);
        i += m;
      }
      rg->size = 0;
      return;
    }
    for (size_t i = 0; i < n; ++i) {
      rg->order[i] |= uint64_t(OriginKey(rays, uint32_t(rg->order[i]), *rg)) << 32;
    }
    std::sort(rg->order, rg->order + n);
    const float* src[8] = {rays.ox, rays.oy, rays.oz, rays.dx, rays.dy, rays.dz, rays.tmin,
                           rays.tmax};
    for (int c = 0; c < 8; ++c) {
      float* dst = rg->f[c];
      for (size_t i = 0; i < n; ++i) dst[i] = src[c][uint32_t(rg->order[i])];
      for (size_t i = n; i < PaddedSize(n); ++i) dst[i] = 0.0f;
    }
    const RayStreamView v = rg->Rays();
    if (n < 2 * kCoherentPacketRays) {  // too few to make packets of
      rest(v, 0, n, regrouped);
    } else {
      ForPackets(
          n, stats, /*regrouped=*/true,
          [&](size_t first, size_t m) { return packet(v, first, m, regrouped); },
          [&](size_t first, size_t m) { rest(v, first, m, regrouped); });
    }
    for (size_t i = 0; i < n; ++i) scatter(i, uint32_t(rg->order[i]));
    rg->size = 0;
  };
  ForPackets(
      rays.size, stats, /*regrouped=*/false,
      [&](size_t first, size_t n) { return packet(rays, first, n, out); },
      [&](size_t first, size_t n) {
        if (!rg->on) return rest(rays, first, n, out);
        for (size_t i = first; i < first + n; ++i) {
          rg->order[rg->size++] = uint64_t(DirectionKey(rays, i)) << 53 | i;
          if (rg->size == kRegroupRays) flush();
        }
      });
  flush();
}

}  // namespace

void IntersectCoherent(const DdaGrid& g, const RayStreamView& rays, const HitStreamView& hits,
                       const DdaOptions& options, TraceStats* stats) {
  if (rays.size < kCoherentPacketRays || g.empty() || !g.simd_ok) {
    return IntersectStreamDda(g, rays, hits, options, stats);
  }
  detail::PacketScratch sc;
  InitScratch(&sc);
  Regroup rg(g, rays.size, kRegroupMaxPerCell);
  const HitStreamView mine = rg.Hits();
  TraceWithRegroup(
      rays, hits, &rg, mine, stats,
      [&](const RayStreamView& v, size_t first, size_t n, const HitStreamView& out) {
        return HWY_DYNAMIC_DISPATCH(IntersectPacket)(g, v, first, n, out, stats, &sc);
      },
      [&](const RayStreamView& v, size_t first, size_t n, const HitStreamView& out) {
        IntersectStreamDda(g, SubView(v, first, n), SubView(out, first, n), options, stats);
      },
      [&](size_t i, size_t j) {
        hits.t[j] = mine.t[i];
        hits.u[j] = mine.u[i];
        hits.v[j] = mine.v[i];
        hits.prim[j] = mine.prim[i];
      });
}

void OccludedCoherent(const DdaGrid& g, const RayStreamView& rays, int32_t* occluded,
                      const DdaOptions& options, TraceStats* stats) {
  if (rays.size < kCoherentPacketRays || g.empty() || !g.simd_ok) {
    return OccludedStreamDda(g, rays, occluded, options, stats);
  }
  detail::PacketScratch sc;
  InitScratch(&sc);
  Regroup rg(g, rays.size, kAnyRegroupScale * kRegroupMaxPerCell);
  int32_t* const mine = rg.result;
  TraceWithRegroup(
      rays, occluded, &rg, mine, stats,
      [&](const RayStreamView& v, size_t first, size_t n, int32_t* out) {
        return HWY_DYNAMIC_DISPATCH(OccludedPacket)(g, v, first, n, out, stats, &sc);
      },
      [&](const RayStreamView& v, size_t first, size_t n, int32_t* out) {
        OccludedStreamDda(g, SubView(v, first, n), out + first, options, stats);
      },
      [&](size_t i, size_t j) { occluded[j] = mine[i]; });
}

}  // namespace rs
#endif  // HWY_ONCE
