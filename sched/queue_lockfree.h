// LFREE: the Michael & Scott (PODC 1996) lock-free FIFO queue with safe memory reclamation by
// tagged 32-bit indices into a growable, type-stable node pool with a lock-free free list. It
// replaces the paper's listing 5, whose `delete first` after the CAS is a use-after-free and ABA.
#pragma once

#include <atomic>
#include <bit>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <memory>
#include <new>
#include <span>
#include <type_traits>
#include <utility>

#include "sched/queue.h"

namespace rs {

// Multi-producer multi-consumer unbounded FIFO; every operation is lock-free (no mutex, no
// blocking; a thread retries only when another thread's CAS succeeded, i.e. made progress).
// The one exception is growing the pool, which calls operator new (the allocator may lock);
// pass reserve_nodes >= the peak queue length to keep the hot path allocation-free.
//
// Representation. Head, Tail, every node's `next` and the free-list top are one 64-bit atomic
// word {tag: high 32 bits, index: low 32 bits}; kNull is the null index. Nodes live in chunks of
// 64, 64, 128, 256, ... nodes that are allocated on demand, published with a CAS into a fixed
// table, and freed only by the destructor. Free nodes sit in a small per-worker node cache (plain
// memory, private to the thread using that worker id) or on the shared free list, a Treiber
// stack over the same nodes. The cache is what makes LFREE cheap in the renderer's pattern (pop
// a task, push its secondary tasks): the node a worker frees is reused by its next push, so a
// push+pop pair costs 3 CASes on the queue instead of 5 with 2 on a shared free-list top.
// PushMany and TryPopMany (inline tasks) move whole chains of nodes with the same CASes, and
// an empty cache refills with up to half its size from the free list in one CAS.
//
// Why this is safe (the argument the tests probe under TSan and ASan):
//  1. No use-after-free: node memory is type-stable: a node removed from the queue goes to a
//     cache or the free list and is reused for another task, but lives until ~LockFreeQueue. A
//     slow thread holding a stale index therefore reads a live object. Stale readers touch only
//     atomic fields (`next`, `refs`, `free_next`, and for inline tasks `bits`), never T storage,
//     so there are no data races, only stale values, which the next point rejects.
//  2. No ABA: every successful write to a tagged word (Head, Tail, each `next`, free-list top)
//     increments its tag, including the reset of `next` to null when a node is reallocated
//     (a free node's `next` is never null, so no enqueuer's CAS can hit a node while it is
//     free). A CAS whose expected value was read before the node was recycled therefore fails,
//     unless a multiple of 2^32 writes hit that one word while the thread was stalled between
//     its load and its CAS: ~4.3e9 contended CASes, minutes of saturated traffic, while one
//     thread sits descheduled between two adjacent instructions. This is M&S's counted-pointer
//     argument with 32-bit counts (and its usual caveat). tests/sched/queue_test.cc replays the
//     free-list, Head and link-reset ABA interleavings deterministically; each fails when the
//     corresponding tag increment is removed. (The link CAS's own increment is then redundant,
//     since the reset already bumps the tag; it is kept so that the rule has no exceptions.)
//  3. Ownership of the task: only the enqueuer writes T storage, before the release-CAS that
//     links the node; only the dequeuer whose CAS moved Head from H to N reads it (N's task),
//     after its acquire load of H.next. M&S read the value *before* that CAS because N may be
//     freed as soon as Head moves on; for a general (move-only, non-trivial) T that read would
//     race with a recycled node's new task. Instead each node carries refs = 2 (its task and its
//     link) and returns to the free list when both are released: the winning dequeuer moves the
//     task out of N, destroys it, and releases N's task reference; whoever later unlinks N as the
//     dummy releases its link reference. So N cannot be recycled while its task is being moved.
//     Tasks that are trivially copyable and <= 8 bytes (e.g. an index into a task pool) are
//     stored in an atomic word and read before the CAS exactly as in M&S (a stale read is an
//     atomic read of a live node, discarded when the CAS fails), and need no reference count.
//  4. Memory order: a node's contents are published by the release CAS that links it (E9) and
//     acquired by the load of `next`; Head/Tail CASes are acq_rel and their loads acquire, so
//     every index a thread dereferences was obtained through an acquire that is ordered after
//     the installation of its chunk and the initialization of the node.
//
// Costs per operation: Push and PushMany = link CAS + tail CAS (+ a free-list pop CAS when the
// worker's cache is empty); TryPop = head CAS (+ one fetch_sub for non-inline tasks; + one
// free-list push CAS per node_cache/2 pops when the cache overflows); TryPopMany = one head CAS
// per kMaxPopChain inline tasks. Destroying the queue destroys remaining tasks;
// destruction, like construction, must not be concurrent with other operations.
//
// Worker ids identify threads: at any time at most one thread may use a given worker id (and
// one thread PushPrimary, which has its own id). The id selects the node cache and the
// statistics slot; which thread holds which id may change between frames (after a barrier).
template <QueueTask T, class Stats = NoQueueStats>
class LockFreeQueue {
 public:
  using value_type = T;
  using stats_type = Stats;
  static constexpr QueueKind kKind = QueueKind::kLockFree;
  // True when tasks are kept in an atomic word and read before the CAS (M&S D12).
  static constexpr bool kInlineTask =
      std::is_trivially_copyable_v<T> && sizeof(T) <= 8 && std::is_default_constructible_v<T>;

  static_assert(std::atomic<uint64_t>::is_always_lock_free, "LFREE needs 64-bit atomics");
  static_assert(std::atomic<uint32_t>::is_always_lock_free, "LFREE needs 32-bit atomics");

  static constexpr uint32_t kDefaultNodeCache = 32;
  static constexpr uint32_t kMaxNodeCache = 1024;

  // num_workers >= 1 threads will pass worker ids in [0, num_workers). reserve_nodes > 0
  // preallocates at least that many nodes (one is the dummy), so that many tasks can be queued
  // without allocating. node_cache (<= kMaxNodeCache) free nodes are kept per worker; 0 sends
  // every freed node to the shared free list (the plain M&S allocator; tests use it to replay
  // free-list ABA). Throws std::bad_alloc.
  explicit LockFreeQueue(int num_workers, size_t reserve_nodes = 0,
                         uint32_t node_cache = kDefaultNodeCache)
      : num_workers_(num_workers),
        node_cache_(node_cache < kMaxNodeCache ? node_cache : kMaxNodeCache),
        caches_(std::make_unique<NodeCache[]>(static_cast<size_t>(num_workers) + 1)),
        stats_(num_workers) {
    for (auto& chunk : chunks_) chunk.store(nullptr, std::memory_order_relaxed);
    free_.store(Pack(0, kNull), std::memory_order_relaxed);
    uint32_t dummy = kNull;
    try {
      while (capacity() < reserve_nodes) {
        const uint32_t first = Grow();
        PushFreeChain(first, first);
      }
      dummy = AllocShared();
    } catch (...) {
      FreeChunks();
      throw;
    }
    Node& node = At(dummy);
    node.next.store(Pack(Tag(node.next.load(std::memory_order_relaxed)) + 1, kNull),
                    std::memory_order_relaxed);
    node.refs.store(1, std::memory_order_relaxed);  // the dummy has a link, no task
    head_.store(Pack(0, dummy), std::memory_order_relaxed);
    tail_.store(Pack(0, dummy), std::memory_order_relaxed);
  }

  ~LockFreeQueue() {
    if constexpr (!kInlineTask) {
      uint32_t index = Index(
          At(Index(head_.load(std::memory_order_acquire))).next.load(std::memory_order_acquire));
      while (index != kNull) {
        Node& node = At(index);
        std::destroy_at(node.payload.Ptr());
        index = Index(node.next.load(std::memory_order_acquire));
      }
    }
    FreeChunks();
  }

  LockFreeQueue(const LockFreeQueue&) = delete;
  LockFreeQueue& operator=(const LockFreeQueue&) = delete;

  // addRays: appends the task. Called by the thread holding worker id `worker` (which selects
  // the node cache and statistics slot). Throws std::bad_alloc (queue unchanged) if the pool
  // must grow and cannot.
  void Push(int worker, T&& task) {
    [[maybe_unused]] auto scope = stats_.Measure(worker);
    Enqueue(worker, 1, [&](size_t, T* slot) { std::construct_at(slot, std::move(task)); });
  }
  void Push(int worker, const T& task) requires std::copy_constructible<T> {
    [[maybe_unused]] auto scope = stats_.Measure(worker);
    if constexpr (std::is_nothrow_copy_constructible_v<T>) {
      Enqueue(worker, 1, [&](size_t, T* slot) { std::construct_at(slot, task); });  // no copy
    } else {
      T copy(task);  // a throwing copy happens before any node is taken
      Enqueue(worker, 1, [&](size_t, T* slot) { std::construct_at(slot, std::move(copy)); });
    }
  }
  // Appends tasks[0], tasks[1], ... in that order (moved from), as consecutive Push calls of
  // this worker would, but as one operation: the nodes are linked to each other first and then
  // to the queue by one link CAS and one Tail CAS, so a batch of n tasks costs the shared
  // cache lines 2 CASes instead of 2n. Consumers may see the chain before Tail has moved over
  // it; they help Tail along node by node, as M&S's dequeuers already do for one node. Throws
  // std::bad_alloc (queue unchanged, tasks untouched) if the pool must grow and cannot.
  void PushMany(int worker, std::span<T> tasks) {
    if (tasks.empty()) return;
    [[maybe_unused]] auto scope = stats_.Measure(worker);
    Enqueue(worker, tasks.size(),
            [&](size_t i, T* slot) { std::construct_at(slot, std::move(tasks[i])); });
  }
  // The application thread's push of a primary task; timed in the application slot, so call it
  // from one thread at a time when Stats is enabled.
  void PushPrimary(T&& task) {
    [[maybe_unused]] auto scope = stats_.Measure(num_workers_);
    Enqueue(num_workers_, 1, [&](size_t, T* slot) { std::construct_at(slot, std::move(task)); });
  }

  // getRays: moves the oldest task into `out` and returns true, or returns false (EMPTY) if the
  // queue was empty at the moment of the call's linearization (`out` untouched). Called by the
  // thread holding worker id `worker`. Never throws.
  bool TryPop(int worker, T& out) noexcept {
    [[maybe_unused]] auto scope = stats_.Measure(worker);
    return Dequeue(worker, out);
  }

  // getRays for up to out.size() tasks: moves the oldest ones into out[0], out[1], ... in FIFO
  // order and returns how many (0: EMPTY at the call's linearization; out untouched past the
  // count). For inline tasks up to kMaxPopChain of them leave with one Head CAS: the dequeuer
  // walks `next` from Head (not past the Tail it read, so Head never overtakes Tail), reads
  // the tasks, and moves Head to the last of them, which becomes the dummy. If the CAS
  // succeeds Head did not move meanwhile, so no node of the walk was recycled and every value
  // read is current (the argument of D12 for one node). Out-of-line tasks pop one at a time.
  // Never throws.
  size_t TryPopMany(int worker, std::span<T> out) noexcept {
    if (out.empty()) return 0;
    [[maybe_unused]] auto scope = stats_.Measure(worker);
    if constexpr (!kInlineTask) {
      size_t n = 0;
      while (n < out.size() && Dequeue(worker, out[n])) ++n;
      return n;
    } else {
      size_t n = 0;
      while (n < out.size()) {
        const size_t got = DequeueChain(worker, out.subspan(n));
        n += got;
        if (got < kMaxPopChain) break;  // the queue ran out (or out is full)
      }
      return n;
    }
  }

  // Tasks a TryPopMany takes with one Head CAS (inline tasks).
  static constexpr size_t kMaxPopChain = 64;

  // Fill phase only (no concurrent Push / TryPop): grows the node pool to at least n nodes,
  // so that many tasks can be queued without allocating. Throws std::bad_alloc.
  void Reserve(size_t n) {
    while (capacity() < n) {
      const uint32_t first = Grow();
      PushFreeChain(first, first);
    }
  }

  int num_workers() const { return num_workers_; }
  const Stats& stats() const { return stats_; }
  Stats& stats() { return stats_; }

  // Nodes allocated so far (queued tasks + dummy + free list). Grows geometrically, never
  // shrinks; steady push/pop traffic reuses nodes and does not grow it. Racy while in use.
  size_t capacity() const {
    size_t total = 0;
    for (int k = 0; k < kMaxChunks; ++k) {
      if (chunks_[k].load(std::memory_order_acquire) != nullptr) total += ChunkSize(k);
    }
    return total;
  }

 private:
  static constexpr uint32_t kNull = 0xFFFFFFFFu;
  static constexpr int kLogFirstChunk = 6;
  static constexpr uint32_t kFirstChunk = 1u << kLogFirstChunk;
  // Chunks 0..25 hold indices [0, 2^31): far beyond memory, and kNull is never a node index.
  static constexpr int kMaxChunks = 32 - kLogFirstChunk;

  static constexpr uint64_t Pack(uint32_t tag, uint32_t index) {
    return (static_cast<uint64_t>(tag) << 32) | index;
  }
  static constexpr uint32_t Tag(uint64_t word) { return static_cast<uint32_t>(word >> 32); }
  static constexpr uint32_t Index(uint64_t word) { return static_cast<uint32_t>(word); }

  // Task storage: an atomic word for small trivially copyable tasks, raw storage otherwise.
  struct InlinePayload {
    std::atomic<uint64_t> bits{0};
  };
  struct OutOfLinePayload {
    alignas(T) std::byte storage[sizeof(T)];
    T* Ptr() { return std::launder(reinterpret_cast<T*>(storage)); }
  };
  using Payload = std::conditional_t<kInlineTask, InlinePayload, OutOfLinePayload>;

  // 64-byte aligned so that a producer filling one node and a consumer reading its neighbour do
  // not share a cache line (for small tasks a node is exactly one line).
  struct alignas(alignof(T) > 64 ? alignof(T) : 64) Node {
    std::atomic<uint64_t> next{Pack(0, kNull)};  // {tag, index of the successor}
    std::atomic<uint32_t> refs{0};               // task + link references (non-inline tasks)
    std::atomic<uint32_t> free_next{kNull};      // free-list link (index only; top is tagged)
    Payload payload;
  };

  static uint64_t ToBits(const T& task) {
    uint64_t bits = 0;
    std::memcpy(&bits, &task, sizeof(T));
    return bits;
  }
  static T FromBits(uint64_t bits) {
    T task;
    std::memcpy(&task, &bits, sizeof(T));
    return task;
  }

  void FreeChunks() noexcept {
    for (int k = 0; k < kMaxChunks; ++k) delete[] chunks_[k].load(std::memory_order_acquire);
  }

  static constexpr uint32_t ChunkSize(int k) {
    return k == 0 ? kFirstChunk : kFirstChunk << (k - 1);
  }
  static constexpr uint32_t ChunkFirst(int k) { return k == 0 ? 0 : kFirstChunk << (k - 1); }

  Node& At(uint32_t index) const {
    const int k = static_cast<int>(std::bit_width(index >> kLogFirstChunk));
    // acquire: free on x86; the index already arrived through an acquire chain (point 4), this
    // only makes the chunk publication self-evidently ordered.
    return chunks_[k].load(std::memory_order_acquire)[index - ChunkFirst(k)];
  }

  // D2-D10 of M&S dequeue: Head, Tail and Head's next read consistently, with Head != Tail and
  // a non-null next (a lagging Tail is helped along first). False: the queue was empty.
  bool Snapshot(uint64_t& head, uint64_t& tail, uint64_t& next) noexcept {
    for (;;) {
      head = head_.load(std::memory_order_acquire);                 // D2
      tail = tail_.load(std::memory_order_acquire);                 // D3
      next = At(Index(head)).next.load(std::memory_order_acquire);  // D4
      if (head != head_.load(std::memory_order_acquire)) continue;  // D5: consistent?
      if (Index(head) == Index(tail)) {                             // D6
        if (Index(next) == kNull) return false;                     // D7-D8: empty
        // D10: Tail lags behind a linked node; help it along before Head may pass it.
        tail_.compare_exchange_strong(tail, Pack(Tag(tail) + 1, Index(next)),
                                      std::memory_order_acq_rel, std::memory_order_relaxed);
        continue;
      }
      if (Index(next) == kNull) continue;  // cannot happen when Head was stable; re-read
      return true;
    }
  }

  // M&S dequeue of one task (D1-D19), untimed.
  bool Dequeue(int worker, T& out) noexcept {
    if constexpr (kInlineTask) {
      // The walk of one node (D12: the task is read before the CAS).
      return DequeueChain(worker, std::span<T>(&out, 1)) == 1;
    } else {
      for (;;) {
        uint64_t head, tail, next;
        if (!Snapshot(head, tail, next)) return false;
        Node& second = At(Index(next));
        RS_QUEUE_CHAOS_POINT("dequeue");
        if (head_.compare_exchange_strong(head, Pack(Tag(head) + 1, Index(next)),
                                          std::memory_order_acq_rel,
                                          std::memory_order_relaxed)) {  // D13
          // We own second's task: nobody else reads it, and `second` keeps its task reference
          // until the Release below, so it cannot be recycled while we move from it.
          RS_QUEUE_CHAOS_POINT("dequeue_owned");
          T* task = second.payload.Ptr();
          out = std::move(*task);
          std::destroy_at(task);
          Release(worker, Index(next));  // the task reference
          Release(worker, Index(head));  // the link reference of the old dummy
          return true;
        }
      }
    }
  }

  // M&S dequeue of up to min(out.size(), kMaxPopChain) inline tasks with one Head CAS
  // (TryPopMany's walk; TryPop's with one). Returns how many; 0 only when the queue was empty.
  size_t DequeueChain(int worker, std::span<T> out) noexcept {
    const size_t want = out.size() < kMaxPopChain ? out.size() : kMaxPopChain;
    uint64_t bits[kMaxPopChain];
    for (;;) {
      uint64_t head, tail, next;
      if (!Snapshot(head, tail, next)) return 0;
      // Stale reads in the walk (Head moved meanwhile) read live nodes (point 1) and are
      // discarded when the CAS fails; the walk is bounded by `want`, so it ends regardless.
      uint32_t last = Index(next);
      size_t n = 0;
      for (;;) {
        bits[n++] = At(last).payload.bits.load(std::memory_order_relaxed);
        if (n == want || last == Index(tail)) break;
        const uint32_t after = Index(At(last).next.load(std::memory_order_acquire));
        if (after == kNull) break;
        last = after;
      }
      RS_QUEUE_CHAOS_POINT("dequeue");
      if (head_.compare_exchange_strong(head, Pack(Tag(head) + 1, last), std::memory_order_acq_rel,
                                        std::memory_order_relaxed)) {  // D13
        // D19: the old dummy and every node taken but the last (the new dummy) are free. Each
        // `next` is read before its node goes to the cache, whose overflow may hand it on.
        uint32_t node = Index(head);
        for (size_t i = 0; i < n; ++i) {
          out[i] = FromBits(bits[i]);
          const uint32_t following = Index(At(node).next.load(std::memory_order_relaxed));
          FreeNode(worker, node);
          node = following;
        }
        return n;
      }
    }
  }

  // M&S enqueue (E1-E17) of a chain of n >= 1 new nodes; fill(i, slot) constructs task i at
  // `slot` and must not throw. All nodes are taken before any task is built, so a bad_alloc
  // leaves the queue and the tasks as they were.
  template <class Fill>
  void Enqueue(int slot, size_t n, Fill&& fill) {
    // E1: the nodes, linked first -> ... -> last. E3 for all but the last: each link is
    // written with a new tag (see below), which makes a stale enqueuer's CAS on it fail.
    const uint32_t first = AllocNode(slot);  // may throw, nothing is published yet
    uint32_t last = first;
    try {
      for (size_t i = 1; i < n; ++i) {
        const uint32_t index = AllocNode(slot);
        Node& prev = At(last);
        prev.next.store(Pack(Tag(prev.next.load(std::memory_order_relaxed)) + 1, index),
                        std::memory_order_relaxed);
        last = index;
      }
    } catch (...) {
      for (uint32_t node = first;;) {  // every `next` of the chain is non-null: free is safe
        const uint32_t following = Index(At(node).next.load(std::memory_order_relaxed));
        const bool end = node == last;
        FreeNode(slot, node);
        if (end) break;
        node = following;
      }
      throw;
    }
    uint32_t node = first;
    for (size_t i = 0; i < n; ++i) {  // E2
      Node& dst = At(node);
      if constexpr (kInlineTask) {
        alignas(T) std::byte raw[sizeof(T)];
        fill(i, reinterpret_cast<T*>(raw));
        dst.payload.bits.store(ToBits(*std::launder(reinterpret_cast<T*>(raw))),
                               std::memory_order_relaxed);
      } else {
        fill(i, dst.payload.Ptr());
        dst.refs.store(2, std::memory_order_relaxed);
      }
      node = Index(dst.next.load(std::memory_order_relaxed));
    }
    // E3: reset the last link with a new tag. Nobody else writes `next` of a free node:
    // enqueuers only CAS a null `next`, and a free node's `next` is non-null (it was unlinked
    // as a dummy with a successor, or was an inner link of a chain) or, for a never-used node,
    // has a tag no stale thread has read.
    Node& end = At(last);
    end.next.store(Pack(Tag(end.next.load(std::memory_order_relaxed)) + 1, kNull),
                   std::memory_order_relaxed);
    const uint32_t index = first;
    uint64_t tail;
    for (;;) {                                                               // E4
      tail = tail_.load(std::memory_order_acquire);                          // E5
      uint64_t next = At(Index(tail)).next.load(std::memory_order_acquire);  // E6
      if (tail != tail_.load(std::memory_order_acquire)) continue;           // E7
      if (Index(next) == kNull) {                                            // E8
        RS_QUEUE_CHAOS_POINT("enqueue");
        // E9: link; release publishes the tasks and the chain's links.
        if (At(Index(tail))
                .next.compare_exchange_weak(next, Pack(Tag(next) + 1, index),
                                            std::memory_order_release, std::memory_order_relaxed)) {
          break;
        }
      } else {
        // E13: another enqueuer linked but has not swung Tail yet; help it.
        tail_.compare_exchange_strong(tail, Pack(Tag(tail) + 1, Index(next)),
                                      std::memory_order_acq_rel, std::memory_order_relaxed);
      }
    }
    // E17: swing Tail to our last node; failure means another thread already helped (Tail then
    // lags inside the chain until helpers move it on, node by node: E13, D10).
    tail_.compare_exchange_strong(tail, Pack(Tag(tail) + 1, last), std::memory_order_acq_rel,
                                  std::memory_order_relaxed);
  }

  // Drops one of a node's two references; the last one returns it to the free list. A load of 1
  // means the other reference is gone (its fetch_sub wrote the 1 and we acquired it) and we are
  // the only owner, so the common "old dummy" case costs no read-modify-write.
  void Release(int slot, uint32_t index) noexcept {
    Node& node = At(index);
    if (node.refs.load(std::memory_order_acquire) == 1 ||
        node.refs.fetch_sub(1, std::memory_order_acq_rel) == 1) {
      FreeNode(slot, index);
    }
  }

  // A worker's private stack of free node indices. Only the thread holding the worker id
  // touches it, so it needs no atomics; a node in it is free in the sense of point 1.
  struct alignas(kQueueFalseSharing) NodeCache {
    uint32_t count = 0;
    uint32_t nodes[kMaxNodeCache];
  };

  // From the worker's cache; an empty cache takes up to half its size from the shared free
  // list at once (one CAS), so a PushMany of many tasks does not pay a CAS per node.
  uint32_t AllocNode(int slot) {
    NodeCache& cache = caches_[slot];
    if (cache.count > 0) return cache.nodes[--cache.count];
    if (node_cache_ > 1) {
      cache.count = PopFreeChain(cache.nodes, node_cache_ / 2);
      if (cache.count > 0) return cache.nodes[--cache.count];
    }
    return AllocShared();
  }

  // Treiber pop of up to max >= 1 nodes with one CAS: walks free_next from the top and moves
  // the top past the last node taken. As in AllocShared, the walk may read stale links when
  // the list changes meanwhile; then the top's tag changed and the CAS fails. Returns how many
  // (0: the list is empty).
  uint32_t PopFreeChain(uint32_t* out, uint32_t max) noexcept {
    uint64_t top = free_.load(std::memory_order_acquire);
    for (;;) {
      if (Index(top) == kNull) return 0;
      uint32_t n = 0;
      uint32_t node = Index(top);
      uint32_t rest = kNull;
      for (;;) {
        out[n++] = node;
        rest = At(node).free_next.load(std::memory_order_relaxed);
        if (n == max || rest == kNull) break;
        node = rest;
      }
      RS_QUEUE_CHAOS_POINT("alloc");
      if (free_.compare_exchange_weak(top, Pack(Tag(top) + 1, rest), std::memory_order_acquire,
                                      std::memory_order_acquire)) {
        return n;
      }
    }
  }

  // Keeps the node in the worker's cache; when the cache is full, its older half goes to the
  // shared free list as one chain (one CAS).
  void FreeNode(int slot, uint32_t index) noexcept {
    NodeCache& cache = caches_[slot];
    if (cache.count < node_cache_) {
      cache.nodes[cache.count++] = index;
      return;
    }
    if (node_cache_ == 0) {
      PushFreeChain(index, index);
      return;
    }
    const uint32_t give = (cache.count + 1) / 2;
    for (uint32_t i = 0; i + 1 < give; ++i) {
      At(cache.nodes[i]).free_next.store(cache.nodes[i + 1], std::memory_order_relaxed);
    }
    PushFreeChain(cache.nodes[0], cache.nodes[give - 1]);
    for (uint32_t i = give; i < cache.count; ++i) cache.nodes[i - give] = cache.nodes[i];
    cache.count -= give;
    cache.nodes[cache.count++] = index;
  }

  // Treiber push of the chain first -> ... -> last (linked by free_next) onto the free list;
  // release orders the destroyed tasks and the last reads of the nodes before their reuse by
  // the thread that pops them.
  void PushFreeChain(uint32_t first, uint32_t last) noexcept {
    Node& tail_node = At(last);
    uint64_t top = free_.load(std::memory_order_relaxed);
    do {
      tail_node.free_next.store(Index(top), std::memory_order_relaxed);
    } while (!free_.compare_exchange_weak(top, Pack(Tag(top) + 1, first), std::memory_order_release,
                                          std::memory_order_relaxed));
  }

  // Treiber pop; grows the pool when the free list is empty. The relaxed read of free_next may
  // see a stale value if the node was popped and pushed again meanwhile, but then the top's tag
  // changed and the CAS fails (point 2).
  uint32_t AllocShared() {
    for (;;) {
      uint64_t top = free_.load(std::memory_order_acquire);
      while (Index(top) != kNull) {
        const uint32_t next = At(Index(top)).free_next.load(std::memory_order_relaxed);
        RS_QUEUE_CHAOS_POINT("alloc");
        if (free_.compare_exchange_weak(top, Pack(Tag(top) + 1, next), std::memory_order_acquire,
                                        std::memory_order_acquire)) {
          return Index(top);
        }
      }
      const uint32_t grown = Grow();
      if (grown != kNull) return grown;
      // Another thread installed the chunk we tried; its nodes are arriving on the free list.
    }
  }

  // Installs the first empty chunk, keeps its first node for the caller and pushes the rest onto
  // the free list. Returns kNull if another thread won that chunk slot (the caller retries).
  uint32_t Grow() {
    for (int k = 0; k < kMaxChunks; ++k) {
      if (chunks_[k].load(std::memory_order_acquire) != nullptr) continue;
      const uint32_t size = ChunkSize(k);
      Node* chunk = new Node[size];
      Node* expected = nullptr;
      if (!chunks_[k].compare_exchange_strong(expected, chunk, std::memory_order_acq_rel,
                                              std::memory_order_acquire)) {
        delete[] chunk;  // never published
        return kNull;
      }
      const uint32_t first = ChunkFirst(k);
      for (uint32_t i = 1; i + 1 < size; ++i) {
        chunk[i].free_next.store(first + i + 1, std::memory_order_relaxed);
      }
      PushFreeChain(first + 1, first + size - 1);
      return first;
    }
    throw std::bad_alloc();
  }

  alignas(kQueueFalseSharing) std::atomic<uint64_t> head_;
  alignas(kQueueFalseSharing) std::atomic<uint64_t> tail_;
  alignas(kQueueFalseSharing) std::atomic<uint64_t> free_;
  alignas(kQueueFalseSharing) std::atomic<Node*> chunks_[kMaxChunks];
  int num_workers_;
  uint32_t node_cache_;
  std::unique_ptr<NodeCache[]> caches_;  // num_workers + 1 (the last is PushPrimary's)
  [[no_unique_address]] Stats stats_;
};

}  // namespace rs
