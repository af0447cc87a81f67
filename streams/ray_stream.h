// Owning SoA ray and hit buffers: every array 64-B aligned and padded to kStreamPad, so
// kernels may load whole vectors past `size` (padding lanes hold a harmless sentinel).
#pragma once

#include <hwy/aligned_allocator.h>
#include <hwy/base.h>

#include <cstddef>
#include <cstdint>

#include "include/raystream/raystream.h"

namespace rs {

// One aligned array of T with capacity rounded up to kStreamPad.
template <typename T>
class AlignedArray {
 public:
  AlignedArray() = default;
  explicit AlignedArray(size_t capacity) { Reserve(capacity); }
  // Grows (never shrinks) to hold at least `capacity` elements; old contents are kept.
  void Reserve(size_t capacity);
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
  auto grown = hwy::AllocateAligned<T>(padded);
  HWY_ASSERT(grown);
  for (size_t i = 0; i < capacity_; ++i) grown[i] = ptr_[i];
  for (size_t i = capacity_; i < padded; ++i) grown[i] = T{};
  ptr_ = std::move(grown);
  capacity_ = padded;
}

// A stream of rays that owns its arrays. view() hands out the SoA view for kernels.
class RayStream {
 public:
  RayStream() = default;
  explicit RayStream(size_t capacity) { Reserve(capacity); }
  void Reserve(size_t capacity);
  void Clear() { size_ = 0; }
  size_t size() const { return size_; }
  size_t capacity() const { return ox_.capacity(); }
  bool empty() const { return size_ == 0; }
  // Sets size; grows capacity when needed. New rays are uninitialised until written.
  void Resize(size_t n);

  // Appends one ray; grows as needed. Returns its index.
  size_t Push(float ox, float oy, float oz, float dx, float dy, float dz, float tmin, float tmax,
              uint32_t pixel, float wr, float wg, float wb, int32_t depth, RayKind kind);
  // Copies ray i of `from` to the end of this stream.
  size_t PushFrom(const RayStreamView& from, size_t i);

  // Padding lanes [size, capacity) are set to a ray that can never hit (NaN origin,
  // tmax < tmin) so that full-vector loads see harmless values.
  void FillPadding();

  RayStreamView view();

 private:
  AlignedArray<float> ox_, oy_, oz_, dx_, dy_, dz_, tmin_, tmax_, wr_, wg_, wb_;
  AlignedArray<uint32_t> pixel_;
  AlignedArray<int32_t> depth_, kind_;
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
  AlignedArray<float> t_, u_, v_;
  AlignedArray<int32_t> prim_;
  size_t size_ = 0;
};

}  // namespace rs
