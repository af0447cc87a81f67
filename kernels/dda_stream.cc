// SIMD 3D-DDA over SoA ray streams (one ray per lane, lanes refilled from the stream), flat and
// two-level grids. Per-target code; foreach_target re-includes this file. Contracts in
// kernels/dda_simd.h; the single-ray form is kernels/dda_single.cc, the DdaGrid it reads is
// built in kernels/dda_grid.cc.
//
// Stream kernel, per iteration of the lane loop (Lanes(d) rays in flight):
//   1. free lanes take the next rays, whose setup (slab clip, start cell, boundary t, and the
//      watertight test's shear) was done a vector of rays at a time into a staging area;
//   2. one vector step: lanes whose current cell was handled check termination (candidate hit
//      or segment end before the cell's exit), pick the axis of the nearest boundary (ties to
//      the last axis, as the scalar DDA), step cell and index, recompute that boundary's t from
//      the cell index (bit-identical to the scalar code, no drift), and gather the occupancy
//      bit of the new cell (occupancy first: empty cells never touch cell data);
//   3. lanes that reached an occupied cell (found from the mask's bits, LaneBits) go through a
//      small visit pipeline, the CPU form of the paper's asynchronous loads (3.2, 3.4): the
//      leaf's span entry is prefetched, one iteration later its bundles are looked up and
//      prefetched, one more iteration later they are tested with the 1-ray x 4-triangle bundle
//      kernel (kernels/tri_intersect-inl.h, inlined); meanwhile the other lanes keep stepping.
//      Finished lanes become free and are refilled in step 1.
// A lane never waits for the others: there is no "all lanes done" barrier, so the vector stays
// full until the stream runs dry. Two-level grids: a lane that enters a refined cell switches
// to the cell's 8x8x8 sub-grid (Descend) and keeps stepping in the same vector loop with that
// level's geometry and occupancy bits (per-lane vectors instead of broadcasts); stepping out of
// the sub-grid restores its top-level state. Sub-cell steps are therefore as cheap as top-level
// ones, and the scalar oracle's TraverseSubGrid arithmetic is reproduced exactly.
//
// Micro-cache (Cell paper 3.5): the last `micro_cache` leaves looked up in this call, with their
// bundle spans, probed with one vector compare. On the SPE a hit saved a 128-B atomic load and a
// DMA of the triangles into the local store (hundreds of cycles). On a CPU the triangles stay in
// the hardware caches either way and the span lookup a hit replaces is two adjacent 32-bit
// loads; a hit skips stage 1 (the lookup and the prefetch, which the lane that entered the leaf
// a moment ago has issued) and the lane is tested one iteration later. Testing at once instead
// stalled on that prefetch while it was still in flight: 10-12 % slower on the room scenes
// (sponza, office-graz, conference, primary and shadow rays, AVX3). It never changes a result.
#include "kernels/dda_simd.h"

#include <algorithm>
#include <cfloat>
#include <cmath>
#include <cstring>
#include <limits>

#include "kernels/irregular_simd.h"
#include "streams/ray_stream.h"  // SubView

#undef HWY_TARGET_INCLUDE
#define HWY_TARGET_INCLUDE "kernels/dda_stream.cc"
#include <hwy/foreach_target.h>  // IWYU pragma: keep
#include <hwy/highway.h>         // must follow foreach_target.h

#include <hwy/cache_control.h>

#include "kernels/ray_setup-inl.h"
#include "kernels/tri_intersect-inl.h"
#include "kernels/two_level_dda.h"

HWY_BEFORE_NAMESPACE();
namespace rs {
namespace HWY_NAMESPACE {
namespace hn = hwy::HWY_NAMESPACE;

// Lanes of the widest float vector of this target (array bounds).
inline constexpr size_t kDdaMaxLanes = HWY_MAX_BYTES / sizeof(float);

// Per-lane DDA state, SoA (one slot per lane). Also the staging area of freshly set-up rays.
struct LaneSlots {
  HWY_ALIGN int32_t ray[kDdaMaxLanes];    // ray index, -1 = free slot
  HWY_ALIGN int32_t fresh[kDdaMaxLanes];  // 1: start cell not yet checked
  HWY_ALIGN int32_t idx[kDdaMaxLanes];    // flat cell index
  HWY_ALIGN int32_t cell[3][kDdaMaxLanes];
  HWY_ALIGN int32_t step[3][kDdaMaxLanes];  // +1 / -1, 0 on parallel axes
  HWY_ALIGN int32_t up[3][kDdaMaxLanes];    // 1 if step > 0: next boundary = cell + up
  HWY_ALIGN int32_t didx[3][kDdaMaxLanes];  // index change of a step: +-stride, 0 if parallel
  HWY_ALIGN int32_t enter_axis[kDdaMaxLanes];
  HWY_ALIGN float o[3][kDdaMaxLanes];
  HWY_ALIGN float d[3][kDdaMaxLanes];
  HWY_ALIGN float inv[3][kDdaMaxLanes];     // 1 / d, 0 on parallel axes
  HWY_ALIGN float t_next[3][kDdaMaxLanes];  // t of the next boundary per axis, +inf if parallel
  HWY_ALIGN float t1[kDdaMaxLanes];         // end of the segment inside the grid
  HWY_ALIGN float best[kDdaMaxLanes];       // candidate t (starts at finite tmax)
  HWY_ALIGN float t_enter[kDdaMaxLanes];    // t where the ray entered its current cell
  HWY_ALIGN float tmin[kDdaMaxLanes];
  HWY_ALIGN float tmax[kDdaMaxLanes];       // finite (+inf clamped to FLT_MAX)
  HWY_ALIGN int32_t stage[kDdaMaxLanes];    // cell visit pipeline: 0 stepping, 1, 2 (below)
  int32_t prim[kDdaMaxLanes];               // candidate triangle, -1 none
  int32_t leaf[kDdaMaxLanes];               // stage 1: the leaf to visit
  TriBundleSpan span[kDdaMaxLanes];         // stage 2: the leaf's bundles
  // Two-level grids: the grid level each lane steps through (0 top, 1 the sub-grid of record
  // rec), that level's geometry, the word offset of its occupancy bits in DdaGrid::bits, and
  // the top-level state to resume when the lane leaves the sub-grid.
  HWY_ALIGN int32_t level[kDdaMaxLanes];
  HWY_ALIGN int32_t rec[kDdaMaxLanes];
  HWY_ALIGN int32_t bits_base[kDdaMaxLanes];
  HWY_ALIGN float glo[3][kDdaMaxLanes];
  HWY_ALIGN float gcs[3][kDdaMaxLanes];
  HWY_ALIGN int32_t gres_m1[3][kDdaMaxLanes];
  HWY_ALIGN int32_t top_cell[3][kDdaMaxLanes];
  HWY_ALIGN int32_t top_idx[kDdaMaxLanes];
  HWY_ALIGN float top_t_next[3][kDdaMaxLanes];
  PreparedRay prepared_ray[kDdaMaxLanes];       // watertight setup, once per ray (at refill)
  // staging only: the watertight setup computed a vector at a time (PrepareWatertightRay)
  HWY_ALIGN int32_t k[3][kDdaMaxLanes];     // kx, ky, kz
  HWY_ALIGN float shear[3][kDdaMaxLanes];   // sx, sy, sz
  HWY_ALIGN float ok[3][kDdaMaxLanes];      // origin in (kx, ky, kz) order
};

inline void CopySlot(const LaneSlots& from, size_t j, LaneSlots* to, size_t l) {
  to->ray[l] = from.ray[j];
  to->fresh[l] = 1;
  to->idx[l] = from.idx[j];
  for (int a = 0; a < 3; ++a) {
    to->cell[a][l] = from.cell[a][j];
    to->step[a][l] = from.step[a][j];
    to->up[a][l] = from.up[a][j];
    to->didx[a][l] = from.didx[a][j];
    to->o[a][l] = from.o[a][j];
    to->d[a][l] = from.d[a][j];
    to->inv[a][l] = from.inv[a][j];
    to->t_next[a][l] = from.t_next[a][j];
  }
  to->enter_axis[l] = -1;
  to->t1[l] = from.t1[j];
  to->best[l] = from.tmax[j];
  to->t_enter[l] = from.t_enter[j];
  to->tmin[l] = from.tmin[j];
  to->tmax[l] = from.tmax[j];
  to->prim[l] = -1;
  to->stage[l] = 0;
  to->level[l] = 0;
  to->bits_base[l] = 0;
  // only valid rays are queued
  const float* const o[3] = {from.o[0], from.o[1], from.o[2]};
  const float* const d[3] = {from.d[0], from.d[1], from.d[2]};
  const float* const wo[3] = {from.ok[0], from.ok[1], from.ok[2]};
  const float* const shear[3] = {from.shear[0], from.shear[1], from.shear[2]};
  const int32_t* const k[3] = {from.k[0], from.k[1], from.k[2]};
  to->prepared_ray[l] = PreparedRayFromLanes(o, d, wo, shear, k, j);
}

// The last few leaves looked up, with their bundle spans (see the file comment).
class MicroCache {
 public:
  MicroCache(const TriBundles& bundles, int size) : bundles_(bundles) {
    size_ = size < 0 ? 0 : (size > kMaxMicroCache ? kMaxMicroCache : size);
    for (int i = 0; i < kMaxMicroCache; ++i) keys_[i] = -1;
  }
  // True (and the span) if `leaf` is cached; counts a lookup. Off (size 0): always false.
  bool Probe(int32_t leaf, TriBundleSpan* span) {
    if (size_ == 0) return false;
    ++lookups_;
    // all entries in one compare per vector (the paper: 2 x 4 indices on the SPE)
    const hn::CappedTag<int32_t, kMaxMicroCache> dk;
    const auto key = hn::Set(dk, leaf);
    for (int i = 0; i < size_; i += int(hn::Lanes(dk))) {
      const intptr_t j = hn::FindFirstTrue(dk, hn::Eq(hn::Load(dk, keys_ + i), key));
      if (j >= 0 && i + j < size_) {
        ++hits_;
        *span = spans_[i + j];
        return true;
      }
    }
    return false;
  }
  // The span of `leaf` from the bundles, entered in the cache (replacing the oldest entry).
  TriBundleSpan Insert(int32_t leaf) {
    const TriBundleSpan span = bundles_.Cell(size_t(leaf));
    if (size_ == 0) return span;
    keys_[next_] = leaf;
    spans_[next_] = span;
    next_ = next_ + 1 == size_ ? 0 : next_ + 1;
    return span;
  }
  TriBundleSpan Lookup(int32_t leaf) {
    TriBundleSpan span;
    return Probe(leaf, &span) ? span : Insert(leaf);
  }
  uint64_t lookups() const { return lookups_; }
  uint64_t hits() const { return hits_; }

 private:
  const TriBundles& bundles_;
  HWY_ALIGN int32_t keys_[kMaxMicroCache];
  TriBundleSpan spans_[kMaxMicroCache];
  int size_ = 0;
  int next_ = 0;
  uint64_t lookups_ = 0;
  uint64_t hits_ = 0;
};



// Output of one kernel call: closest hits or occlusion flags.
struct StreamOut {
  HitStreamView hits;
  int32_t* occluded = nullptr;
};

// DDA setup of rays [first, first + Lanes(d)) into `st` (slots 0..Lanes(d)-1), the scalar
// code's arithmetic lane by lane (kernels/dda.cc). Rays that can never hit (invalid, empty
// (tmin, tmax], missing the grid) get their result now; returns the slots of the others as
// bits (slot j = bit j; see LaneBits). Unaligned loads: views at an offset into a padded stream
// (the renderer's tasks) work too; lanes past `size` are read (padding) but never written.
template <bool kAny, class D>
HWY_INLINE uint64_t SetupVector(D d, const Grid& grid, const RayStreamView& rays, size_t first,
                                const StreamOut& out, LaneSlots* st) {
  using V = hn::Vec<D>;
  const hn::RebindToSigned<D> di;
  using VI = hn::Vec<decltype(di)>;
  const V zero = hn::Zero(d);
  const V inf = hn::Set(d, std::numeric_limits<float>::infinity());
  const auto live = hn::FirstN(d, rays.size - first);
  const V o[3] = {hn::LoadU(d, rays.ox + first), hn::LoadU(d, rays.oy + first),
                  hn::LoadU(d, rays.oz + first)};
  const V dir[3] = {hn::LoadU(d, rays.dx + first), hn::LoadU(d, rays.dy + first),
                    hn::LoadU(d, rays.dz + first)};
  const V tmin = hn::LoadU(d, rays.tmin + first), tmax = hn::LoadU(d, rays.tmax + first);
  // results of rays that never hit, written now for every live lane (padding untouched)
  const size_t n_live = hn::CountTrue(d, live);
  if constexpr (kAny) {
    for (size_t l = 0; l < n_live; ++l) out.occluded[first + l] = 0;  // not padded: scalar
  } else {
    StoreFirstN(inf, d, n_live, out.hits.t + first);
    StoreFirstN(zero, d, n_live, out.hits.u + first);
    StoreFirstN(zero, d, n_live, out.hits.v + first);
    StoreFirstN(hn::Set(di, -1), di, n_live, out.hits.prim + first);
  }
  // RayIsValid and a non-empty (tmin, tmax] (+inf clamped to FLT_MAX), then the slab clip;
  // parallel axes (d = +-0 or 1/d not finite) need the origin inside the slab
  const V tmax_f = FiniteTmax(d, tmax);
  auto valid = ValidRayLanes(d, o, dir, tmin, tmax_f, live);
  if (hn::AllFalse(d, valid)) return 0;
  V t0 = tmin, t1 = tmax_f;
  V inv[3];
  hn::Mask<D> parallel[3];
  valid = ClipRayLanes(d, grid.lo, grid.hi, o, dir, valid, &t0, &t1, inv, parallel);
  if (hn::AllFalse(d, valid)) return 0;
  // start cell (entry point clamped into the grid), boundary t, steps
  const int32_t stride[3] = {1, grid.res[0], grid.res[0] * grid.res[1]};
  VI idx = hn::Zero(di);
  for (int a = 0; a < 3; ++a) {
    const V lo = hn::Set(d, grid.lo[a]);
    const V p = hn::Add(o[a], hn::Mul(t0, dir[a]));
    const V f = hn::Mul(hn::Sub(p, lo), hn::Set(d, grid.inv_cell_size[a]));
    const VI res_m1 = hn::Set(di, grid.res[a] - 1);
    const VI c = hn::IfThenElse(
        hn::RebindMask(di, hn::Ge(f, zero)),
        hn::IfThenElse(hn::RebindMask(di, hn::Lt(f, hn::Set(d, float(grid.res[a])))),
                       hn::ConvertTo(di, f), res_m1),
        hn::Zero(di));  // NaN -> 0
    idx = hn::Add(idx, hn::Mul(c, hn::Set(di, stride[a])));
    const auto par_i = hn::RebindMask(di, parallel[a]);
    const auto pos = hn::RebindMask(di, hn::Gt(dir[a], zero));
    const VI step = hn::IfThenZeroElse(par_i, hn::IfThenElse(pos, hn::Set(di, 1), hn::Set(di, -1)));
    const VI up = hn::IfThenElseZero(hn::AndNot(par_i, pos), hn::Set(di, 1));
    const V boundary = hn::ConvertTo(d, hn::Add(c, up));
    const V tn = hn::Mul(
        hn::Sub(hn::Add(lo, hn::Mul(boundary, hn::Set(d, grid.cell_size[a]))), o[a]), inv[a]);
    hn::Store(c, di, st->cell[a]);
    hn::Store(step, di, st->step[a]);
    hn::Store(up, di, st->up[a]);
    hn::Store(hn::Mul(step, hn::Set(di, stride[a])), di, st->didx[a]);
    hn::Store(o[a], d, st->o[a]);
    hn::Store(dir[a], d, st->d[a]);
    hn::Store(inv[a], d, st->inv[a]);
    hn::Store(hn::IfThenElse(parallel[a], inf, tn), d, st->t_next[a]);
  }
  // the watertight test's per-ray setup (PrepareWatertightRay, lane by lane)
  {
    const WatertightSetupLanes<D> wt = SetupWatertightLanes(d, o, dir);
    for (int a = 0; a < 3; ++a) {
      hn::Store(wt.k[a], di, st->k[a]);
      hn::Store(wt.shear[a], d, st->shear[a]);
      hn::Store(wt.o[a], d, st->ok[a]);
    }
  }
  hn::Store(idx, di, st->idx);
  hn::Store(hn::Add(hn::Iota(di, 0), hn::Set(di, int32_t(first))), di, st->ray);
  hn::Store(t1, d, st->t1);
  hn::Store(t0, d, st->t_enter);
  hn::Store(tmin, d, st->tmin);
  hn::Store(tmax_f, d, st->tmax);
  return LaneBits(di, hn::RebindMask(di, valid));
}

// Tests the bundles of one leaf for lane l; true iff the lane found an occluder (any-hit).
// Adds the leaf's triangles to *tests unless tests is null.
template <bool kAny>
HWY_INLINE bool TestSpan(LaneSlots* ls, size_t l, const PreparedRay& ray, const TriBundleSpan& span,
                         const StreamOut& out, uint64_t* tests) {
  if (tests != nullptr) *tests += SpanTriangles(span);
  if constexpr (kAny) {
    if (!BundlesWidth<TriTest::kWatertight, true>(ray, span, ls->tmin[l], ls->tmax[l],
                                                  BundleWidth::kAuto, nullptr)) {
      return false;
    }
    out.occluded[ls->ray[l]] = 1;
    return true;
  } else {
    ClosestHit h;
    h.t = ls->best[l];
    h.prim = ls->prim[l];
    if (BundlesWidth<TriTest::kWatertight, false>(ray, span, ls->tmin[l], ls->tmax[l],
                                                  BundleWidth::kAuto, &h)) {
      ls->best[l] = h.t;
      ls->prim[l] = h.prim;
      const size_t i = size_t(ls->ray[l]);
      out.hits.t[i] = h.t;
      out.hits.u[i] = h.u;
      out.hits.v[i] = h.v;
      out.hits.prim[i] = h.prim;
    }
    return false;
  }
}

// Asks the memory system for a leaf's bundles (ids and up to 1 KiB of vertices), so that the
// test one iteration later finds them in cache: the CPU version of the Cell pipeline's
// asynchronous triangle DMA (section 3.2). The first 256 bytes (a bundle is 144) are asked for
// whatever the span's size: a prefetch never faults, and the lines past a small span hold the
// next leaves' bundles; the loop, whose exit depends on the size (a mispredicted branch per
// visit), runs for larger spans only.
HWY_INLINE void PrefetchSpan(const TriBundleSpan& span) {
  hwy::Prefetch(span.ids);
  const char* p = reinterpret_cast<const char*>(span.vertices);
  hwy::Prefetch(p);
  hwy::Prefetch(p + 64);
  hwy::Prefetch(p + 128);
  hwy::Prefetch(p + 192);
  const size_t bytes = span.count * kBundleFloats * sizeof(float);
  for (size_t b = 256; b < bytes && b < 1024; b += 64) hwy::Prefetch(p + b);
}

// Stage 1 of lane l's visit of an occupied leaf: its bundle span is looked up (and entered in
// the micro-cache) and prefetched.
HWY_INLINE void RequestLeaf(MicroCache* cache, LaneSlots* ls, size_t l) {
  ls->span[l] = cache->Insert(ls->leaf[l]);
  PrefetchSpan(ls->span[l]);
}

// Two-level grids: lane l has entered a refined top-level cell. Saves the top-level state and
// switches the lane to the cell's 8x8x8 sub-grid, starting where the ray entered the cell
// (SubGridStart: the same arithmetic as the scalar TraverseSubGrid). The lane is fresh again:
// the next vector step checks the occupancy of its first sub-cell.
HWY_INLINE void Descend(const DdaGrid& g, LaneSlots* ls, size_t l) {
  const TwoLevelGrid& two = *g.two_level;
  const uint32_t cell = uint32_t(ls->idx[l]);
  const SubGridRecord& rec = two.Record(cell);
  DdaRay r;
  for (int a = 0; a < 3; ++a) {
    r.o[a] = ls->o[a][l];
    r.d[a] = ls->d[a][l];
    r.inv_d[a] = ls->inv[a][l];
    r.step[a] = ls->step[a][l];
  }
  r.t1 = ls->t1[l];
  int c[3];
  float t_next[3];
  SubGridStart(rec, r, ls->t_enter[l], ls->enter_axis[l], c, t_next);
  static constexpr int32_t kSubStride[3] = {1, kSubRes, kSubRes * kSubRes};
  for (int a = 0; a < 3; ++a) {
    ls->top_cell[a][l] = ls->cell[a][l];
    ls->top_t_next[a][l] = ls->t_next[a][l];
    ls->cell[a][l] = c[a];
    ls->t_next[a][l] = t_next[a];
    ls->glo[a][l] = rec.lo[a];
    ls->gcs[a][l] = rec.cell_size[a];
    ls->gres_m1[a][l] = kSubRes - 1;
    ls->didx[a][l] = r.step[a] * kSubStride[a];
  }
  ls->top_idx[l] = ls->idx[l];
  ls->idx[l] = c[0] + kSubRes * (c[1] + kSubRes * c[2]);
  const size_t record = size_t(&rec - two.records.get());
  ls->rec[l] = int32_t(record);
  ls->bits_base[l] = int32_t(g.top_words32 + record * (kSubCells / 32));
  ls->level[l] = 1;
  ls->fresh[l] = 1;
}

// Empty-space skipping (DdaOptions::empty_skip) for the top-level lanes `empty_i` that have
// just entered an empty cell: a lane whose cell has k >= 1 empty rings around it
// (DdaGrid::skip) jumps to the DDA state in which every cell boundary with t < t_cube has been
// crossed, t_cube being where the ray leaves the (2k+1)^3 block of empty cells. The boundary t
// of an axis, (lo + float(b) * cell_size - o) * inv, never decreases along the ray (each float
// operation is monotone), so the exact DDA crosses the boundaries in t order and that state is
// one it passes through, with all the cells before it empty: the cells with triangles that a
// lane visits, and so every result, stay those of the DDA. Per axis the number of boundaries to
// cross comes from the block exit point and is then corrected with the exact boundary t. A
// lane whose candidate or segment end lies inside the block, or that leaves the grid in it, is
// done. Returns the number of jumps.
template <class D, class MI>
HWY_INLINE size_t JumpEmpty(D d, const Grid& grid, const uint32_t* skip, MI empty_i,
                            LaneSlots* ls) {
  const hn::RebindToSigned<D> di;
  const hn::RebindToUnsigned<D> du;
  using V = hn::Vec<D>;
  using VI = hn::Vec<decltype(di)>;
  const VI zero_i = hn::Zero(di), one_i = hn::Set(di, 1);
  const VI idx = hn::IfThenElseZero(empty_i, hn::Load(di, ls->idx));
  // (inactive lanes read word 0; the array is whole, aligned 32-bit words)
  const auto words = hn::GatherIndex(du, skip, hn::ShiftRight<2>(idx));
  const VI shift = hn::ShiftLeft<3>(hn::And(idx, hn::Set(di, 3)));
  const VI k = hn::BitCast(di, hn::And(hn::Shr(words, hn::BitCast(du, shift)), hn::Set(du, 0xFFu)));
  const auto jump_i = hn::And(empty_i, hn::Gt(k, zero_i));
  if (hn::AllFalse(di, jump_i)) return 0;
  const V inf = hn::Set(d, std::numeric_limits<float>::infinity());
  VI c[3], step[3], up[3];
  V o[3], inv[3], lo[3], cs[3];
  hn::Mask<D> par[3];
  // t of boundary j of axis a (the j-th boundary ahead of the current cell), +inf if parallel
  auto boundary_t = [&](int a, const VI& j) {
    const V b = hn::ConvertTo(d, hn::Add(hn::Add(c[a], up[a]), hn::Mul(step[a], j)));
    return hn::IfThenElse(par[a], inf,
                          hn::Mul(hn::Sub(hn::Add(lo[a], hn::Mul(b, cs[a])), o[a]), inv[a]));
  };
  V t_cube = inf;
  for (int a = 0; a < 3; ++a) {
    c[a] = hn::Load(di, ls->cell[a]);
    step[a] = hn::Load(di, ls->step[a]);
    up[a] = hn::Load(di, ls->up[a]);
    o[a] = hn::Load(d, ls->o[a]);
    inv[a] = hn::Load(d, ls->inv[a]);
    lo[a] = hn::Set(d, grid.lo[a]);
    cs[a] = hn::Set(d, grid.cell_size[a]);
    par[a] = hn::RebindMask(d, hn::Eq(step[a], zero_i));
    t_cube = hn::Min(t_cube, boundary_t(a, k));
  }
  const V limit = hn::Min(hn::Load(d, ls->best), hn::Load(d, ls->t1));
  auto end_i = hn::And(jump_i, hn::RebindMask(di, hn::Le(limit, t_cube)));
  const auto move_i = hn::AndNot(end_i, jump_i);
  const V t_dir[3] = {hn::Load(d, ls->d[0]), hn::Load(d, ls->d[1]), hn::Load(d, ls->d[2])};
  VI idx_new = zero_i;
  VI c_new[3];
  V t_new[3];
  for (int a = 0; a < 3; ++a) {
    const auto live_i = hn::AndNot(hn::RebindMask(di, par[a]), move_i);
    // estimate: the cell of the block exit point, as a count of boundaries ahead
    const V f = hn::Mul(hn::Sub(hn::Add(o[a], hn::Mul(t_cube, t_dir[a])), lo[a]),
                        hn::Set(d, grid.inv_cell_size[a]));
    const V fc = hn::Floor(hn::Min(hn::Max(f, hn::Set(d, -1.0f)),
                                   hn::Set(d, float(grid.res[a]))));  // NaN-free, bounded
    const VI cell_f = hn::ConvertTo(di, fc);
    VI m = hn::Mul(hn::Sub(cell_f, c[a]), step[a]);
    m = hn::IfThenElseZero(live_i, hn::Min(hn::Max(m, zero_i), k));
    // exact count: m = #{j in [0, k] : boundary_t(j) < t_cube} (monotone in j)
    for (;;) {
      const auto inc = hn::And(hn::And(live_i, hn::Lt(m, k)),
                               hn::RebindMask(di, hn::Lt(boundary_t(a, m), t_cube)));
      if (hn::AllFalse(di, inc)) break;
      m = hn::Add(m, hn::IfThenElseZero(inc, one_i));
    }
    for (;;) {
      const VI m1 = hn::Sub(m, one_i);
      const auto dec = hn::And(hn::And(live_i, hn::Gt(m, zero_i)),
                               hn::RebindMask(di, hn::Ge(boundary_t(a, m1), t_cube)));
      if (hn::AllFalse(di, dec)) break;
      m = hn::IfThenElse(dec, m1, m);
    }
    c_new[a] = hn::Add(c[a], hn::Mul(step[a], m));
    end_i = hn::Or(end_i, hn::And(move_i, hn::Or(hn::Lt(c_new[a], zero_i),
                                                 hn::Gt(c_new[a], hn::Set(di, grid.res[a] - 1)))));
    t_new[a] = boundary_t(a, m);
  }
  const int32_t stride[3] = {1, grid.res[0], grid.res[0] * grid.res[1]};
  for (int a = 0; a < 3; ++a) idx_new = hn::Add(idx_new, hn::Mul(c_new[a], hn::Set(di, stride[a])));
  const auto ok_i = hn::AndNot(end_i, move_i);
  const auto ok = hn::RebindMask(d, ok_i);
  for (int a = 0; a < 3; ++a) {
    hn::Store(hn::IfThenElse(ok_i, c_new[a], c[a]), di, ls->cell[a]);
    hn::Store(hn::IfThenElse(ok, t_new[a], hn::Load(d, ls->t_next[a])), d, ls->t_next[a]);
  }
  hn::Store(hn::IfThenElse(ok_i, idx_new, hn::Load(di, ls->idx)), di, ls->idx);
  hn::Store(hn::IfThenElse(end_i, hn::Set(di, -1), hn::Load(di, ls->ray)), di, ls->ray);
  return hn::CountTrue(di, jump_i);
}

template <bool kAny, bool kTwoLevel>
HWY_NOINLINE void StreamT(const DdaGrid& g, const RayStreamView& rays, const StreamOut& out,
                          const DdaOptions& options, TraceStats* stats) {
  using D = hn::ScalableTag<float>;
  const D d;
  const hn::RebindToSigned<D> di;
  const hn::RebindToUnsigned<D> du;
  using V = hn::Vec<D>;
  using VI = hn::Vec<decltype(di)>;
  static_assert(HWY_MAX_BYTES <= kStreamAlign, "stream padding too small");
  const Grid& grid = *g.grid;
  const size_t n = hn::Lanes(d);
  MicroCache cache(g.bundles, options.micro_cache);

  LaneSlots ls{};  // zeroed: free lanes are loaded (never used) by the vector step
  LaneSlots st;     // staging: written a whole vector at a time before any read
  for (size_t l = 0; l < kDdaMaxLanes; ++l) ls.ray[l] = -1;
  uint64_t queue = 0;    // staging slots (bits) of set-up rays not yet taken
  size_t next_ray = 0;   // first ray not yet set up
  uint64_t steps = 0, tests = 0;

  const V lo_top[3] = {hn::Set(d, grid.lo[0]), hn::Set(d, grid.lo[1]), hn::Set(d, grid.lo[2])};
  const V cs_top[3] = {hn::Set(d, grid.cell_size[0]), hn::Set(d, grid.cell_size[1]),
                       hn::Set(d, grid.cell_size[2])};
  const VI res_m1_top[3] = {hn::Set(di, grid.res[0] - 1), hn::Set(di, grid.res[1] - 1),
                            hn::Set(di, grid.res[2] - 1)};
  const VI stride_top[3] = {hn::Set(di, 1), hn::Set(di, grid.res[0]),
                            hn::Set(di, grid.res[0] * grid.res[1])};
  const VI zero_i = hn::Zero(di), minus1 = hn::Set(di, -1);
  const uint32_t* bits = g.bits.get();
  const uint32_t* skip = options.empty_skip ? g.skip.get() : nullptr;
  uint64_t jumps = 0;
  // triangle tests are counted only when asked for (the count reads the ids of the leaf's last
  // bundle, which the any-hit test never needs)
  uint64_t* count_tests = stats != nullptr ? &tests : nullptr;

  for (;;) {
    // 1. refill free lanes from the staging queue, setting up more rays as needed
    const auto free_lanes = hn::Lt(hn::Load(di, ls.ray), zero_i);
    if (!hn::AllFalse(di, free_lanes) && (queue != 0 || next_ray < rays.size)) {
      for (uint64_t lanes = LaneBits(di, free_lanes); lanes != 0; lanes &= lanes - 1) {
        while (queue == 0 && next_ray < rays.size) {
          queue = SetupVector<kAny>(d, grid, rays, next_ray, out, &st);
          next_ray += n;
        }
        if (queue == 0) break;  // stream exhausted
        const size_t l = LowestLane(lanes);
        CopySlot(st, LowestLane(queue), &ls, l);
        queue &= queue - 1;
        if constexpr (kTwoLevel) {
          for (int a = 0; a < 3; ++a) {
            ls.glo[a][l] = grid.lo[a];
            ls.gcs[a][l] = grid.cell_size[a];
            ls.gres_m1[a][l] = grid.res[a] - 1;
          }
        }
      }
    }
    const VI ray = hn::Load(di, ls.ray);
    const auto active_i = hn::Gt(ray, minus1);
    if (hn::AllFalse(di, active_i)) break;

    // 2. one step of every active lane whose current cell has been handled
    const auto active = hn::RebindMask(d, active_i);
    const auto fresh_i = hn::Gt(hn::Load(di, ls.fresh), zero_i);
    const auto fresh = hn::RebindMask(d, fresh_i);
    // lanes in the visit pipeline (stage 1 or 2) hold their cell
    const auto staged_i = hn::And(active_i, hn::Gt(hn::Load(di, ls.stage), zero_i));
    const auto stepping = hn::AndNot(hn::Or(fresh, hn::RebindMask(d, staged_i)), active);
    const V t_old[3] = {hn::Load(d, ls.t_next[0]), hn::Load(d, ls.t_next[1]),
                        hn::Load(d, ls.t_next[2])};
    const V tx = t_old[0], ty = t_old[1], tz = t_old[2];
    const V t_exit = hn::Min(tx, hn::Min(ty, tz));
    // the candidate (or the end of the segment) lies before the next cell: done
    auto done = hn::And(stepping, hn::Or(hn::Le(hn::Load(d, ls.best), t_exit),
                                         hn::Le(hn::Load(d, ls.t1), t_exit)));
    const auto go = hn::AndNot(done, stepping);
    // nearest boundary: x iff tx < ty && tx < tz, y iff !(tx < ty) && ty < tz, else z
    const auto x_lt_y = hn::Lt(tx, ty);
    const auto pick_x = hn::And(x_lt_y, hn::Lt(tx, tz));
    const auto pick_y = hn::AndNot(x_lt_y, hn::Lt(ty, tz));
    const hn::Mask<D> sel[3] = {hn::And(go, pick_x), hn::And(go, pick_y),
                                hn::AndNot(hn::Or(pick_x, pick_y), go)};
    VI idx = hn::Load(di, ls.idx);
    auto out_i = hn::Lt(zero_i, zero_i);  // all false: the stepped coordinate left its grid
    VI c_new[3];
    V t_new[3];
    for (int a = 0; a < 3; ++a) {
      const auto sel_i = hn::RebindMask(di, sel[a]);
      const VI c = hn::Add(hn::Load(di, ls.cell[a]),
                           hn::IfThenElseZero(sel_i, hn::Load(di, ls.step[a])));
      const VI res_m1 = kTwoLevel ? hn::Load(di, ls.gres_m1[a]) : res_m1_top[a];
      out_i = hn::Or(out_i, hn::And(sel_i, hn::Or(hn::Lt(c, zero_i), hn::Gt(c, res_m1))));
      idx = hn::Add(idx, hn::IfThenElseZero(sel_i, hn::Load(di, ls.didx[a])));
      // (lo + float(boundary) * cell_size - o) * inv: the scalar expression, unfused
      const V lo = kTwoLevel ? hn::Load(d, ls.glo[a]) : lo_top[a];
      const V cs = kTwoLevel ? hn::Load(d, ls.gcs[a]) : cs_top[a];
      const V boundary = hn::ConvertTo(d, hn::Add(c, hn::Load(di, ls.up[a])));
      const V tn = hn::Mul(hn::Sub(hn::Add(lo, hn::Mul(boundary, cs)), hn::Load(d, ls.o[a])),
                           hn::Load(d, ls.inv[a]));
      c_new[a] = c;
      t_new[a] = hn::IfThenElse(sel[a], tn, t_old[a]);
    }
    const auto out_of_grid = hn::RebindMask(d, out_i);
    const auto alive = hn::AndNot(out_of_grid, go);
    if constexpr (kTwoLevel) {
      // a lane leaving its sub-grid resumes the top level in the parent cell (whose
      // termination test and step come in the next iteration); leaving the top grid is done
      const auto sub_i = hn::Gt(hn::Load(di, ls.level), zero_i);
      const auto ascend_i = hn::And(out_i, sub_i);
      done = hn::Or(done, hn::RebindMask(d, hn::AndNot(sub_i, out_i)));
      if (!hn::AllFalse(di, ascend_i)) {
        const auto ascend = hn::RebindMask(d, ascend_i);
        for (int a = 0; a < 3; ++a) {
          c_new[a] = hn::IfThenElse(ascend_i, hn::Load(di, ls.top_cell[a]), c_new[a]);
          t_new[a] = hn::IfThenElse(ascend, hn::Load(d, ls.top_t_next[a]), t_new[a]);
          hn::Store(hn::IfThenElse(ascend, lo_top[a], hn::Load(d, ls.glo[a])), d, ls.glo[a]);
          hn::Store(hn::IfThenElse(ascend, cs_top[a], hn::Load(d, ls.gcs[a])), d, ls.gcs[a]);
          hn::Store(hn::IfThenElse(ascend_i, res_m1_top[a], hn::Load(di, ls.gres_m1[a])), di,
                    ls.gres_m1[a]);
          hn::Store(hn::IfThenElse(ascend_i, hn::Mul(hn::Load(di, ls.step[a]), stride_top[a]),
                                   hn::Load(di, ls.didx[a])),
                    di, ls.didx[a]);
        }
        idx = hn::IfThenElse(ascend_i, hn::Load(di, ls.top_idx), idx);
        hn::Store(hn::IfThenZeroElse(ascend_i, hn::Load(di, ls.level)), di, ls.level);
        hn::Store(hn::IfThenZeroElse(ascend_i, hn::Load(di, ls.bits_base)), di, ls.bits_base);
      }
      hn::Store(hn::IfThenElse(alive, t_exit, hn::Load(d, ls.t_enter)), d, ls.t_enter);
      const VI axis = hn::IfThenElse(hn::RebindMask(di, sel[0]), zero_i,
                                     hn::IfThenElse(hn::RebindMask(di, sel[1]), hn::Set(di, 1),
                                                    hn::Set(di, 2)));
      hn::Store(hn::IfThenElse(hn::RebindMask(di, alive), axis, hn::Load(di, ls.enter_axis)), di,
                ls.enter_axis);
    } else {
      done = hn::Or(done, out_of_grid);
    }
    for (int a = 0; a < 3; ++a) {
      hn::Store(c_new[a], di, ls.cell[a]);
      hn::Store(t_new[a], d, ls.t_next[a]);
    }
    const auto entered = hn::Or(alive, fresh);
    // occupancy bit of the entered cell: gather its 32-bit word, shift, test
    const auto entered_i = hn::RebindMask(di, entered);
    const VI idx_e = hn::IfThenElseZero(entered_i, idx);
    VI word = hn::ShiftRight<5>(idx_e);
    if constexpr (kTwoLevel) word = hn::Add(word, hn::Load(di, ls.bits_base));
    const auto words = hn::GatherIndex(du, bits, word);
    const auto bit = hn::And(hn::Shr(words, hn::BitCast(du, hn::And(idx_e, hn::Set(di, 31)))),
                             hn::Set(du, 1u));
    const auto pending_i = hn::And(entered_i, hn::RebindMask(di, hn::Eq(bit, hn::Set(du, 1u))));
    hn::Store(idx, di, ls.idx);
    hn::Store(zero_i, di, ls.fresh);
    hn::Store(hn::IfThenElse(hn::RebindMask(di, done), minus1, ray), di, ls.ray);
    steps += hn::CountTrue(d, entered);
    if (skip != nullptr) {
      auto empty_i = hn::AndNot(pending_i, entered_i);
      if constexpr (kTwoLevel) empty_i = hn::And(empty_i, hn::Eq(hn::Load(di, ls.level), zero_i));
      if (!hn::AllFalse(di, empty_i)) jumps += JumpEmpty(d, grid, skip, empty_i, &ls);
    }

    // 3. the cell visit pipeline, one lane at a time: stage 2 lanes test their (prefetched)
    // leaf and resume stepping; stage 1 lanes look up and prefetch their leaf's triangles;
    // lanes that just found an occupied cell enter stage 1 (their leaf's span entry is
    // prefetched), or go straight to stage 2 on a micro-cache hit. Each visit is thus spread
    // over two or three iterations while the other lanes keep stepping. (Lanes that enter a
    // refined cell step into its sub-grid instead: Descend.)
    // Stage 1 and stage 2 lanes are taken from two masks rather than by a per-lane branch on
    // the stage (unpredictable); only stage 1 touches the micro-cache, in lane order as before.
    if (!hn::AllFalse(di, staged_i)) {
      const auto stage1_i = hn::And(staged_i, hn::Eq(hn::Load(di, ls.stage), hn::Set(di, 1)));
      const uint64_t staged = LaneBits(di, staged_i);
      const uint64_t stage1 = LaneBits(di, stage1_i);
      for (uint64_t lanes = stage1; lanes != 0; lanes &= lanes - 1) {
        const size_t l = LowestLane(lanes);
        RequestLeaf(&cache, &ls, l);
        ls.stage[l] = 2;
      }
      for (uint64_t lanes = staged & ~stage1; lanes != 0; lanes &= lanes - 1) {
        const size_t l = LowestLane(lanes);
        ls.stage[l] = 0;
        if (TestSpan<kAny>(&ls, l, ls.prepared_ray[l], ls.span[l], out, count_tests)) {
          ls.ray[l] = -1;
        }
      }
    }
    if (hn::AllFalse(di, pending_i)) continue;
    for (uint64_t lanes = LaneBits(di, pending_i); lanes != 0; lanes &= lanes - 1) {
      const size_t l = LowestLane(lanes);
      int32_t leaf = ls.idx[l];
      if constexpr (kTwoLevel) {
        if (ls.level[l] == 0) {
          if (g.two_level->Refined(uint32_t(leaf))) {
            Descend(g, &ls, l);
            continue;
          }
        } else {
          leaf = int32_t(g.two_level->records[size_t(ls.rec[l])].Leaf(ls.cell[0][l], ls.cell[1][l],
                                                                      ls.cell[2][l]));
        }
      }
      // a micro-cache hit means a lane asked for this leaf's triangles a moment ago: skip the
      // lookup and the prefetch, and test them next iteration (see the file comment)
      if (cache.Probe(leaf, &ls.span[l])) {
        ls.stage[l] = 2;
        continue;
      }
      ls.stage[l] = 1;
      ls.leaf[l] = leaf;
      hwy::Prefetch(&g.bundles.cell_begin[uint32_t(leaf)]);
    }
  }
  if (stats != nullptr) {
    stats->cell_steps += steps;
    stats->triangle_tests += tests;
    stats->cache_lookups += cache.lookups();
    stats->cache_hits += cache.hits();
    stats->empty_skips += jumps;
  }
}

void IntersectStreamDda(const DdaGrid& g, const RayStreamView& rays, const HitStreamView& hits,
                        const DdaOptions& options, TraceStats* stats) {
  StreamOut out;
  out.hits = hits;
  if (g.two_level != nullptr && !g.two_level->empty()) {
    StreamT<false, true>(g, rays, out, options, stats);
  } else {
    StreamT<false, false>(g, rays, out, options, stats);
  }
}

void OccludedStreamDda(const DdaGrid& g, const RayStreamView& rays, int32_t* occluded,
                       const DdaOptions& options, TraceStats* stats) {
  StreamOut out;
  out.occluded = occluded;
  if (g.two_level != nullptr && !g.two_level->empty()) {
    StreamT<true, true>(g, rays, out, options, stats);
  } else {
    StreamT<true, false>(g, rays, out, options, stats);
  }
}

const char* DdaTargetName() { return hwy::TargetName(HWY_TARGET); }

}  // namespace HWY_NAMESPACE
}  // namespace rs
HWY_AFTER_NAMESPACE();

#if HWY_ONCE
namespace rs {

HWY_EXPORT(IntersectStreamDda);
HWY_EXPORT(OccludedStreamDda);
HWY_EXPORT(DdaTargetName);

namespace {

// Streams are traced in chunks of this many rays (the lanes' ray indices are int32); a multiple
// of kStreamPad, so every chunk starts aligned.
constexpr size_t kMaxChunk = size_t{1} << 30;

// Rays the SIMD kernels cannot take: an empty grid (all miss) or a grid too large for int32
// cell indices (the scalar DDA).
void ScalarStream(const DdaGrid& g, const RayStreamView& rays, const HitStreamView* hits,
                  int32_t* occluded, TraceStats* stats) {
  for (size_t i = 0; i < rays.size; ++i) {
    RayHit h{std::numeric_limits<float>::infinity(), 0.0f, 0.0f, -1};
    bool any = false;
    if (!g.empty()) {
      const float o[3] = {rays.ox[i], rays.oy[i], rays.oz[i]};
      const float d[3] = {rays.dx[i], rays.dy[i], rays.dz[i]};
      any = hits != nullptr
                ? TraceClosestGrid(*g.grid, g.two_level, *g.tris, o[0], o[1], o[2], d[0], d[1],
                                   d[2], rays.tmin[i], rays.tmax[i], &h, stats)
                : TraceAnyGrid(*g.grid, g.two_level, *g.tris, o[0], o[1], o[2], d[0], d[1],
                               d[2], rays.tmin[i], rays.tmax[i], stats);
    }
    if (hits != nullptr) {
      hits->t[i] = h.t;
      hits->u[i] = h.u;
      hits->v[i] = h.v;
      hits->prim[i] = h.prim;
    } else {
      occluded[i] = any ? 1 : 0;
    }
  }
}

}  // namespace

void IntersectStreamDda(const DdaGrid& g, const RayStreamView& rays, const HitStreamView& hits,
                        const DdaOptions& options, TraceStats* stats) {
  HWY_DASSERT(hits.size == rays.size);
  if (g.irregular != nullptr) return IntersectStreamIrregular(*g.irregular, rays, hits, stats);
  if (stats != nullptr) stats->rays += rays.size;
  if (rays.size == 0) return;
  if (g.empty() || !g.simd_ok) return ScalarStream(g, rays, &hits, nullptr, stats);
  // lanes hold int32 ray indices: chunks of at most kMaxChunk rays (aligned sub-views)
  for (size_t first = 0; first < rays.size; first += kMaxChunk) {
    const RayStreamView part = SubView(rays, first, std::min(kMaxChunk, rays.size - first));
    HWY_DYNAMIC_DISPATCH(IntersectStreamDda)(g, part, SubView(hits, first, part.size), options,
                                             stats);
  }
}

void OccludedStreamDda(const DdaGrid& g, const RayStreamView& rays, int32_t* occluded,
                       const DdaOptions& options, TraceStats* stats) {
  if (g.irregular != nullptr) return OccludedStreamIrregular(*g.irregular, rays, occluded, stats);
  if (stats != nullptr) stats->rays += rays.size;
  if (rays.size == 0) return;
  if (g.empty() || !g.simd_ok) return ScalarStream(g, rays, nullptr, occluded, stats);
  for (size_t first = 0; first < rays.size; first += kMaxChunk) {
    const RayStreamView part = SubView(rays, first, std::min(kMaxChunk, rays.size - first));
    HWY_DYNAMIC_DISPATCH(OccludedStreamDda)(g, part, occluded + first, options, stats);
  }
}

const char* DdaTargetName() { return HWY_DYNAMIC_DISPATCH(DdaTargetName)(); }

}  // namespace rs
#endif  // HWY_ONCE
