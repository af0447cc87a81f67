// The large-array blocks (streams/block_memory.h): alignment and usable size from the system and
// from a BlockCache, reuse of a freed block by a request it fits, BeginBuild / EndBuild releasing
// the blocks a build did not take back, and a cache shared by threads.
#include "streams/block_memory.h"

#include <doctest/doctest.h>

#include <cstdint>
#include <cstring>
#include <thread>
#include <vector>

namespace rs {
namespace {

bool Aligned64(const void* p) { return reinterpret_cast<uintptr_t>(p) % 64 == 0; }

TEST_CASE("blocks from the system: aligned, writable to their end, small and huge") {
  CHECK(CurrentBlockCache() == nullptr);
  for (const size_t n : {size_t{1}, size_t{1000}, size_t{1} << 20, (size_t{5} << 20) + 12345}) {
    INFO("n = ", n);
    auto a = AllocateBlockArray<uint8_t>(n);
    REQUIRE(a);
    CHECK(Aligned64(a.get()));
    std::memset(a.get(), 0xAB, n);
    CHECK(a[n - 1] == 0xAB);
  }
  CHECK(!AllocateBlockArray<uint8_t>(size_t{1} << 63));  // out of memory: null, no throw
}

TEST_CASE("a cache gives a freed block back to a request it fits, and releases old blocks") {
  BlockCache cache;
  const BlockCacheScope scope(&cache);
  CHECK(CurrentBlockCache() == &cache);
  const size_t huge = (size_t{3} << 20) + 100, small = 50000;
  auto a = AllocateBlockArray<float>(huge / 4);
  auto b = AllocateBlockArray<float>(small / 4);
  REQUIRE((a && b));
  const size_t before = SystemBlockCount();
  a.reset();
  b.reset();
  CHECK(cache.kept_bytes() >= huge + small);
  // The same requests (hwy staggers each by a different offset) take the same blocks back.
  cache.BeginBuild();
  auto a2 = AllocateBlockArray<float>(huge / 4);
  auto b2 = AllocateBlockArray<float>(small / 4);
  CHECK(SystemBlockCount() == before);
  CHECK(cache.kept_bytes() == 0);
  // A request far smaller than every kept block is not served by one (no waste beyond 1/4).
  a2.reset();
  auto tiny = AllocateBlockArray<float>(16);
  CHECK(SystemBlockCount() == before + 1);
  CHECK(cache.kept_bytes() >= huge);
  // EndBuild(true) keeps what this build freed; a block older than the build is released.
  cache.EndBuild(true);
  CHECK(cache.kept_bytes() >= huge);
  cache.BeginBuild();
  cache.EndBuild(true);  // a build that took nothing: the kept block is now older, released
  CHECK(cache.kept_bytes() == 0);
  b2.reset();
  tiny.reset();
  cache.EndBuild(false);
  CHECK(cache.kept_bytes() == 0);
}

TEST_CASE("threads share a cache; a scope restores the previous cache") {
  BlockCache outer, inner;
  {
    const BlockCacheScope a(&outer);
    {
      const BlockCacheScope b(&inner);
      CHECK(CurrentBlockCache() == &inner);
    }
    CHECK(CurrentBlockCache() == &outer);
  }
  CHECK(CurrentBlockCache() == nullptr);
  std::vector<std::thread> threads;
  for (int t = 0; t < 4; ++t) {
    threads.emplace_back([&inner, t] {
      const BlockCacheScope scope(&inner);
      for (int i = 0; i < 200; ++i) {
        auto p = AllocateBlockArray<int32_t>(size_t(1000 + 97 * ((i + t) % 13)));
        REQUIRE(p);
        p[0] = i;
      }
    });
  }
  for (std::thread& th : threads) th.join();
  CHECK(inner.kept_bytes() > 0);
  inner.EndBuild(false);
  CHECK(inner.kept_bytes() == 0);
}

}  // namespace
}  // namespace rs
