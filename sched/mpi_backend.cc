// Cluster backend over MPI (Cosenza et al. §2-4): rank 0 is the master (tiling, PBT, framebuffer,
// images, statistics), ranks 1..N-1 load the scene themselves and render the tiles they are sent.

// Protocol (all point-to-point, MPI_COMM_WORLD):
//   master -> worker  kTagTile   int32[6] {frame, tile, x0, y0, x1, y1}
//   worker -> master  kTagResult int64[kHeader + 3 * pixels] {frame, tile, wall-time bits,
//                     cpu-time bits, rays, tasks, nan, clamped} + the tile's fixed-point sums
//   master -> worker  kTagStop   int32[1] (after the last frame)
// The master polls with MPI_Iprobe (sleeping between polls) and ends the run with MPI_Abort when
// a worker holding a tile stays silent for timeout_seconds.
#include <mpi.h>
#include <time.h>
#include <unistd.h>

#include <algorithm>
#include <bit>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <deque>
#include <exception>
#include <fstream>
#include <iterator>
#include <memory>
#include <ostream>
#include <string>
#include <string_view>
#include <thread>
#include <vector>

#include <fmt/core.h>
#include <nlohmann/json.hpp>

#include "include/raystream/raystream.h"
#include "scenes/image_io.h"
#include "scenes/load.h"
#include "sched/mpi_backend.h"
#include "sched/pbt.h"

namespace rs {
namespace {

using Json = nlohmann::ordered_json;
using Clock = std::chrono::steady_clock;

constexpr int kTagTile = 1;
constexpr int kTagResult = 2;
constexpr int kTagStop = 3;
constexpr int kHeader = 8;  // int64 words before the sums of a result
constexpr int kTileWords = 6;

double Seconds(Clock::duration d) { return std::chrono::duration<double>(d).count(); }

double CpuSeconds() {
  timespec ts{};
  if (clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts) != 0) return 0;
  return double(ts.tv_sec) + 1e-9 * double(ts.tv_nsec);
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

bool EndsWith(const std::string& s, const std::string& suffix) {
  return s.size() >= suffix.size() &&
         s.compare(s.size() - suffix.size(), suffix.size(), suffix) == 0;
}

// CSV statistics: the host backends' columns (sched/backends.cc WriteCsv) where they apply, then
// the cluster's own. Per frame: one row scope=frame (index -1), one row scope=worker per worker
// (index = worker, rank = index + 1), one row scope=tile per tile (index = tile). Columns that do
// not apply are empty.
constexpr const char* kCsvColumns[] = {
    // The host backends' columns, in their order.
    "frame", "scope", "index", "thread", "worker", "seconds", "busy_seconds", "idle_seconds",
    "queue_seconds", "queue_ops", "empty_polls", "tasks", "tiles", "rays", "primary", "shadow",
    "reflection", "refraction", "x0", "y0", "x1", "y1", "cpu_seconds", "predicted_seconds",
    "imbalance", "worker_imbalance", "within5", "within10", "within15",
    // The cluster's own.
    "rank", "steals", "messages", "bytes", "messages_sent", "bytes_sent", "messages_received",
    "bytes_received"};
constexpr size_t kNumCsvColumns = std::size(kCsvColumns);

class CsvRow {
 public:
  // Sets column `name` (one of kCsvColumns) from a JSON number or string.
  CsvRow& Set(std::string_view name, const Json& value) {
    for (size_t c = 0; c < kNumCsvColumns; ++c) {
      if (name == kCsvColumns[c]) {
        cells_[c] = value.is_string() ? value.get<std::string>() : value.dump();
        return *this;
      }
    }
    throw Error(fmt::format("internal: no CSV column '{}'", name));
  }
  void Write(std::ostream& out) const {
    for (size_t c = 0; c < kNumCsvColumns; ++c) out << (c ? "," : "") << cells_[c];
    out << "\n";
  }

 private:
  std::string cells_[kNumCsvColumns];
};

// Writes the frames' statistics (the JSON objects Master::FrameJson made) as CSV rows.
void WriteStatsCsv(std::ostream& out, const Json& frames) {
  for (size_t c = 0; c < kNumCsvColumns; ++c) out << (c ? "," : "") << kCsvColumns[c];
  out << "\n";
  for (const Json& f : frames) {
    const Json& frame = f["frame"];
    CsvRow row;
    row.Set("frame", frame).Set("scope", "frame").Set("index", -1).Set("seconds", f["seconds"]);
    row.Set("busy_seconds", f["busy_seconds"]).Set("idle_seconds", f["idle_seconds"]);
    row.Set("tiles", f["tiles_count"]).Set("rays", f["rays"]).Set("imbalance", f["imbalance"]);
    row.Set("messages", f["messages"]).Set("bytes", f["bytes"]);
    if (f.contains("accuracy")) {
      for (const char* k : {"within5", "within10", "within15"}) row.Set(k, f["accuracy"][k]);
    }
    row.Write(out);
    for (const Json& w : f["workers"]) {
      CsvRow r;
      r.Set("frame", frame).Set("scope", "worker").Set("index", w["rank"].get<int>() - 1);
      r.Set("worker", w["rank"].get<int>() - 1).Set("rank", w["rank"]);
      r.Set("busy_seconds", w["busy_seconds"]).Set("idle_seconds", w["idle_seconds"]);
      r.Set("cpu_seconds", w["cpu_seconds"]).Set("tiles", w["tiles"]).Set("steals", w["steals"]);
      r.Set("rays", w["rays"]).Set("messages_sent", w["messages_sent"]);
      r.Set("bytes_sent", w["bytes_sent"]).Set("messages_received", w["messages_received"]);
      r.Set("bytes_received", w["bytes_received"]);
      r.Set("messages",
            w["messages_sent"].get<uint64_t>() + w["messages_received"].get<uint64_t>());
      r.Set("bytes", w["bytes_sent"].get<uint64_t>() + w["bytes_received"].get<uint64_t>());
      r.Write(out);
    }
    size_t i = 0;
    for (const Json& t : f["tiles"]) {
      CsvRow r;
      r.Set("frame", frame).Set("scope", "tile").Set("index", i++);
      r.Set("worker", t["rank"].get<int>() - 1).Set("rank", t["rank"]);
      r.Set("seconds", t["seconds"]).Set("cpu_seconds", t["cpu_seconds"]);
      r.Set("rays", t["rays"]).Set("tasks", t["tasks"]);
      for (const char* k : {"x0", "y0", "x1", "y1"}) r.Set(k, t[k]);
      if (t["predicted"].get<double>() >= 0) r.Set("predicted_seconds", t["predicted"]);
      r.Write(out);
    }
  }
}

// What every rank builds before rendering. Workers own an Accel; the master only the scene.
struct Setup {
  Scene scene;
  std::unique_ptr<Accel> accel;
};

void ValidateConfig(const MpiRenderConfig& c, int ranks) {
  if (ranks < 2) {
    throw Error(fmt::format("--backend mpi needs at least 2 ranks (a master and a worker), got {}; "
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
  if (c.prefetch < 1 || c.prefetch > 64) {
    throw Error(fmt::format("mpi prefetch {}: must be in [1, 64]", c.prefetch));
  }
  if (!(c.timeout_seconds > 0) || c.timeout_seconds > 1e6) {
    throw Error(fmt::format("--mpi-timeout {}: must be in (0, 1e6] seconds", c.timeout_seconds));
  }
  if (!c.stats.empty() && !EndsWith(c.stats, ".json") && !EndsWith(c.stats, ".csv")) {
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
}

// ------------------------------------------------------------------------------------------------
// Worker.

void RunWorker(const MpiRenderConfig& c, const Setup& s, int rank) {
  const int kill_rank = EnvRank("RAYSTREAM_MPI_TEST_KILL_RANK");
  const int hang_rank = EnvRank("RAYSTREAM_MPI_TEST_HANG_RANK");
  Framebuffer fb(c.options.width, c.options.height);
  SerialRenderer renderer;  // one tile's whole ray tree on this rank
  std::vector<int64_t> result;
  int ctx_frame = -1;
  FrameContext ctx;
  uint64_t tiles_done = 0;
  for (;;) {
    MPI_Status status;
    int msg[kTileWords] = {};
    MPI_Recv(msg, kTileWords, MPI_INT, 0, MPI_ANY_TAG, MPI_COMM_WORLD, &status);
    if (status.MPI_TAG == kTagStop) return;
    if (status.MPI_TAG != kTagTile) Abort(rank, fmt::format("unexpected tag {}", status.MPI_TAG));
    const int frame = msg[0];
    const Tile tile{msg[2], msg[3], msg[4], msg[5]};
    if (frame < 0 || frame >= c.frames || tile.x0 < 0 || tile.y0 < 0 ||
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
    const double cpu0 = CpuSeconds();
    const auto t0 = Clock::now();
    renderer.RenderTiles(ctx, &tile, 1, fb, stats);
    const double seconds = Seconds(Clock::now() - t0);
    const double cpu = CpuSeconds() - cpu0;
    const size_t tw = static_cast<size_t>(tile.Width());
    result.resize(kHeader + 3 * tile.NumPixels());
    result[0] = frame;
    result[1] = msg[1];
    result[2] = std::bit_cast<int64_t>(seconds);
    result[3] = std::bit_cast<int64_t>(cpu);
    result[4] = static_cast<int64_t>(stats.TotalRays());
    result[5] = static_cast<int64_t>(stats.tasks);
    result[6] = static_cast<int64_t>(fb.dropped_nan() - nan0);
    result[7] = static_cast<int64_t>(fb.clamped() - clamped0);
    int64_t* dst = result.data() + kHeader;
    for (int y = tile.y0; y < tile.y1; ++y) {
      std::memcpy(dst, sums + 3 * (y * w + tile.x0), 3 * tw * sizeof(int64_t));
      dst += 3 * tw;
    }
    MPI_Send(result.data(), static_cast<int>(result.size()), MPI_INT64_T, 0, kTagResult,
             MPI_COMM_WORLD);
    ++tiles_done;
    if (tiles_done == 1 && rank == kill_rank) {
      fmt::print(stderr, "raystream: test hook: rank {} exits after its first tile\n", rank);
      std::fflush(stderr);
      _exit(1);
    }
    if (tiles_done == 1 && rank == hang_rank) {
      fmt::print(stderr, "raystream: test hook: rank {} stops answering after its first tile\n",
                 rank);
      std::fflush(stderr);
      for (;;) std::this_thread::sleep_for(std::chrono::seconds(1));
    }
  }
}

// ------------------------------------------------------------------------------------------------
// Master.

struct WorkerFrame {
  uint64_t tiles = 0;
  uint64_t steals = 0;  // PBT: tiles from another worker's list
  double busy_seconds = 0;
  double cpu_seconds = 0;
  uint64_t rays = 0;
  uint64_t msgs_sent = 0, bytes_sent = 0;  // master -> this worker
  uint64_t msgs_recv = 0, bytes_recv = 0;  // this worker -> master
};

struct TileRec {
  Tile tile;
  int rank = -1;
  double seconds = 0, cpu_seconds = 0, predicted = -1;
  uint64_t rays = 0, tasks = 0;
};

class Master {
 public:
  Master(const MpiRenderConfig& c, const Setup& s, int ranks)
      : c_(c), s_(s), workers_(ranks - 1), fb_(c.options.width, c.options.height) {
    if (c.pbt_tiles_per_worker > 0) {
      pbt_ = std::make_unique<Pbt>(c.options.width, c.options.height, workers_,
                                   c.pbt_tiles_per_worker);
    }
  }

  void Run() {
    const std::string out = c_.out.empty() ? s_.scene.name + ".png" : c_.out;
    Json frames = Json::array();
    double total = 0;
    uint64_t rays = 0;
    for (int frame = 0; frame < c_.frames; ++frame) {
      const Json f = RenderFrame(frame);
      total += f["seconds"].get<double>();
      rays += f["rays"].get<uint64_t>();
      // Only complete frames reach this point (a failure aborts inside RenderFrame).
      const bool write = frame + 1 == c_.frames || out.find('#') != std::string::npos;
      if (write) {
        fb_.ToRgb(rgb_);
        WriteImage(FramePath(out, frame), c_.options.width, c_.options.height, rgb_);
        if (!c_.dump_raw.empty()) WriteRawFramebuffer(FramePath(c_.dump_raw, frame), fb_);
      }
      frames.push_back(f);
      if (c_.frames > 1 && !c_.quiet) {
        fmt::print(stderr, "frame {}/{}  {:.1f} ms  imbalance {:.3f}\n", frame + 1, c_.frames,
                   1e3 * f["seconds"].get<double>(), f["imbalance"].get<double>());
      }
    }
    for (int r = 1; r <= workers_; ++r) {
      int stop = 0;
      MPI_Send(&stop, 1, MPI_INT, r, kTagStop, MPI_COMM_WORLD);
    }
    if (!c_.stats.empty()) {
      std::ofstream f(c_.stats);
      if (EndsWith(c_.stats, ".csv")) {
        WriteStatsCsv(f, frames);
      } else {
        f << Json{{"scene", s_.scene.name},
                  {"backend", "mpi"},
                  {"ranks", workers_ + 1},
                  {"workers", workers_},
                  {"tiling", pbt_ ? fmt::format("PBT k={} assign {}", c_.pbt_tiles_per_worker,
                                                PbtAssignName(c_.assign))
                                  : fmt::format("tiles {}x{}", c_.tile_width, c_.tile_height)},
                  {"prefetch", c_.prefetch},
                  {"timeout_seconds", c_.timeout_seconds},
                  {"frames", frames}}
                 .dump(2)
          << "\n";
      }
      f.flush();
      if (!f) throw Error(fmt::format("--stats {}: cannot write the file", c_.stats));
    }
    if (!c_.quiet) {
      fmt::print("scene      {}: {} triangles, {} lights\n", s_.scene.name,
                 s_.scene.mesh().num_triangles, s_.scene.lights.size());
      fmt::print("image      {}x{}, depth {}, {} frame(s), backend mpi, {} workers, {}\n",
                 c_.options.width, c_.options.height, c_.options.max_depth, c_.frames, workers_,
                 pbt_ ? fmt::format("PBT k={} assign {}", c_.pbt_tiles_per_worker,
                                    PbtAssignName(c_.assign))
                      : fmt::format("tiles {}x{}", c_.tile_width, c_.tile_height));
      fmt::print("trace      {:.1f} ms, {} rays, {:.2f} Mrays/s\n", 1e3 * total, rays,
                 total > 0 ? rays / total * 1e-6 : 0.0);
      fmt::print("wrote      {}\n", FramePath(out, c_.frames - 1));
    }
  }

 private:
  // Tiles and per-worker preference lists for this frame.
  void PlanFrame(int frame) {
    lists_.assign(static_cast<size_t>(workers_), {});
    next_grid_ = 0;
    if (pbt_) {
      tiles_ = pbt_->Tiles();
      estimates_ = pbt_->Estimates();
      Assignment a;
      switch (c_.assign) {
        case PbtAssign::kGreedy: a = AssignPbtGreedy(*pbt_); break;
        case PbtAssign::kVisit: a = AssignPbtVisit(*pbt_); break;
        case PbtAssign::kStatic: a = AssignPbtRandom(*pbt_, c_.seed); break;
        case PbtAssign::kRandom:
        default: a = AssignPbtRandom(*pbt_, c_.seed + static_cast<uint64_t>(frame)); break;
      }
      predicted_makespan_ = a.PredictedMakespan();
      for (int w = 0; w < workers_; ++w) {
        const auto& mine = a.tiles[static_cast<size_t>(w)];
        lists_[static_cast<size_t>(w)].assign(mine.begin(), mine.end());
      }
      has_prediction_ = frame > 0;
      // Before the first measurement, steal by area.
      weight_.resize(tiles_.size());
      for (size_t i = 0; i < tiles_.size(); ++i) {
        weight_[i] = has_prediction_ ? estimates_[i] : double(tiles_[i].NumPixels());
      }
    } else {
      tiles_.clear();
      for (int y = 0; y < c_.options.height; y += c_.tile_height) {
        for (int x = 0; x < c_.options.width; x += c_.tile_width) {
          tiles_.push_back(Tile{x, y, std::min(x + c_.tile_width, c_.options.width),
                                std::min(y + c_.tile_height, c_.options.height)});
        }
      }
      has_prediction_ = false;
    }
  }

  // The next tile for worker w (0-based), or -1 if none is waiting. *stolen: not from w's list.
  int NextTile(int w, bool* stolen) {
    *stolen = false;
    if (!pbt_) return next_grid_ < tiles_.size() ? static_cast<int>(next_grid_++) : -1;
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
      for (int32_t t : lists_[static_cast<size_t>(v)]) waiting += weight_[static_cast<size_t>(t)];
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
    MPI_Send(msg, kTileWords, MPI_INT, w + 1, kTagTile, MPI_COMM_WORLD);
    WorkerFrame& wf = wstats_[static_cast<size_t>(w)];
    ++wf.msgs_sent;
    wf.bytes_sent += sizeof(msg);
    in_flight_[static_cast<size_t>(w)].push_back(t);
    // The silence clock starts when the worker gets work after having none.
    if (in_flight_[static_cast<size_t>(w)].size() == 1) {
      last_heard_[static_cast<size_t>(w)] = Clock::now();
    }
  }

  // Tops up w's tiles in flight to c_.prefetch. PBT: prefetching takes only w's own tiles; a
  // tile of another worker's list is taken only when w has nothing left to render (so the
  // first round never strips a worker of its own tiles).
  void FeedWorker(int w, int frame) {
    auto& flight = in_flight_[static_cast<size_t>(w)];
    while (flight.size() < static_cast<size_t>(c_.prefetch)) {
      if (pbt_ && !flight.empty() && lists_[static_cast<size_t>(w)].empty()) return;
      bool stolen = false;
      const int t = NextTile(w, &stolen);
      if (t < 0) return;
      if (stolen) ++wstats_[static_cast<size_t>(w)].steals;
      SendTile(w, frame, t);
    }
  }

  Json RenderFrame(int frame) {
    PlanFrame(frame);
    fb_.Clear();
    const size_t m = tiles_.size();
    records_.assign(m, TileRec{});
    for (size_t i = 0; i < m; ++i) {
      records_[i].tile = tiles_[i];
      if (has_prediction_) records_[i].predicted = estimates_[i];
    }
    std::vector<char> done(m, 0);
    wstats_.assign(static_cast<size_t>(workers_), WorkerFrame{});
    in_flight_.assign(static_cast<size_t>(workers_), {});
    last_heard_.assign(static_cast<size_t>(workers_), Clock::now());
    const auto t0 = Clock::now();
    for (int w = 0; w < workers_; ++w) FeedWorker(w, frame);
    size_t received = 0;
    std::vector<int64_t> buf;
    const size_t width = static_cast<size_t>(c_.options.width);
    int polls_idle = 0;
    while (received < m) {
      int flag = 0;
      MPI_Status status;
      MPI_Iprobe(MPI_ANY_SOURCE, kTagResult, MPI_COMM_WORLD, &flag, &status);
      if (!flag) {
        // Nothing yet: check the deadlines, then sleep a little (the master shares the cores).
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
        ++polls_idle;
        std::this_thread::sleep_for(std::chrono::microseconds(polls_idle < 100 ? 50 : 500));
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
      buf.resize(static_cast<size_t>(count));
      MPI_Recv(buf.data(), count, MPI_INT64_T, src, kTagResult, MPI_COMM_WORLD, MPI_STATUS_IGNORE);
      const int64_t f = buf[0], t = buf[1];
      auto& flight = in_flight_[static_cast<size_t>(w)];
      if (f != frame || t < 0 || static_cast<size_t>(t) >= m || flight.empty() ||
          flight.front() != t || done[static_cast<size_t>(t)]) {
        Abort(0, fmt::format("unexpected result from rank {}: frame {} tile {} (expected frame "
                             "{} tile {})",
                             src, f, t, frame, flight.empty() ? -1 : flight.front()));
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
      TileRec& rec = records_[static_cast<size_t>(t)];
      rec.rank = src;
      rec.seconds = std::bit_cast<double>(buf[2]);
      rec.cpu_seconds = std::bit_cast<double>(buf[3]);
      rec.rays = static_cast<uint64_t>(buf[4]);
      rec.tasks = static_cast<uint64_t>(buf[5]);
      nan_ += static_cast<uint64_t>(buf[6]);
      clamped_ += static_cast<uint64_t>(buf[7]);
      WorkerFrame& wf = wstats_[static_cast<size_t>(w)];
      ++wf.tiles;
      wf.busy_seconds += rec.seconds;
      wf.cpu_seconds += rec.cpu_seconds;
      wf.rays += rec.rays;
      ++wf.msgs_recv;
      wf.bytes_recv += static_cast<uint64_t>(count) * sizeof(int64_t);
      FeedWorker(w, frame);
    }
    const double seconds = Seconds(Clock::now() - t0);
    return FrameJson(frame, seconds);
  }

  Json FrameJson(int frame, double seconds) {
    const size_t m = tiles_.size();
    std::vector<double> times(m), predicted(m);
    uint64_t rays = 0;
    Json tiles = Json::array();
    for (size_t i = 0; i < m; ++i) {
      const TileRec& r = records_[i];
      times[i] = c_.pbt_cpu_time ? r.cpu_seconds : r.seconds;
      predicted[i] = r.predicted;
      rays += r.rays;
      tiles.push_back(Json{{"x0", r.tile.x0}, {"y0", r.tile.y0}, {"x1", r.tile.x1},
                           {"y1", r.tile.y1}, {"rank", r.rank}, {"seconds", r.seconds},
                           {"cpu_seconds", r.cpu_seconds}, {"predicted", r.predicted},
                           {"rays", r.rays}, {"tasks", r.tasks}});
    }
    Json workers = Json::array();
    std::vector<double> busy;
    double busy_sum = 0, idle_sum = 0;
    uint64_t msgs = 0, bytes = 0;
    for (int w = 0; w < workers_; ++w) {
      const WorkerFrame& wf = wstats_[static_cast<size_t>(w)];
      busy.push_back(wf.busy_seconds);
      busy_sum += wf.busy_seconds;
      idle_sum += std::max(0.0, seconds - wf.busy_seconds);
      msgs += wf.msgs_sent + wf.msgs_recv;
      bytes += wf.bytes_sent + wf.bytes_recv;
      workers.push_back(Json{{"rank", w + 1}, {"tiles", wf.tiles}, {"steals", wf.steals},
                             {"busy_seconds", wf.busy_seconds}, {"cpu_seconds", wf.cpu_seconds},
                             {"idle_seconds", std::max(0.0, seconds - wf.busy_seconds)},
                             {"rays", wf.rays}, {"messages_sent", wf.msgs_sent},
                             {"bytes_sent", wf.bytes_sent}, {"messages_received", wf.msgs_recv},
                             {"bytes_received", wf.bytes_recv}});
    }
    Json j{{"frame", frame},
           {"seconds", seconds},
           {"fps", seconds > 0 ? 1.0 / seconds : 0.0},
           {"busy_seconds", busy_sum},
           {"idle_seconds", idle_sum},
           {"rays", rays},
           {"tiles_count", m},
           {"imbalance", FrameImbalance(busy)},
           {"messages", msgs},
           {"bytes", bytes},
           {"dropped_nan", nan_},
           {"clamped", clamped_}};
    nan_ = clamped_ = 0;
    if (pbt_) {
      j["pbt"] = true;
      j["predicted_makespan"] = predicted_makespan_;
      if (has_prediction_) {
        const PredictionAccuracy a = MeasurePredictionAccuracy(predicted, times);
        j["accuracy"] = Json{{"within5", a.within5}, {"within10", a.within10},
                             {"within15", a.within15}};
      }
      if (c_.assign != PbtAssign::kStatic) {
        const PbtUpdateStats u = pbt_->Update(times);
        j["update"] = Json{{"steps", u.steps}, {"hit_step_bound", u.hit_step_bound},
                           {"variance_before", u.variance_before},
                           {"variance_after", u.variance_after}};
      }
    }
    j["workers"] = workers;
    j["tiles"] = tiles;
    return j;
  }

  const MpiRenderConfig& c_;
  const Setup& s_;
  int workers_;
  Framebuffer fb_;
  std::vector<float> rgb_;
  std::unique_ptr<Pbt> pbt_;
  std::vector<Tile> tiles_;
  std::vector<double> estimates_, weight_;
  std::vector<std::deque<int32_t>> lists_;
  size_t next_grid_ = 0;
  bool has_prediction_ = false;
  double predicted_makespan_ = 0;
  std::vector<TileRec> records_;
  std::vector<WorkerFrame> wstats_;
  std::vector<std::deque<int32_t>> in_flight_;
  std::vector<Clock::time_point> last_heard_;
  uint64_t nan_ = 0, clamped_ = 0;
};

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
  int failed = error.empty() ? ranks : rank;  // lowest failing rank, `ranks` if none
  int first_failed = ranks;
  MPI_Allreduce(&failed, &first_failed, 1, MPI_INT, MPI_MIN, MPI_COMM_WORLD);
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
