// Large-array blocks and their cache (see block_memory.h).
#include "streams/block_memory.h"

#include <atomic>
#include <cstdlib>
#include <new>

#if defined(__linux__)
#include <sys/mman.h>
#endif

namespace rs {
namespace {

// Every block starts with this header (one cache line: the block's payload stays 64-B aligned).
struct alignas(64) BlockHeader {
  size_t capacity;  // payload bytes
  size_t requested;  // bytes asked for (the waste rule of BlockCache::Take)
  size_t mapped;    // bytes mapped (mmap), 0 for malloc
};
constexpr size_t kHeader = sizeof(BlockHeader);
constexpr size_t kPage = 4096;
// hwy::AllocateAligned asks for the payload plus a cyclic offset of up to 2 KiB (it staggers
// arrays against 2 KiB aliasing): every block allocated for a BlockCache holds this much more, so
// the same array asked for again fits the block it had. Blocks without a cache go back to the
// system when freed and get no slack: a queue backend's 20-ray task streams (3.6 KiB each,
// thousands of them) took 2 KiB more each: 22 MiB more peak RSS (office-graz 1024x1024, LOCAL,
// 2 threads: 139 -> 117 MiB), and where fresh pages are dear (a VM whose host backs them on
// first touch) the first frame's reservation took 58 ms instead of 7.5; with pages already
// backed, 11.4 against 9.6 ms of the first frame's application time.
constexpr size_t kSlack = 2048;

std::atomic<size_t> g_system_blocks{0};

size_t RoundUp(size_t x, size_t to) { return (x + to - 1) / to * to; }

BlockHeader* HeaderOf(void* block) {
  return reinterpret_cast<BlockHeader*>(static_cast<char*>(block) - kHeader);
}

void* SystemAllocate(size_t requested, bool cached) {
  if (requested > (size_t{1} << 62)) return nullptr;
  const size_t bytes = requested + (cached ? kSlack : 0);
  // (AddressSanitizer checks heap blocks only: under it every block comes from malloc)
#if defined(__linux__) && defined(MADV_HUGEPAGE) && !defined(__SANITIZE_ADDRESS__)
  if (bytes + kHeader >= kHugeBlockBytes / 2) {
    // Mapped from a 2 MiB boundary (one extra huge page mapped, the slack unmapped again), to
    // its size rounded to 4 KiB: the whole 2 MiB pages inside get huge pages, the tail small
    // ones; a tail of 1 MiB or more is rounded up to a huge page too (less than 1 MiB more, and
    // one fault instead of 256 or more).
    size_t size = RoundUp(bytes + kHeader, kPage);
    if (size % kHugeBlockBytes >= kHugeBlockBytes / 2) size = RoundUp(size, kHugeBlockBytes);
    const size_t span = size + kHugeBlockBytes;
    void* m = mmap(nullptr, span, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
    if (m == MAP_FAILED) return nullptr;
    const uintptr_t lo = reinterpret_cast<uintptr_t>(m);
    const uintptr_t at = RoundUp(lo, kHugeBlockBytes);
    if (at > lo) munmap(m, at - lo);
    if (lo + span > at + size) munmap(reinterpret_cast<void*>(at + size), lo + span - (at + size));
    madvise(reinterpret_cast<void*>(at), size, MADV_HUGEPAGE);  // advice: errors ignored
    auto* h = reinterpret_cast<BlockHeader*>(at);
    h->capacity = size - kHeader;
    h->requested = requested;
    h->mapped = size;
    return reinterpret_cast<char*>(at) + kHeader;
  }
#endif
  void* m = std::aligned_alloc(kHeader, RoundUp(bytes + kHeader, kHeader));
  if (m == nullptr) return nullptr;
  auto* h = static_cast<BlockHeader*>(m);
  h->capacity = bytes;
  h->requested = requested;
  h->mapped = 0;
  return static_cast<char*>(m) + kHeader;
}

void SystemFree(void* block) {
  BlockHeader* h = HeaderOf(block);
#if defined(__linux__)
  if (h->mapped != 0) {
    munmap(h, h->mapped);
    return;
  }
#endif
  std::free(h);
}

thread_local BlockCache* t_cache = nullptr;

}  // namespace

void* AllocateBlock(void* opaque, size_t bytes) {
  if (opaque != nullptr) {
    if (void* block = static_cast<BlockCache*>(opaque)->Take(bytes)) return block;
  }
  void* block = SystemAllocate(bytes, opaque != nullptr);
  if (block != nullptr) g_system_blocks.fetch_add(1, std::memory_order_relaxed);
  return block;
}

void FreeBlock(void* opaque, void* block) {
  if (block == nullptr) return;
  if (opaque != nullptr) return static_cast<BlockCache*>(opaque)->Keep(block);
  SystemFree(block);
}

void* BlockCache::Take(size_t bytes) {
  const std::lock_guard<std::mutex> lock(mutex_);
  size_t best = free_.size();
  for (size_t i = 0; i < free_.size(); ++i) {  // the smallest that fits (few blocks: a scan)
    // fits, and the block's first request was not much larger (a block's capacity may hold
    // up to 1 MiB of huge-page rounding the waste rule should not count)
    const size_t c = free_[i].capacity, r = free_[i].requested;
    if (c >= bytes && (r <= bytes || r - bytes <= bytes / 4 + 4 * kPage) &&
        (best == free_.size() || c < free_[best].capacity)) {
      best = i;
    }
  }
  if (best == free_.size()) return nullptr;
  void* block = free_[best].block;
  free_[best] = free_.back();
  free_.pop_back();
  return block;
}

void BlockCache::Keep(void* block) {
  const std::lock_guard<std::mutex> lock(mutex_);
  try {
    free_.push_back({block, HeaderOf(block)->capacity, HeaderOf(block)->requested, generation_});
  } catch (const std::bad_alloc&) {
    SystemFree(block);
  }
}

void BlockCache::BeginBuild() {
  const std::lock_guard<std::mutex> lock(mutex_);
  ++generation_;
}

void BlockCache::EndBuild(bool keep_freed) {
  const std::lock_guard<std::mutex> lock(mutex_);
  size_t kept = 0;
  for (const Kept& k : free_) {
    if (keep_freed && k.generation == generation_) {
      free_[kept++] = k;
    } else {
      SystemFree(k.block);
    }
  }
  free_.resize(kept);
}

size_t BlockCache::kept_bytes() const {
  const std::lock_guard<std::mutex> lock(mutex_);
  size_t bytes = 0;
  for (const Kept& k : free_) bytes += k.capacity;
  return bytes;
}

BlockCache::~BlockCache() {
  for (const Kept& k : free_) SystemFree(k.block);
}

size_t SystemBlockCount() { return g_system_blocks.load(std::memory_order_relaxed); }

void AdviseHugePages(void* p, size_t bytes) {
#if defined(__linux__) && defined(MADV_HUGEPAGE)
  if (p == nullptr || bytes < kHugePageMinBytes) return;
  const uintptr_t lo = RoundUp(reinterpret_cast<uintptr_t>(p), kHugeBlockBytes);
  const uintptr_t hi = (reinterpret_cast<uintptr_t>(p) + bytes) / kHugeBlockBytes * kHugeBlockBytes;
  if (hi > lo) madvise(reinterpret_cast<void*>(lo), hi - lo, MADV_HUGEPAGE);  // advice: errors ignored
#else
  (void)p;
  (void)bytes;
#endif
}

BlockCache* CurrentBlockCache() { return t_cache; }

BlockCacheScope::BlockCacheScope(BlockCache* cache) : previous_(t_cache) { t_cache = cache; }
BlockCacheScope::~BlockCacheScope() { t_cache = previous_; }

}  // namespace rs
