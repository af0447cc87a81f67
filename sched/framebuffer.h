// Order-independent framebuffer: per-pixel rgb sums as 64-bit fixed-point integers added with
// relaxed atomic fetch_add. Integer addition is associative, so any thread count and any order
// of contributions give the same image bit for bit (the backend-independence guarantee).
#pragma once

#include <hwy/base.h>

#include <atomic>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <mutex>
#include <vector>

#include "streams/ray_stream.h"

namespace rs {

// Pixel values are stored as round(c * 2^kFixedFracBits) per contribution c. Each contribution
// channel is clamped to [0, kMaxContribution] (negative values and +inf are clamped and
// counted; NaN is dropped and counted). Per contribution the fixed value is <= 2^44, so a pixel
// channel can take 2^19 maximal contributions (or any number of ordinary ones) before the
// int64 sum could overflow. Resolution is 2^-32 ~ 2.3e-10 per contribution.
inline constexpr int kFixedFracBits = 32;
inline constexpr float kFixedScale = 4294967296.0f;  // 2^32, exact in float
inline constexpr float kMaxContribution = 4096.0f;   // 2^12

// The fixed-point channels of one contribution (Framebuffer::ToFixed per channel). Returns false
// if a channel is NaN (the contribution is then dropped whole); *clamped is set when a channel
// was clamped.
inline bool ContributionToFixed(float r, float g, float b, int64_t out[3], bool* clamped);

// The fixed-point channels of contributions [0, n): ContributionToFixed for each, a vector at a
// time on the best SIMD target, into out_r / out_g / out_b[i]. A lane whose contribution has a
// NaN channel gets 0 in all three and adds 1 to *nan; a lane with skip[i] != 0 (skip may be
// null) gets 0 and is not counted; *clamped counts the other lanes with a clamped channel. The
// same values and counts as the scalar calls, on every target. No alignment required.
void ContributionsToFixed(const float* r, const float* g, const float* b, const int32_t* skip,
                          size_t n, int64_t* out_r, int64_t* out_g, int64_t* out_b, uint64_t* nan,
                          uint64_t* clamped);

// Adds contribution i < n (r[i], g[i], b[i]), unless skip[i] != 0 (skip may be null), to the
// fixed-point sums[3 * index[i] + channel], as adding them one by one with ContributionToFixed
// does (NaN contributions dropped and counted in *nan, clamped ones counted in *clamped).
// kShared: relaxed atomic adds (other threads may add to the same sums); else plain adds.
// ContributionsToFixed over contributions [0, n) a block at a time: fn(i, f) for each i with
// its three fixed-point channels f (all 0 for a skipped or dropped one), in order.
template <class Fn>
void ForFixedContributions(const float* r, const float* g, const float* b, const int32_t* skip,
                           size_t n, uint64_t* nan, uint64_t* clamped, const Fn& fn) {
  constexpr size_t kBlock = 256;
  alignas(64) int64_t f[3][kBlock];
  for (size_t i0 = 0; i0 < n; i0 += kBlock) {
    const size_t m = n - i0 < kBlock ? n - i0 : kBlock;
    ContributionsToFixed(r + i0, g + i0, b + i0, skip != nullptr ? skip + i0 : nullptr, m, f[0],
                         f[1], f[2], nan, clamped);
    for (size_t k = 0; k < m; ++k) {
      const int64_t fk[3] = {f[0][k], f[1][k], f[2][k]};
      fn(i0 + k, fk);
    }
  }
}

template <bool kShared>
void AddFixedContributions(int64_t* sums, const uint32_t* index, const float* r, const float* g,
                           const float* b, const int32_t* skip, size_t n, uint64_t* nan,
                           uint64_t* clamped) {
  ForFixedContributions(r, g, b, skip, n, nan, clamped, [&](size_t i, const int64_t f[3]) {
    int64_t* p = sums + 3 * static_cast<size_t>(index[i]);
    for (int c = 0; c < 3; ++c) {
      if constexpr (kShared) {
        if (f[c] != 0) std::atomic_ref<int64_t>(p[c]).fetch_add(f[c], std::memory_order_relaxed);
      } else {
        p[c] += f[c];  // 0 for a skipped or dropped lane
      }
    }
  });
}

// One fixed-point pixel channel sum as the image's float: sum * 2^-32 (exact in double),
// rounded once to float.
inline float FixedToFloat(int64_t sum) {
  constexpr double kInvScale = 1.0 / 4294967296.0;
  return static_cast<float>(static_cast<double>(sum) * kInvScale);
}

class Framebuffer {
 public:
  // kFixed: per-pixel fixed-point sums (24 bytes per pixel) taking concurrent Adds from any
  // thread in any order: every backend. kResolved: the float image only (12 bytes per pixel);
  // each pixel receives its complete sums once per frame through SetPixelSums (the frame
  // engine's tiles, whose rays contribute only to their own pixels), so a big image needs half
  // the memory. The image is the same either way.
  enum class Storage { kFixed, kResolved };

  Framebuffer() = default;
  // width * height pixels, all zero. Throws rs::Error if width or height < 1 or the pixel
  // count does not fit 32-bit pixel ids.
  Framebuffer(int width, int height, Storage storage = Storage::kFixed);
  Storage storage() const { return storage_; }

  // Movable (not while other threads add), not copyable.
  Framebuffer(Framebuffer&& other) noexcept;
  Framebuffer& operator=(Framebuffer&& other) noexcept;
  Framebuffer(const Framebuffer&) = delete;
  Framebuffer& operator=(const Framebuffer&) = delete;

  int width() const { return width_; }
  int height() const { return height_; }
  size_t num_pixels() const { return static_cast<size_t>(width_) * height_; }

  // Zeroes every pixel and the counters. Not concurrent with Add.
  void Clear();

  // Converts one contribution channel to fixed point: NaN -> 0 with *nan = true; clamped to
  // [0, kMaxContribution] with *clamped = true when it was outside. Deterministic (depends on
  // c only; the current rounding mode is round-to-nearest-even, never changed in raystream).
  static int64_t ToFixed(float c, bool* nan, bool* clamped) {
    if (std::isnan(c)) {
      *nan = true;
      return 0;
    }
    if (!(c >= 0.0f)) {
      *clamped = true;
      return 0;
    }
    if (c > kMaxContribution) {
      *clamped = true;
      c = kMaxContribution;
    }
    // c * 2^32 is exact in float (power-of-two scale, no overflow), then rounded to an integer:
    // at 2^23 and above a float is one already; below, adding and subtracting 2^23 rounds it to
    // nearest even, as std::nearbyint does in that mode (which is a libm call on baseline x86-64).
    const float x = c * kFixedScale;
    constexpr float k2p23 = 8388608.0f;
    return static_cast<int64_t>(x < k2p23 ? (x + k2p23) - k2p23 : x);
  }

  // Adds (r, g, b) to pixel `pixel` (< num_pixels()). Thread-safe and wait-free: three relaxed
  // atomic adds (only the final sums matter; the frame barrier orders them before ToRgb). A
  // contribution with a NaN channel is dropped entirely (all three channels) and counted.
  void Add(uint32_t pixel, float r, float g, float b) { AddAs<true>(pixel, r, g, b); }

  // Add(pixel[i], r[i], g[i], b[i]) for every contribution of `c` (pixels < num_pixels()), in
  // stream order: the same fixed-point sums, NaN drops and clamp counts as adding them one by
  // one. Thread-safe like Add. kShared = false: plain adds, for a caller whose pixels no other
  // thread adds to during the frame (the same sums, without the atomic read-modify-writes).
  template <bool kShared = true>
  void Add(const ContributionView& c) {
    Add<kShared>(c.pixel, c.r, c.g, c.b, nullptr, c.size);
  }
  // The same for the contributions i < n with skip[i] == 0 (skip may be null) of arrays.
  template <bool kShared = true>
  void Add(const uint32_t* pixel, const float* r, const float* g, const float* b,
           const int32_t* skip, size_t n) {
    HWY_DASSERT(storage_ == Storage::kFixed);
    uint64_t nan = 0, clamped = 0;
    AddFixedContributions<kShared>(sums_.data(), pixel, r, g, b, skip, n, &nan, &clamped);
    AddCounters(nan, clamped);
  }

  // Add (shared = true: three relaxed atomic adds) or plain adds (false) to a kFixed buffer.
  template <bool kShared>
  void AddAs(uint32_t pixel, float r, float g, float b) {
    HWY_DASSERT(storage_ == Storage::kFixed);
    int64_t f[3];
    bool clamped = false;
    if (!ContributionToFixed(r, g, b, f, &clamped)) {
      std::atomic_ref<uint64_t>(dropped_nan_).fetch_add(1, std::memory_order_relaxed);
      return;
    }
    if (clamped) std::atomic_ref<uint64_t>(clamped_).fetch_add(1, std::memory_order_relaxed);
    HWY_DASSERT(pixel < num_pixels());
    int64_t* p = sums_.data() + 3 * static_cast<size_t>(pixel);
    for (int c = 0; c < 3; ++c) {
      if constexpr (kShared) {
        if (f[c] != 0) std::atomic_ref<int64_t>(p[c]).fetch_add(f[c], std::memory_order_relaxed);
      } else {
        p[c] += f[c];
      }
    }
  }

  // A pixel's complete sums of the frame (3 channels) from a caller that owns the pixel (no
  // other thread adds to it, and no other call sets it this frame): kFixed adds them (plain
  // adds), kResolved stores their floats. The image is then what Add-ing the contributions
  // behind the sums one by one gives. AddCounters: the contributions the caller dropped (NaN)
  // and clamped.
  void SetPixelSums(uint32_t pixel, const int64_t sums[3]) {
    HWY_DASSERT(pixel < num_pixels());
    const size_t i = 3 * static_cast<size_t>(pixel);
    if (storage_ == Storage::kFixed) {
      for (int c = 0; c < 3; ++c) sums_[i + c] += sums[c];
    } else {
      for (int c = 0; c < 3; ++c) rgb_[i + c] = FixedToFloat(sums[c]);
    }
  }
  void AddCounters(uint64_t dropped_nan, uint64_t clamped) {
    if (dropped_nan != 0) {
      std::atomic_ref<uint64_t>(dropped_nan_).fetch_add(dropped_nan, std::memory_order_relaxed);
    }
    if (clamped != 0) {
      std::atomic_ref<uint64_t>(clamped_).fetch_add(clamped, std::memory_order_relaxed);
    }
  }

  // Adds every pixel sum and counter of `other` (same size, both kFixed) into this one: partial
  // framebuffers (e.g. per MPI rank) merge exactly. Not concurrent with Add.
  void Accumulate(const Framebuffer& other);

  // rgb floats, width * height * 3, row 0 at the top: sum * 2^-32 rounded once to float.
  // Call after all adds of the frame have completed (after the frame barrier).
  std::vector<float> ToRgb() const;
  void ToRgb(std::vector<float>& rgb) const;

  // kResolved: the image (width * height * 3 floats, the ToRgb values); empty for kFixed.
  const std::vector<float>& resolved() const { return rgb_; }

  // Raw fixed-point sums (3 per pixel; kFixed only), for exact comparisons and reductions.
  const int64_t* sums() const { return sums_.data(); }
  int64_t* sums() { return sums_.data(); }

  uint64_t dropped_nan() const {
    return std::atomic_ref<uint64_t>(const_cast<uint64_t&>(dropped_nan_))
        .load(std::memory_order_relaxed);
  }
  uint64_t clamped() const {
    return std::atomic_ref<uint64_t>(const_cast<uint64_t&>(clamped_))
        .load(std::memory_order_relaxed);
  }

 private:
  static_assert(std::atomic_ref<int64_t>::required_alignment <= alignof(int64_t),
                "vector<int64_t> elements must be usable with atomic_ref");
  static_assert(std::atomic_ref<int64_t>::is_always_lock_free, "need lock-free 64-bit adds");

  int width_ = 0;
  int height_ = 0;
  Storage storage_ = Storage::kFixed;
  std::vector<int64_t> sums_;  // kFixed: 3 per pixel
  std::vector<float> rgb_;     // kResolved: 3 per pixel
  alignas(std::atomic_ref<uint64_t>::required_alignment) uint64_t dropped_nan_ = 0;
  alignas(std::atomic_ref<uint64_t>::required_alignment) uint64_t clamped_ = 0;
};

// One thread's contributions to pixels other threads also add to (a shared queue's rays of one
// pixel are traced by whichever thread pops them), summed per pixel in a small table and added
// to the framebuffer a table at a time with plain adds under a mutex the threads share: about
// 2048 pixels per lock instead of an atomic read-modify-write per contribution channel (a
// pixel's contributions rarely meet in the table: it is the atomics that cost). A half-full
// table is flushed if the mutex is free, else it keeps filling; it waits for the mutex only
// when 7/8 full, and in Flush. The same
// sums and counters as Framebuffer::Add (integer addition is associative; NaN drops and clamps
// are counted per contribution). 4096 slots (128 KiB), allocated by Reserve (or the first
// Add); nothing after. Not thread-safe: one per thread; every thread adding to pixels another
// thread may also add to during the frame must go through a table with the same mutex.
class PixelSumTable {
 public:
  static constexpr size_t kSlots = 4096;  // a power of two
  void Reserve();  // allocates the table (no-op once allocated)
  // Framebuffer::Add(pixel, r, g, b, skip, n), combined: what is not flushed yet stays here.
  void Add(Framebuffer& fb, std::mutex& lock, const uint32_t* pixel, const float* r,
           const float* g, const float* b, const int32_t* skip, size_t n);
  // Adds every pixel sum and counter held to fb (holding `lock`) and empties the table. The
  // frame's image needs every thread's Flush (before the closing barrier).
  void Flush(Framebuffer& fb, std::mutex& lock);
  // Empties the table without adding (a frame that was abandoned).
  void Clear();
  size_t size() const { return used_.size(); }

 private:
  void FlushLocked(Framebuffer& fb);  // Flush's adds; the caller holds the lock
  static constexpr uint32_t kEmpty = 0xffffffffu;
  std::vector<uint32_t> keys_;  // per slot: its pixel, or kEmpty
  std::vector<int64_t> sums_;   // per slot: 3 fixed-point channels
  std::vector<uint32_t> used_;  // the slots in use (capacity kSlots)
  uint64_t nan_ = 0, clamped_ = 0;
};

inline bool ContributionToFixed(float r, float g, float b, int64_t out[3], bool* clamped) {
  bool nan = false;
  out[0] = Framebuffer::ToFixed(r, &nan, clamped);
  out[1] = Framebuffer::ToFixed(g, &nan, clamped);
  out[2] = Framebuffer::ToFixed(b, &nan, clamped);
  return !nan;
}

}  // namespace rs
