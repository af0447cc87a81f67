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
//                                   shade seconds) + the tile's fixed-point sums; with PBT's
//                                   cost map (UsesCostMap of the plan's options, which every
//                                   rank derives from its BackendConfig) then the cost map's
//                                   record of the tile (TileRecordWords): the block work of the
//                                   cost blocks the tile overlaps (row-major) and the tile's
//                                   primary hit distances (row-major floats, two per word)
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
#include <limits>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "include/raystream/raystream.h"
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

// The master's tile plan options (a worker derives from them whether and in which blocks it
// records the cost map: every rank has the same BackendConfig).
TilePlanOptions PlanOptions(const BackendConfig& c, int workers) {
  TilePlanOptions p;
  p.tile_width = c.host.tile_width;
  p.tile_height = c.host.tile_height;
  p.pbt_tiles_per_worker = c.host.pbt_tiles_per_worker;
  p.workers = workers;
  p.assign = c.host.assign;
  p.seed = c.host.seed;
  p.steal = c.host.pbt_tiles_per_worker > 0 && c.host.assign != PbtAssign::kCounter;  // lists
  p.cost = c.host.pbt_cost;
  p.predict = c.host.pbt_predict;
  p.cost_block = c.host.pbt_cost_block;
  return p;
}

// The cost-map blocks a tile overlaps: [bx0, bx1) x [by0, by1) of blocks of `block` pixels.
struct BlockRect {
  int bx0, by0, bx1, by1;
  size_t NumBlocks() const {
    return static_cast<size_t>(bx1 - bx0) * static_cast<size_t>(by1 - by0);
  }
};
BlockRect BlocksOf(const Tile& tile, int block) {
  return BlockRect{tile.x0 / block, tile.y0 / block, (tile.x1 - 1) / block + 1,
                   (tile.y1 - 1) / block + 1};
}

// Words of a result after the sums for the cost map's record of `tile` (block 0: none): a word
// per overlapped block, then the tile's hit distances, two floats a word.
size_t TileRecordWords(const Tile& tile, int block) {
  if (block == 0) return 0;
  return BlocksOf(tile, block).NumBlocks() + (static_cast<size_t>(tile.NumPixels()) + 1) / 2;
}

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

void ValidateConfig(const BackendConfig& c, int ranks) {
  if (ranks < 2) {
    throw Error(
        fmt::format("--backend mpi needs at least 2 ranks (a master and a worker), got {}; "
                    "run it as `mpirun -np N raystream render --backend mpi ...`",
                    ranks));
  }
  ValidateRenderOptions(c.render);
  const BackendOptions& h = c.host;
  if (h.tile_width < 1 || h.tile_height < 1) {
    throw Error(fmt::format("--tile {}x{}: must be at least 1x1", h.tile_width, h.tile_height));
  }
  if (h.pbt_tiles_per_worker < 0 || h.pbt_tiles_per_worker > 4096) {
    throw Error(fmt::format("--pbt {}: must be in [0, 4096]", h.pbt_tiles_per_worker));
  }
  if (h.threads < 1 || h.threads > 256) {
    throw Error(fmt::format("--threads {}: render threads per worker must be in [1, 256]",
                            h.threads));
  }
  if (c.mpi_prefetch < 1 || c.mpi_prefetch > 64) {
    throw Error(fmt::format("mpi prefetch {}: must be in [1, 64]", c.mpi_prefetch));
  }
  if (!(c.mpi_timeout_seconds > 0) || c.mpi_timeout_seconds > 1e6) {
    throw Error(
        fmt::format("--mpi-timeout {}: must be in (0, 1e6] seconds", c.mpi_timeout_seconds));
  }
  if (h.pbt_tiles_per_worker > 0) {
    const double m = double(h.pbt_tiles_per_worker) * (ranks - 1);
    if (m > double(c.render.width) * c.render.height) {
      throw Error(fmt::format("--pbt {}: {} tiles for {} workers exceed the {}x{} pixels",
                              h.pbt_tiles_per_worker, m, ranks - 1, c.render.width,
                              c.render.height));
    }
  }
  const int cost = static_cast<int>(h.pbt_cost);
  if (cost < 0 || cost > static_cast<int>(PbtCost::kWork)) {
    throw Error(fmt::format("--pbt-cost {}: unknown", cost));
  }
  if (h.pbt_cost != PbtCost::kWall && h.pbt_tiles_per_worker == 0) {
    throw Error(
        fmt::format("--pbt-cost {}: needs a PBT tiling (--pbt k)", PbtCostName(h.pbt_cost)));
  }
  const int assign = static_cast<int>(h.assign);
  if (assign < 0 || assign > static_cast<int>(PbtAssign::kLpt)) {
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

  // PBT's cost map (sched/cost_map.h): every render thread's engine charges its own BlockWork
  // of a width x height image in block x block blocks, and stores the primaries' hit distances
  // into one array (one writer per pixel). Sized once per layout; block 0: no record.
  void SetRecord(int width, int height, int block) {
    if (block == 0) {
      for (SerialRenderer& r : renderers_) r.engine().SetBlockWork(nullptr);
      return;
    }
    if (sinks_.size() == renderers_.size() && sinks_[0].Matches(width, height, block)) return;
    sinks_.assign(renderers_.size(), BlockWork{});
    depth_.assign(static_cast<size_t>(width) * static_cast<size_t>(height),
                  std::numeric_limits<float>::quiet_NaN());
    for (size_t t = 0; t < renderers_.size(); ++t) {
      sinks_[t].Resize(width, height, block);
      sinks_[t].pixel_depth = depth_.data();
      renderers_[t].engine().SetBlockWork(&sinks_[t]);
    }
  }

  // After Render of `tile` with a record: its blocks' work summed over the threads (and zeroed
  // for the next tile; a tile's rays charge only the blocks of its own pixels) and its pixels'
  // hit distances, into dst (TileRecordWords(tile, block) words).
  void TakeRecord(const Tile& tile, int64_t* dst) {
    const BlockWork& first = sinks_[0];
    const BlockRect r = BlocksOf(tile, first.block);
    for (int by = r.by0; by < r.by1; ++by) {
      for (int bx = r.bx0; bx < r.bx1; ++bx) {
        const size_t b =
            static_cast<size_t>(by) * static_cast<size_t>(first.blocks_x) + static_cast<size_t>(bx);
        int64_t sum = 0;
        for (BlockWork& s : sinks_) {
          sum += s.work[b];
          s.work[b] = 0;
        }
        *dst++ = sum;
      }
    }
    const size_t w = static_cast<size_t>(first.width), tw = static_cast<size_t>(tile.Width());
    char* bytes = reinterpret_cast<char*>(dst);
    for (int y = tile.y0; y < tile.y1; ++y) {
      std::memcpy(bytes, depth_.data() + static_cast<size_t>(y) * w + static_cast<size_t>(tile.x0),
                  tw * sizeof(float));
      bytes += tw * sizeof(float);
    }
    if (tile.NumPixels() % 2 != 0) std::memset(bytes, 0, sizeof(float));  // the last word's pad
  }

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
  std::vector<BlockWork> sinks_;           // cost map: one per render thread
  std::vector<float> depth_;               // cost map: per pixel, the primary hit distance
};

// A worker rank: serves the master's tiles one frame at a time. A frame ends when the next
// message is not one of its tiles (a tile of the next frame, kept for it, or the stop message,
// kept for Finish): the master sends frame f + 1 only after every result of frame f.
class Worker {
 public:
  Worker(const BackendConfig& c, int rank)
      : c_(c),
        rank_(rank),
        kill_rank_(EnvRank("RAYSTREAM_MPI_TEST_KILL_RANK")),
        hang_rank_(EnvRank("RAYSTREAM_MPI_TEST_HANG_RANK")),
        hang_end_rank_(EnvRank("RAYSTREAM_MPI_TEST_HANG_END_RANK")),
        stall_rank_(EnvRank("RAYSTREAM_MPI_TEST_STALL_RANK")),
        renderer_(c.host.threads) {
    int ranks = 0;
    MPI_Comm_size(MPI_COMM_WORLD, &ranks);
    const TilePlanOptions plan = PlanOptions(c, ranks - 1);
    record_block_ = UsesCostMap(plan) ? plan.cost_block : 0;
  }

  void ServeFrame(const FrameContext& ctx, int frame) {
    const int w = ctx.options.width, h = ctx.options.height;
    if (!fb_ || fb_->width() != w || fb_->height() != h) fb_ = std::make_unique<Framebuffer>(w, h);
    renderer_.SetRecord(w, h, record_block_);
    for (;;) {
      Receive();
      if (tag_ == kTagStop) return;  // for Finish
      if (tag_ != kTagTile) Abort(rank_, fmt::format("unexpected tag {}", tag_));
      if (msg_[0] == frame + 1) return;  // the next frame's first tile
      const Tile tile{msg_[2], msg_[3], msg_[4], msg_[5]};
      if (msg_[0] != frame || msg_[1] < 0 || tile.x0 < 0 || tile.y0 < 0 || tile.x1 > w ||
          tile.y1 > h || tile.NumPixels() == 0) {
        Abort(rank_, fmt::format("malformed tile message (frame {} in frame {}, tile {})",
                                 msg_[0], frame, msg_[1]));
      }
      pending_ = false;
      RenderTile(ctx, frame, msg_[1], tile);
    }
  }

  // After the last frame: the stop message, then the goodbye (the master writes the last image
  // once every worker has said it).
  void Finish() {
    Receive();
    if (tag_ != kTagStop) {
      Abort(rank_, fmt::format("expected the end of the run, got tag {} (frame {})", tag_,
                               msg_[0]));
    }
    if (rank_ == hang_end_rank_) HangForever(rank_, "after its last tile (never says goodbye)");
    const int bye = 0;
    MPI_Send(&bye, 1, MPI_INT, 0, kTagBye, MPI_COMM_WORLD);
  }

 private:
  // The next message from the master into msg_ / tag_, unless one is kept already.
  void Receive() {
    if (pending_) return;
    MPI_Status status;
    std::fill(std::begin(msg_), std::end(msg_), 0);
    MPI_Recv(msg_, kTileWords, MPI_INT, 0, MPI_ANY_TAG, MPI_COMM_WORLD, &status);
    tag_ = status.MPI_TAG;
    pending_ = true;
  }

  // Zero the tile's pixels, render (a ray's contributions stay on its own pixel, so the whole
  // tree of the tile lands inside it), then ship the tile's sums.
  void RenderTile(const FrameContext& ctx, int frame, int index, const Tile& tile) {
    Framebuffer& fb = *fb_;
    const size_t w = static_cast<size_t>(ctx.options.width);
    int64_t* sums = fb.sums();
    for (int y = tile.y0; y < tile.y1; ++y) {
      std::fill(sums + 3 * (y * w + tile.x0), sums + 3 * (y * w + tile.x1), int64_t{0});
    }
    const uint64_t nan0 = fb.dropped_nan(), clamped0 = fb.clamped();
    FrameStats stats;
    const auto t0 = Clock::now();
    const double cpu = renderer_.Render(ctx, tile, fb, stats);
    const double seconds = Seconds(Clock::now() - t0);
    const size_t tw = static_cast<size_t>(tile.Width());
    const size_t sums_words = kHeader + 3 * static_cast<size_t>(tile.NumPixels());
    result_.resize(sums_words + TileRecordWords(tile, record_block_));
    result_[kResFrameTile] = (int64_t{frame} << 32) | static_cast<int64_t>(index);
    result_[kResSeconds] = std::bit_cast<int64_t>(seconds);
    result_[kResCpuSeconds] = std::bit_cast<int64_t>(cpu);
    result_[kResDroppedNan] = static_cast<int64_t>(fb.dropped_nan() - nan0);
    result_[kResClamped] = static_cast<int64_t>(fb.clamped() - clamped0);
    PackTileStats(stats, result_.data());
    int64_t* dst = result_.data() + kHeader;
    for (int y = tile.y0; y < tile.y1; ++y) {
      std::memcpy(dst, sums + 3 * (y * w + tile.x0), 3 * tw * sizeof(int64_t));
      dst += 3 * tw;
    }
    if (record_block_ > 0) renderer_.TakeRecord(tile, result_.data() + sums_words);
    if (tiles_done_ == 0 && rank_ == stall_rank_) {
      // Test hook: start sending the first result, then never make MPI progress again. The
      // result is larger than the eager limit, so the master matches it but cannot receive it.
      MPI_Request request;
      MPI_Isend(result_.data(), static_cast<int>(result_.size()), MPI_INT64_T, 0, kTagResult,
                MPI_COMM_WORLD, &request);
      HangForever(rank_, "in the middle of sending its first result");
    }
    MPI_Send(result_.data(), static_cast<int>(result_.size()), MPI_INT64_T, 0, kTagResult,
             MPI_COMM_WORLD);
    ++tiles_done_;
    if (tiles_done_ == 1 && rank_ == kill_rank_) {
      fmt::print(stderr, "raystream: test hook: rank {} exits after its first tile\n", rank_);
      std::fflush(stderr);
      _exit(1);
    }
    if (tiles_done_ == 1 && rank_ == hang_rank_) HangForever(rank_, "after its first tile");
  }

  const BackendConfig& c_;
  int rank_;
  int kill_rank_, hang_rank_, hang_end_rank_, stall_rank_;
  TileRenderer renderer_;  // one tile's whole ray tree on this rank
  int record_block_ = 0;   // PBT's cost map: its block size (0: no record)
  std::unique_ptr<Framebuffer> fb_;
  std::vector<int64_t> result_;
  uint64_t tiles_done_ = 0;
  bool pending_ = false;  // msg_ / tag_ hold a message not acted on yet
  int msg_[kTileWords] = {};
  int tag_ = 0;
};

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
  Master(const BackendConfig& c, int ranks)
      : c_(c), workers_(ranks - 1), fb_(c.render.width, c.render.height) {
    plan_ = std::make_unique<TilePlan>(c.render.width, c.render.height, PlanOptions(c, workers_));
    if (plan_->uses_cost_map()) {
      record_block_ = plan_->options().cost_block;
      record_.Resize(c.render.width, c.render.height, record_block_);
      depth_.assign(static_cast<size_t>(c.render.width) * static_cast<size_t>(c.render.height),
                    std::numeric_limits<float>::quiet_NaN());
    }
  }

  const Framebuffer& image() const { return fb_; }
  const FrameReport& report() const { return report_; }
  bool uses_lists() const { return plan_->options().steal; }
  // What the last frame gave the plan's cost map (empty without one).
  const TilePlanMeasure& cost_map_measure() const { return measure_; }

  // After the last frame: stop every worker and wait (bounded) for each one's goodbye, so that
  // MPI_Finalize cannot hang on a worker that stopped after its last tile, and a run that fails
  // here writes neither the last image nor the statistics.
  void EndRun() {
    const std::string unwritten = "the last frame's image and the statistics are not written";
    const int stop = 0;
    for (int r = 1; r <= workers_; ++r) {
      MasterSend(&stop, 1, r, kTagStop, c_.mpi_timeout_seconds, "the end-of-run message",
                 unwritten);
    }
    std::vector<int> bye(static_cast<size_t>(workers_), 0);
    std::vector<MPI_Request> requests(static_cast<size_t>(workers_));
    for (int w = 0; w < workers_; ++w) {
      MPI_Irecv(&bye[static_cast<size_t>(w)], 1, MPI_INT, w + 1, kTagBye, MPI_COMM_WORLD,
                &requests[static_cast<size_t>(w)]);
    }
    const auto deadline = Deadline(c_.mpi_timeout_seconds);
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
                             RankList(silent), c_.mpi_timeout_seconds, unwritten));
      }
      PollSleep(polls);
    }
  }

  // Renders one frame into fb_ (cleared first); report() then holds its statistics and the
  // cluster's fields. Aborts the run on a silent worker or a malformed result.
  void RenderFrame(const FrameContext& ctx, int frame) { RenderFrameBody(ctx, frame); }

 private:
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
    MasterSend(msg, kTileWords, w + 1, kTagTile, c_.mpi_timeout_seconds,
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

  // Tops up w's tiles in flight to c_.mpi_prefetch. PBT: prefetching takes only w's own tiles; a
  // tile of another worker's list is taken only when w has nothing left to render (so the
  // first round never strips a worker of its own tiles).
  void FeedWorker(int w, int frame, HostFrameStats& f) {
    auto& flight = in_flight_[static_cast<size_t>(w)];
    while (flight.size() < static_cast<size_t>(c_.mpi_prefetch)) {
      if (lists_mode_ && !flight.empty() && lists_[static_cast<size_t>(w)].empty()) return;
      bool stolen = false;
      const int t = NextTile(w, &stolen);
      if (t < 0) return;
      if (stolen) ++f.threads[static_cast<size_t>(w)].steals;
      SendTile(w, frame, t);
    }
  }

  void RenderFrameBody(const FrameContext& ctx, int frame) {
    const auto begin = Clock::now();
    const double cpu0 = ThreadCpuSeconds();
    PlanFrame();
    fb_.Clear();
    measure_ = TilePlanMeasure{};
    if (record_block_ > 0) {  // every pixel is rewritten: the tiles cover the image
      record_.Clear();
      std::fill(depth_.begin(), depth_.end(), std::numeric_limits<float>::quiet_NaN());
    }
    const size_t m = tiles_.size();
    report_ = FrameReport{};
    HostFrameStats& f = report_.stats;
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
    const size_t width = static_cast<size_t>(c_.render.width);
    int polls_idle = 0;
    while (received < m) {
      // Deadlines on every pass, not only when nothing arrives: results from the other workers
      // must not postpone noticing a silent one.
      const auto now = Clock::now();
      for (int w = 0; w < workers_; ++w) {
        if (in_flight_[static_cast<size_t>(w)].empty()) continue;
        const double silent = Seconds(now - last_heard_[static_cast<size_t>(w)]);
        if (silent > c_.mpi_timeout_seconds) {
          Abort(0, fmt::format("worker rank {} did not return tile {} of frame {} within {:g} s "
                               "(dead or hung); aborting the run, no image written for "
                               "frame {}",
                               w + 1, in_flight_[static_cast<size_t>(w)].front(), frame,
                               c_.mpi_timeout_seconds, frame));
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
      if (!TestUntil(request, Deadline(c_.mpi_timeout_seconds))) {
        Abort(0, fmt::format("worker rank {} stopped while sending a result of frame {} ({} "
                             "bytes, not received within {:g} s: hung or stalled); aborting the "
                             "run, no image written for frame {}",
                             src, frame, int64_t{count} * 8, c_.mpi_timeout_seconds, frame));
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
      const size_t sums_words = kHeader + 3 * static_cast<size_t>(tile.NumPixels());
      const size_t words = sums_words + TileRecordWords(tile, record_block_);
      if (static_cast<size_t>(count) != words) {
        Abort(0, fmt::format("result of tile {} from rank {} has {} words, expected {}", t, src,
                             count, words));
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
      if (record_block_ > 0) AddRecord(tile, buf.data() + sums_words);
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
    if (record_block_ > 0) {
      measure_.blocks = &record_;
      measure_.pixel_depth = depth_;
      measure_.camera = &ctx.camera;
      measure_.next_camera = ctx.has_next_camera ? &ctx.next_camera : nullptr;
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
    report_.extra = {
        {"messages", msgs}, {"bytes", bytes}, {"dropped_nan", nan}, {"clamped", clamped}};
    report_.worker_extra = std::move(workers);
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
      costs[i] = TileCost(r, c_.host.pbt_cost);
      ran_by[i] = r.thread;
    }
    // PBT-Update between frames (the cost map from the workers' records, if any).
    const TilePlanReport report = plan_->End(costs, ran_by, measure_);
    frame_ = nullptr;
    if (!report.pbt) return;
    ApplyPlanReport(report, f);
  }

  // A tile's cost-map record (Worker, TileRenderer::TakeRecord) into the frame's: block work
  // added (integer sums: the same whichever worker rendered a tile and in which order the
  // results arrive; a block that several tiles overlap gets each tile's rays), hit distances
  // copied.
  void AddRecord(const Tile& tile, const int64_t* src) {
    const BlockRect r = BlocksOf(tile, record_block_);
    for (int by = r.by0; by < r.by1; ++by) {
      int64_t* row =
          record_.work.data() + static_cast<size_t>(by) * static_cast<size_t>(record_.blocks_x);
      for (int bx = r.bx0; bx < r.bx1; ++bx) row[bx] += *src++;
    }
    const size_t w = static_cast<size_t>(c_.render.width), tw = static_cast<size_t>(tile.Width());
    const char* bytes = reinterpret_cast<const char*>(src);
    for (int y = tile.y0; y < tile.y1; ++y) {
      std::memcpy(depth_.data() + static_cast<size_t>(y) * w + static_cast<size_t>(tile.x0), bytes,
                  tw * sizeof(float));
      bytes += tw * sizeof(float);
    }
  }

  const BackendConfig& c_;
  int workers_;
  Framebuffer fb_;
  std::unique_ptr<TilePlan> plan_;
  int record_block_ = 0;                  // PBT's cost map: its block size (0: none)
  BlockWork record_;                      // the frame's block work, the workers' records summed
  std::vector<float> depth_;              // the frame's primary hit distances
  TilePlanMeasure measure_;               // the last frame's, for plan_->End
  const TilePlanFrame* frame_ = nullptr;  // the plan's frame being rendered
  std::vector<Tile> tiles_;
  bool lists_mode_ = false;                 // PBT per-worker lists (else: shared_)
  std::vector<std::deque<int32_t>> lists_;  // per worker: its waiting tiles
  std::deque<int32_t> shared_;              // fixed tiles / assign counter: waiting tiles
  std::vector<WorkerTraffic> traffic_;
  std::vector<std::deque<int32_t>> in_flight_;
  std::vector<Clock::time_point> last_heard_;
  FrameReport report_;  // the last frame's
};

// The master's bounded wait for every worker's setup (scene loaded, grid built): returns the
// lowest failing rank (`ranks` if none; `first` is the master's own: 0 or `ranks`) after sending
// it to every worker. A worker that reports nothing within the timeout (hung while loading or
// building) ends the run with an error naming it; an invalid timeout, which every rank rejects
// at once, waits the default 120 s at most.
int GatherSetup(const BackendConfig& c, int ranks, int first) {
  const double timeout = c.mpi_timeout_seconds > 0 && c.mpi_timeout_seconds <= 1e6
                             ? c.mpi_timeout_seconds
                             : 120.0;
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

// The backend on one rank: the master (rank 0) or a worker.
class MpiBackend final : public Backend {
 public:
  explicit MpiBackend(const BackendConfig& c) : c_(c) {
    int initialized = 0;
    MPI_Initialized(&initialized);
    if (!initialized) MPI_Init(nullptr, nullptr);
    MPI_Comm_rank(MPI_COMM_WORLD, &rank_);
    MPI_Comm_size(MPI_COMM_WORLD, &ranks_);
    workers_ = std::max(ranks_ - 1, 0);
    options_.kind = BackendKind::kTiles;  // the same tiling, run by worker ranks
    options_.threads = workers_;
    options_.tile_width = c.host.tile_width;
    options_.tile_height = c.host.tile_height;
    options_.pbt_tiles_per_worker = c.host.pbt_tiles_per_worker;
    options_.pbt_workers = workers_;
    options_.pbt_steal = c.host.pbt_tiles_per_worker > 0 && c.host.assign != PbtAssign::kCounter;
    options_.assign = c.host.assign;
    options_.seed = c.host.seed;
    options_.pbt_cost = c.host.pbt_cost;
    options_.queue_stats = false;
  }

  // A run that ends before Finish (an exception in the command) cannot leave the other ranks
  // waiting: abort the job. Otherwise every rank agreed to stop (setup failed, or Finish done).
  ~MpiBackend() override {
    if (state_ == State::kRunning) {
      std::fflush(stderr);
      MPI_Abort(MPI_COMM_WORLD, 1);
    }
    int finalized = 0;
    MPI_Finalized(&finalized);
    if (!finalized) MPI_Finalize();
  }

  std::string_view name() const override { return "mpi"; }

  std::string Describe() const override {
    const BackendOptions& h = c_.host;
    return fmt::format("mpi, {} workers ({} thread(s) each), {}", workers_, h.threads,
                       h.pbt_tiles_per_worker > 0
                           ? fmt::format("PBT k={} assign {} cost {}", h.pbt_tiles_per_worker,
                                         PbtAssignName(h.assign), PbtCostName(h.pbt_cost))
                           : fmt::format("tiles {}x{}", h.tile_width, h.tile_height));
  }

  const BackendOptions& options() const override { return options_; }

  StatsFields StatsOptions() const override {
    return {{"ranks", int64_t{ranks_}},
            {"workers", int64_t{workers_}},
            {"worker_threads", int64_t{c_.host.threads}},
            {"prefetch", int64_t{c_.mpi_prefetch}},
            {"timeout_seconds", c_.mpi_timeout_seconds}};
  }

  // Setup on every rank; errors are gathered so that one line is printed (by rank 0, or by the
  // lowest failing rank when rank 0 succeeded) and every rank leaves cleanly with status 1.
  bool Setup(const std::function<void()>& setup) override {
    std::exception_ptr error;
    try {
      if (rank_ > 0 && rank_ == EnvRank("RAYSTREAM_MPI_TEST_HANG_SETUP_RANK")) {
        HangForever(rank_, "while loading the scene");
      }
      ValidateConfig(c_, ranks_);
      setup();
    } catch (...) {
      error = std::current_exception();
    }
    int first_failed = ranks_;  // the lowest failing rank, `ranks` if none
    if (rank_ == 0) {
      first_failed = GatherSetup(c_, ranks_, error ? 0 : ranks_);
    } else {
      const int failed = error ? 1 : 0;
      MPI_Send(&failed, 1, MPI_INT, 0, kTagSetup, MPI_COMM_WORLD);
      MPI_Recv(&first_failed, 1, MPI_INT, 0, kTagSetupDone, MPI_COMM_WORLD, MPI_STATUS_IGNORE);
    }
    if (first_failed < ranks_) {
      state_ = State::kStopped;
      if (rank_ != first_failed) return false;
      if (rank_ == 0) std::rethrow_exception(error);
      try {
        std::rethrow_exception(error);
      } catch (const std::exception& e) {
        throw Error(fmt::format("mpi rank {}: {}", rank_, e.what()));
      }
    }
    state_ = State::kRunning;
    if (rank_ == 0) {
      master_ = std::make_unique<Master>(c_, ranks_);
    } else {
      worker_ = std::make_unique<Worker>(c_, rank_);
    }
    return true;
  }

  // A failure inside a frame ends the job naming this rank (the others are waiting on it).
  void BeginFrame(const FrameContext& ctx) override {
    if (state_ != State::kRunning) throw Error("mpi backend: BeginFrame before a successful Setup");
    try {
      if (master_) {
        master_->RenderFrame(ctx, frame_);
      } else {
        worker_->ServeFrame(ctx, frame_);
      }
    } catch (const std::exception& e) {
      Abort(rank_, e.what());
    }
    ++frame_;
  }

  const FrameReport& EndFrame() override { return master_ ? master_->report() : empty_; }
  const Framebuffer* image() const override { return master_ ? &master_->image() : nullptr; }
  bool owns_image() const override { return rank_ == 0; }

  void Finish() override {
    if (state_ != State::kRunning) return;
    try {
      if (master_) {
        master_->EndRun();
      } else {
        worker_->Finish();
      }
    } catch (const std::exception& e) {
      Abort(rank_, e.what());
    }
    state_ = State::kStopped;
  }

 private:
  enum class State { kSetup, kRunning, kStopped };

  BackendConfig c_;
  int rank_ = 0, ranks_ = 1, workers_ = 0;
  BackendOptions options_;
  State state_ = State::kSetup;
  int frame_ = 0;
  std::unique_ptr<Master> master_;  // rank 0
  std::unique_ptr<Worker> worker_;  // ranks 1..N-1
  FrameReport empty_;               // a worker's report
};

}  // namespace

void RegisterMpiBackend(BackendRegistry& registry) {
  registry.Add("mpi", "master-worker over MPI ranks (under mpirun)",
               [](const BackendConfig& c) { return std::make_unique<MpiBackend>(c); });
}

}  // namespace rs
