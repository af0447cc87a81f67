// LOCK: the two-lock unbounded FIFO of Michael & Scott (PODC 1996) / Herlihy & Shavit's
// "unbounded total queue" (paper listing 4): a dummy head node, one lock for Push and one for
// TryPop, so producers and consumers only meet on the dummy's `next` pointer.
#pragma once

#include <atomic>
#include <cstddef>
#include <memory>
#include <mutex>
#include <new>
#include <span>
#include <type_traits>
#include <utility>

#include "sched/queue.h"

namespace rs {

// Multi-producer multi-consumer unbounded FIFO. Pushes serialize on tail_mutex, pops on
// head_mutex; a push and a pop proceed in parallel unless the queue is empty.
//
// Nodes are recycled without a third lock or a free list (Sutter's "first/divider" scheme):
// the producers own the consumed prefix of the list, [first_, head_), and reuse its nodes for new
// tasks; consumers only advance head_. head_ is therefore an atomic that consumers store with
// release (after moving the task out) and producers load with acquire (before reusing a node).
// So after warm-up a push neither allocates nor frees, and the node memory of a frame's peak
// queue length is kept until the queue is destroyed.
//
// Note: the paper's listing 4 returns `actual->value`, the value of the old dummy; the task is
// in the new head node (head->next), as in Herlihy & Shavit. TryPop below reads the right node.
//
// Mutex: std::mutex (default) or rs::SpinLock. The queue's critical sections are ~50 ns, and
// std::mutex (a futex) costs one uncontended CAS to lock and one to unlock, like the spinlock,
// but sleeps when the holder is preempted, which matters when threads outnumber cores (this
// machine: 2 cores). bench/sched/queue_bench.cc measures both (LOCK vs LOCK_spin).
template <QueueTask T, class Stats = NoQueueStats, class Mutex = std::mutex>
class LockQueue {
 public:
  using value_type = T;
  using stats_type = Stats;
  static constexpr QueueKind kKind = QueueKind::kLock;

  // num_workers >= 1 threads will pass worker ids in [0, num_workers). Throws std::bad_alloc.
  explicit LockQueue(int num_workers) : num_workers_(num_workers), stats_(num_workers) {
    Node* dummy = new Node;
    head_.store(dummy, std::memory_order_relaxed);
    tail_ = dummy;
    first_ = dummy;
  }

  // Destroys the remaining tasks and frees every node. Not concurrent with other operations.
  ~LockQueue() {
    Node* node = first_;
    Node* const head = head_.load(std::memory_order_acquire);
    bool after_head = false;
    while (node != nullptr) {
      Node* next = node->next.load(std::memory_order_acquire);
      if (after_head) std::destroy_at(node->Ptr());
      if (node == head) after_head = true;
      delete node;
      node = next;
    }
  }

  LockQueue(const LockQueue&) = delete;
  LockQueue& operator=(const LockQueue&) = delete;

  // addRays: appends the task. Any thread; worker selects the statistics slot (so with
  // QueueTimeStats, one thread per worker id at a time, as for every WorkQueue). Throws
  // std::bad_alloc (queue unchanged) if no consumed node can be reused and `new` fails.
  void Push(int worker, T&& task) {
    [[maybe_unused]] auto scope = stats_.Measure(worker);
    Enqueue(1, [&](size_t, T* slot) { std::construct_at(slot, std::move(task)); });
  }
  void Push(int worker, const T& task) requires std::copy_constructible<T> {
    [[maybe_unused]] auto scope = stats_.Measure(worker);
    if constexpr (std::is_nothrow_copy_constructible_v<T>) {
      Enqueue(1, [&](size_t, T* slot) { std::construct_at(slot, task); });  // straight in
    } else {
      T copy(task);  // a throwing copy happens outside the lock, before any node is taken
      Enqueue(1, [&](size_t, T* slot) { std::construct_at(slot, std::move(copy)); });
    }
  }
  // Appends tasks[0], tasks[1], ... in that order (moved from) under one acquisition of the
  // tail lock. Throws std::bad_alloc (queue unchanged, tasks untouched).
  void PushMany(int worker, std::span<T> tasks) {
    if (tasks.empty()) return;
    [[maybe_unused]] auto scope = stats_.Measure(worker);
    Enqueue(tasks.size(), [&](size_t i, T* slot) { std::construct_at(slot, std::move(tasks[i])); });
  }
  // The application thread's push of a primary task (timed in the application slot).
  void PushPrimary(T&& task) {
    [[maybe_unused]] auto scope = stats_.Measure(num_workers_);
    Enqueue(1, [&](size_t, T* slot) { std::construct_at(slot, std::move(task)); });
  }

  // getRays: moves the oldest task into `out` and returns true, or returns false (EMPTY; `out`
  // untouched). Any thread, as for Push.
  bool TryPop(int worker, T& out) noexcept {
    [[maybe_unused]] auto scope = stats_.Measure(worker);
    std::lock_guard<Mutex> lock(head_mutex_);
    return PopLocked(out);
  }
  // getRays for up to out.size() tasks under one acquisition of the head lock: the oldest
  // ones into out[0], out[1], ...; returns how many (0: EMPTY; out untouched past the count).
  size_t TryPopMany(int worker, std::span<T> out) noexcept {
    if (out.empty()) return 0;
    [[maybe_unused]] auto scope = stats_.Measure(worker);
    std::lock_guard<Mutex> lock(head_mutex_);
    size_t n = 0;
    while (n < out.size() && PopLocked(out[n])) ++n;
    return n;
  }

  int num_workers() const { return num_workers_; }
  const Stats& stats() const { return stats_; }
  Stats& stats() { return stats_; }

  // Fill phase only (no concurrent Push / TryPop): at least n consumed nodes wait for reuse, so
  // the next n pushes allocate nothing. Walks the consumed prefix. Throws std::bad_alloc.
  void Reserve(size_t n) {
    const Node* head = head_.load(std::memory_order_relaxed);
    size_t spare = 0;
    for (Node* p = first_; p != head; p = p->next.load(std::memory_order_relaxed)) ++spare;
    for (; spare < n; ++spare) {
      Node* node = new Node;
      node->next.store(first_, std::memory_order_relaxed);
      first_ = node;
    }
  }

 private:
  struct Node {
    std::atomic<Node*> next{nullptr};
    alignas(T) std::byte storage[sizeof(T)];
    T* Ptr() { return std::launder(reinterpret_cast<T*>(storage)); }
  };

  // Under head_mutex_: moves the task after the dummy out and makes its node the dummy.
  bool PopLocked(T& out) noexcept {
    Node* const head = head_.load(std::memory_order_relaxed);  // only consumers write head_
    // acquire pairs with the producer's release store of `next`: the task is fully built.
    Node* const next = head->next.load(std::memory_order_acquire);
    if (next == nullptr) return false;
    // The task is moved out under the lock: once head_ moves past `next`, a later pop could
    // make `next` reusable by producers.
    T* task = next->Ptr();
    out = std::move(*task);
    std::destroy_at(task);
    // release: producers that see the new head may reuse the old dummy and everything before.
    head_.store(next, std::memory_order_release);
    return true;
  }

  // Appends n >= 1 tasks under the tail lock; fill(i, slot) constructs task i at `slot` and
  // must not throw. The nodes (the oldest consumed ones, then new ones) are all taken before
  // anything changes, so a bad_alloc leaves the queue as it was.
  template <class Fill>
  void Enqueue(size_t n, Fill&& fill) {
    std::lock_guard<Mutex> lock(tail_mutex_);
    // Consumed nodes are [first_, head): their `next` links were written under this lock.
    Node* const head = head_.load(std::memory_order_acquire);
    Node* reuse_end = first_;
    size_t reused = 0;
    for (; reused < n && reuse_end != head; ++reused) {
      reuse_end = reuse_end->next.load(std::memory_order_relaxed);
    }
    Node* fresh = nullptr;  // n - reused new nodes, linked by `next`
    try {
      for (size_t i = reused; i < n; ++i) {
        Node* node = new Node;
        node->next.store(fresh, std::memory_order_relaxed);
        fresh = node;
      }
    } catch (...) {
      while (fresh != nullptr) delete std::exchange(fresh, fresh->next.load());
      throw;
    }
    Node* reuse = std::exchange(first_, reuse_end);
    Node* chain = nullptr;
    Node* last = nullptr;
    for (size_t i = 0; i < n; ++i) {
      Node*& from = i < reused ? reuse : fresh;
      Node* node = std::exchange(from, from->next.load(std::memory_order_relaxed));
      node->next.store(nullptr, std::memory_order_relaxed);
      fill(i, node->Ptr());
      if (last != nullptr) {
        last->next.store(node, std::memory_order_relaxed);
      } else {
        chain = node;
      }
      last = node;
    }
    // release: a consumer that loads this pointer with acquire sees the constructed tasks and
    // the chain's links.
    tail_->next.store(chain, std::memory_order_release);
    tail_ = last;
  }

  // Consumer side.
  alignas(kQueueFalseSharing) Mutex head_mutex_;
  std::atomic<Node*> head_;  // the dummy; written under head_mutex_, read by producers
  // Producer side.
  alignas(kQueueFalseSharing) Mutex tail_mutex_;
  Node* tail_;   // last node, under tail_mutex_
  Node* first_;  // oldest node not yet reused, under tail_mutex_
  alignas(kQueueFalseSharing) int num_workers_;
  [[no_unique_address]] Stats stats_;
};

}  // namespace rs
