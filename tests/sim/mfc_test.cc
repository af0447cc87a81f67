// MFC / DMA rules (sizes, alignment, tags, ranges, lists, the 16-entry queue, fences, data landing
// at the tag wait), the shared MIC's contention, the atomic unit's reservations and atomic cache,
// and the software cache's hits, misses and LRU replacement.
#include "sim/mfc.h"

#include <doctest/doctest.h>

#include <cstdint>
#include <cstring>
#include <string>
#include <vector>

#include "include/raystream/raystream.h"
#include "sim/aligned_buffer.h"
#include "sim/sw_cache.h"

namespace rs::sim {
namespace {

// One SPE (LS, clock, MFC, atomic unit) over 256 KiB of read-only and 64 KiB of writable
// main memory, with an optional second SPE on the same MIC.
struct Env {
  explicit Env(const MemoryTiming& t = MemoryTiming{})
      : timing(t),
        mic(t.mic_line_cycles),
        ls(256 * 1024, 0),
        ls2(256 * 1024, 1),
        mfc(0, ls, memory, mic, clock, timing),
        mfc2(1, ls2, memory, mic, clock2, timing),
        atomic(0, ls, memory, mic, atomic_memory, clock, timing),
        atomic2(1, ls2, memory, mic, atomic_memory, clock2, timing) {
    ro.Resize(256 * 1024);
    rw.Resize(64 * 1024);
    for (size_t i = 0; i < ro.size(); ++i) ro.data()[i] = static_cast<uint8_t>(i * 7 + 3);
    ro_ea = memory.Register(ro.data(), ro.size(), "read-only table");
    rw_ea = memory.Register(rw.data(), rw.size(), "writable table", true);
  }
  MemoryTiming timing;
  MainMemory memory;
  MemoryController mic;
  AtomicMemory atomic_memory;
  LocalStore ls, ls2;
  SpuClock clock, clock2;
  Mfc mfc, mfc2;
  AtomicUnit atomic, atomic2;
  AlignedBuffer ro, rw;
  Ea ro_ea = 0, rw_ea = 0;  // simulated effective addresses of ro and rw
};

TEST_CASE("legal DMA sizes move data, which lands at the tag wait") {
  Env e;
  for (const uint32_t size : {1u, 2u, 4u, 8u, 16u, 48u, 128u, 4096u, 16384u}) {
    INFO("size ", size);
    const uint32_t off = size < 16 ? 8 : 32;  // natural alignment; low 4 bits shared
    const Lsa ls = 1024 + off;
    e.mfc.MfcGet(ls, e.ro_ea + 4096 + off, size, 5);
    // Before the wait the buffer holds the poison pattern, not the data.
    CHECK(e.ls.Bytes(ls, size)[0] == 0xFF);
    CHECK(e.mfc.outstanding() == 1);
    e.mfc.WaitTagsAll(1u << 5);
    CHECK(e.mfc.outstanding() == 0);
    CHECK(std::memcmp(e.ls.Bytes(ls, size), e.ro.data() + 4096 + off, size) == 0);
  }
  // Put: LS -> main memory.
  std::memset(e.ls.Bytes(2048, 64), 0xAB, 64);
  e.mfc.MfcPut(2048, e.rw_ea + 128, 64, 1);
  e.mfc.WaitTagsAll(1u << 1);
  CHECK(e.rw.data()[128] == 0xAB);
  CHECK(e.rw.data()[191] == 0xAB);
  CHECK(e.rw.data()[192] == 0);
  CHECK(e.mfc.stats().gets == 9);
  CHECK(e.mfc.stats().puts == 1);
}

TEST_CASE("illegal DMAs are hard errors naming the rule") {
  Env e;
  const Ea ea = e.ro_ea;
  for (const uint32_t size : {0u, 3u, 12u, 24u, 16400u, 32768u}) {
    INFO("size ", size);
    CHECK_THROWS_WITH_AS(e.mfc.MfcGet(0, ea, size, 0), doctest::Contains("illegal DMA size"),
                         Error);
  }
  CHECK_THROWS_WITH_AS(e.mfc.MfcGet(4, ea + 8, 4, 0),
                       doctest::Contains("differ in their low 4 bits"), Error);
  CHECK_THROWS_WITH_AS(e.mfc.MfcGet(2, ea + 2, 4, 0), doctest::Contains("naturally aligned"),
                       Error);
  CHECK_THROWS_WITH_AS(e.mfc.MfcGet(8, ea + 8, 32, 0), doctest::Contains("16-byte aligned"), Error);
  CHECK_THROWS_WITH_AS(e.mfc.MfcGet(0, ea, 16, 32), doctest::Contains("tag 32 is out of range"),
                       Error);
  CHECK_THROWS_WITH_AS(e.mfc.MfcGet(0, ea + e.ro.size() - 16, 32, 0),
                       doctest::Contains("not inside registered main memory"), Error);
  CHECK_THROWS_WITH_AS(e.mfc.MfcPut(0, ea, 16, 0), doctest::Contains("read-only"), Error);
  CHECK_THROWS_WITH_AS(e.mfc.MfcGet(256 * 1024 - 16, ea, 32, 0),
                       doctest::Contains("runs past the 262144-byte local store"), Error);
  CHECK(e.mfc.outstanding() == 0);
  CHECK(e.mfc.stats().commands == 0);
}

TEST_CASE("a 17th queued DMA stalls until the oldest completes") {
  Env e;
  uint64_t first_done = 0;
  for (uint32_t i = 0; i < 16; ++i) {
    e.mfc.MfcGet(i * 16384 % (192 * 1024), e.ro_ea + i * 16384 % (192 * 1024), 16384, i);
    if (i == 0) first_done = e.clock.now();  // the first command starts here
  }
  CHECK(e.mfc.QueueOccupancy() == 16);
  CHECK(e.mfc.stats().queue_full_stalls == 0);
  const uint64_t before = e.clock.now();
  CHECK(before == 16 * e.timing.dma_issue_cycles);
  e.mfc.MfcGet(0, e.ro_ea, 16, 20);
  CHECK(e.mfc.stats().queue_full_stalls == 1);
  // The SPU (after issuing) waited for the first 16 KiB get: 128 lines + latency after its start.
  const uint64_t stalled_to = e.clock.now();
  CHECK(stalled_to >= first_done + 128 * 16 + e.timing.dma_latency_cycles);
  CHECK(stalled_to <= first_done + 128 * 16 + e.timing.dma_latency_cycles + 32);
  CHECK(e.mfc.QueueOccupancy() == 16);
  e.mfc.WaitAll();
  CHECK(e.mfc.QueueOccupancy() == 0);
  CHECK(std::memcmp(e.ls.Bytes(16384, 16384), e.ro.data() + 16384, 16384) == 0);
}

TEST_CASE("synchronous get timing and MIC contention between SPEs") {
  Env e;
  e.mfc.MfcGet(0, e.ro_ea, 128, 0);
  e.mfc.WaitTagsAll(1);
  // issue + one line (slot aligned to 16 cycles) + latency + wait
  const uint64_t one =
      e.timing.dma_issue_cycles + 16 + e.timing.dma_latency_cycles + e.timing.dma_wait_cycles;
  CHECK(e.clock.now() >= one);
  CHECK(e.clock.now() <= one + 16);

  // Two SPEs each fetching 16 KiB at the same moment share the MIC's 16 cycles per line.
  Env alone, both;
  alone.mfc.MfcGet(0, alone.ro_ea, 16384, 0);
  alone.mfc.WaitTagsAll(1);
  both.mfc.MfcGet(0, both.ro_ea, 16384, 0);
  both.mfc2.MfcGet(0, both.ro_ea + 65536, 16384, 0);
  both.mfc.WaitTagsAll(1);
  both.mfc2.WaitTagsAll(1);
  const uint64_t later = std::max(both.clock.now(), both.clock2.now());
  CHECK(later > alone.clock.now());
  CHECK(later <= alone.clock.now() + 128 * 16 + 16);
  CHECK(both.mic.lines() == 256);
  CHECK(both.mic.queue_cycles() > 0);
}

TEST_CASE("DMA lists") {
  Env e;
  DmaListElement* list = e.ls.As<DmaListElement>(8192, 3);
  const Ea base = e.ro_ea;
  list[0] = {32, static_cast<uint32_t>(base + 256)};
  list[1] = {16, static_cast<uint32_t>(base + 1024)};
  list[2] = {128, static_cast<uint32_t>(base + 4096)};
  e.mfc.MfcGetList(0, static_cast<uint32_t>(base >> 32), 8192, 24, 3);
  e.mfc.WaitTagsAll(1u << 3);
  CHECK(std::memcmp(e.ls.Bytes(0, 32), e.ro.data() + 256, 32) == 0);
  CHECK(std::memcmp(e.ls.Bytes(32, 16), e.ro.data() + 1024, 16) == 0);
  CHECK(std::memcmp(e.ls.Bytes(48, 128), e.ro.data() + 4096, 128) == 0);
  CHECK(e.mfc.stats().list_elements == 3);
  CHECK(e.mfc.stats().commands == 1);
  const uint32_t hi = static_cast<uint32_t>(base >> 32);
  CHECK_THROWS_WITH_AS(e.mfc.MfcGetList(0, hi, 8192, 2049 * 8, 0),
                       doctest::Contains("1 to 2048 elements"), Error);
  CHECK_THROWS_WITH_AS(e.mfc.MfcGetList(0, hi, 8192, 0, 0), doctest::Contains("1 to 2048"), Error);
  CHECK_THROWS_WITH_AS(e.mfc.MfcGetList(0, hi, 8196, 8, 0), doctest::Contains("8-byte aligned"),
                       Error);
  list[0] = {16400, static_cast<uint32_t>(base)};
  CHECK_THROWS_WITH_AS(e.mfc.MfcGetList(0, hi, 8192, 8, 0),
                       doctest::Contains("element 0: element size 16400"), Error);
  list[0] = {24, static_cast<uint32_t>(base)};
  CHECK_THROWS_WITH_AS(e.mfc.MfcGetList(0, hi, 8192, 8, 0), doctest::Contains("illegal DMA size"),
                       Error);
}

TEST_CASE("fences order commands of a tag") {
  MemoryTiming t;
  t.mfc_bus_slots = 16;  // pipelined: without a fence both gets overlap
  Env plain(t), fenced(t);
  plain.mfc.MfcGet(0, plain.ro_ea, 128, 4);
  plain.mfc.MfcGet(128, plain.ro_ea + 128, 128, 4);
  plain.mfc.WaitTagsAll(1u << 4);
  fenced.mfc.MfcGet(0, fenced.ro_ea, 128, 4);
  fenced.mfc.MfcGetf(128, fenced.ro_ea + 128, 128, 4);
  fenced.mfc.WaitTagsAll(1u << 4);
  CHECK(fenced.clock.now() >= plain.clock.now() + t.dma_latency_cycles);
  // A barrier holds later commands of its tag.
  Env barrier(t);
  barrier.mfc.MfcGetb(0, barrier.ro_ea, 128, 4);
  barrier.mfc.MfcGet(128, barrier.ro_ea + 128, 128, 4);
  barrier.mfc.WaitTagsAll(1u << 4);
  CHECK(barrier.clock.now() >= plain.clock.now() + t.dma_latency_cycles);
}

TEST_CASE("atomic unit: reservations, lost reservations, atomic cache") {
  Env e;
  const Ea line = e.rw_ea + 1024;
  uint32_t* mine = e.ls.As<uint32_t>(4096, 32);
  uint32_t* theirs = e.ls2.As<uint32_t>(4096, 32);
  // Uncontended increment.
  e.atomic.Getllar(4096, line);
  CHECK(e.atomic.ReadStatus() == kGetllarDone);
  const uint64_t miss = e.clock.now();
  CHECK(miss >= e.timing.atomic_issue_cycles + 16 + e.timing.atomic_latency_cycles);
  mine[0] += 1;
  e.atomic.Putllc(4096, line);
  CHECK(e.atomic.ReadStatus() == 0);
  CHECK(reinterpret_cast<uint32_t*>(e.rw.data() + 1024)[0] == 1);
  // Second getllar of the line hits the atomic cache.
  const uint64_t t0 = e.clock.now();
  e.atomic.Getllar(4096, line);
  e.atomic.ReadStatus();
  CHECK(e.clock.now() - t0 ==
        e.timing.atomic_issue_cycles + e.timing.atomic_hit_cycles + e.timing.atomic_status_cycles);
  CHECK(e.atomic.stats().cache_hits == 1);
  // SPE 1 stores to the line between SPE 0's getllar and putllc: SPE 0's putllc fails.
  e.atomic2.Getllar(4096, line);
  e.atomic2.ReadStatus();
  theirs[0] += 1;
  e.atomic2.Putllc(4096, line);
  CHECK(e.atomic2.ReadStatus() == 0);
  mine[0] += 1;
  e.atomic.Putllc(4096, line);
  CHECK(e.atomic.ReadStatus() == kPutllcFailed);
  CHECK(reinterpret_cast<uint32_t*>(e.rw.data() + 1024)[0] == 2);  // SPE 1's value stays
  CHECK(e.atomic.stats().putllc_failed == 1);
  // Retry: the line changed, so it misses the atomic cache, and the increment succeeds.
  e.atomic.Getllar(4096, line);
  e.atomic.ReadStatus();
  CHECK(mine[0] == 2);
  mine[0] += 1;
  e.atomic.Putllc(4096, line);
  CHECK(e.atomic.ReadStatus() == 0);
  CHECK(reinterpret_cast<uint32_t*>(e.rw.data() + 1024)[0] == 3);
  CHECK(e.atomic.stats().cache_hits == 1);
  // putllc without a reservation fails; putlluc always stores.
  e.atomic.Putllc(4096, line);
  CHECK(e.atomic.ReadStatus() == kPutllcFailed);
  mine[0] = 42;
  e.atomic.Putlluc(4096, line);
  CHECK(e.atomic.ReadStatus() == kPutllucDone);
  CHECK(reinterpret_cast<uint32_t*>(e.rw.data() + 1024)[0] == 42);
  // Rules.
  CHECK_THROWS_WITH_AS(e.atomic.Getllar(4096 + 16, line), doctest::Contains("128-byte aligned"),
                       Error);
  CHECK_THROWS_WITH_AS(e.atomic.Putllc(4096, e.ro_ea), doctest::Contains("read-only"), Error);
}

TEST_CASE("software cache: hits, misses, LRU, lines straddled") {
  Env e;
  SoftwareCacheConfig c;
  SoftwareCache cache(c, e.ls, e.mfc, e.clock);
  uint8_t out[64];
  const Ea base = e.ro_ea;
  uint64_t t0 = e.clock.now();
  CHECK(!cache.Read(base + 200, 8, out));
  CHECK(std::memcmp(out, e.ro.data() + 200, 8) == 0);
  CHECK(e.clock.now() - t0 > e.timing.dma_latency_cycles);
  CHECK(e.clock.spent()[Cost::kCache] == e.clock.now());  // all of it is cache time
  t0 = e.clock.now();
  CHECK(cache.Read(base + 192, 16, out));
  CHECK(e.clock.now() - t0 == c.hit_cycles);
  CHECK(std::memcmp(out, e.ro.data() + 192, 16) == 0);
  // 5 lines in the same set (stride sets x line = 8 KiB): the first is evicted by the fifth.
  for (int k = 1; k <= 4; ++k) cache.Read(base + 128 + uint64_t(k) * 8192, 8, out);
  CHECK(!cache.Read(base + 200, 8, out));
  // A read across a line boundary touches two lines.
  const uint64_t reads = cache.stats().reads;
  cache.Read(base + 120, 16, out);
  CHECK(cache.stats().reads == reads + 2);
  CHECK(std::memcmp(out, e.ro.data() + 120, 16) == 0);
  CHECK(cache.stats().hits + cache.stats().misses == cache.stats().reads);
  SoftwareCacheConfig bad;
  bad.ways = 2;
  CHECK_THROWS_WITH_AS(SoftwareCache(bad, e.ls, e.mfc, e.clock), doctest::Contains("1 or 4"),
                       Error);
}

TEST_CASE("effective addresses are simulated, not host pointers") {
  AlignedBuffer a(5000), b(128);
  MainMemory m;
  const Ea ea_a = m.Register(a.data(), a.size(), "a");
  const Ea ea_b = m.Register(b.data(), b.size(), "b", true);
  CHECK(ea_a == MainMemory::kMainMemoryBase);
  CHECK(ea_b == MainMemory::kMainMemoryBase + 8192);  // next page after a's 5120 bytes
  CHECK(m.NextEa() == ea_b + 4096);
  CHECK(m.Find(ea_a + 100, 8, false) == a.data() + 100);
  CHECK(m.Find(ea_b, 128, true) == b.data());
  CHECK(m.Find(ea_a, 8, true) == nullptr);  // read-only
  CHECK(m.Find(ea_a + a.size(), 8, false) == nullptr);
  // The host address itself is not an effective address.
  CHECK(m.Find(reinterpret_cast<uintptr_t>(a.data()), 8, false) == nullptr);
  CHECK_THROWS_WITH_AS(m.RegisterAt(ea_a + 4096, b.data(), 128, "c"),  // inside a
                       doctest::Contains("overlaps"), Error);
  CHECK_THROWS_WITH_AS(m.RegisterAt(0, b.data(), 128, "null"),
                       doctest::Contains("nonzero 128-byte boundary"), Error);
  // The same registrations give the same EAs whatever the host buffers are.
  AlignedBuffer a2(5000), b2(128);
  MainMemory m2;
  CHECK(m2.Register(a2.data(), a2.size(), "a") == ea_a);
  CHECK(m2.Register(b2.data(), b2.size(), "b") == ea_b);
}

// The set index of the software cache comes from simulated EAs: two tables whose host storage
// sits at different offsets modulo the cache's 8 KiB way size give identical hits, misses and
// cycles (with host addresses, the second table's lines move to other sets).
TEST_CASE("software-cache timing does not depend on host addresses") {
  std::vector<uint64_t> first;
  for (const size_t shift : {size_t{0}, size_t{4096}, size_t{128 * 5}}) {
    INFO("host shift ", shift);
    AlignedBuffer storage(24 * 1024 + 24 * 1024 + 8192);
    for (size_t i = 0; i < storage.size(); ++i) storage.data()[i] = static_cast<uint8_t>(i * 13);
    MainMemory memory;
    const Ea ta = memory.Register(storage.data(), 24 * 1024, "table a");
    const Ea tb = memory.Register(storage.data() + 24 * 1024 + shift, 24 * 1024, "table b");
    MemoryTiming timing;
    MemoryController mic(timing.mic_line_cycles);
    LocalStore ls(256 * 1024, 0);
    SpuClock clock;
    Mfc mfc(0, ls, memory, mic, clock, timing);
    SoftwareCache cache(SoftwareCacheConfig{}, ls, mfc, clock);
    // Three lines of each table that share one set by EA (way stride 8 KiB): six lines in a
    // 4-way set, read round robin, always miss.
    uint64_t v = 0;
    for (int round = 0; round < 4; ++round) {
      for (const Ea t : {ta, tb}) {
        for (uint64_t k = 0; k < 3; ++k) {
          cache.Read(t + k * 8192 + 8, 8, &v);
          const size_t host = size_t(t == ta ? 0 : 24 * 1024 + shift) + k * 8192 + 8;
          uint64_t want;
          std::memcpy(&want, storage.data() + host, 8);
          CHECK(v == want);
        }
      }
    }
    const std::vector<uint64_t> got = {cache.stats().hits, cache.stats().misses, clock.now()};
    CHECK(cache.stats().hits == 0);
    if (first.empty()) {
      first = got;
    } else {
      CHECK(got == first);
    }
  }
}

}  // namespace
}  // namespace rs::sim
