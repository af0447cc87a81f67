// IBM-style SPE software cache (cache-api.h geometry: 128-B lines, 64 sets, 4-way, LRU) in the
// simulated local store, read-only: the shading stage reads materials and texels through it
// (paper 3.7). A miss fetches the line with a synchronous DMA through the SPE's MFC.
#pragma once

#include <cstdint>
#include <vector>

#include "sim/config.h"
#include "sim/local_store.h"
#include "sim/mfc.h"

namespace rs::sim {

struct SoftwareCacheStats {
  uint64_t reads = 0;
  uint64_t hits = 0;
  uint64_t misses = 0;
  void Merge(const SoftwareCacheStats& o);
};

class SoftwareCache {
 public:
  // Allocates the data lines (sets x ways x line_bytes, 128-B aligned) and the tag array in
  // `ls` (throws rs::Error if they do not fit). Validates the geometry (ways 1 or 4, sets and
  // line size powers of two, line >= 16).
  SoftwareCache(const SoftwareCacheConfig& config, LocalStore& ls, Mfc& mfc, SpuClock& clock);

  // cache_rd: copies `bytes` at `ea` into `out` (host memory standing for SPU registers),
  // line by line through the cache. Each line touched costs hit_cycles, and a miss adds
  // miss_extra_cycles plus a synchronous line DMA (its issue, wait and stall are charged as
  // cache time). Returns true if every line hit.
  bool Read(Ea ea, uint32_t bytes, void* out);

  // Forgets every line (e.g. a new frame with new data).
  void Invalidate();
  const SoftwareCacheStats& stats() const { return stats_; }

 private:
  // LS address of the line holding `line_ea` (fetched on a miss); `hit` tells which.
  Lsa Lookup(Ea line_ea, bool* hit);

  SoftwareCacheConfig config_;
  LocalStore& ls_;
  Mfc& mfc_;
  SpuClock& clock_;
  Lsa data_ = 0;
  Lsa tags_ = 0;  // sets x ways x {line ea (8 B)}, the SIMD-compared tag array
  uint32_t line_shift_ = 7;
  std::vector<uint32_t> lru_;  // per line: last-use stamp (LS-resident in IBM's cache)
  uint32_t stamp_ = 0;
  SoftwareCacheStats stats_;
};

}  // namespace rs::sim
