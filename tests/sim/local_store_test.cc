// The simulated local store: named 16/128-B aligned allocations, zeroed memory, bounds-checked
// access, and a hard rs::Error on overflow that names the allocation and the sizes.
#include "sim/local_store.h"

#include <doctest/doctest.h>

#include <string>

#include "include/raystream/raystream.h"

namespace rs::sim {
namespace {

TEST_CASE("allocations are aligned, zeroed and described") {
  LocalStore ls(256 * 1024, 3);
  CHECK(ls.size() == 262144);
  const Lsa a = ls.Allocate("code and stack", 1000);
  CHECK(a == 0);
  CHECK(ls.used() == 1008);  // rounded to 16 B
  const Lsa b = ls.Allocate("dma buffer", 64, 128);
  CHECK(b == 1024);
  CHECK(b % 128 == 0);
  const Lsa c = ls.Allocate("list", 8, 16);
  CHECK(c == 1088);
  for (uint32_t i = 0; i < 64; ++i) CHECK(ls.Bytes(b, 64)[i] == 0);
  ls.Bytes(b, 64)[5] = 7;
  CHECK(ls.As<uint8_t>(b)[5] == 7);
  CHECK(ls.allocations().size() == 3);
  CHECK(ls.Describe().find("dma buffer 64 B @ 1024") != std::string::npos);
  ls.Reset();
  CHECK(ls.used() == 0);
  CHECK(ls.Allocate("again", 16) == 0);
}

TEST_CASE("overflow is a hard error naming the allocation and the sizes") {
  LocalStore ls(256 * 1024, 2);
  ls.Allocate("code and stack", 40 * 1024);
  ls.Allocate("software cache lines", 32 * 1024, 128);
  CHECK_THROWS_WITH_AS(ls.Allocate("occupancy bits", 200 * 1024, 128),
                       doctest::Contains("SPE 2 local store overflow: allocating 'occupancy "
                                         "bits' (204800 B, aligned 128) needs 204800 B but only "
                                         "188416 B of 262144 B are free"),
                       Error);
  try {
    ls.Allocate("occupancy bits", 200 * 1024, 128);
  } catch (const Error& e) {
    CHECK(std::string(e.what()).find("code and stack 40960 B") != std::string::npos);
  }
  // Exactly filling the store works; one more byte does not.
  const uint32_t left = ls.free_bytes();
  ls.Allocate("rest", left);
  CHECK(ls.free_bytes() == 0);
  CHECK_THROWS_AS(ls.Allocate("one more", 1), Error);
  // Alignment padding counts.
  LocalStore small(16 * 1024, 0);
  small.Allocate("a", 16);
  CHECK_THROWS_WITH_AS(small.Allocate("b", 16 * 1024 - 64, 128),
                       doctest::Contains("needs 16432 B but only 16368 B"), Error);
  CHECK_NOTHROW(small.Allocate("c", 16 * 1024 - 128, 128));  // 112 B of padding + 16256 B
}

TEST_CASE("bad requests and out-of-range access") {
  LocalStore ls(16 * 1024, 0);
  CHECK_THROWS_AS(ls.Allocate("x", 16, 8), Error);   // alignment < 16
  CHECK_THROWS_AS(ls.Allocate("x", 16, 48), Error);  // not a power of two
  CHECK_THROWS_AS(ls.Bytes(16 * 1024 - 8, 16), Error);
  CHECK_NOTHROW(ls.Bytes(16 * 1024 - 16, 16));
  CHECK_THROWS_AS(LocalStore(1000, 0), Error);
  CHECK(ls.Contains(0, 16 * 1024));
  CHECK(!ls.Contains(1, 16 * 1024));
}

}  // namespace
}  // namespace rs::sim
