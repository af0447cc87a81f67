// Local-store arena of one simulated SPE (see local_store.h).
#include "sim/local_store.h"

#include <algorithm>
#include <cstring>

#include "include/raystream/raystream.h"

namespace rs::sim {

LocalStore::LocalStore(uint32_t size, int spe) : size_(size), spe_(spe) {
  if (size == 0 || size % 128 != 0) {
    throw Error("local store size " + std::to_string(size) + " must be a positive multiple of 128");
  }
  storage_ = std::make_unique<uint8_t[]>(size_t{size} + 128);
  const uintptr_t p = reinterpret_cast<uintptr_t>(storage_.get());
  base_ = storage_.get() + ((128 - (p & 127)) & 127);
  std::memset(base_, 0, size);
}

Lsa LocalStore::Allocate(std::string_view what, uint64_t bytes, uint32_t align) {
  if (align < 16 || (align & (align - 1)) != 0) {
    throw Error("SPE " + std::to_string(spe_) + " local store: alignment " + std::to_string(align) +
                " for '" + std::string(what) + "' must be a power of two >= 16");
  }
  const uint64_t start = (uint64_t{top_} + align - 1) & ~uint64_t{align - 1};
  const uint64_t rounded = (bytes + 15) & ~uint64_t{15};
  if (start + rounded > size_) {
    std::vector<Allocation> largest = allocations_;
    std::sort(largest.begin(), largest.end(),
              [](const Allocation& a, const Allocation& b) { return a.bytes > b.bytes; });
    std::string held;
    for (size_t i = 0; i < largest.size() && i < 6; ++i) {
      held += (i ? ", " : "") + largest[i].what + " " + std::to_string(largest[i].bytes) + " B";
    }
    throw Error("SPE " + std::to_string(spe_) + " local store overflow: allocating '" +
                std::string(what) + "' (" + std::to_string(bytes) + " B, aligned " +
                std::to_string(align) + ") needs " + std::to_string(start + rounded - top_) +
                " B but only " + std::to_string(size_ - top_) + " B of " + std::to_string(size_) +
                " B are free (held: " + held + ")");
  }
  std::memset(base_ + start, 0, rounded);
  top_ = static_cast<uint32_t>(start + rounded);
  allocations_.push_back(
      Allocation{std::string(what), static_cast<Lsa>(start), static_cast<uint32_t>(rounded)});
  return static_cast<Lsa>(start);
}

void LocalStore::Reset() {
  top_ = 0;
  allocations_.clear();
}

uint8_t* LocalStore::Bytes(Lsa lsa, uint64_t bytes) {
  if (!Contains(lsa, bytes)) {
    throw Error("SPE " + std::to_string(spe_) + " local store access [" + std::to_string(lsa) +
                ", +" + std::to_string(bytes) + ") outside the " + std::to_string(size_) +
                " B local store");
  }
  return base_ + lsa;
}

const uint8_t* LocalStore::Bytes(Lsa lsa, uint64_t bytes) const {
  return const_cast<LocalStore*>(this)->Bytes(lsa, bytes);
}

std::string LocalStore::Describe() const {
  std::string s;
  for (const Allocation& a : allocations_) {
    s += (s.empty() ? "" : ", ") + a.what + " " + std::to_string(a.bytes) + " B @ " +
         std::to_string(a.lsa);
  }
  s += " (" + std::to_string(top_) + " of " + std::to_string(size_) + " B used)";
  return s;
}

}  // namespace rs::sim
