// Owning SoA ray, hit and contribution buffers (see ray_stream.h).
#include "streams/ray_stream.h"

#include <algorithm>
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
  for (auto* a : {&ox_, &oy_, &oz_, &dx_, &dy_, &dz_, &tmin_, &tmax_, &wr_, &wg_, &wb_}) {
    a->Reserve(capacity);
  }
  pixel_.Reserve(capacity);
  depth_.Reserve(capacity);
  kind_.Reserve(capacity);
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
  ox_[i] = ox;
  oy_[i] = oy;
  oz_[i] = oz;
  dx_[i] = dx;
  dy_[i] = dy;
  dz_[i] = dz;
  tmin_[i] = tmin;
  tmax_[i] = tmax;
  pixel_[i] = pixel;
  wr_[i] = wr;
  wg_[i] = wg;
  wb_[i] = wb;
  depth_[i] = depth;
  kind_[i] = static_cast<int32_t>(kind);
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

void RayStream::SealLanes(size_t from, size_t end) {
  const float nan = std::numeric_limits<float>::quiet_NaN();
  for (size_t i = from; i < end; ++i) {
    ox_[i] = oy_[i] = oz_[i] = nan;
    dx_[i] = dy_[i] = dz_[i] = nan;
    tmin_[i] = 1.0f;
    tmax_[i] = 0.0f;
    pixel_[i] = 0;
    wr_[i] = wg_[i] = wb_[i] = 0.0f;
    depth_[i] = 0;
    kind_[i] = 0;
  }
}

RayStreamView RayStream::view() {
  if (capacity() == 0) Reserve(1);
  RayStreamView v;
  v.ox = ox_.data();
  v.oy = oy_.data();
  v.oz = oz_.data();
  v.dx = dx_.data();
  v.dy = dy_.data();
  v.dz = dz_.data();
  v.tmin = tmin_.data();
  v.tmax = tmax_.data();
  v.pixel = pixel_.data();
  v.wr = wr_.data();
  v.wg = wg_.data();
  v.wb = wb_.data();
  v.depth = depth_.data();
  v.kind = kind_.data();
  v.size = size_;
  return v;
}

void HitStream::Reserve(size_t capacity) {
  t_.Reserve(capacity);
  u_.Reserve(capacity);
  v_.Reserve(capacity);
  prim_.Reserve(capacity);
}

void HitStream::Resize(size_t n) {
  if (n > t_.capacity() || t_.capacity() == 0) Reserve(n);
  size_ = n;
}

void HitStream::Reset() {
  if (t_.capacity() == 0) Reserve(1);
  for (size_t i = 0; i < t_.capacity(); ++i) {
    t_[i] = std::numeric_limits<float>::infinity();
    u_[i] = v_[i] = 0.0f;
    prim_[i] = -1;
  }
}

HitStreamView HitStream::view() {
  if (t_.capacity() == 0) Reserve(1);
  HitStreamView h;
  h.t = t_.data();
  h.u = u_.data();
  h.v = v_.data();
  h.prim = prim_.data();
  h.size = size_;
  return h;
}

void ContributionStream::Reserve(size_t capacity) {
  pixel_.Reserve(capacity);
  r_.Reserve(capacity);
  g_.Reserve(capacity);
  b_.Reserve(capacity);
}

void ContributionStream::Resize(size_t n) {
  if (n > capacity() || capacity() == 0) Reserve(n < 2 * capacity() ? 2 * capacity() : n);
  size_ = n;
}

}  // namespace rs
