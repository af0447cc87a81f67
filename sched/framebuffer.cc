// Order-independent fixed-point framebuffer (see framebuffer.h): allocation, clearing,
// merging and the once-per-frame conversion to floats.
#include "sched/framebuffer.h"

#include <algorithm>
#include <string>
#include <utility>

#include "include/raystream/raystream.h"

namespace rs {

Framebuffer::Framebuffer(int width, int height, Storage storage) {
  if (width < 1 || height < 1 ||
      static_cast<uint64_t>(width) * static_cast<uint64_t>(height) >= (uint64_t{1} << 32)) {
    throw Error("framebuffer: image size " + std::to_string(width) + "x" +
                std::to_string(height) + " must be at least 1x1 and below 2^32 pixels");
  }
  width_ = width;
  height_ = height;
  storage_ = storage;
  if (storage == Storage::kFixed) {
    sums_.assign(3 * num_pixels(), 0);
  } else {
    rgb_.assign(3 * num_pixels(), 0.0f);
  }
}

Framebuffer::Framebuffer(Framebuffer&& other) noexcept { *this = std::move(other); }

Framebuffer& Framebuffer::operator=(Framebuffer&& other) noexcept {
  width_ = std::exchange(other.width_, 0);
  height_ = std::exchange(other.height_, 0);
  storage_ = std::exchange(other.storage_, Storage::kFixed);
  sums_ = std::move(other.sums_);
  other.sums_.clear();
  rgb_ = std::move(other.rgb_);
  other.rgb_.clear();
  dropped_nan_ = std::exchange(other.dropped_nan_, 0);
  clamped_ = std::exchange(other.clamped_, 0);
  return *this;
}

void Framebuffer::Clear() {
  std::fill(sums_.begin(), sums_.end(), 0);
  std::fill(rgb_.begin(), rgb_.end(), 0.0f);
  dropped_nan_ = 0;
  clamped_ = 0;
}

void Framebuffer::Accumulate(const Framebuffer& other) {
  if (other.width_ != width_ || other.height_ != height_ || storage_ != Storage::kFixed ||
      other.storage_ != Storage::kFixed) {
    throw Error("framebuffer: cannot accumulate " + std::to_string(other.width_) + "x" +
                std::to_string(other.height_) + " into " + std::to_string(width_) + "x" +
                std::to_string(height_) + " (both must hold fixed-point sums)");
  }
  for (size_t i = 0; i < sums_.size(); ++i) sums_[i] += other.sums_[i];
  dropped_nan_ += other.dropped_nan_;
  clamped_ += other.clamped_;
}

void Framebuffer::ToRgb(std::vector<float>& rgb) const {
  if (storage_ == Storage::kResolved) {
    rgb = rgb_;
    return;
  }
  rgb.resize(sums_.size());
  for (size_t i = 0; i < sums_.size(); ++i) rgb[i] = FixedToFloat(sums_[i]);
}

std::vector<float> Framebuffer::ToRgb() const {
  std::vector<float> rgb;
  ToRgb(rgb);
  return rgb;
}

void PixelSumTable::Reserve() {
  if (!keys_.empty()) return;
  keys_.assign(kSlots, kEmpty);
  sums_.assign(3 * kSlots, 0);
  used_.reserve(kSlots);  // up to 7/8 full while the lock is busy
}

void PixelSumTable::Add(Framebuffer& fb, std::mutex& lock, const uint32_t* pixel, const float* r,
                        const float* g, const float* b, const int32_t* skip, size_t n) {
  Reserve();
  constexpr uint32_t kMask = kSlots - 1;
  static_assert(kSlots == 4096, "the slot of a pixel below takes 9 + 3 bits");
  ForFixedContributions(r, g, b, skip, n, &nan_, &clamped_, [&](size_t i, const int64_t f[3]) {
    if ((f[0] | f[1] | f[2]) == 0) return;  // skipped, dropped or black
    const uint32_t p = pixel[i];
    // Runs of 8 neighbouring pixels share a bucket of 8 slots (one line of keys), buckets
    // spread by a Fibonacci hash of p / 8: a shade chunk's pixels come in runs.
    uint32_t slot = (((p >> 3) * 0x9E3779B1u) >> 23) << 3 | (p & 7);  // 9 + 3 bits: kSlots
    while (keys_[slot] != p && keys_[slot] != kEmpty) slot = (slot + 1) & kMask;
    int64_t* sum = sums_.data() + 3 * size_t(slot);
    if (keys_[slot] != kEmpty) {
      for (int c = 0; c < 3; ++c) sum[c] += f[c];
      return;
    }
    keys_[slot] = p;
    used_.push_back(slot);
    for (int c = 0; c < 3; ++c) sum[c] = f[c];
    // half full: flush if the lock is free, else keep filling (probes stay short up to 7/8
    // full, where the flush waits for the lock)
    if (used_.size() < kSlots / 2) return;
    if (used_.size() >= kSlots / 8 * 7) {
      lock.lock();
    } else if (!lock.try_lock()) {
      return;
    }
    FlushLocked(fb);
    lock.unlock();
  });
}

void PixelSumTable::Flush(Framebuffer& fb, std::mutex& lock) {
  const std::lock_guard<std::mutex> hold(lock);
  FlushLocked(fb);
}

void PixelSumTable::FlushLocked(Framebuffer& fb) {
  int64_t* const sums = fb.sums();
  for (const uint32_t slot : used_) {
    int64_t* p = sums + 3 * size_t(keys_[slot]);
    const int64_t* f = sums_.data() + 3 * size_t(slot);
    p[0] += f[0];
    p[1] += f[1];
    p[2] += f[2];
    keys_[slot] = kEmpty;
  }
  used_.clear();
  fb.AddCounters(nan_, clamped_);
  nan_ = clamped_ = 0;
}

void PixelSumTable::Clear() {
  for (const uint32_t slot : used_) keys_[slot] = kEmpty;
  used_.clear();
  nan_ = clamped_ = 0;
}

}  // namespace rs
