// The build threads' pool (kernels/build_threads.h): threads started on first use and kept for
// the process, parked on a condition variable between RunParts calls. One RunParts uses the
// pool at a time; a part claims the next index under the mutex.
#include "kernels/build_threads.h"

#include <pthread.h>

#include <condition_variable>
#include <mutex>

namespace rs {
namespace {

struct BuildPool {
  std::mutex run;  // held by the RunParts that owns the pool
  std::mutex mutex;
  std::condition_variable work, done;
  std::vector<std::thread> threads;
  void (*call)(void*, int) = nullptr;
  void* ctx = nullptr;
  int parts = 0, next = 0, pending = 0;  // next part to claim; parts not finished
};

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
  std::unique_lock<std::mutex> lock(p->mutex);
  for (;;) {
    p->work.wait(lock, [p] { return p->next < p->parts; });
    const int t = p->next++;
    void (*const call)(void*, int) = p->call;
    void* const ctx = p->ctx;
    lock.unlock();
    call(ctx, t);
    lock.lock();
    if (--p->pending == 0) p->done.notify_all();
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
    p.pending = parts - 1;
    p.next = 1;
    p.parts = parts;
  }
  p.work.notify_all();
  call(ctx, 0);
  std::unique_lock<std::mutex> lock(p.mutex);
  p.done.wait(lock, [&p] { return p.pending == 0; });
  p.parts = p.next = 0;
  return true;
}

}  // namespace rs
