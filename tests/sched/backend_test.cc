// Host backends: serial, LOCK, LFREE, LOCAL and tiles (many tile shapes, PBT re-tiling over
// frames) must give the serial renderer's framebuffer bit for bit (integer fixed-point sums, no
// tolerance) at 1, 2 and 4 threads; their statistics must add up; the frame loop must run many
// frames, finish empty frames and shut down without hanging. Smaller under ThreadSanitizer (or
// with RS_BACKEND_TEST_QUICK=1).
#include "sched/backends.h"

#include <doctest/doctest.h>
#include <nlohmann/json.hpp>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <functional>
#include <memory>
#include <span>
#include <sstream>
#include <stdexcept>
#include <string>
#include <system_error>
#include <thread>
#include <utility>
#include <vector>

#include "scenes/load.h"
#include "sched/frame_loop.h"
#include "sched/queue_lockfree.h"
#include "tests/test_util.h"

namespace rs {
namespace {

// Under TSan (10-50x slower, debug build) and on request: smaller images, fewer variants.
bool Quick() {
  if (RS_TEST_TSAN) return true;
  const char* q = std::getenv("RS_BACKEND_TEST_QUICK");
  return q != nullptr && std::string(q) == "1";
}

struct Loaded {
  Scene scene;
  std::unique_ptr<Accel> accel;
  std::vector<LightBuffer> lights;  // over *accel: CheckBackend's backends trace shadow rays
                                    // through them, the serial references through the grid
};

Loaded Load(const std::string& name) {
  Loaded l{LoadScene(name), nullptr, {}};
  l.accel = std::make_unique<Accel>(l.scene.mesh());
  l.lights = BuildLightBuffers(l.scene, *l.accel);
  return l;
}

RenderOptions Options(int width, int height, int depth) {
  RenderOptions o;
  o.width = width;
  o.height = height;
  o.max_depth = depth;
  return o;
}

// "" if the fixed-point sums are identical, else the first differing pixel and channel.
std::string DiffSums(const Framebuffer& got, const Framebuffer& want) {
  if (got.width() != want.width() || got.height() != want.height()) return "size differs";
  const size_t n = 3 * got.num_pixels();
  size_t differing = 0;
  size_t first = n;
  for (size_t i = 0; i < n; ++i) {
    if (got.sums()[i] != want.sums()[i]) {
      if (first == n) first = i;
      ++differing;
    }
  }
  if (differing == 0) return "";
  std::ostringstream s;
  s << differing << " channel sums differ; first: pixel " << first / 3 << " channel " << first % 3
    << " got " << got.sums()[first] << " want " << want.sums()[first];
  return s.str();
}

// Threads of this process (Linux: the entries of /proc/self/task; 0 if unreadable).
size_t ThreadCount() {
  std::error_code ec;
  size_t n = 0;
  for (std::filesystem::directory_iterator it("/proc/self/task", ec), end; !ec && it != end;
       it.increment(ec)) {
    ++n;
  }
  return n;
}

// The thread count once it has dropped to `want` (a joined thread can linger in /proc for a
// moment), or the count after 5 s of waiting.
size_t ThreadCountSettlesAt(size_t want) {
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(5);
  size_t n = ThreadCount();
  while (n != want && std::chrono::steady_clock::now() < deadline) {
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
    n = ThreadCount();
  }
  return n;
}

// Runs f on a helper thread and waits up to 60 s for it. A hang cannot be unwound (f's thread
// still uses the caller's objects), so it aborts with `what` instead of waiting for the test
// timeout. doctest assertions inside f are reported as usual.
template <class F>
void FinishesWithin(const char* what, F&& f) {
  std::atomic<bool> done{false};
  std::thread t([&] {
    f();
    done.store(true, std::memory_order_release);
  });
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(60);
  while (!done.load(std::memory_order_acquire) && std::chrono::steady_clock::now() < deadline) {
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
  }
  if (!done.load(std::memory_order_acquire)) {
    std::fprintf(stderr, "backend_test: hang: %s did not finish within 60 s\n", what);
    std::abort();
  }
  t.join();
}

struct Reference {
  Framebuffer fb;
  FrameStats stats;
};

Reference RenderReference(const FrameContext& ctx) {
  Reference r{Framebuffer(ctx.options.width, ctx.options.height), {}};
  r.stats = RenderSerial(ctx, r.fb);
  return r;
}

// A queue backend with PBT: one record per tile, taken by one thread, every traced ray charged
// to one tile (work = TileWorkCost of its rays). LOCAL keeps a tile on the thread that took it
// (without stealing: the thread owning its list): that thread traces the tile's primaries and
// its whole ray tree.
void CheckQueuePbtStats(const HostFrameStats& s, const BackendOptions& o, const FrameStats& want,
                        size_t expected_tiles) {
  REQUIRE(s.tiles.size() == expected_tiles);
  const size_t threads = static_cast<size_t>(o.threads);
  std::vector<uint64_t> pixels(threads, 0), rays(threads, 0);
  uint64_t tile_rays = 0, tiles = 0, steals = 0, foreign = 0;
  size_t all_pixels = 0;
  for (const TileRecord& r : s.tiles) {
    REQUIRE(r.thread >= 0);
    REQUIRE(r.thread < o.threads);
    CHECK(r.worker >= 0);
    CHECK(r.rays >= r.tile.NumPixels());  // at least its primary rays
    CHECK(r.counts.rays == r.rays);
    CHECK(r.counts.cell_steps == 0);  // per batch, not per ray: not attributed
    CHECK(r.work == TileWorkCost(r.counts));
    CHECK(r.seconds == 0.0);  // a tile has no time of its own on a queue backend
    tile_rays += r.rays;
    all_pixels += r.tile.NumPixels();
    pixels[static_cast<size_t>(r.thread)] += r.tile.NumPixels();
    rays[static_cast<size_t>(r.thread)] += r.rays;
    if (o.assign == PbtAssign::kCounter) {
      CHECK(r.worker == r.thread);
    } else {
      foreign += r.worker % o.threads != r.thread;
    }
  }
  CHECK(tile_rays == want.TotalRays());
  CHECK(all_pixels == static_cast<size_t>(want.rays[0]));
  for (const ThreadStats& t : s.threads) {
    tiles += t.tiles;
    steals += t.steals;
  }
  CHECK(tiles == expected_tiles);
  CHECK(foreign == steals);
  if (o.kind == BackendKind::kLocal) {
    if (!o.pbt_steal) CHECK(steals == 0);  // so every tile ran on its list's thread
    for (size_t t = 0; t < threads; ++t) {
      CHECK(s.threads[t].work.rays[0] == pixels[t]);
      CHECK(s.threads[t].work.TotalRays() == rays[t]);
    }
  }
  if (o.kind != BackendKind::kLocal && o.assign != PbtAssign::kCounter) {
    CHECK(steals <= expected_tiles);  // shared queues take other lists' tiles when theirs are done
  }
}

// The demand-driven master's rule replayed on a frame's records in the order the master handed
// the tiles out (whatever the threads' timing): every tile handed out once, each the first
// waiting tile (in PBT order) of its thread's lists (list v is thread v % threads's) if one was
// left, else the first waiting tile; a steal is a tile from another thread's lists.
void CheckDemandOrder(const HostFrameStats& s, const BackendOptions& o) {
  const size_t m = s.tiles.size();
  std::vector<size_t> tile_at(m, m);  // hand-out position -> tile
  for (size_t i = 0; i < m; ++i) {
    const int64_t h = s.tiles[i].handout;
    REQUIRE(h >= 0);
    REQUIRE(static_cast<size_t>(h) < m);
    REQUIRE(tile_at[static_cast<size_t>(h)] == m);  // one tile per position
    tile_at[static_cast<size_t>(h)] = i;
  }
  auto mine = [&](size_t t, int thread) { return s.tiles[t].worker % o.threads == thread; };
  std::vector<bool> taken(m, false);
  uint64_t foreign = 0;
  for (size_t h = 0; h < m; ++h) {
    const size_t got = tile_at[h];
    const int thread = s.tiles[got].thread;
    size_t want = m;
    for (size_t t = 0; t < m && want == m; ++t) {
      if (!taken[t] && mine(t, thread)) want = t;
    }
    for (size_t t = 0; t < m && want == m; ++t) {
      if (!taken[t]) want = t;
    }
    INFO("hand-out ", h, " to thread ", thread);
    CHECK(got == want);
    taken[got] = true;
    foreign += !mine(got, thread);
  }
  uint64_t steals = 0;
  for (const ThreadStats& t : s.threads) steals += t.steals;
  CHECK(steals == foreign);
}

// Rays, tasks and per-thread bookkeeping must add up to the serial frame's counts.
void CheckStats(const HostFrameStats& s, const BackendOptions& o, const RenderOptions& ro,
                const FrameStats& want, size_t expected_tiles) {
  INFO("backend ", std::string(BackendName(o.kind)), " threads ", o.threads);
  for (int k = 0; k < kNumRayKinds; ++k) CHECK(s.total.rays[k] == want.rays[k]);
  // Tasks (at most task_size = 20 rays of one class each) cover every ray once: the engine
  // counts task units per kernel call, the queue backends the tasks they popped, so the counts
  // depend on batching and cutting but stay between these bounds.
  CHECK(s.total.tasks * 20 >= s.total.TotalRays());
  CHECK(s.total.tasks <= s.total.TotalRays());
  CHECK(s.total.hits == want.hits);
  CHECK(s.total.occluded == want.occluded);
  const size_t threads = o.kind == BackendKind::kSerial ? 1 : static_cast<size_t>(o.threads);
  REQUIRE(s.threads.size() == threads);
  uint64_t rays[kNumRayKinds] = {};
  uint64_t tasks = 0, tiles = 0;
  for (const ThreadStats& t : s.threads) {
    for (int k = 0; k < kNumRayKinds; ++k) rays[k] += t.work.rays[k];
    tasks += t.work.tasks;
    tiles += t.tiles;
    CHECK(t.busy_seconds >= 0.0);
    CHECK(t.idle_seconds >= 0.0);
    CHECK(t.queue_seconds >= 0.0);
  }
  for (int k = 0; k < kNumRayKinds; ++k) CHECK(rays[k] == want.rays[k]);
  CHECK(tasks == s.total.tasks);
  CHECK(s.total.total_seconds > 0.0);
  CHECK(s.imbalance >= 1.0);
  switch (o.kind) {
    case BackendKind::kLock:
    case BackendKind::kLockFree:
    case BackendKind::kLocal: {
      uint64_t primary_rays = 0;
      CHECK(s.primary_tasks > 0);
      for (const ThreadStats& t : s.threads) {
        // Every thread polled its queue at least once (the EMPTY that ended its frame) and
        // timed it. A LOCAL thread traces only the tiles it took (no stealing).
        CHECK(t.queue_ops >= 1);
        CHECK(t.empty_polls >= 1);
        primary_rays += t.work.rays[0];
      }
      CHECK(primary_rays == want.rays[0]);
      if (ro.batch >= 4 * ro.task_size && s.total.tasks >= 1000) {
        // A batch of tasks leaves the queue, and its children enter it, in one operation each
        // (PushMany / TryPopMany), besides the polls that found the queue empty. (Frames of a
        // few dozen tasks are all partial batches and tile chunks: no bound there.)
        uint64_t ops = 0, empty = 0;
        for (const ThreadStats& t : s.threads) {
          ops += t.queue_ops;
          empty += t.empty_polls;
        }
        CHECK(ops - std::min(ops, empty) <= s.total.tasks / 2);
      }
      CHECK(s.primary_tasks * 20 >= want.rays[0]);  // tiles cut into tasks of <= 20 rays
      CHECK(s.primary_tasks <= want.rays[0]);
      CHECK(s.total.budget_dropped == 0);
      if (o.pbt_tiles_per_worker > 0) CheckQueuePbtStats(s, o, want, expected_tiles);
      break;
    }
    case BackendKind::kTiles: {
      REQUIRE(s.tiles.size() == expected_tiles);
      CHECK(tiles == expected_tiles);
      uint64_t tile_rays = 0;
      size_t pixels = 0;
      for (const TileRecord& r : s.tiles) {
        CHECK(r.thread >= 0);
        CHECK(r.thread < o.threads);
        CHECK(r.seconds > 0.0);
        CHECK(r.cpu_seconds >= 0.0);
        CHECK(r.rays >= r.tile.NumPixels());  // at least its primary rays
        tile_rays += r.rays;
        pixels += r.tile.NumPixels();
      }
      CHECK(tile_rays == want.TotalRays());
      CHECK(pixels == static_cast<size_t>(want.rays[0]));
      // Each thread took at least one counter value: the one past the end that stopped it.
      if (o.pbt_tiles_per_worker == 0) {
        for (const ThreadStats& t : s.threads) CHECK(t.queue_ops >= 1);
      }
      uint64_t steals = 0;
      for (const ThreadStats& t : s.threads) steals += t.steals;
      if (!o.pbt_steal && !o.pbt_demand) CHECK(steals == 0);
      if (o.pbt_demand) {
        CheckDemandOrder(s, o);
      } else {
        for (const TileRecord& r : s.tiles) CHECK(r.handout == -1);
      }
      CHECK(steals <= expected_tiles);
      // A tile ran on the thread owning its list unless it was stolen.
      uint64_t foreign = 0;
      for (const TileRecord& r : s.tiles) {
        CHECK(r.worker >= 0);
        if (o.pbt_tiles_per_worker > 0) foreign += r.worker % o.threads != r.thread;
      }
      CHECK(foreign == steals);
      break;
    }
    case BackendKind::kSerial:
      break;
  }
}

// Serial references per (frame, camera speed) of one scene and image size, rendered once.
class References {
 public:
  References(const Loaded& l, const RenderOptions& ro) : l_(l), ro_(ro) {}
  const Reference& Get(int frame, float speed) {
    const Camera camera = l_.scene.path.At(frame, speed, l_.scene.camera);
    for (const auto& [cam, ref] : refs_) {
      if (cam.eye == camera.eye && cam.look_at == camera.look_at && cam.up == camera.up &&
          cam.fov_y_deg == camera.fov_y_deg) {
        return *ref;
      }
    }
    const FrameContext ctx = MakeFrameContext(l_.scene, *l_.accel, camera, ro_);
    refs_.emplace_back(camera, std::make_unique<Reference>(RenderReference(ctx)));
    return *refs_.back().second;
  }

 private:
  const Loaded& l_;
  RenderOptions ro_;
  std::vector<std::pair<Camera, std::unique_ptr<Reference>>> refs_;
};

// Renders frames 0..frames-1 of the scene's path with one renderer (the render threads live
// across frames) and compares each against the serial render of the same camera; `more` (if
// any) checks each frame's statistics further.
void CheckBackend(const Loaded& l, const RenderOptions& ro, References& refs,
                  const BackendOptions& o, int frames, float speed = 1.0f,
                  const std::function<void(const HostFrameStats&)>& more = {}) {
  HostRenderer renderer(o);
  Framebuffer fb(ro.width, ro.height);
  for (int f = 0; f < frames; ++f) {
    const Camera camera = l.scene.path.At(f, speed, l.scene.camera);
    FrameContext ctx = MakeFrameContext(l.scene, *l.accel, camera, ro);
    ctx.light_buffers = l.lights;  // the same image as the grid's (LightBuffer's contract)
    const Reference& ref = refs.Get(f, speed);
    fb.Clear();
    const std::vector<Tile> expected = o.pbt_tiles_per_worker > 0 && renderer.pbt() != nullptr
                                           ? renderer.pbt()->Tiles()
                                           : std::vector<Tile>{};
    const HostFrameStats& s = renderer.RenderFrame(ctx, fb);
    INFO("scene ", l.scene.name, " backend ", std::string(BackendName(o.kind)), " threads ",
         o.threads, " tile ", o.tile_width, "x", o.tile_height, " pbt k ", o.pbt_tiles_per_worker,
         " assign ", std::string(PbtAssignName(o.assign)), " frame ", f);
    CHECK(DiffSums(fb, ref.fb) == "");
    CHECK(fb.dropped_nan() == ref.fb.dropped_nan());
    CHECK(fb.clamped() == ref.fb.clamped());
    size_t tiles = 0;
    if (o.kind == BackendKind::kTiles || o.pbt_tiles_per_worker > 0) {
      if (o.pbt_tiles_per_worker > 0) {
        const int n = o.pbt_workers > 0 ? o.pbt_workers : o.threads;
        tiles = static_cast<size_t>(n) * static_cast<size_t>(o.pbt_tiles_per_worker);
        // The frame ran on the tiling the PBT held before it (the first frame creates it).
        if (!expected.empty()) {
          REQUIRE(s.tiles.size() == expected.size());
          for (size_t i = 0; i < expected.size(); ++i) {
            CHECK(s.tiles[i].tile.x0 == expected[i].x0);
            CHECK(s.tiles[i].tile.y1 == expected[i].y1);
          }
        }
        CHECK(s.pbt);
        CHECK(s.has_prediction == (f > 0));
        if (f > 0) {
          CHECK(s.accuracy.tiles == tiles);
          CHECK(s.accuracy.within5 <= s.accuracy.within10);
          CHECK(s.accuracy.within10 <= s.accuracy.within15);
          CHECK(s.accuracy.within15 <= 1.0);
          for (const TileRecord& r : s.tiles) CHECK(r.predicted >= 0.0);
        }
        CHECK(s.worker_imbalance >= 1.0);
        REQUIRE(renderer.pbt() != nullptr);
        CHECK(renderer.pbt()->Validate() == "");
        CHECK(renderer.pbt()->NumLeaves() == tiles);
      } else {
        const int tw = std::min(o.tile_width, ro.width);
        const int th = std::min(o.tile_height, ro.height);
        tiles = static_cast<size_t>((ro.width + tw - 1) / tw) *
                static_cast<size_t>((ro.height + th - 1) / th);
      }
    }
    CheckStats(s, o, ro, ref.stats, tiles);
    if (more) more(s);
  }
  CHECK(renderer.frames() == static_cast<uint64_t>(frames));
}

BackendOptions Backend(BackendKind kind, int threads) {
  BackendOptions o;
  o.kind = kind;
  o.threads = threads;
  return o;
}

BackendOptions TilesBackend(int threads, int tw, int th) {
  BackendOptions o = Backend(BackendKind::kTiles, threads);
  o.tile_width = tw;
  o.tile_height = th;
  return o;
}

BackendOptions PbtBackend(int threads, int k, PbtAssign assign) {
  BackendOptions o = Backend(BackendKind::kTiles, threads);
  o.pbt_tiles_per_worker = k;
  o.assign = assign;
  o.seed = 7;
  return o;
}

// PBT tiles feeding a queue backend (its tiles' costs are their deterministic work).
BackendOptions QueuePbt(BackendKind kind, int threads, int k, PbtAssign assign) {
  BackendOptions o = PbtBackend(threads, k, assign);
  o.kind = kind;
  o.pbt_cost = PbtCost::kWork;
  return o;
}

void CheckAllBackends(const std::string& scene_name, int size, const std::vector<int>& threads,
                      bool all_shapes) {
  const Loaded l = Load(scene_name);
  const RenderOptions ro = Options(size, size, 4);
  References refs(l, ro);
  CheckBackend(l, ro, refs, Backend(BackendKind::kSerial, 1), 1);
  for (const int n : threads) {
    for (const BackendKind kind :
         {BackendKind::kLock, BackendKind::kLockFree, BackendKind::kLocal}) {
      CheckBackend(l, ro, refs, Backend(kind, n), 2);
      // PBT tiles feeding the queues, every assignment, re-tiled over the walk-through.
      for (const int k : all_shapes ? std::vector<int>{2, 4} : std::vector<int>{2}) {
        for (const PbtAssign a : {PbtAssign::kRandom, PbtAssign::kGreedy, PbtAssign::kVisit,
                                  PbtAssign::kStatic, PbtAssign::kCounter, PbtAssign::kLpt}) {
          CheckBackend(l, ro, refs, QueuePbt(kind, n, k, a), 3, 2.0f);
        }
      }
      // More lists than threads, stealing at the end (LOCAL: into the thief's own queue).
      BackendOptions steal = QueuePbt(kind, n, 2, PbtAssign::kGreedy);
      steal.pbt_workers = 3 * n;
      steal.pbt_steal = true;
      CheckBackend(l, ro, refs, steal, 3, 2.0f);
    }
    // The Cell paper's shapes (Fig. 3): squares, 40x32, 640x2 (clamped to the width), rows,
    // plus an odd shape that leaves partial tiles at both edges.
    std::vector<std::pair<int, int>> shapes = {{16, 16}, {640, 2}, {7, 3}};
    if (all_shapes) shapes = {{8, 8}, {16, 16}, {32, 32}, {40, 32}, {640, 2}, {size, 1}, {7, 3}};
    for (const auto& [tw, th] : shapes) CheckBackend(l, ro, refs, TilesBackend(n, tw, th), 1);
    // PBT re-tiling over a few frames of the walk-through (camera speed 2).
    for (const PbtAssign a : {PbtAssign::kRandom, PbtAssign::kGreedy, PbtAssign::kVisit,
                              PbtAssign::kStatic, PbtAssign::kCounter, PbtAssign::kLpt}) {
      CheckBackend(l, ro, refs, PbtBackend(n, all_shapes ? 4 : 2, a), 3, 2.0f);
    }
    // The deterministic work cost, and the counter with more (model) workers than threads.
    BackendOptions work = PbtBackend(n, 2, PbtAssign::kGreedy);
    work.pbt_cost = PbtCost::kWork;
    CheckBackend(l, ro, refs, work, 3, 2.0f);
    BackendOptions counter = PbtBackend(n, 2, PbtAssign::kCounter);
    counter.pbt_workers = 3 * n;
    counter.pbt_cost = PbtCost::kCpu;
    CheckBackend(l, ro, refs, counter, 2, 2.0f);
    if (all_shapes) CheckBackend(l, ro, refs, PbtBackend(n, 1, PbtAssign::kGreedy), 3, 2.0f);
    // Demand-driven with affinity: 3 PBT workers' lists per thread, stealing at the end.
    BackendOptions steal = PbtBackend(n, 2, PbtAssign::kVisit);
    steal.pbt_workers = 3 * n;
    steal.pbt_steal = true;
    CheckBackend(l, ro, refs, steal, 3, 2.0f);
    // The demand-driven master: tiles on request in PBT order, own lists first, over the
    // walk-through; one list per thread, and 3 lists per thread.
    for (const PbtAssign a : {PbtAssign::kGreedy, PbtAssign::kVisit, PbtAssign::kRandom}) {
      BackendOptions demand = PbtBackend(n, 2, a);
      demand.pbt_demand = true;
      if (a == PbtAssign::kVisit) demand.pbt_workers = 3 * n;
      CheckBackend(l, ro, refs, demand, 3, 2.0f);
    }
  }
}

// ---------------------------------------------------------------------------------------------

TEST_CASE("procedural scenes: every backend gives the serial framebuffer bit for bit") {
  const int size = Quick() ? 24 : 64;
  const std::vector<int> threads = Quick() ? std::vector<int>{2, 3} : std::vector<int>{1, 2, 4};
  for (const char* name : {"cornell", "erw6", "spherebox", "amphitheater:1"}) {
    if (Quick() && std::string(name) == "amphitheater:1") continue;
    INFO("scene ", std::string(name));
    CheckAllBackends(name, size, threads, !Quick());
  }
}

// LOCK and LFREE with batches of >= 64 rays trace their own tiles' rays as private
// generations and push only the surplus (or everything waiting, to a hungry thread). Small
// batches make the surplus path run on small images; 20-ray batches route every ray through
// the queue. Each gives the serial framebuffer. A thread adds to the framebuffer directly
// until it pushes or pops a task, then through its pixel-sum table (table_adds).
TEST_CASE("shared queues: private generations, their surplus and hungry threads, bit for bit") {
  const Loaded l = Load("erw6");
  const int size = Quick() ? 32 : 64;
  for (const int batch : {20, 64, 100, 1024}) {
    RenderOptions ro = Options(size, size, 4);
    ro.batch = batch;
    ro.tile_size = 16;
    References refs(l, ro);
    for (const BackendKind kind : {BackendKind::kLock, BackendKind::kLockFree}) {
      for (const int n : {1, 2, 3}) {
        INFO("batch ", batch, " threads ", n);
        uint64_t pushed_or_popped = 0, table_adds = 0, rays = 0;
        CheckBackend(l, ro, refs, Backend(kind, n), 2, 1.0f, [&](const HostFrameStats& s) {
          for (const ThreadStats& t : s.threads) {
            pushed_or_popped += t.queue_ops - t.empty_polls;
            table_adds += t.table_adds;
            rays += t.work.TotalRays();
          }
        });
        // 64-ray slices keep 256 rays of each class: a 16x16 tile's primaries alone exceed
        // that, so tasks went through the queue.
        if (batch <= 64) CHECK(pushed_or_popped > 0);
        // 20-ray batches: every ray is pushed, so every contribution goes through a table. One
        // thread with 1024-ray batches keeps a 16x16 tile's tree private: none does.
        if (batch == 20) CHECK(table_adds > 0);
        if (batch == 1024 && n == 1) CHECK(table_adds == 0);
        CHECK(table_adds <= 2 * rays);  // at most one per ray traced (two frames)
      }
    }
  }
}

TEST_CASE("shared scenes: every backend bit-identical at 1, 2 and 4 threads") {
  struct Shared {
    const char* name;
    const char* file;
    bool quick;  // also under TSan (small meshes only: debug builds of big grids are slow)
  };
  const Shared scenes[] = {{"bunny", "bunny/bun_zipper.ply", true},
                           {"teapot", "teapot/teapot.obj", true},
                           {"sponza", "sponza/sponza.obj", false},
                           {"office-graz", "office-graz/office-graz.obj", false},
                           {"conference", "conference/conference.obj", false},
                           {"sibenik", "sibenik/sibenik.obj", false}};
  for (const Shared& s : scenes) {
    if (Quick() && !s.quick) continue;
    if (!test::HaveSharedScene(s.file)) continue;
    INFO("scene ", std::string(s.name));
    const Loaded l = Load(s.name);
    const int size = Quick() ? 16 : 40;
    const RenderOptions ro = Options(size, size, 4);
    References refs(l, ro);
    for (const int n : {1, 2, 4}) {
      for (const BackendKind kind :
           {BackendKind::kLock, BackendKind::kLockFree, BackendKind::kLocal}) {
        CheckBackend(l, ro, refs, Backend(kind, n), 1);
      }
      CheckBackend(l, ro, refs, TilesBackend(n, 8, 8), 1);
      CheckBackend(l, ro, refs, TilesBackend(n, size, 1), 1);
      CheckBackend(l, ro, refs, PbtBackend(n, 2, PbtAssign::kVisit), 2, 2.0f);
    }
  }
}

// The queue path once traced Shade's shadow rays in its order (light by light per SIMD vector),
// so its 64-ray runs mixed lights: 17.5 % of office-graz 256x256's rays in coherent packets on
// LOCAL against 61.2 % on tiles. Grouped by light, and with a sub-chunk's worth of shadow tasks
// per call, a queue backend at 1 thread reaches nearly the tiles' share (60.8 %; 96x96: 28.1 %
// against 28.3 %, 10.7 % before); the scheduling work is timed apart from the kernels.
TEST_CASE("queue backends at 1 thread: the tiles' packet share, scheduling timed apart") {
  if (Quick() || !test::HaveSharedScene("office-graz/office-graz.obj")) return;
  const Loaded l = Load("office-graz");
  const RenderOptions ro = Options(96, 96, 4);
  const FrameContext ctx = MakeFrameContext(l.scene, *l.accel, l.scene.camera, ro);
  auto share = [&](const BackendOptions& o, FrameStats* total) {
    HostRenderer r(o);
    Framebuffer fb(ro.width, ro.height);
    *total = r.RenderFrame(ctx, fb).total;
    REQUIRE(total->trace.rays > 0);
    return static_cast<double>(total->trace.packet_rays) / static_cast<double>(total->trace.rays);
  };
  FrameStats tiles_total;
  const double tiles = share(TilesBackend(1, 32, 32), &tiles_total);
  MESSAGE("tiles: ", 100 * tiles, " % of rays in packets");
  CHECK(tiles > 0.2);
  CHECK(tiles_total.schedule_seconds == 0.0);
  for (const BackendKind kind : {BackendKind::kLock, BackendKind::kLockFree, BackendKind::kLocal}) {
    INFO("backend ", std::string(BackendName(kind)));
    FrameStats total;
    const double queue = share(Backend(kind, 1), &total);
    MESSAGE(std::string(BackendName(kind)), ": ", 100 * queue, " % of rays in packets");
    CHECK(queue >= 0.9 * tiles);
    CHECK(total.TotalRays() == tiles_total.TotalRays());
    // More than a batch of shadow rays per call on average, as RenderTile traces them.
    const int shadow = static_cast<int>(RayKind::kShadow);
    CHECK(total.rays[shadow] > static_cast<uint64_t>(ro.batch) * total.trace_calls[shadow]);
    CHECK(total.schedule_seconds > 0.0);
  }
}

// Per frame: the tiles' records; the image checked against serial on the way.
struct PbtRun {
  std::vector<std::vector<TileRecord>> frames;
  std::vector<int> update_steps;
  std::vector<Tile> next_tiles;  // the PBT after the last frame
};

PbtRun RunPbt(const Loaded& l, const RenderOptions& ro, References& refs, const BackendOptions& o,
              int frames, float speed) {
  PbtRun run;
  HostRenderer renderer(o);
  Framebuffer fb(ro.width, ro.height);
  for (int f = 0; f < frames; ++f) {
    const Camera camera = l.scene.path.At(f, speed, l.scene.camera);
    const FrameContext ctx = MakeFrameContext(l.scene, *l.accel, camera, ro);
    fb.Clear();
    const HostFrameStats& s = renderer.RenderFrame(ctx, fb);
    INFO("backend ", std::string(BackendName(o.kind)), " threads ", o.threads, " assign ",
         std::string(PbtAssignName(o.assign)), " frame ", f);
    CHECK(DiffSums(fb, refs.Get(f, speed).fb) == "");
    CHECK(s.pbt);
    CHECK(s.has_prediction == (f > 0));
    run.frames.push_back(s.tiles);
    run.update_steps.push_back(s.update.steps);
  }
  REQUIRE(renderer.pbt() != nullptr);
  run.next_tiles = renderer.pbt()->Tiles();
  return run;
}

bool SameTile(const Tile& a, const Tile& b) {
  return a.x0 == b.x0 && a.y0 == b.y0 && a.x1 == b.x1 && a.y1 == b.y1;
}

// The deterministic part of two runs: tilings, per-tile rays and costs, predictions.
void CheckSameCosts(const PbtRun& a, const PbtRun& b) {
  REQUIRE(a.frames.size() == b.frames.size());
  for (size_t f = 0; f < a.frames.size(); ++f) {
    INFO("frame ", f);
    REQUIRE(a.frames[f].size() == b.frames[f].size());
    for (size_t i = 0; i < a.frames[f].size(); ++i) {
      const TileRecord& x = a.frames[f][i];
      const TileRecord& y = b.frames[f][i];
      CHECK(SameTile(x.tile, y.tile));
      CHECK(x.rays == y.rays);
      CHECK(x.work == y.work);  // bit-identical: same counts, same evaluation order
      CHECK(x.predicted == y.predicted);
    }
  }
  REQUIRE(a.next_tiles.size() == b.next_tiles.size());
  for (size_t i = 0; i < a.next_tiles.size(); ++i) {
    CHECK(SameTile(a.next_tiles[i], b.next_tiles[i]));
  }
}

TEST_CASE("queue backends with PBT: re-tiling, affinity, deterministic work costs") {
  const Loaded l = Load("erw6");
  const int size = Quick() ? 32 : 64;
  const int frames = 4;
  const float speed = 2.0f;
  const RenderOptions ro = Options(size, size, 4);
  References refs(l, ro);

  // PBT-Update re-tiles the queue backends from their tiles' ray counts: from the second frame
  // the tiles carry predictions, and split-merge steps change the tiling.
  for (const BackendKind kind : {BackendKind::kLock, BackendKind::kLockFree, BackendKind::kLocal}) {
    BackendOptions o = QueuePbt(kind, 2, 4, PbtAssign::kGreedy);
    o.pbt_workers = 4;  // 16 tiles
    const PbtRun run = RunPbt(l, ro, refs, o, frames, speed);
    INFO("backend ", std::string(BackendName(kind)));
    int steps = 0;
    bool changed = false;
    for (int f = 0; f < frames; ++f) {
      steps += run.update_steps[static_cast<size_t>(f)];
      const std::vector<TileRecord>& tiles = run.frames[static_cast<size_t>(f)];
      REQUIRE(tiles.size() == 16);
      for (size_t i = 0; i < tiles.size(); ++i) {
        if (f > 0) CHECK(tiles[i].predicted > 0.0);
        if (!SameTile(tiles[i].tile, run.frames[0][i].tile)) changed = true;
      }
    }
    CHECK(steps > 0);
    CHECK(changed);
  }

  // LOCAL with Greedy or Visit and no stealing: each tile on its list's thread, which traces
  // its primaries and whole ray tree (CheckQueuePbtStats), frame after frame.
  for (const PbtAssign a : {PbtAssign::kGreedy, PbtAssign::kVisit}) {
    for (const int threads : {2, 3}) {
      BackendOptions o = QueuePbt(BackendKind::kLocal, threads, 2, a);
      o.pbt_workers = 6;  // two or three lists per thread
      CheckBackend(l, ro, refs, o, frames, speed);
    }
  }

  // The work costs do not depend on the threads, the queue or the order the rays were traced
  // in: the same tilings, rays and costs in every run (PBT workers fixed at 4).
  for (const PbtAssign a : {PbtAssign::kVisit, PbtAssign::kGreedy, PbtAssign::kCounter}) {
    INFO("assign ", std::string(PbtAssignName(a)));
    const int workers = a == PbtAssign::kCounter ? 0 : 4;
    auto options = [&](BackendKind kind, int threads) {
      BackendOptions o = QueuePbt(kind, threads, 2, a);
      o.pbt_workers = workers;
      if (a == PbtAssign::kCounter) o.pbt_tiles_per_worker = 8 / threads;  // 8 tiles
      return o;
    };
    const PbtRun first = RunPbt(l, ro, refs, options(BackendKind::kLockFree, 1), frames, speed);
    CheckSameCosts(first, RunPbt(l, ro, refs, options(BackendKind::kLockFree, 4), frames, speed));
    CheckSameCosts(first, RunPbt(l, ro, refs, options(BackendKind::kLocal, 2), frames, speed));
    CheckSameCosts(first, RunPbt(l, ro, refs, options(BackendKind::kLock, 2), frames, speed));
    if (a != PbtAssign::kVisit) continue;
    // The first frame's tiling is the initial PBT's on every backend: the tiles backend traces
    // the same rays per tile.
    BackendOptions tiles = PbtBackend(2, 2, a);
    tiles.pbt_workers = workers;
    tiles.pbt_cost = PbtCost::kWork;
    const PbtRun t = RunPbt(l, ro, refs, tiles, 1, speed);
    REQUIRE(t.frames[0].size() == first.frames[0].size());
    for (size_t i = 0; i < t.frames[0].size(); ++i) {
      CHECK(SameTile(t.frames[0][i].tile, first.frames[0][i].tile));
      CHECK(t.frames[0][i].rays == first.frames[0][i].rays);
    }
  }
}

// The queue backends feed PBT's cost map as the tiles backend does: per-block work from their
// engines (each ray its own count, RayEngine::SetBlockWork, so the same record at 1 and 2
// threads and on lock, lfree and local, however the threads grouped the rays), the primaries'
// hit distances (the tiles backend's bit for bit: the same primary rays) and the cameras, so
// the map is reprojected to the next camera. The images stay the serial ones.
TEST_CASE("queue backends with PBT: the cost map from their block work, deterministic, moved") {
  const Loaded l = Load("erw6");
  const int size = Quick() ? 32 : 48;
  const int frames = 3;
  const float speed = 2.0f;
  const RenderOptions ro = Options(size, size, 4);
  References refs(l, ro);
  struct Frame {
    std::vector<int64_t> work;  // the threads' block work summed
    std::vector<float> depth;
    std::vector<Tile> tiles;
    std::vector<double> predicted;
    double cost = 0;  // the tiles' costs summed
  };
  // The walk-through's frames; with `next`, each frame knows the next frame's camera.
  auto run = [&](const BackendOptions& o, bool next) {
    HostRenderer r(o);
    Framebuffer fb(size, size);
    std::vector<Frame> out;
    for (int f = 0; f < frames; ++f) {
      FrameContext ctx =
          MakeFrameContext(l.scene, *l.accel, l.scene.path.At(f, speed, l.scene.camera), ro);
      if (next) SetNextCamera(ctx, l.scene.path.At(f + 1, speed, l.scene.camera));
      fb.Clear();
      const HostFrameStats& s = r.RenderFrame(ctx, fb);
      INFO("backend ", std::string(BackendName(o.kind)), " threads ", o.threads, " frame ", f);
      CHECK(DiffSums(fb, refs.Get(f, speed).fb) == "");
      const TilePlanMeasure m = r.cost_map_measure();
      REQUIRE(m.blocks != nullptr);
      CHECK(m.blocks->Matches(size, size, o.pbt_cost_block));
      CHECK(m.camera != nullptr);
      CHECK((m.next_camera != nullptr) == next);
      REQUIRE(m.pixel_depth.size() == static_cast<size_t>(size * size));
      Frame fr;
      fr.work = m.blocks->work;
      fr.depth.assign(m.pixel_depth.begin(), m.pixel_depth.end());
      for (const TileRecord& t : s.tiles) {
        fr.tiles.push_back(t.tile);
        fr.predicted.push_back(t.predicted);
        fr.cost += t.work;
      }
      out.push_back(std::move(fr));
    }
    REQUIRE(r.in_frame() == false);
    return out;
  };
  auto queue = [&](BackendKind kind, int threads) {
    BackendOptions o = QueuePbt(kind, threads, 2, PbtAssign::kGreedy);
    o.pbt_workers = 4;  // 8 tiles at any thread count
    return o;
  };
  auto same_tiles = [](const std::vector<Tile>& a, const std::vector<Tile>& b) {
    return a.size() == b.size() && std::equal(a.begin(), a.end(), b.begin(), SameTile);
  };
  const std::vector<Frame> want = run(queue(BackendKind::kLock, 1), true);
  BackendOptions tiles_options = PbtBackend(2, 2, PbtAssign::kGreedy);
  tiles_options.pbt_workers = 4;
  tiles_options.pbt_cost = PbtCost::kWork;
  const std::vector<Frame> tiles = run(tiles_options, true);
  for (int f = 0; f < frames; ++f) {
    INFO("frame ", f);
    const Frame& w = want[static_cast<size_t>(f)];
    int64_t total = 0;
    for (const int64_t b : w.work) total += b;
    // Each ray charged its cost: the blocks sum to the tiles' ray costs (up to the fixed point's
    // rounding of a ray's cost, about 6e7 units).
    CHECK(static_cast<double>(total) * kBlockWorkUnit == doctest::Approx(w.cost).epsilon(1e-7));
    // erw6 is a closed room: every primary hits.
    CHECK(std::all_of(w.depth.begin(), w.depth.end(),
                      [](float t) { return t > 0.0f && std::isfinite(t); }));
    CHECK(w.depth == tiles[static_cast<size_t>(f)].depth);  // the tilings may differ, not t
  }
  for (const BackendKind kind : {BackendKind::kLock, BackendKind::kLockFree, BackendKind::kLocal}) {
    for (const int threads : {1, 2}) {
      if (kind == BackendKind::kLock && threads == 1) continue;  // `want`
      const std::vector<Frame> got = run(queue(kind, threads), true);
      for (int f = 0; f < frames; ++f) {
        INFO("backend ", std::string(BackendName(kind)), " threads ", threads, " frame ", f);
        const Frame& g = got[static_cast<size_t>(f)];
        const Frame& w = want[static_cast<size_t>(f)];
        CHECK(same_tiles(g.tiles, w.tiles));
        CHECK(g.work == w.work);  // integer sums: exact
        CHECK(g.depth == w.depth);
        CHECK(g.predicted == w.predicted);
      }
    }
  }
  // Without the next camera the map is not moved: the same first frame, other predictions for
  // the second (the camera moves along the path).
  const std::vector<Frame> still = run(queue(BackendKind::kLock, 2), false);
  CHECK(still[0].work == want[0].work);
  CHECK(still[1].predicted != want[1].predicted);
}

// The demand-driven master over a walk-through, with the hand-out order pinned down where the
// threads cannot race: one thread asks for every tile (all its own: PBT order, no steals); a
// thread with no lists (threads > PBT workers) gets only other threads' tiles (all steals).
TEST_CASE("tiles, demand-driven master: PBT order, own lists first, every tile once, stats") {
  const Loaded l = Load("erw6");
  const RenderOptions ro = Options(40, 32, 3);
  References refs(l, ro);
  BackendOptions one = PbtBackend(1, 3, PbtAssign::kGreedy);
  one.pbt_workers = 4;  // 12 tiles in 4 lists, all thread 0's
  one.pbt_demand = true;
  CheckBackend(l, ro, refs, one, 4, 2.0f, [](const HostFrameStats& s) {
    REQUIRE(s.tiles.size() == 12u);
    for (size_t i = 0; i < s.tiles.size(); ++i) {
      CHECK(s.tiles[i].handout == static_cast<int64_t>(i));  // PBT (in-order) order
      CHECK(s.tiles[i].thread == 0);
    }
    CHECK(s.threads[0].tiles == 12u);
    CHECK(s.threads[0].steals == 0u);
    CHECK(s.threads[0].queue_ops == 13u);  // 12 tiles and the request that found none
  });
  BackendOptions three = PbtBackend(3, 2, PbtAssign::kVisit);
  three.pbt_workers = 2;  // lists 0 and 1: threads 0 and 1; thread 2 has none
  three.pbt_demand = true;
  CheckBackend(l, ro, refs, three, 3, 2.0f, [](const HostFrameStats& s) {
    CHECK(s.threads[2].steals == s.threads[2].tiles);  // CheckStats ran CheckDemandOrder
  });
  // The statistics say which mode ran.
  BackendOptions o = PbtBackend(2, 2, PbtAssign::kGreedy);
  o.pbt_demand = true;
  HostRenderer r(o);
  Framebuffer fb(ro.width, ro.height);
  std::vector<HostFrameStats> frames = {
      r.RenderFrame(MakeFrameContext(l.scene, *l.accel, l.scene.camera, ro), fb)};
  const std::filesystem::path path =
      std::filesystem::temp_directory_path() /
      ("rs_backend_test_demand_" + std::to_string(getpid()) + ".json");
  WriteHostStats(path.string(), "erw6", o, frames);
  std::ifstream in(path);
  const nlohmann::json j = nlohmann::json::parse(in);
  in.close();
  std::filesystem::remove(path);
  CHECK(j["options"]["demand"] == true);
  CHECK(j["options"]["steal"] == false);
  REQUIRE(j["frames"][0]["threads"].size() == 2);
  uint64_t steals = 0;
  for (const auto& t : j["frames"][0]["threads"]) steals += t["steals"].get<uint64_t>();
  CHECK(steals == frames[0].threads[0].steals + frames[0].threads[1].steals);
}

TEST_CASE("queue backends with PBT: options") {
  auto message = [](const BackendOptions& o) {
    try {
      ValidateBackendOptions(o);
    } catch (const Error& e) {
      return std::string(e.what());
    }
    return std::string();
  };
  for (const BackendKind kind : {BackendKind::kLock, BackendKind::kLockFree, BackendKind::kLocal}) {
    const std::string name = BackendName(kind);
    BackendOptions o = QueuePbt(kind, 2, 2, PbtAssign::kGreedy);
    CHECK(message(o) == "");
    o.pbt_steal = true;
    CHECK(message(o) == "");
    for (const PbtCost cost : {PbtCost::kWall, PbtCost::kCpu}) {
      o.pbt_cost = cost;
      const std::string m = message(o);
      INFO(m);
      CHECK(m.find(std::string("pbt_cost ") + PbtCostName(cost)) != std::string::npos);
      CHECK(m.find("backend " + name) != std::string::npos);
      CHECK(m.find("no wall or CPU time of its own") != std::string::npos);
    }
  }
  BackendOptions serial = QueuePbt(BackendKind::kSerial, 1, 2, PbtAssign::kGreedy);
  CHECK(message(serial).find("not serial") != std::string::npos);
  // Explicit tiles cannot be combined with PBT.
  const Loaded l = Load("cornell");
  const RenderOptions ro = Options(16, 16, 1);
  const FrameContext ctx = MakeFrameContext(l.scene, *l.accel, l.scene.camera, ro);
  Framebuffer fb(16, 16);
  HostRenderer r(QueuePbt(BackendKind::kLockFree, 2, 2, PbtAssign::kVisit));
  const Tile some[] = {Tile{0, 0, 8, 8}};
  CHECK_THROWS_AS(r.BeginFrame(ctx, fb, some), Error);
  CHECK_FALSE(r.in_frame());
  r.RenderFrame(ctx, fb);
  CHECK(r.pbt() != nullptr);
}

TEST_CASE("a scene that hits nothing, and frames with no rays at all, terminate") {
  Scene empty;
  empty.name = "empty";
  empty.materials.push_back(Material{});
  empty.background = glm::vec3(0.25f, 0.5f, 1.0f);
  empty.camera.eye = glm::vec3(0, 0, 5);
  empty.features = ComputeFeatures(empty);
  const Accel accel(empty.mesh());
  const RenderOptions ro = Options(21, 13, 4);
  const FrameContext ctx = MakeFrameContext(empty, accel, empty.camera, ro);
  const Reference ref = RenderReference(ctx);
  CHECK(ref.stats.rays[0] == 21u * 13u);
  CHECK(ref.stats.TotalRays() == 21u * 13u);  // misses spawn nothing
  const BackendOptions all[] = {Backend(BackendKind::kSerial, 1),
                                Backend(BackendKind::kLock, 3),
                                Backend(BackendKind::kLockFree, 3),
                                Backend(BackendKind::kLocal, 3),
                                TilesBackend(3, 5, 4),
                                PbtBackend(3, 2, PbtAssign::kGreedy),
                                QueuePbt(BackendKind::kLocal, 3, 2, PbtAssign::kGreedy),
                                QueuePbt(BackendKind::kLock, 3, 2, PbtAssign::kCounter)};
  for (const BackendOptions& o : all) {
    INFO("backend ", std::string(BackendName(o.kind)), " pbt ", o.pbt_tiles_per_worker);
    HostRenderer renderer(o);
    Framebuffer fb(ro.width, ro.height);
    for (int f = 0; f < 3; ++f) {
      fb.Clear();
      renderer.RenderFrame(ctx, fb);
      CHECK(DiffSums(fb, ref.fb) == "");
    }
    if (o.pbt_tiles_per_worker > 0) {
      // PBT cannot take explicit tiles.
      fb.Clear();
      CHECK_THROWS_AS(renderer.BeginFrame(ctx, fb, std::span<const Tile>()), Error);
      CHECK_FALSE(renderer.in_frame());
      continue;
    }
    // No tiles: zero primary tasks, the threads must still leave the frame.
    for (int f = 0; f < 5; ++f) {
      fb.Clear();
      renderer.BeginFrame(ctx, fb, std::span<const Tile>());
      CHECK(renderer.in_frame());
      const HostFrameStats& s = renderer.EndFrame();
      CHECK(s.total.TotalRays() == 0);
      CHECK(s.total.tasks == 0);
      CHECK(s.primary_tasks == 0);
      CHECK(DiffSums(fb, Framebuffer(ro.width, ro.height)) == "");
    }
    // Empty tiles (zero pixels) and a subset of tiles.
    const Tile some[] = {Tile{3, 3, 3, 9}, Tile{0, 0, 10, 5}, Tile{10, 5, 21, 13},
                         Tile{7, 7, 2, 2}};
    fb.Clear();
    renderer.BeginFrame(ctx, fb, some);
    const HostFrameStats& s = renderer.EndFrame();
    CHECK(s.total.rays[0] == 50u + 88u);
    if (o.kind == BackendKind::kTiles) CHECK(s.tiles.size() == 4);
  }
}

TEST_CASE("many frames in a row, then END: every backend, one renderer") {
  const Loaded l = Load("cornell");
  const int size = Quick() ? 12 : 24;
  const int frames = Quick() ? 15 : 60;
  const RenderOptions ro = Options(size, size, 3);
  const FrameContext ctx = MakeFrameContext(l.scene, *l.accel, l.scene.camera, ro);
  const Reference ref = RenderReference(ctx);
  const BackendOptions all[] = {Backend(BackendKind::kLock, 4),
                                Backend(BackendKind::kLockFree, 4),
                                Backend(BackendKind::kLocal, 4),
                                TilesBackend(4, 4, 4),
                                PbtBackend(4, 2, PbtAssign::kRandom),
                                QueuePbt(BackendKind::kLockFree, 4, 2, PbtAssign::kRandom)};
  for (const BackendOptions& o : all) {
    INFO("backend ", std::string(BackendName(o.kind)));
    HostRenderer renderer(o);
    Framebuffer fb(size, size);
    int app_logic_runs = 0;
    for (int f = 0; f < frames; ++f) {
      fb.Clear();
      const HostFrameStats& s = renderer.RenderFrame(ctx, fb, [&] { ++app_logic_runs; });
      CHECK(s.frame == static_cast<uint64_t>(f));
      if (DiffSums(fb, ref.fb) != "") {
        FAIL_CHECK("frame ", f, ": ", DiffSums(fb, ref.fb));
        break;
      }
    }
    CHECK(app_logic_runs == frames);
    CHECK(renderer.frames() == static_cast<uint64_t>(frames));
  }  // destructors: END flag, threads joined
  // Every renderer above has joined its render threads.
  const size_t threads_before = ThreadCount();
  REQUIRE(threads_before >= 1);
  // A renderer destroyed in the middle of a frame waits for it (the image is the complete
  // frame) and stops its 3 threads, within a deadline.
  {
    Framebuffer fb(size, size);  // declared first: it must outlive the running frame
    FinishesWithin("destroying a LFREE renderer in the middle of a frame", [&] {
      HostRenderer renderer(Backend(BackendKind::kLockFree, 3));
      CHECK(ThreadCount() >= threads_before + 3);
      renderer.BeginFrame(ctx, fb);
      CHECK(renderer.in_frame());
    });
    CHECK(DiffSums(fb, ref.fb) == "");
    CHECK(ThreadCountSettlesAt(threads_before) == threads_before);
  }
  // A renderer that never ran a frame starts and stops its 2 threads.
  FinishesWithin("destroying a LOCAL renderer that never ran a frame", [&] {
    HostRenderer renderer(Backend(BackendKind::kLocal, 2));
    CHECK(ThreadCount() >= threads_before + 2);
    CHECK_FALSE(renderer.in_frame());
    CHECK(renderer.frames() == 0);
  });
  CHECK(ThreadCountSettlesAt(threads_before) == threads_before);
}

TEST_CASE("FrameLoop: barriers, idle times, exceptions, END") {
  constexpr int kThreads = 3;
  std::vector<std::atomic<int>> runs(kThreads);
  std::atomic<int> frame_of_throw{-1};
  std::atomic<int> current{0};
  {
    FrameLoop loop(kThreads, [&](int w) {
      runs[static_cast<size_t>(w)].fetch_add(1, std::memory_order_relaxed);
      if (w == 1 && current.load(std::memory_order_relaxed) ==
                        frame_of_throw.load(std::memory_order_relaxed)) {
        throw std::runtime_error("boom");
      }
      if (w == 0) std::this_thread::sleep_for(std::chrono::milliseconds(2));  // the slow one
    });
    CHECK(loop.num_threads() == kThreads);
    CHECK_THROWS_AS(loop.Wait(), Error);  // not in a frame
    for (int f = 0; f < 40; ++f) {
      current.store(f, std::memory_order_relaxed);
      if (f == 17) frame_of_throw.store(17, std::memory_order_relaxed);  // before Release
      loop.Release();
      CHECK(loop.in_frame());
      CHECK_THROWS_AS(loop.Release(), Error);
      if (f == 17) {
        CHECK_THROWS_WITH_AS(loop.Wait(), "boom", std::runtime_error);
        continue;
      }
      loop.Wait();
      const auto& t = loop.times();
      REQUIRE(t.size() == kThreads);
      // Thread 0 sleeps 2 ms. Busy + idle is the same span (release -> closing barrier) for
      // every thread. (Which thread idles most is up to the OS scheduler on a loaded machine.)
      CHECK(t[0].busy_seconds >= 0.0015);
      for (int w = 0; w < kThreads; ++w) {
        CHECK(t[static_cast<size_t>(w)].idle_seconds >= 0.0);
        CHECK(t[static_cast<size_t>(w)].idle_seconds + t[static_cast<size_t>(w)].busy_seconds ==
              doctest::Approx(t[0].idle_seconds + t[0].busy_seconds).epsilon(1e-9));
      }
      CHECK(loop.frame_seconds() >= t[0].busy_seconds);
    }
    CHECK(loop.frames() == 40);
    loop.Release();  // destroyed while in a frame: Shutdown waits for it
  }
  for (int w = 0; w < kThreads; ++w) {
    CHECK(runs[static_cast<size_t>(w)].load(std::memory_order_relaxed) == 41);
  }
  CHECK_THROWS_AS(FrameLoop(0, [](int) {}), Error);
  CHECK_THROWS_AS(FrameLoop(2, FrameLoop::Work()), Error);
  // A 1-participant barrier never blocks; shrinking releases the waiters.
  FrameBarrier single(1);
  single.ArriveAndWait();
  // Two of three arrive; dropping the third participant releases them (if they arrived late,
  // the lowered count completes the phase at their arrival instead).
  FrameBarrier shrink(3);
  std::thread a([&] { shrink.ArriveAndWait(); });
  std::thread b([&] { shrink.ArriveAndWait(); });
  std::this_thread::sleep_for(std::chrono::milliseconds(20));
  shrink.SetParticipants(2);
  a.join();
  b.join();
}

// A synthetic ray tree through a shared lock-free queue: a task at depth d < kDepth spawns
// 1 + (id % 3) children, with random yields while "processing" so that threads often find the
// queue EMPTY while others still hold tasks. A thread may leave only when every task of the
// tree is processed; leaving earlier (a count that touched 0 too soon) is what this catches.
TEST_CASE("TaskCount: no thread leaves while a task is queued or being processed") {
  constexpr int kThreads = 4;
  constexpr uint32_t kDepth = 5;
  constexpr uint32_t kPrimary = 3;
  const int trials = Quick() ? 20 : 200;
  // Task = (depth << 24) | id; ids are assigned from a shared counter only to vary fan-out.
  auto children_of = [](uint32_t task) -> uint32_t {
    const uint32_t depth = task >> 24;
    return depth + 1 < kDepth ? 1 + (task & 0xFFFFFFu) % 3 : 0;
  };
  int early = 0, hung = 0;
  for (int trial = 0; trial < trials; ++trial) {
    LockFreeQueue<uint32_t> queue(kThreads);
    TaskCount count;
    std::atomic<uint32_t> next_id{kPrimary};
    std::atomic<uint64_t> processed{0}, created{kPrimary};
    std::atomic<int> early_exits{0};
    for (uint32_t i = 0; i < kPrimary; ++i) queue.PushPrimary(uint32_t{i});
    count.Reset(kPrimary);
    std::vector<std::thread> threads;
    for (int w = 0; w < kThreads; ++w) {
      threads.emplace_back([&, w] {
        uint64_t rng = 0x9E3779B97F4A7C15ull * static_cast<uint64_t>(w + 1 + trial * 16);
        auto coin = [&] {
          rng ^= rng << 13;
          rng ^= rng >> 7;
          rng ^= rng << 17;
          return (rng & 3) == 0;
        };
        uint32_t task = 0;
        for (int polls = 0; polls < 10'000'000; ++polls) {
          if (queue.TryPop(w, task)) {
            if (coin()) std::this_thread::yield();  // "processing"
            const uint32_t k = children_of(task);
            std::vector<uint32_t> kids;
            for (uint32_t c = 0; c < k; ++c) {
              kids.push_back((((task >> 24) + 1) << 24) |
                             (next_id.fetch_add(1, std::memory_order_relaxed) & 0xFFFFFFu));
            }
            created.fetch_add(k, std::memory_order_relaxed);
            processed.fetch_add(1, std::memory_order_relaxed);
            count.Retire(static_cast<int64_t>(k));
            if (coin()) std::this_thread::yield();  // widen the window before the pushes
            for (const uint32_t kid : kids) queue.Push(w, kid);
            continue;
          }
          if (count.Done()) {
            // Everything created so far must be processed (Done's acquire sees every Retire).
            if (processed.load(std::memory_order_relaxed) !=
                created.load(std::memory_order_relaxed)) {
              early_exits.fetch_add(1, std::memory_order_relaxed);
            }
            return;
          }
          std::this_thread::yield();
        }
        early_exits.fetch_add(1000, std::memory_order_relaxed);  // did not terminate
      });
    }
    for (auto& t : threads) t.join();
    const int e = early_exits.load(std::memory_order_relaxed);  // after join
    hung += e >= 1000;
    early += e % 1000;
    CHECK(count.value() == 0);
    CHECK(processed.load(std::memory_order_relaxed) == created.load(std::memory_order_relaxed));
    uint32_t left = 0;
    CHECK_FALSE(queue.TryPop(0, left));
  }
  CHECK(early == 0);
  CHECK(hung == 0);
}

TEST_CASE("renderer misuse and bad options are rs::Error") {
  const Loaded l = Load("cornell");
  const RenderOptions ro = Options(16, 16, 1);
  const FrameContext ctx = MakeFrameContext(l.scene, *l.accel, l.scene.camera, ro);
  Framebuffer fb(16, 16);
  Framebuffer wrong(16, 15);
  HostRenderer r(Backend(BackendKind::kLock, 2));
  CHECK_THROWS_AS(r.EndFrame(), Error);
  CHECK_THROWS_AS(r.BeginFrame(ctx, wrong), Error);
  const Tile outside[] = {Tile{0, 0, 17, 4}};
  CHECK_THROWS_AS(r.BeginFrame(ctx, fb, outside), Error);
  r.BeginFrame(ctx, fb);
  CHECK_THROWS_AS(r.BeginFrame(ctx, fb), Error);
  r.EndFrame();

  auto bad = [](BackendOptions o) { CHECK_THROWS_AS(ValidateBackendOptions(o), Error); };
  bad(Backend(BackendKind::kSerial, 2));
  bad(Backend(BackendKind::kLock, 0));
  bad(Backend(BackendKind::kLocal, FrameLoop::kMaxThreads + 1));
  bad(TilesBackend(2, 0, 8));
  bad(TilesBackend(2, 8, -1));
  BackendOptions pbt_lock = Backend(BackendKind::kLockFree, 2);
  pbt_lock.pbt_tiles_per_worker = 2;
  bad(pbt_lock);
  BackendOptions neg = PbtBackend(2, -1, PbtAssign::kGreedy);
  bad(neg);
  BackendOptions steal_without_pbt = TilesBackend(2, 8, 8);
  steal_without_pbt.pbt_steal = true;
  bad(steal_without_pbt);
  BackendOptions workers_without_pbt = TilesBackend(2, 8, 8);
  workers_without_pbt.pbt_workers = 4;
  bad(workers_without_pbt);
  BackendOptions cost_without_pbt = TilesBackend(2, 8, 8);
  cost_without_pbt.pbt_cost = PbtCost::kWork;
  bad(cost_without_pbt);
  BackendOptions steal_counter = PbtBackend(2, 2, PbtAssign::kCounter);
  steal_counter.pbt_steal = true;
  bad(steal_counter);
  BackendOptions demand_without_pbt = TilesBackend(2, 8, 8);
  demand_without_pbt.pbt_demand = true;
  bad(demand_without_pbt);
  BackendOptions demand_counter = PbtBackend(2, 2, PbtAssign::kCounter);
  demand_counter.pbt_demand = true;
  bad(demand_counter);
  BackendOptions demand_steal = PbtBackend(2, 2, PbtAssign::kGreedy);
  demand_steal.pbt_demand = true;
  demand_steal.pbt_steal = true;
  bad(demand_steal);
  BackendOptions demand_queue = QueuePbt(BackendKind::kLocal, 2, 2, PbtAssign::kGreedy);
  demand_queue.pbt_demand = true;
  bad(demand_queue);
  BackendOptions unknown_cost = PbtBackend(2, 2, PbtAssign::kVisit);
  unknown_cost.pbt_cost = static_cast<PbtCost>(9);
  bad(unknown_cost);
  BackendOptions weird = Backend(BackendKind::kLock, 2);
  weird.kind = static_cast<BackendKind>(42);
  bad(weird);
  CHECK_THROWS_AS([] { HostRenderer serial4(Backend(BackendKind::kSerial, 4)); }(), Error);
  // More PBT tiles than pixels.
  HostRenderer too_many(PbtBackend(4, 100, PbtAssign::kVisit));
  Framebuffer tiny_fb(8, 8);
  const FrameContext tiny = MakeFrameContext(l.scene, *l.accel, l.scene.camera, Options(8, 8, 1));
  CHECK_THROWS_AS(too_many.BeginFrame(tiny, tiny_fb), Error);
  CHECK_FALSE(too_many.in_frame());

  BackendKind kind = BackendKind::kSerial;
  CHECK(ParseBackendKind("lfree", &kind));
  CHECK(kind == BackendKind::kLockFree);
  CHECK(ParseBackendKind("LOCAL", &kind));
  CHECK(kind == BackendKind::kLocal);
  CHECK_FALSE(ParseBackendKind("nosuch", &kind));
  CHECK(kind == BackendKind::kLocal);
  for (const std::string& name : BackendNames()) {
    CHECK(ParseBackendKind(name, &kind));
    CHECK(std::string(BackendName(kind)) == name);
  }
  PbtAssign assign = PbtAssign::kRandom;
  CHECK(ParsePbtAssign("visit", &assign));
  CHECK(assign == PbtAssign::kVisit);
  CHECK(ParsePbtAssign("lpt", &assign));
  CHECK(assign == PbtAssign::kLpt);
  CHECK_FALSE(ParsePbtAssign("sjf", &assign));
}

TEST_CASE("statistics export: JSON and CSV by extension") {
  const Loaded l = Load("cornell");
  const RenderOptions ro = Options(20, 20, 2);
  BackendOptions o = PbtBackend(2, 2, PbtAssign::kGreedy);
  HostRenderer r(o);
  Framebuffer fb(20, 20);
  std::vector<HostFrameStats> frames;
  for (int f = 0; f < 3; ++f) {
    fb.Clear();
    frames.push_back(r.RenderFrame(
        MakeFrameContext(l.scene, *l.accel, l.scene.path.At(f, 1.0f, l.scene.camera), ro), fb));
  }
  const std::filesystem::path dir =
      std::filesystem::temp_directory_path() / ("rs_backend_test_" + std::to_string(getpid()));
  std::filesystem::create_directories(dir);
  const std::string json_path = (dir / "s.json").string();
  const std::string csv_path = (dir / "s.CSV").string();
  WriteHostStats(json_path, "cornell", o, frames);
  WriteHostStats(csv_path, "cornell", o, frames);
  std::ifstream jf(json_path);
  const nlohmann::json j = nlohmann::json::parse(jf);
  CHECK(j["backend"] == "tiles");
  REQUIRE(j["frames"].size() == 3);
  CHECK(j["frames"][1]["threads"].size() == 2);
  CHECK(j["frames"][1]["tiles"].size() == 4);
  CHECK(j["frames"][1]["pbt"]["has_prediction"] == true);
  CHECK(j["frames"][2]["rays"]["primary"] == 400);
  CHECK(j["options"]["assign"] == "greedy");
  CHECK(j["options"]["pbt_cost"] == "wall");
  CHECK(j["options"]["pbt_time"] == "wall");  // the older name, kept for readers
  for (const auto& t : j["frames"][1]["tiles"]) {
    CHECK(t["work"].get<double>() > 0);
    CHECK(t["cell_steps"].get<uint64_t>() > 0);
    CHECK(t["shading_calls"].get<uint64_t>() > 0);
  }
  CHECK(j["frames"][1]["pbt"]["demand_imbalance"].get<double>() >= 1.0);
  CHECK(j["frames"][1]["schedule_seconds"].get<double>() == 0.0);  // tiles move no tasks
  CHECK(j["frames"][1]["threads"][0]["schedule_seconds"].get<double>() == 0.0);
  std::ifstream cf(csv_path);
  std::string line;
  size_t lines = 0, tile_rows = 0, thread_rows = 0, columns = 0;
  std::string header;
  while (std::getline(cf, line)) {
    const size_t commas = static_cast<size_t>(std::count(line.begin(), line.end(), ','));
    if (lines == 0) {
      columns = commas;
      header = line;
    }
    CHECK(commas == columns);  // every row has every column
    if (lines > 0) {           // the header names a "thread" column too
      tile_rows += line.find(",tile,") != std::string::npos;
      thread_rows += line.find(",thread,") != std::string::npos;
    }
    ++lines;
  }
  CHECK(lines == 1 + 3 * (1 + 1 + 2 + 4));
  CHECK(tile_rows == 12);
  CHECK(header.find(",work,cell_steps,triangle_tests,shading_calls,demand_imbalance") !=
        std::string::npos);
  CHECK(thread_rows == 6);
  CHECK_THROWS_AS(WriteHostStats((dir / "s.txt").string(), "x", o, frames), Error);
  CHECK_FALSE(StatsFileFormatOk("a.png"));
  CHECK(StatsFileFormatOk("a.Json"));
  CHECK_THROWS_AS(WriteHostStats((dir / "no" / "such" / "s.json").string(), "x", o, frames), Error);
  std::filesystem::remove_all(dir);
}

std::vector<std::string> Keys(const nlohmann::ordered_json& object) {
  std::vector<std::string> keys;
  for (auto it = object.begin(); it != object.end(); ++it) keys.push_back(it.key());
  return keys;
}

std::vector<std::string> Lines(const std::string& path) {
  std::ifstream f(path);
  std::vector<std::string> lines;
  for (std::string line; std::getline(f, line);) lines.push_back(line);
  return lines;
}

// The MPI master writes its statistics through WriteHostStats with StatsExtra: the host keys and
// columns must stay as they are, in order, with the extra ones after them.
TEST_CASE("statistics export: extra fields after the host keys and columns") {
  const Loaded l = Load("cornell");
  const RenderOptions ro = Options(16, 16, 2);
  const BackendOptions o = PbtBackend(2, 1, PbtAssign::kRandom);
  HostRenderer r(o);
  Framebuffer fb(16, 16);
  std::vector<HostFrameStats> frames;
  for (int f = 0; f < 2; ++f) {
    fb.Clear();
    frames.push_back(r.RenderFrame(
        MakeFrameContext(l.scene, *l.accel, l.scene.path.At(f, 1.0f, l.scene.camera), ro), fb));
  }
  const std::filesystem::path dir =
      std::filesystem::temp_directory_path() / ("rs_backend_extra_" + std::to_string(getpid()));
  std::filesystem::create_directories(dir);
  auto path = [&](const char* name) { return (dir / name).string(); };
  WriteHostStats(path("plain.json"), "cornell", o, frames);
  WriteHostStats(path("plain.csv"), "cornell", o, frames);
  StatsExtra extra;
  extra.backend = "mpi";
  extra.options = {{"ranks", int64_t{3}}, {"timeout_seconds", 2.5}};
  extra.frames = {{{"messages", uint64_t{8}}, {"note", std::string("a,\"b\"")}},
                  {{"messages", uint64_t{9}}}};
  extra.threads = {{{{"rank", int64_t{1}}}, {{"rank", int64_t{2}}, {"ok", true}}}, {}};
  WriteHostStats(path("extra.json"), "cornell", o, frames, extra);
  WriteHostStats(path("extra.csv"), "cornell", o, frames, extra);

  using OJson = nlohmann::ordered_json;
  std::ifstream pf(path("plain.json")), ef(path("extra.json"));
  const OJson plain = OJson::parse(pf), ext = OJson::parse(ef);
  CHECK(Keys(ext) == Keys(plain));
  CHECK(ext["backend"] == "mpi");
  std::vector<std::string> options = Keys(plain["options"]);
  options.insert(options.end(), {"ranks", "timeout_seconds"});
  CHECK(Keys(ext["options"]) == options);
  CHECK(ext["options"]["name"] == "mpi");
  CHECK(ext["options"]["timeout_seconds"] == 2.5);
  REQUIRE(ext["frames"].size() == 2);
  std::vector<std::string> frame0 = Keys(plain["frames"][0]);
  frame0.insert(frame0.end(), {"messages", "note"});
  CHECK(Keys(ext["frames"][0]) == frame0);
  CHECK(ext["frames"][0]["note"] == "a,\"b\"");
  CHECK(ext["frames"][1]["messages"] == 9);
  CHECK(ext["frames"][1]["rays"] == plain["frames"][1]["rays"]);
  std::vector<std::string> thread1 = Keys(plain["frames"][0]["threads"][1]);
  thread1.insert(thread1.end(), {"rank", "ok"});
  CHECK(Keys(ext["frames"][0]["threads"][1]) == thread1);
  CHECK(ext["frames"][0]["threads"][1]["ok"] == true);
  CHECK(Keys(ext["frames"][1]["threads"][0]) == Keys(plain["frames"][1]["threads"][0]));

  const std::vector<std::string> pc = Lines(path("plain.csv")), ec = Lines(path("extra.csv"));
  REQUIRE(ec.size() == pc.size());
  CHECK(ec[0] == pc[0] + ",messages,note,rank,ok");
  // Frame 0: frame row, app row, thread rows 0 and 1, then its tile rows.
  const std::string quoted = "\"a,\"\"b\"\"\"";
  CHECK(ec[1].size() > quoted.size());
  CHECK(ec[1].ends_with(",8," + quoted + ",,"));
  CHECK(ec[2].ends_with(",,,,"));
  CHECK(ec[3].ends_with(",,,1,"));
  CHECK(ec[4].ends_with(",,,2,true"));
  const size_t frame1 = 1 + pc.size() / 2;  // both frames have the same number of rows
  CHECK(ec[frame1].rfind("1,frame,", 0) == 0);
  CHECK(ec[frame1].ends_with(",9,,,"));

  // Sizes that do not match the frames, and names the host already uses, are errors, and no
  // file is left behind.
  const std::string bad = path("bad.json"), bad_csv = path("bad.csv");
  StatsExtra e = extra;
  e.frames.pop_back();
  CHECK_THROWS_AS(WriteHostStats(bad, "x", o, frames, e), Error);
  e = extra;
  e.threads[0].push_back({});
  CHECK_THROWS_AS(WriteHostStats(bad, "x", o, frames, e), Error);
  e = extra;
  e.frames[1].push_back({"fps", 1.0});  // a host JSON key
  CHECK_THROWS_AS(WriteHostStats(bad, "x", o, frames, e), Error);
  e = extra;
  e.threads[0][0].push_back({"tiles", int64_t{1}});  // a host key and CSV column
  CHECK_THROWS_AS(WriteHostStats(bad, "x", o, frames, e), Error);
  CHECK_THROWS_AS(WriteHostStats(bad_csv, "x", o, frames, e), Error);
  e = extra;
  e.frames[0].push_back({"messages", uint64_t{1}});  // twice in one object
  CHECK_THROWS_AS(WriteHostStats(bad, "x", o, frames, e), Error);
  CHECK_THROWS_AS(WriteHostStats(bad_csv, "x", o, frames, e), Error);
  CHECK_FALSE(std::filesystem::exists(bad));
  CHECK_FALSE(std::filesystem::exists(bad_csv));
  std::filesystem::remove_all(dir);
}

}  // namespace
}  // namespace rs
