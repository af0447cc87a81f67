// The micro-benchmarks behind Table 1 of the Cell paper (section 3.4): average SPU cycles to
// load 8 bytes from main memory through the software cache, a synchronous / asynchronous DMA,
// and a synchronous / asynchronous atomic (getllar) load, run on the simulated MFC. A probe of
// the memory model for tests/sim/load_cost_test and bench/sim/load_cost_bench (its own static
// library, not part of libraystream).
#pragma once

#include <cstdint>

#include "sim/config.h"

namespace rs::sim {

// The paper's Table 1, in the order of LoadCosts.
inline constexpr double kPaperLoadCosts[5] = {315, 986, 609, 470, 269};
inline constexpr const char* kLoadCostNames[5] = {"SW-Cache", "DMA sync.", "DMA async.",
                                                  "Atomic sync.", "Atomic async."};

struct LoadCosts {
  double cycles[5] = {};  // SW cache, DMA sync, DMA async, atomic sync, atomic async
  double sw_cache_hit_rate = 0;
  uint64_t loads = 0;  // per method
};

// The pattern mirrors the ray pipeline (paper 3.2): per iteration 8 rays; ray r's traversal
// (options.traverse_cycles of compute) finds its cell, then the cell's 8-byte record is loaded
// (and read with one LS load, config.costs.ls_load); each ray's visit of its cell costs
// options.visit_cycles:
//   SW cache:     read through the 4-way cache (records spread over cache_working_set bytes; the
//                 paper used "a very cache friendly dataset", so by default the cache's capacity);
//   DMA sync:     MfcGet 8 B + wait, then use;
//   DMA async:    MfcGet 8 B right after each traversal, all 8 waited for in VisitVoxel;
//   atomic sync:  getllar of the record's 128-B line + status read, then use;
//   atomic async: getllar issued after ray r's traversal, its status read after ray r+1's
//                 traversal (the last ray's after the first visit; one atomic command at a
//                 time).
// Records are drawn with a fixed seed from a table of table_bytes (far larger than any cache).
// Cost per load = (SPU cycles - the work) / loads. Every loaded value is checked against the
// table (throws rs::Error on a mismatch: the benchmark doubles as a functional test).
struct LoadBenchOptions {
  int iterations = 512;             // x 8 loads per method
  uint32_t table_bytes = 8u << 20;  // 8 MiB of 8-byte records
  // SW-cache dataset; 0: the software cache's capacity (sets x ways x line_bytes, 32 KiB by
  // default), the best case the paper's "very cache friendly dataset" stands for.
  uint32_t cache_working_set = 0;
  // SPU work per ray, in cycles: its traversal to the cell (between issuing the load and the
  // first chance to use it) and its visit. Both >= 1; LoadWorkOf derives them from the compute
  // model and a render's counts.
  uint32_t traverse_cycles = 0;
  uint32_t visit_cycles = 0;
  uint64_t seed = 1;
};

// Cycles of the pipeline's compute model per visited cell (ComputeCosts): traversal = ray_resume
// + steps_per_visit x dda_step + dda_exit; visit = visit_setup + bundles_per_visit x
// triangle_bundle. The counts come from a render (cell steps / visits, bundles / visits).
struct LoadWork {
  uint32_t traverse_cycles = 0;
  uint32_t visit_cycles = 0;
};
LoadWork LoadWorkOf(const ComputeCosts& costs, double steps_per_visit, double bundles_per_visit);

// Throws rs::Error for bad options (iterations < 1, a table under 4 KiB, a working set outside
// [128 B, table], zero work) or an invalid config.
LoadCosts MeasureLoadCosts(const SimConfig& config, const LoadBenchOptions& options = {});

}  // namespace rs::sim
