// The host backends of HostRenderer (see backends.h): serial, LOCK / LFREE / LOCAL queues with an
// outstanding-task counter for termination, and the tile counter / PBT tile lists; plus the
// JSON / CSV export of their per-frame, per-thread and per-tile statistics.
#include "sched/backends.h"

#include "scenes/image_io.h"  // WriteFileAtomically

#include <fmt/core.h>
#include <nlohmann/json.hpp>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <deque>
#include <exception>
#include <fstream>
#include <mutex>
#include <span>
#include <sstream>
#include <thread>
#include <type_traits>
#include <utility>

#include "sched/engine.h"
#include "sched/frame_loop.h"
#include "sched/queue.h"
#include "sched/queue_local.h"
#include "sched/queue_lock.h"
#include "sched/queue_lockfree.h"

namespace rs {

// ---------------------------------------------------------------------------------------------
// Names and options.

const char* BackendName(BackendKind kind) {
  switch (kind) {
    case BackendKind::kSerial:
      return "serial";
    case BackendKind::kLock:
      return "lock";
    case BackendKind::kLockFree:
      return "lfree";
    case BackendKind::kLocal:
      return "local";
    case BackendKind::kTiles:
      return "tiles";
  }
  return "?";
}

bool ParseBackendKind(std::string_view name, BackendKind* kind) {
  if (name == "serial" || name == "SERIAL") {
    *kind = BackendKind::kSerial;
  } else if (name == "tiles" || name == "TILES") {
    *kind = BackendKind::kTiles;
  } else {
    QueueKind q;
    if (!ParseQueueKind(name, &q)) return false;
    *kind = q == QueueKind::kLock       ? BackendKind::kLock
            : q == QueueKind::kLockFree ? BackendKind::kLockFree
                                        : BackendKind::kLocal;
  }
  return true;
}

std::vector<std::string> BackendNames() { return {"serial", "lock", "lfree", "local", "tiles"}; }

void ValidateBackendOptions(const BackendOptions& o) {
  auto fail = [](const std::string& what) { throw Error("backend options: " + what); };
  const int kind = static_cast<int>(o.kind);
  if (kind < 0 || kind > static_cast<int>(BackendKind::kTiles)) {
    fail(fmt::format("unknown backend {}", kind));
  }
  const char* name = BackendName(o.kind);
  if (o.threads < 1 || o.threads > FrameLoop::kMaxThreads) {
    fail(fmt::format("threads {} must be in [1, {}]", o.threads, FrameLoop::kMaxThreads));
  }
  if (o.kind == BackendKind::kSerial && o.threads != 1) {
    fail(fmt::format("backend serial runs on the calling thread: threads must be 1, not {}",
                     o.threads));
  }
  if (o.tile_width < 1 || o.tile_height < 1) {
    fail(fmt::format("tile {}x{} must be at least 1x1", o.tile_width, o.tile_height));
  }
  if (o.pbt_tiles_per_worker < 0 || o.pbt_tiles_per_worker > 4096) {
    fail(fmt::format("pbt tiles per worker {} must be in [0, 4096]", o.pbt_tiles_per_worker));
  }
  if (o.pbt_workers < 0 || o.pbt_workers > 65536) {
    fail(fmt::format("pbt workers {} must be in [0, 65536]", o.pbt_workers));
  }
  const bool queues = o.kind == BackendKind::kLock || o.kind == BackendKind::kLockFree ||
                      o.kind == BackendKind::kLocal;
  if (o.pbt_tiles_per_worker > 0 && o.kind == BackendKind::kSerial) {
    fail(fmt::format("PBT tiling (k = {}) needs a parallel backend (lock, lfree, local or "
                     "tiles), not serial",
                     o.pbt_tiles_per_worker));
  }
  if (o.pbt_steal && o.pbt_tiles_per_worker == 0) {
    fail("pbt_steal needs a PBT tiling (pbt_tiles_per_worker > 0)");
  }
  if (o.pbt_workers > 0 && o.pbt_tiles_per_worker == 0) {
    fail(fmt::format("pbt_workers {} needs a PBT tiling (pbt_tiles_per_worker > 0)",
                     o.pbt_workers));
  }
  const int assign = static_cast<int>(o.assign);
  if (assign < 0 || assign > static_cast<int>(PbtAssign::kLpt)) {
    fail(fmt::format("unknown PBT assignment {}", assign));
  }
  const int cost = static_cast<int>(o.pbt_cost);
  if (cost < 0 || cost > static_cast<int>(PbtCost::kWork)) {
    fail(fmt::format("unknown PBT cost {}", cost));
  }
  const int predict = static_cast<int>(o.pbt_predict);
  if (predict < 0 || predict > static_cast<int>(PbtPredict::kCostMap)) {
    fail(fmt::format("unknown PBT predictor {}", predict));
  }
  if (o.pbt_cost_block < 1 || o.pbt_cost_block > 256) {
    fail(fmt::format("pbt_cost_block {} must be in [1, 256] pixels", o.pbt_cost_block));
  }
  if (o.pbt_cost != PbtCost::kWall && o.pbt_tiles_per_worker == 0) {
    fail(fmt::format("pbt_cost {} needs a PBT tiling (pbt_tiles_per_worker > 0)",
                     PbtCostName(o.pbt_cost)));
  }
  if (o.pbt_tiles_per_worker > 0 && queues && o.pbt_cost != PbtCost::kWork) {
    fail(fmt::format("pbt_cost {} with backend {}: a queue backend traces a tile's rays on "
                     "whichever thread pops them, mixed with other tiles' rays in one batch, so "
                     "a tile has no wall or CPU time of its own; use pbt_cost work",
                     PbtCostName(o.pbt_cost), name));
  }
  if (o.pbt_steal && o.assign == PbtAssign::kCounter) {
    fail("pbt_steal needs per-worker lists; assign counter has one shared counter");
  }
  if (o.pbt_demand && (o.kind != BackendKind::kTiles || o.pbt_tiles_per_worker == 0)) {
    fail(fmt::format("pbt_demand (the demand-driven master) needs the tiles backend with a PBT "
                     "tiling (pbt_tiles_per_worker > 0), not {} with k = {}",
                     name, o.pbt_tiles_per_worker));
  }
  if (o.pbt_demand && o.assign == PbtAssign::kCounter) {
    fail("pbt_demand needs per-worker lists as the affinity; assign counter has none");
  }
  if (o.pbt_demand && o.pbt_steal) {
    fail("pbt_demand and pbt_steal exclude each other (the master hands out every tile)");
  }
}

int PbtWorkers(const BackendOptions& o) { return o.pbt_workers > 0 ? o.pbt_workers : o.threads; }

TilePlanOptions TilePlanOptionsFor(const BackendOptions& o) {
  TilePlanOptions p;
  p.tile_width = o.tile_width;
  p.tile_height = o.tile_height;
  p.pbt_tiles_per_worker = o.pbt_tiles_per_worker;
  p.workers = PbtWorkers(o);
  p.assign = o.assign;
  p.seed = o.seed;
  p.steal = o.pbt_steal;
  p.demand = o.pbt_demand;
  p.cost = o.pbt_cost;
  p.predict = o.pbt_predict;
  p.cost_block = o.pbt_cost_block;
  return p;
}

double TileCost(const TileRecord& r, PbtCost cost) {
  return cost == PbtCost::kCpu ? r.cpu_seconds : cost == PbtCost::kWork ? r.work : r.seconds;
}

void ApplyPlanReport(const TilePlanReport& report, HostFrameStats& s) {
  if (!report.pbt) return;
  s.pbt = true;
  s.has_prediction = report.has_prediction;
  s.accuracy = report.accuracy;
  s.worker_imbalance = report.worker_imbalance;
  s.demand_imbalance = report.demand_imbalance;
  s.lpt_imbalance = report.lpt_imbalance;
  s.predicted_makespan = report.predicted_makespan;
  s.update = report.update;
}

double HostFrameStats::IdleSeconds() const {
  double s = 0;
  for (const ThreadStats& t : threads) s += t.idle_seconds;
  return s;
}

double HostFrameStats::ContentionFreeSeconds(int cores) const {
  double slowest = 0, sum = 0;
  for (const ThreadStats& t : threads) {
    slowest = std::max(slowest, t.cpu_seconds);
    sum += t.cpu_seconds;
  }
  return app_cpu_seconds + std::max(slowest, sum / std::max(cores, 1));
}

double HostFrameStats::QueueSeconds() const {
  double s = app_queue_seconds;
  for (const ThreadStats& t : threads) s += t.queue_seconds;
  return s;
}

// ---------------------------------------------------------------------------------------------
// Shared pieces.

namespace {

using Clock = std::chrono::steady_clock;

double Seconds(Clock::time_point a, Clock::time_point b) {
  return std::chrono::duration<double>(b - a).count();
}

// max / mean of the threads' busy seconds (FrameImbalance's definition, without a copy).
double Imbalance(const std::vector<ThreadStats>& threads) {
  double sum = 0, most = 0;
  for (const ThreadStats& t : threads) {
    sum += t.busy_seconds;
    most = std::max(most, t.busy_seconds);
  }
  return sum > 0 ? most * static_cast<double>(threads.size()) / sum : 1.0;
}

}  // namespace

// The per-backend part of HostRenderer. The application-thread-only state lives here; the
// backends add what their render threads share.
class HostRenderer::Impl {
 public:
  explicit Impl(const BackendOptions& options) : options_(options) {}
  virtual ~Impl() = default;

  // Called by BeginFrame on the application thread with ctx_, fb_, begin_ set. `tiles` is the
  // explicit tile set or nullptr for the whole image. Loads the frame and releases the threads.
  virtual void Begin(const std::vector<Tile>* tiles) = 0;
  // Called by EndFrame: waits for the frame and fills stats_.threads, total (counters),
  // primary_tasks, tiles and the PBT fields; EndFrame sets frame, backend, the frame's wall
  // time and the imbalance. Rethrows a render thread's exception.
  virtual void End() = 0;
  virtual const Pbt* pbt() const { return nullptr; }
  virtual TilePlanMeasure cost_map_measure() const { return {}; }

  BackendOptions options_;
  FrameContext ctx_;
  Framebuffer* fb_ = nullptr;
  Clock::time_point begin_{};
  double app_cpu_ = 0;  // application thread's CPU time in Begin
  HostFrameStats stats_;
  uint64_t frames_ = 0;
  bool in_frame_ = false;
};

namespace {

// ---------------------------------------------------------------------------------------------
// serial: the reference renderer on the application thread, run in EndFrame.

class SerialImpl final : public HostRenderer::Impl {
 public:
  using Impl::Impl;

  void Begin(const std::vector<Tile>* tiles) override {
    whole_ = tiles == nullptr;
    if (tiles != nullptr) tiles_ = *tiles;
  }

  void End() override {
    const double cpu0 = ThreadCpuSeconds();
    FrameStats work;
    if (whole_) {
      work = renderer_.Render(ctx_, *fb_);
    } else {
      fifo_.RenderTiles(ctx_, tiles_.data(), tiles_.size(), *fb_, work);
    }
    stats_.threads.assign(1, ThreadStats{});
    ThreadStats& t = stats_.threads[0];
    t.work = work;
    t.busy_seconds = Seconds(begin_, Clock::now());
    t.cpu_seconds = ThreadCpuSeconds() - cpu0;
    stats_.total = work;
    stats_.primary_tasks = 0;
  }

 private:
  SerialRenderer renderer_;
  SerialRenderer fifo_;  // one tile's whole ray tree on this thread
  std::vector<Tile> tiles_;
  bool whole_ = true;
};

// ---------------------------------------------------------------------------------------------
// LOCK / LFREE / LOCAL: listing 2 over a WorkQueue of task pointers, fed by image tiles.
//
// A task is a RayStream of at most task_size rays of one class (shadow or not), owned by the
// backend's TaskArena; the queues carry RayStream* (8 bytes: LFREE keeps it inline in the node
// and reads it before its CAS). A thread pops tasks until it holds ceil(batch / task_size) tasks
// of non-shadow rays or as many shadow rays as one Shade sub-chunk spawns (EngineShadowBatch:
// what RenderTile traces in one call), and traces each class as one stream
// (RayEngine::TraceGeneration), so the kernels see batches while the task stays the unit of the
// queues and of their statistics. Each ray is copied once on the
// way in (a class's tasks gathered array by array; a class of one task is traced in place) and
// once on the way out (the engine splits Shade's output by class, shadow rays grouped by light,
// and those streams are cut into tasks array by array); the secondary rays are pushed back
// (LOCAL: to the thread's own queue). That scheduling work is timed as
// FrameStats::schedule_seconds, apart from the kernels. Pushes and pops move a batch of tasks
// in one queue operation (PushMany, TryPopMany).
//
// With batches of >= 64 rays (Private()) the queues carry only the surplus of the threads' work
// instead of every ray: a thread traces the primaries of the tiles it feeds and what its own
// batches spawn itself, as private generations (Worker::Generation: the current one traced a
// batch slice at a time, in place; the next one appended to by the engine), and cuts into
// tasks and pushes only what exceeds kPrivateSlices slices per class, or all of its next
// generation when a thread of a shared queue found nothing to do (hungry_). Popped tasks are
// traced as above, their children joining the private rays. So a ray is copied only if it goes
// through a queue, a tile's rays mostly stay on one core, and a shared queue carries the
// surplus that balances the threads (LOCAL's surplus waits in the thread's own queue).
// With smaller batches (the paper's `--task-size 20 --batch 20`) every ray goes through the
// queue, task by task, as in the paper.
//
// Tiles feed the queues: a thread that finds its queue empty takes the next tile (an atomic
// counter) and pushes its primary tasks, so the tasks in flight are those of about one tile per
// thread, never the whole image. The rays in flight are capped (QueueRayCap): bounce rays that
// would pass the cap are dropped and counted (FrameStats::budget_dropped) — only exponential
// ray trees reach it.
//
// Termination with shared queues (LOCK, LFREE): TaskCount (frame_loop.h) counts tasks pushed and
// not yet processed, plus one for each thread holding private rays; a tile's primary tasks are
// counted before they are pushed, a batch's children (and a change of hold) before its tasks
// are retired. A thread leaves when it holds no private rays, the queue is EMPTY, no tile is
// left and the count is 0. LOCAL needs no counter: nobody else pushes into a thread's queue.
//
// PBT (pbt_tiles_per_worker > 0): the tiles and their order come from a TilePlan, as for the
// tiles backend. A thread takes the tiles of its own lists first (workers w, w + threads, ...,
// each in list order) and installs each in its feed slot, from which the primaries go out in
// chunks of about tile_size^2 (whole tasks), so a large PBT tile never floods the queue. LOCAL
// keeps a tile's chunks and all their descendants on the thread's own queue: with Greedy and
// Visit the same thread traces the same tiles frame after frame. A thread whose lists are done
// takes the back of the list with the most predicted work waiting (shared queues always, LOCAL
// with pbt_steal); on a shared queue it also takes chunks of other threads' tiles. Counter:
// the tiles from one shared counter over the plan's order. A tile's rays are traced by whoever
// pops them, mixed with other tiles' rays, so a tile has no time of its own: its cost is its
// deterministic work, every traced ray charged to the tile of its pixel (PbtTileLookup). Cell
// steps, triangle tests and shading calls are counted per kernel call, not per ray, and a
// coherent packet's cell steps and triangle tests depend on which rays a thread popped
// together, so only the ray counts enter (TileWork::rays; the calibrated cost of a shading
// call is 0, kTileWorkCoefficients). With the cost map (pbt_predict kCostMap) the engines
// charge each ray the same per-ray work to its pixel's block (RayEngine::SetBlockWork) and
// store the primaries' hit distances (CostMapRecord), so the plan gets a per-block map that is
// reprojected to the next camera, as from the tiles backend. The tile costs are not summed
// from the blocks: PBT tiles are halved at any pixel, not on block boundaries.

// Rays in flight a queue backend allows: per thread, its engine's budget and at least 64
// batches or tiles (a breadth-first generation of a tile is wider than the engine's depth-first
// one). Independent of the image size.
size_t QueueRayCap(const RenderOptions& o, size_t lights, size_t tile_pixels, int threads) {
  const size_t wide = 64 * std::max(static_cast<size_t>(o.batch), tile_pixels);
  return std::max(EngineRayBudget(o, lights), wide) * static_cast<size_t>(threads);
}

// Task streams, pooled: a shared pool (a mutex per Get / Put that reaches it) behind one free
// list per thread. A thread reuses the streams it retired itself first, so a task's lines are
// still in the cache of the core that rewrites them; with one LIFO pool for all, LOCAL's
// streams (each of its 14 arrays a separate line pair) went to whichever thread asked next and
// every Cut took them from the other core's cache. A thread's list holds at most `keep`
// streams (the rest spill to the pool), and the pool holds threads x keep streams on top of the
// peak of live tasks, so the lists cannot starve it. Addresses are stable (deque); nothing is
// allocated once the pool has reached its peak.
class TaskArena {
 public:
  // At least n streams of task_size rays plus `keep` per thread's list (application thread,
  // threads parked).
  void Reserve(int threads, size_t n, size_t keep, size_t task_size) {
    if (lists_ == nullptr) lists_ = std::make_unique<List[]>(static_cast<size_t>(threads));
    keep_ = keep;
    n += static_cast<size_t>(threads) * keep;
    while (all_.size() < n) {
      RayStream& s = all_.emplace_back();
      s.Reserve(task_size);
      free_.push_back(&s);
    }
    free_.reserve(all_.size());
    for (int w = 0; w < threads; ++w) lists_[static_cast<size_t>(w)].free.reserve(keep);
  }
  // n empty streams appended to `out` for thread w: its own list first, then the pool under
  // one lock.
  void Get(int w, size_t n, size_t task_size, std::vector<RayStream*>& out) {
    std::vector<RayStream*>& own = lists_[static_cast<size_t>(w)].free;
    for (; n > 0 && !own.empty(); --n) {
      out.push_back(own.back());
      own.pop_back();
    }
    if (n == 0) return;
    std::lock_guard<std::mutex> lock(mutex_);
    for (; n > 0; --n) {
      if (free_.empty()) {
        RayStream& s = all_.emplace_back();
        s.Reserve(task_size);
        free_.reserve(all_.size());
        out.push_back(&s);
        continue;
      }
      out.push_back(free_.back());
      free_.pop_back();
    }
  }
  // Thread w's retired streams: into its list up to `keep`, the rest into the pool.
  void Put(int w, RayStream* const* tasks, size_t n) {
    std::vector<RayStream*>& own = lists_[static_cast<size_t>(w)].free;
    size_t i = 0;
    for (; i < n && own.size() < keep_; ++i) {
      tasks[i]->Clear();
      own.push_back(tasks[i]);
    }
    if (i == n) return;
    std::lock_guard<std::mutex> lock(mutex_);
    for (; i < n; ++i) {
      tasks[i]->Clear();
      free_.push_back(tasks[i]);
    }
  }

 private:
  struct alignas(kQueueFalseSharing) List {
    std::vector<RayStream*> free;
  };
  std::unique_ptr<List[]> lists_;  // one per thread; a backend's thread count is fixed
  size_t keep_ = 0;
  std::mutex mutex_;
  std::deque<RayStream> all_;
  std::vector<RayStream*> free_;
};

// PBT per-worker tile lists for a frame: list v's waiting tiles are [head, tail) of the plan's
// list v, packed in one 64-bit word so the owner (front) and thieves (back) arbitrate the last
// tile with one CAS. Relaxed: the CAS only decides who feeds a tile; the lists were published
// by the opening barrier and the records are read after the closing one.
class PbtListRanges {
 public:
  // Application thread, threads parked: one range per list (allocates when the count changes).
  void Load(const Assignment& assignment) {
    const size_t lists = assignment.tiles.size();
    if (lists != size_) {
      ranges_ = std::make_unique<Range[]>(lists);
      size_ = lists;
    }
    for (size_t v = 0; v < lists; ++v) {
      ranges_[v].word.store(Pack(0, static_cast<uint32_t>(assignment.tiles[v].size())),
                            std::memory_order_relaxed);  // published by the opening barrier
    }
  }
  // The front (owner) or back (thief) waiting position of list v; false if none waits.
  bool Take(size_t v, bool front, uint32_t* pos) {
    std::atomic<uint64_t>& range = ranges_[v].word;
    uint64_t r = range.load(std::memory_order_relaxed);
    for (;;) {
      const uint32_t head = static_cast<uint32_t>(r);
      const uint32_t tail = static_cast<uint32_t>(r >> 32);
      if (head >= tail) return false;
      const uint64_t next = front ? Pack(head + 1, tail) : Pack(head, tail - 1);
      if (range.compare_exchange_weak(r, next, std::memory_order_relaxed,
                                      std::memory_order_relaxed)) {
        *pos = front ? head : tail - 1;
        return true;
      }
    }
  }
  // The list with the most predicted work waiting (the plan's steal weights; ties: lowest
  // index), or the number of lists if all are empty. Racy snapshot by design: a stale choice
  // only costs one failed Take. Lists never refill within a frame, so "all empty" is final.
  size_t Richest(const Assignment& assignment, const std::vector<double>& weight) const {
    const auto& lists = assignment.tiles;
    size_t best = lists.size();
    double best_work = -1.0;
    for (size_t v = 0; v < lists.size(); ++v) {
      const uint64_t r = ranges_[v].word.load(std::memory_order_relaxed);
      const uint32_t head = static_cast<uint32_t>(r);
      const uint32_t tail = static_cast<uint32_t>(r >> 32);
      if (head >= tail) continue;
      double work = 0;
      for (uint32_t p = head; p < tail; ++p) work += weight[static_cast<size_t>(lists[v][p])];
      if (work > best_work) {
        best_work = work;
        best = v;
      }
    }
    return best;
  }

 private:
  static uint64_t Pack(uint32_t head, uint32_t tail) {
    return static_cast<uint64_t>(head) | (static_cast<uint64_t>(tail) << 32);
  }
  struct alignas(kQueueFalseSharing) Range {
    std::atomic<uint64_t> word{0};
  };
  std::unique_ptr<Range[]> ranges_;
  size_t size_ = 0;
};

// Pixel -> tile index of a PBT frame: the tree's inner nodes flattened into one array (m - 1
// cuts), descended per ray (depth ~ log2 m). No per-pixel map; rebuilt each frame in place, so
// it allocates only in the first frame (m is fixed).
class PbtTileLookup {
 public:
  // Application thread. Leaves are numbered in in-order, the PBT's tile indices; throws
  // rs::Error if they do not match `tiles` (the plan's frame).
  void Build(const Pbt& pbt, const std::vector<Tile>& tiles, int width) {
    nodes_.clear();
    width_ = static_cast<uint32_t>(width);
    int32_t leaves = 0;
    root_ = Flatten(pbt, pbt.Root(), tiles, leaves);
    if (static_cast<size_t>(leaves) != tiles.size()) {
      throw Error(fmt::format("PBT lookup: {} leaves for {} tiles", leaves, tiles.size()));
    }
  }
  // The tile holding pixel y * width + x (inside the image).
  size_t TileOf(uint32_t pixel) const {
    const uint32_t y = pixel / width_;
    const uint32_t x = pixel - y * width_;
    int32_t e = root_;
    while (e >= 0) {
      const Node& n = nodes_[static_cast<size_t>(e)];
      e = n.next[(n.along_y ? y : x) >= n.cut ? 1 : 0];
    }
    return static_cast<size_t>(~e);
  }

 private:
  struct Node {
    uint32_t cut;     // next[0] holds coordinates < cut, next[1] the others
    bool along_y;     // the coordinate compared: y (kY cut) or x (kX cut)
    int32_t next[2];  // >= 0: a node; < 0: ~tile index
  };
  // The entry for PBT node `id`, in-order, so leaves get their tile indices.
  int32_t Flatten(const Pbt& pbt, int32_t id, const std::vector<Tile>& tiles, int32_t& leaves) {
    const PbtNode& node = pbt.Node(id);
    if (node.IsLeaf()) {
      const size_t i = static_cast<size_t>(leaves);
      const Tile& t = node.tile;
      if (i >= tiles.size() || tiles[i].x0 != t.x0 || tiles[i].y0 != t.y0 || tiles[i].x1 != t.x1 ||
          tiles[i].y1 != t.y1) {
        throw Error(fmt::format("PBT lookup: leaf {} is not the frame's tile {}", id, i));
      }
      return ~leaves++;
    }
    const size_t slot = nodes_.size();
    const Tile& first = pbt.Node(node.child[0]).tile;
    const bool along_y = node.axis == PbtAxis::kY;
    nodes_.push_back(Node{static_cast<uint32_t>(along_y ? first.y1 : first.x1), along_y, {0, 0}});
    const int32_t a = Flatten(pbt, node.child[0], tiles, leaves);
    const int32_t b = Flatten(pbt, node.child[1], tiles, leaves);
    nodes_[slot].next[0] = a;
    nodes_[slot].next[1] = b;
    return static_cast<int32_t>(slot);
  }

  std::vector<Node> nodes_;
  int32_t root_ = -1;
  uint32_t width_ = 1;
};

// PBT's cost-map record of a host backend with render threads (tiles, lock, lfree, local): one
// BlockWork per thread, which only that thread's engine charges (RayEngine::SetBlockWork), and
// one per-pixel primary hit distance array all of them share (one writer per pixel: each
// primary ray is traced once, by one thread, and all pixels are rewritten every frame); after
// the closing barrier the threads' records are summed into the plan's TilePlanMeasure. Integer
// sums: the same record whichever thread traced what. Sized in the first frame of a layout and
// cleared after: no allocation in the steady state.
class CostMapRecord {
 public:
  // Application thread, threads parked, before each frame: a record when `plan` (nullptr: no
  // plan this frame) uses the cost map (TilePlan::uses_cost_map), in its layout, for `threads`
  // render threads; then Sink(w) is thread w's sink, nullptr without a record.
  void Load(const TilePlan* plan, size_t threads) {
    measure_ = TilePlanMeasure{};
    on_ = plan != nullptr && plan->uses_cost_map();
    if (!on_) return;
    const int width = plan->width(), height = plan->height();
    const int block = plan->options().cost_block;
    if (!sum_.Matches(width, height, block)) sum_.Resize(width, height, block);
    const size_t pixels = static_cast<size_t>(width) * static_cast<size_t>(height);
    if (pixel_depth_.size() != pixels) pixel_depth_.resize(pixels);
    if (threads_.size() != threads) threads_.resize(threads);
    for (BlockWork& b : threads_) {
      if (!b.Matches(width, height, block)) {
        b.Resize(width, height, block);
      } else {
        b.Clear();
      }
      b.pixel_depth = pixel_depth_.data();
    }
  }
  BlockWork* Sink(size_t thread) { return on_ ? &threads_[thread] : nullptr; }
  // After the closing barrier: the threads' block work summed, the hit distances and ctx's
  // cameras, for TilePlan::End (empty without a record). Kept for measure() until the next
  // Load.
  const TilePlanMeasure& Finish(const FrameContext& ctx) {
    if (!on_) return measure_;
    sum_.Clear();
    for (const BlockWork& b : threads_) sum_.Add(b);
    measure_.blocks = &sum_;
    measure_.pixel_depth = pixel_depth_;
    measure_.camera = &ctx.camera;
    measure_.next_camera = ctx.has_next_camera ? &ctx.next_camera : nullptr;
    return measure_;
  }
  const TilePlanMeasure& measure() const { return measure_; }

 private:
  bool on_ = false;
  std::vector<BlockWork> threads_;  // per render thread
  BlockWork sum_;
  std::vector<float> pixel_depth_;
  TilePlanMeasure measure_;
};

template <class Q>
class QueueImpl final : public HostRenderer::Impl {
  static constexpr bool kShared = Q::kKind != QueueKind::kLocal;
  static constexpr bool kTimed = Q::stats_type::kEnabled;

 public:
  explicit QueueImpl(const BackendOptions& options)
      : Impl(options), queue_(MakeQueue(options.threads)) {
    for (int w = 0; w < options.threads; ++w) {
      workers_.push_back(std::make_unique<Worker>());
      // Plain framebuffer adds (Load): LOCAL, because nobody else pushes into a thread's queue,
      // so a tile's rays (and its pixels' adds) stay on the thread that took the tile; LOCK and
      // LFREE until a thread pushes or pops a task (Share). From then on it sums its
      // contributions per pixel and adds them a table at a time under pixel_lock_ (Work
      // flushes the rest).
      workers_.back()->engine.SetCombinePixels(kShared ? &pixel_lock_ : nullptr);
    }
    feeds_ = std::make_unique<Feed[]>(static_cast<size_t>(options.threads));
    loop_ = std::make_unique<FrameLoop>(options.threads, [this](int w) { Work(w); });
  }

  ~QueueImpl() override {
    loop_.reset();  // END: stop the threads before the queue and the workers go away
  }

  const Pbt* pbt() const override { return plan_ ? plan_->pbt() : nullptr; }
  TilePlanMeasure cost_map_measure() const override { return record_.measure(); }

  void Begin(const std::vector<Tile>* tiles) override {
    frame_ = nullptr;
    if (options_.pbt_tiles_per_worker > 0) {
      if (tiles != nullptr) {
        throw Error(fmt::format("{} backend: explicit tiles cannot be combined with PBT tiling",
                                BackendName(options_.kind)));
      }
      const int width = ctx_.options.width;
      const int height = ctx_.options.height;
      if (!plan_ || plan_->width() != width || plan_->height() != height) {
        plan_.reset();
        plan_ = std::make_unique<TilePlan>(width, height, PlanOptions());
      }
      frame_ = &plan_->Begin();  // published to the threads by the opening barrier
    }
    try {
      Load(tiles);
    } catch (...) {
      if (frame_ != nullptr) plan_->Cancel();
      frame_ = nullptr;
      throw;
    }
    loop_->Release();  // listing 3 line 7
  }

  void End() override {
    std::exception_ptr error;
    try {
      loop_->Wait();  // listing 3 line 9
    } catch (...) {
      error = std::current_exception();
    }
    const int n = options_.threads;
    stats_.threads.assign(static_cast<size_t>(n), ThreadStats{});
    FrameStats total;
    uint64_t primary = 0;
    for (int w = 0; w < n; ++w) {
      const Worker& me = *workers_[static_cast<size_t>(w)];
      ThreadStats& t = stats_.threads[static_cast<size_t>(w)];
      t.work = me.stats;
      t.busy_seconds = loop_->times()[static_cast<size_t>(w)].busy_seconds;
      t.idle_seconds = loop_->times()[static_cast<size_t>(w)].idle_seconds;
      t.cpu_seconds = loop_->times()[static_cast<size_t>(w)].cpu_seconds;
      t.empty_polls = me.empty_polls;
      t.table_adds = me.engine.table_adds();
      t.tiles = me.tiles;
      t.steals = me.steals;
      if constexpr (kTimed) {
        t.queue_seconds = queue_.stats().Seconds(w);
        t.queue_ops = queue_.stats().Ops(w);
      }
      total.Merge(me.stats);
      primary += me.primary;
    }
    stats_.app_queue_seconds = 0;
    stats_.primary_tasks = primary;
    stats_.total = total;
    if (error) {
      if (frame_ != nullptr) plan_->Cancel();  // the same tiles and lists again next frame
      frame_ = nullptr;
      Drain();
      std::rethrow_exception(error);
    }
    if (frame_ != nullptr) FinishPlan();
  }

 private:
  struct alignas(kQueueFalseSharing) Worker {
    RayEngine engine;
    RayStream shadow_in;   // the popped shadow tasks, as one stream (two or more of them)
    RayStream rays_in;     // the popped other tasks, the same
    RayStream shadow_out;  // their secondary rays by class, before cutting: shadow rays
    RayStream bounce_out;  // (grouped by light) and the others
    std::vector<RayStream*> popped;
    std::vector<RayStream*> children;
    // Batches of >= 64 rays (Private()): the rays this thread traces itself, never cut into
    // tasks. `cur` is traced a batch slice at a time; what its slices and popped tasks spawn
    // is appended to `next`; when cur is done the two swap. Beyond kPrivateSlices slices per
    // class (or all of next, when a thread is hungry) next's tail is cut into tasks for the
    // queue.
    struct Generation {
      RayStream shadow;
      RayStream rays;
      size_t shadow_pos = 0;  // cur: the rays before these are traced
      size_t rays_pos = 0;
      size_t Left() const { return shadow.size() - shadow_pos + rays.size() - rays_pos; }
      void Clear() {
        shadow.Clear();
        rays.Clear();
        shadow_pos = rays_pos = 0;
      }
    };
    Generation cur;
    Generation next;
    bool holding = false;  // private rays are counted in outstanding_ as one task
    // Shared queues: no task pushed or popped yet this frame, so no other thread adds to the
    // pixels this one adds to (Share)
    bool exclusive = false;
    void DropPrivate() {  // an abandoned frame's
      cur.Clear();
      next.Clear();
      holding = false;
    }
    FrameStats stats;
    uint64_t empty_polls = 0;
    uint64_t primary = 0;
    // PBT.
    uint64_t tiles = 0;               // tiles this thread took (from a list or the counter)
    uint64_t steals = 0;              // of those, from another thread's list
    size_t own = 0;                   // the own list it takes from next (w, w + threads, ...)
    bool no_tiles = false;            // every list (or the counter) found empty: final
    std::vector<uint64_t> tile_rays;  // per tile: rays of it this thread traced
  };

  // PBT: the tile a thread took, handed out in chunks of primaries {tile + 1, next primary}
  // (0: none). The owner installs a tile only when its slot is exhausted; shared queues let any
  // thread take a chunk by CAS (relaxed: it only arbitrates primary ranges; the tiles were
  // published by the opening barrier). Positions only grow within a tile and each tile is
  // installed once, so a CAS on a stale word fails (no ABA).
  struct alignas(kQueueFalseSharing) Feed {
    std::atomic<uint64_t> word{0};
  };
  struct Chunk {
    size_t tile;
    size_t first;
    size_t count;
  };

  // Tasks one TryPopMany asks for (LFREE takes up to its kMaxPopChain with one Head CAS).
  static constexpr size_t kPopChunk = 64;

  static Q MakeQueue(int n) {
    if constexpr (Q::kKind == QueueKind::kLockFree) {
      // Node caches as large as they go: a thread's frees then feed its own pushes (its
      // batches pop about as many tasks as they push), not the shared free list.
      return Q(n, /*reserve_nodes=*/4096, /*node_cache=*/Q::kMaxNodeCache);
    } else {
      return Q(n);
    }
  }

  size_t TaskSize() const { return static_cast<size_t>(ctx_.options.task_size); }
  size_t BatchTasks() const {
    return std::max<size_t>(
        1, (static_cast<size_t>(ctx_.options.batch) + TaskSize() - 1) / TaskSize());
  }
  // Shadow tasks a thread gathers into one Occlude call (whole tasks, within the engine's
  // scratch), at least a batch's.
  size_t ShadowBatchTasks() const {
    const size_t rays = EngineShadowBatch(ctx_.options, ctx_.scene->lights.size());
    return std::max(BatchTasks(), rays / TaskSize());
  }

  // Threads trace their own rays privately when a batch slice of them keeps the arrays aligned
  // (slices start at multiples of 64 rays).
  bool Private() const { return ctx_.options.batch >= 64; }
  size_t SliceRays() const { return static_cast<size_t>(ctx_.options.batch) / 64 * 64; }
  size_t ShadowSliceRays() const {
    return std::max<size_t>(64, ShadowBatchTasks() * TaskSize() / 64 * 64);
  }
  // Rays of each class a thread keeps in `next` beyond what one batch spawns.
  static constexpr size_t kPrivateSlices = 4;

  int PbtWorkers() const { return rs::PbtWorkers(options_); }
  TilePlanOptions PlanOptions() const { return TilePlanOptionsFor(options_); }

  // The frame's tiles, arenas and per-thread state (application thread, threads parked).
  void Load(const std::vector<Tile>* tiles) {
    if constexpr (kTimed) queue_.stats().Reset();
    abort_.store(false, std::memory_order_relaxed);
    for (size_t w = 0; w < workers_.size(); ++w) {
      Worker& me = *workers_[w];
      me.stats = FrameStats();
      me.empty_polls = 0;
      me.primary = 0;
      me.tiles = 0;
      me.steals = 0;
      me.own = w;
      me.no_tiles = false;
      me.engine.Reserve(ctx_);
      me.engine.DiscardContributions();  // an abandoned frame's, if any
      me.exclusive = kShared;
      me.engine.ResetTableAdds();
      me.engine.SetSharedPixels(false);  // until Share
    }
    // PBT's cost map: each thread's engine charges its rays to its own record (the pixels'
    // global indices; each primary traced once, by whoever popped it).
    record_.Load(frame_ != nullptr ? plan_.get() : nullptr, workers_.size());
    for (size_t w = 0; w < workers_.size(); ++w) workers_[w]->engine.SetBlockWork(record_.Sink(w));
    size_t tile_pixels = 0;
    if (frame_ != nullptr) {
      tiles_.assign(frame_->tiles.begin(), frame_->tiles.end());
    } else if (tiles == nullptr) {
      const int t = ctx_.options.tile_size;
      ImageTiles(ctx_.options.width, ctx_.options.height, t, t, tiles_);
    } else {
      tiles_.assign(tiles->begin(), tiles->end());
    }
    for (const Tile& t : tiles_) tile_pixels = std::max(tile_pixels, t.NumPixels());
    if (frame_ != nullptr) {
      // PBT tiles are fed in chunks of about a tile_size^2 tile (whole tasks), so the rays in
      // flight stay those of the default tiling, however large the PBT's tiles are.
      const size_t ts = TaskSize();
      const size_t t = static_cast<size_t>(ctx_.options.tile_size);
      const size_t chunk_bound = std::max<size_t>(1, (t * t + ts - 1) / ts) * ts;
      chunk_ = std::min(chunk_bound, std::max<size_t>(tile_pixels, 1));
      // The arena is sized for the bound, not this frame's tiling: a later frame whose largest
      // tile grows finds its streams already there (no allocation once the first frame ran).
      tile_pixels = chunk_bound;
      LoadPbt();
    }
    const size_t lights = ctx_.scene->lights.size();
    const size_t cap = QueueRayCap(ctx_.options, lights, tile_pixels, options_.threads);
    cap_ = static_cast<int64_t>(cap);
    // Streams for the tasks the cap allows (partial tasks: two per batch and thread on top),
    // allocated in the first frame only.
    const size_t ts = TaskSize();
    const size_t tasks = cap / ts + static_cast<size_t>(options_.threads) * (2 * BatchTasks() + 8);
    // A thread's own list keeps two batches' worth of popped tasks.
    arena_.Reserve(options_.threads, tasks, 2 * (BatchTasks() + ShadowBatchTasks()), ts);
    queue_.Reserve(tasks);
    // A batch of popped tasks and everything Shade can spawn from it (one per light, two
    // bounces), so the threads' streams never grow in the steady state.
    const size_t batch_rays = BatchTasks() * TaskSize() + kStreamPad;
    for (auto& w : workers_) {
      w->shadow_in.Reserve(ShadowBatchTasks() * TaskSize() + kStreamPad);
      w->rays_in.Reserve(batch_rays);
      w->shadow_out.Reserve(batch_rays * std::max<size_t>(lights, 1) + kStreamPad);
      w->bounce_out.Reserve(2 * batch_rays + kStreamPad);
      w->popped.reserve(BatchTasks() + ShadowBatchTasks());

      const size_t out = w->shadow_out.capacity() + w->bounce_out.capacity();
      w->children.reserve(std::max(tile_pixels, out) / TaskSize() + 2);
      if (Private()) {
        const size_t shadow = kPrivateSlices * ShadowSliceRays() + w->shadow_out.capacity();
        const size_t rays =
            kPrivateSlices * SliceRays() + w->bounce_out.capacity() + tile_pixels;
        for (auto* g : {&w->cur, &w->next}) {
          g->Clear();
          g->shadow.Reserve(shadow);
          g->rays.Reserve(rays);
        }
      }
      w->holding = false;
    }
    // Published to the threads by the opening barrier (Release), hence relaxed.
    next_tile_.store(0, std::memory_order_relaxed);
    in_flight_.store(0, std::memory_order_relaxed);
    hungry_.store(false, std::memory_order_relaxed);
    outstanding_.Reset(0);
  }

  // PBT: lists, feed slots, records, per-thread tile counters and the pixel -> tile lookup.
  void LoadPbt() {
    const size_t m = tiles_.size();
    lists_ = options_.assign != PbtAssign::kCounter;
    if (lists_) ranges_.Load(frame_->assignment);
    for (size_t w = 0; w < workers_.size(); ++w) {
      feeds_[w].word.store(0, std::memory_order_relaxed);
      workers_[w]->tile_rays.assign(m, 0);
    }
    records_.assign(m, TileRecord{});
    lookup_.Build(*plan_->pbt(), tiles_, ctx_.options.width);
  }

  // Cuts `rays` (one class) into tasks of task_size rays (the last one shorter), copied array
  // by array, into me.children.
  void Cut(Worker& me, int w, const RayStreamView& rays) {
    if (rays.size == 0) return;
    const size_t ts = TaskSize();
    size_t c = me.children.size();
    arena_.Get(w, (rays.size + ts - 1) / ts, ts, me.children);
    for (size_t f = 0; f < rays.size; f += ts) {
      RayStream& task = *me.children[c++];
      task.Append(rays, f, std::min(ts, rays.size - f));
      task.SealTail();
    }
  }

  static bool IsShadowTask(RayStream& task) {
    return task.view().kind[0] == static_cast<int32_t>(RayKind::kShadow);
  }

  // The popped tasks of one class as one stream: a lone task is traced in place (tasks are
  // sealed), two or more are copied into `into` array by array. Empty if the class has none.
  RayStreamView Gather(Worker& me, bool shadow, RayStream& into) {
    RayStream* only = nullptr;
    size_t count = 0;
    for (RayStream* task : me.popped) {
      if (IsShadowTask(*task) != shadow) continue;
      only = task;
      ++count;
    }
    if (count == 0) return RayStreamView{};
    if (count == 1) return only->view();
    into.Clear();
    for (RayStream* task : me.popped) {
      if (IsShadowTask(*task) == shadow) into.Append(task->view(), 0, task->size());
    }
    into.SealTail();
    return into.view();
  }

  // Pushes the children of one batch (counted first for termination) or of a tile.
  void PushChildren(Worker& me, int w, int64_t retired) {
    if constexpr (kShared) {
      outstanding_.Retire(static_cast<int64_t>(me.children.size()) - retired + 1);
    }
    // One add for all of them, before any is pushed: the count never falls below the rays in
    // queued tasks (a popper subtracts what it took), and the threads share one cache line
    // per batch instead of per task.
    int64_t rays = 0;
    for (const RayStream* child : me.children) rays += static_cast<int64_t>(child->size());
    in_flight_.fetch_add(rays, std::memory_order_relaxed);
    PushOut(me, w);
  }

  // me.children into the queue, one operation for the lot (Share first: once they are
  // visible, other threads may add to their pixels).
  void PushOut(Worker& me, int w) {
    if (!me.children.empty()) Share(me);
    queue_.PushMany(w, std::span<RayStream*>(me.children));
    me.children.clear();
  }

  // Primary rays [first, first + count) of tile i as tasks into the queue (LOCAL: this
  // thread's own), or (Private()) into the thread's private rays. Tasks start at multiples of
  // task_size within the tile.
  void PushPrimaries(Worker& me, int w, size_t i, size_t first, size_t count) {
    const auto t0 = Clock::now();
    const Tile& tile = tiles_[i];
    if (Private()) {
      // Into the thread's next private generation (KeepChildren shares what exceeds it).
      RayStream& g = me.next.rays;
      const size_t at = g.size();
      g.Resize(at + count);
      GeneratePrimaryRays(ctx_.camera, tile, ctx_.options.order, first, count, g.view(), at);
      me.primary += (count + TaskSize() - 1) / TaskSize();
      me.stats.generate_seconds += Seconds(t0, Clock::now());
      in_flight_.fetch_add(static_cast<int64_t>(count), std::memory_order_relaxed);
      KeepChildren(me, w);
      return;
    }
    const size_t end = first + count;
    size_t c = me.children.size();
    const size_t tasks = (count + TaskSize() - 1) / TaskSize();
    arena_.Get(w, tasks, TaskSize(), me.children);
    for (size_t f = first; f < end; f += TaskSize()) {
      const size_t n = std::min(TaskSize(), end - f);
      RayStream* task = me.children[c++];
      task->Resize(n);
      GeneratePrimaryRays(ctx_.camera, tile, ctx_.options.order, f, n, task->view(), 0);
      task->SealTail();
    }
    me.primary += tasks;
    me.stats.generate_seconds += Seconds(t0, Clock::now());
    PushChildren(me, w, /*retired=*/0);
  }

  // The next tile's primary tasks into the queue (LOCAL: this thread's own). False: none left.
  bool FeedTile(Worker& me, int w) {
    const size_t i = next_tile_.fetch_add(1, std::memory_order_relaxed);
    if (i >= tiles_.size()) return false;
    PushPrimaries(me, w, i, 0, tiles_[i].NumPixels());
    return true;
  }

  // PBT: a chunk of this thread's tile, else its next tile (own lists in order; then, shared
  // queues or pbt_steal, the back of the list with most predicted work waiting; counter: the
  // shared counter over the plan's order), else (shared queues) a chunk of another thread's
  // tile. False: nothing left to feed.
  bool FeedPbt(Worker& me, int w) {
    Chunk c;
    for (;;) {
      if (TakeChunk(static_cast<size_t>(w), &c)) break;
      size_t tile = 0;
      int32_t worker = -1;
      if (!NextTile(me, w, &tile, &worker)) {
        if constexpr (kShared) {
          const size_t n = workers_.size();
          for (size_t s = 1; s < n; ++s) {
            if (TakeChunk((static_cast<size_t>(w) + s) % n, &c)) {
              PushPrimaries(me, w, c.tile, c.first, c.count);
              return true;
            }
          }
        }
        return false;
      }
      TileRecord& r = records_[tile];  // this tile is ours alone (list CAS or counter RMW)
      r.tile = tiles_[tile];
      r.thread = w;
      r.worker = worker;
      r.predicted = frame_->predicted[tile];
      ++me.tiles;
      feeds_[static_cast<size_t>(w)].word.store(static_cast<uint64_t>(tile + 1) << 32,
                                                std::memory_order_relaxed);
    }
    PushPrimaries(me, w, c.tile, c.first, c.count);
    return true;
  }

  bool TakeChunk(size_t slot, Chunk* c) {
    std::atomic<uint64_t>& word = feeds_[slot].word;
    uint64_t f = word.load(std::memory_order_relaxed);
    for (;;) {
      const uint64_t tile1 = f >> 32;
      if (tile1 == 0) return false;
      const size_t pos = static_cast<uint32_t>(f);
      const size_t n = tiles_[tile1 - 1].NumPixels();
      if (pos >= n) return false;
      const size_t count = std::min(chunk_, n - pos);
      if (word.compare_exchange_weak(f, f + count, std::memory_order_relaxed,
                                     std::memory_order_relaxed)) {
        *c = Chunk{tile1 - 1, pos, count};
        return true;
      }
    }
  }

  bool NextTile(Worker& me, int w, size_t* tile, int32_t* worker) {
    if (me.no_tiles) return false;
    if (!lists_) {
      const std::vector<int32_t>& order = frame_->order;
      const size_t i = next_tile_.fetch_add(1, std::memory_order_relaxed);
      if (i >= order.size()) {
        me.no_tiles = true;
        return false;
      }
      *tile = static_cast<size_t>(order[i]);
      *worker = w;
      return true;
    }
    const Assignment& a = frame_->assignment;
    uint32_t pos = 0;
    for (; me.own < a.tiles.size(); me.own += workers_.size()) {
      if (ranges_.Take(me.own, /*front=*/true, &pos)) {
        *tile = static_cast<size_t>(a.tiles[me.own][pos]);
        *worker = static_cast<int32_t>(me.own);
        return true;
      }
    }
    if (!kShared && !options_.pbt_steal) {
      me.no_tiles = true;
      return false;
    }
    for (;;) {
      const size_t victim = ranges_.Richest(a, frame_->weight);
      if (victim == a.tiles.size()) {
        me.no_tiles = true;
        return false;
      }
      if (!ranges_.Take(victim, /*front=*/false, &pos)) continue;  // raced; look again
      ++me.steals;
      *tile = static_cast<size_t>(a.tiles[victim][pos]);
      *worker = static_cast<int32_t>(victim);
      return true;
    }
  }

  // Up to ceil(batch / task_size) popped tasks, or (me.popped empty) the next slice of the
  // thread's private generation, through the engine, one stream per class; children pushed
  // (Private(): appended to the next private generation, its surplus cut into tasks and
  // pushed). Everything but the engine's call is scheduling (FrameStats::schedule_seconds).
  void ProcessBatch(Worker& me, int w) {
    const auto t0 = Clock::now();
    const bool own = me.popped.empty();  // a private slice
    RayStreamView shadow;
    RayStreamView others;
    if (own) {
      auto& g = me.cur;
      const size_t ns = std::min(ShadowSliceRays(), g.shadow.size() - g.shadow_pos);
      const size_t nr = std::min(SliceRays(), g.rays.size() - g.rays_pos);
      shadow = SubView(g.shadow.view(), g.shadow_pos, ns);
      others = SubView(g.rays.view(), g.rays_pos, nr);
      g.shadow_pos += ns;
      g.rays_pos += nr;
    } else {
      shadow = Gather(me, /*shadow=*/true, me.shadow_in);
      others = Gather(me, /*shadow=*/false, me.rays_in);
    }
    const int64_t rays = static_cast<int64_t>(shadow.size + others.size);
    if (frame_ != nullptr) {
      // PBT's work cost: every ray traced is charged to the tile of its pixel.
      for (size_t i = 0; i < shadow.size; ++i) ++me.tile_rays[lookup_.TileOf(shadow.pixel[i])];
      for (size_t i = 0; i < others.size; ++i) ++me.tile_rays[lookup_.TileOf(others.pixel[i])];
    }
    const bool keep = Private();
    RayStream& shadow_out = keep ? me.next.shadow : me.shadow_out;
    RayStream& bounce_out = keep ? me.next.rays : me.bounce_out;
    if (!keep) {
      shadow_out.Clear();
      bounce_out.Clear();
    }
    const size_t shadow0 = shadow_out.size();
    const size_t bounce0 = bounce_out.size();
    const auto t1 = Clock::now();
    const uint64_t tasks0 = me.stats.tasks;
    me.engine.TraceGeneration(ctx_, shadow, others, *fb_, shadow_out, bounce_out, me.stats);
    const size_t ts = TaskSize();
    me.stats.tasks = tasks0 + (own ? (shadow.size + ts - 1) / ts + (others.size + ts - 1) / ts
                                   : me.popped.size());
    const auto t2 = Clock::now();
    const int64_t now = in_flight_.fetch_sub(rays, std::memory_order_relaxed) - rays;
    size_t spawned = shadow_out.size() - shadow0 + bounce_out.size() - bounce0;
    if (now + static_cast<int64_t>(spawned) > cap_) {  // the cap: only exponential trees
      me.stats.budget_dropped += bounce_out.size() - bounce0;
      spawned -= bounce_out.size() - bounce0;
      bounce_out.Resize(bounce0);
    }
    if (keep) {
      in_flight_.fetch_add(static_cast<int64_t>(spawned), std::memory_order_relaxed);
      KeepChildren(me, w);
    } else {
      Cut(me, w, shadow_out.view());
      Cut(me, w, bounce_out.view());
      PushChildren(me, w, static_cast<int64_t>(me.popped.size()));
    }
    arena_.Put(w, me.popped.data(), me.popped.size());
    me.popped.clear();
    me.stats.schedule_seconds += Seconds(t0, t1) + Seconds(t2, Clock::now());
  }

  // Private(), after a batch: cuts next's tail beyond kPrivateSlices slices per class (all
  // of it when another thread is hungry) into tasks and pushes them, with the termination
  // count adjusted for them, for the retired popped tasks and for the hold on private rays.
  void KeepChildren(Worker& me, int w) {
    const bool share = kShared && hungry_.load(std::memory_order_relaxed);
    if (share) hungry_.store(false, std::memory_order_relaxed);
    auto& g = me.next;
    const size_t keep_shadow = share ? 0 : kPrivateSlices * ShadowSliceRays();
    const size_t keep_rays = share ? 0 : kPrivateSlices * SliceRays();
    if (g.shadow.size() > keep_shadow) {
      Cut(me, w, SubView(g.shadow.view(), keep_shadow, g.shadow.size() - keep_shadow));
      g.shadow.Resize(keep_shadow);
    }
    if (g.rays.size() > keep_rays) {
      Cut(me, w, SubView(g.rays.view(), keep_rays, g.rays.size() - keep_rays));
      g.rays.Resize(keep_rays);
    }
    g.shadow.SealTail();
    g.rays.SealTail();
    const bool holding = me.cur.Left() + me.next.Left() > 0;
    const int64_t net = static_cast<int64_t>(me.children.size()) + (holding ? 1 : 0) -
                        (me.holding ? 1 : 0) - static_cast<int64_t>(me.popped.size());
    me.holding = holding;
    if constexpr (kShared) outstanding_.Retire(net + 1);  // before the children are visible
    PushOut(me, w);
  }

  // Shared queues: a thread adds its contributions to the framebuffer directly (plain adds, as
  // LOCAL) while no other thread can add to the same pixels: its tiles and PBT chunks are its
  // own, and their rays reach another thread only through the queue. From its first push or
  // pop of the frame on, its adds go through its PixelSumTable. Its earlier plain adds
  // happen before the push (release) and hence before any popper's flush (acquire, then
  // pixel_lock_); after it, every add to a pixel another thread may reach is under the lock.
  void Share(Worker& me) {
    if (!me.exclusive) return;
    me.exclusive = false;
    me.engine.SetSharedPixels(true);
  }

  // Listing 2 on thread w (Poll), then the thread's combined contributions into the image.
  void Work(int w) {
    Worker& me = *workers_[static_cast<size_t>(w)];
    Poll(me, w);
    if constexpr (kShared) me.engine.FlushContributions(*fb_);
  }

  // ProcessBatch; an exception abandons the frame: other threads stop polling, End drains the
  // queues, this thread's tasks go back to the arena and its private rays are dropped.
  void RunBatch(Worker& me, int w) {
    try {
      ProcessBatch(me, w);
    } catch (...) {
      abort_.store(true, std::memory_order_relaxed);
      arena_.Put(w, me.children.data(), me.children.size());
      me.children.clear();
      arena_.Put(w, me.popped.data(), me.popped.size());
      me.popped.clear();
      me.DropPrivate();
      throw;
    }
  }

  // Listing 2, lines 4-10, on thread w, with batches and tiles feeding the queue.
  void Poll(Worker& me, int w) {
    const size_t batch_tasks = BatchTasks();
    const size_t shadow_tasks = ShadowBatchTasks();
    const bool pbt = frame_ != nullptr;
    int spins = 0;
    RayStream* got[kPopChunk];
    for (;;) {
      if (me.holding) {
        // The thread's own rays first: the next slice of the current generation, or the
        // next generation once the current one is traced.
        if (abort_.load(std::memory_order_relaxed)) {
          me.DropPrivate();  // the frame is abandoned
          return;
        }
        if (me.cur.Left() == 0) {
          std::swap(me.cur, me.next);
          me.next.Clear();
        }
        if (me.cur.Left() > 0) {
          spins = 0;
          RunBatch(me, w);
          continue;
        }
      }
      // Tasks until a batch of one class is full or the queue is empty, popped several at a
      // time (TryPopMany: one CAS or one lock for each chunk), never more than either class
      // could still take, so the batch is what one-by-one pops would have made it.
      size_t shadow = 0;  // of the popped tasks
      for (;;) {
        const size_t others = me.popped.size() - shadow;
        if (others >= batch_tasks || shadow >= shadow_tasks) break;
        const size_t want =
            std::min({batch_tasks - others, shadow_tasks - shadow, size_t{kPopChunk}});
        const size_t n = queue_.TryPopMany(w, std::span<RayStream*>(got, want));
        if (n > 0) Share(me);
        for (size_t i = 0; i < n; ++i) {
          me.popped.push_back(got[i]);
          shadow += IsShadowTask(*got[i]) ? 1 : 0;
        }
        if (n < want) break;
      }
      if (!me.popped.empty()) {
        spins = 0;
        RunBatch(me, w);
        continue;
      }
      ++me.empty_polls;
      if (abort_.load(std::memory_order_relaxed)) return;
      if (pbt ? FeedPbt(me, w) : FeedTile(me, w)) continue;
      if constexpr (!kShared) return;  // LOCAL: nobody else feeds this queue
      if (outstanding_.Done()) return;
      // Ask the threads with private rays to share them (at their next batch's end).
      if (!hungry_.load(std::memory_order_relaxed)) hungry_.store(true, std::memory_order_relaxed);
      // Others are still processing tasks that may spawn children. Pause, and give the core
      // away now and then: with more threads than cores the producer may be descheduled.
      if (++spins < 64) {
        queue_detail::CpuRelax();
      } else {
        spins = 0;
        std::this_thread::yield();
      }
    }
  }

  // After the closing barrier: each tile's rays summed over the threads, its work cost to the
  // plan (PBT-Update, next assignment) and the records.
  void FinishPlan() {
    const size_t m = records_.size();
    costs_.resize(m);
    ran_by_.resize(m);
    for (size_t i = 0; i < m; ++i) {
      uint64_t rays = 0;
      for (const auto& w : workers_) rays += w->tile_rays[i];
      TileRecord& r = records_[i];
      r.rays = rays;
      r.counts = TileWork{};
      r.counts.rays = rays;
      r.work = TileWorkCost(r.counts);
      costs_[i] = r.work;
      ran_by_[i] = r.thread;
    }
    stats_.tiles = records_;
    // Counter: the thread that took a tile traced all of it only on LOCAL (its own queue) and
    // only if the threads are the plan's workers; otherwise the plan models the workers.
    const bool exact = !kShared && PbtWorkers() == options_.threads;
    const TilePlanReport report =
        plan_->End(costs_, exact ? std::span<const int32_t>(ran_by_) : std::span<const int32_t>(),
                   record_.Finish(ctx_));
    frame_ = nullptr;
    if (!report.pbt) return;
    ApplyPlanReport(report, stats_);
  }

  // Application thread, threads parked: empties the queues after an aborted frame.
  void Drain() {
    const int n = options_.threads;
    RayStream* task = nullptr;
    for (int w = 0; w < n; ++w) {
      while (queue_.TryPop(w, task)) arena_.Put(w, &task, 1);
    }
    outstanding_.Reset(0);
  }

  std::mutex pixel_lock_;  // LOCK, LFREE: the engines' framebuffer flushes (SetCombinePixels)
  Q queue_;
  TaskArena arena_;
  std::vector<std::unique_ptr<Worker>> workers_;
  std::vector<Tile> tiles_;
  int64_t cap_ = 0;
  // PBT (frame_ != nullptr): the plan, this frame's lists, feed slots, records and lookup.
  std::unique_ptr<TilePlan> plan_;
  const TilePlanFrame* frame_ = nullptr;
  bool lists_ = false;  // per-worker lists (not the counter)
  size_t chunk_ = 0;    // primaries per chunk
  PbtListRanges ranges_;
  std::unique_ptr<Feed[]> feeds_;  // per thread
  PbtTileLookup lookup_;
  std::vector<TileRecord> records_;
  std::vector<double> costs_;
  std::vector<int32_t> ran_by_;
  CostMapRecord record_;   // PBT's cost map: block work and hit distances
  TaskCount outstanding_;  // shared queues: tasks pushed and not yet processed
  alignas(kQueueFalseSharing) std::atomic<size_t> next_tile_{0};   // tiles_, or PBT's order
  alignas(kQueueFalseSharing) std::atomic<int64_t> in_flight_{0};  // rays in queued tasks
  alignas(kQueueFalseSharing) std::atomic<bool> abort_{false};
  alignas(kQueueFalseSharing) std::atomic<bool> hungry_{false};  // a thread found no work
  std::unique_ptr<FrameLoop> loop_;  // last: its threads use everything above
};

// ---------------------------------------------------------------------------------------------
// tiles: an atomic tile counter (Benthin et al. 3.9) or PBT tile lists (Cosenza et al.), run
// as static lists, with stealing, or through the demand-driven master.

class TilesImpl final : public HostRenderer::Impl {
 public:
  explicit TilesImpl(const BackendOptions& options) : Impl(options) {
    for (int w = 0; w < options.threads; ++w) workers_.push_back(std::make_unique<Worker>());
    loop_ = std::make_unique<FrameLoop>(options.threads, [this](int w) { Work(w); });
  }
  ~TilesImpl() override { loop_.reset(); }

  const Pbt* pbt() const override { return plan_ ? plan_->pbt() : nullptr; }
  TilePlanMeasure cost_map_measure() const override { return record_.measure(); }

  void Begin(const std::vector<Tile>* tiles) override {
    const bool use_pbt = options_.pbt_tiles_per_worker > 0;
    if (use_pbt && tiles != nullptr) {
      throw Error("tiles backend: explicit tiles cannot be combined with PBT tiling");
    }
    frame_ = nullptr;
    lists_ = false;
    if (tiles != nullptr) {
      tiles_ = *tiles;
      explicit_order_.resize(tiles_.size());
      for (size_t i = 0; i < tiles_.size(); ++i) explicit_order_[i] = static_cast<int32_t>(i);
      order_ = &explicit_order_;
    } else {
      const int width = ctx_.options.width;
      const int height = ctx_.options.height;
      if (!plan_ || plan_->width() != width || plan_->height() != height) {
        plan_.reset();
        plan_ = std::make_unique<TilePlan>(width, height, PlanOptions());
      }
      frame_ = &plan_->Begin();  // published to the threads by the opening barrier
      order_ = &frame_->order;
      lists_ = use_pbt && options_.assign != PbtAssign::kCounter;
    }
    try {
      Load();
    } catch (...) {
      if (frame_ != nullptr) plan_->Cancel();
      frame_ = nullptr;
      throw;
    }
    loop_->Release();
  }

  void End() override {
    std::exception_ptr error;
    try {
      loop_->Wait();
    } catch (...) {
      error = std::current_exception();
    }
    const int n = options_.threads;
    stats_.threads.assign(static_cast<size_t>(n), ThreadStats{});
    FrameStats total;
    const double tick = QueueClock::SecondsPerTick();
    for (int w = 0; w < n; ++w) {
      const Worker& me = *workers_[static_cast<size_t>(w)];
      ThreadStats& t = stats_.threads[static_cast<size_t>(w)];
      t.work = me.stats;
      t.busy_seconds = loop_->times()[static_cast<size_t>(w)].busy_seconds;
      t.idle_seconds = loop_->times()[static_cast<size_t>(w)].idle_seconds;
      t.cpu_seconds = loop_->times()[static_cast<size_t>(w)].cpu_seconds;
      t.queue_seconds = static_cast<double>(me.ticks) * tick;
      t.queue_ops = me.ops;
      t.tiles = me.tiles;
      t.steals = me.steals;
      total.Merge(me.stats);
    }
    stats_.total = total;
    stats_.tiles = records_;
    stats_.primary_tasks = 0;
    stats_.app_queue_seconds = 0;
    if (error) {
      if (frame_ != nullptr) plan_->Cancel();  // the same tiles and lists again next frame
      std::rethrow_exception(error);
    }
    if (frame_ != nullptr) FinishPlan();
  }

 private:
  struct alignas(kQueueFalseSharing) Worker {
    SerialRenderer fifo;
    FrameStats stats;
    uint64_t ticks = 0;  // QueueClock ticks inside the tile counter
    uint64_t ops = 0;
    uint64_t tiles = 0;
    uint64_t steals = 0;
  };

  // The frame's tiles, steal ranges, records and worker counters (application thread).
  void Load() {
    if (frame_ != nullptr) tiles_ = frame_->tiles;
    record_.Load(frame_ != nullptr ? plan_.get() : nullptr, workers_.size());
    for (size_t w = 0; w < workers_.size(); ++w) {
      workers_[w]->fifo.engine().SetBlockWork(record_.Sink(w));
    }
    if (lists_ && options_.pbt_steal) ranges_.Load(frame_->assignment);
    if (lists_ && options_.pbt_demand) master_.Load(frame_->owner, options_.threads);
    records_.assign(tiles_.size(), TileRecord{});
    for (auto& w : workers_) {
      // Arenas sized here, not in the thread's first tile: a thread that took no tile in frame
      // 0 (another took them all, e.g. stealing on a loaded machine) must not allocate later.
      w->fifo.engine().Reserve(ctx_);
      w->stats = FrameStats();
      w->ticks = 0;
      w->ops = 0;
      w->tiles = 0;
      w->steals = 0;
    }
    next_.store(0, std::memory_order_relaxed);  // published by the opening barrier
  }

  int PbtWorkers() const { return rs::PbtWorkers(options_); }
  TilePlanOptions PlanOptions() const { return TilePlanOptionsFor(options_); }

  void RenderTile(Worker& me, int thread, int worker, size_t i) {
    const Clock::time_point wall0 = Clock::now();
    const double cpu0 = ThreadCpuSeconds();
    const FrameStats before = me.stats;
    me.fifo.RenderTiles(ctx_, &tiles_[i], 1, *fb_, me.stats);
    TileRecord& r = records_[i];  // this tile is ours alone (counter RMW or assignment)
    r.tile = tiles_[i];
    r.thread = thread;
    r.worker = worker;
    r.cpu_seconds = ThreadCpuSeconds() - cpu0;
    r.seconds = Seconds(wall0, Clock::now());
    r.predicted = frame_ != nullptr ? frame_->predicted[i] : -1.0;
    r.counts = TileWorkDelta(me.stats, before);
    r.rays = r.counts.rays;
    r.work = TileWorkCost(r.counts);
    ++me.tiles;
  }

  void Work(int w) {
    Worker& me = *workers_[static_cast<size_t>(w)];
    if (lists_ && options_.pbt_demand) {
      // The demand-driven master: ask for a tile, render it, ask again (the lists only say
      // which tiles are w's). The lock is the master; the records are read after the barrier.
      for (;;) {
        const uint64_t t0 = options_.queue_stats ? QueueClock::Now() : 0;
        bool affine = false;
        int32_t i = -1;
        size_t handout = 0;
        {
          const std::lock_guard<std::mutex> lock(master_mutex_);
          handout = records_.size() - master_.Waiting();
          i = master_.Next(w, &affine);
        }
        if (options_.queue_stats) me.ticks += QueueClock::Now() - t0;
        ++me.ops;
        if (i < 0) return;
        if (!affine) ++me.steals;
        const size_t tile = static_cast<size_t>(i);
        RenderTile(me, w, frame_->owner[tile], tile);
        records_[tile].handout = static_cast<int64_t>(handout);
      }
    }
    if (lists_) {
      // Thread w runs the lists of (virtual) workers w, w + threads, ... in list order.
      const auto& lists = frame_->assignment.tiles;
      for (size_t v = static_cast<size_t>(w); v < lists.size(); v += workers_.size()) {
        const std::vector<int32_t>& list = lists[v];
        if (!options_.pbt_steal) {
          for (const int32_t i : list)
            RenderTile(me, w, static_cast<int>(v), static_cast<size_t>(i));
          continue;
        }
        uint32_t pos = 0;
        while (ranges_.Take(v, /*front=*/true, &pos)) {
          RenderTile(me, w, static_cast<int>(v), static_cast<size_t>(list[pos]));
        }
      }
      if (!options_.pbt_steal) return;
      // Demand-driven: steal from the list with the most predicted work still waiting.
      for (;;) {
        const size_t victim = ranges_.Richest(frame_->assignment, frame_->weight);
        if (victim == lists.size()) return;
        uint32_t pos = 0;
        if (!ranges_.Take(victim, /*front=*/false, &pos)) continue;  // raced with its owner
        ++me.steals;
        RenderTile(me, w, static_cast<int>(victim), static_cast<size_t>(lists[victim][pos]));
      }
    }
    // The tile counter over the plan's order (row-major, or decreasing prediction).
    const std::vector<int32_t>& order = *order_;
    const size_t count = order.size();
    for (;;) {
      // The counter only has to hand each index to one thread: relaxed RMW. The tile list was
      // published by the opening barrier, the records are read after the closing one.
      const uint64_t t0 = options_.queue_stats ? QueueClock::Now() : 0;
      const size_t i = next_.fetch_add(1, std::memory_order_relaxed);
      if (options_.queue_stats) me.ticks += QueueClock::Now() - t0;
      ++me.ops;
      if (i >= count) return;
      RenderTile(me, w, w, static_cast<size_t>(order[i]));
    }
  }

  // After the closing barrier: the measured costs to the plan (PBT-Update, next assignment).
  void FinishPlan() {
    std::vector<double>& costs = costs_;  // members: no allocation in the steady state
    std::vector<int32_t>& ran_by = ran_by_;
    costs.resize(records_.size());
    ran_by.resize(records_.size());
    for (size_t i = 0; i < records_.size(); ++i) {
      const TileRecord& r = records_[i];
      costs[i] = TileCost(r, options_.pbt_cost);
      ran_by[i] = r.thread;
    }
    // Counter: the threads are the workers only when there are as many (else a model of n).
    if (PbtWorkers() != options_.threads) ran_by.clear();
    const TilePlanReport report = plan_->End(costs, ran_by, record_.Finish(ctx_));
    frame_ = nullptr;
    if (!report.pbt) return;
    ApplyPlanReport(report, stats_);
  }

  std::vector<std::unique_ptr<Worker>> workers_;
  std::unique_ptr<TilePlan> plan_;
  const TilePlanFrame* frame_ = nullptr;  // the plan's frame (nullptr: explicit tiles)
  bool lists_ = false;                    // PBT per-worker lists (not the counter)
  std::vector<Tile> tiles_;
  const std::vector<int32_t>* order_ = nullptr;  // counter: tile indices in hand-out order
  std::vector<int32_t> explicit_order_;
  std::vector<TileRecord> records_;
  std::vector<double> costs_;     // FinishPlan's scratch
  std::vector<int32_t> ran_by_;
  CostMapRecord record_;  // PBT's cost map: block work and hit distances
  alignas(kQueueFalseSharing) std::atomic<size_t> next_{0};
  PbtListRanges ranges_;     // pbt_steal: per list {head, tail}
  std::mutex master_mutex_;  // pbt_demand: the render threads' requests, one at a time
  DemandMaster master_;
  std::unique_ptr<FrameLoop> loop_;  // last: its threads use everything above
};

template <template <class, class> class Queue>
std::unique_ptr<HostRenderer::Impl> MakeQueueImpl(const BackendOptions& o) {
  if (o.queue_stats) return std::make_unique<QueueImpl<Queue<RayStream*, QueueTimeStats>>>(o);
  return std::make_unique<QueueImpl<Queue<RayStream*, NoQueueStats>>>(o);
}

// Unconstrained two-parameter aliases, so the three queues fit one template template parameter.
template <class T, class S>
using LockQueueOf = LockQueue<T, S>;
template <class T, class S>
using LockFreeQueueOf = LockFreeQueue<T, S>;
template <class T, class S>
using LocalQueuesOf = LocalQueues<T, S>;

}  // namespace

// ---------------------------------------------------------------------------------------------
// HostRenderer.

HostRenderer::HostRenderer(const BackendOptions& options) {
  ValidateBackendOptions(options);
  switch (options.kind) {
    case BackendKind::kSerial:
      impl_ = std::make_unique<SerialImpl>(options);
      break;
    case BackendKind::kLock:
      impl_ = MakeQueueImpl<LockQueueOf>(options);
      break;
    case BackendKind::kLockFree:
      impl_ = MakeQueueImpl<LockFreeQueueOf>(options);
      break;
    case BackendKind::kLocal:
      impl_ = MakeQueueImpl<LocalQueuesOf>(options);
      break;
    case BackendKind::kTiles:
      impl_ = std::make_unique<TilesImpl>(options);
      break;
  }
}

HostRenderer::~HostRenderer() = default;

const BackendOptions& HostRenderer::options() const { return impl_->options_; }
bool HostRenderer::in_frame() const { return impl_->in_frame_; }
uint64_t HostRenderer::frames() const { return impl_->frames_; }
const Pbt* HostRenderer::pbt() const { return impl_->pbt(); }

TilePlanMeasure HostRenderer::cost_map_measure() const { return impl_->cost_map_measure(); }

namespace {

void CheckFrame(const FrameContext& ctx, const Framebuffer& fb, bool in_frame, BackendKind kind) {
  if (in_frame) throw Error("renderer: BeginFrame while a frame is running (call EndFrame)");
  if (fb.storage() == Framebuffer::Storage::kResolved && kind != BackendKind::kSerial &&
      kind != BackendKind::kTiles) {
    throw Error(fmt::format("renderer: the {} backend adds contributions from any thread to any "
                            "pixel: it needs a kFixed framebuffer",
                            BackendName(kind)));
  }
  if (ctx.scene == nullptr || ctx.accel == nullptr) {
    throw Error("renderer: frame context without scene or acceleration structure");
  }
  if (fb.width() != ctx.options.width || fb.height() != ctx.options.height) {
    throw Error(fmt::format("renderer: framebuffer {}x{} does not match the image {}x{}",
                            fb.width(), fb.height(), ctx.options.width, ctx.options.height));
  }
}

}  // namespace

void HostRenderer::BeginFrame(const FrameContext& ctx, Framebuffer& fb) {
  CheckFrame(ctx, fb, impl_->in_frame_, impl_->options_.kind);
  impl_->begin_ = Clock::now();
  impl_->ctx_ = ctx;
  impl_->fb_ = &fb;
  const double cpu0 = ThreadCpuSeconds();
  impl_->Begin(nullptr);
  impl_->app_cpu_ = ThreadCpuSeconds() - cpu0;
  impl_->in_frame_ = true;
}

void HostRenderer::BeginFrame(const FrameContext& ctx, Framebuffer& fb,
                              std::span<const Tile> tiles) {
  CheckFrame(ctx, fb, impl_->in_frame_, impl_->options_.kind);
  std::vector<Tile> list(tiles.begin(), tiles.end());
  for (size_t i = 0; i < list.size(); ++i) {
    const Tile& t = list[i];
    const bool empty = t.x1 <= t.x0 || t.y1 <= t.y0;
    if (!empty && (t.x0 < 0 || t.y0 < 0 || t.x1 > ctx.options.width || t.y1 > ctx.options.height)) {
      throw Error(fmt::format("renderer: tile {} [{}, {}) x [{}, {}) is outside the {}x{} image", i,
                              t.x0, t.x1, t.y0, t.y1, ctx.options.width, ctx.options.height));
    }
  }
  impl_->begin_ = Clock::now();
  impl_->ctx_ = ctx;
  impl_->fb_ = &fb;
  const double cpu0 = ThreadCpuSeconds();
  impl_->Begin(&list);
  impl_->app_cpu_ = ThreadCpuSeconds() - cpu0;
  impl_->in_frame_ = true;
}

const HostFrameStats& HostRenderer::EndFrame() {
  if (!impl_->in_frame_) throw Error("renderer: EndFrame without BeginFrame");
  impl_->in_frame_ = false;
  HostFrameStats& s = impl_->stats_;
  // Reset, keeping the vectors' capacity (no allocation in the steady state).
  std::vector<ThreadStats> threads = std::move(s.threads);
  std::vector<TileRecord> tiles = std::move(s.tiles);
  s = HostFrameStats{};
  s.threads = std::move(threads);
  s.threads.clear();
  s.tiles = std::move(tiles);
  s.tiles.clear();
  s.frame = impl_->frames_;
  s.backend = impl_->options_.kind;
  struct Count {  // frames_ advances even when End rethrows
    uint64_t& frames;
    ~Count() { ++frames; }
  } count{impl_->frames_};
  impl_->End();
  const Clock::time_point done = Clock::now();
  s.total.total_seconds = Seconds(impl_->begin_, done);
  s.render_seconds = 0;
  if (impl_->options_.kind != BackendKind::kSerial) {
    double render = 0;
    for (const ThreadStats& t : s.threads)
      render = std::max(render, t.busy_seconds + t.idle_seconds);
    s.render_seconds = render;
  }
  s.imbalance = Imbalance(s.threads);
  s.app_cpu_seconds = impl_->app_cpu_;
  return s;
}

const HostFrameStats& HostRenderer::RenderFrame(const FrameContext& ctx, Framebuffer& fb,
                                                const std::function<void()>& app_logic) {
  BeginFrame(ctx, fb);
  if (app_logic) {
    try {
      app_logic();
    } catch (...) {
      try {
        EndFrame();
      } catch (...) {
      }
      throw;
    }
  }
  return EndFrame();
}

// ---------------------------------------------------------------------------------------------
// Export.

namespace {

using Json = nlohmann::ordered_json;

bool EndsWith(const std::string& s, std::string_view suffix) {
  if (s.size() < suffix.size()) return false;
  for (size_t i = 0; i < suffix.size(); ++i) {
    const char c = s[s.size() - suffix.size() + i];
    const char l = (c >= 'A' && c <= 'Z') ? static_cast<char>(c - 'A' + 'a') : c;
    if (l != suffix[i]) return false;
  }
  return true;
}

Json RaysJson(const FrameStats& s) {
  Json rays = Json::object();
  for (int k = 0; k < kNumRayKinds; ++k) rays[RayKindName(RayKind(k))] = s.rays[k];
  return rays;
}

// The caller's fields after the host ones; a name the object already has is an error (JSON
// would silently overwrite it).
Json FieldJson(const StatsValue& value) {
  return std::visit([](const auto& v) { return Json(v); }, value);
}

void AddFields(Json& object, const StatsFields& fields, std::string_view where) {
  for (const StatsField& field : fields) {
    if (object.contains(field.name)) {
      throw Error(fmt::format("statistics: extra {} field '{}' repeats an existing key", where,
                              field.name));
    }
    object[field.name] = FieldJson(field.value);
  }
}

const StatsFields& FrameExtra(const StatsExtra& extra, size_t frame) {
  static const StatsFields kNone;
  return frame < extra.frames.size() ? extra.frames[frame] : kNone;
}

const StatsFields& ThreadExtra(const StatsExtra& extra, size_t frame, size_t thread) {
  static const StatsFields kNone;
  if (frame >= extra.threads.size() || thread >= extra.threads[frame].size()) return kNone;
  return extra.threads[frame][thread];
}

void CheckExtra(const StatsExtra& extra, std::span<const HostFrameStats> frames) {
  if (!extra.frames.empty() && extra.frames.size() != frames.size()) {
    throw Error(fmt::format("statistics: extra fields for {} frames, but {} frames",
                            extra.frames.size(), frames.size()));
  }
  if (!extra.threads.empty() && extra.threads.size() != frames.size()) {
    throw Error(fmt::format("statistics: extra thread fields for {} frames, but {} frames",
                            extra.threads.size(), frames.size()));
  }
  for (size_t i = 0; i < extra.threads.size(); ++i) {
    const size_t n = extra.threads[i].size();
    if (n != 0 && n != frames[i].threads.size()) {
      throw Error(fmt::format("statistics: frame {}: extra fields for {} threads, but {} threads",
                              i, n, frames[i].threads.size()));
    }
  }
}

Json FrameJson(const HostFrameStats& f, const StatsFields& frame_extra,
               std::span<const StatsFields> thread_extra) {
  const FrameStats& s = f.total;
  Json j{{"frame", f.frame},
         {"rays", RaysJson(s)},
         {"tasks", s.tasks},
         {"cell_steps", s.trace.cell_steps},
         {"triangle_tests", s.trace.triangle_tests},
         {"seconds", s.total_seconds},
         {"fps", f.FramesPerSecond()},
         {"render_seconds", f.render_seconds},
         {"generate_seconds", s.generate_seconds},
         {"trace_seconds", s.trace_seconds},
         {"shade_seconds", s.shade_seconds},
         {"schedule_seconds", s.schedule_seconds},
         {"mrays_per_second", s.MraysPerSecond()},
         {"primary_tasks", f.primary_tasks},
         {"idle_seconds", f.IdleSeconds()},
         {"queue_seconds", f.QueueSeconds()},
         {"app_queue_seconds", f.app_queue_seconds},
         {"app_cpu_seconds", f.app_cpu_seconds},
         {"imbalance", f.imbalance}};
  Json threads = Json::array();
  for (size_t w = 0; w < f.threads.size(); ++w) {
    const ThreadStats& t = f.threads[w];
    Json entry{{"thread", w},
               {"busy_seconds", t.busy_seconds},
               {"idle_seconds", t.idle_seconds},
               {"cpu_seconds", t.cpu_seconds},
               {"queue_seconds", t.queue_seconds},
               {"queue_ops", t.queue_ops},
               {"empty_polls", t.empty_polls},
               {"table_adds", t.table_adds},
               {"tasks", t.work.tasks},
               {"tiles", t.tiles},
               {"steals", t.steals},
               {"rays", RaysJson(t.work)},
               {"trace_seconds", t.work.trace_seconds},
               {"shade_seconds", t.work.shade_seconds},
               {"schedule_seconds", t.work.schedule_seconds}};
    if (w < thread_extra.size()) AddFields(entry, thread_extra[w], "thread");
    threads.push_back(std::move(entry));
  }
  j["threads"] = threads;
  if (!f.tiles.empty()) {
    Json tiles = Json::array();
    for (const TileRecord& r : f.tiles) {
      tiles.push_back(Json{{"x0", r.tile.x0},
                           {"y0", r.tile.y0},
                           {"x1", r.tile.x1},
                           {"y1", r.tile.y1},
                           {"thread", r.thread},
                           {"worker", r.worker},
                           {"seconds", r.seconds},
                           {"cpu_seconds", r.cpu_seconds},
                           {"predicted_seconds", r.predicted},
                           {"rays", r.rays},
                           {"work", r.work},
                           {"cell_steps", r.counts.cell_steps},
                           {"triangle_tests", r.counts.triangle_tests},
                           {"shading_calls", r.counts.shading_calls}});
    }
    j["tiles"] = tiles;
  }
  if (f.pbt) {
    Json pbt{{"has_prediction", f.has_prediction},
             {"worker_imbalance", f.worker_imbalance},
             {"demand_imbalance", f.demand_imbalance},
             {"predicted_makespan", f.predicted_makespan},
             {"update_steps", f.update.steps},
             {"variance_before", f.update.variance_before},
             {"variance_after", f.update.variance_after}};
    if (f.has_prediction) {
      pbt["within5"] = f.accuracy.within5;
      pbt["within10"] = f.accuracy.within10;
      pbt["within15"] = f.accuracy.within15;
    }
    j["pbt"] = pbt;
  }
  AddFields(j, frame_extra, "frame");
  return j;
}

// CSV: one header, then per frame the rows
//   scope=frame  (index -1; seconds = frame wall time, busy = render time, idle/queue = sums)
//   scope=app    (index -1; seconds = primary generation, queue = PushPrimary time,
//                 tasks = primary tasks)
//   scope=thread (index = thread)
//   scope=tile   (index = tile; seconds = wall time, worker = PBT worker, predicted, cpu, work
//                 and its counts cell_steps, triangle_tests, shading_calls)
// Columns that do not apply are empty. A caller's extra fields (StatsExtra) follow as columns
// of their own, on the frame and thread rows.
enum CsvColumn : int {
  kFrame,
  kScope,
  kIndex,
  kThread,
  kWorker,
  kSeconds,
  kBusy,
  kIdle,
  kQueue,
  kQueueOps,
  kEmptyPolls,
  kTasks,
  kTiles,
  kRays,
  kPrimary,
  kShadow,
  kReflection,
  kRefraction,
  kX0,
  kY0,
  kX1,
  kY1,
  kCpu,
  kPredicted,
  kImbalance,
  kWorkerImbalance,
  kWithin5,
  kWithin10,
  kWithin15,
  kWork,
  kCellSteps,
  kTriangleTests,
  kShadingCalls,
  kDemandImbalance,
  kNumCsvColumns
};
constexpr const char* kCsvNames[kNumCsvColumns] = {"frame",
                                                   "scope",
                                                   "index",
                                                   "thread",
                                                   "worker",
                                                   "seconds",
                                                   "busy_seconds",
                                                   "idle_seconds",
                                                   "queue_seconds",
                                                   "queue_ops",
                                                   "empty_polls",
                                                   "tasks",
                                                   "tiles",
                                                   "rays",
                                                   "primary",
                                                   "shadow",
                                                   "reflection",
                                                   "refraction",
                                                   "x0",
                                                   "y0",
                                                   "x1",
                                                   "y1",
                                                   "cpu_seconds",
                                                   "predicted_seconds",
                                                   "imbalance",
                                                   "worker_imbalance",
                                                   "within5",
                                                   "within10",
                                                   "within15",
                                                   "work",
                                                   "cell_steps",
                                                   "triangle_tests",
                                                   "shading_calls",
                                                   "demand_imbalance"};

// The extra columns: every extra name in order of first occurrence (frame fields, then thread
// fields). Throws rs::Error for a name that is a host column.
std::vector<std::string> ExtraColumns(const StatsExtra& extra) {
  std::vector<std::string> names;
  auto add = [&](const StatsFields& fields) {
    for (const StatsField& field : fields) {
      for (const char* host : kCsvNames) {
        if (field.name == host) {
          throw Error(fmt::format("statistics: extra field '{}' repeats a CSV column", host));
        }
      }
      if (std::find(names.begin(), names.end(), field.name) == names.end()) {
        names.push_back(field.name);
      }
    }
  };
  for (const StatsFields& fields : extra.frames) add(fields);
  for (const auto& frame : extra.threads) {
    for (const StatsFields& fields : frame) add(fields);
  }
  return names;
}

// RFC 4180 quoting for a string holding a comma, quote or line break.
std::string CsvText(const std::string& s) {
  if (s.find_first_of(",\"\r\n") == std::string::npos) return s;
  std::string q = "\"";
  for (const char c : s) q += c == '"' ? std::string("\"\"") : std::string(1, c);
  return q + "\"";
}

class CsvRow {
 public:
  explicit CsvRow(const std::vector<std::string>& extra_names)
      : extra_names_(extra_names), cells_(kNumCsvColumns + extra_names.size()) {}
  template <class T>
  CsvRow& Set(CsvColumn c, const T& value) {
    cells_[static_cast<size_t>(c)] = fmt::format("{}", value);
    return *this;
  }
  CsvRow& SetRays(const FrameStats& s) {
    Set(kRays, s.TotalRays());
    for (int k = 0; k < kNumRayKinds; ++k) Set(static_cast<CsvColumn>(kPrimary + k), s.rays[k]);
    return *this;
  }
  // The fields go to their extra columns; a name twice in `fields` is an error.
  CsvRow& SetExtra(const StatsFields& fields) {
    std::vector<char> set(extra_names_.size(), 0);
    for (const StatsField& field : fields) {
      const size_t i = static_cast<size_t>(
          std::find(extra_names_.begin(), extra_names_.end(), field.name) - extra_names_.begin());
      if (set[i]) throw Error(fmt::format("statistics: extra field '{}' given twice", field.name));
      set[i] = 1;
      cells_[kNumCsvColumns + i] = std::visit(
          [](const auto& v) {
            if constexpr (std::is_same_v<std::decay_t<decltype(v)>, std::string>) {
              return CsvText(v);
            } else {
              return fmt::format("{}", v);
            }
          },
          field.value);
    }
    return *this;
  }
  void Write(std::ostream& out) const {
    for (size_t c = 0; c < cells_.size(); ++c) out << (c ? "," : "") << cells_[c];
    out << "\n";
  }

 private:
  const std::vector<std::string>& extra_names_;
  std::vector<std::string> cells_;
};

void WriteCsv(std::ostream& out, std::span<const HostFrameStats> frames, const StatsExtra& extra) {
  const std::vector<std::string> extra_names = ExtraColumns(extra);
  for (int c = 0; c < kNumCsvColumns; ++c) out << (c ? "," : "") << kCsvNames[c];
  for (const std::string& name : extra_names) out << "," << CsvText(name);
  out << "\n";
  for (size_t fi = 0; fi < frames.size(); ++fi) {
    const HostFrameStats& f = frames[fi];
    const FrameStats& s = f.total;
    CsvRow frame(extra_names);
    frame.Set(kFrame, f.frame).Set(kScope, "frame").Set(kIndex, -1).Set(kSeconds, s.total_seconds);
    frame.Set(kBusy, f.render_seconds).Set(kIdle, f.IdleSeconds()).Set(kQueue, f.QueueSeconds());
    frame.Set(kTasks, s.tasks).Set(kTiles, f.tiles.size()).SetRays(s).Set(kImbalance, f.imbalance);
    frame.Set(kCellSteps, s.trace.cell_steps).Set(kTriangleTests, s.trace.triangle_tests);
    frame.Set(kShadingCalls, s.shade.shading_calls);
    if (f.pbt) {
      frame.Set(kWorkerImbalance, f.worker_imbalance).Set(kDemandImbalance, f.demand_imbalance);
      if (f.has_prediction) {
        frame.Set(kWithin5, f.accuracy.within5).Set(kWithin10, f.accuracy.within10);
        frame.Set(kWithin15, f.accuracy.within15);
      }
    }
    frame.SetExtra(FrameExtra(extra, fi)).Write(out);
    CsvRow app(extra_names);
    app.Set(kFrame, f.frame).Set(kScope, "app").Set(kIndex, -1).Set(kSeconds, s.generate_seconds);
    app.Set(kQueue, f.app_queue_seconds).Set(kTasks, f.primary_tasks).Write(out);
    for (size_t w = 0; w < f.threads.size(); ++w) {
      const ThreadStats& t = f.threads[w];
      CsvRow row(extra_names);
      row.Set(kFrame, f.frame).Set(kScope, "thread").Set(kIndex, w).Set(kThread, w);
      row.Set(kBusy, t.busy_seconds).Set(kIdle, t.idle_seconds).Set(kQueue, t.queue_seconds);
      row.Set(kQueueOps, t.queue_ops).Set(kEmptyPolls, t.empty_polls).Set(kTasks, t.work.tasks);
      row.Set(kTiles, t.tiles).SetRays(t.work).SetExtra(ThreadExtra(extra, fi, w)).Write(out);
    }
    for (size_t i = 0; i < f.tiles.size(); ++i) {
      const TileRecord& r = f.tiles[i];
      CsvRow row(extra_names);
      row.Set(kFrame, f.frame).Set(kScope, "tile").Set(kIndex, i).Set(kThread, r.thread);
      row.Set(kWorker, r.worker).Set(kSeconds, r.seconds).Set(kRays, r.rays);
      row.Set(kX0, r.tile.x0).Set(kY0, r.tile.y0).Set(kX1, r.tile.x1).Set(kY1, r.tile.y1);
      row.Set(kCpu, r.cpu_seconds).Set(kWork, r.work).Set(kCellSteps, r.counts.cell_steps);
      row.Set(kTriangleTests, r.counts.triangle_tests).Set(kShadingCalls, r.counts.shading_calls);
      if (r.predicted >= 0) row.Set(kPredicted, r.predicted);
      row.Write(out);
    }
  }
}

}  // namespace

bool StatsFileFormatOk(const std::string& path) {
  return EndsWith(path, ".json") || EndsWith(path, ".csv");
}

std::string HostStatsText(const std::string& path, const std::string& scene,
                          const BackendOptions& options, std::span<const HostFrameStats> frames,
                          const StatsExtra& extra) {
  if (!StatsFileFormatOk(path)) {
    throw Error(fmt::format("{}: statistics file must end in .json or .csv", path));
  }
  CheckExtra(extra, frames);
  // Built in memory first: an error in the extra fields leaves no half-written file.
  std::ostringstream text;
  if (EndsWith(path, ".csv")) {
    WriteCsv(text, frames, extra);
  } else {
    const std::string name = extra.backend.empty() ? BackendName(options.kind) : extra.backend;
    Json backend{{"name", name}, {"threads", options.threads}};
    // The PBT's keys wherever a PBT tiles the image (the queue backends' tiles feed queues).
    if (options.kind == BackendKind::kTiles || options.pbt_tiles_per_worker > 0) {
      if (options.kind == BackendKind::kTiles) {
        backend["tile"] = fmt::format("{}x{}", options.tile_width, options.tile_height);
      }
      backend["pbt_tiles_per_worker"] = options.pbt_tiles_per_worker;
      if (options.pbt_tiles_per_worker > 0) {
        backend["pbt_workers"] = options.pbt_workers > 0 ? options.pbt_workers : options.threads;
        backend["assign"] = PbtAssignName(options.assign);
        // pbt_time: the older name of pbt_cost, kept for readers of earlier files.
        backend["pbt_time"] = PbtCostName(options.pbt_cost);
        backend["pbt_cost"] = PbtCostName(options.pbt_cost);
        backend["steal"] = options.pbt_steal;
        backend["demand"] = options.pbt_demand;
      }
    }
    AddFields(backend, extra.options, "options");
    Json j{{"scene", scene},
           {"backend", name},
           {"threads", options.threads},
           {"hardware_threads", std::thread::hardware_concurrency()},
           {"options", backend}};
    Json list = Json::array();
    for (size_t i = 0; i < frames.size(); ++i) {
      const std::vector<StatsFields> none;
      const std::vector<StatsFields>& threads = i < extra.threads.size() ? extra.threads[i] : none;
      list.push_back(FrameJson(frames[i], FrameExtra(extra, i), threads));
    }
    j["frames"] = list;
    text << j.dump(2) << "\n";
  }
  return text.str();
}

void WriteHostStats(const std::string& path, const std::string& scene,
                    const BackendOptions& options, std::span<const HostFrameStats> frames,
                    const StatsExtra& extra) {
  WriteFileAtomically(path, HostStatsText(path, scene, options, frames, extra), "statistics");
}

}  // namespace rs
