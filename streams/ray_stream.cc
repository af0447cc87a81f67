// Owning SoA ray, hit and contribution buffers (see ray_stream.h).
#include "streams/ray_stream.h"

#include <algorithm>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <limits>
#include <string>
#include <utility>

namespace rs {

const char* RayKindName(RayKind kind) {
  switch (kind) {
    case RayKind::kPrimary: return "primary";
    case RayKind::kShadow: return "shadow";
    case RayKind::kReflection: return "reflection";
    case RayKind::kRefraction: return "refraction";
  }
  return "unknown";
}

const char* Version() { return RS_VERSION; }

void ThrowOutOfMemory(size_t bytes, const char* what) {
  char size[32];
  if (bytes >= (size_t{1} << 30)) {
    std::snprintf(size, sizeof(size), "%.1f GiB", double(bytes) / double(size_t{1} << 30));
  } else {
    std::snprintf(size, sizeof(size), "%.1f MiB", double(bytes) / double(size_t{1} << 20));
  }
  throw Error(std::string("out of memory: cannot allocate ") + size + " for " + what);
}

void RayStream::Reserve(size_t capacity) {
  arrays_.Reserve(capacity, "a ray stream");
  RayStreamView& v = arrays_view_;
  v.ox = arrays_.array<float>(0);
  v.oy = arrays_.array<float>(1);
  v.oz = arrays_.array<float>(2);
  v.dx = arrays_.array<float>(3);
  v.dy = arrays_.array<float>(4);
  v.dz = arrays_.array<float>(5);
  v.tmin = arrays_.array<float>(6);
  v.tmax = arrays_.array<float>(7);
  v.pixel = arrays_.array<uint32_t>(8);
  v.wr = arrays_.array<float>(9);
  v.wg = arrays_.array<float>(10);
  v.wb = arrays_.array<float>(11);
  v.depth = arrays_.array<int32_t>(12);
  v.kind = arrays_.array<int32_t>(13);
}

void RayStream::Resize(size_t n) {
  if (n > capacity() || capacity() == 0) Reserve(n < 2 * capacity() ? 2 * capacity() : n);
  size_ = n;
}

size_t RayStream::Push(float ox, float oy, float oz, float dx, float dy, float dz, float tmin,
                       float tmax, uint32_t pixel, float wr, float wg, float wb, int32_t depth,
                       RayKind kind) {
  const size_t i = size_;
  Resize(size_ + 1);
  const RayStreamView v = view();
  v.ox[i] = ox;
  v.oy[i] = oy;
  v.oz[i] = oz;
  v.dx[i] = dx;
  v.dy[i] = dy;
  v.dz[i] = dz;
  v.tmin[i] = tmin;
  v.tmax[i] = tmax;
  v.pixel[i] = pixel;
  v.wr[i] = wr;
  v.wg[i] = wg;
  v.wb[i] = wb;
  v.depth[i] = depth;
  v.kind[i] = static_cast<int32_t>(kind);
  return i;
}

size_t RayStream::PushFrom(const RayStreamView& f, size_t i) {
  const size_t j = size_;
  Resize(size_ + 1);
  CopyRay(f, i, view(), j);
  return j;
}

void RayStream::Append(const RayStreamView& from, size_t first, size_t n) {
  const size_t at = size_;
  Resize(size_ + n);
  CopyRays(from, first, n, view(), at);
}

namespace {

template <typename T>
void CopyArray(const T* from, size_t first, size_t n, T* to, size_t at, T fallback) {
  if (to == nullptr) return;
  if (from != nullptr) {
    std::memcpy(to + at, from + first, n * sizeof(T));
  } else {
    std::fill(to + at, to + at + n, fallback);
  }
}

}  // namespace

void CopyRays(const RayStreamView& f, size_t first, size_t n, const RayStreamView& t,
              size_t at) {
  if (n == 0) return;
  for (auto [from, to] : {std::pair{f.ox, t.ox}, std::pair{f.oy, t.oy}, std::pair{f.oz, t.oz},
                          std::pair{f.dx, t.dx}, std::pair{f.dy, t.dy}, std::pair{f.dz, t.dz},
                          std::pair{f.tmin, t.tmin}, std::pair{f.tmax, t.tmax}}) {
    std::memcpy(to + at, from + first, n * sizeof(float));
  }
  CopyArray<uint32_t>(f.pixel, first, n, t.pixel, at, 0u);
  CopyArray<float>(f.wr, first, n, t.wr, at, 1.0f);
  CopyArray<float>(f.wg, first, n, t.wg, at, 1.0f);
  CopyArray<float>(f.wb, first, n, t.wb, at, 1.0f);
  CopyArray<int32_t>(f.depth, first, n, t.depth, at, 0);
  CopyArray<int32_t>(f.kind, first, n, t.kind, at, static_cast<int32_t>(RayKind::kPrimary));
}

namespace {
template <typename T>
T* Offset(T* p, size_t first) {
  return p != nullptr ? p + first : nullptr;
}
}  // namespace

RayStreamView SubView(const RayStreamView& r, size_t first, size_t n) {
  RayStreamView v;
  v.ox = Offset(r.ox, first);
  v.oy = Offset(r.oy, first);
  v.oz = Offset(r.oz, first);
  v.dx = Offset(r.dx, first);
  v.dy = Offset(r.dy, first);
  v.dz = Offset(r.dz, first);
  v.tmin = Offset(r.tmin, first);
  v.tmax = Offset(r.tmax, first);
  v.pixel = Offset(r.pixel, first);
  v.wr = Offset(r.wr, first);
  v.wg = Offset(r.wg, first);
  v.wb = Offset(r.wb, first);
  v.depth = Offset(r.depth, first);
  v.kind = Offset(r.kind, first);
  v.size = n;
  return v;
}

HitStreamView SubView(const HitStreamView& h, size_t first, size_t n) {
  return HitStreamView{Offset(h.t, first), Offset(h.u, first), Offset(h.v, first),
                       Offset(h.prim, first), n};
}


void RayStream::FillPadding() { SealLanes(size_, capacity()); }

void RayStream::SealTail() { SealLanes(size_, std::min(size_ + kStreamPad, capacity())); }

void RayStream::SealLanes(size_t from, size_t end) { SealRays(view(), from, end); }

void SealRays(const RayStreamView& v, size_t from, size_t end) {
  if (end <= from) return;
  const float nan = std::numeric_limits<float>::quiet_NaN();
  for (float* a : {v.ox, v.oy, v.oz, v.dx, v.dy, v.dz}) std::fill(a + from, a + end, nan);
  std::fill(v.tmin + from, v.tmin + end, 1.0f);
  std::fill(v.tmax + from, v.tmax + end, 0.0f);
  std::fill(v.pixel + from, v.pixel + end, 0u);
  for (float* a : {v.wr, v.wg, v.wb}) std::fill(a + from, a + end, 0.0f);
  std::fill(v.depth + from, v.depth + end, 0);
  std::fill(v.kind + from, v.kind + end, 0);
}


void HitStream::Reserve(size_t capacity) { arrays_.Reserve(capacity, "a hit stream"); }

void HitStream::Resize(size_t n) {
  if (n > arrays_.capacity() || arrays_.capacity() == 0) Reserve(n);
  size_ = n;
}

void HitStream::Reset() {
  const HitStreamView h = view();
  for (size_t i = 0; i < arrays_.capacity(); ++i) {
    h.t[i] = std::numeric_limits<float>::infinity();
    h.u[i] = h.v[i] = 0.0f;
    h.prim[i] = -1;
  }
}

HitStreamView HitStream::view() {
  if (arrays_.capacity() == 0) Reserve(1);
  return HitStreamView{arrays_.array<float>(0), arrays_.array<float>(1), arrays_.array<float>(2),
                       arrays_.array<int32_t>(3), size_};
}

void ContributionStream::Reserve(size_t capacity) {
  arrays_.Reserve(capacity, "a contribution stream");
}

void ContributionStream::Resize(size_t n) {
  if (n > capacity() || capacity() == 0) Reserve(n < 2 * capacity() ? 2 * capacity() : n);
  size_ = n;
}

}  // namespace rs
