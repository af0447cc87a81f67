// Light buffer build (kernels/light_buffer.h), scalar double: per triangle its distance from the
// light and its projections on the cube faces, then the lists by a counting sort of the
// references in ascending reach order. And rs::LightBuffer, the public wrapper.
#include "kernels/light_buffer.h"

#include <algorithm>
#include <array>
#include <bit>
#include <cfloat>
#include <chrono>
#include <cmath>
#include <memory>
#include <numeric>
#include <string>
#include <utility>
#include <vector>

#include "kernels/accel_impl.h"
#include "kernels/grid_binning.h"  // AllocateBuildArray
#include "streams/block_memory.h"  // AdviseHugePages

namespace rs {
namespace {

using Vec3 = std::array<double, 3>;

Vec3 Sub(const Vec3& a, const Vec3& b) { return {a[0] - b[0], a[1] - b[1], a[2] - b[2]}; }
double Dot(const Vec3& a, const Vec3& b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
Vec3 Lerp(const Vec3& a, const Vec3& b, double s) {
  return {a[0] + (b[0] - a[0]) * s, a[1] + (b[1] - a[1]) * s, a[2] + (b[2] - a[2]) * s};
}

// Distance from the origin to the triangle (a, b, c), in double: the closest point by Voronoi
// regions (Ericson, Real-Time Collision Detection, 5.1.5).
double OriginDistance(const Vec3& a, const Vec3& b, const Vec3& c) {
  const Vec3 p = {0.0, 0.0, 0.0};
  const auto dist = [&](const Vec3& q) { return std::sqrt(Dot(q, q)); };
  const Vec3 ab = Sub(b, a), ac = Sub(c, a), ap = Sub(p, a);
  const double d1 = Dot(ab, ap), d2 = Dot(ac, ap);
  if (d1 <= 0.0 && d2 <= 0.0) return dist(a);
  const Vec3 bp = Sub(p, b);
  const double d3 = Dot(ab, bp), d4 = Dot(ac, bp);
  if (d3 >= 0.0 && d4 <= d3) return dist(b);
  const double vc = d1 * d4 - d3 * d2;
  if (vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0) return dist(Lerp(a, b, d1 / (d1 - d3)));
  const Vec3 cp = Sub(p, c);
  const double d5 = Dot(ab, cp), d6 = Dot(ac, cp);
  if (d6 >= 0.0 && d5 <= d6) return dist(c);
  const double vb = d5 * d2 - d1 * d6;
  if (vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0) return dist(Lerp(a, c, d2 / (d2 - d6)));
  const double va = d3 * d6 - d5 * d4;
  if (va <= 0.0 && d4 - d3 >= 0.0 && d5 - d6 >= 0.0) {
    return dist(Lerp(b, c, (d4 - d3) / ((d4 - d3) + (d5 - d6))));
  }
  const double denom = 1.0 / (va + vb + vc);
  const Vec3 q = {a[0] + ab[0] * vb * denom + ac[0] * vc * denom,
                  a[1] + ab[1] * vb * denom + ac[1] * vc * denom,
                  a[2] + ab[2] * vb * denom + ac[2] * vc * denom};
  return dist(q);
}

// The float nearest to x below (at most x) and above (at least x), x finite: one step of the
// bit pattern when the conversion rounded the wrong way.
float FloatBelow(double x) {
  float f = static_cast<float>(x);
  if (double(f) > x) f = f > 0.0f ? std::bit_cast<float>(std::bit_cast<uint32_t>(f) - 1)
                                   : -std::bit_cast<float>(std::bit_cast<uint32_t>(-f) + 1);
  return f;
}
float FloatAbove(double x) { return -FloatBelow(-x); }

// A triangle's projection on one face (ProjectTriangle): face coordinates, widened by
// kLightMargin, within [-1, 1], rounded outwards to float.
struct FaceRect {
  int32_t face;
  float u0, u1, v0, v1;
  bool whole;  // the rectangle holds the projections of the three vertices (LightPlanes)
};

// A rectangle's face and, once the layout is known, its cells [x0, x1] x [y0, y1] (at most
// kLightMaxRes per axis), and where its reference's floats come from: its triangle's id (the
// SIMD projection's rectangle: the output pass projects the triangle again, with its planes),
// or kScalarRect | the index of its LightRecord (the scalar path's rectangles, kept whole). The
// passes that follow the projection read these 16 bytes per rectangle (the scatter in reach
// order at random) and the layout its coordinates (RectUv, in rectangle order).
struct RectCells {
  uint16_t x0, x1, y0, y1;
  uint8_t face;
  uint32_t src;
};
constexpr uint32_t kScalarRect = 0x80000000u;
struct RectUv {
  float u0, u1, v0, v1;
};
static_assert(kLightMaxRes <= 65536);

// The face of direction q: the axis of the largest |q| (first on ties), as the query picks it.
int FaceOf(const Vec3& q) {
  int k = 0;
  if (std::fabs(q[1]) > std::fabs(q[0])) k = 1;
  if (std::fabs(q[2]) > std::fabs(q[k])) k = 2;
  return 2 * k + (q[k] < 0.0 ? 1 : 0);
}

// The projections of triangle q (vertices relative to the light) on the faces it reaches, in
// rects[0, n) (at most one per face); returns n, or -1 if the triangle reaches the light itself
// (some clipped point at the pyramid's apex): it then goes to the list every ray reads.
int ProjectTriangle(const Vec3 q[3], FaceRect rects[6]) {
  const double widen = 1.0 + kLightMargin;
  int n_rects = 0;
  const auto add = [&](int face, double u0, double u1, double v0, double v1, bool whole) {
    rects[n_rects++] = {face, FloatBelow(std::max(-1.0, u0 - kLightMargin)),
                        FloatAbove(std::min(1.0, u1 + kLightMargin)),
                        FloatBelow(std::max(-1.0, v0 - kLightMargin)),
                        FloatAbove(std::min(1.0, v1 + kLightMargin)), whole};
  };
  // fast path: the three vertices on one face, at least kLightMargin of face coordinate inside
  // its pyramid; the pyramid is convex, so the whole triangle is, and no ray that picks a
  // neighbouring face (a tie of |d| components, decided by the rounding) can reach it
  const int f0 = FaceOf(q[0]);
  if (FaceOf(q[1]) == f0 && FaceOf(q[2]) == f0) {
    const int k = f0 >> 1, u = (k + 1) % 3, v = (k + 2) % 3;
    const double s = (f0 & 1) ? -1.0 : 1.0;
    double u0 = DBL_MAX, u1 = -DBL_MAX, v0 = DBL_MAX, v1 = -DBL_MAX;
    bool ok = true;
    for (int c = 0; c < 3; ++c) {
      const double z = s * q[c][k];
      if (!(z > 0.0)) {
        ok = false;
        break;
      }
      const double pu = q[c][u] / z, pv = q[c][v] / z;
      if (std::fabs(pu) > 1.0 - kLightMargin || std::fabs(pv) > 1.0 - kLightMargin) {
        ok = false;
        break;
      }
      u0 = std::min(u0, pu), u1 = std::max(u1, pu);
      v0 = std::min(v0, pv), v1 = std::max(v1, pv);
    }
    if (ok) {
      add(f0, u0, u1, v0, v1, true);
      return n_rects;
    }
  }
  // general case: clip to each face's widened pyramid (|x_u|, |x_v| <= widen s x_k: four planes
  // through the light), then project the clipped polygon
  for (int face = 0; face < 6; ++face) {
    const int k = face >> 1, u = (k + 1) % 3, v = (k + 2) % 3;
    const double s = (face & 1) ? -1.0 : 1.0;
    Vec3 poly[9], next[9];
    int n = 3;
    for (int c = 0; c < 3; ++c) poly[c] = {q[c][u], q[c][v], s * q[c][k]};
    for (int plane = 0; plane < 4 && n > 0; ++plane) {
      const int axis = plane >> 1;
      const double sign = (plane & 1) ? -1.0 : 1.0;
      const auto inside = [&](const Vec3& p) { return widen * p[2] - sign * p[axis]; };
      int m = 0;
      for (int a = 0; a < n; ++a) {
        const Vec3& p = poly[a];
        const Vec3& r = poly[(a + 1) % n];
        const double dp = inside(p), dr = inside(r);
        if (dp >= 0.0) next[m++] = p;
        if ((dp >= 0.0) != (dr >= 0.0)) next[m++] = Lerp(p, r, dp / (dp - dr));
      }
      n = m;
      std::copy(next, next + n, poly);
    }
    if (n == 0) continue;
    double u0 = DBL_MAX, u1 = -DBL_MAX, v0 = DBL_MAX, v1 = -DBL_MAX;
    for (int a = 0; a < n; ++a) {
      if (!(poly[a][2] > 0.0)) return -1;  // the apex: the triangle touches the light
      const double pu = poly[a][0] / poly[a][2], pv = poly[a][1] / poly[a][2];
      u0 = std::min(u0, pu), u1 = std::max(u1, pu);
      v0 = std::min(v0, pv), v1 = std::max(v1, pv);
    }
    add(face, u0, u1, v0, v1, false);  // a clipped polygon's rectangle
  }
  return n_rects;
}

// The edge planes of triangle `v` (9 floats, x0 y0 z0 x1 ...) on `face` for a light at `light`
// (light_buffer.h, kLightPlaneFloats): a, b, c of the edges (2, 1), (0, 2), (1, 0), then M, plus
// 4 if the rectangle does not hold the vertices' projections (whole = false: W <= 2 bounds
// the sheared coordinates instead).
void LightPlanes(const float v[9], const float light[3], int face, bool whole,
                 float out[kLightPlaneFloats]) {
  double q[3][3], r[3];
  for (int c = 0; c < 3; ++c) {
    r[c] = 0.0;
    for (int a = 0; a < 3; ++a) {
      q[c][a] = double(v[3 * c + a] - light[a]);  // the float translation of the test
      r[c] = std::max(r[c], std::fabs(q[c][a]));
    }
  }
  const int k = face >> 1, ua = (k + 1) % 3, va = (k + 2) % 3;
  const double s = (face & 1) ? -1.0 : 1.0;
  // 1 / (R_b R_c) = R_a / (R_0 R_1 R_2): one division (a vertex at the light: no planes)
  const double inv = 1.0 / (r[0] * r[1] * r[2]);
  if (!std::isfinite(inv)) {
    std::fill(out, out + kLightPlaneFloats, 0.0f);
    return;
  }
  double most = 0.0;
  for (int e = 0; e < 3; ++e) {
    const double* p = q[kLightPlaneEdges[e][0]];
    const double* t = q[kLightPlaneEdges[e][1]];
    // products of floats are exact in double; each difference rounds once (2^-53 relative)
    const double n[3] = {p[1] * t[2] - p[2] * t[1], p[2] * t[0] - p[0] * t[2],
                         p[0] * t[1] - p[1] * t[0]};
    const double scale = r[e] * inv;  // edge e is opposite vertex e
    float* abc = out + 3 * e;
    abc[0] = float(s * n[k] * scale), abc[1] = float(n[ua] * scale), abc[2] = float(n[va] * scale);
    most = std::max(most, double(std::fabs(abc[0])) + std::fabs(abc[1]) + std::fabs(abc[2]));
  }
  out[9] = FloatAbove((most + (whole ? 0.0 : 4.0)) * (1.0 + 1e-6));
}

// Face coordinate -> cell along one axis of a face's window, clamped (as the query's).
int CellOf(float x, float lo, float scale, int top) {
  // x >= lo for a binned rectangle: truncation is the floor
  return std::clamp(int((double(x) - double(lo)) * double(scale)), 0, top);
}

// Grows *a to hold n elements if it holds fewer (contents not kept); *capacity tracks it.
template <typename T>
void Ensure(hwy::AlignedFreeUniquePtr<T[]>* a, size_t n, size_t* capacity, const char* what) {
  if (*a && n <= *capacity) return;
  a->reset();  // first: the old and the new array are never held at once
  *a = AllocateBuildArray<T>(n, what);
  *capacity = n;
}

// std::allocator whose construct() without arguments default-initializes: resize() leaves the
// build's trivial temporaries unwritten instead of zeroing what the build overwrites anyway.
template <typename T>
struct NoInitAllocator : std::allocator<T> {
  NoInitAllocator() = default;
  template <typename U>
  NoInitAllocator(const NoInitAllocator<U>&) noexcept {}  // NOLINT: an allocator converts
  template <typename U>
  struct rebind {
    using other = NoInitAllocator<U>;
  };
  template <typename U>
  void construct(U* p) noexcept {
    ::new (static_cast<void*>(p)) U;
  }
  template <typename U, typename... A>
  void construct(U* p, A&&... a) {
    ::new (static_cast<void*>(p)) U(std::forward<A>(a)...);
  }
};
template <typename T>
using ScratchVec = std::vector<T, NoInitAllocator<T>>;

// v->reserve(n), with huge pages for a new large array (AdviseHugePages: before any write).
template <typename V>
void Reserve(V* v, size_t n) {
  if (n <= v->capacity()) return;
  v->reserve(n);
  AdviseHugePages(v->data(), v->capacity() * sizeof(typename V::value_type));
}

// The low bits of a reach that a list's order ignores: the reach is rounded down to 24
// significant bits (8 of exponent, 16 of mantissa: 1.5e-5 relative, the size of
// kLightReachSlack), which keeps it a lower bound of the distance, so that the sort takes three
// 8-bit digits. 8-bit digits keep the 256 scatter streams of a pass in L1: 11-bit ones (2,048
// streams) spent 13 ns per key and pass (bunny, AVX2 host).
constexpr int kReachDropBits = 7;
float TruncateReach(float reach) {
  return std::bit_cast<float>(std::bit_cast<uint32_t>(reach) & ~((1u << kReachDropBits) - 1));
}

// keys sorted by their high 32 bits, stable (ties keep their order): an LSD radix sort of the
// three 8-bit digits above kReachDropBits, skipping a digit every key shares. Reaches are
// >= 0, so their float bits sort as the values do.
void SortByReach(ScratchVec<uint64_t>* keys, ScratchVec<uint64_t>* tmp) {
  constexpr int kDigits = 3, kFirst = 32 + kReachDropBits;
  static_assert(kReachDropBits + 8 * kDigits == 31);  // the sign bit is 0
  const size_t n = keys->size();
  tmp->resize(n);
  uint32_t count[kDigits][257] = {};  // the digits' histograms, counted at once (no heap)
  for (const uint64_t k : *keys) {
    for (int p = 0; p < kDigits; ++p) ++count[p][1 + ((k >> (kFirst + 8 * p)) & 255)];
  }
  for (int p = 0; p < kDigits; ++p) {
    uint32_t* c = count[p];
    if (std::find(c + 1, c + 257, n) != c + 257) continue;  // one digit for all
    for (int b = 0; b < 256; ++b) c[b + 1] += c[b];
    const int shift = kFirst + 8 * p;
    uint64_t* const out = tmp->data();
    for (const uint64_t k : *keys) out[c[(k >> shift) & 255]++] = k;
    keys->swap(*tmp);
  }
}

}  // namespace

// A reference as the output arrays hold it: kept for the scalar path's rectangles (whose
// planes are computed in double) and written to the lists by `put`.
struct alignas(64) LightRecord {
  float reach, u0, u1, v0, v1;
  uint32_t tri;
  float planes[kLightPlaneFloats];
};
static_assert(sizeof(LightRecord) == 64);

// The build's temporaries, kept between builds (no fresh pages for a build no larger than an
// earlier one: rs::LightBuffer keeps one per thread, shared by all its light buffers).
struct LightBuildScratch {
  ScratchVec<RectCells> cells;      // per rectangle, in triangle order
  ScratchVec<RectUv> uv;            // per rectangle, in triangle order
  std::vector<LightRecord> records;  // the rectangles of the scalar path (RectCells::src)
  std::vector<std::pair<float, uint32_t>> always;  // (reach, triangle)
  ScratchVec<uint64_t> keys, keys_tmp;  // reach bits << 32 | rectangle (SortByReach)
  std::vector<uint32_t> cursor;
  ScratchVec<uint32_t> order;       // per reference: its rectangle's RectCells::src
};

void BuildLightBuffer(const TriangleSoA& tris, const float world_light[3],
                      double cells_per_triangle, LightBufferData* out, LightBuildScratch* reuse,
                      const float* shift) {
  LightBuildScratch local;
  LightBuildScratch& sc = reuse != nullptr ? *reuse : local;
  LightBufferData& lb = *out;
  lb.res = 0;
  lb.faces = LightFaces{};
  lb.num_cells = lb.num_refs = lb.num_always = 0;
  for (int a = 0; a < 3; ++a) {
    lb.light[a] = world_light[a];
    lb.frame_light[a] = shift != nullptr ? world_light[a] - shift[a] : world_light[a];
  }
  const float* const light = lb.frame_light;  // what the build and the tests translate by
  lb.verts = tris.verts.data();
  const Vec3 l = {double(light[0]), double(light[1]), double(light[2])};
  // per rectangle, in triangle order (sequential reads of the triangles): its face, cells and
  // source, its coordinates and its sort key, reach bits << 32 | rectangle (SortByReach).
  // Written through local pointers (a store of the face byte would otherwise make the compiler
  // reload every vector's pointers), the arrays sized ahead for a whole projection block. The
  // references' floats are not kept: the output pass computes them again from the triangles
  // (ProjectLightList), but for the scalar path's rectangles, whose LightRecords are kept.
  if (tris.size >= kScalarRect) {
    throw Error("light buffer: " + std::to_string(tris.size) + " triangles (at most 2^31 - 1)");
  }
  ScratchVec<RectCells>& rect_cells = sc.cells;
  ScratchVec<RectUv>& rect_uv = sc.uv;
  std::vector<LightRecord>& records = sc.records;
  records.clear();
  ScratchVec<uint64_t>& keys = sc.keys;
  size_t num_rects = 0;
  RectCells* out_cells = nullptr;
  RectUv* out_uv = nullptr;
  uint64_t* out_keys = nullptr;
  const auto room = [&](size_t more) {  // at least num_rects + more of each, contents kept
    if (num_rects + more > rect_cells.size()) {
      // first the usual bound (one rectangle per triangle, some on two faces), then doubling
      const size_t n = num_rects == 0 ? tris.size + tris.size / 8 + more
                                      : std::max(num_rects + more, 2 * rect_cells.size());
      Reserve(&rect_cells, n), Reserve(&rect_uv, n), Reserve(&keys, n);
      rect_cells.resize(n), rect_uv.resize(n), keys.resize(n);
    }
    out_cells = rect_cells.data(), out_uv = rect_uv.data(), out_keys = keys.data();
  };
  std::vector<std::pair<float, uint32_t>>& always = sc.always;  // triangles touching the light
  always.clear();
  // each face's window: the union of its rectangles
  struct Window {
    float lo_u = FLT_MAX, hi_u = -FLT_MAX, lo_v = FLT_MAX, hi_v = -FLT_MAX;
    size_t rects = 0;
  } win[6];
  // one rectangle on `face`, in rectangle order; its reach rounded down (SortByReach)
  const auto append = [&](float reach, float u0, float u1, float v0, float v1, int face,
                          uint32_t src) {
    out_keys[num_rects] = uint64_t(std::bit_cast<uint32_t>(TruncateReach(reach))) << 32 | num_rects;
    out_cells[num_rects] = {0, 0, 0, 0, uint8_t(face), src};
    out_uv[num_rects] = {u0, u1, v0, v1};
    ++num_rects;
    Window& w = win[face];
    w.lo_u = std::min(w.lo_u, u0), w.hi_u = std::max(w.hi_u, u1);
    w.lo_v = std::min(w.lo_v, v0), w.hi_v = std::max(w.hi_v, v1);
    ++w.rects;
  };
  size_t listed = 0;             // and those with projections
  LightProjection block;
  for (size_t i = 0; i < tris.size; ++i) {
    const size_t in_block = i % kLightProjectBlock;
    if (in_block == 0) {
      ProjectLightBlock(tris, light, i, std::min(kLightProjectBlock, tris.size - i), &block);
      room(6 * kLightProjectBlock);  // a triangle has a rectangle on at most 6 faces
    }
    if (tris.degenerate[i]) continue;
    if (block.face[in_block] >= 0) {  // the SIMD pass's common case
      append(block.reach[in_block], block.u0[in_block], block.u1[in_block], block.v0[in_block],
             block.v1[in_block], block.face[in_block], uint32_t(i));
      ++listed;
      continue;
    }
    Vec3 q[3];
    double farthest = 0.0;
    for (int c = 0; c < 3; ++c) {
      for (int a = 0; a < 3; ++a) q[c][a] = double(tris.p[c][a][i]) - l[a];
      farthest = std::max(farthest, std::sqrt(Dot(q[c], q[c])));
    }
    const double near = OriginDistance(q[0], q[1], q[2]);
    const float reach = FloatBelow(std::max(
        0.0, near * (1.0 - kLightReachSlack) - kLightReachSlack * farthest));
    FaceRect rects[6];
    const int n_rects = near <= 1e-6 * farthest ? -1 : ProjectTriangle(q, rects);
    if (n_rects < 0) {
      always.emplace_back(reach, uint32_t(i));
      continue;
    }
    for (int r = 0; r < n_rects; ++r) {  // (planes computed here in double)
      const FaceRect& f = rects[r];
      LightRecord rec;
      rec.reach = TruncateReach(reach);
      rec.u0 = f.u0, rec.u1 = f.u1, rec.v0 = f.v0, rec.v1 = f.v1;
      rec.tri = uint32_t(i);
      LightPlanes(tris.Vertices(i), light, f.face, f.whole, rec.planes);
      if (records.size() >= kScalarRect) throw Error("light buffer: too many clipped triangles");
      append(reach, f.u0, f.u1, f.v0, f.v1, f.face, kScalarRect | uint32_t(records.size()));
      records.push_back(rec);
    }
    ++listed;
  }
  rect_cells.resize(num_rects), rect_uv.resize(num_rects);
  keys.resize(num_rects);  // (shrinking: the capacity stays for the next build)
  const size_t valid = listed + always.size();
  if (valid == 0) return;
  // about `cells` cells over the faces, shared by their rectangle counts, square-ish cells over
  // each window; returns the references (and sets each rectangle's cells)
  LightFaces& fc = lb.faces;
  const auto layout = [&](double cells) {
    int32_t base = 0;
    lb.res = 0;
    for (int face = 0; face < 6; ++face) {
      const Window& w = win[face];
      int ru = 1, rv = 1;
      float lo_u = 0.0f, lo_v = 0.0f, su = 0.0f, sv = 0.0f;
      if (w.rects > 0) {
        const double wu = double(w.hi_u) - double(w.lo_u);  // >= 2 kLightMargin
        const double wv = double(w.hi_v) - double(w.lo_v);
        const double cf = std::max(1.0, cells * double(w.rects) / double(num_rects));
        ru = std::clamp(int(std::lround(std::sqrt(cf * wu / wv))), 1, kLightMaxRes);
        rv = std::clamp(int(std::lround(cf / double(ru))), 1, kLightMaxRes);
        lo_u = w.lo_u, lo_v = w.lo_v;
        su = float(double(ru) / wu), sv = float(double(rv) / wv);
      }
      fc.lo_u[face] = lo_u, fc.lo_v[face] = lo_v, fc.scale_u[face] = su, fc.scale_v[face] = sv;
      fc.res_u[face] = ru, fc.res_v[face] = rv, fc.top_u[face] = ru - 1, fc.top_v[face] = rv - 1;
      fc.base[face] = base;
      base += ru * rv;
      lb.res = std::max({lb.res, ru, rv});
    }
    lb.num_cells = size_t(base);
    size_t refs = 0;
    for (size_t r = 0; r < num_rects; ++r) {
      const RectUv& f = rect_uv[r];
      RectCells& rc = rect_cells[r];
      const int face = rc.face;
      const int x0 = CellOf(f.u0, fc.lo_u[face], fc.scale_u[face], fc.top_u[face]);
      const int x1 = CellOf(f.u1, fc.lo_u[face], fc.scale_u[face], fc.top_u[face]);
      const int y0 = CellOf(f.v0, fc.lo_v[face], fc.scale_v[face], fc.top_v[face]);
      const int y1 = CellOf(f.v1, fc.lo_v[face], fc.scale_v[face], fc.top_v[face]);
      rc.x0 = uint16_t(x0), rc.x1 = uint16_t(x1), rc.y0 = uint16_t(y0), rc.y1 = uint16_t(y1);
      refs += size_t(x1 - x0 + 1) * size_t(y1 - y0 + 1);
    }
    return refs;
  };
  // about cells_per_triangle cells per triangle, fewer while the references pass the budget
  const size_t budget = kLightRefsPerTriangle * valid + (size_t{1} << 16);
  double cells = std::max(1.0, cells_per_triangle * double(valid));
  size_t refs = layout(cells);
  while (refs > budget && lb.num_cells > 6) {
    cells *= 0.5625;  // 0.75 per axis
    refs = layout(cells);
  }
  lb.num_always = always.size();
  lb.num_refs = refs + always.size();
  // a counting sort of the references by cell (each cell's list in (reach, triangle) order, see
  // below); calls fn(cell) for each cell of rectangle f
  const auto for_cells = [&](const RectCells& f, auto&& fn) {
    const size_t base = size_t(fc.base[f.face]), row_len = size_t(fc.res_u[f.face]);
    for (int y = f.y0; y <= f.y1; ++y) {
      const size_t row = base + size_t(y) * row_len;
      for (int x = f.x0; x <= f.x1; ++x) fn(row + size_t(x));
    }
  };
  Ensure(&lb.cell_begin, lb.num_cells + 2, &lb.cell_capacity, "light buffer cell offsets");
  uint32_t* begin = lb.cell_begin.get();
  std::fill(begin, begin + lb.num_cells + 2, 0u);
  for (const RectCells& f : rect_cells) for_cells(f, [&](size_t c) { ++begin[1 + c]; });
  begin[lb.num_cells + 1] = uint32_t(always.size());
  for (size_t c = 0; c <= lb.num_cells; ++c) begin[c + 1] += begin[c];
  // the output arrays (reused by Rebuild when large enough)
  const size_t pad = 16;  // one vector of the widest target
  if (lb.num_refs + pad > lb.ref_capacity || !lb.tri) {
    for (auto* a : {&lb.reach, &lb.u0, &lb.u1, &lb.v0, &lb.v1, &lb.planes}) a->reset();
    lb.tri.reset();
    for (auto* a : {&lb.reach, &lb.u0, &lb.u1, &lb.v0, &lb.v1}) {
      *a = AllocateBuildArray<float>(lb.num_refs + pad, "light buffer references");
    }
    lb.tri = AllocateBuildArray<uint32_t>(lb.num_refs + pad, "light buffer triangle ids");
    lb.planes = AllocateBuildArray<float>(kLightPlaneFloats * (lb.num_refs + pad),
                                          "light buffer edge planes");
    lb.ref_capacity = lb.num_refs + pad;
  }
  // the rectangles by ascending reach (ties in rectangle order = triangle order), scattered in
  // that order: every cell's list comes out sorted; each reference gets its reach, its
  // rectangle (the whole face for the list every ray reads) and its triangle's id
  Reserve(&sc.keys_tmp, num_rects);
  SortByReach(&keys, &sc.keys_tmp);
  // (local pointers: the stores below cannot alias them)
  float* const out_reach = lb.reach.get();
  float* const out_u0 = lb.u0.get();
  float* const out_u1 = lb.u1.get();
  float* const out_v0 = lb.v0.get();
  float* const out_v1 = lb.v1.get();
  uint32_t* const out_tri = lb.tri.get();
  float* out_planes[kLightPlaneFloats];
  for (int c = 0; c < kLightPlaneFloats; ++c) out_planes[c] = lb.planes.get() + c * lb.ref_capacity;
  const auto put = [&](size_t j, const LightRecord& r) {
    out_reach[j] = r.reach;
    out_u0[j] = r.u0, out_u1[j] = r.u1, out_v0[j] = r.v0, out_v1[j] = r.v1;
    out_tri[j] = r.tri;
    for (int c = 0; c < kLightPlaneFloats; ++c) out_planes[c][j] = r.planes[c];
  };
  // The rectangles in reach order append their source to each of their cells' lists (one 4-B
  // stream per cell); then the references are written list by list, a projection block at a
  // time: the listed triangles projected again with their planes (ProjectLightList, the same
  // float operations as the first pass's, so the same reach and rectangle) into the output
  // arrays in order, the scalar path's from their records.
  ScratchVec<uint32_t>& order = sc.order;
  Reserve(&order, refs);
  order.resize(refs);
  std::vector<uint32_t>& cursor = sc.cursor;
  cursor.assign(begin, begin + lb.num_cells + 1);
  uint32_t* const cur = cursor.data();
  for (size_t i = 0; i < keys.size(); ++i) {
    if (i + 8 < keys.size()) __builtin_prefetch(&rect_cells[uint32_t(keys[i + 8])]);
    const RectCells& f = rect_cells[uint32_t(keys[i])];
    const uint32_t src = f.src;
    for_cells(f, [&](size_t c) { order[cur[c]++] = src; });
  }
  uint32_t ids[kLightProjectBlock];
  for (size_t j0 = 0; j0 < refs; j0 += kLightProjectBlock) {
    const size_t n = std::min(kLightProjectBlock, refs - j0);
    bool scalar = false;
    for (size_t k = 0; k < n; ++k) {
      const uint32_t src = order[j0 + k];
      scalar = scalar || (src & kScalarRect) != 0;
      ids[k] = (src & kScalarRect) != 0 ? 0u : src;
    }
    // straight into the output arrays (their padding holds the last vector's extra lanes,
    // overwritten below by the list every ray reads and the padding)
    LightProjectionOut at{block.face, out_u0 + j0, out_u1 + j0, out_v0 + j0, out_v1 + j0,
                          out_reach + j0, {}};
    for (int c = 0; c < kLightPlaneFloats; ++c) at.planes[c] = out_planes[c] + j0;
    ProjectLightList(tris, light, ids, n, at);
    for (size_t k = 0; k < n; ++k) out_reach[j0 + k] = TruncateReach(out_reach[j0 + k]);
    std::copy(ids, ids + n, out_tri + j0);
    if (!scalar) continue;
    for (size_t k = 0; k < n; ++k) {
      const uint32_t src = order[j0 + k];
      if ((src & kScalarRect) != 0) put(j0 + k, records[src & ~kScalarRect]);
    }
  }
  std::sort(always.begin(), always.end());  // (reach, triangle)
  for (size_t a = 0; a < always.size(); ++a) {
    const LightRecord r{always[a].first, -FLT_MAX, FLT_MAX, -FLT_MAX, FLT_MAX, always[a].second,
                        {}};
    put(refs + a, r);  // planes 0: never culled
  }
  for (size_t p = lb.num_refs; p < lb.num_refs + pad; ++p) {
    lb.reach[p] = FLT_MAX;
    lb.u0[p] = lb.v0[p] = FLT_MAX;
    lb.u1[p] = lb.v1[p] = -FLT_MAX;
    lb.tri[p] = 0;
    for (int c = 0; c < kLightPlaneFloats; ++c) out_planes[c][p] = 0.0f;
  }
}

// ---- rs::LightBuffer -------------------------------------------------------------------------

struct LightBuffer::Impl {
  const Accel* accel = nullptr;
  LightBufferData data;
  double build_seconds = 0.0;
  bool built = false;  // false while (or after a failed) Rebuild
};

LightBuffer::LightBuffer(const Accel& accel, const float light[3])
    : impl_(std::make_unique<Impl>()) {
  Rebuild(accel, light);
}

void LightBuffer::Rebuild(const Accel& accel, const float light[3]) {
  const auto start = std::chrono::steady_clock::now();
  if (!impl_) throw Error("LightBuffer::Rebuild: this LightBuffer was moved from");
  if (light == nullptr || !std::isfinite(light[0]) || !std::isfinite(light[1]) ||
      !std::isfinite(light[2])) {
    throw Error("LightBuffer: the light position must be three finite numbers");
  }
  const Accel::Impl& m = AccelImpl(accel);
  impl_->built = false;
  impl_->accel = &accel;
  // one scratch per thread for every light buffer it builds: a scene's lights pay the fresh
  // pages of the temporaries once, not once each (and hold them once)
  static thread_local LightBuildScratch scratch;
  BuildLightBuffer(m.triangles, light, kLightCellsPerTriangle, &impl_->data, &scratch, m.shift);
  impl_->built = true;
  impl_->build_seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
}

LightBuffer::~LightBuffer() = default;
LightBuffer::LightBuffer(LightBuffer&&) noexcept = default;
LightBuffer& LightBuffer::operator=(LightBuffer&&) noexcept = default;

void LightBuffer::Occluded(const RayStreamView& rays, int32_t* occluded, TraceStats* stats) const {
  if (!impl_) throw Error("LightBuffer::Occluded: this LightBuffer was moved from");
  const Impl& m = *impl_;
  if (!m.built) throw Error("LightBuffer::Occluded: the last Rebuild failed");
  if (rays.size == 0) return;
  const float* arrays[] = {rays.ox, rays.oy, rays.oz, rays.dx, rays.dy, rays.dz, rays.tmin,
                           rays.tmax};
  for (const float* a : arrays) {
    if (a == nullptr) {
      throw Error("LightBuffer::Occluded: a ray array is null for " + std::to_string(rays.size) +
                  " rays");
    }
  }
  if (occluded == nullptr) {
    throw Error("LightBuffer::Occluded: occluded is null for " + std::to_string(rays.size) +
                " rays");
  }
  // chunks of whole vectors traced in place (the kernel loads and stores whole vectors, so the
  // last size % kStreamPad rays go through a padded copy); rays not starting at the light go to
  // the Accel through a copy
  alignas(kStreamAlign) float f[8][kLightChunk];
  alignas(kStreamAlign) int32_t result[kLightChunk];
  uint32_t far[kLightChunk];
  float* const src[8] = {rays.ox, rays.oy, rays.oz, rays.dx, rays.dy, rays.dz, rays.tmin,
                         rays.tmax};
  const auto view = [](float* const a[8], size_t offset, size_t n) {
    RayStreamView v{};
    v.ox = a[0] + offset, v.oy = a[1] + offset, v.oz = a[2] + offset;
    v.dx = a[3] + offset, v.dy = a[4] + offset, v.dz = a[5] + offset;
    v.tmin = a[6] + offset, v.tmax = a[7] + offset;
    v.size = n;
    return v;
  };
  float* const copy[8] = {f[0], f[1], f[2], f[3], f[4], f[5], f[6], f[7]};
  const size_t body = rays.size / kStreamPad * kStreamPad;
  for (size_t first = 0; first < rays.size; first += kLightChunk) {
    const size_t n = std::min(kLightChunk, rays.size - first);
    size_t num_far = 0;
    RayStreamView part;
    if (first + n <= body) {
      part = view(src, first, n);
      OccludedLightBuffer(m.data, part, occluded + first, far, &num_far, stats);
    } else {  // the tail: fewer than kStreamPad rays
      for (int a = 0; a < 8; ++a) {
        std::copy(src[a] + first, src[a] + first + n, f[a]);
        std::fill(f[a] + n, f[a] + PaddedSize(n), 0.0f);
      }
      part = view(copy, 0, n);
      OccludedLightBuffer(m.data, part, result, far, &num_far, stats);
      std::copy(result, result + n, occluded + first);
    }
    if (num_far == 0) continue;
    const float* const from[8] = {part.ox, part.oy, part.oz, part.dx, part.dy, part.dz,
                                  part.tmin, part.tmax};
    for (int a = 0; a < 8; ++a) {
      for (size_t j = 0; j < num_far; ++j) f[a][j] = from[a][far[j]];  // far ascends
    }
    m.accel->Occluded(view(copy, 0, num_far), result, stats);
    for (size_t j = 0; j < num_far; ++j) occluded[first + far[j]] = result[j];
  }
}

LightBufferInfo LightBuffer::Info() const {
  if (!impl_) throw Error("LightBuffer::Info: this LightBuffer was moved from");
  const LightBufferData& d = impl_->data;
  LightBufferInfo info;
  info.resolution = d.res;
  info.cells = d.num_cells;
  info.references = d.num_refs;
  info.always = d.num_always;
  for (size_t c = 0; c < d.num_cells; ++c) {
    info.longest = std::max<size_t>(info.longest, d.cell_begin[c + 1] - d.cell_begin[c]);
  }
  info.bytes = d.Bytes();
  info.build_seconds = impl_->build_seconds;
  return info;
}

}  // namespace rs
