// The micro-benchmarks behind Table 1 of the Cell paper (section 3.4): average SPU cycles to
// load 8 bytes from main memory through the software cache, a synchronous / asynchronous DMA,
// and a synchronous / asynchronous atomic (getllar) load, run on the simulated MFC.
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
// (config.load_bench.work_cycles of compute) finds its cell, then the cell's 8-byte record is
// loaded (and read with one LS load, config.costs.ls_load):
//   SW cache:     read through the 4-way cache (records spread over cache_working_set bytes, so
//                 the hit rate is the dataset's: the paper used "a very cache friendly dataset");
//   DMA sync:     MfcGet 8 B + wait, then use;
//   DMA async:    MfcGet 8 B right after each traversal, all 8 waited for in VisitVoxel (each
//                 visit = work_cycles as well);
//   atomic sync:  getllar of the record's 128-B line + status read, then use;
//   atomic async: getllar issued after ray r's traversal, its status read after ray r+1's
//                 traversal (the last ray's after the first visit; one atomic command at a
//                 time).
// Records are drawn with a fixed seed from a table of table_bytes (far larger than any cache).
// Cost per load = (SPU cycles - the work) / loads. Every loaded value is checked against the
// table (throws rs::Error on a mismatch: the benchmark doubles as a functional test).
struct LoadBenchOptions {
  int iterations = 512;                          // x 8 loads per method
  uint32_t table_bytes = 8u << 20;               // 8 MiB of 8-byte records
  uint32_t cache_working_set = 44 * 1024 + 512;  // SW-cache dataset (1.4 x the 32 KiB cache)
  uint64_t seed = 1;
};

LoadCosts MeasureLoadCosts(const SimConfig& config, const LoadBenchOptions& options = {});

}  // namespace rs::sim
