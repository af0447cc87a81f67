// The memory of the library's large aligned arrays (AllocateAlignedOrThrow, the builds'
// AllocateBuildArray): hwy::AllocateAligned's alloc / free hooks. Blocks of 1 MiB and more are
// mapped from a 2 MiB boundary with transparent huge pages advised (a fresh 4 KiB page costs a
// fault each, measured 11-15 us in this project's VMs; a huge page one per 2 MiB), a tail of
// 1 MiB or more rounded up to a whole huge page; smaller ones come from malloc. A BlockCache keeps the blocks of a structure that is rebuilt
// (Accel::Rebuild): a rebuild of the same size takes its arrays' blocks back instead of fresh
// pages.
#pragma once

#include <hwy/aligned_allocator.h>

#include <cstddef>
#include <cstdint>
#include <mutex>
#include <vector>

namespace rs {

inline constexpr size_t kHugeBlockBytes = size_t{2} << 20;

// Asks the kernel for transparent huge pages (madvise MADV_HUGEPAGE) on the whole 2 MiB pages
// inside [p, p + bytes), for an array of at least kHugePageMinBytes about to be written for the
// first time (an array not from a block, e.g. a std::vector's). A fresh 4 KiB page costs a fault
// each (measured 11-15 us in this project's VMs: a cold grid or light buffer build paid 4-7x the
// warm one in faults); a huge page one per 2 MiB. Advice only: without THP (or on other
// systems) nothing changes.
inline constexpr size_t kHugePageMinBytes = size_t{4} << 20;
void AdviseHugePages(void* p, size_t bytes);

class BlockCache;

// hwy::AllocPtr / FreePtr: `opaque` is the BlockCache the block is taken from and returned to,
// or null (straight to the system). AllocateBlock returns null when out of memory.
void* AllocateBlock(void* opaque, size_t bytes);
void FreeBlock(void* opaque, void* block);

// Free blocks kept for the next build of one structure. A block freed into the cache is kept,
// tagged with the current build, and reused by a later request it fits without wasting more
// than a quarter. A rebuild frees the old arrays into the cache, calls BeginBuild, builds (taking
// blocks back) and calls EndBuild, which releases the old blocks it did not take (a rebuild of a
// smaller structure does not keep the larger one's memory) and keeps, if asked, those freed
// during the build (its temporaries) for the next one. Every array allocated through the cache
// must be freed before the cache is destroyed (declare the cache before the arrays).
// Thread-safe (a build's threads share it).
class BlockCache {
 public:
  BlockCache() = default;
  BlockCache(const BlockCache&) = delete;
  BlockCache& operator=(const BlockCache&) = delete;
  ~BlockCache();

  void BeginBuild();
  // keep_freed: keep the blocks this build freed (its temporaries) for the next one; false
  // releases every free block.
  void EndBuild(bool keep_freed);
  size_t kept_bytes() const;  // free blocks held

 private:
  friend void* AllocateBlock(void* opaque, size_t bytes);
  friend void FreeBlock(void* opaque, void* block);
  struct Kept {
    void* block;
    size_t capacity;
    size_t requested;
    uint64_t generation;
  };
  void* Take(size_t bytes);
  void Keep(void* block);

  mutable std::mutex mutex_;
  std::vector<Kept> free_;
  uint64_t generation_ = 0;
};

// Blocks taken from the system so far, by every thread (tests: a rebuild from the cache takes
// none).
size_t SystemBlockCount();

// The cache this thread's large arrays are allocated through (null: none). Set for the scope of
// a build; RunParts (kernels/build_threads.h) hands it to the build's threads.
BlockCache* CurrentBlockCache();
class BlockCacheScope {
 public:
  explicit BlockCacheScope(BlockCache* cache);
  ~BlockCacheScope();
  BlockCacheScope(const BlockCacheScope&) = delete;
  BlockCacheScope& operator=(const BlockCacheScope&) = delete;

 private:
  BlockCache* previous_;
};

// n elements of T, 64-B aligned, from the current thread's BlockCache (or the system); null
// when out of memory.
template <typename T>
hwy::AlignedFreeUniquePtr<T[]> AllocateBlockArray(size_t n) {
  return hwy::AllocateAligned<T>(n, &AllocateBlock, &FreeBlock, CurrentBlockCache());
}

}  // namespace rs
