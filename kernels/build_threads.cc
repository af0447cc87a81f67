// The build threads' pool (kernels/build_threads.h): threads started on first use and kept for
// the process. A thread that finishes a part spins for kSpin before it parks on a condition
// variable, and so does the caller waiting for the parts: a build calls RunParts 15-20 times
// in a row, and on this VM (2 vCPUs) waking a parked thread costs as much as some of the parts.
// A loop of two-part calls (50 us of work each, 20 us apart) took 104-109 us a call with the
// threads parked between calls, 52 us with them spinning (04:52 UTC, load 0.56). One RunParts
// uses the pool at a time; a part claims the next index under the mutex.
#include "kernels/build_threads.h"

#include <pthread.h>

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <mutex>

namespace rs {
namespace {

// How long a pool thread, or the caller of RunParts, spins for the next call or the last part
// before it sleeps: short against a frame (the CPU it spins away is bounded by it), longer than
// the serial stretches between a build's RunParts calls. Measured (trace_bench rebuild-2t, gaps
// from the end of one call to the start of the next, 04:53 UTC, load 0.77): bunny, sponza,
// office-graz and spherebox had 2 gaps over 200 us in 4,000-7,000 calls (the first ones);
// conference, whose two-level refinement has longer serial passes, 137 of 432.
constexpr std::chrono::microseconds kSpin{200};

struct BuildPool {
  std::mutex run;  // held by the RunParts that owns the pool
  std::mutex mutex;
  std::condition_variable work, done;
  std::vector<std::thread> threads;
  void (*call)(void*, int) = nullptr;
  void* ctx = nullptr;
  // next part to claim; parts not finished (written under `mutex`; read without it by the
  // spins, which then take the mutex to act)
  int parts = 0, next = 0;
  std::atomic<int> pending{0};
  std::atomic<uint64_t> posted{0};  // RunParts calls so far
};

inline void CpuRelax() {
#if defined(__x86_64__) || defined(__i386__)
  __builtin_ia32_pause();
#endif
}

// Spins until done() or kSpin has passed; returns done().
template <class Done>
bool SpinFor(Done&& done) {
  const auto until = std::chrono::steady_clock::now() + kSpin;
  for (;;) {
    for (int i = 0; i < 64; ++i) {
      if (done()) return true;
      CpuRelax();
    }
    if (std::chrono::steady_clock::now() >= until) return done();
  }
}

thread_local bool t_pool_thread = false;

// Never destroyed: its threads stay parked until the process exits. A forked child (which has
// none of them) starts a pool of its own.
BuildPool* g_pool = nullptr;
std::once_flag g_atfork;

BuildPool& Pool() {
  std::call_once(g_atfork, [] {
    pthread_atfork(nullptr, nullptr, [] { g_pool = nullptr; });  // (the old one is lost)
  });
  static std::mutex create;
  const std::lock_guard<std::mutex> lock(create);
  if (g_pool == nullptr) g_pool = new BuildPool;
  return *g_pool;
}

void Worker(BuildPool* p) {
  t_pool_thread = true;
  uint64_t seen = 0;  // the calls this thread has looked at
  std::unique_lock<std::mutex> lock(p->mutex);
  for (;;) {
    if (!(p->next < p->parts)) {
      seen = p->posted.load(std::memory_order_relaxed);
      lock.unlock();
      SpinFor([p, seen] { return p->posted.load(std::memory_order_acquire) != seen; });
      lock.lock();
      p->work.wait(lock, [p] { return p->next < p->parts; });
    }
    const int t = p->next++;
    void (*const call)(void*, int) = p->call;
    void* const ctx = p->ctx;
    lock.unlock();
    call(ctx, t);
    lock.lock();
    if (p->pending.fetch_sub(1, std::memory_order_acq_rel) == 1) p->done.notify_all();
  }
}

}  // namespace

bool RunOnBuildPool(int parts, void (*call)(void*, int), void* ctx) {
  if (t_pool_thread || parts <= 1) return false;
  BuildPool& p = Pool();
  std::unique_lock<std::mutex> owner(p.run, std::try_to_lock);
  if (!owner.owns_lock()) return false;
  {
    const std::lock_guard<std::mutex> lock(p.mutex);
    try {
      while (p.threads.size() < size_t(parts - 1)) p.threads.emplace_back(Worker, &p);
    } catch (...) {  // fewer threads than parts: the caller starts its own
      return false;
    }
    p.call = call;
    p.ctx = ctx;
    p.pending.store(parts - 1, std::memory_order_relaxed);
    p.next = 1;
    p.parts = parts;
    p.posted.fetch_add(1, std::memory_order_release);
  }
  p.work.notify_all();
  call(ctx, 0);
  const auto finished = [&p] { return p.pending.load(std::memory_order_acquire) == 0; };
  SpinFor(finished);
  std::unique_lock<std::mutex> lock(p.mutex);
  p.done.wait(lock, finished);
  p.parts = p.next = 0;
  return true;
}

}  // namespace rs
