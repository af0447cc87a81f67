// Threads of the structure builds (BuildOptions::build_threads): run one body per part on
// std::threads and split index ranges into contiguous parts. Build code only; the traversal
// kernels never start threads. Every threaded pass writes disjoint outputs per part and merges
// them in part order, so a build gives the same structure for any thread count.
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

// Calls body(t) for t in [0, parts): part 0 on the calling thread, the others on new threads.
// The first exception thrown by a part (in part order) is rethrown after all have finished.
// The parts allocate through the calling thread's BlockCache (block_memory.h).
template <class Body>
void RunParts(int parts, Body&& body) {
  if (parts <= 1) {
    body(0);
    return;
  }
  std::vector<std::exception_ptr> errors(static_cast<size_t>(parts));
  std::vector<std::thread> threads;
  threads.reserve(size_t(parts - 1));
  BlockCache* const cache = CurrentBlockCache();
  auto run = [&](int t) {
    const BlockCacheScope scope(cache);
    try {
      body(t);
    } catch (...) {
      errors[size_t(t)] = std::current_exception();
    }
  };
  for (int t = 1; t < parts; ++t) {
    try {
      threads.emplace_back(run, t);
    } catch (...) {  // no thread: run that part here
      run(t);
    }
  }
  run(0);
  for (std::thread& th : threads) th.join();
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
