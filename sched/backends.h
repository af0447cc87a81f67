// Host scheduling backends behind one renderer: serial (the reference), the iRT queues LOCK /
// LFREE / LOCAL (Nunes & Santos) on the FrameLoop, and image tiles handed out by an atomic counter
// (Benthin et al. 3.9) or assigned from a Prediction Binary Tree (Cosenza et al.). All run
// ProcessTask on the same rays, so they produce the same framebuffer bit for bit.
#pragma once

#include <cstddef>
#include <cstdint>
#include <functional>
#include <memory>
#include <span>
#include <string>
#include <string_view>
#include <variant>
#include <vector>

#include "sched/framebuffer.h"
#include "sched/pbt.h"
#include "sched/render.h"
#include "sched/tile_plan.h"  // PbtAssign, PbtCost, TileWork
#include "streams/raygen.h"

namespace rs {

enum class BackendKind : int {
  kSerial = 0,    // SerialRenderer on the calling thread (no render threads)
  kLock = 1,      // one shared two-lock FIFO (queue_lock.h)
  kLockFree = 2,  // one shared Michael-Scott lock-free FIFO (queue_lockfree.h)
  kLocal = 3,     // one private FIFO per thread, primary tasks dealt round-robin (queue_local.h)
  kTiles = 4,     // image tiles: atomic tile counter, or PBT tiling with per-worker tile lists
};

// "serial", "lock", "lfree", "local", "tiles" (ParseBackendKind also takes upper case and
// "lockfree"). Parse returns false for anything else and leaves *kind unchanged.
const char* BackendName(BackendKind kind);
bool ParseBackendKind(std::string_view name, BackendKind* kind);
std::vector<std::string> BackendNames();

struct BackendOptions {
  BackendKind kind = BackendKind::kSerial;
  int threads = 1;  // render threads, [1, FrameLoop::kMaxThreads]; serial needs 1
  // Tiles backend without PBT: tile_width x tile_height tiles in row-major order (partial at the
  // right and bottom; clamped to the image), handed out by an atomic counter. Any shape works:
  // 8x8, 32x32, 40x32, 640x2, W x 1 (single rows).
  int tile_width = 32;
  int tile_height = 32;
  // Tiles backend: k > 0 switches to a PBT tiling of m = k * n tiles, n = pbt_workers (0: n =
  // threads). The PBT's n worker lists are run by the threads in turn: thread t runs the lists
  // of workers t, t + threads, ... (each in list order). By default there is no stealing
  // between lists (the brief's reading of the paper: assigned lists; a thread that finishes
  // early idles at the barrier).
  // Queue backends (lock, lfree, local) take the same plan's tiles to feed their queues: a
  // thread feeds its own lists' tiles first; LOCAL keeps their rays on the thread's own queue;
  // a thread done with its lists takes waiting tiles of others (shared queues always, LOCAL
  // with pbt_steal). They need pbt_cost kWork (a tile has no time of its own there).
  int pbt_tiles_per_worker = 0;
  int pbt_workers = 0;
  // Demand-driven with affinity, the paper's master-worker of §2 with §4's affine tiles as the
  // preference (what SimulateDemandDriven in pbt.h models): a thread whose own lists are done
  // takes the LAST waiting tile of the list with the most predicted work waiting (tile pixels
  // before the first prediction), so the owner keeps its spatial order. Lock-free: each list is
  // one 64-bit {head, tail} word; the owner CASes head forward, thieves CAS tail back.
  bool pbt_steal = false;
  // Tiles backend, the paper's demand-driven master (§2, with §4's "when a worker asks for a
  // tile the master node tries to assign an affine tile"): no thread owns a list; a thread that
  // is free asks one DemandMaster (pbt.h, under a lock) for a tile and gets the first waiting
  // tile of its own lists (w, w + threads, ...) in PBT order (the in-order leaves), else the
  // first waiting tile in PBT order (counted in ThreadStats::steals). The lists (assign) are
  // only the preference. Not with pbt_steal or assign counter.
  bool pbt_demand = false;
  // PBT assignment (tile_plan.h). kCounter: no lists, the threads take the tiles from the tile
  // counter in order of decreasing prediction (pbt_workers n > threads: m = k n tiles, and the
  // statistics' worker imbalance is the demand-driven model of n workers).
  PbtAssign assign = PbtAssign::kRandom;
  uint64_t seed = 1;  // PBT-Random / static assignment
  // Which tile cost PBT-Update gets: wall-clock seconds (the paper's), the rendering thread's
  // CPU seconds (steadier when threads outnumber cores), or the deterministic work count
  // (TileWorkCost: the same in every run, whatever the machine's load or the threads).
  PbtCost pbt_cost = PbtCost::kWall;
  // What PBT-Update predicts the next frame's tiles with (tile_plan.h): the paper's (split halves
  // e(a) / 2) or the cost map (default). With kCostMap the engines of the tiles and queue
  // backends charge their rays' work to pixel blocks of pbt_cost_block x pbt_cost_block (tiles:
  // every trace call's counts, cell steps and triangle tests included; lock / lfree / local:
  // each ray's own count, which does not depend on how the rays were grouped into calls,
  // RayEngine::SetBlockWork) and store the primary hit distances, and the map is moved to the
  // next camera (FrameContext::next_camera); so do the cell backend (each pipeline iteration's
  // simulated cycles charged to its rays' blocks, sim/spe.h FrameOutputs) and the mpi backend
  // (the workers' engines record as the tiles backend's and return each tile's blocks and hit
  // distances with its result). The image does not change.
  PbtPredict pbt_predict = PbtPredict::kCostMap;
  int pbt_cost_block = 4;
  // Time queue operations (LOCK/LFREE/LOCAL) and tile-counter accesses (tiles), the paper's
  // Fig. 7. Costs two time-stamp reads per operation.
  bool queue_stats = true;
};

// Throws rs::Error naming the option: threads outside [1, FrameLoop::kMaxThreads], serial with
// threads != 1, tile sizes < 1, pbt_tiles_per_worker < 0 or > 4096, pbt_workers < 0 or > 65536,
// PBT options (k > 0, pbt_steal, pbt_workers, pbt_cost other than wall) on serial or without
// k > 0, PBT on a queue backend with pbt_cost other than work, pbt_steal with assign counter,
// pbt_demand other than on tiles with PBT lists or with pbt_steal, unknown enum values.
void ValidateBackendOptions(const BackendOptions& options);

// Per render thread, one frame.
struct ThreadStats {
  FrameStats work;           // rays by kind, tasks, trace/shade times of what this thread ran
  double busy_seconds = 0;   // release -> arrival at the closing barrier (FrameLoopTimes)
  double idle_seconds = 0;   // at the closing barrier (paper Fig. 6)
  double cpu_seconds = 0;    // the thread's CPU time in the frame (FrameLoopTimes::cpu_seconds)
  double queue_seconds = 0;  // inside queue operations / tile-counter accesses (Fig. 7)
  uint64_t queue_ops = 0;
  uint64_t empty_polls = 0;  // TryPop calls that found EMPTY
  // LOCK, LFREE: contributions added through the thread's pixel-sum table (after its first
  // push or pop of the frame); the others were plain adds
  uint64_t table_adds = 0;
  uint64_t tiles = 0;        // tiles rendered (tiles backend) / taken to feed (queues + PBT)
  uint64_t steals = 0;       // PBT with pbt_steal: tiles taken from another worker's list;
                             // pbt_demand: tiles the master gave from another thread's lists
};

// One tile of the tiles backend, one frame. Queue backends with PBT: thread = the thread that
// took the tile and fed its primaries (its rays are traced by whoever pops them), seconds and
// cpu_seconds 0 (a tile has no time of its own there), counts only `rays` (every traced ray
// charged to its pixel's tile; cell steps, triangle tests and shading calls are per batch).
struct TileRecord {
  Tile tile;
  int32_t thread = -1;     // render thread that ran it
  int32_t worker = -1;     // PBT: the (virtual) worker whose list held it; else = thread
  double seconds = 0;      // wall time: primary generation + the tile's whole ray tree
  double cpu_seconds = 0;  // the thread's CPU time for the same span
  double predicted = -1;   // PBT: the estimate e(l) this frame was tiled with (-1: none)
  int64_t handout = -1;    // pbt_demand: the master handed it out as its handout-th (from 0)
  uint64_t rays = 0;       // rays traced for this tile, all kinds
  TileWork counts;         // the deterministic counters of the tile's ray tree
  double work = 0;         // TileWorkCost(counts): its work in calibrated seconds
};

struct HostFrameStats {
  uint64_t frame = 0;  // frames rendered before this one by the renderer
  BackendKind backend = BackendKind::kSerial;
  // Merged over the threads and the application thread (generate_seconds = the application's
  // primary generation); total_seconds = BeginFrame start -> closing barrier completion.
  FrameStats total;
  double render_seconds = 0;     // opening -> closing barrier completion (0 for serial)
  double app_queue_seconds = 0;  // application thread inside PushPrimary
  double app_cpu_seconds = 0;    // application thread's CPU time in BeginFrame (generation)
  uint64_t primary_tasks = 0;
  std::vector<ThreadStats> threads;  // one per render thread (serial: one)
  std::vector<TileRecord> tiles;     // tiles backend, PBT: one per tile, in tile order
  // max / mean of the threads' busy_seconds (>= 1; 1 when the mean is 0).
  double imbalance = 1.0;

  // PBT (tiles or queue backend with pbt_tiles_per_worker > 0).
  bool pbt = false;
  bool has_prediction = false;    // tiles carry predictions (not the first PBT frame)
  PredictionAccuracy accuracy;    // predicted vs measured tile times (if has_prediction)
  double worker_imbalance = 1.0;  // FrameImbalance(WorkerTimes(assignment, tile costs))
  double demand_imbalance = 1.0;  // TilePlanReport::demand_imbalance (the paper's master-worker)
  double lpt_imbalance = 1.0;     // TilePlanReport::lpt_imbalance (LPT lists on the predictions)
  double predicted_makespan = 0;  // the assignment's predicted max worker load
  PbtUpdateStats update;          // the PBT-Update run after this frame (not for static)

  double FramesPerSecond() const { return total.total_seconds > 0 ? 1.0 / total.total_seconds : 0; }
  double IdleSeconds() const;   // sum over threads
  double QueueSeconds() const;  // sum over threads + application (aggregate, Fig. 7)
  // Frame time this frame would take on an idle machine with `cores` cores, from CPU times:
  // app_cpu_seconds + max(slowest thread's CPU, all threads' CPU / cores). Barrier wake-ups and
  // memory-bandwidth limits are not modelled; spinning on an EMPTY queue counts as work. Use it
  // where other processes share the machine and wall-clock times mostly measure the CPU share.
  double ContentionFreeSeconds(int cores) const;
};

// The renderer an application drives (listing 3):
//   HostRenderer r({.kind = BackendKind::kLockFree, .threads = 4});
//   while (running) {
//     FrameContext ctx = MakeFrameContext(scene, accel, camera, options);
//     fb.Clear();
//     r.BeginFrame(ctx, fb);         // primary tasks into the queue(s), threads released
//     application_logic();           // runs while the threads render
//     const HostFrameStats& s = r.EndFrame();   // closing barrier; fb complete
//   }                                // ~HostRenderer: END flag, threads joined
// or RenderFrame(ctx, fb, logic) for the three steps. Single application thread; not
// thread-safe otherwise. The render threads are created once in the constructor.
class HostRenderer {
 public:
  // Throws rs::Error (ValidateBackendOptions), std::system_error if threads cannot start.
  explicit HostRenderer(const BackendOptions& options);
  // END flag, threads joined. A running frame is waited for first (its fb must still exist).
  ~HostRenderer();
  HostRenderer(const HostRenderer&) = delete;
  HostRenderer& operator=(const HostRenderer&) = delete;

  const BackendOptions& options() const;

  // Starts a frame of the whole image: ctx is copied (its scene and accel must outlive
  // EndFrame), fb (ctx.options.width x height, not cleared) must outlive EndFrame. serial and
  // tiles take a kResolved fb (each pixel set once per frame; half the memory), the queue
  // backends need kFixed. Throws rs::Error if fb's size or storage does not fit or a frame is
  // already running; PBT tiles: rs::Error if the image has fewer pixels than tiles.
  void BeginFrame(const FrameContext& ctx, Framebuffer& fb);
  // The same for an explicit set of tiles (inside the image; may be empty: a frame with no
  // rays). Not with PBT (throws rs::Error). Queue backends cut each tile into primary tasks; the
  // tiles backend hands these tiles out.
  void BeginFrame(const FrameContext& ctx, Framebuffer& fb, std::span<const Tile> tiles);

  // Waits for the frame (closing barrier), gathers the statistics and, with PBT, runs
  // PBT-Update on the measured tile times and assigns the next frame's tiles. Rethrows an
  // exception a render thread met (the frame's image is then incomplete). The reference stays
  // valid until the next BeginFrame.
  const HostFrameStats& EndFrame();

  // BeginFrame, app_logic() (if any) while the threads render, EndFrame.
  const HostFrameStats& RenderFrame(const FrameContext& ctx, Framebuffer& fb,
                                    const std::function<void()>& app_logic = {});

  bool in_frame() const;
  uint64_t frames() const;  // completed frames
  // The PBT the next frame will be tiled with (nullptr without PBT).
  const Pbt* pbt() const;
  // What the last frame gave the PBT cost map (pbt_predict kCostMap on tiles, lock, lfree,
  // local): its threads' block work summed, the pixels' primary hit distances and the cameras.
  // Empty (blocks nullptr) without the cost map, in a frame and after a failed one. Valid until
  // the next BeginFrame.
  TilePlanMeasure cost_map_measure() const;

  class Impl;

 private:
  std::unique_ptr<Impl> impl_;
};

// The PBT workers n of `o` (pbt_workers, or threads when 0), the tile plan its options ask for,
// and a plan's frame report copied into the frame's statistics (the PBT fields; nothing
// without PBT). Shared by the host backends and the MPI master.
int PbtWorkers(const BackendOptions& o);
TilePlanOptions TilePlanOptionsFor(const BackendOptions& o);
void ApplyPlanReport(const TilePlanReport& report, HostFrameStats& stats);
// The cost PBT-Update gets for a tile: its wall seconds, CPU seconds or work (PbtCost).
double TileCost(const TileRecord& record, PbtCost cost);

// A named value a caller adds on top of the host statistics (StatsExtra).
using StatsValue = std::variant<int64_t, uint64_t, double, bool, std::string>;
struct StatsField {
  std::string name;
  StatsValue value;
};
using StatsFields = std::vector<StatsField>;

// What a backend outside HostRenderer (the MPI master, sched/mpi_backend.h) adds to the host
// statistics, so that every backend writes one format: the host keys and columns unchanged, its
// own after them. Empty members add nothing.
struct StatsExtra {
  std::string backend;  // JSON "backend" and options "name" (empty: BackendName(options.kind))
  StatsFields options;  // JSON: appended to "options"
  // Per frame (size 0 or frames.size()): JSON appended to the frame object; CSV the frame row.
  std::vector<StatsFields> frames;
  // Per frame (size 0 or frames.size()), per thread entry (size 0 or that frame's
  // threads.size()): JSON appended to the entry of "threads"; CSV the thread row.
  std::vector<std::vector<StatsFields>> threads;
};

// Writes per-frame statistics: JSON if path ends in ".json", CSV if ".csv" (one row per frame,
// application thread, render thread and tile; see backends.cc for the columns). `extra` adds
// fields after the host ones; in CSV they become columns after the host columns, named in the
// order they first occur (frame fields, then thread fields), empty where a row has none. Throws
// rs::Error for another extension (StatsFileFormatOk checks it up front), an unwritable file,
// extra sizes that do not match `frames`, or an extra name that repeats a host key / column
// or another extra name of the same object.
void WriteHostStats(const std::string& path, const std::string& scene,
                    const BackendOptions& options, std::span<const HostFrameStats> frames,
                    const StatsExtra& extra = {});
// The same file's text (the format from path's extension), for a caller that stages several
// outputs and places them together (scenes/image_io.h StageFile). WriteHostStats writes it
// atomically: the whole file or nothing at `path`.
std::string HostStatsText(const std::string& path, const std::string& scene,
                          const BackendOptions& options, std::span<const HostFrameStats> frames,
                          const StatsExtra& extra = {});
bool StatsFileFormatOk(const std::string& path);

}  // namespace rs
