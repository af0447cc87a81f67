// The 256 KiB local store of one simulated SPE: a byte arena from which everything the SPE works
// on is allocated by name (code/stack budget, ray buffers, triangle buffers, occupancy bits,
// software cache, DMA lists). Overflow is a hard rs::Error naming the allocation and the sizes.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <string>
#include <string_view>
#include <vector>

namespace rs::sim {

// A local-store address (byte offset into the LS), as the SPU sees it.
using Lsa = uint32_t;

class LocalStore {
 public:
  struct Allocation {
    std::string what;
    Lsa lsa = 0;
    uint32_t bytes = 0;
  };

  // size: bytes of local store (256 KiB on the Cell); spe: id used in messages.
  explicit LocalStore(uint32_t size = 256 * 1024, int spe = 0);

  // Reserves `bytes` (rounded up to 16) at an address aligned to `align` (a power of two >= 16;
  // DMA buffers use 128). Returns its LSA. Throws rs::Error naming `what`, the request, the
  // bytes still free and the largest allocations so far if it does not fit. Zeroes the bytes.
  Lsa Allocate(std::string_view what, uint64_t bytes, uint32_t align = 16);

  // Frees every allocation (the next program's layout starts at 0).
  void Reset();

  uint32_t size() const { return size_; }
  uint32_t used() const { return top_; }
  uint32_t free_bytes() const { return size_ - top_; }
  int spe() const { return spe_; }
  const std::vector<Allocation>& allocations() const { return allocations_; }

  // Host pointer to [lsa, lsa + bytes); the range must lie inside the LS (checked: throws
  // rs::Error, since an out-of-range LS access is a bug of the simulated SPE program).
  uint8_t* Bytes(Lsa lsa, uint64_t bytes);
  const uint8_t* Bytes(Lsa lsa, uint64_t bytes) const;
  template <class T>
  T* As(Lsa lsa, uint64_t count = 1) {
    return reinterpret_cast<T*>(Bytes(lsa, count * sizeof(T)));
  }
  template <class T>
  const T* As(Lsa lsa, uint64_t count = 1) const {
    return reinterpret_cast<const T*>(Bytes(lsa, count * sizeof(T)));
  }
  bool Contains(Lsa lsa, uint64_t bytes) const { return uint64_t{lsa} + bytes <= size_; }

  // "code and stack 40960 B @ 0, ray ring buffer 16384 B @ 40960, ..." for reports.
  std::string Describe() const;

 private:
  uint32_t size_;
  int spe_;
  uint32_t top_ = 0;
  std::unique_ptr<uint8_t[]> storage_;
  uint8_t* base_ = nullptr;  // 128-B aligned start inside storage_
  std::vector<Allocation> allocations_;
};

}  // namespace rs::sim
