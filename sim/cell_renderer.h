// The Cell backend: renders a frame on 1..8 simulated SPEs (sim/spe.h) under a deterministic
// discrete-event loop on one host thread that always advances the SPE furthest behind in
// simulated time. Produces the serial backend's image bit for bit, plus the simulated frame time
// at 3.2 GHz and a per-SPE cycle breakdown (compute, DMA, atomic, software cache, idle).
#pragma once

#include <cstdint>
#include <memory>
#include <span>
#include <string>
#include <vector>

#include "sched/backend.h"
#include "sched/framebuffer.h"
#include "sched/pbt.h"
#include "sched/render.h"
#include "sched/tile_plan.h"
#include "sim/cell_image.h"
#include "sim/config.h"
#include "sim/mfc.h"
#include "sim/spe.h"
#include "sim/sw_cache.h"

namespace rs::sim {

struct SpeReport {
  int id = 0;
  CycleBreakdown cycles;  // sums to the frame's cycles (idle = after its last ray)
  uint64_t finish = 0;    // cycle its program ended
  SpeCounters counters;
  MfcStats mfc;
  AtomicStats atomic;
  SoftwareCacheStats cache;
  uint32_t ls_used = 0;  // local-store bytes allocated (code/stack budget included)
  std::string ls_layout;
};

struct CellTileRecord {
  Tile tile;
  int32_t spe = -1;       // the SPE that took it from its tile counter
  int32_t worker = -1;    // PBT lists: the (virtual) worker whose list held it (-1: counter)
  double cycles = 0;      // SPE cycles attributed to its rays (FrameOutputs::tile_cycles)
  double predicted = -1;  // PBT: the estimate it was tiled with (-1: none)
};

struct CellFrameStats {
  // Counters in the host backends' form (rays by kind, hits, occluded, shading, cell steps,
  // triangle tests); total_seconds is the host wall time of the simulation.
  FrameStats frame;
  uint64_t cycles = 0;  // simulated frame time: the last SPE's finish
  double seconds = 0;   // cycles / clock_hz
  double clock_hz = 3.2e9;
  std::vector<SpeReport> spes;
  SpeCounters totals;
  CycleBreakdown breakdown;  // summed over SPEs
  uint64_t mic_lines = 0;
  uint64_t mic_queue_cycles = 0;  // lines' waiting at the shared MIC (contention)
  double host_seconds = 0;        // wall time of Render (image build excluded)
  double image_seconds = 0;       // PPE layout of the main-memory image (when (re)built)
  size_t image_bytes = 0;
  std::vector<CellTileRecord> tiles;
  // PBT tiling (config.pbt_tiles_per_spe > 0).
  bool pbt = false;
  bool has_prediction = false;
  PredictionAccuracy accuracy;
  double worker_imbalance = 1.0;  // slowest / mean worker, in simulated tile cycles
  double predicted_makespan = 0;  // the largest predicted worker load (cycles)
  PbtUpdateStats update;

  // Rays per simulated second / 1e6.
  double SimulatedMraysPerSecond() const;
};

// The cell backend's PBT policy (with config.pbt_tiles_per_spe = k > 0), run by the tile plan
// of the host backends (sched/tile_plan.h) on the simulated tile cycles, its deterministic cost.
struct CellPlanOptions {
  // kCounter (the default): every SPE takes the PBT's tiles from one atomic tile counter, the
  // costliest predicted first. random / greedy / visit / static: per-worker lists; SPE s runs
  // the lists of workers s, s + spes, ... through a tile counter of its own (its own tile list
  // and counter line in main memory, so the SPE program is unchanged), without stealing: the
  // SPE program reads no other SPE's counter.
  PbtAssign assign = PbtAssign::kCounter;
  uint64_t seed = 1;    // PBT-Random / static
  int pbt_workers = 0;  // PBT workers n (0: config.num_spes); m = k n tiles
  // PBT-Update's predictor (tile_plan.h). The cost map (cost_block x cost_block pixel blocks)
  // gets the SPEs' cycles per block: each pipeline iteration's cycles charged to its rays'
  // pixels in the shares of CellTileRecord::cycles (FrameOutputs::block_work), and the
  // primaries' hit distances with the frame's and the next frame's camera
  // (FrameContext::next_camera), so it is reprojected like the host backends' maps. The record
  // is the same in every run of a configuration; like the tile cycles it depends on the SPE
  // count (DMA waits at the shared MIC, which rays share an iteration). The hit distances do
  // not: they are the host backends' bit for bit.
  PbtPredict predict = PbtPredict::kCostMap;
  int cost_block = 4;
};

class CellRenderer {
 public:
  // Throws rs::Error if the config is invalid (ValidateConfig) or the plan options are
  // (unknown assignment, pbt_workers outside [0, 65536]).
  explicit CellRenderer(const SimConfig& config, const CellPlanOptions& plan = {});
  ~CellRenderer();
  CellRenderer(const CellRenderer&) = delete;
  CellRenderer& operator=(const CellRenderer&) = delete;

  // Renders the whole image into fb (added to it, not cleared first; fb must be width x height
  // of ctx): regular tiles of config.tile_width x tile_height from the atomic tile counter, or
  // the PBT's tiles as CellPlanOptions says (the PBT is updated with the simulated tile cycles
  // after the frame, CellTileRecord::cycles). The SPEs
  // accumulate the image in their local-store pixel buffers and put them into a main-memory
  // pixel image by DMA; fb receives that image (and the drop and clamp counts of the SPEs'
  // status records) after the frame. Throws rs::Error if fb's size differs, a local store
  // overflows (e.g. the grid's occupancy bits do not fit), or a DMA is illegal.
  CellFrameStats Render(const FrameContext& ctx, Framebuffer& fb);
  // The same with an explicit tile list (inside the image, not overlapping: throws rs::Error
  // naming the two tiles otherwise), handed out in list order. Pixels outside every tile stay
  // unchanged in fb.
  CellFrameStats Render(const FrameContext& ctx, Framebuffer& fb, std::span<const Tile> tiles);

  const SimConfig& config() const { return config_; }
  const CellPlanOptions& plan_options() const { return plan_options_; }
  const Pbt* pbt() const { return plan_ ? plan_->pbt() : nullptr; }
  // What the last PBT frame gave its plan's cost map (TilePlan::End): the blocks' cycles in
  // kBlockWorkUnit (FrameOutputs::block_units_per_cycle units a cycle: seconds at clock_hz),
  // the primaries' hit distances and ctx's cameras; empty without a cost map (regular tiles,
  // predict kPaper, assign static). Valid until the next Render.
  const TilePlanMeasure& cost_map_measure() const { return measure_; }
  // The main-memory image of the last frame's scene (nullptr before the first frame).
  const CellImage* image() const { return image_.get(); }

 private:
  // queues: tile indices per tile counter. One queue: every SPE takes from it; num_spes
  // queues: SPE s takes from queue s only. Empty: one queue of all tiles in list order.
  CellFrameStats RenderTiles(const FrameContext& ctx, Framebuffer& fb, std::span<const Tile> tiles,
                             bool explicit_tiles,
                             const std::vector<std::vector<int32_t>>& queues = {},
                             BlockWork* block_work = nullptr);

  SimConfig config_;
  CellPlanOptions plan_options_;
  std::unique_ptr<CellImage> image_;
  std::unique_ptr<TilePlan> plan_;
  AlignedBuffer pixels_;
  // PBT's cost-map record (sized once per image layout, cleared per frame).
  BlockWork block_work_;
  std::vector<float> pixel_depth_;
  TilePlanMeasure measure_;
  uint64_t frames_ = 0;
};

// The acceleration structure for the cell backend: built with `options` when its top-level
// occupancy bits fit the SPE's local store (OccupancyBudgetCells); otherwise rebuilt with a lower
// lambda (the grid kind kept, so kAuto may refine dense cells into 8x8x8
// sub-grids, as paper 3.8 does for large scenes) until they fit. *note (if given) is set to a
// sentence saying what was changed, or cleared. Throws rs::Error if no lambda fits.
Accel BuildCellAccel(const Scene& scene, BuildOptions options, const SimConfig& config,
                     int image_width, std::string* note = nullptr);

// Registers "cell" (sim/cell_backend.cc): the CellRenderer behind the command's backend interface
// (sched/backend.h), with BuildCellAccel as its Build and FormatCellReport as its summary. Its
// BackendConfig: spes, host.tile_width x tile_height, host.pbt_tiles_per_worker (k per SPE),
// host.assign, host.seed, host.pbt_workers.
void RegisterCellBackend(BackendRegistry& registry);

// A multi-line human-readable report: simulated time, rays/s, per-SPE breakdown table, loads,
// caches, tile counter contention.
std::string FormatCellReport(const CellFrameStats& stats, const SimConfig& config);

}  // namespace rs::sim
