// FrameBarrier and FrameLoop (see frame_loop.h): the render threads' loop of listing 2 and the
// application side of listing 3, with per-thread busy and idle times.
#include "sched/frame_loop.h"

#include <time.h>

#include <string>
#include <system_error>
#include <utility>

#include "include/raystream/raystream.h"
#include "sched/queue.h"  // queue_detail::CpuRelax

namespace rs {

namespace {

double Seconds(FrameBarrier::Clock::time_point a, FrameBarrier::Clock::time_point b) {
  return b > a ? std::chrono::duration<double>(b - a).count() : 0.0;
}

// Spin budget before blocking: ~100 pauses are a few microseconds, which covers the usual skew
// of a balanced frame's end without burning a time slice when threads outnumber cores.
constexpr int kBarrierSpins = 100;

}  // namespace

double ThreadCpuSeconds() {
  timespec ts{};
  if (clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts) != 0) return 0.0;
  return static_cast<double>(ts.tv_sec) + 1e-9 * static_cast<double>(ts.tv_nsec);
}

FrameBarrier::FrameBarrier(int participants) : participants_(participants < 1 ? 1 : participants) {}

void FrameBarrier::CompleteLocked() noexcept {
  arrived_ = 0;
  completion_ = Clock::now();
  // release: publishes completion_ and every arriver's prior writes (they reached us through
  // mutex_) to waiters that spin on phase_ with acquire.
  phase_.store(phase_.load(std::memory_order_relaxed) + 1, std::memory_order_release);
}

FrameBarrier::Clock::time_point FrameBarrier::ArriveAndWait() noexcept {
  std::unique_lock<std::mutex> lock(mutex_);
  const uint64_t phase = phase_.load(std::memory_order_relaxed);  // stable under mutex_
  if (++arrived_ >= participants_) {
    CompleteLocked();
    const Clock::time_point done = completion_;
    lock.unlock();
    cv_.notify_all();
    return done;
  }
  lock.unlock();
  for (int i = 0; i < kBarrierSpins; ++i) {
    // acquire pairs with CompleteLocked's release store. completion_ cannot be overwritten
    // before we return: the next phase cannot complete without our next arrival.
    if (phase_.load(std::memory_order_acquire) != phase) return completion_;
    queue_detail::CpuRelax();
  }
  lock.lock();
  cv_.wait(lock, [&] { return phase_.load(std::memory_order_relaxed) != phase; });
  return completion_;
}

void FrameBarrier::SetParticipants(int participants) noexcept {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    participants_ = participants < 1 ? 1 : participants;
    if (arrived_ == 0 || arrived_ < participants_) return;
    CompleteLocked();
  }
  cv_.notify_all();
}

FrameLoop::FrameLoop(int num_threads, Work work)
    : num_threads_(num_threads),
      work_(std::move(work)),
      open_(num_threads + 1),
      close_(num_threads + 1) {
  if (num_threads < 1 || num_threads > kMaxThreads) {
    throw Error("frame loop: thread count " + std::to_string(num_threads) + " must be in [1, " +
                std::to_string(kMaxThreads) + "]");
  }
  if (!work_) throw Error("frame loop: no work function");
  slots_ = std::make_unique<Slot[]>(static_cast<size_t>(num_threads));
  times_.resize(static_cast<size_t>(num_threads));
  threads_.reserve(static_cast<size_t>(num_threads));
  try {
    for (int w = 0; w < num_threads; ++w) threads_.emplace_back([this, w] { ThreadMain(w); });
  } catch (...) {
    // The threads already running wait at the opening barrier for num_threads + 1 arrivals;
    // count only them and us, raise END and release them.
    open_.SetParticipants(static_cast<int>(threads_.size()) + 1);
    end_.store(true, std::memory_order_relaxed);
    open_.ArriveAndWait();
    for (auto& t : threads_) t.join();
    throw;
  }
}

FrameLoop::~FrameLoop() { Shutdown(); }

void FrameLoop::ThreadMain(int worker) {
  Slot& slot = slots_[static_cast<size_t>(worker)];
  for (;;) {
    open_.ArriveAndWait();                             // listing 2, line 3
    if (end_.load(std::memory_order_relaxed)) return;  // ordered by the barrier
    const double cpu0 = ThreadCpuSeconds();
    try {
      work_(worker);  // lines 4-10: drain the queue
    } catch (...) {
      slot.error = std::current_exception();
    }
    slot.cpu_seconds = ThreadCpuSeconds() - cpu0;
    slot.arrival = Clock::now();
    close_.ArriveAndWait();  // line 11
  }
}

FrameLoop::Clock::time_point FrameLoop::Release() {
  if (shut_down_) throw Error("frame loop: Release after Shutdown");
  if (in_frame_) throw Error("frame loop: Release called twice without Wait");
  in_frame_ = true;
  release_time_ = open_.ArriveAndWait();
  return release_time_;
}

FrameLoop::Clock::time_point FrameLoop::Wait() {
  if (!in_frame_) throw Error("frame loop: Wait without Release");
  const Clock::time_point done = close_.ArriveAndWait();
  in_frame_ = false;
  ++frames_;
  frame_seconds_ = Seconds(release_time_, done);
  std::exception_ptr error;
  for (int w = 0; w < num_threads_; ++w) {
    Slot& slot = slots_[static_cast<size_t>(w)];
    FrameLoopTimes& t = times_[static_cast<size_t>(w)];
    t.busy_seconds = Seconds(release_time_, slot.arrival);
    t.idle_seconds = Seconds(slot.arrival, done);
    t.cpu_seconds = slot.cpu_seconds;
    if (slot.error && !error) error = slot.error;
    slot.error = nullptr;
  }
  if (error) std::rethrow_exception(error);
  return done;
}

void FrameLoop::Shutdown() noexcept {
  if (shut_down_) return;
  shut_down_ = true;
  if (in_frame_) {
    close_.ArriveAndWait();
    in_frame_ = false;
  }
  end_.store(true, std::memory_order_relaxed);  // listing 3, line 12
  open_.ArriveAndWait();                        // line 13
  for (auto& t : threads_) t.join();
}

}  // namespace rs
