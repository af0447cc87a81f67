// Read-only 4-way software cache in the simulated local store (see sw_cache.h).
#include "sim/sw_cache.h"

#include <algorithm>
#include <cstring>

#include "include/raystream/raystream.h"

namespace rs::sim {
namespace {

bool PowerOfTwo(uint32_t x) { return x != 0 && (x & (x - 1)) == 0; }

constexpr Ea kInvalidLine = ~Ea{0};

}  // namespace

void SoftwareCacheStats::Merge(const SoftwareCacheStats& o) {
  reads += o.reads;
  hits += o.hits;
  misses += o.misses;
}

SoftwareCache::SoftwareCache(const SoftwareCacheConfig& config, LocalStore& ls, Mfc& mfc,
                             SpuClock& clock)
    : config_(config), ls_(ls), mfc_(mfc), clock_(clock) {
  if (config.ways != 1 && config.ways != 4) {
    throw Error("software cache: ways must be 1 or 4 (IBM cache-api.h), got " +
                std::to_string(config.ways));
  }
  if (!PowerOfTwo(config.sets) || !PowerOfTwo(config.line_bytes) || config.line_bytes < 16 ||
      config.line_bytes > kMaxDmaSize) {
    throw Error("software cache: sets and line size must be powers of two, line 16..16384 B");
  }
  if (config.tag >= kNumTags) throw Error("software cache: DMA tag must be 0..31");
  line_shift_ = static_cast<uint32_t>(__builtin_ctz(config.line_bytes));
  const uint64_t lines = uint64_t{config.sets} * config.ways;
  data_ = ls.Allocate("software cache lines", lines * config.line_bytes, 128);
  tags_ = ls.Allocate("software cache tags", lines * sizeof(Ea), 16);
  lru_.assign(lines, 0);
  Invalidate();
}

void SoftwareCache::Invalidate() {
  const uint64_t lines = uint64_t{config_.sets} * config_.ways;
  Ea* tags = ls_.As<Ea>(tags_, lines);
  std::fill(tags, tags + lines, kInvalidLine);
  std::fill(lru_.begin(), lru_.end(), 0);
  stamp_ = 0;
}

Lsa SoftwareCache::Lookup(Ea line_ea, bool* hit) {
  const uint32_t set = static_cast<uint32_t>(line_ea >> line_shift_) & (config_.sets - 1);
  const uint32_t base = set * config_.ways;
  Ea* tags = ls_.As<Ea>(tags_ + base * sizeof(Ea), config_.ways);
  ++stamp_;
  uint32_t victim = 0;
  for (uint32_t w = 0; w < config_.ways; ++w) {
    if (tags[w] == line_ea) {
      lru_[base + w] = stamp_;
      *hit = true;
      return data_ + (base + w) * config_.line_bytes;
    }
    if (lru_[base + w] < lru_[base + victim]) victim = w;
  }
  // Miss: the LRU way gets the line with a synchronous DMA (read-only cache: no write-back).
  *hit = false;
  const Lsa line = data_ + (base + victim) * config_.line_bytes;
  clock_.Charge(Cost::kCache, config_.miss_extra_cycles);
  mfc_.MfcGet(line, line_ea, config_.line_bytes, config_.tag);
  mfc_.WaitTagsAll(1u << config_.tag);
  tags[victim] = line_ea;
  lru_[base + victim] = stamp_;
  return line;
}

bool SoftwareCache::Read(Ea ea, uint32_t bytes, void* out) {
  // Everything the cache does (including its MFC traffic) is cache time.
  const int old = clock_.Redirect(static_cast<int>(Cost::kCache));
  bool all_hit = true;
  uint8_t* dst = static_cast<uint8_t*>(out);
  while (bytes > 0) {
    const Ea line_ea = ea & ~Ea{config_.line_bytes - 1};
    const uint32_t offset = static_cast<uint32_t>(ea - line_ea);
    const uint32_t n = std::min(bytes, config_.line_bytes - offset);
    bool hit = false;
    clock_.Charge(Cost::kCache, config_.hit_cycles);
    const Lsa line = Lookup(line_ea, &hit);
    ++stats_.reads;
    (hit ? stats_.hits : stats_.misses) += 1;
    all_hit &= hit;
    std::memcpy(dst, ls_.Bytes(line + offset, n), n);
    dst += n;
    ea += n;
    bytes -= n;
  }
  clock_.Redirect(old);
  return all_hit;
}

}  // namespace rs::sim
