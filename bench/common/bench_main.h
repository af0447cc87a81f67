// The main() of the Google Benchmark suites: their flags (an unknown one is an error), the
// tsc_ghz context every report carries (tsc.h), the suite's own context lines, its
// registrations and the run.
#pragma once

#include <benchmark/benchmark.h>

#include <hwy/targets.h>

#include <cstdio>
#include <cstdlib>
#include <initializer_list>
#include <string>
#include <utility>

#include "bench/common/tsc.h"

namespace rs::bench {

// RS_BENCH_ISA=avx2: the raystream kernels run their AVX2 target (AVX-512 disabled for
// HWY_DYNAMIC_DISPATCH) and the Embree peer is created with isa=avx2, for the AVX2 table on an
// AVX-512 machine. Adds "isa" to the benchmark context. Unset: the best target of the CPU.
inline void ApplyIsaEnv() {
  const char* isa = std::getenv("RS_BENCH_ISA");
  if (isa == nullptr || std::string(isa).empty()) return;
  if (std::string(isa) != "avx2") {
    std::fprintf(stderr, "RS_BENCH_ISA: only avx2 is known, not '%s'\n", isa);
    std::exit(2);
  }
  hwy::DisableTargets(HWY_AVX3 | HWY_AVX3_DL);
  benchmark::AddCustomContext("isa", "avx2 (RS_BENCH_ISA)");
}

// Adds "tsc_ghz" (TscGhz, three decimals) to the benchmark context.
inline void AddTscContext() {
  char ghz[32];
  std::snprintf(ghz, sizeof(ghz), "%.3f", TscGhz());
  benchmark::AddCustomContext("tsc_ghz", ghz);
}

inline int RunBenchmarkMain(int argc, char** argv,
                            std::initializer_list<std::pair<const char*, std::string>> context,
                            void (*register_all)()) {
  benchmark::Initialize(&argc, argv);
  if (benchmark::ReportUnrecognizedArguments(argc, argv)) return 1;
  AddTscContext();
  ApplyIsaEnv();
  for (const auto& [key, value] : context) benchmark::AddCustomContext(key, value);
  register_all();
  benchmark::RunSpecifiedBenchmarks();
  benchmark::Shutdown();
  return 0;
}

}  // namespace rs::bench
