// The iRT frame loop (Nunes & Santos, listings 2 and 3): N symmetric render threads created once,
// parked at a barrier between frames; the application thread releases them, may run its own logic,
// and waits for the frame at a second barrier; an END flag stops them. Measures, per thread and
// frame, the time spent working and the time spent idle at the closing barrier (the paper's Fig.
// 6).
#pragma once

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstddef>
#include <cstdint>
#include <exception>
#include <functional>
#include <memory>
#include <mutex>
#include <thread>
#include <vector>

namespace rs {

// Cyclic barrier for a fixed set of participants that also stamps the moment each phase
// completes (the last arrival), so a waiter's idle time excludes its own wake-up latency.
// A waiter spins briefly (a few microseconds, pausing) and then blocks on a condition variable:
// blocking matters when threads outnumber cores (2 cores here), where a spinning waiter would
// steal the time slice of the thread it waits for.
//
// Memory order: arrivals serialize on a mutex; the last arriver stamps the completion time and
// advances the phase with a release store under that mutex; waiters leave after an acquire load
// of the phase (spin) or under the mutex (block). So everything a participant did before
// ArriveAndWait happens-before everything every participant does after it returns (the same
// guarantee as std::barrier). std::barrier is not used: it cannot report the completion time, and
// it cannot shrink when a thread fails to start.
class FrameBarrier {
 public:
  using Clock = std::chrono::steady_clock;

  // participants >= 1.
  explicit FrameBarrier(int participants);
  FrameBarrier(const FrameBarrier&) = delete;
  FrameBarrier& operator=(const FrameBarrier&) = delete;

  // Blocks until `participants` threads have arrived in this phase; returns the time the phase
  // completed (the last arrival). Never throws (std::mutex errors terminate).
  Clock::time_point ArriveAndWait() noexcept;

  // Lowers the participant count (a thread that will never arrive, e.g. one that failed to
  // start); completes the current phase if everyone still counted has arrived.
  void SetParticipants(int participants) noexcept;

 private:
  void CompleteLocked() noexcept;

  std::mutex mutex_;
  std::condition_variable cv_;
  int participants_;
  int arrived_ = 0;                 // under mutex_
  std::atomic<uint64_t> phase_{0};  // written under mutex_ (release), spun on (acquire)
  Clock::time_point completion_{};  // written under mutex_ before phase_ advances
};

// Termination detection for a frame whose tasks create tasks, with shared queues (LOCK, LFREE):
// EMPTY does not mean done, because another thread may be processing a task whose children are
// not pushed yet. The count is the number of tasks pushed and not yet fully processed:
//   application: Reset(primary tasks) before the opening barrier (the barrier publishes it);
//   worker:      pop a task, process it, collect its k children; Retire(k) (the k children
//                counted and the parent retired in ONE read-modify-write, before any child is
//                visible); then push the children;
//   worker:      on EMPTY, leave the frame iff Done(); otherwise pause / yield and poll again.
// Why Done() becomes true only when every task is finished: all updates are RMWs on one atomic,
// so they form one modification order. A child is counted by its parent's Retire, which is
// sequenced before the child's Push; the Push synchronizes with the child's Pop (the queues'
// release/acquire), which is sequenced before the child's own Retire. So the parent's update
// precedes the child's in the modification order (write-write coherence), the running value
// includes every child from before it can be popped until after it was processed, it is >= 1
// while any task exists, and it never leaves 0 again once there.
// Memory orders: Retire is acq_rel and Done an acquire load, so a thread that sees 0 also sees
// every processed task's effects (the image does not need it, the closing barrier orders those,
// but it keeps the argument local); the counting itself needs only the RMW's atomicity.
// One RMW per task (not one per push) keeps its cache-line traffic at the queue's own level.
// Without the count, a thread leaving at the first EMPTY still yields a complete image (the
// pusher keeps polling its own children) but idles at the barrier while others still work.
class TaskCount {
 public:
  // Application thread, before the opening barrier (relaxed: the barrier publishes it).
  void Reset(int64_t tasks) { count_.store(tasks, std::memory_order_relaxed); }
  // A task is fully processed and its `children` are about to be pushed.
  void Retire(int64_t children) { count_.fetch_add(children - 1, std::memory_order_acq_rel); }
  // No task is queued or being processed: leave the frame.
  bool Done() const { return count_.load(std::memory_order_acquire) == 0; }
  int64_t value() const { return count_.load(std::memory_order_relaxed); }

 private:
  alignas(128) std::atomic<int64_t> count_{0};
};

// Per render thread, one frame.
struct FrameLoopTimes {
  double busy_seconds = 0;  // opening-barrier completion -> this thread's arrival at the closing
                            // barrier (includes its wake-up latency)
  double idle_seconds = 0;  // its arrival at the closing barrier -> that barrier's completion
                            // (waiting for the other threads and the application: Fig. 6)
  double cpu_seconds = 0;   // the thread's CPU time inside work(worker) (CLOCK_THREAD_CPUTIME_ID):
                            // equals busy_seconds on an idle machine with a core per thread;
                            // less when the thread was preempted (other load, oversubscription)
};

// CPU time consumed so far by the calling thread, in seconds (0 if the clock is unavailable).
double ThreadCpuSeconds();

// Owns the render threads. Usage (listing 3), from ONE application thread:
//   FrameLoop loop(n, [&](int worker) { ... drain the queue ... });
//   for each frame: fill queues; loop.Release(); application_logic2(); loop.Wait(); read results
//   (destructor: END flag, threads released and joined)
// Between Wait() and the next Release() the threads are parked at the opening barrier, so the
// application thread may touch any per-frame state without synchronization: Release() and
// Wait() are both full happens-before edges (see FrameBarrier).
//
// Deviation from listing 2: the paper tests END before the opening barrier, so a thread released
// by the final barrier would start one more frame and wait at a closing barrier nobody else
// joins. Here a thread tests END right after the opening barrier and leaves.
class FrameLoop {
 public:
  using Clock = FrameBarrier::Clock;
  using Work = std::function<void(int worker)>;

  // Starts num_threads >= 1 render threads that call work(worker), worker in [0, num_threads),
  // once per frame. work may throw: the first exception of a frame is rethrown by Wait().
  // Throws rs::Error if num_threads < 1 or > kMaxThreads, std::system_error if a thread cannot
  // be started (the threads already started are stopped first).
  FrameLoop(int num_threads, Work work);
  // Shutdown(); never throws.
  ~FrameLoop();
  FrameLoop(const FrameLoop&) = delete;
  FrameLoop& operator=(const FrameLoop&) = delete;

  static constexpr int kMaxThreads = 1024;

  int num_threads() const { return num_threads_; }
  bool in_frame() const { return in_frame_; }
  uint64_t frames() const { return frames_; }  // completed frames

  // Listing 3 line 7: joins the opening barrier, starting a frame on every thread. Returns the
  // barrier's completion time. Precondition: not in a frame (throws rs::Error otherwise).
  Clock::time_point Release();

  // Listing 3 line 9: joins the closing barrier, returning when every thread has finished its
  // work(worker) call; then times() holds this frame's figures. Rethrows the first exception a
  // work call threw in this frame (the loop stays usable). Precondition: in a frame.
  Clock::time_point Wait();

  // Per thread, the last completed frame (valid after Wait()).
  const std::vector<FrameLoopTimes>& times() const { return times_; }
  // Release() -> closing barrier completion of the last frame.
  double frame_seconds() const { return frame_seconds_; }

  // Listing 3 lines 12-13: raises END and releases the threads through the opening barrier,
  // then joins them. If a frame is running it is waited for first (its exception is dropped).
  // Idempotent.
  void Shutdown() noexcept;

 private:
  void ThreadMain(int worker);

  struct alignas(128) Slot {  // written by its thread only, read after a barrier
    Clock::time_point arrival{};
    double cpu_seconds = 0;
    std::exception_ptr error;
  };

  int num_threads_;
  Work work_;
  FrameBarrier open_;
  FrameBarrier close_;
  // END flag. Written by the application thread before it joins the opening barrier and read by
  // the threads after it: the barrier orders the two, so relaxed is enough.
  std::atomic<bool> end_{false};
  std::unique_ptr<Slot[]> slots_;
  std::vector<std::thread> threads_;
  std::vector<FrameLoopTimes> times_;
  Clock::time_point release_time_{};
  double frame_seconds_ = 0;
  uint64_t frames_ = 0;
  bool in_frame_ = false;
  bool shut_down_ = false;
};

}  // namespace rs
