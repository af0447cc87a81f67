// Threads of the structure builds (BuildOptions::build_threads): run one body per part on a
// pool of threads kept between builds, and split index ranges into contiguous parts. Build code
// only; the traversal kernels never start threads. Every threaded pass writes disjoint outputs
// per part and merges them in part order, so a build gives the same structure for any thread
// count.
#pragma once

#include <cstddef>
#include <exception>
#include <thread>
#include <vector>

#include "streams/block_memory.h"  // BlockCacheScope

namespace rs {

// The thread count a build uses for `threads` (BuildOptions::build_threads): at least 1, at
// most 64.
inline int BuildThreadCount(int threads) { return threads < 1 ? 1 : (threads > 64 ? 64 : threads); }

// Runs call(ctx, t) for t in [1, parts) on the process's pool of build threads, kept between
// builds (a thread started per pass cost more than a small build's pass on 2 cores), while the
// calling thread runs call(ctx, 0); returns when all are done. False, having run nothing, if
// the pool is busy (another thread's RunParts), the caller is a pool thread (a nested RunParts)
// or a thread cannot be started: the caller then starts its own threads. call must not throw.
bool RunOnBuildPool(int parts, void (*call)(void*, int), void* ctx);

// Calls body(t) for t in [0, parts): part 0 on the calling thread, the others on the build
// pool's threads (or on new threads, see RunOnBuildPool). The first exception thrown by a part
// (in part order) is rethrown after all have finished. The parts allocate through the calling
// thread's BlockCache (block_memory.h).
template <class Body>
void RunParts(int parts, Body&& body) {
  if (parts <= 1) {
    body(0);
    return;
  }
  std::vector<std::exception_ptr> errors(static_cast<size_t>(parts));
  BlockCache* const cache = CurrentBlockCache();
  auto run = [&](int t) {
    const BlockCacheScope scope(cache);
    try {
      body(t);
    } catch (...) {
      errors[size_t(t)] = std::current_exception();
    }
  };
  using Run = decltype(run);
  const auto call = [](void* ctx, int t) { (*static_cast<Run*>(ctx))(t); };
  if (!RunOnBuildPool(parts, call, &run)) {
    std::vector<std::thread> threads;
    threads.reserve(size_t(parts - 1));
    for (int t = 1; t < parts; ++t) {
      try {
        threads.emplace_back(run, t);
      } catch (...) {  // no thread: run that part here
        run(t);
      }
    }
    run(0);
    for (std::thread& th : threads) th.join();
  }
  for (const std::exception_ptr& e : errors) {
    if (e) std::rethrow_exception(e);
  }
}

// Start of part t of `parts` contiguous parts of [0, n), part boundaries at multiples of `align`
// (the last part ends at n): PartBegin(n, parts, parts, align) = n.
inline size_t PartBegin(size_t n, int parts, int t, size_t align) {
  if (t >= parts) return n;
  const size_t units = (n + align - 1) / align;
  const size_t at = units * size_t(t) / size_t(parts) * align;
  return at < n ? at : n;
}

}  // namespace rs
