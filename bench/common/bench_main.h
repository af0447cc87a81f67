// The main() of the Google Benchmark suites: their flags (an unknown one is an error), the
// tsc_ghz context every report carries (tsc.h), the suite's own context lines, its
// registrations and the run.
#pragma once

#include <benchmark/benchmark.h>

#include <cstdio>
#include <initializer_list>
#include <string>
#include <utility>

#include "bench/common/tsc.h"

namespace rs::bench {

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
  for (const auto& [key, value] : context) benchmark::AddCustomContext(key, value);
  register_all();
  benchmark::RunSpecifiedBenchmarks();
  benchmark::Shutdown();
  return 0;
}

}  // namespace rs::bench
