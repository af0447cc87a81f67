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

}  // namespace rs
