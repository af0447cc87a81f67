// Table 1 micro-benchmarks on the simulated MFC, atomic unit and software cache (load_bench.h).
#include "sim/load_bench.h"

#include <cmath>
#include <cstring>
#include <random>
#include <string>
#include <vector>

#include "include/raystream/raystream.h"
#include "sim/aligned_buffer.h"
#include "sim/local_store.h"
#include "sim/mfc.h"
#include "sim/sw_cache.h"

namespace rs::sim {
namespace {

constexpr int kRays = 8;

struct Bench {
  explicit Bench(const SimConfig& config, uint32_t table_bytes)
      : ls(config.local_store_bytes, 0),
        mic(config.memory.mic_line_cycles),
        mfc(0, ls, memory, mic, clock, config.memory),
        atomic(0, ls, memory, mic, atomic_memory, clock, config.memory) {
    table.Resize(table_bytes);
    uint64_t* t = table.As<uint64_t>();
    for (uint32_t i = 0; i < table_bytes / 8; ++i) t[i] = 0x9E3779B97F4A7C15ull * (i + 1);
    table_ea = memory.Register(table.data(), table.size(), "record table");
    slots = ls.Allocate("load slots", kRays * 128, 128);
  }
  Ea RecordEa(uint32_t index) const { return table_ea + uint64_t{index} * 8; }
  uint64_t Expected(uint32_t index) const { return table.As<uint64_t>()[index]; }
  void Check(uint64_t got, uint32_t index, const char* method) const {
    if (got != Expected(index)) {
      throw Error(std::string("load benchmark ") + method + ": record " + std::to_string(index) +
                  " read back wrong");
    }
  }

  LocalStore ls;
  MainMemory memory;
  MemoryController mic;
  AtomicMemory atomic_memory;
  SpuClock clock;
  Mfc mfc;
  AtomicUnit atomic;
  AlignedBuffer table;
  Ea table_ea = 0;
  Lsa slots = 0;
};

}  // namespace

LoadWork LoadWorkOf(const ComputeCosts& costs, double steps_per_visit, double bundles_per_visit) {
  if (!(steps_per_visit >= 0) || !(bundles_per_visit >= 0)) {
    throw Error("load benchmark: counts per visit must be >= 0");
  }
  LoadWork w;
  w.traverse_cycles = static_cast<uint32_t>(
      std::lround(costs.ray_resume + steps_per_visit * costs.dda_step + costs.dda_exit));
  w.visit_cycles = static_cast<uint32_t>(
      std::lround(costs.visit_setup + bundles_per_visit * costs.triangle_bundle));
  return w;
}

LoadCosts MeasureLoadCosts(const SimConfig& config, const LoadBenchOptions& options) {
  ValidateConfig(config);
  const uint32_t working_set =
      options.cache_working_set != 0
          ? options.cache_working_set
          : config.sw_cache.sets * config.sw_cache.ways * config.sw_cache.line_bytes;
  if (options.iterations < 1 || options.table_bytes < 4096 || working_set < 128 ||
      working_set > options.table_bytes) {
    throw Error("load benchmark: bad options (iterations >= 1, table >= 4 KiB, working set in "
                "[128 B, table])");
  }
  if (options.traverse_cycles < 1 || options.visit_cycles < 1) {
    throw Error("load benchmark: traverse_cycles and visit_cycles must be >= 1 (LoadWorkOf)");
  }
  const uint32_t records = options.table_bytes / 8;
  const uint32_t cache_records = working_set / 8;
  const uint64_t loads = uint64_t(options.iterations) * kRays;
  const uint32_t w = options.traverse_cycles;
  const uint32_t v = options.visit_cycles;
  const uint32_t use = config.costs.ls_load;  // reading the loaded record
  const uint64_t work = loads * (uint64_t{w} + v);  // traversal + visit per ray
  LoadCosts out;
  out.loads = loads;

  // Same record sequence for every method.
  std::mt19937_64 rng(options.seed);
  std::vector<uint32_t> index(loads), cached_index(loads);
  for (uint64_t i = 0; i < loads; ++i) {
    index[i] = static_cast<uint32_t>(rng() % records);
    cached_index[i] = static_cast<uint32_t>(rng() % cache_records);
  }

  {  // SW cache
    Bench b(config, options.table_bytes);
    SoftwareCache cache(config.sw_cache, b.ls, b.mfc, b.clock);
    // Warm up on the same dataset so the figure is the steady state.
    for (uint64_t i = 0; i < loads; ++i) {
      uint64_t value;
      cache.Read(b.RecordEa(cached_index[(i * 7919) % loads]), 8, &value);
    }
    const SoftwareCacheStats before = cache.stats();
    const uint64_t t0 = b.clock.now();
    for (uint64_t i = 0; i < loads; ++i) {
      b.clock.Charge(Cost::kCompute, w);
      uint64_t value = 0;
      cache.Read(b.RecordEa(cached_index[i]), 8, &value);
      b.Check(value, cached_index[i], "SW cache");
      b.clock.Charge(Cost::kCompute, v);
    }
    out.cycles[0] = double(b.clock.now() - t0 - work) / double(loads);
    out.sw_cache_hit_rate =
        double(cache.stats().hits - before.hits) / double(cache.stats().reads - before.reads);
  }
  {  // DMA sync
    Bench b(config, options.table_bytes);
    for (uint64_t i = 0; i < loads; ++i) {
      const uint32_t r = uint32_t(i % kRays);
      const Lsa ls = b.slots + r * 128 + uint32_t(b.RecordEa(index[i]) & 15);
      b.clock.Charge(Cost::kCompute, w);
      b.mfc.MfcGet(ls, b.RecordEa(index[i]), 8, r);
      b.mfc.WaitTagsAll(1u << r);
      b.clock.Charge(Cost::kDma, use);
      b.Check(*b.ls.As<uint64_t>(ls), index[i], "DMA sync");
      b.clock.Charge(Cost::kCompute, v);
    }
    out.cycles[1] = double(b.clock.now() - work) / double(loads);
  }
  {  // DMA async
    Bench b(config, options.table_bytes);
    for (uint64_t it = 0; it < loads; it += kRays) {
      for (uint32_t r = 0; r < kRays; ++r) {
        const Ea ea = b.RecordEa(index[it + r]);
        b.clock.Charge(Cost::kCompute, w);
        b.mfc.MfcGet(b.slots + r * 128 + uint32_t(ea & 15), ea, 8, r);
      }
      for (uint32_t r = 0; r < kRays; ++r) {
        const Ea ea = b.RecordEa(index[it + r]);
        b.mfc.WaitTagsAll(1u << r);
        b.clock.Charge(Cost::kDma, use);
        b.Check(*b.ls.As<uint64_t>(b.slots + r * 128 + uint32_t(ea & 15)), index[it + r],
                "DMA async");
        b.clock.Charge(Cost::kCompute, v);
      }
    }
    out.cycles[2] = double(b.clock.now() - work) / double(loads);
  }
  {  // atomic sync
    Bench b(config, options.table_bytes);
    for (uint64_t i = 0; i < loads; ++i) {
      const uint32_t r = uint32_t(i % kRays);
      const Ea ea = b.RecordEa(index[i]);
      b.clock.Charge(Cost::kCompute, w);
      b.atomic.Getllar(b.slots + r * 128, ea & ~Ea{127});
      b.atomic.ReadStatus();
      b.clock.Charge(Cost::kAtomic, use);
      b.Check(*b.ls.As<uint64_t>(b.slots + r * 128 + uint32_t(ea & 127)), index[i], "atomic sync");
      b.clock.Charge(Cost::kCompute, v);
    }
    out.cycles[3] = double(b.clock.now() - work) / double(loads);
  }
  {  // atomic async
    Bench b(config, options.table_bytes);
    for (uint64_t it = 0; it < loads; it += kRays) {
      auto complete = [&](uint32_t q) {
        const Ea ea = b.RecordEa(index[it + q]);
        b.atomic.ReadStatus();
        b.clock.Charge(Cost::kAtomic, use);
        b.Check(*b.ls.As<uint64_t>(b.slots + q * 128 + uint32_t(ea & 127)), index[it + q],
                "atomic async");
      };
      for (uint32_t r = 0; r < kRays; ++r) {
        b.clock.Charge(Cost::kCompute, w);  // traversal of ray r
        if (r > 0) complete(r - 1);         // ray r-1's line arrived while ray r traversed
        b.atomic.Getllar(b.slots + r * 128, b.RecordEa(index[it + r]) & ~Ea{127});
      }
      b.clock.Charge(Cost::kCompute, v);  // visit of ray 0 hides the last ray's load
      complete(kRays - 1);
      for (uint32_t r = 1; r < kRays; ++r) b.clock.Charge(Cost::kCompute, v);  // other visits
    }
    out.cycles[4] = double(b.clock.now() - work) / double(loads);
  }
  return out;
}

}  // namespace rs::sim
