// LOCAL: one private FIFO per worker thread (paper section 4.2). The application thread deals
// primary tasks round-robin before releasing the workers; each worker then pushes its secondary
// tasks to, and pops from, its own queue only. No locks, no atomics, no stealing.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <new>
#include <span>
#include <utility>

#include "sched/queue.h"

namespace rs {
namespace queue_detail {

// Single-threaded unbounded FIFO of blocks of tasks. Emptied blocks go to a LIFO free list and
// an emptied queue rewinds to the start of its block, so the memory it touches is about the
// live tasks plus one block (a ring buffer walks its whole power-of-two capacity, which for
// 1 KB tasks of 20 rays falls out of L2 long before the queue is that long).
template <QueueTask T>
class BlockFifo {
 public:
  // Slots of large tasks start on cache lines: a 1124-byte task of 20 rays packed at its own
  // size would sit at 4 mod 8 bytes in every other slot, and the block copies (rep movs) of
  // misaligned slots measured ~2x slower. Small tasks are packed.
  static constexpr size_t kSlotBytes = sizeof(T) >= 256 ? (sizeof(T) + 63) / 64 * 64 : sizeof(T);
  // ~16 KiB per block, at least 8 tasks.
  static constexpr uint32_t kPerBlock =
      kSlotBytes * 8 >= 16384 ? 8 : static_cast<uint32_t>(16384 / kSlotBytes);

  BlockFifo() = default;
  ~BlockFifo() {
    for (Block* b = head_; b != nullptr;) {
      for (uint32_t i = b->head; i < b->tail; ++i) std::destroy_at(b->Slot(i));
      Block* next = b->next;
      delete b;
      b = next;
    }
    while (free_ != nullptr) delete std::exchange(free_, free_->next);
  }
  BlockFifo(const BlockFifo&) = delete;
  BlockFifo& operator=(const BlockFifo&) = delete;

  // Preallocates blocks so that n more tasks fit without allocating (the free blocks and the
  // room left in the tail block count). May throw std::bad_alloc.
  void Reserve(size_t n) {
    const size_t room = tail_ != nullptr ? kPerBlock - tail_->tail : 0;
    while (free_blocks_ * size_t{kPerBlock} + room < n) GiveBlock(new Block);
  }

  // U is T (moved) or const T& (copied). May throw std::bad_alloc or T's copy exception; the
  // queue's contents are unchanged then.
  template <class U>
  void Push(U&& task) {
    if (tail_ == nullptr) {
      head_ = tail_ = TakeBlock();
    } else if (tail_->tail == kPerBlock) {
      Block* b = TakeBlock();
      tail_->next = b;
      tail_ = b;
    }
    std::construct_at(tail_->Slot(tail_->tail), std::forward<U>(task));
    ++tail_->tail;
    ++size_;
  }

  bool Pop(T& out) noexcept {
    if (size_ == 0) return false;
    Block* b = head_;
    if (b->head == kPerBlock) {  // exhausted; a later block holds the next task
      head_ = b->next;
      GiveBlock(b);
      b = head_;
    }
    T* task = b->Slot(b->head);
    out = std::move(*task);
    std::destroy_at(task);
    ++b->head;
    if (--size_ == 0 && b == tail_) b->head = b->tail = 0;  // rewind: reuse the warm slots
    return true;
  }

  size_t size() const { return size_; }

 private:
  struct Block {
    Block* next = nullptr;
    uint32_t head = 0;  // first live slot
    uint32_t tail = 0;  // one past the last live slot
    alignas(alignof(T) > 64 ? alignof(T) : 64) std::byte storage[kPerBlock * kSlotBytes];
    T* Slot(uint32_t i) { return std::launder(reinterpret_cast<T*>(storage + i * kSlotBytes)); }
  };

  Block* TakeBlock() {
    if (free_ == nullptr) return new Block;
    Block* b = std::exchange(free_, free_->next);
    --free_blocks_;
    b->next = nullptr;
    b->head = b->tail = 0;
    return b;
  }
  void GiveBlock(Block* b) noexcept {
    b->next = free_;
    free_ = b;
    ++free_blocks_;
  }

  Block* head_ = nullptr;  // oldest block with live tasks (or the single, empty block)
  Block* tail_ = nullptr;  // block that receives pushes
  Block* free_ = nullptr;  // LIFO: the most recently emptied block is the warmest
  size_t free_blocks_ = 0;
  size_t size_ = 0;
};

}  // namespace queue_detail

// Per-worker queues behind the WorkQueue interface.
//
// Threading contract (the fill-then-release pattern of the paper's listings 2 and 3):
//  * Fill phase: while no worker is inside Push/TryPop, one application thread calls
//    PushPrimary (round-robin over the workers) and/or Push(w, task) for any w.
//  * Release: the application thread then arrives at a barrier (e.g. std::barrier
//    arrive_and_wait) that the workers wait on. Barrier completion synchronizes: everything
//    before the application thread's arrival happens-before everything after the workers'
//    return from the wait, so each worker sees its filled queue. No atomics are needed.
//  * Work phase: worker w calls Push(w, ...) and TryPop(w, ...) only, from one thread;
//    TryPop(w) returns false when w's own queue is empty (no stealing), even if others are not.
//  * End of frame: workers arrive at the closing barrier; only after it may the application
//    thread fill again (or read stats()). Any other overlap is a data race (TSan reports it).
template <QueueTask T, class Stats = NoQueueStats>
class LocalQueues {
 public:
  using value_type = T;
  using stats_type = Stats;
  static constexpr QueueKind kKind = QueueKind::kLocal;

  // num_workers >= 1 queues, each with room for reserve_per_worker tasks before it regrows.
  explicit LocalQueues(int num_workers, size_t reserve_per_worker = 0)
      : num_workers_(num_workers),
        lanes_(std::make_unique<Lane[]>(static_cast<size_t>(num_workers))),
        stats_(num_workers) {
    if (reserve_per_worker > 0) {
      for (int w = 0; w < num_workers; ++w) lanes_[w].fifo.Reserve(reserve_per_worker);
    }
  }

  LocalQueues(const LocalQueues&) = delete;
  LocalQueues& operator=(const LocalQueues&) = delete;

  // addRays into worker's own queue (work phase: from worker `worker` only; fill phase: from
  // the application thread). Throws std::bad_alloc (queue unchanged) if it must grow and cannot.
  void Push(int worker, T&& task) {
    [[maybe_unused]] auto scope = stats_.Measure(worker);
    lanes_[worker].fifo.Push(std::move(task));
  }
  void Push(int worker, const T& task) requires std::copy_constructible<T> {
    [[maybe_unused]] auto scope = stats_.Measure(worker);
    lanes_[worker].fifo.Push(task);
  }
  // Push of tasks[0], tasks[1], ... in that order (moved from), with room made first: throws
  // std::bad_alloc with the queue unchanged and the tasks untouched.
  void PushMany(int worker, std::span<T> tasks) {
    [[maybe_unused]] auto scope = stats_.Measure(worker);
    queue_detail::BlockFifo<T>& fifo = lanes_[worker].fifo;
    fifo.Reserve(tasks.size());
    for (T& task : tasks) fifo.Push(std::move(task));
  }
  // Fill phase only: deals the task to the next worker in round-robin order (task i of the
  // frame to worker (start + i) % num_workers; RewindPrimary() resets start to 0).
  void PushPrimary(T&& task) {
    [[maybe_unused]] auto scope = stats_.Measure(num_workers_);
    lanes_[next_primary_].fifo.Push(std::move(task));
    if (++next_primary_ == num_workers_) next_primary_ = 0;
  }
  // Fill phase only: room for n tasks in every worker's queue before it regrows.
  void Reserve(size_t n) {
    for (int w = 0; w < num_workers_; ++w) lanes_[w].fifo.Reserve(n);
  }
  // Fill phase only: the next PushPrimary goes to worker 0 (deterministic per-frame dealing).
  void RewindPrimary() { next_primary_ = 0; }

  // getRays from worker's own queue; false (EMPTY) when that queue is empty. Never throws.
  bool TryPop(int worker, T& out) noexcept {
    [[maybe_unused]] auto scope = stats_.Measure(worker);
    return lanes_[worker].fifo.Pop(out);
  }

  // TryPop for up to out.size() tasks; returns how many (0: EMPTY; out untouched past it).
  size_t TryPopMany(int worker, std::span<T> out) noexcept {
    [[maybe_unused]] auto scope = stats_.Measure(worker);
    queue_detail::BlockFifo<T>& fifo = lanes_[worker].fifo;
    size_t n = 0;
    while (n < out.size() && fifo.Pop(out[n])) ++n;
    return n;
  }

  // Tasks waiting in worker's queue. Same threading rules as TryPop(worker).
  size_t size(int worker) const { return lanes_[worker].fifo.size(); }

  int num_workers() const { return num_workers_; }
  const Stats& stats() const { return stats_; }
  Stats& stats() { return stats_; }

 private:
  // Padded: workers write their own lane's indices on every operation.
  struct alignas(kQueueFalseSharing) Lane {
    queue_detail::BlockFifo<T> fifo;
  };

  int num_workers_;
  int next_primary_ = 0;
  std::unique_ptr<Lane[]> lanes_;
  [[no_unique_address]] Stats stats_;
};

}  // namespace rs
