// Throughput of the work queues (LOCK, LOCK with a spinlock, LFREE, LOCAL) against
// boost::lockfree::queue and moodycamel::ConcurrentQueue: push+pop pairs per second at 1, 2, 4
// and 8 threads with the paper's task of 20 rays, plus the cost of the queue-time counters.
#include <benchmark/benchmark.h>
#include <unistd.h>

#include <chrono>
#include <cstdint>
#include <cstdio>
#include <map>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "sched/queue.h"
#include "sched/queue_local.h"
#include "sched/queue_lock.h"
#include "sched/queue_lockfree.h"

// The peers meson found (bench/meson.build passes both macros; a build without them guesses).
#ifndef RS_BENCH_HAVE_BOOST
#if __has_include(<boost/lockfree/queue.hpp>)
#define RS_BENCH_HAVE_BOOST 1
#else
#define RS_BENCH_HAVE_BOOST 0
#endif
#endif
#ifndef RS_BENCH_HAVE_MOODYCAMEL
#if __has_include(<concurrentqueue/concurrentqueue.h>)
#define RS_BENCH_HAVE_MOODYCAMEL 1
#else
#define RS_BENCH_HAVE_MOODYCAMEL 0
#endif
#endif
#if RS_BENCH_HAVE_BOOST
#include <boost/lockfree/queue.hpp>
#endif
#if RS_BENCH_HAVE_MOODYCAMEL
#include <concurrentqueue/concurrentqueue.h>
#endif

namespace rs {
namespace {

// The paper's task: 20 rays (section 4), here as the SoA fields of RayStreamView. 1124 bytes,
// trivially copyable (boost::lockfree::queue requires that).
constexpr int kRaysPerTask = 20;
struct Task20 {
  float ox[kRaysPerTask], oy[kRaysPerTask], oz[kRaysPerTask];
  float dx[kRaysPerTask], dy[kRaysPerTask], dz[kRaysPerTask];
  float tmin[kRaysPerTask], tmax[kRaysPerTask];
  uint32_t pixel[kRaysPerTask];
  float wr[kRaysPerTask], wg[kRaysPerTask], wb[kRaysPerTask];
  int32_t depth[kRaysPerTask], kind[kRaysPerTask];
  uint32_t count;
};

Task20 MakeTask20(int seed) {
  Task20 t{};
  for (int i = 0; i < kRaysPerTask; ++i) {
    t.ox[i] = static_cast<float>(seed + i);
    t.dz[i] = 1.0f;
    t.tmax[i] = 1e30f;
    t.pixel[i] = static_cast<uint32_t>(seed * kRaysPerTask + i);
    t.wr[i] = t.wg[i] = t.wb[i] = 1.0f;
  }
  t.count = kRaysPerTask;
  return t;
}

// A 4-byte index into a task pool: the other task representation the renderer may use.
using TaskIndex = uint32_t;

template <class T>
T MakeTask(int seed) {
  if constexpr (std::is_same_v<T, Task20>) {
    return MakeTask20(seed);
  } else {
    return static_cast<T>(seed);
  }
}

// ---------------------------------------------------------------------------------------------
// Adapters: Push(worker, const T&) / TryPop(worker, T&) for every contender. One copy in, one
// copy (move) out for all of them.

template <class Q>
struct Ours {
  using T = typename Q::value_type;
  Q q;
  explicit Ours(int threads) : q(threads) {}
  void Push(int w, const T& t) { q.Push(w, t); }
  bool TryPop(int w, T& t) { return q.TryPop(w, t); }
};

#if RS_BENCH_HAVE_BOOST
template <class T>
struct Boost {
  boost::lockfree::queue<T> q{1024};  // preallocated nodes; grows from the heap if needed
  explicit Boost(int /*threads*/) {}
  void Push(int /*w*/, const T& t) {
    while (!q.push(t)) {
    }
  }
  bool TryPop(int /*w*/, T& t) { return q.pop(t); }
};
#endif

#if RS_BENCH_HAVE_MOODYCAMEL
template <class T>
struct Moody {
  moodycamel::ConcurrentQueue<T> q;  // implicit producers (no tokens), like the others
  explicit Moody(int /*threads*/) {}
  void Push(int /*w*/, const T& t) { q.enqueue(t); }
  bool TryPop(int /*w*/, T& t) { return q.try_dequeue(t); }
};
#endif

int Cores() {
  const unsigned n = std::thread::hardware_concurrency();
  return n == 0 ? 1 : static_cast<int>(n);
}

// Every thread does `push own task; pop one task` per iteration, on a queue that starts with
// `prefill` tasks per thread (a frame's queue is never near empty until its end; prefill 0 is
// the contended near-empty case where head and tail meet). Items = push+pop pairs.
template <class Adapter, class T>
void PushPop(benchmark::State& state, std::shared_ptr<std::unique_ptr<Adapter>> shared,
             int prefill) {
  const int w = state.thread_index();
  if (w == 0) {
    *shared = std::make_unique<Adapter>(state.threads());
    for (int t = 0; t < state.threads(); ++t) {
      for (int i = 0; i < prefill; ++i) (*shared)->Push(t, MakeTask<T>(i));
    }
  }
  const T task = MakeTask<T>(w);
  T out{};
  int64_t empty = 0;
  Adapter* queue = nullptr;
  for (auto _ : state) {
    // The loop starts with a barrier of all threads (after thread 0's setup above), so the
    // queue may be looked up only inside it.
    if (queue == nullptr) queue = shared->get();
    queue->Push(w, task);
    if (!queue->TryPop(w, out)) ++empty;
    benchmark::DoNotOptimize(out);
  }
  state.SetItemsProcessed(state.iterations());
  state.counters["empty_pops"] = benchmark::Counter(static_cast<double>(empty));
  if (state.threads() > Cores()) {
    state.SetLabel("oversubscribed: " + std::to_string(state.threads()) + " threads > " +
                   std::to_string(Cores()) + " cores");
  }
  if (w == 0) {
    // All threads have left the loop (stop barrier) before thread 0 gets here.
    shared->reset();
  }
}

template <class Adapter, class T>
void Register(const std::string& payload, const std::string& kind, int prefill) {
  auto shared = std::make_shared<std::unique_ptr<Adapter>>();
  const std::string name =
      "PushPop/" + payload + "/" + kind + "/prefill:" + std::to_string(prefill);
  benchmark::RegisterBenchmark(name.c_str(), PushPop<Adapter, T>, shared, prefill)
      ->Threads(1)
      ->Threads(2)
      ->Threads(4)
      ->Threads(8)
      ->UseRealTime();
}

template <class T>
void RegisterAll(const std::string& payload, int prefill) {
  Register<Ours<LockQueue<T>>, T>(payload, "LOCK", prefill);
  Register<Ours<LockQueue<T, NoQueueStats, SpinLock>>, T>(payload, "LOCK_spin", prefill);
  Register<Ours<LockFreeQueue<T>>, T>(payload, "LFREE", prefill);
  Register<Ours<LocalQueues<T>>, T>(payload, "LOCAL", prefill);
#if RS_BENCH_HAVE_BOOST
  Register<Boost<T>, T>(payload, "boost_lockfree", prefill);
#endif
#if RS_BENCH_HAVE_MOODYCAMEL
  Register<Moody<T>, T>(payload, "moodycamel", prefill);
#endif
}

// ---------------------------------------------------------------------------------------------
// Cost of the queue-time counters: the two clocks, and one thread's push+pop with stats on/off.

void BM_ClockSteady(benchmark::State& state) {
  for (auto _ : state) {
    benchmark::DoNotOptimize(std::chrono::steady_clock::now());
  }
}
BENCHMARK(BM_ClockSteady);

void BM_ClockRdtsc(benchmark::State& state) {
  for (auto _ : state) {
    benchmark::DoNotOptimize(QueueClock::Now());
  }
}
BENCHMARK(BM_ClockRdtsc);

template <class Q>
void BM_StatsOverhead(benchmark::State& state) {
  Q queue(1);
  for (int i = 0; i < 64; ++i) queue.Push(0, TaskIndex(i));
  TaskIndex out = 0;
  for (auto _ : state) {
    queue.Push(0, out);
    queue.TryPop(0, out);
    benchmark::DoNotOptimize(out);
  }
  state.SetItemsProcessed(state.iterations());
}
BENCHMARK_TEMPLATE(BM_StatsOverhead, LockFreeQueue<TaskIndex, NoQueueStats>);
BENCHMARK_TEMPLATE(BM_StatsOverhead, LockFreeQueue<TaskIndex, QueueTimeStats>);
BENCHMARK_TEMPLATE(BM_StatsOverhead, LockQueue<TaskIndex, NoQueueStats>);
BENCHMARK_TEMPLATE(BM_StatsOverhead, LockQueue<TaskIndex, QueueTimeStats>);
BENCHMARK_TEMPLATE(BM_StatsOverhead, LocalQueues<TaskIndex, NoQueueStats>);
BENCHMARK_TEMPLATE(BM_StatsOverhead, LocalQueues<TaskIndex, QueueTimeStats>);

// ---------------------------------------------------------------------------------------------
// Console output plus a closing table of LFREE / boost::lockfree and LFREE / LOCK throughput.

class RatioReporter : public benchmark::ConsoleReporter {
 public:
  explicit RatioReporter(OutputOptions options) : ConsoleReporter(options) {}
  void ReportRuns(const std::vector<Run>& runs) override {
    // With --benchmark_repetitions the median aggregate (reported after the repetitions)
    // replaces the single runs.
    for (const Run& run : runs) {
      const auto it = run.counters.find("items_per_second");
      if (it == run.counters.end() || run.error_occurred) continue;
      if (run.run_type == Run::RT_Iteration || run.aggregate_name == "median") {
        rate_[run.run_name.str()] = it->second.value;
      }
    }
    ConsoleReporter::ReportRuns(runs);
  }
  void Finalize() override {
    ConsoleReporter::Finalize();
    std::printf("\nThroughput ratios (push+pop pairs per second; > 1 means LFREE is faster):\n");
    std::printf("%-34s %8s %14s %10s %12s\n", "case", "threads", "LFREE/boost", "LFREE/LOCK",
                "LFREE/moody");
    for (const char* payload : {"Task20", "Index"}) {
      for (const int prefill : {1024, 0}) {
        for (const int threads : {1, 2, 4, 8}) {
          const auto name = [&](const char* kind) {
            return std::string("PushPop/") + payload + "/" + kind +
                   "/prefill:" + std::to_string(prefill) +
                   "/real_time/threads:" + std::to_string(threads);
          };
          const double lfree = Rate(name("LFREE"));
          if (lfree <= 0) continue;
          const std::string label = std::string(payload) + " prefill:" + std::to_string(prefill);
          std::printf("%-34s %8d %14.2f %10.2f %12.2f%s\n", label.c_str(), threads,
                      Ratio(lfree, Rate(name("boost_lockfree"))), Ratio(lfree, Rate(name("LOCK"))),
                      Ratio(lfree, Rate(name("moodycamel"))),
                      threads > Cores() ? "  (oversubscribed)" : "");
        }
      }
    }
    std::printf(
        "Note: this machine has %d hardware threads; runs with more threads "
        "oversubscribe it and measure preemption as much as the queues.\n",
        Cores());
  }

 private:
  double Rate(const std::string& name) const {
    const auto it = rate_.find(name);
    return it == rate_.end() ? 0.0 : it->second;
  }
  static double Ratio(double a, double b) { return b > 0 ? a / b : 0.0; }
  std::map<std::string, double> rate_;
};

}  // namespace
}  // namespace rs

int main(int argc, char** argv) {
  benchmark::Initialize(&argc, argv);
  if (benchmark::ReportUnrecognizedArguments(argc, argv)) return 1;
  const int cores = rs::Cores();
  const std::string note = std::to_string(cores) + " hardware threads: runs with more than " +
                           std::to_string(cores) +
                           " threads oversubscribe this machine (labelled 'oversubscribed')";
  benchmark::AddCustomContext("oversubscription", note);
  std::fprintf(stderr, "NOTE: %s.\n", note.c_str());
  rs::RegisterAll<rs::Task20>("Task20", 1024);
  rs::RegisterAll<rs::Task20>("Task20", 0);
  rs::RegisterAll<rs::TaskIndex>("Index", 1024);
  rs::RegisterAll<rs::TaskIndex>("Index", 0);
  rs::RatioReporter reporter(isatty(fileno(stdout)) ? benchmark::ConsoleReporter::OO_Defaults
                                                    : benchmark::ConsoleReporter::OO_Tabular);
  benchmark::RunSpecifiedBenchmarks(&reporter);
  benchmark::Shutdown();
  return 0;
}
