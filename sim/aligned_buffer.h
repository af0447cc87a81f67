// An owning byte buffer aligned to a 128-B line: the host storage of an array in simulated main
// memory. SPEs reach it by DMA at the effective address MainMemory::Register gives it (never at
// its host address, which differs between processes).
#pragma once

#include <cstddef>
#include <cstdint>
#include <cstring>
#include <memory>

namespace rs::sim {

class AlignedBuffer {
 public:
  AlignedBuffer() = default;
  // `bytes` rounded up to a multiple of 128, zeroed.
  explicit AlignedBuffer(size_t bytes) { Resize(bytes); }
  void Resize(size_t bytes) {
    size_ = (bytes + 127) / 128 * 128;
    storage_ = std::make_unique<uint8_t[]>(size_ + 128);
    const uintptr_t p = reinterpret_cast<uintptr_t>(storage_.get());
    data_ = storage_.get() + ((128 - (p & 127)) & 127);
    std::memset(data_, 0, size_);
  }
  uint8_t* data() { return data_; }
  const uint8_t* data() const { return data_; }
  template <class T>
  T* As() {
    return reinterpret_cast<T*>(data_);
  }
  template <class T>
  const T* As() const {
    return reinterpret_cast<const T*>(data_);
  }
  size_t size() const { return size_; }

 private:
  std::unique_ptr<uint8_t[]> storage_;
  uint8_t* data_ = nullptr;
  size_t size_ = 0;
};

}  // namespace rs::sim
