// Calibration of the simulated memory system against Table 1 of the Cell paper: the average
// cycles to load 8 bytes through the software cache, a synchronous / asynchronous DMA and a
// synchronous / asynchronous atomic load must land within +-10 % of 315 / 986 / 609 / 470 / 269
// and keep the paper's order. Also checks the costs move the right way when the model changes.
#include <doctest/doctest.h>

#include <cmath>
#include <string>

#include "include/raystream/raystream.h"
#include "sim/load_bench.h"

namespace rs::sim {
namespace {

TEST_CASE("Table 1 load costs within 10 % of the paper") {
  const LoadCosts c = MeasureLoadCosts(SimConfig{});
  MESSAGE("simulated ", c.cycles[0], " / ", c.cycles[1], " / ", c.cycles[2], " / ", c.cycles[3],
          " / ", c.cycles[4], " cycles (paper 315 / 986 / 609 / 470 / 269), SW-cache hit rate ",
          c.sw_cache_hit_rate);
  for (int i = 0; i < 5; ++i) {
    INFO(std::string(kLoadCostNames[i]), ": simulated ", c.cycles[i], " cycles, paper ",
         kPaperLoadCosts[i]);
    CHECK(std::fabs(c.cycles[i] - kPaperLoadCosts[i]) <= 0.10 * kPaperLoadCosts[i]);
  }
  // The paper's ranking: atomic async < SW cache < atomic sync < DMA async < DMA sync.
  CHECK(c.cycles[4] < c.cycles[0]);
  CHECK(c.cycles[0] < c.cycles[3]);
  CHECK(c.cycles[3] < c.cycles[2]);
  CHECK(c.cycles[2] < c.cycles[1]);
  CHECK(c.sw_cache_hit_rate > 0.6);
  CHECK(c.sw_cache_hit_rate < 0.85);
}

TEST_CASE("load costs follow the model's parameters") {
  const LoadCosts base = MeasureLoadCosts(SimConfig{});
  {
    SimConfig c;
    c.memory.dma_latency_cycles += 100;
    const LoadCosts slow = MeasureLoadCosts(c);
    CHECK(slow.cycles[1] == doctest::Approx(base.cycles[1] + 100).epsilon(0.01));
    CHECK(slow.cycles[3] == doctest::Approx(base.cycles[3]).epsilon(0.001));  // atomics unchanged
  }
  {
    // Pipelined DMA (16 commands in flight per SPE, as Kistler et al. measured on a quiet
    // machine) hides nearly all latency of the asynchronous loads.
    SimConfig c;
    c.memory.mfc_bus_slots = 16;
    const LoadCosts piped = MeasureLoadCosts(c);
    CHECK(piped.cycles[2] < 0.3 * base.cycles[2]);
    CHECK(piped.cycles[1] == doctest::Approx(base.cycles[1]).epsilon(0.01));
  }
  {
    // A cache that holds the whole working set: only the hit cost remains.
    LoadBenchOptions o;
    o.cache_working_set = 16 * 1024;
    const LoadCosts warm = MeasureLoadCosts(SimConfig{}, o);
    CHECK(warm.sw_cache_hit_rate == 1.0);
    CHECK(warm.cycles[0] == doctest::Approx(28.0).epsilon(0.001));
  }
  CHECK_THROWS_AS(MeasureLoadCosts(SimConfig{}, LoadBenchOptions{.iterations = 0}), Error);
}

}  // namespace
}  // namespace rs::sim
