// The load-cost micro-benchmarks of the Cell paper's Table 1 (sim/load_bench.h) as a probe of the
// simulated memory system: its own properties and the hardware facts it is built from
// (shared/CELL-FACTS.md), never the paper's five figures (bench/sim/load_cost_bench.cc reports
// those). A synchronous load costs one 128-B line round trip (Kistler et al.: < 100 ns = 320
// cycles) plus the LS load; asynchronous loads never cost more and hide the line behind enough
// work; every cost moves the right way, and only the right costs move, when a parameter changes;
// the software cache costs its hit time on a dataset that fits and a line fetch per miss otherwise.
#include <doctest/doctest.h>

#include <cstdint>
#include <string>

#include "include/raystream/raystream.h"
#include "sim/load_bench.h"

namespace rs::sim {
namespace {

constexpr int kSwCache = 0, kDmaSync = 1, kDmaAsync = 2, kAtomicSync = 3, kAtomicAsync = 4;

// Work per ray from the compute model at 4 cell steps and 2 triangle bundles per visit
// (132 + 120 cycles): less than a line round trip, so asynchronous loads still wait a little.
LoadBenchOptions Options(double steps = 4, double bundles = 2) {
  const LoadWork w = LoadWorkOf(ComputeCosts{}, steps, bundles);
  LoadBenchOptions o;
  o.traverse_cycles = w.traverse_cycles;
  o.visit_cycles = w.visit_cycles;
  return o;
}

LoadBenchOptions Work(uint32_t traverse, uint32_t visit) {
  LoadBenchOptions o;
  o.traverse_cycles = traverse;
  o.visit_cycles = visit;
  return o;
}

void Log(const char* what, const LoadCosts& c) {
  MESSAGE(std::string(what), ": ", c.cycles[0], " / ", c.cycles[1], " / ", c.cycles[2], " / ", c.cycles[3],
          " / ", c.cycles[4], " cycles (SW cache / DMA sync / async / atomic sync / async)");
}

TEST_CASE("the default timing adds up to one 128-B line in 320 cycles") {
  const MemoryTiming t;
  // Kistler et al.: < 100 ns per line at 3.2 GHz (CELL-FACTS section 1).
  CHECK(MemoryTiming::kLineRoundTripCycles == 320);
  CHECK(100e-9 * SimConfig{}.clock_hz == doctest::Approx(320.0));
  CHECK(t.dma_issue_cycles + t.mic_line_cycles + t.dma_latency_cycles + t.dma_wait_cycles == 320);
  CHECK(t.atomic_issue_cycles + t.mic_line_cycles + t.atomic_latency_cycles +
            t.atomic_status_cycles ==
        320);
  // 128 B at 25.6 GB/s = 8 B per cycle.
  CHECK(double(t.mic_line_cycles) == doctest::Approx(128.0 / (25.6e9 / SimConfig{}.clock_hz)));
  CHECK(t.mfc_bus_slots == t.mfc_queue_depth);  // commands overlap up to the 16-entry queue
  CHECK(t.mfc_queue_depth == 16);
}

TEST_CASE("synchronous loads cost one line round trip plus the LS load") {
  const SimConfig config;
  const uint32_t ls = config.costs.ls_load;
  const uint32_t slot = config.memory.mic_line_cycles;  // wait for the MIC's next line slot
  for (const double steps : {1.0, 4.0, 12.0}) {
    INFO("cell steps per visit ", steps);
    const LoadCosts c = MeasureLoadCosts(config, Options(steps));
    Log("sync", c);
    for (const int m : {kDmaSync, kAtomicSync}) {
      INFO(kLoadCostNames[m]);
      CHECK(c.cycles[m] >= 320 + ls);
      CHECK(c.cycles[m] < 320 + ls + slot);
    }
  }
}

TEST_CASE("asynchronous loads never cost more and hide the line behind enough work") {
  const SimConfig config;
  const MemoryTiming& t = config.memory;
  double last_dma = 1e30, last_atomic = 1e30;
  for (const uint32_t work : {20u, 60u, 120u, 200u, 320u, 400u}) {
    INFO("traverse and visit cycles ", work);
    const LoadCosts c = MeasureLoadCosts(config, Work(work, work));
    CHECK(c.cycles[kDmaAsync] <= c.cycles[kDmaSync]);
    CHECK(c.cycles[kAtomicAsync] <= c.cycles[kAtomicSync]);
    // More work between issue and use hides more of the line.
    CHECK(c.cycles[kDmaAsync] <= last_dma);
    CHECK(c.cycles[kAtomicAsync] <= last_atomic);
    last_dma = c.cycles[kDmaAsync];
    last_atomic = c.cycles[kAtomicAsync];
  }
  // A traversal and a visit of a whole line round trip: only issue, status and use are left.
  const LoadCosts hidden = MeasureLoadCosts(config, Work(320, 320));
  Log("hidden", hidden);
  CHECK(hidden.cycles[kDmaAsync] ==
        doctest::Approx(t.dma_issue_cycles + t.dma_wait_cycles + config.costs.ls_load));
  CHECK(hidden.cycles[kAtomicAsync] ==
        doctest::Approx(t.atomic_issue_cycles + t.atomic_status_cycles + config.costs.ls_load));
  // Little work: the 8 gets overlap each other (16 in flight), the atomic loads cannot (one
  // atomic command at a time), so DMA async is the cheaper of the two.
  const LoadCosts busy = MeasureLoadCosts(config, Work(20, 20));
  Log("little work", busy);
  CHECK(busy.cycles[kDmaAsync] < busy.cycles[kAtomicAsync]);
  CHECK(busy.cycles[kDmaAsync] < 0.5 * busy.cycles[kDmaSync]);
}

TEST_CASE("each cost follows its own parameters and no others") {
  const LoadBenchOptions o = Options();
  const LoadCosts base = MeasureLoadCosts(SimConfig{}, o);
  Log("base", base);
  // +160 cycles (a multiple of the MIC's 16-cycle slot grid, so slot waits stay the same).
  {
    SimConfig c;
    c.memory.dma_latency_cycles += 160;
    const LoadCosts slow = MeasureLoadCosts(c, o);
    CHECK(slow.cycles[kDmaSync] == doctest::Approx(base.cycles[kDmaSync] + 160));
    CHECK(slow.cycles[kDmaAsync] >= base.cycles[kDmaAsync]);
    CHECK(slow.cycles[kAtomicSync] == base.cycles[kAtomicSync]);
    CHECK(slow.cycles[kAtomicAsync] == base.cycles[kAtomicAsync]);
    CHECK(slow.cycles[kSwCache] == base.cycles[kSwCache]);  // the dataset fits: no miss DMA
  }
  {
    SimConfig c;
    c.memory.atomic_latency_cycles += 160;
    const LoadCosts slow = MeasureLoadCosts(c, o);
    CHECK(slow.cycles[kAtomicSync] == doctest::Approx(base.cycles[kAtomicSync] + 160));
    CHECK(slow.cycles[kAtomicAsync] > base.cycles[kAtomicAsync]);
    CHECK(slow.cycles[kDmaSync] == base.cycles[kDmaSync]);
    CHECK(slow.cycles[kDmaAsync] == base.cycles[kDmaAsync]);
  }
  {
    // Issue costs are paid in full by every method that issues.
    SimConfig c;
    c.memory.dma_issue_cycles += 16;
    c.memory.atomic_issue_cycles += 16;
    const LoadCosts slow = MeasureLoadCosts(c, o);
    for (const int m : {kDmaSync, kDmaAsync, kAtomicSync, kAtomicAsync}) {
      INFO(kLoadCostNames[m]);
      CHECK(slow.cycles[m] >= base.cycles[m] + 16 - 1e-9);
    }
  }
  {
    // A slower memory (half the bandwidth) makes every line longer.
    SimConfig c;
    c.memory.mic_line_cycles = 32;
    const LoadCosts slow = MeasureLoadCosts(c, o);
    CHECK(slow.cycles[kDmaSync] > base.cycles[kDmaSync]);
    CHECK(slow.cycles[kAtomicSync] > base.cycles[kAtomicSync]);
  }
  {
    // One DMA at a time per SPE: the synchronous load is unchanged, the asynchronous ones queue
    // behind each other.
    SimConfig c;
    c.memory.mfc_bus_slots = 1;
    const LoadCosts serial = MeasureLoadCosts(c, Work(20, 20));
    const LoadCosts piped = MeasureLoadCosts(SimConfig{}, Work(20, 20));
    CHECK(serial.cycles[kDmaSync] == piped.cycles[kDmaSync]);
    CHECK(serial.cycles[kDmaAsync] > 2 * piped.cycles[kDmaAsync]);
    CHECK(serial.cycles[kAtomicAsync] == piped.cycles[kAtomicAsync]);
  }
  {
    // The LS load that reads the record is paid once per load by every method but the cache.
    SimConfig c;
    c.costs.ls_load += 10;
    const LoadCosts slow = MeasureLoadCosts(c, o);
    for (const int m : {kDmaSync, kAtomicSync}) {
      INFO(kLoadCostNames[m]);
      CHECK(slow.cycles[m] == doctest::Approx(base.cycles[m] + 10).epsilon(0.05));
    }
  }
}

TEST_CASE("software cache: its hit time when the data fits, a line fetch per miss otherwise") {
  const SimConfig config;
  const SoftwareCacheConfig& sc = config.sw_cache;
  const uint32_t capacity = sc.sets * sc.ways * sc.line_bytes;
  CHECK(capacity == 32 * 1024);  // IBM cache-api.h defaults
  const LoadCosts fits = MeasureLoadCosts(config, Options());
  CHECK(fits.sw_cache_hit_rate == 1.0);
  CHECK(fits.cycles[kSwCache] == doctest::Approx(sc.hit_cycles));
  // A miss: the lookup, the miss handling and one synchronous 128-B line (320 cycles, plus the
  // wait for the MIC's slot).
  const double miss_low = sc.miss_extra_cycles + 320.0;
  const double miss_high = miss_low + config.memory.mic_line_cycles;
  double last_rate = 1.0, last_cost = fits.cycles[kSwCache];
  for (const uint32_t set : {2 * capacity, 8 * capacity, 64 * capacity}) {
    INFO("working set ", set, " bytes");
    LoadBenchOptions o = Options();
    o.cache_working_set = set;
    const LoadCosts c = MeasureLoadCosts(config, o);
    const double miss_rate = 1.0 - c.sw_cache_hit_rate;
    CHECK(c.sw_cache_hit_rate < last_rate);
    CHECK(c.cycles[kSwCache] > last_cost);
    CHECK(c.cycles[kSwCache] >= sc.hit_cycles + miss_rate * miss_low - 1e-9);
    CHECK(c.cycles[kSwCache] <= sc.hit_cycles + miss_rate * miss_high + 1e-9);
    // The other methods do not use the cache.
    CHECK(c.cycles[kDmaSync] == fits.cycles[kDmaSync]);
    last_rate = c.sw_cache_hit_rate;
    last_cost = c.cycles[kSwCache];
  }
}

TEST_CASE("work per visit from the compute model") {
  const ComputeCosts costs;
  const LoadWork w = LoadWorkOf(costs, 4, 2);
  CHECK(w.traverse_cycles == costs.ray_resume + 4 * costs.dda_step + costs.dda_exit);
  CHECK(w.visit_cycles == costs.visit_setup + 2 * costs.triangle_bundle);
  CHECK(LoadWorkOf(costs, 5, 2).traverse_cycles == w.traverse_cycles + costs.dda_step);
  CHECK(LoadWorkOf(costs, 4, 3).visit_cycles == w.visit_cycles + costs.triangle_bundle);
  CHECK_THROWS_AS(LoadWorkOf(costs, -1, 2), Error);
}

TEST_CASE("bad options are refused") {
  LoadBenchOptions o = Options();
  o.iterations = 0;
  CHECK_THROWS_AS(MeasureLoadCosts(SimConfig{}, o), Error);
  CHECK_THROWS_AS(MeasureLoadCosts(SimConfig{}, LoadBenchOptions{}), Error);  // no work given
  o = Options();
  o.cache_working_set = o.table_bytes * 2;
  CHECK_THROWS_AS(MeasureLoadCosts(SimConfig{}, o), Error);
}

}  // namespace
}  // namespace rs::sim
