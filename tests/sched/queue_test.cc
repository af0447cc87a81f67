// Tests of the LOCK, LFREE and LOCAL work queues: multi-producer multi-consumer stress with
// exactly-once and per-producer FIFO checks, EMPTY, move-only tasks, destruction with tasks left,
// the fill-then-release pattern, and the queue-time counters. Also run under TSan and ASan+UBSan.
#include <doctest/doctest.h>

#include <algorithm>
#include <atomic>
#include <barrier>
#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <semaphore>
#include <span>
#include <string_view>
#include <thread>
#include <type_traits>
#include <vector>

// Chaos injection at RS_QUEUE_CHAOS_POINT (sched/queue.h). When one_in > 0, each point pauses
// the thread with probability 1/one_in (mostly a yield, sometimes a 20 us sleep), so a stale
// load is likely to meet a recycled node at its CAS. A thread can also install `hook`, which
// runs (not re-entrantly) at every point it passes: the deterministic ABA tests use it to run
// "another thread's" operations between a load and its CAS. Both are how these tests fail on a
// 2-core machine when tags or reference counts are broken (checked by mutating the queue).
namespace rs_test_chaos {
inline std::atomic<uint32_t> one_in{0};
inline thread_local std::function<void(const char*)>* hook = nullptr;
inline thread_local bool in_hook = false;
inline void Point(const char* where) {
  if (hook != nullptr && !in_hook) {
    in_hook = true;
    (*hook)(where);
    in_hook = false;
  }
  const uint32_t n = one_in.load(std::memory_order_relaxed);
  if (n == 0) return;
  thread_local uint64_t rng = 0;
  if (rng == 0) rng = std::hash<std::thread::id>()(std::this_thread::get_id()) | 1;
  rng ^= rng << 13;
  rng ^= rng >> 7;
  rng ^= rng << 17;
  if (rng % n != 0) return;
  if ((rng >> 32) % 64 == 0) {
    std::this_thread::sleep_for(std::chrono::microseconds(20));
  } else {
    std::this_thread::yield();
  }
}
}  // namespace rs_test_chaos
#define RS_QUEUE_CHAOS_POINT(where) ::rs_test_chaos::Point(where)

#include "sched/queue.h"
#include "sched/queue_local.h"
#include "sched/queue_lock.h"
#include "sched/queue_lockfree.h"

namespace rs {
namespace {

// ---------------------------------------------------------------------------------------------
// Task payloads. Each encodes (producer, seq) and can tell whether it arrived intact.

// 40 bytes, trivially copyable: LFREE stores it out of line (reference-counted path).
struct WideTask {
  uint32_t producer = 0;
  uint32_t seq = 0;
  uint32_t words[8] = {};
};

constexpr uint32_t Mix(uint32_t producer, uint32_t seq, uint32_t i) {
  uint32_t h = producer * 0x9E3779B1u ^ (seq + 0x7F4A7C15u) * 0x85EBCA77u ^ i * 0xC2B2AE3Du;
  h ^= h >> 15;
  h *= 0x2C1B3C6Du;
  return h ^ (h >> 13);
}

template <class T>
struct Codec;

template <>
struct Codec<WideTask> {
  static WideTask Make(uint32_t producer, uint32_t seq) {
    WideTask t;
    t.producer = producer;
    t.seq = seq;
    for (uint32_t i = 0; i < 8; ++i) t.words[i] = Mix(producer, seq, i);
    return t;
  }
  static bool Decode(const WideTask& t, uint32_t* producer, uint32_t* seq) {
    for (uint32_t i = 0; i < 8; ++i) {
      if (t.words[i] != Mix(t.producer, t.seq, i)) return false;
    }
    *producer = t.producer;
    *seq = t.seq;
    return true;
  }
};

// 8 bytes, trivially copyable: LFREE keeps it in the node's atomic word (M&S read-before-CAS).
template <>
struct Codec<uint64_t> {
  static uint64_t Make(uint32_t producer, uint32_t seq) { return (uint64_t{producer} << 32) | seq; }
  static bool Decode(uint64_t t, uint32_t* producer, uint32_t* seq) {
    *producer = static_cast<uint32_t>(t >> 32);
    *seq = static_cast<uint32_t>(t);
    return true;
  }
};

// Move-only: a lost or doubly destroyed task shows up under ASan.
template <>
struct Codec<std::unique_ptr<WideTask>> {
  static std::unique_ptr<WideTask> Make(uint32_t producer, uint32_t seq) {
    return std::make_unique<WideTask>(Codec<WideTask>::Make(producer, seq));
  }
  static bool Decode(const std::unique_ptr<WideTask>& t, uint32_t* producer, uint32_t* seq) {
    return t != nullptr && Codec<WideTask>::Decode(*t, producer, seq);
  }
};

// Counts live objects and owns heap memory, so leaks show in release (count) and under ASan.
struct Tracked {
  static inline std::atomic<int> live{0};
  int value = -1;
  std::unique_ptr<int> heap;

  Tracked() { live.fetch_add(1, std::memory_order_relaxed); }
  explicit Tracked(int v) : value(v), heap(std::make_unique<int>(v)) {
    live.fetch_add(1, std::memory_order_relaxed);
  }
  Tracked(Tracked&& o) noexcept : value(o.value), heap(std::move(o.heap)) {
    live.fetch_add(1, std::memory_order_relaxed);
  }
  Tracked& operator=(Tracked&& o) noexcept {
    value = o.value;
    heap = std::move(o.heap);
    return *this;
  }
  Tracked(const Tracked&) = delete;
  Tracked& operator=(const Tracked&) = delete;
  ~Tracked() { live.fetch_sub(1, std::memory_order_relaxed); }
};

struct ThrowingMove {
  ThrowingMove(ThrowingMove&&) noexcept(false) {}
  ThrowingMove& operator=(ThrowingMove&&) noexcept(false) { return *this; }
};

// ---------------------------------------------------------------------------------------------
// Compile-time contracts.

static_assert(WorkQueue<LockQueue<int>>);
static_assert(WorkQueue<LockQueue<std::unique_ptr<int>, QueueTimeStats, SpinLock>>);
static_assert(WorkQueue<LockFreeQueue<WideTask>>);
static_assert(WorkQueue<LockFreeQueue<std::unique_ptr<int>, QueueTimeStats>>);
static_assert(WorkQueue<LocalQueues<std::unique_ptr<int>>>);
static_assert(WorkQueue<LocalQueues<WideTask, QueueTimeStats>>);
static_assert(!QueueTask<ThrowingMove>);
static_assert(!QueueTask<const int>);
static_assert(LockFreeQueue<uint64_t>::kInlineTask);
static_assert(LockFreeQueue<uint32_t>::kInlineTask);
static_assert(!LockFreeQueue<WideTask>::kInlineTask);
static_assert(!LockFreeQueue<std::unique_ptr<int>>::kInlineTask);
static_assert(std::atomic<uint64_t>::is_always_lock_free);
// "Off" statistics are an empty type, take no space and read no clock.
static_assert(std::is_empty_v<NoQueueStats> && std::is_empty_v<NoQueueStats::Scope>);
static_assert(sizeof(LocalQueues<int, NoQueueStats>) < sizeof(LocalQueues<int, QueueTimeStats>));
static_assert(queue_detail::BlockFifo<Tracked>::kPerBlock == 1024);

// ---------------------------------------------------------------------------------------------
// Multi-producer multi-consumer stress.

struct StressResult {
  uint64_t expected = 0;
  uint64_t popped = 0;
  uint64_t duplicates = 0;
  uint64_t missing = 0;
  uint64_t order_violations = 0;  // a consumer saw a producer's seq not increase
  uint64_t bad_payloads = 0;      // torn, mixed up or out-of-range task
  uint64_t spurious_empty = 0;    // TryPop right after one's own Push said EMPTY (pairs mode)
  bool empty_after = false;       // TryPop on the drained queue returns false
};

void Tally(const std::vector<std::vector<uint64_t>>& taken, StressResult* r) {
  std::vector<uint8_t> seen(r->expected, 0);
  for (const auto& list : taken) {
    for (const uint64_t key : list) {
      if (key >= r->expected) {
        ++r->bad_payloads;
        continue;
      }
      if (seen[key]++ != 0) ++r->duplicates;
      ++r->popped;
    }
  }
  for (const uint8_t s : seen) r->missing += (s == 0);
}

void CheckClean(const StressResult& r) {
  CHECK(r.popped == r.expected);
  CHECK(r.duplicates == 0);
  CHECK(r.missing == 0);
  CHECK(r.order_violations == 0);
  CHECK(r.bad_payloads == 0);
  CHECK(r.spurious_empty == 0);
  CHECK(r.empty_after);
}

// Per-consumer bookkeeping: every task's (producer, seq) must decode, and each producer's seqs
// must strictly increase in the order this consumer pops them (FIFO per producer).
template <class T>
struct Consumer {
  int num_producers;
  uint32_t per_producer;
  std::vector<int64_t> last;
  std::vector<uint64_t> taken;
  uint64_t order_violations = 0;
  uint64_t bad_payloads = 0;

  Consumer(int producers, uint32_t per, size_t expect)
      : num_producers(producers), per_producer(per), last(producers, -1) {
    taken.reserve(expect);
  }
  void Take(const T& task) {
    uint32_t producer = 0;
    uint32_t seq = 0;
    if (!Codec<T>::Decode(task, &producer, &seq) ||
        producer >= static_cast<uint32_t>(num_producers) || seq >= per_producer) {
      ++bad_payloads;
      return;
    }
    if (static_cast<int64_t>(seq) <= last[producer]) ++order_violations;
    last[producer] = seq;
    taken.push_back(uint64_t{producer} * per_producer + seq);
  }
};

// Sizes of the PushMany / TryPopMany calls of the chain modes: 1..max, from a per-thread
// xorshift, so chains of every length up to max (and LFREE's kMaxPopChain) meet each other.
struct ChainSizes {
  uint64_t state;
  uint32_t max;
  uint32_t Next() {
    state ^= state << 13;
    state ^= state >> 7;
    state ^= state << 17;
    return 1 + static_cast<uint32_t>(state % max);
  }
};

// PushMany of producer's tasks first .. first + n - 1, built in `batch`.
template <class Q, class T = typename Q::value_type>
void PushChain(Q& queue, int producer, uint32_t first, uint32_t n, std::vector<T>& batch) {
  batch.clear();
  for (uint32_t i = 0; i < n; ++i) {
    batch.push_back(Codec<T>::Make(static_cast<uint32_t>(producer), first + i));
  }
  queue.PushMany(producer, std::span<T>(batch));
}

// `producers` threads push per_producer tasks each while `consumers` threads pop until all
// producers are done and the queue is empty. Workers 0..P-1 produce, P..P+C-1 consume.
// chain > 0: PushMany and TryPopMany of 1..chain tasks instead of Push and TryPop.
template <class Q>
StressResult RunMpmc(int producers, int consumers, uint32_t per_producer, uint32_t chain = 0) {
  using T = typename Q::value_type;
  Q queue(producers + consumers);
  std::vector<std::unique_ptr<Consumer<T>>> state;
  for (int c = 0; c < consumers; ++c) {
    state.push_back(std::make_unique<Consumer<T>>(
        producers, per_producer, uint64_t{per_producer} * producers / consumers + 1024));
  }
  std::atomic<int> producers_done{0};
  std::barrier start(producers + consumers);
  std::vector<std::thread> threads;
  for (int p = 0; p < producers; ++p) {
    threads.emplace_back([&, p] {
      start.arrive_and_wait();
      if (chain == 0) {
        for (uint32_t s = 0; s < per_producer; ++s) {
          queue.Push(p, Codec<T>::Make(static_cast<uint32_t>(p), s));
        }
      } else {
        ChainSizes sizes{0x9E3779B97F4A7C15ull * (p + 1), chain};
        std::vector<T> batch;
        for (uint32_t s = 0; s < per_producer;) {
          const uint32_t n = std::min(sizes.Next(), per_producer - s);
          PushChain(queue, p, s, n, batch);
          s += n;
        }
      }
      producers_done.fetch_add(1, std::memory_order_release);
    });
  }
  for (int c = 0; c < consumers; ++c) {
    threads.emplace_back([&, c] {
      Consumer<T>& me = *state[c];
      const int worker = producers + c;
      start.arrive_and_wait();
      ChainSizes sizes{0xD1B54A32D192ED03ull * (c + 1), chain == 0 ? 1 : chain};
      std::vector<T> got(sizes.max);
      // One TryPop, or one TryPopMany: true if it took anything.
      auto pop = [&] {
        if (chain == 0) {
          if (!queue.TryPop(worker, got[0])) return false;
          me.Take(got[0]);
          return true;
        }
        const size_t n = queue.TryPopMany(worker, std::span<T>(got.data(), sizes.Next()));
        for (size_t i = 0; i < n; ++i) me.Take(got[i]);
        return n > 0;
      };
      for (;;) {
        if (pop()) continue;
        // acquire: every push happens-before this point, so EMPTY now means drained.
        if (producers_done.load(std::memory_order_acquire) == producers) {
          if (pop()) continue;
          break;
        }
        std::this_thread::yield();  // threads outnumber the 2 cores: let producers run
      }
    });
  }
  for (auto& t : threads) t.join();

  StressResult r;
  r.expected = uint64_t{per_producer} * producers;
  std::vector<std::vector<uint64_t>> taken;
  for (auto& c : state) {
    r.order_violations += c->order_violations;
    r.bad_payloads += c->bad_payloads;
    taken.push_back(std::move(c->taken));
  }
  Tally(taken, &r);
  T task{};
  r.empty_after = !queue.TryPop(0, task);
  return r;
}

// Every thread alternates Push(own task) and TryPop on a nearly empty queue: nodes are recycled
// immediately, the pattern most likely to expose ABA or use-after-free. A linearizable queue
// can never answer EMPTY to a pop that follows the thread's own push.
// chain > 0: each round is a PushMany of 1..chain own tasks and a TryPopMany of as many.
template <class Q>
StressResult RunPairs(int threads_n, uint32_t per_thread, uint32_t chain = 0) {
  using T = typename Q::value_type;
  Q queue(threads_n);
  std::vector<std::unique_ptr<Consumer<T>>> state;
  std::vector<uint64_t> spurious(threads_n, 0);
  for (int w = 0; w < threads_n; ++w) {
    state.push_back(std::make_unique<Consumer<T>>(threads_n, per_thread, per_thread + 1024));
  }
  std::barrier start(threads_n);
  std::barrier finish(threads_n);
  std::vector<std::thread> threads;
  for (int w = 0; w < threads_n; ++w) {
    threads.emplace_back([&, w] {
      Consumer<T>& me = *state[w];
      uint64_t empty = 0;
      start.arrive_and_wait();
      T task{};
      if (chain == 0) {
        for (uint32_t s = 0; s < per_thread; ++s) {
          queue.Push(w, Codec<T>::Make(static_cast<uint32_t>(w), s));
          if (queue.TryPop(w, task)) {
            me.Take(task);
          } else {
            ++empty;
          }
        }
      } else {
        ChainSizes sizes{0x94D049BB133111EBull * (w + 1), chain};
        std::vector<T> batch;
        std::vector<T> got(chain);
        for (uint32_t s = 0; s < per_thread;) {
          const uint32_t n = std::min(sizes.Next(), per_thread - s);
          PushChain(queue, w, s, n, batch);
          s += n;
          const size_t k = queue.TryPopMany(w, std::span<T>(got.data(), n));
          for (size_t i = 0; i < k; ++i) me.Take(got[i]);
          if (k == 0) ++empty;
        }
        // What the pops left behind (a pop may take fewer than its push), once every thread
        // is done: an earlier drain would take tasks another thread's next pop is owed.
        finish.arrive_and_wait();
        for (;;) {
          const size_t k = queue.TryPopMany(w, std::span<T>(got));
          if (k == 0) break;
          for (size_t i = 0; i < k; ++i) me.Take(got[i]);
        }
      }
      spurious[w] = empty;
    });
  }
  for (auto& t : threads) t.join();
  StressResult r;
  r.expected = uint64_t{per_thread} * threads_n;
  std::vector<std::vector<uint64_t>> taken;
  for (int w = 0; w < threads_n; ++w) {
    r.order_violations += state[w]->order_violations;
    r.bad_payloads += state[w]->bad_payloads;
    r.spurious_empty += spurious[w];
    taken.push_back(std::move(state[w]->taken));
  }
  Tally(taken, &r);
  T task{};
  r.empty_after = !queue.TryPop(0, task);
  return r;
}

template <class Q>
void MpmcSuite(uint32_t total) {
  SUBCASE("1 producer x 1 consumer") { CheckClean(RunMpmc<Q>(1, 1, total)); }
  SUBCASE("4 producers x 4 consumers") { CheckClean(RunMpmc<Q>(4, 4, total / 4)); }
  SUBCASE("8 producers x 8 consumers") { CheckClean(RunMpmc<Q>(8, 8, total / 8)); }
  SUBCASE("8 threads push+pop pairs") { CheckClean(RunPairs<Q>(8, total / 8)); }
}

constexpr uint32_t kStressTasks = 1'000'000;

// LFREE without per-worker node caches: every node goes through the shared free list.
template <class T>
struct LfreeNoCache : LockFreeQueue<T> {
  explicit LfreeNoCache(int num_workers) : LockFreeQueue<T>(num_workers, 0, 0) {}
};
static_assert(WorkQueue<LfreeNoCache<uint64_t>>);

TEST_CASE("LOCK (std::mutex) MPMC stress, 1e6 tasks") {
  MpmcSuite<LockQueue<WideTask>>(kStressTasks);
}
// The variants below share their algorithm with a full suite above, so they run the 4x4 and
// pairs configurations only (keeps the TSan run well inside its timeout on 2 cores).
TEST_CASE("LOCK (SpinLock) MPMC stress, 1e6 tasks") {
  using Q = LockQueue<WideTask, NoQueueStats, SpinLock>;
  SUBCASE("4 producers x 4 consumers") { CheckClean(RunMpmc<Q>(4, 4, kStressTasks / 4)); }
  SUBCASE("8 threads push+pop pairs") { CheckClean(RunPairs<Q>(8, kStressTasks / 8)); }
}
TEST_CASE("LFREE MPMC stress, 1e6 tasks, out-of-line 40-byte tasks") {
  MpmcSuite<LockFreeQueue<WideTask>>(kStressTasks);
}
TEST_CASE("LFREE MPMC stress, 1e6 tasks, inline 8-byte tasks") {
  MpmcSuite<LockFreeQueue<uint64_t>>(kStressTasks);
}
TEST_CASE("LFREE MPMC stress, 1e6 tasks, no node cache (shared free list only)") {
  SUBCASE("out-of-line, 4 producers x 4 consumers") {
    CheckClean(RunMpmc<LfreeNoCache<WideTask>>(4, 4, kStressTasks / 4));
  }
  SUBCASE("inline, 8 threads push+pop pairs") {
    CheckClean(RunPairs<LfreeNoCache<uint64_t>>(8, kStressTasks / 8));
  }
}
TEST_CASE("move-only tasks (unique_ptr) under MPMC stress") {
  SUBCASE("LOCK") { CheckClean(RunMpmc<LockQueue<std::unique_ptr<WideTask>>>(4, 4, 50'000)); }
  SUBCASE("LFREE") { CheckClean(RunMpmc<LockFreeQueue<std::unique_ptr<WideTask>>>(4, 4, 50'000)); }
  SUBCASE("LFREE pairs") {
    CheckClean(RunPairs<LockFreeQueue<std::unique_ptr<WideTask>>>(4, 50'000));
  }
}
// PushMany / TryPopMany: chains of 1..100 tasks (longer than LFREE's 64-task pop chain), the
// same exactly-once and per-producer FIFO checks, mixed with each other and with lone ops.
TEST_CASE("PushMany / TryPopMany MPMC stress") {
  constexpr uint32_t kChain = 100;
  SUBCASE("LOCK 4x4") { CheckClean(RunMpmc<LockQueue<WideTask>>(4, 4, 250'000, kChain)); }
  SUBCASE("LOCK pairs") { CheckClean(RunPairs<LockQueue<uint64_t>>(4, 250'000, kChain)); }
  SUBCASE("LFREE inline 1x1") {
    CheckClean(RunMpmc<LockFreeQueue<uint64_t>>(1, 1, 500'000, kChain));
  }
  SUBCASE("LFREE inline 4x4") {
    CheckClean(RunMpmc<LockFreeQueue<uint64_t>>(4, 4, 250'000, kChain));
  }
  SUBCASE("LFREE inline pairs") {
    CheckClean(RunPairs<LockFreeQueue<uint64_t>>(8, 125'000, kChain));
  }
  SUBCASE("LFREE out-of-line 4x4") {
    CheckClean(RunMpmc<LockFreeQueue<WideTask>>(4, 4, 100'000, kChain));
  }
  SUBCASE("LFREE no node cache, inline pairs") {
    CheckClean(RunPairs<LfreeNoCache<uint64_t>>(4, 100'000, kChain));
  }
  SUBCASE("LFREE move-only pairs") {
    CheckClean(RunPairs<LockFreeQueue<std::unique_ptr<WideTask>>>(4, 50'000, kChain));
  }
}

// Sets the chaos rate for the scope of one test.
struct Chaos {
  explicit Chaos(uint32_t one_in) {
    rs_test_chaos::one_in.store(one_in, std::memory_order_relaxed);
  }
  ~Chaos() { rs_test_chaos::one_in.store(0, std::memory_order_relaxed); }
};

TEST_CASE("LFREE with injected preemption between loads and CASes (ABA, reclamation)") {
  Chaos chaos(4);
  SUBCASE("inline tasks, pairs") { CheckClean(RunPairs<LockFreeQueue<uint64_t>>(4, 50'000)); }
  SUBCASE("out-of-line tasks, pairs") { CheckClean(RunPairs<LockFreeQueue<WideTask>>(4, 50'000)); }
  SUBCASE("out-of-line tasks, 3x3") { CheckClean(RunMpmc<LockFreeQueue<WideTask>>(3, 3, 50'000)); }
  SUBCASE("move-only tasks, pairs") {
    CheckClean(RunPairs<LockFreeQueue<std::unique_ptr<WideTask>>>(4, 50'000));
  }
  SUBCASE("no node cache, inline, pairs") {
    CheckClean(RunPairs<LfreeNoCache<uint64_t>>(4, 50'000));
  }
  SUBCASE("no node cache, out-of-line, 3x3") {
    CheckClean(RunMpmc<LfreeNoCache<WideTask>>(3, 3, 50'000));
  }
  // The chain walk reads nodes that others may recycle before its Head CAS.
  SUBCASE("chains, inline, pairs") { CheckClean(RunPairs<LockFreeQueue<uint64_t>>(4, 50'000, 70)); }
  SUBCASE("chains, inline, 3x3") { CheckClean(RunMpmc<LockFreeQueue<uint64_t>>(3, 3, 50'000, 70)); }
  SUBCASE("chains, no node cache, inline, 3x3") {
    CheckClean(RunMpmc<LfreeNoCache<uint64_t>>(3, 3, 50'000, 70));
  }
}

// Runs `scenario` once, the first time this thread reaches chaos point `where`.
struct HookOnce {
  std::function<void(const char*)> fn;
  HookOnce(const char* where, std::function<void()> scenario) {
    fn = [where, scenario, fired = false](const char* at) mutable {
      if (!fired && std::string_view(at) == where) {
        fired = true;
        scenario();
      }
    };
    rs_test_chaos::hook = &fn;
  }
  ~HookOnce() { rs_test_chaos::hook = nullptr; }
};

TEST_CASE("LFREE regression: free-list ABA (pop reads top X, next Y; X is reused meanwhile)") {
  // Without the free-list tag, the stalled pop's CAS sees X on top again and installs its stale
  // `next` Y, which by then is the queue's dummy; Y is then handed out twice. No node cache, so
  // every node goes through the shared free list.
  LockFreeQueue<uint64_t> queue(1, 0, 0);
  uint64_t out = 0;
  {
    HookOnce hook("alloc", [&] {
      queue.Push(0, uint64_t{2});     // takes X
      queue.Push(0, uint64_t{3});     // takes Y
      REQUIRE(queue.TryPop(0, out));  // frees the first dummy
      CHECK(out == 2);
      REQUIRE(queue.TryPop(0, out));  // frees X: X is back on top, Y is now the dummy
      CHECK(out == 3);
    });
    queue.Push(0, uint64_t{1});  // stalls inside its free-list pop, after reading X and Y
  }
  queue.Push(0, uint64_t{4});
  std::vector<uint64_t> got;
  for (int i = 0; i < 8 && queue.TryPop(0, out); ++i) got.push_back(out);
  CHECK(got == std::vector<uint64_t>{1, 4});
}

TEST_CASE("LFREE regression: Head ABA (dequeue reads Head D, next X; D is the dummy again)") {
  // Without the Head tag, the stalled dequeue's CAS succeeds on the recycled D and returns the
  // already dequeued task of X a second time.
  for (const bool out_of_line : {false, true}) {
    for (const uint32_t cache : {0u, LockFreeQueue<uint64_t>::kDefaultNodeCache}) {
      INFO("out-of-line tasks: ", out_of_line, ", node cache: ", cache);
      auto run = [](auto& queue, auto make, auto value) {
        using T = typename std::remove_reference_t<decltype(queue)>::value_type;
        queue.Push(0, make(1));
        T out{};
        bool popped = false;
        {
          HookOnce hook("dequeue", [&] {
            T other{};
            REQUIRE(queue.TryPop(0, other));  // Head D -> X; D is freed
            CHECK(value(other) == 1);
            queue.Push(0, make(2));           // reuses D: X -> D
            REQUIRE(queue.TryPop(0, other));  // Head X -> D; X is freed, D is the dummy again
            CHECK(value(other) == 2);
          });
          popped = queue.TryPop(0, out);  // stalls after reading Head = D and D.next = X
        }
        CHECK_FALSE(popped);  // everything was taken by the "other thread"
        CHECK_FALSE(queue.TryPop(0, out));
      };
      if (out_of_line) {
        LockFreeQueue<std::unique_ptr<uint64_t>> queue(1, 0, cache);
        run(
            queue, [](uint64_t v) { return std::make_unique<uint64_t>(v); },
            [](const std::unique_ptr<uint64_t>& p) { return p ? *p : 0; });
      } else {
        LockFreeQueue<uint64_t> queue(1, 0, cache);
        run(
            queue, [](uint64_t v) { return v; }, [](uint64_t v) { return v; });
      }
    }
  }
}

TEST_CASE("LFREE regression: link ABA (enqueuer about to CAS X.next; X freed and reallocated)") {
  // Thread A stalls right before linking after X (the last node). X is then dequeued, freed and
  // taken by thread B, which resets X.next to null and stalls before linking X. Without the tag
  // bump of that reset, A's CAS on X.next succeeds and A's task hangs off the unlinked X: A's
  // Push returns, yet the queue reads EMPTY. Workers: A = 0, main = 1, B = 2; no node cache, so
  // the freed X is on top of the shared free list for B.
  LockFreeQueue<uint64_t> queue(3, 0, 0);
  queue.Push(0, uint64_t{10});  // queue: D -> X(10)
  std::binary_semaphore a_stalled(0), a_go(0), b_stalled(0), b_go(0);
  std::thread a([&] {
    HookOnce hook("enqueue", [&] {
      a_stalled.release();
      a_go.acquire();
    });
    queue.Push(0, uint64_t{1});
  });
  a_stalled.acquire();          // A read Tail = X and X.next = null
  queue.Push(1, uint64_t{11});  // D -> X(10) -> Y(11)
  uint64_t out = 0;
  REQUIRE(queue.TryPop(1, out));  // 10; D freed
  REQUIRE(queue.TryPop(1, out));  // 11; X freed (top of the free list)
  CHECK(out == 11);
  std::thread b([&] {
    HookOnce hook("enqueue", [&] {
      b_stalled.release();
      b_go.acquire();
    });
    queue.Push(2, uint64_t{2});  // reuses X, resets X.next, stalls before linking it
  });
  b_stalled.acquire();
  a_go.release();
  a.join();  // A's Push has returned: its task must be reachable now
  const bool got_a = queue.TryPop(1, out);
  CHECK(got_a);
  if (got_a) CHECK(out == 1);
  b_go.release();
  b.join();
  std::vector<uint64_t> rest;
  for (int i = 0; i < 4 && queue.TryPop(1, out); ++i) rest.push_back(out);
  CHECK(rest.size() == 1);
  if (rest.size() == 1) CHECK(rest[0] == 2);
}

TEST_CASE("LFREE regression: a task is not recycled while its dequeuer still moves it") {
  // The paper's listing 5 frees the old dummy right after the CAS. Here the winning dequeuer
  // stalls before moving its task out while another thread dequeues past it and pushes new
  // tasks; the stalled task's node must not be reused (reference count) until it is moved.
  for (const uint32_t cache : {0u, 32u}) {
    INFO("node cache: ", cache);
    LockFreeQueue<std::unique_ptr<uint64_t>> queue(1, 0, cache);
    for (uint64_t v = 1; v <= 3; ++v) queue.Push(0, std::make_unique<uint64_t>(v));
    std::unique_ptr<uint64_t> out;
    std::vector<uint64_t> others;
    {
      HookOnce hook("dequeue_owned", [&] {
        std::unique_ptr<uint64_t> other;
        while (queue.TryPop(0, other)) others.push_back(*other);  // 2, 3; frees past our node
        for (uint64_t v = 10; v < 20; ++v) queue.Push(0, std::make_unique<uint64_t>(v));
      });
      REQUIRE(queue.TryPop(0, out));  // owns task 1, stalls before moving it
    }
    REQUIRE(out != nullptr);
    CHECK(*out == 1);
    CHECK(others == std::vector<uint64_t>{2, 3});
    std::vector<uint64_t> rest;
    while (queue.TryPop(0, out)) rest.push_back(*out);
    CHECK(rest.size() == 10);
    CHECK(rest.front() == 10);
    CHECK(rest.back() == 19);
  }
}

TEST_CASE("stress checks can fail: a duplicated, a lost and a reordered task are reported") {
  StressResult r;
  r.expected = 4;
  Tally({{0, 1}, {1, 3}}, &r);  // 1 twice, 2 never
  CHECK(r.duplicates == 1);
  CHECK(r.missing == 1);
  Consumer<uint64_t> c(2, 10, 4);
  c.Take(Codec<uint64_t>::Make(1, 5));
  c.Take(Codec<uint64_t>::Make(1, 4));  // producer 1 went backwards
  c.Take(Codec<uint64_t>::Make(7, 0));  // no producer 7
  CHECK(c.order_violations == 1);
  CHECK(c.bad_payloads == 1);
  WideTask torn = Codec<WideTask>::Make(3, 9);
  torn.words[5] ^= 1;
  uint32_t p = 0;
  uint32_t s = 0;
  CHECK_FALSE(Codec<WideTask>::Decode(torn, &p, &s));
}

// ---------------------------------------------------------------------------------------------
// Render-like frames: the application thread pushes primary tasks, releases the workers with a
// barrier, workers pop until EMPTY and push each task's child (secondary rays) until
// max_depth, then meet at the closing barrier (paper listings 2 and 3).

struct FrameTask {
  uint32_t id = 0;        // primary task index within the frame
  uint32_t depth = 0;     // 0 = primary
  uint32_t producer = 0;  // worker that pushed it; num_workers = application thread
  uint32_t seq = 0;       // per-producer push counter within the frame
};

struct FrameResult {
  uint64_t processed = 0;
  uint64_t duplicates = 0;
  uint64_t missing = 0;
  uint64_t order_violations = 0;
  uint64_t wrong_worker = 0;  // LOCAL only: a task popped by a worker that does not own it
  uint64_t left_over = 0;     // tasks still queued after the closing barrier
};

template <class Q>
FrameResult RunFrames(int workers, uint32_t primaries, uint32_t max_depth, int frames) {
  Q queue(workers);
  const uint64_t per_frame = uint64_t{primaries} * (max_depth + 1);
  FrameResult result;
  std::vector<uint8_t> seen(per_frame);
  // Per-worker records of one frame, written by the worker, read by the application thread
  // after the closing barrier.
  struct Record {
    std::vector<uint64_t> keys;
    uint64_t order_violations = 0;
    uint64_t wrong_worker = 0;
  };
  std::vector<Record> records(workers);
  std::barrier release(workers + 1);
  std::barrier finished(workers + 1);
  std::atomic<bool> end{false};
  std::vector<std::thread> threads;
  for (int w = 0; w < workers; ++w) {
    threads.emplace_back([&, w] {
      std::vector<int64_t> last(workers + 1);
      for (;;) {
        release.arrive_and_wait();                        // listing 2, line 3
        if (end.load(std::memory_order_relaxed)) return;  // ordered by the barrier
        Record& rec = records[w];
        std::fill(last.begin(), last.end(), -1);
        uint32_t pushed = 0;
        FrameTask task;
        while (queue.TryPop(w, task)) {
          if (static_cast<int64_t>(task.seq) <= last[task.producer]) ++rec.order_violations;
          last[task.producer] = task.seq;
          if constexpr (Q::kKind == QueueKind::kLocal) {
            const uint32_t owner = task.depth == 0 ? task.id % workers : task.producer;
            if (owner != static_cast<uint32_t>(w)) ++rec.wrong_worker;
          }
          rec.keys.push_back(uint64_t{task.depth} * primaries + task.id);
          if (task.depth < max_depth) {
            queue.Push(w, FrameTask{task.id, task.depth + 1, static_cast<uint32_t>(w), pushed++});
          }
        }
        finished.arrive_and_wait();  // listing 2, line 12
      }
    });
  }
  for (int f = 0; f < frames; ++f) {
    if constexpr (Q::kKind == QueueKind::kLocal) queue.RewindPrimary();
    for (uint32_t i = 0; i < primaries; ++i) {
      queue.PushPrimary(FrameTask{i, 0, static_cast<uint32_t>(workers), i});
    }
    release.arrive_and_wait();   // listing 3, line 7: release the render threads
    finished.arrive_and_wait();  // listing 3, line 9: wait for the frame to finish
    std::fill(seen.begin(), seen.end(), 0);
    for (Record& rec : records) {
      for (const uint64_t key : rec.keys) {
        if (seen[key]++ != 0) ++result.duplicates;
        ++result.processed;
      }
      result.order_violations += rec.order_violations;
      result.wrong_worker += rec.wrong_worker;
      rec = Record{};
    }
    for (const uint8_t s : seen) result.missing += (s == 0);
    for (int w = 0; w < workers; ++w) {
      FrameTask task;
      while (queue.TryPop(w, task)) ++result.left_over;
    }
  }
  end.store(true, std::memory_order_relaxed);
  release.arrive_and_wait();
  for (auto& t : threads) t.join();
  CHECK(result.processed == per_frame * frames);
  CHECK(result.duplicates == 0);
  CHECK(result.missing == 0);
  CHECK(result.order_violations == 0);
  CHECK(result.wrong_worker == 0);
  CHECK(result.left_over == 0);
  return result;
}

TEST_CASE("LOCAL: fill, release, per-worker secondary tasks; >= 1e6 tasks per frame") {
  // 250k primaries x 4 generations = 1e6 tasks per frame; 2 frames test barrier and queue reuse.
  SUBCASE("1 worker") { RunFrames<LocalQueues<FrameTask>>(1, 250'000, 3, 1); }
  SUBCASE("4 workers, 2 frames") { RunFrames<LocalQueues<FrameTask>>(4, 250'000, 3, 2); }
  SUBCASE("8 workers") { RunFrames<LocalQueues<FrameTask>>(8, 250'000, 3, 1); }
}

TEST_CASE("shared queues under the render loop pattern") {
  SUBCASE("LOCK") { RunFrames<LockQueue<FrameTask>>(4, 50'000, 3, 2); }
  SUBCASE("LOCK spin") { RunFrames<LockQueue<FrameTask, NoQueueStats, SpinLock>>(4, 50'000, 3, 2); }
  SUBCASE("LFREE") { RunFrames<LockFreeQueue<FrameTask>>(4, 50'000, 3, 2); }
  SUBCASE("LFREE, 8 workers, timed") {
    RunFrames<LockFreeQueue<FrameTask, QueueTimeStats>>(8, 20'000, 3, 2);
  }
}

// ---------------------------------------------------------------------------------------------
// Single-threaded contracts, for every kind.

template <class Q>
void SingleThreadFifo() {
  Q queue(2);
  uint64_t out = 7;
  CHECK_FALSE(queue.TryPop(0, out));  // fresh queue is EMPTY
  CHECK(out == 7);                    // and `out` is untouched
  for (uint64_t i = 0; i < 5000; ++i) queue.Push(0, uint64_t{i});
  for (uint64_t i = 0; i < 5000; ++i) {
    REQUIRE(queue.TryPop(0, out));
    CHECK(out == i);
  }
  CHECK_FALSE(queue.TryPop(0, out));
  // Interleaved: queue length oscillates between 0 and 3.
  uint64_t next_in = 0;
  uint64_t next_out = 0;
  for (int round = 0; round < 1000; ++round) {
    for (int k = 0; k < 3; ++k) queue.Push(0, uint64_t{next_in++});
    for (int k = 0; k < 3; ++k) {
      REQUIRE(queue.TryPop(0, out));
      CHECK(out == next_out++);
    }
    CHECK_FALSE(queue.TryPop(0, out));
  }
  const uint64_t copy = 42;
  queue.Push(0, copy);  // const T& overload
  REQUIRE(queue.TryPop(0, out));
  CHECK(out == 42);
  // PushMany / TryPopMany keep the order, with each other and with lone operations; a
  // TryPopMany takes what there is, leaves `out` alone past its count, and says 0 on EMPTY.
  std::vector<uint64_t> in(200);
  std::vector<uint64_t> got(300, 7);
  for (uint64_t i = 0; i < 200; ++i) in[i] = 1000 + i;
  queue.PushMany(0, std::span<uint64_t>(in.data(), 150));
  queue.Push(0, uint64_t{1150});
  queue.PushMany(0, std::span<uint64_t>(in.data() + 151, 49));
  queue.PushMany(0, std::span<uint64_t>());  // nothing
  REQUIRE(queue.TryPop(0, out));
  CHECK(out == 1000);
  CHECK(queue.TryPopMany(0, std::span<uint64_t>(got.data(), 3)) == 3);
  CHECK(got[0] == 1001);
  CHECK(got[2] == 1003);
  CHECK(got[3] == 7);
  const size_t rest = queue.TryPopMany(0, std::span<uint64_t>(got));
  CHECK(rest == 196);
  bool in_order = true;
  for (size_t i = 0; i < rest; ++i) in_order = in_order && got[i] == 1004 + i;
  CHECK(in_order);
  CHECK(got[rest] == 7);
  CHECK(queue.TryPopMany(0, std::span<uint64_t>(got)) == 0);
  CHECK(queue.TryPopMany(0, std::span<uint64_t>()) == 0);
  CHECK_FALSE(queue.TryPop(0, out));
}

TEST_CASE("FIFO order and EMPTY, single thread") {
  SUBCASE("LOCK") { SingleThreadFifo<LockQueue<uint64_t>>(); }
  SUBCASE("LOCK spin") { SingleThreadFifo<LockQueue<uint64_t, NoQueueStats, SpinLock>>(); }
  SUBCASE("LFREE") { SingleThreadFifo<LockFreeQueue<uint64_t>>(); }
  SUBCASE("LFREE out-of-line") {
    // 16-byte task forces the reference-counted path with the same test.
    struct Pair {
      uint64_t a, b;
    };
    LockFreeQueue<Pair> queue(1);
    Pair out{};
    CHECK_FALSE(queue.TryPop(0, out));
    for (uint64_t i = 0; i < 3000; ++i) queue.Push(0, Pair{i, ~i});
    for (uint64_t i = 0; i < 3000; ++i) {
      REQUIRE(queue.TryPop(0, out));
      CHECK(out.a == i);
      CHECK(out.b == ~i);
    }
    CHECK_FALSE(queue.TryPop(0, out));
  }
  SUBCASE("LOCAL") { SingleThreadFifo<LocalQueues<uint64_t>>(); }
}

TEST_CASE("LOCAL: queues are private, primaries are dealt round-robin, no stealing") {
  LocalQueues<int> queues(3);
  for (int i = 0; i < 10; ++i) queues.PushPrimary(int{i});
  CHECK(queues.size(0) == 4);  // 0 3 6 9
  CHECK(queues.size(1) == 3);  // 1 4 7
  CHECK(queues.size(2) == 3);  // 2 5 8
  queues.Push(1, 100);
  int out = -1;
  std::vector<int> lane1;
  while (queues.TryPop(1, out)) lane1.push_back(out);
  CHECK(lane1 == std::vector<int>{1, 4, 7, 100});
  CHECK_FALSE(queues.TryPop(1, out));  // empty although lanes 0 and 2 still hold tasks
  CHECK(queues.size(0) == 4);
  queues.RewindPrimary();
  queues.PushPrimary(int{50});
  CHECK(queues.size(0) == 5);
  for (int expect : {0, 3, 6, 9, 50}) {
    REQUIRE(queues.TryPop(0, out));
    CHECK(out == expect);
  }
}

TEST_CASE("LFREE pool grows geometrically and steady traffic reuses nodes") {
  LockFreeQueue<uint64_t> queue(1);
  CHECK(queue.capacity() == 64);
  for (uint64_t i = 0; i < 10'000; ++i) queue.Push(0, uint64_t{i});
  const size_t grown = queue.capacity();
  CHECK(grown >= 10'001);
  CHECK(grown < 2 * 10'001 + 64);
  uint64_t out = 0;
  for (uint64_t i = 0; i < 10'000; ++i) {
    REQUIRE(queue.TryPop(0, out));
    REQUIRE(out == i);
  }
  for (uint64_t i = 0; i < 100'000; ++i) {
    queue.Push(0, uint64_t{i});
    REQUIRE(queue.TryPop(0, out));
  }
  CHECK(queue.capacity() == grown);
  LockFreeQueue<WideTask> reserved(1, 1000);
  CHECK(reserved.capacity() >= 1000);
}

template <class Q>
void LeftOverTasksAreDestroyed() {
  const int before = Tracked::live.load(std::memory_order_relaxed);
  {
    // 5000 tasks, 3000 taken: LOCAL's 16-byte tasks span 3 blocks (1024 each) per lane, the
    // first one emptied and recycled, the second partly consumed.
    Q queue(2);
    for (int i = 0; i < 5000; ++i) queue.Push(i % 2, Tracked(i));
    Tracked out;
    for (int i = 0; i < 3000; ++i) {
      REQUIRE(queue.TryPop(i % 2, out));
      REQUIRE(out.value == i);  // FIFO (per lane for LOCAL: lane i % 2 holds i, i + 2, ...)
    }
    CHECK(out.heap != nullptr);
    CHECK(*out.heap == out.value);
    CHECK(Tracked::live.load(std::memory_order_relaxed) == before + 1 + 2000);
  }  // ~Q destroys 2000 queued tasks; ASan's leak check sees their heap ints otherwise
  CHECK(Tracked::live.load(std::memory_order_relaxed) == before);
}

TEST_CASE("destruction with tasks left destroys them (move-only, heap-owning tasks)") {
  SUBCASE("LOCK") { LeftOverTasksAreDestroyed<LockQueue<Tracked>>(); }
  SUBCASE("LFREE") { LeftOverTasksAreDestroyed<LockFreeQueue<Tracked>>(); }
  SUBCASE("LOCAL") { LeftOverTasksAreDestroyed<LocalQueues<Tracked>>(); }
  SUBCASE("unique_ptr left in every kind") {
    LockQueue<std::unique_ptr<int>> lock(1);
    LockFreeQueue<std::unique_ptr<int>> lfree(1);
    LocalQueues<std::unique_ptr<int>> local(1);
    for (int i = 0; i < 100; ++i) {
      lock.Push(0, std::make_unique<int>(i));
      lfree.Push(0, std::make_unique<int>(i));
      local.Push(0, std::make_unique<int>(i));
    }
    std::unique_ptr<int> out;
    REQUIRE(lfree.TryPop(0, out));
    CHECK(*out == 0);
  }
}

// ---------------------------------------------------------------------------------------------
// Queue-time statistics.

template <class Q>
void StatsCount() {
  Q queue(3);
  int out = 0;
  for (int i = 0; i < 100; ++i) queue.Push(1, int{i});
  for (int i = 0; i < 100; ++i) REQUIRE(queue.TryPop(1, out));
  CHECK_FALSE(queue.TryPop(1, out));  // an EMPTY poll is queue time too
  queue.PushPrimary(int{5});
  const QueueTimeStats& stats = queue.stats();
  CHECK(stats.num_slots() == 4);
  CHECK(stats.Ops(0) == 0);
  CHECK(stats.Ops(1) == 201);
  CHECK(stats.Ops(2) == 0);
  CHECK(stats.Ops(3) == 1);  // application slot
  CHECK(stats.TotalOps() == 202);
  CHECK(stats.Ticks(1) > 0);
  CHECK(stats.Seconds(1) > 0.0);
  CHECK(stats.Seconds(1) < 1.0);
  CHECK(stats.Seconds(0) == 0.0);
  CHECK(stats.TotalSeconds() == doctest::Approx(stats.Seconds(1) + stats.Seconds(3)));
  queue.stats().Reset();
  CHECK(queue.stats().TotalOps() == 0);
  CHECK(queue.stats().TotalSeconds() == 0.0);
}

TEST_CASE("queue-time statistics count each thread's operations and time") {
  SUBCASE("LOCK") { StatsCount<LockQueue<int, QueueTimeStats>>(); }
  SUBCASE("LFREE") { StatsCount<LockFreeQueue<int, QueueTimeStats>>(); }
  SUBCASE("LOCAL") { StatsCount<LocalQueues<int, QueueTimeStats>>(); }
  SUBCASE("clock calibration") {
    const double spt = QueueClock::SecondsPerTick();
    CHECK(spt > 1e-11);  // < 100 GHz
    CHECK(spt < 1e-6);   // > 1 MHz
    const uint64_t t0 = QueueClock::Now();
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
    const double measured = static_cast<double>(QueueClock::Now() - t0) * spt;
    CHECK(measured > 0.019);
    CHECK(measured < 0.5);
  }
}

TEST_CASE("SpinLock gives mutual exclusion") {
  SpinLock lock;
  uint64_t counter = 0;  // plain: TSan reports a race if the lock fails
  std::vector<std::thread> threads;
  for (int t = 0; t < 4; ++t) {
    threads.emplace_back([&] {
      for (int i = 0; i < 100'000; ++i) {
        std::lock_guard<SpinLock> guard(lock);
        ++counter;
      }
    });
  }
  for (auto& t : threads) t.join();
  CHECK(counter == 400'000);
  CHECK(lock.try_lock());
  CHECK_FALSE(lock.try_lock());
  lock.unlock();
}

TEST_CASE("queue kind names") {
  CHECK(QueueKindName(QueueKind::kLock) == "LOCK");
  CHECK(QueueKindName(QueueKind::kLockFree) == "LFREE");
  CHECK(QueueKindName(QueueKind::kLocal) == "LOCAL");
  QueueKind kind = QueueKind::kLock;
  CHECK(ParseQueueKind("LFREE", &kind));
  CHECK(kind == QueueKind::kLockFree);
  CHECK(ParseQueueKind("local", &kind));
  CHECK(kind == QueueKind::kLocal);
  CHECK_FALSE(ParseQueueKind("steal", &kind));
  CHECK(kind == QueueKind::kLocal);
  static_assert(LockQueue<int>::kKind == QueueKind::kLock);
  static_assert(LockFreeQueue<int>::kKind == QueueKind::kLockFree);
  static_assert(LocalQueues<int>::kKind == QueueKind::kLocal);
}

}  // namespace
}  // namespace rs
