// Work-queue interface shared by the LOCK, LFREE and LOCAL task queues (Nunes & Santos, section
// 4), plus what they share: the WorkQueue concept, a TTAS spinlock, and per-thread counters of
// time spent inside queue operations (the paper's Figure 7) that compile to nothing when off.
#pragma once

#include <atomic>
#include <chrono>
#include <concepts>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <span>
#include <string_view>
#include <thread>
#include <type_traits>
#include <utility>

#if defined(__x86_64__) || defined(__i386__)
#include <x86intrin.h>
#define RS_QUEUE_HAVE_RDTSC 1
#else
#define RS_QUEUE_HAVE_RDTSC 0
#endif

// Test hook placed between a lock-free load and the CAS that depends on it; `where` names the
// point ("alloc", "enqueue", "dequeue", "dequeue_owned"). Empty (no code) unless a test defines
// it before including the queue headers: tests/sched/queue_test.cc makes it yield at random, so
// ABA and reclamation windows a few ns wide become easy to hit, and replays exact ABA
// interleavings by running other queue operations from inside the hook.
#ifndef RS_QUEUE_CHAOS_POINT
#define RS_QUEUE_CHAOS_POINT(where) static_cast<void>(0)
#endif

namespace rs {

// Destructive interference size used to keep independently written fields apart. 128, not 64:
// Intel's adjacent-line prefetcher pulls 64-byte lines in pairs, so two hot atomics 64 bytes
// apart still contend. (std::hardware_destructive_interference_size trips GCC's
// -Winterference-size in headers and would differ between compilers.)
inline constexpr size_t kQueueFalseSharing = 128;

// The three queue designs of the paper. Names match the paper's figures.
enum class QueueKind : int { kLock = 0, kLockFree = 1, kLocal = 2 };

constexpr std::string_view QueueKindName(QueueKind kind) {
  switch (kind) {
    case QueueKind::kLock:
      return "LOCK";
    case QueueKind::kLockFree:
      return "LFREE";
    case QueueKind::kLocal:
      return "LOCAL";
  }
  return "?";
}

// Parses "LOCK" / "LFREE" / "LOCAL" (also lower case). Returns false for anything else and leaves
// *kind unchanged, so the caller can throw rs::Error naming the option.
constexpr bool ParseQueueKind(std::string_view name, QueueKind* kind) {
  if (name == "LOCK" || name == "lock") {
    *kind = QueueKind::kLock;
  } else if (name == "LFREE" || name == "lfree" || name == "lockfree") {
    *kind = QueueKind::kLockFree;
  } else if (name == "LOCAL" || name == "local") {
    *kind = QueueKind::kLocal;
  } else {
    return false;
  }
  return true;
}

// What a task must be: a movable value whose move and destruction cannot throw. Queue operations
// move tasks after they have been linked or unlinked, where an exception could not be undone.
// Copyability is optional (move-only tasks such as std::unique_ptr work).
template <class T>
concept QueueTask =
    std::is_object_v<T> && !std::is_const_v<T> && std::is_nothrow_move_constructible_v<T> &&
    std::is_nothrow_move_assignable_v<T> && std::is_nothrow_destructible_v<T>;

// The interface the renderer's thread loop is written against (paper listing 2), implemented by
// LockQueue (queue_lock.h), LockFreeQueue (queue_lockfree.h) and LocalQueues (queue_local.h):
//   q.Push(worker, std::move(task))   addRays: enqueue a task (a secondary task from worker).
//   q.PushPrimary(std::move(task))    the application thread's Generate_PrimRays (listing 3).
//   q.TryPop(worker, task) -> bool    getRays: false means EMPTY (for LOCAL: this worker's queue).
//   q.PushMany(worker, tasks)         Push of tasks[0], tasks[1], ... in order, as one operation
//                                     (one lock / one link for the lot where the design allows).
//   q.TryPopMany(worker, out) -> n    up to out.size() oldest tasks, in order; 0 means EMPTY.
// worker is in [0, num_workers()) and identifies the calling thread: at most one thread uses a
// given id at a time (it selects LOCAL's queue, LFREE's node cache and the statistics slot);
// PushPrimary has an id of its own, so one application thread calls it at a time. On EMPTY,
// TryPop leaves `task` untouched (TryPopMany: out past the count). Push and PushMany may throw
// std::bad_alloc (the queue is unchanged then); nothing else throws. All queues are FIFO: tasks
// pushed by one thread are popped in push order (for LOCAL, per worker queue).
template <class Q>
concept WorkQueue = QueueTask<typename Q::value_type> &&
    requires(Q& q, const Q& cq, typename Q::value_type&& task, typename Q::value_type& out,
             int worker) {
  typename Q::stats_type;
  { Q::kKind } -> std::convertible_to<QueueKind>;
  { q.Push(worker, std::move(task)) } -> std::same_as<void>;
  { q.PushPrimary(std::move(task)) } -> std::same_as<void>;
  { q.TryPop(worker, out) } -> std::same_as<bool>;
  { q.PushMany(worker, std::span<typename Q::value_type>()) } -> std::same_as<void>;
  { q.TryPopMany(worker, std::span<typename Q::value_type>()) } -> std::same_as<size_t>;
  { cq.num_workers() } -> std::same_as<int>;
  { cq.stats() } -> std::same_as<const typename Q::stats_type&>;
};

namespace queue_detail {

inline void CpuRelax() noexcept {
#if RS_QUEUE_HAVE_RDTSC
  _mm_pause();
#endif
}

}  // namespace queue_detail

// Test-and-test-and-set spinlock (Herlihy & Shavit 7.3) that yields to the OS after a short
// spin, so a preempted holder does not stall waiters for a whole time slice when threads
// outnumber cores. Satisfies Lockable; use with std::lock_guard. Not recursive, not fair.
class SpinLock {
 public:
  void lock() noexcept {
    for (;;) {
      if (!locked_.exchange(true, std::memory_order_acquire)) return;
      int spins = 0;
      while (locked_.load(std::memory_order_relaxed)) {
        if (++spins < kSpinsBeforeYield) {
          queue_detail::CpuRelax();
        } else {
          std::this_thread::yield();
          spins = 0;
        }
      }
    }
  }
  bool try_lock() noexcept {
    return !locked_.load(std::memory_order_relaxed) &&
           !locked_.exchange(true, std::memory_order_acquire);
  }
  void unlock() noexcept { locked_.store(false, std::memory_order_release); }

 private:
  // ~64 pauses are a few microseconds on current Intel cores (PAUSE ~ 40-140 cycles): longer
  // than any queue critical section, far shorter than a scheduler time slice.
  static constexpr int kSpinsBeforeYield = 64;
  std::atomic<bool> locked_{false};
};

// Clock of the queue-time counters. On x86 it is the time-stamp counter (RDTSC, unserialized:
// the counters sum many short intervals, so a few cycles of reordering do not matter). It is
// invariant (constant_tsc, nonstop_tsc) on x86-64 CPUs of the last 15 years and, measured on this
// KVM guest (bench/sched/queue_bench.cc BM_ClockRdtsc vs BM_ClockSteady), 8 ns per read against
// 19 ns for steady_clock::now() (vDSO), so a timed queue operation costs ~17 ns instead of ~40 ns.
// Elsewhere it is std::chrono::steady_clock in nanoseconds.
struct QueueClock {
  static uint64_t Now() noexcept {
#if RS_QUEUE_HAVE_RDTSC
    return __rdtsc();
#else
    return static_cast<uint64_t>(std::chrono::duration_cast<std::chrono::nanoseconds>(
                                     std::chrono::steady_clock::now().time_since_epoch())
                                     .count());
#endif
  }

  // Seconds per tick. For the TSC it is measured against steady_clock over the span since the
  // process started (the anchor below, taken during static initialization) without waiting: by
  // the time a frame's queue times are converted, that span holds the scene's load and the
  // frame, and steady_clock's nanoseconds over it make the rate good to 1e-4 or better. A span
  // under 2 ms is waited out (to about 1e-5). The rate is refined on every call until the span
  // passes 1 s, then fixed. Thread-safe. (It used to spin 20 ms on first use, which was inside
  // the first frame of every render with queue statistics: 20 ms on a 30-100 ms frame.)
  static double SecondsPerTick() {
#if RS_QUEUE_HAVE_RDTSC
    static std::atomic<double> fixed{0.0};
    const double known = fixed.load(std::memory_order_relaxed);
    if (known > 0.0) return known;
    using Clock = std::chrono::steady_clock;
    Clock::time_point t;
    uint64_t c = 0;
    do {
      t = Clock::now();
      c = __rdtsc();
    } while (t - kAnchor.time < std::chrono::milliseconds(2));
    const double seconds = std::chrono::duration<double>(t - kAnchor.time).count();
    const double rate = c > kAnchor.tsc ? seconds / static_cast<double>(c - kAnchor.tsc) : 1e-9;
    if (seconds >= 1.0) fixed.store(rate, std::memory_order_relaxed);
    return rate;
#else
    return 1e-9;
#endif
  }

 private:
#if RS_QUEUE_HAVE_RDTSC
  struct Anchor {
    std::chrono::steady_clock::time_point time;
    uint64_t tsc;
  };
  static inline const Anchor kAnchor{std::chrono::steady_clock::now(), __rdtsc()};
#endif
};

// Statistics policy "off": an empty type whose Measure() returns an empty scope. With
// [[no_unique_address]] in the queues, a queue with NoQueueStats has no counter fields and its
// operations contain no clock reads (zero cost, checked in tests/sched/queue_test.cc).
class NoQueueStats {
 public:
  static constexpr bool kEnabled = false;
  struct Scope {};
  explicit NoQueueStats(int /*num_workers*/) {}
  Scope Measure(int /*slot*/) noexcept { return {}; }
};

// Statistics policy "on": per-thread aggregate time spent inside queue operations (including
// waiting for locks and failed EMPTY polls) and the number of operations (calls: a PushMany or
// TryPopMany is one, whatever its count of tasks), one cache-line-padded
// slot per worker plus one slot (index num_workers) for the application thread's PushPrimary.
// Each slot is written only by its own thread (relaxed load + store, no read-modify-write);
// read the totals after the frame's closing barrier, which orders them (happens-before) after
// the workers' writes. Reset() must not run concurrently with queue operations.
class QueueTimeStats {
 public:
  static constexpr bool kEnabled = true;

 private:
  struct alignas(kQueueFalseSharing) Slot {
    std::atomic<uint64_t> ticks{0};
    std::atomic<uint64_t> ops{0};
  };

 public:
  // RAII timer of one queue operation; adds the elapsed ticks to its slot when destroyed.
  class Scope {
   public:
    explicit Scope(Slot& slot) noexcept : slot_(slot), start_(QueueClock::Now()) {}
    ~Scope() {
      const uint64_t now = QueueClock::Now();
      const uint64_t elapsed = now > start_ ? now - start_ : 0;  // never wraps if TSCs disagree
      slot_.ticks.store(slot_.ticks.load(std::memory_order_relaxed) + elapsed,
                        std::memory_order_relaxed);
      slot_.ops.store(slot_.ops.load(std::memory_order_relaxed) + 1, std::memory_order_relaxed);
    }
    Scope(const Scope&) = delete;
    Scope& operator=(const Scope&) = delete;

   private:
    Slot& slot_;
    uint64_t start_;
  };

  explicit QueueTimeStats(int num_workers)
      : num_slots_(num_workers + 1), slots_(std::make_unique<Slot[]>(num_workers + 1)) {}

  // slot in [0, num_workers]; num_workers is the application thread.
  Scope Measure(int slot) noexcept { return Scope(slots_[slot]); }

  int num_slots() const { return num_slots_; }
  uint64_t Ticks(int slot) const { return slots_[slot].ticks.load(std::memory_order_relaxed); }
  uint64_t Ops(int slot) const { return slots_[slot].ops.load(std::memory_order_relaxed); }
  double Seconds(int slot) const {
    return static_cast<double>(Ticks(slot)) * QueueClock::SecondsPerTick();
  }
  // Aggregate queue access time summed over all threads (the paper's Figure 7 quantity).
  double TotalSeconds() const {
    uint64_t ticks = 0;
    for (int s = 0; s < num_slots_; ++s) ticks += Ticks(s);
    return static_cast<double>(ticks) * QueueClock::SecondsPerTick();
  }
  uint64_t TotalOps() const {
    uint64_t ops = 0;
    for (int s = 0; s < num_slots_; ++s) ops += Ops(s);
    return ops;
  }
  void Reset() {
    for (int s = 0; s < num_slots_; ++s) {
      slots_[s].ticks.store(0, std::memory_order_relaxed);
      slots_[s].ops.store(0, std::memory_order_relaxed);
    }
  }

 private:
  int num_slots_;
  std::unique_ptr<Slot[]> slots_;
};

}  // namespace rs
