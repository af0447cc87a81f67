// Time-stamp counter helpers shared by the kernel benchmarks. rdtsc counts reference ticks at a
// constant rate (TscGhz), not core cycles: hardware performance counters (cycles, instructions)
// are not available on these machines (KVM guest without a PMU), so cycle figures are ticks, and
// instruction counts come from callgrind (bench/scripts/run_callgrind.sh).
#pragma once

#include <time.h>

#include <chrono>
#include <cstdint>

#if defined(__x86_64__) || defined(__i386__)
#include <x86intrin.h>
#define RS_HAVE_RDTSC 1
#endif

namespace rs::bench {

// rdtsc where there is one, steady_clock nanoseconds elsewhere.
inline uint64_t Ticks() {
#ifdef RS_HAVE_RDTSC
  return __rdtsc();
#else
  return static_cast<uint64_t>(std::chrono::steady_clock::now().time_since_epoch().count());
#endif
}

// Ticks per nanosecond, measured once against steady_clock over 50 ms.
inline double TscGhz() {
  static const double ghz = [] {
    const auto t0 = std::chrono::steady_clock::now();
    const uint64_t c0 = Ticks();
    while (std::chrono::steady_clock::now() - t0 < std::chrono::milliseconds(50)) {
    }
    const uint64_t c1 = Ticks();
    const double ns =
        std::chrono::duration<double, std::nano>(std::chrono::steady_clock::now() - t0).count();
    return static_cast<double>(c1 - c0) / ns;
  }();
  return ghz;
}

// This thread's CPU time: unlike wall-clock ticks it excludes time the thread was descheduled.
inline double ThreadCpuSeconds() {
  timespec ts;
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return static_cast<double>(ts.tv_sec) + 1e-9 * static_cast<double>(ts.tv_nsec);
}

}  // namespace rs::bench
