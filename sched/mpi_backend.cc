// Cluster backend over MPI (Cosenza et al. §2-4): rank 0 is the master (tiling, PBT, framebuffer,
// images, statistics), ranks 1..N-1 load the scene themselves and render the tiles they are sent.

// Protocol (all point-to-point, MPI_COMM_WORLD):
//   worker -> master  kTagSetup     int32[1] 0: scene loaded and grid built, 1: failed
//   master -> worker  kTagSetupDone int32[1] the lowest failing rank (N: none, render)
//   master -> worker  kTagTile      int32[6] {frame, tile, x0, y0, x1, y1}
//   worker -> master  kTagResult    int64[kHeader + 3 * pixels]: the header (ResultWord: frame
//                                   and tile in one word, the tile's wall and CPU time, NaN /
//                                   clamped counts, its FrameStats: tasks, rays by kind, cell
//                                   steps, triangle tests, shading calls, generate / trace /
//                                   shade seconds) + the tile's fixed-point sums
//   master -> worker  kTagStop      int32[1] (after the last frame)
//   worker -> master  kTagBye       int32[1] (then MPI_Finalize)
// Every wait of the master is bounded by timeout_seconds: it never blocks in MPI, it posts
// non-blocking operations (MPI_Irecv, MPI_Isend, MPI_Improbe + MPI_Imrecv) and polls them
// against a deadline, sleeping between polls (it shares the cores with the workers). A worker
// that misses a deadline (setup, a tile, a result in transfer, the end of the run) ends the run
// with one line naming its rank and MPI_Abort; the last frame's image and the statistics are
// written only after every worker has said goodbye, so a failed run leaves neither. Workers
// block on the master (it is bounded, and mpirun ends the job if it dies). The master's
// statistics are the host backends' (HostFrameStats, one ThreadStats per worker,
// WriteHostStats) plus the cluster's own.
#include "sched/mpi_backend.h"

#include <fmt/core.h>
#include <mpi.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <bit>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <deque>
#include <exception>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "include/raystream/raystream.h"
#include "scenes/image_io.h"
#include "scenes/load.h"
#include "sched/engine.h"      // SerialRenderer
#include "sched/frame_loop.h"  // ThreadCpuSeconds
#include "sched/pbt.h"
#include "sched/tile_plan.h"

namespace rs {
namespace {

using Clock = std::chrono::steady_clock;

constexpr int kTagTile = 1;
constexpr int kTagResult = 2;
constexpr int kTagStop = 3;
constexpr int kTagSetup = 4;
constexpr int kTagSetupDone = 5;
constexpr int kTagBye = 6;
constexpr int kTileWords = 6;

// A result's header: int64 words before the tile's sums (doubles travel as their bits).
enum ResultWord : int {
  kResFrameTile,   // frame << 32 | tile (both in [0, 2^31))
  kResSeconds,     // wall time of the tile's whole ray tree on the worker
  kResCpuSeconds,  // the CPU time of the worker's render threads for the same span
  kResDroppedNan,  // Framebuffer::dropped_nan() added by the tile
  kResClamped,     // Framebuffer::clamped() added by the tile
  kResTasks,       // FrameStats of the tile, what the statistics report:
  kResRays,        //   rays by RayKind, kNumRayKinds words
  kResCellSteps = kResRays + kNumRayKinds,
  kResTriangleTests,
  kResShadingCalls,
  kResGenerateSeconds,
  kResTraceSeconds,
  kResShadeSeconds,
  kHeader  // words in the header
};

void PackTileStats(const FrameStats& s, int64_t* header) {
  header[kResTasks] = static_cast<int64_t>(s.tasks);
  for (int k = 0; k < kNumRayKinds; ++k) header[kResRays + k] = static_cast<int64_t>(s.rays[k]);
  header[kResCellSteps] = static_cast<int64_t>(s.trace.cell_steps);
  header[kResTriangleTests] = static_cast<int64_t>(s.trace.triangle_tests);
  header[kResShadingCalls] = static_cast<int64_t>(s.shade.shading_calls);
  header[kResGenerateSeconds] = std::bit_cast<int64_t>(s.generate_seconds);
  header[kResTraceSeconds] = std::bit_cast<int64_t>(s.trace_seconds);
  header[kResShadeSeconds] = std::bit_cast<int64_t>(s.shade_seconds);
}

FrameStats UnpackTileStats(const int64_t* header) {
  FrameStats s;
  s.tasks = static_cast<uint64_t>(header[kResTasks]);
  for (int k = 0; k < kNumRayKinds; ++k) s.rays[k] = static_cast<uint64_t>(header[kResRays + k]);
  s.trace.cell_steps = static_cast<uint64_t>(header[kResCellSteps]);
  s.trace.triangle_tests = static_cast<uint64_t>(header[kResTriangleTests]);
  s.shade.shading_calls = static_cast<uint64_t>(header[kResShadingCalls]);
  s.generate_seconds = std::bit_cast<double>(header[kResGenerateSeconds]);
  s.trace_seconds = std::bit_cast<double>(header[kResTraceSeconds]);
  s.shade_seconds = std::bit_cast<double>(header[kResShadeSeconds]);
  return s;
}

double Seconds(Clock::duration d) { return std::chrono::duration<double>(d).count(); }

Clock::time_point Deadline(double seconds) {
  return Clock::now() +
         std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(seconds));
}

// Between polls of a non-blocking operation: 50 us for the first 100 polls, then 500 us (the
// master shares the cores with the workers; a result rarely waits longer than a tile).
void PollSleep(int polls) {
  std::this_thread::sleep_for(std::chrono::microseconds(polls < 100 ? 50 : 500));
}

// Polls `request` until it completes (true) or `deadline` passes (false; the request is still
// pending and the caller aborts the run).
bool TestUntil(MPI_Request& request, Clock::time_point deadline) {
  for (int polls = 0;; ++polls) {
    int done = 0;
    MPI_Test(&request, &done, MPI_STATUS_IGNORE);
    if (done) return true;
    if (Clock::now() > deadline) return false;
    PollSleep(polls);
  }
}

// "rank 2" or "ranks 2, 4" for an error line.
std::string RankList(const std::vector<int>& ranks) {
  std::string out = ranks.size() == 1 ? "rank " : "ranks ";
  for (size_t i = 0; i < ranks.size(); ++i) out += (i ? ", " : "") + std::to_string(ranks[i]);
  return out;
}

std::string FramePath(const std::string& pattern, int frame) {
  const size_t hash = pattern.find('#');
  if (hash == std::string::npos) return pattern;
  return pattern.substr(0, hash) + fmt::format("{:04d}", frame) + pattern.substr(hash + 1);
}

int EnvRank(const char* name) {
  const char* v = std::getenv(name);
  if (v == nullptr || *v == '\0') return -1;
  return std::atoi(v);
}

// Prints one line naming the rank and aborts the whole job (mpirun exits non-zero).
[[noreturn]] void Abort(int rank, const std::string& message) {
  fmt::print(stderr, "raystream: error: mpi rank {}: {}\n", rank, message);
  std::fflush(stderr);
  MPI_Abort(MPI_COMM_WORLD, 3);
  std::_Exit(3);
}

// Test hooks (sched/mpi_backend.h): this rank stops answering for good, without touching MPI.
[[noreturn]] void HangForever(int rank, const char* when) {
  fmt::print(stderr, "raystream: test hook: rank {} stops answering {}\n", rank, when);
  std::fflush(stderr);
  for (;;) std::this_thread::sleep_for(std::chrono::seconds(1));
}

// A sendable int32 message from the master, completed within the deadline or the run ends
// naming the worker. (Tile and control messages are a few bytes, sent eagerly by MPI; the bound
// still holds if a worker stops taking them.)
// `unwritten` says what the abort leaves unwritten.
void MasterSend(const int* msg, int count, int rank, int tag, double timeout,
                const std::string& what, const std::string& unwritten) {
  MPI_Request request;
  MPI_Isend(msg, count, MPI_INT, rank, tag, MPI_COMM_WORLD, &request);
  if (!TestUntil(request, Deadline(timeout))) {
    Abort(0, fmt::format("worker rank {} did not take {} within {:g} s (hung); aborting the run, "
                         "{}",
                         rank, what, timeout, unwritten));
  }
}

// What every rank builds before rendering. Workers own an Accel; the master only the scene.
struct Setup {
  Scene scene;
  std::unique_ptr<Accel> accel;
};

void ValidateConfig(const MpiRenderConfig& c, int ranks) {
  if (ranks < 2) {
    throw Error(
        fmt::format("--backend mpi needs at least 2 ranks (a master and a worker), got {}; "
                    "run it as `mpirun -np N raystream render --backend mpi ...`",
                    ranks));
  }
  ValidateRenderOptions(c.options);
  if (c.frames < 1) throw Error(fmt::format("--frames {}: must be at least 1", c.frames));
  if (c.tile_width < 1 || c.tile_height < 1) {
    throw Error(fmt::format("--tile {}x{}: must be at least 1x1", c.tile_width, c.tile_height));
  }
  if (c.pbt_tiles_per_worker < 0 || c.pbt_tiles_per_worker > 4096) {
    throw Error(fmt::format("--pbt {}: must be in [0, 4096]", c.pbt_tiles_per_worker));
  }
  if (c.threads < 1 || c.threads > 256) {
    throw Error(fmt::format("--threads {}: render threads per worker must be in [1, 256]",
                            c.threads));
  }
  if (c.prefetch < 1 || c.prefetch > 64) {
    throw Error(fmt::format("mpi prefetch {}: must be in [1, 64]", c.prefetch));
  }
  if (!(c.timeout_seconds > 0) || c.timeout_seconds > 1e6) {
    throw Error(fmt::format("--mpi-timeout {}: must be in (0, 1e6] seconds", c.timeout_seconds));
  }
  if (!c.stats.empty() && !StatsFileFormatOk(c.stats)) {
    throw Error(fmt::format("--stats {}: statistics file must end in .json or .csv", c.stats));
  }
  if (c.pbt_tiles_per_worker > 0) {
    const double m = double(c.pbt_tiles_per_worker) * (ranks - 1);
    if (m > double(c.options.width) * c.options.height) {
      throw Error(fmt::format("--pbt {}: {} tiles for {} workers exceed the {}x{} pixels",
                              c.pbt_tiles_per_worker, m, ranks - 1, c.options.width,
                              c.options.height));
    }
  }
  const int cost = static_cast<int>(c.pbt_cost);
  if (cost < 0 || cost > static_cast<int>(PbtCost::kWork)) {
    throw Error(fmt::format("--pbt-cost {}: unknown", cost));
  }
  if (c.pbt_cost != PbtCost::kWall && c.pbt_tiles_per_worker == 0) {
    throw Error(
        fmt::format("--pbt-cost {}: needs a PBT tiling (--pbt k)", PbtCostName(c.pbt_cost)));
  }
  const int assign = static_cast<int>(c.assign);
  if (assign < 0 || assign > static_cast<int>(PbtAssign::kCounter)) {
    throw Error(fmt::format("--assign {}: unknown", assign));
  }
}

// ------------------------------------------------------------------------------------------------
// Worker.

// Renders one tile on this rank with `threads` render threads: with more than one, the tile's
// rows are cut into up to 4 bands per thread, taken from an atomic counter, each thread with its
// own SerialRenderer (kept across tiles) and FrameStats. A ray's contributions stay on its own
// pixel and the framebuffer adds atomically in fixed point, so the sums are the same however
// the tile is cut and whoever renders a band. Threads are started per tile (tens of
// microseconds against a tile's milliseconds).
class TileRenderer {
 public:
  explicit TileRenderer(int threads) : renderers_(static_cast<size_t>(threads)) {}

  // Adds the tile's contributions to fb and its counters to stats; returns the CPU seconds of
  // all its render threads.
  double Render(const FrameContext& ctx, const Tile& tile, Framebuffer& fb, FrameStats& stats) {
    const size_t threads = renderers_.size();
    if (threads == 1 || tile.Height() < 2) {
      const double cpu0 = ThreadCpuSeconds();
      renderers_[0].RenderTiles(ctx, &tile, 1, fb, stats);
      return ThreadCpuSeconds() - cpu0;
    }
    const int bands = std::min(tile.Height(), 4 * static_cast<int>(threads));
    std::vector<Tile> parts;
    for (int b = 0; b < bands; ++b) {
      parts.push_back(Tile{tile.x0, tile.y0 + tile.Height() * b / bands, tile.x1,
                           tile.y0 + tile.Height() * (b + 1) / bands});
    }
    std::atomic<size_t> next{0};
    std::vector<FrameStats> part_stats(threads);
    std::vector<double> cpu(threads, 0.0);
    const auto body = [&](size_t t) {
      const double cpu0 = ThreadCpuSeconds();
      // relaxed: the counter only hands out indices; thread start / join order the data.
      for (size_t i; (i = next.fetch_add(1, std::memory_order_relaxed)) < parts.size();) {
        renderers_[t].RenderTiles(ctx, &parts[i], 1, fb, part_stats[t]);
      }
      cpu[t] = ThreadCpuSeconds() - cpu0;
    };
    std::vector<std::thread> helpers;
    for (size_t t = 1; t < threads; ++t) helpers.emplace_back(body, t);
    body(0);
    for (std::thread& h : helpers) h.join();
    double total = 0;
    for (size_t t = 0; t < threads; ++t) {
      stats.Merge(part_stats[t]);
      total += cpu[t];
    }
    return total;
  }

 private:
  std::vector<SerialRenderer> renderers_;  // one per render thread
};

void RunWorker(const MpiRenderConfig& c, const Setup& s, int rank) {
  const int kill_rank = EnvRank("RAYSTREAM_MPI_TEST_KILL_RANK");
  const int hang_rank = EnvRank("RAYSTREAM_MPI_TEST_HANG_RANK");
  const int hang_end_rank = EnvRank("RAYSTREAM_MPI_TEST_HANG_END_RANK");
  const int stall_rank = EnvRank("RAYSTREAM_MPI_TEST_STALL_RANK");
  Framebuffer fb(c.options.width, c.options.height);
  TileRenderer renderer(c.threads);  // one tile's whole ray tree on this rank
  std::vector<int64_t> result;
  int ctx_frame = -1;
  FrameContext ctx;
  uint64_t tiles_done = 0;
  for (;;) {
    MPI_Status status;
    int msg[kTileWords] = {};
    MPI_Recv(msg, kTileWords, MPI_INT, 0, MPI_ANY_TAG, MPI_COMM_WORLD, &status);
    if (status.MPI_TAG == kTagStop) {
      // The master writes the last image once every worker has said goodbye.
      if (rank == hang_end_rank) HangForever(rank, "after its last tile (never says goodbye)");
      const int bye = 0;
      MPI_Send(&bye, 1, MPI_INT, 0, kTagBye, MPI_COMM_WORLD);
      return;
    }
    if (status.MPI_TAG != kTagTile) Abort(rank, fmt::format("unexpected tag {}", status.MPI_TAG));
    const int frame = msg[0];
    const Tile tile{msg[2], msg[3], msg[4], msg[5]};
    if (frame < 0 || frame >= c.frames || msg[1] < 0 || tile.x0 < 0 || tile.y0 < 0 ||
        tile.x1 > c.options.width || tile.y1 > c.options.height || tile.NumPixels() == 0) {
      Abort(rank, fmt::format("malformed tile message (frame {}, tile {})", frame, msg[1]));
    }
    if (frame != ctx_frame) {
      const Camera camera = s.scene.path.At(frame, c.speed, s.scene.camera);
      ctx = MakeFrameContext(s.scene, *s.accel, camera, c.options);
      ctx_frame = frame;
    }
    // Zero the tile's pixels, render (a ray's contributions stay on its own pixel, so the whole
    // tree of the tile lands inside it), then ship the tile's sums.
    const size_t w = static_cast<size_t>(c.options.width);
    int64_t* sums = fb.sums();
    for (int y = tile.y0; y < tile.y1; ++y) {
      std::fill(sums + 3 * (y * w + tile.x0), sums + 3 * (y * w + tile.x1), int64_t{0});
    }
    const uint64_t nan0 = fb.dropped_nan(), clamped0 = fb.clamped();
    FrameStats stats;
    const auto t0 = Clock::now();
    const double cpu = renderer.Render(ctx, tile, fb, stats);
    const double seconds = Seconds(Clock::now() - t0);
    const size_t tw = static_cast<size_t>(tile.Width());
    result.resize(kHeader + 3 * tile.NumPixels());
    result[kResFrameTile] = (int64_t{frame} << 32) | static_cast<int64_t>(msg[1]);
    result[kResSeconds] = std::bit_cast<int64_t>(seconds);
    result[kResCpuSeconds] = std::bit_cast<int64_t>(cpu);
    result[kResDroppedNan] = static_cast<int64_t>(fb.dropped_nan() - nan0);
    result[kResClamped] = static_cast<int64_t>(fb.clamped() - clamped0);
    PackTileStats(stats, result.data());
    int64_t* dst = result.data() + kHeader;
    for (int y = tile.y0; y < tile.y1; ++y) {
      std::memcpy(dst, sums + 3 * (y * w + tile.x0), 3 * tw * sizeof(int64_t));
      dst += 3 * tw;
    }
    if (tiles_done == 0 && rank == stall_rank) {
      // Test hook: start sending the first result, then never make MPI progress again. The
      // result is larger than the eager limit, so the master matches it but cannot receive it.
      MPI_Request request;
      MPI_Isend(result.data(), static_cast<int>(result.size()), MPI_INT64_T, 0, kTagResult,
                MPI_COMM_WORLD, &request);
      HangForever(rank, "in the middle of sending its first result");
    }
    MPI_Send(result.data(), static_cast<int>(result.size()), MPI_INT64_T, 0, kTagResult,
             MPI_COMM_WORLD);
    ++tiles_done;
    if (tiles_done == 1 && rank == kill_rank) {
      fmt::print(stderr, "raystream: test hook: rank {} exits after its first tile\n", rank);
      std::fflush(stderr);
      _exit(1);
    }
    if (tiles_done == 1 && rank == hang_rank) HangForever(rank, "after its first tile");
  }
}

// ------------------------------------------------------------------------------------------------
// Master.

// Messages and bytes between the master and one worker in one frame (what the host statistics
// do not have).
struct WorkerTraffic {
  uint64_t msgs_sent = 0, bytes_sent = 0;  // master -> this worker
  uint64_t msgs_recv = 0, bytes_recv = 0;  // this worker -> master
};

class Master {
 public:
  Master(const MpiRenderConfig& c, const Setup& s, int ranks)
      : c_(c), s_(s), workers_(ranks - 1), fb_(c.options.width, c.options.height) {
    TilePlanOptions p;
    p.tile_width = c.tile_width;
    p.tile_height = c.tile_height;
    p.pbt_tiles_per_worker = c.pbt_tiles_per_worker;
    p.workers = workers_;
    p.assign = c.assign;
    p.seed = c.seed;
    p.steal = c.pbt_tiles_per_worker > 0 && c.assign != PbtAssign::kCounter;  // always, lists
    p.cost = c.pbt_cost;
    plan_ = std::make_unique<TilePlan>(c.options.width, c.options.height, p);
  }

  void Run() {
    const std::string out = c_.out.empty() ? s_.scene.name + ".png" : c_.out;
    frames_.reserve(static_cast<size_t>(c_.frames));
    double total = 0;
    uint64_t rays = 0;
    const auto write = [&](int frame) {
      fb_.ToRgb(rgb_);
      WriteImage(FramePath(out, frame), c_.options.width, c_.options.height, rgb_);
      if (!c_.dump_raw.empty()) WriteRawFramebuffer(FramePath(c_.dump_raw, frame), fb_);
    };
    const int last = c_.frames - 1;
    for (int frame = 0; frame <= last; ++frame) {
      RenderFrame(frame);
      const HostFrameStats& f = frames_.back();
      total += f.total.total_seconds;
      rays += f.total.TotalRays();
      // Only complete frames reach this point (a failure aborts inside RenderFrame); the last
      // one waits for the end of the run.
      if (frame < last && out.find('#') != std::string::npos) write(frame);
      if (c_.frames > 1 && !c_.quiet) {
        fmt::print(stderr, "frame {}/{}  {:.1f} ms  imbalance {:.3f}\n", frame + 1, c_.frames,
                   1e3 * f.total.total_seconds, f.imbalance);
      }
    }
    EndRun();
    write(last);
    if (!c_.stats.empty()) WriteStats();
    if (!c_.quiet) {
      fmt::print("scene      {}: {} triangles, {} lights\n", s_.scene.name,
                 s_.scene.mesh().num_triangles, s_.scene.lights.size());
      fmt::print("image      {}x{}, depth {}, {} frame(s), backend mpi, {} workers, {}\n",
                 c_.options.width, c_.options.height, c_.options.max_depth, c_.frames, workers_,
                 plan_->uses_pbt()
                     ? fmt::format("PBT k={} assign {} cost {}", c_.pbt_tiles_per_worker,
                                   PbtAssignName(c_.assign), PbtCostName(c_.pbt_cost))
                     : fmt::format("tiles {}x{}", c_.tile_width, c_.tile_height));
      fmt::print("trace      {:.1f} ms, {} rays, {:.2f} Mrays/s\n", 1e3 * total, rays,
                 total > 0 ? rays / total * 1e-6 : 0.0);
      fmt::print("wrote      {}\n", FramePath(out, c_.frames - 1));
    }
  }

 private:
  // The host backends' format (WriteHostStats) with the options of the tiles backend that runs
  // the same tiling (one "thread" per worker; PBT lists with stealing, as the master hands out
  // tiles), backend "mpi", then the cluster's own fields.
  void WriteStats() const {
    BackendOptions o;
    o.kind = BackendKind::kTiles;
    o.threads = workers_;
    o.tile_width = c_.tile_width;
    o.tile_height = c_.tile_height;
    o.pbt_tiles_per_worker = c_.pbt_tiles_per_worker;
    o.pbt_workers = workers_;
    o.pbt_steal = plan_->options().steal;
    o.assign = c_.assign;
    o.seed = c_.seed;
    o.pbt_cost = c_.pbt_cost;
    o.queue_stats = false;
    StatsExtra extra;
    extra.backend = "mpi";
    extra.options = {{"ranks", int64_t{workers_} + 1},
                     {"workers", int64_t{workers_}},
                     {"worker_threads", int64_t{c_.threads}},
                     {"prefetch", int64_t{c_.prefetch}},
                     {"timeout_seconds", c_.timeout_seconds}};
    extra.frames = frame_extra_;
    extra.threads = worker_extra_;
    WriteHostStats(c_.stats, s_.scene.name, o, frames_, extra);
  }

  // After the last frame: stop every worker and wait (bounded) for each one's goodbye, so that
  // MPI_Finalize cannot hang on a worker that stopped after its last tile, and a run that fails
  // here writes neither the last image nor the statistics.
  void EndRun() {
    const std::string unwritten = "the last frame's image and the statistics are not written";
    const int stop = 0;
    for (int r = 1; r <= workers_; ++r) {
      MasterSend(&stop, 1, r, kTagStop, c_.timeout_seconds, "the end-of-run message", unwritten);
    }
    std::vector<int> bye(static_cast<size_t>(workers_), 0);
    std::vector<MPI_Request> requests(static_cast<size_t>(workers_));
    for (int w = 0; w < workers_; ++w) {
      MPI_Irecv(&bye[static_cast<size_t>(w)], 1, MPI_INT, w + 1, kTagBye, MPI_COMM_WORLD,
                &requests[static_cast<size_t>(w)]);
    }
    const auto deadline = Deadline(c_.timeout_seconds);
    for (int polls = 0;; ++polls) {
      std::vector<int> silent;
      for (int w = 0; w < workers_; ++w) {
        MPI_Request& request = requests[static_cast<size_t>(w)];
        int done = 0;
        if (request != MPI_REQUEST_NULL) MPI_Test(&request, &done, MPI_STATUS_IGNORE);
        if (request != MPI_REQUEST_NULL) silent.push_back(w + 1);
      }
      if (silent.empty()) return;
      if (Clock::now() > deadline) {
        Abort(0, fmt::format("worker {} did not answer the end of the run within {:g} s (hung "
                             "after its last tile); aborting the run, {}",
                             RankList(silent), c_.timeout_seconds, unwritten));
      }
      PollSleep(polls);
    }
  }

  // Tiles, per-worker preference lists (PBT) or the shared hand-out order, and predictions for
  // this frame: the tile plan's (sched/tile_plan.h), as the tiles backend runs it.
  void PlanFrame() {
    frame_ = &plan_->Begin();
    tiles_ = frame_->tiles;
    lists_mode_ = !frame_->assignment.tiles.empty();
    lists_.assign(static_cast<size_t>(workers_), {});
    shared_.clear();
    if (lists_mode_) {
      for (int w = 0; w < workers_; ++w) {
        const auto& mine = frame_->assignment.tiles[static_cast<size_t>(w)];
        lists_[static_cast<size_t>(w)].assign(mine.begin(), mine.end());
      }
    } else {
      shared_.assign(frame_->order.begin(), frame_->order.end());
    }
  }

  // The next tile for worker w (0-based), or -1 if none is waiting. *stolen: not from w's list.
  int NextTile(int w, bool* stolen) {
    *stolen = false;
    if (!lists_mode_) {  // fixed tiles or assign counter: one shared order
      if (shared_.empty()) return -1;
      const int t = shared_.front();
      shared_.pop_front();
      return t;
    }
    auto& own = lists_[static_cast<size_t>(w)];
    if (!own.empty()) {
      const int t = own.front();
      own.pop_front();
      return t;
    }
    int victim = -1;
    double most = -1;
    for (int v = 0; v < workers_; ++v) {
      double waiting = 0;
      for (int32_t t : lists_[static_cast<size_t>(v)]) {
        waiting += frame_->weight[static_cast<size_t>(t)];
      }
      if (!lists_[static_cast<size_t>(v)].empty() && waiting > most) {
        most = waiting;
        victim = v;
      }
    }
    if (victim < 0) return -1;
    auto& donor = lists_[static_cast<size_t>(victim)];
    const int t = donor.back();
    donor.pop_back();
    *stolen = true;
    return t;
  }

  void SendTile(int w, int frame, int t) {
    const Tile& tile = tiles_[static_cast<size_t>(t)];
    const int msg[kTileWords] = {frame, t, tile.x0, tile.y0, tile.x1, tile.y1};
    MasterSend(msg, kTileWords, w + 1, kTagTile, c_.timeout_seconds,
               fmt::format("tile {} of frame {}", t, frame),
               fmt::format("no image written for frame {}", frame));
    WorkerTraffic& traffic = traffic_[static_cast<size_t>(w)];
    ++traffic.msgs_sent;
    traffic.bytes_sent += sizeof(msg);
    in_flight_[static_cast<size_t>(w)].push_back(t);
    // The silence clock starts when the worker gets work after having none.
    if (in_flight_[static_cast<size_t>(w)].size() == 1) {
      last_heard_[static_cast<size_t>(w)] = Clock::now();
    }
  }

  // Tops up w's tiles in flight to c_.prefetch. PBT: prefetching takes only w's own tiles; a
  // tile of another worker's list is taken only when w has nothing left to render (so the
  // first round never strips a worker of its own tiles).
  void FeedWorker(int w, int frame, HostFrameStats& f) {
    auto& flight = in_flight_[static_cast<size_t>(w)];
    while (flight.size() < static_cast<size_t>(c_.prefetch)) {
      if (lists_mode_ && !flight.empty() && lists_[static_cast<size_t>(w)].empty()) return;
      bool stolen = false;
      const int t = NextTile(w, &stolen);
      if (t < 0) return;
      if (stolen) ++f.threads[static_cast<size_t>(w)].steals;
      SendTile(w, frame, t);
    }
  }

  // Renders one frame into fb_ and appends its statistics to frames_ (and the cluster's fields
  // to frame_extra_, worker_extra_). Aborts the run on a silent worker or a malformed result.
  void RenderFrame(int frame) {
    const auto begin = Clock::now();
    const double cpu0 = ThreadCpuSeconds();
    PlanFrame();
    fb_.Clear();
    const size_t m = tiles_.size();
    HostFrameStats& f = frames_.emplace_back();
    f.frame = static_cast<uint64_t>(frame);
    f.backend = BackendKind::kTiles;
    f.threads.assign(static_cast<size_t>(workers_), ThreadStats{});
    f.tiles.assign(m, TileRecord{});
    for (size_t i = 0; i < m; ++i) {
      f.tiles[i].tile = tiles_[i];
      f.tiles[i].predicted = frame_->predicted[i];
      if (lists_mode_) f.tiles[i].worker = frame_->owner[i];
    }
    std::vector<char> done(m, 0);
    traffic_.assign(static_cast<size_t>(workers_), WorkerTraffic{});
    in_flight_.assign(static_cast<size_t>(workers_), {});
    last_heard_.assign(static_cast<size_t>(workers_), Clock::now());
    uint64_t nan = 0, clamped = 0;
    const auto t0 = Clock::now();
    for (int w = 0; w < workers_; ++w) FeedWorker(w, frame, f);
    size_t received = 0;
    std::vector<int64_t> buf;
    const size_t width = static_cast<size_t>(c_.options.width);
    int polls_idle = 0;
    while (received < m) {
      // Deadlines on every pass, not only when nothing arrives: results from the other workers
      // must not postpone noticing a silent one.
      const auto now = Clock::now();
      for (int w = 0; w < workers_; ++w) {
        if (in_flight_[static_cast<size_t>(w)].empty()) continue;
        const double silent = Seconds(now - last_heard_[static_cast<size_t>(w)]);
        if (silent > c_.timeout_seconds) {
          Abort(0, fmt::format("worker rank {} did not return tile {} of frame {} within {:g} s "
                               "(dead or hung); aborting the run, no image written for "
                               "frame {}",
                               w + 1, in_flight_[static_cast<size_t>(w)].front(), frame,
                               c_.timeout_seconds, frame));
        }
      }
      int flag = 0;
      MPI_Message message;
      MPI_Status status;
      MPI_Improbe(MPI_ANY_SOURCE, kTagResult, MPI_COMM_WORLD, &flag, &message, &status);
      if (!flag) {
        PollSleep(polls_idle++);
        continue;
      }
      polls_idle = 0;
      const int src = status.MPI_SOURCE;
      const int w = src - 1;
      int count = 0;
      MPI_Get_count(&status, MPI_INT64_T, &count);
      if (w < 0 || w >= workers_ || count < kHeader) {
        Abort(0, fmt::format("malformed result from rank {} ({} words)", src, count));
      }
      // The matched message's data may still have to come (MPI's rendezvous protocol for large
      // messages needs the sender's progress): receive it without blocking, within the bound.
      buf.resize(static_cast<size_t>(count));
      MPI_Request request;
      MPI_Imrecv(buf.data(), count, MPI_INT64_T, &message, &request);
      if (!TestUntil(request, Deadline(c_.timeout_seconds))) {
        Abort(0, fmt::format("worker rank {} stopped while sending a result of frame {} ({} "
                             "bytes, not received within {:g} s: hung or stalled); aborting the "
                             "run, no image written for frame {}",
                             src, frame, int64_t{count} * 8, c_.timeout_seconds, frame));
      }
      const int64_t rf = buf[kResFrameTile] >> 32, t = buf[kResFrameTile] & 0xFFFFFFFF;
      auto& flight = in_flight_[static_cast<size_t>(w)];
      if (rf != frame || t < 0 || static_cast<size_t>(t) >= m || flight.empty() ||
          flight.front() != t || done[static_cast<size_t>(t)]) {
        Abort(0, fmt::format("unexpected result from rank {}: frame {} tile {} (expected frame "
                             "{} tile {})",
                             src, rf, t, frame, flight.empty() ? -1 : flight.front()));
      }
      const Tile& tile = tiles_[static_cast<size_t>(t)];
      if (static_cast<size_t>(count) != kHeader + 3 * tile.NumPixels()) {
        Abort(0, fmt::format("result of tile {} from rank {} has {} words, expected {}", t, src,
                             count, kHeader + 3 * tile.NumPixels()));
      }
      flight.pop_front();
      last_heard_[static_cast<size_t>(w)] = Clock::now();
      done[static_cast<size_t>(t)] = 1;
      ++received;
      // Exact merge: the tile's sums are added (not copied), like Framebuffer::Accumulate.
      const int64_t* src_sums = buf.data() + kHeader;
      int64_t* sums = fb_.sums();
      const size_t tw = static_cast<size_t>(tile.Width());
      for (int y = tile.y0; y < tile.y1; ++y) {
        int64_t* row = sums + 3 * (y * width + tile.x0);
        for (size_t i = 0; i < 3 * tw; ++i) row[i] += src_sums[i];
        src_sums += 3 * tw;
      }
      const FrameStats work = UnpackTileStats(buf.data());
      TileRecord& rec = f.tiles[static_cast<size_t>(t)];
      rec.thread = w;
      if (!lists_mode_) rec.worker = w;
      rec.seconds = std::bit_cast<double>(buf[kResSeconds]);
      rec.cpu_seconds = std::bit_cast<double>(buf[kResCpuSeconds]);
      rec.counts = TileWorkDelta(work, FrameStats{});
      rec.rays = rec.counts.rays;
      rec.work = TileWorkCost(rec.counts);
      nan += static_cast<uint64_t>(buf[kResDroppedNan]);
      clamped += static_cast<uint64_t>(buf[kResClamped]);
      ThreadStats& ts = f.threads[static_cast<size_t>(w)];
      ts.work.Merge(work);
      ++ts.tiles;
      ts.busy_seconds += rec.seconds;
      ts.cpu_seconds += rec.cpu_seconds;
      WorkerTraffic& traffic = traffic_[static_cast<size_t>(w)];
      ++traffic.msgs_recv;
      traffic.bytes_recv += static_cast<uint64_t>(count) * sizeof(int64_t);
      FeedWorker(w, frame, f);
    }
    FinishFrame(f, Seconds(Clock::now() - t0));
    f.total.total_seconds = Seconds(Clock::now() - begin);
    f.app_cpu_seconds = ThreadCpuSeconds() - cpu0;

    uint64_t msgs = 0, bytes = 0;
    std::vector<StatsFields> workers;
    for (int w = 0; w < workers_; ++w) {
      const WorkerTraffic& traffic = traffic_[static_cast<size_t>(w)];
      msgs += traffic.msgs_sent + traffic.msgs_recv;
      bytes += traffic.bytes_sent + traffic.bytes_recv;
      workers.push_back({{"rank", int64_t{w} + 1},
                         {"messages_sent", traffic.msgs_sent},
                         {"bytes_sent", traffic.bytes_sent},
                         {"messages_received", traffic.msgs_recv},
                         {"bytes_received", traffic.bytes_recv}});
    }
    frame_extra_.push_back(
        {{"messages", msgs}, {"bytes", bytes}, {"dropped_nan", nan}, {"clamped", clamped}});
    worker_extra_.push_back(std::move(workers));
  }

  // After the last result: totals, idle times and imbalance as the host backends define them
  // (a worker idles for the part of the render span it was not rendering), then the tile
  // plan's measures and PBT-Update on the measured tile costs (tile_plan.h).
  void FinishFrame(HostFrameStats& f, double render_seconds) {
    f.render_seconds = render_seconds;
    std::vector<double> busy;
    for (ThreadStats& t : f.threads) {
      t.idle_seconds = std::max(0.0, render_seconds - t.busy_seconds);
      f.total.Merge(t.work);
      busy.push_back(t.busy_seconds);
    }
    f.imbalance = FrameImbalance(busy);
    std::vector<double> costs(f.tiles.size());
    std::vector<int32_t> ran_by(f.tiles.size());
    for (size_t i = 0; i < f.tiles.size(); ++i) {
      const TileRecord& r = f.tiles[i];
      costs[i] = TileCost(r, c_.pbt_cost);
      ran_by[i] = r.thread;
    }
    const TilePlanReport report = plan_->End(costs, ran_by);  // PBT-Update between frames
    frame_ = nullptr;
    if (!report.pbt) return;
    ApplyPlanReport(report, f);
  }

  const MpiRenderConfig& c_;
  const Setup& s_;
  int workers_;
  Framebuffer fb_;
  std::vector<float> rgb_;
  std::unique_ptr<TilePlan> plan_;
  const TilePlanFrame* frame_ = nullptr;  // the plan's frame being rendered
  std::vector<Tile> tiles_;
  bool lists_mode_ = false;                 // PBT per-worker lists (else: shared_)
  std::vector<std::deque<int32_t>> lists_;  // per worker: its waiting tiles
  std::deque<int32_t> shared_;              // fixed tiles / assign counter: waiting tiles
  std::vector<WorkerTraffic> traffic_;
  std::vector<std::deque<int32_t>> in_flight_;
  std::vector<Clock::time_point> last_heard_;
  // Per frame: the statistics and the cluster's fields (WriteStats).
  std::vector<HostFrameStats> frames_;
  std::vector<StatsFields> frame_extra_;
  std::vector<std::vector<StatsFields>> worker_extra_;
};

// The master's bounded wait for every worker's setup (scene loaded, grid built): returns the
// lowest failing rank (`ranks` if none; `first` is the master's own: 0 or `ranks`) after sending
// it to every worker. A worker that reports nothing within the timeout (hung while loading or
// building) ends the run with an error naming it; an invalid timeout, which every rank rejects
// at once, waits the default 120 s at most.
int GatherSetup(const MpiRenderConfig& c, int ranks, int first) {
  const double timeout =
      c.timeout_seconds > 0 && c.timeout_seconds <= 1e6 ? c.timeout_seconds : 120.0;
  const size_t workers = static_cast<size_t>(ranks - 1);
  std::vector<int> failed(workers, 0);
  std::vector<MPI_Request> requests(workers);
  for (size_t w = 0; w < workers; ++w) {
    MPI_Irecv(&failed[w], 1, MPI_INT, static_cast<int>(w) + 1, kTagSetup, MPI_COMM_WORLD,
              &requests[w]);
  }
  const auto deadline = Deadline(timeout);
  for (int polls = 0;; ++polls) {
    std::vector<int> silent;
    for (size_t w = 0; w < workers; ++w) {
      int done = 0;
      if (requests[w] != MPI_REQUEST_NULL) MPI_Test(&requests[w], &done, MPI_STATUS_IGNORE);
      if (requests[w] != MPI_REQUEST_NULL) silent.push_back(static_cast<int>(w) + 1);
    }
    if (silent.empty()) break;
    if (Clock::now() > deadline) {
      Abort(0, fmt::format("worker {} did not finish its setup (loading the scene {}, building "
                           "its grid) within {:g} s (hung or dead); aborting the run, no image "
                           "written",
                           RankList(silent), c.scene, timeout));
    }
    PollSleep(polls);
  }
  for (size_t w = 0; w < workers && first == ranks; ++w) {
    if (failed[w] != 0) first = static_cast<int>(w) + 1;
  }
  for (int r = 1; r < ranks; ++r) {
    MasterSend(&first, 1, r, kTagSetupDone, timeout, "the setup outcome", "no image written");
  }
  return first;
}

}  // namespace

int RunMpiRender(const MpiRenderConfig& config) {
  int initialized = 0;
  MPI_Initialized(&initialized);
  if (!initialized) MPI_Init(nullptr, nullptr);
  int rank = 0, ranks = 1;
  MPI_Comm_rank(MPI_COMM_WORLD, &rank);
  MPI_Comm_size(MPI_COMM_WORLD, &ranks);

  // Setup on every rank; errors are gathered so that one line is printed (by rank 0, or by the
  // lowest failing rank when rank 0 succeeded) and every rank leaves cleanly with status 1.
  Setup setup;
  std::string error;
  try {
    if (rank > 0 && rank == EnvRank("RAYSTREAM_MPI_TEST_HANG_SETUP_RANK")) {
      HangForever(rank, "while loading the scene");
    }
    ValidateConfig(config, ranks);
    setup.scene = LoadScene(config.scene);
    if (rank > 0) {
      BuildOptions build;
      if (config.lambda > 0) build.lambda = config.lambda;
      setup.accel = std::make_unique<Accel>(setup.scene.mesh(), build);
    }
  } catch (const std::exception& e) {
    error = e.what();
  }
  int first_failed = ranks;  // the lowest failing rank, `ranks` if none
  if (rank == 0) {
    first_failed = GatherSetup(config, ranks, error.empty() ? ranks : 0);
  } else {
    const int failed = error.empty() ? 0 : 1;
    MPI_Send(&failed, 1, MPI_INT, 0, kTagSetup, MPI_COMM_WORLD);
    MPI_Recv(&first_failed, 1, MPI_INT, 0, kTagSetupDone, MPI_COMM_WORLD, MPI_STATUS_IGNORE);
  }
  if (first_failed < ranks) {
    if (rank == first_failed) {
      if (rank == 0) {
        fmt::print(stderr, "raystream: error: {}\n", error);
      } else {
        fmt::print(stderr, "raystream: error: mpi rank {}: {}\n", rank, error);
      }
    }
    MPI_Finalize();
    return 1;
  }

  try {
    if (rank == 0) {
      Master master(config, setup, ranks);
      master.Run();
    } else {
      RunWorker(config, setup, rank);
    }
  } catch (const std::exception& e) {
    Abort(rank, e.what());
  }
  MPI_Finalize();
  return 0;
}

}  // namespace rs
