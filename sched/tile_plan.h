// One tile plan for every tiled backend (tiles, mpi, cell): the image cut into fixed W x H tiles,
// or the per-frame PBT policy of Cosenza et al. (shared/papers/pbt-temporal-spatial-coherence.md):
// PBT-Update between frames, the PBT-Random / Greedy / Visit / static assignments, predictions,
// steal weights and the Table 1 measures. Written once here so the backends cannot drift apart.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <span>
#include <string_view>
#include <vector>

#include "sched/cost_map.h"
#include "sched/pbt.h"
#include "streams/raygen.h"  // rs::Tile, rs::CameraBasis

namespace rs {

struct FrameStats;  // sched/render.h

// How a PBT frame's tiles go to the workers.
enum class PbtAssign : int {
  kRandom = 0,   // PBT-Random: PBT updated every frame, tiles dealt by a seeded permutation
                 // (a different seed each frame: PbtRandomSeed)
  kGreedy = 1,   // PBT-Greedy: PBT updated, each tile to its affine worker (pbt.h)
  kVisit = 2,    // PBT-Visit: PBT updated, in-order runs of equal predicted load
  kStatic = 3,   // baseline: the initial PBT tiling, never updated, random assignment with the
                 // same seed every frame (the paper's "static random assignment")
  kCounter = 4,  // PBT updated, no per-worker lists: the tiles in order of decreasing prediction
                 // (ties: tile order) through one shared tile counter (demand driven, longest
                 // first; what the cell backend's atomic tile counter does by default). The n
                 // workers size the PBT (m = k n) and the demand-driven model.
  kLpt = 5,      // not in the paper: PBT updated, per-worker lists by LPT over the predictions
                 // (AssignLpt: costliest first, each to the least predicted load; the tiles'
                 // pixels before the first prediction), each list costliest first
};
// "random" "greedy" "visit" "static" "counter" "lpt". Parse returns false for anything else and leaves
// *assign unchanged.
const char* PbtAssignName(PbtAssign assign);
bool ParsePbtAssign(std::string_view name, PbtAssign* assign);

// Which measurement of a tile PBT-Update gets as t(l).
enum class PbtCost : int {
  kWall = 0,  // wall-clock seconds of the tile's whole ray tree (the paper's)
  kCpu = 1,   // the rendering thread's CPU seconds for the same span
  kWork = 2,  // TileWorkCost: deterministic counts of the tile's ray tree, in calibrated seconds
};
// "wall" "cpu" "work"; Parse as ParsePbtAssign.
const char* PbtCostName(PbtCost cost);
bool ParsePbtCost(std::string_view name, PbtCost* cost);

// What PBT-Update predicts the next frame's tiles with.
enum class PbtPredict : int {
  kPaper = 0,    // the paper's Algorithm 1: e(l) <- t(l), split halves e(a) / 2, merges the sum
  kCostMap = 1,  // the frame's per-block cost map (cost_map.h), reprojected to the next camera
                 // when the backend gives the cameras and the blocks' hit distances: every tile,
                 // split half and merged pair is predicted as the sum of the blocks it covers
};
// "paper" "costmap"; Parse as ParsePbtAssign.
const char* PbtPredictName(PbtPredict predict);
bool ParsePbtPredict(std::string_view name, PbtPredict* predict);

// The deterministic work of one tile: counters of its whole ray tree (primary rays and every
// ray they spawn). The same tile of the same frame gives the same counts on any thread, any
// backend and any machine (the kernels are bit-identical on every SIMD target).
struct TileWork {
  uint64_t rays = 0;            // rays traced, all kinds (FrameStats::TotalRays)
  uint64_t cell_steps = 0;      // TraceStats::cell_steps
  uint64_t triangle_tests = 0;  // TraceStats::triangle_tests
  uint64_t shading_calls = 0;   // ShadeStats::shading_calls (hit points shaded)
};

// The counters `after` has beyond `before` (a worker's running FrameStats around one tile).
TileWork TileWorkDelta(const FrameStats& after, const FrameStats& before);

// Seconds per unit of each counter of TileWork, fitted to tile CPU times on the development
// machine (values and how they were measured: tile_plan.cc).
struct TileWorkCoefficients {
  double per_ray;
  double per_cell_step;
  double per_triangle_test;
  double per_shading_call;
};
extern const TileWorkCoefficients kTileWorkCoefficients;

// sum of count x coefficient: a tile's cost in seconds of one core of the calibration machine.
// Exact function of the counts (fixed evaluation order), so equal counts give equal costs.
double TileWorkCost(const TileWork& work,
                    const TileWorkCoefficients& coefficients = kTileWorkCoefficients);

// The image in tile_width x tile_height tiles in row-major order (partial at the right and the
// bottom), the tile size clamped to the image. Throws rs::Error if a size is < 1.
std::vector<Tile> GridTiles(int width, int height, int tile_width, int tile_height);

// PBT-Random's seed for frame f of a plan (f = 0: the plan's first frame): a different
// permutation each frame, seed ^ (0x9E3779B97F4A7C15 * (f + 1)) (splitmix-style).
uint64_t PbtRandomSeed(uint64_t seed, uint64_t frame);

struct TilePlanOptions {
  // Fixed tiles (pbt_tiles_per_worker == 0): GridTiles(width, height, tile_width, tile_height).
  int tile_width = 32;
  int tile_height = 32;
  // k > 0: a PBT of m = k * workers tiles, re-tiled between frames.
  int pbt_tiles_per_worker = 0;
  int workers = 1;  // n, the PBT's workers (lists); >= 1
  PbtAssign assign = PbtAssign::kRandom;
  uint64_t seed = 1;  // PBT-Random / static
  // The backend lets a worker whose list is done take the last waiting tile of the list with the
  // most predicted work waiting (TilePlanFrame::weight). Recorded; not with kCounter.
  bool steal = false;
  // The backend's threads ask one DemandMaster (pbt.h) for tiles, in PBT order with their lists
  // as the preference (the paper's demand-driven master). Recorded; lists only, not with steal.
  bool demand = false;
  // What End's costs are (recorded for the statistics; the backend measures them).
  PbtCost cost = PbtCost::kWall;
  // The predictor of PBT-Update (not used by static, which predicts a tile by its own last
  // cost). kCostMap with cost_block x cost_block pixel blocks: the plan's cost map and the
  // backend's BlockWork (TilePlanMeasure) are sized once, for the image.
  PbtPredict predict = PbtPredict::kCostMap;
  int cost_block = 4;
};

// Throws rs::Error naming the field: tile sizes < 1, pbt_tiles_per_worker outside [0, 4096],
// workers outside [1, 65536], unknown assign / cost / predict, cost_block outside [1, 256], steal
// or demand with kCounter or without PBT, steal with demand.
void ValidateTilePlanOptions(const TilePlanOptions& options);

// Whether a plan with these options uses the cost-map predictor (TilePlan::uses_cost_map): PBT,
// predict kCostMap, not static. For a process that measures for a plan it does not hold (an
// MPI worker).
bool UsesCostMap(const TilePlanOptions& options);

// What a frame is rendered with (TilePlan::Begin).
struct TilePlanFrame {
  uint64_t frame = 0;           // frames ended by the plan before this one
  std::vector<Tile> tiles;      // tile index -> rectangle (PBT: the leaves in in-order)
  bool has_prediction = false;  // PBT after its first frame
  // Per tile, the cost the plan predicts (units of End's costs; -1: none): the PBT's estimate
  // e(l), or for static (never re-tiled) the same tile's cost in the previous frame.
  std::vector<double> predicted;
  // PBT with per-worker lists (random, greedy, visit, static, lpt): per worker the tiles in
  // processing order, and their predicted loads (0 before the first prediction). Empty for
  // fixed tiles and kCounter.
  Assignment assignment;
  std::vector<int32_t> owner;  // per tile: the worker whose list holds it (empty: no lists)
  // Tiles without lists (fixed tiles, kCounter): the order a shared counter hands them out:
  // fixed tiles row-major; kCounter by decreasing prediction (ties: tile index). Empty otherwise.
  std::vector<int32_t> order;
  // Per tile, what a thief weighs a list by: the prediction, or the tile's pixels before the
  // first prediction.
  std::vector<double> weight;
};

// What End measured and did.
struct TilePlanReport {
  bool pbt = false;
  bool has_prediction = false;
  PredictionAccuracy accuracy;    // predicted vs measured costs (if has_prediction)
  double worker_imbalance = 1.0;  // FrameImbalance of the workers' measured costs
  // The paper's master-worker (§2), demand driven with the §4 affinity (SimulateDemandDriven on
  // the lists, the steal weights and the measured costs; demand: SimulateDemandMaster on the
  // lists' owners; kCounter: list scheduling in the counter's order): the slowest / mean worker
  // finish time. What a cluster of n workers that asks the master for tiles would have had.
  double demand_imbalance = 1.0;
  double predicted_makespan = 0;  // the largest predicted worker load (if has_prediction)
  // Not in the paper, a model like demand_imbalance: static lists by LPT over this frame's
  // predictions (AssignLpt, no stealing), charged the measured costs (if has_prediction; 1
  // otherwise). What list scheduling on the predictions alone achieves.
  double lpt_imbalance = 1.0;
  PbtUpdateStats update;          // the PBT-Update run after this frame (not for static)
};

// What a backend measured beyond the tile costs, for the cost-map predictor (all optional).
// Without `blocks` the map spreads each tile's cost evenly over its pixels; without both
// cameras or the pixels' hit distances it is not reprojected.
struct TilePlanMeasure {
  // The frame's per-block work, summed over the workers (the plan's block_work() layout). Its
  // total is scaled to the tiles' total cost (1 up to rounding for the work cost), so wall or
  // cpu costs give a map in seconds.
  const BlockWork* blocks = nullptr;
  // Per pixel the primary hit distance (+inf: a miss; NaN: unknown), width x height, for the
  // reprojection (empty: not reprojected).
  std::span<const float> pixel_depth;
  const CameraBasis* camera = nullptr;       // the frame's camera
  const CameraBasis* next_camera = nullptr;  // the next frame's (FrameContext::next_camera)
};

// Begin / End alternate, once per frame; single-threaded (the master / application thread).
// Every buffer of the plan (the frame's vectors, PBT-Update's, the frame models') is reused, so
// after the first frame Begin and End allocate nothing (PBT-Visit: once each worker's list has
// held its longest run; tests/sched/alloc_test counts it).
//   TilePlan plan(w, h, options);
//   for each frame: const TilePlanFrame& f = plan.Begin();  render f.tiles as f says;
//                   TilePlanReport r = plan.End(measured costs per tile, who ran each tile);
class TilePlan {
 public:
  // Throws rs::Error (ValidateTilePlanOptions; Pbt: image size, more tiles than pixels).
  TilePlan(int width, int height, const TilePlanOptions& options);
  ~TilePlan();
  TilePlan(const TilePlan&) = delete;
  TilePlan& operator=(const TilePlan&) = delete;

  int width() const { return width_; }
  int height() const { return height_; }
  const TilePlanOptions& options() const { return options_; }
  bool uses_pbt() const { return options_.pbt_tiles_per_worker > 0; }
  // The tree the next frame is (or this frame was) tiled with; nullptr for fixed tiles.
  const Pbt* pbt() const { return pbt_.get(); }
  uint64_t frames() const { return frames_; }  // frames ended

  // This frame's tiles, predictions and lists. Throws rs::Error if the frame has begun.
  const TilePlanFrame& Begin();
  // The frame's measured costs per tile (size = tiles, finite, >= 0). ran_by (kCounter and
  // demand only, optional): per tile the worker that took it, in [0, workers), when the workers
  // are real (cell: the SPEs; tiles: as many threads as workers); without it the worker
  // imbalance is the demand_imbalance (the workers a model: tiles backend threads != workers).
  // With static lists the list owner is charged (as SimulateDemandDriven models a steal) and
  // ran_by is ignored.
  // Computes the Table 1 accuracy, the worker imbalance and the predicted makespan,
  // then PBT-Update (not for static) and the next frame's assignment. Fixed tiles: the report
  // only says pbt = false. Throws rs::Error (no Begin, sizes, bad costs or workers).
  // measure: the cost-map predictor's inputs (ignored by kPaper and static).
  TilePlanReport End(std::span<const double> costs, std::span<const int32_t> ran_by = {},
                     const TilePlanMeasure& measure = {});
  // The cost-map predictor's block layout: width x height in options().cost_block blocks, or
  // block == 0 if the plan does not use one (fixed tiles, kPaper, static). A backend sizes its
  // engines' BlockWork like this (BlockWork::Resize) and passes their sum to End.
  bool uses_cost_map() const;
  // The map PBT-Update last predicted with (after End; empty before the first).
  const CostMap& cost_map() const { return map_; }
  // Ends a frame that failed (no measurements): the plan is unchanged, the next Begin gives the
  // same tiles and lists again. No-op outside a frame.
  void Cancel() { in_frame_ = false; }

 private:
  void Plan();  // frame_ from pbt_ / the grid for the next frame
  void BuildCostMap(std::span<const double> costs, const TilePlanMeasure& measure);
  std::span<const double> ListSchedule(std::span<const int32_t> order,
                                       std::span<const double> cost);

  int width_ = 0;
  int height_ = 0;
  TilePlanOptions options_;
  std::unique_ptr<Pbt> pbt_;
  std::vector<double> static_costs_;  // static: the previous frame's cost per tile
  CostMap map_;                       // kCostMap: this frame's costs, reprojected
  TilePlanFrame frame_;
  // Scratch kept between frames, so Plan and End allocate nothing once sized (pbt.h).
  std::vector<double> known_;   // Plan: the predictions, 0 before the first
  std::vector<double> lpt_known_;  // Plan (lpt): the predictions, the pixels before the first
  std::vector<double> loads_;   // End: per-worker loads
  std::vector<int32_t> lpt_order_;     // End: tiles in LPT order
  std::vector<double> lpt_predicted_;  // End: per worker, the LPT lists' predicted loads
  DemandDrivenModel demand_model_;
  uint64_t frames_ = 0;
  bool in_frame_ = false;
};

}  // namespace rs
