// Owning SoA ray, hit and contribution buffers: every array 64-B aligned and padded to
// kStreamPad, so kernels may load whole vectors past `size` (padding lanes hold a harmless
// sentinel).
#pragma once

#include <hwy/aligned_allocator.h>
#include <hwy/base.h>

#include <cstddef>
#include <cstdint>
#include <cstring>
#include <utility>

#include "include/raystream/raystream.h"
#include "streams/block_memory.h"

namespace rs {

// Throws rs::Error "out of memory: cannot allocate <size> for <what>" (the allocation that failed
// and how much; an exhausted memory is never an assert abort).
[[noreturn]] void ThrowOutOfMemory(size_t bytes, const char* what);

// AllocateBlockArray<T>(n) (huge pages for large arrays, the current BlockCache's blocks), or
// ThrowOutOfMemory naming `what`.
template <typename T>
hwy::AlignedFreeUniquePtr<T[]> AllocateAlignedOrThrow(size_t n, const char* what) {
  auto p = AllocateBlockArray<T>(n);
  if (!p) ThrowOutOfMemory(n * sizeof(T), what);
  return p;
}

// One aligned array of T with capacity rounded up to kStreamPad.
template <typename T>
class AlignedArray {
 public:
  AlignedArray() = default;
  explicit AlignedArray(size_t capacity) { Reserve(capacity); }
  // Grows (never shrinks) to hold at least `capacity` elements; old contents are kept.
  void Reserve(size_t capacity);
  // The same for an array about to be overwritten: old contents are not kept, and elements
  // [0, capacity) of a grown array are left unset (the padding after them is zeroed).
  void ReserveForOverwrite(size_t capacity);
  T* data() { return ptr_.get(); }
  const T* data() const { return ptr_.get(); }
  size_t capacity() const { return capacity_; }
  T& operator[](size_t i) { return ptr_[i]; }
  const T& operator[](size_t i) const { return ptr_[i]; }

 private:
  hwy::AlignedFreeUniquePtr<T[]> ptr_;
  size_t capacity_ = 0;
};

template <typename T>
void AlignedArray<T>::Reserve(size_t capacity) {
  const size_t padded = PaddedSize(capacity);
  if (padded <= capacity_ && ptr_) return;
  auto grown = AllocateAlignedOrThrow<T>(padded, "a ray, hit or contribution stream");
  for (size_t i = 0; i < capacity_; ++i) grown[i] = ptr_[i];
  for (size_t i = capacity_; i < padded; ++i) grown[i] = T{};
  ptr_ = std::move(grown);
  capacity_ = padded;
}

template <typename T>
void AlignedArray<T>::ReserveForOverwrite(size_t capacity) {
  const size_t padded = PaddedSize(capacity);
  if (padded <= capacity_ && ptr_) return;
  ptr_ = AllocateAlignedOrThrow<T>(padded, "a ray, hit or contribution stream");
  for (size_t i = capacity; i < padded; ++i) ptr_[i] = T{};
  capacity_ = padded;
}

// N arrays of 4-byte elements (float, uint32_t, int32_t) in one aligned allocation, each
// capacity() long (a multiple of kStreamPad) and Stride(capacity()) apart (64-B aligned). One
// allocation per stream: a small stream (a 20-ray task) keeps its arrays on neighbouring cache
// lines, instead of one padded and offset heap block per array.
template <size_t N>
class SoaArrays {
 public:
  SoaArrays() = default;
  SoaArrays(SoaArrays&& o) noexcept
      : ptr_(std::move(o.ptr_)), capacity_(std::exchange(o.capacity_, 0)) {}
  SoaArrays& operator=(SoaArrays&& o) noexcept {
    ptr_ = std::move(o.ptr_);
    capacity_ = std::exchange(o.capacity_, 0);
    return *this;
  }
  // Grows (never shrinks) to hold at least `capacity` elements per array; old contents are kept,
  // new elements are zero. Throws naming `what` when memory is exhausted.
  void Reserve(size_t capacity, const char* what);
  size_t capacity() const { return capacity_; }
  // Array a (< N) as T (4 bytes).
  template <typename T>
  T* array(size_t a) const {
    static_assert(sizeof(T) == 4);
    return reinterpret_cast<T*>(ptr_.get() + a * Stride(capacity_) * 4);
  }

  // Elements from one array's start to the next's: the capacity, and for arrays of 4 KiB or
  // more, that rounded up to a multiple of 4 KiB plus one cache line. Arrays a multiple of 4
  // KiB apart (a batch of 1024 rays, the benchmarks' 2^20) map element i of every array to
  // the same L1 and L2 sets, and a kernel that reads ox .. tmax and writes t, u, v, prim at
  // one index walks 12-14 streams through the 8 ways of one set.
  static size_t Stride(size_t capacity) {
    constexpr size_t kPage = 1024;  // elements of 4 B
    return capacity < kPage ? capacity : (capacity + kPage - 1) / kPage * kPage + kStreamPad;
  }

 private:
  hwy::AlignedFreeUniquePtr<uint8_t[]> ptr_;
  size_t capacity_ = 0;
};

template <size_t N>
void SoaArrays<N>::Reserve(size_t capacity, const char* what) {
  const size_t padded = PaddedSize(capacity);
  if (padded <= capacity_ && ptr_) return;
  auto grown = AllocateAlignedOrThrow<uint8_t>(N * Stride(padded) * 4, what);
  for (size_t a = 0; a < N; ++a) {
    uint8_t* to = grown.get() + a * Stride(padded) * 4;
    if (capacity_ > 0) std::memcpy(to, ptr_.get() + a * Stride(capacity_) * 4, capacity_ * 4);
    std::memset(to + capacity_ * 4, 0, (padded - capacity_) * 4);
  }
  ptr_ = std::move(grown);
  capacity_ = padded;
}

// Rays [from, end) of v become rays that can never hit (NaN origin and direction, tmax < tmin,
// pixel 0, weight 0, depth 0, kind 0): the lanes whole-vector loads past a stream's end reach.
// One fill per array. v must have every array (a RayStream's view) and hold the lanes.
void SealRays(const RayStreamView& v, size_t from, size_t end);

// Rays [first, first + n) of `rays` as a view of their own: every non-null array offset (the
// base is 64-B aligned only when first is a multiple of kStreamPad). The lanes after the view
// are the stream's next rays (or its padding), so whole-vector loads stay inside the arrays.
RayStreamView SubView(const RayStreamView& rays, size_t first, size_t n);
// Hits [first, first + n) of `hits` (t, u, v, prim offset; size n).
HitStreamView SubView(const HitStreamView& hits, size_t first, size_t n);

// Ray i of `from` copied to slot j of `to` (every array both views have; pixel, weights, depth
// and kind only where `from` has them, else their defaults: pixel 0, weight 1, depth 0,
// primary). kWhole: both views have every array (RayStream views), copied without the checks.
// Inline: the frame engine's partitions copy every spawned ray through it.
template <bool kWhole = false>
inline void CopyRay(const RayStreamView& f, size_t i, const RayStreamView& t, size_t j) {
  t.ox[j] = f.ox[i];
  t.oy[j] = f.oy[i];
  t.oz[j] = f.oz[i];
  t.dx[j] = f.dx[i];
  t.dy[j] = f.dy[i];
  t.dz[j] = f.dz[i];
  t.tmin[j] = f.tmin[i];
  t.tmax[j] = f.tmax[i];
  if constexpr (kWhole) {
    t.pixel[j] = f.pixel[i];
    t.wr[j] = f.wr[i];
    t.wg[j] = f.wg[i];
    t.wb[j] = f.wb[i];
    t.depth[j] = f.depth[i];
    t.kind[j] = f.kind[i];
  } else {
    if (t.pixel != nullptr) t.pixel[j] = f.pixel != nullptr ? f.pixel[i] : 0u;
    if (t.wr != nullptr) t.wr[j] = f.wr != nullptr ? f.wr[i] : 1.0f;
    if (t.wg != nullptr) t.wg[j] = f.wg != nullptr ? f.wg[i] : 1.0f;
    if (t.wb != nullptr) t.wb[j] = f.wb != nullptr ? f.wb[i] : 1.0f;
    if (t.depth != nullptr) t.depth[j] = f.depth != nullptr ? f.depth[i] : 0;
    if (t.kind != nullptr) {
      t.kind[j] = f.kind != nullptr ? f.kind[i] : static_cast<int32_t>(RayKind::kPrimary);
    }
  }
}

// Rays [first, first + n) of `from` copied to slots [at, at + n) of `to`, one memcpy per array
// (the bulk form of CopyRay, same defaults where `from` lacks an array that `to` has). The two
// ranges must not overlap; both views must hold them.
void CopyRays(const RayStreamView& from, size_t first, size_t n, const RayStreamView& to,
              size_t at);

// A stream of rays that owns its arrays. view() hands out the SoA view for kernels.
class RayStream {
 public:
  RayStream() = default;
  explicit RayStream(size_t capacity) { Reserve(capacity); }
  void Reserve(size_t capacity);
  void Clear() { size_ = 0; }
  size_t size() const { return size_; }
  size_t capacity() const { return arrays_.capacity(); }
  bool empty() const { return size_ == 0; }
  // Sets size; grows capacity when needed. New rays are uninitialised until written.
  void Resize(size_t n);

  // Appends one ray; grows as needed. Returns its index.
  size_t Push(float ox, float oy, float oz, float dx, float dy, float dz, float tmin, float tmax,
              uint32_t pixel, float wr, float wg, float wb, int32_t depth, RayKind kind);
  // Copies ray i of `from` to the end of this stream.
  size_t PushFrom(const RayStreamView& from, size_t i);
  // Appends rays [first, first + n) of `from` (CopyRays; grows as Resize does). `from` must not
  // be a view of this stream.
  void Append(const RayStreamView& from, size_t first, size_t n);

  // Padding lanes [size, capacity) are set to a ray that can never hit (NaN origin,
  // tmax < tmin) so that full-vector loads see harmless values.
  void FillPadding();
  // The same for lanes [size, size + kStreamPad) only (those inside the capacity): all that a
  // kernel's whole-vector loads past size can reach, at a cost independent of the capacity.
  void SealTail();

  RayStreamView view() {
    if (arrays_.capacity() == 0) Reserve(1);
    RayStreamView v = arrays_view_;
    v.size = size_;
    return v;
  }

 private:
  void SealLanes(size_t from, size_t end);

  // ox, oy, oz, dx, dy, dz, tmin, tmax, pixel, wr, wg, wb, depth, kind (the view's order).
  SoaArrays<14> arrays_;
  RayStreamView arrays_view_;  // arrays_' pointers, set by Reserve (kernels ask for views often)
  size_t size_ = 0;
};

// Closest-hit results, owning.
class HitStream {
 public:
  HitStream() = default;
  explicit HitStream(size_t capacity) { Reserve(capacity); }
  void Reserve(size_t capacity);
  void Resize(size_t n);
  size_t size() const { return size_; }
  // Sets every lane, padding included, to a miss (t = +inf, prim = -1, u = v = 0).
  void Reset();
  HitStreamView view();

 private:
  SoaArrays<4> arrays_;  // t, u, v, prim
  size_t size_ = 0;
};

// Framebuffer contributions (pixel, rgb) of a ContributionStream, read-only, SoA. Entry i adds
// (r[i], g[i], b[i]) to pixel[i]; channels may be NaN, negative or huge (the framebuffer drops or
// clamps them). Does not own its data.
struct ContributionView {
  const uint32_t* pixel = nullptr;
  const float* r = nullptr;
  const float* g = nullptr;
  const float* b = nullptr;
  size_t size = 0;
};

// A stream of contributions that owns its arrays (what Shade emits; the caller adds them to its
// framebuffer). Arrays are aligned and padded like RayStream's. Reserve(n) then at most n
// Push / Resize(n) never allocates; Clear keeps the capacity.
class ContributionStream {
 public:
  ContributionStream() = default;
  explicit ContributionStream(size_t capacity) { Reserve(capacity); }
  // Grows (never shrinks) to at least `capacity`; contents are kept.
  void Reserve(size_t capacity);
  void Clear() { size_ = 0; }
  size_t size() const { return size_; }
  size_t capacity() const { return arrays_.capacity(); }
  bool empty() const { return size_ == 0; }
  // Sets size; grows capacity (at least doubling) only when n > capacity(). Entries
  // [old size, n) are uninitialised until written through the data pointers.
  void Resize(size_t n);
  // Appends one contribution; grows (doubling) only when full.
  void Push(uint32_t pixel, float r, float g, float b) {
    const size_t i = size_;
    Resize(size_ + 1);
    pixel_data()[i] = pixel;
    r_data()[i] = r;
    g_data()[i] = g;
    b_data()[i] = b;
  }
  // Writable arrays (capacity() elements each), for kernels that append in place.
  uint32_t* pixel_data() { return arrays_.array<uint32_t>(0); }
  float* r_data() { return arrays_.array<float>(1); }
  float* g_data() { return arrays_.array<float>(2); }
  float* b_data() { return arrays_.array<float>(3); }
  ContributionView view() const {
    return {arrays_.array<uint32_t>(0), arrays_.array<float>(1), arrays_.array<float>(2),
            arrays_.array<float>(3), size_};
  }

 private:
  SoaArrays<4> arrays_;  // pixel, r, g, b
  size_t size_ = 0;
};

}  // namespace rs
