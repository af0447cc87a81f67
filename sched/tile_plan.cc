// The tile plan (tile_plan.h): fixed tiles or the per-frame PBT policy, the deterministic tile
// work cost and its calibrated coefficients. Scalar code run once per frame by the master.
#include "sched/tile_plan.h"

#include <fmt/core.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <numeric>
#include <string>

#include "include/raystream/raystream.h"
#include "sched/render.h"

namespace rs {

const char* PbtAssignName(PbtAssign assign) {
  switch (assign) {
    case PbtAssign::kRandom:
      return "random";
    case PbtAssign::kGreedy:
      return "greedy";
    case PbtAssign::kVisit:
      return "visit";
    case PbtAssign::kStatic:
      return "static";
    case PbtAssign::kCounter:
      return "counter";
    case PbtAssign::kLpt:
      return "lpt";
  }
  return "?";
}

bool ParsePbtAssign(std::string_view name, PbtAssign* assign) {
  for (const PbtAssign a : {PbtAssign::kRandom, PbtAssign::kGreedy, PbtAssign::kVisit,
                            PbtAssign::kStatic, PbtAssign::kCounter, PbtAssign::kLpt}) {
    if (name == PbtAssignName(a)) {
      *assign = a;
      return true;
    }
  }
  return false;
}

const char* PbtCostName(PbtCost cost) {
  switch (cost) {
    case PbtCost::kWall:
      return "wall";
    case PbtCost::kCpu:
      return "cpu";
    case PbtCost::kWork:
      return "work";
  }
  return "?";
}

bool ParsePbtCost(std::string_view name, PbtCost* cost) {
  for (const PbtCost c : {PbtCost::kWall, PbtCost::kCpu, PbtCost::kWork}) {
    if (name == PbtCostName(c)) {
      *cost = c;
      return true;
    }
  }
  return false;
}

const char* PbtPredictName(PbtPredict predict) {
  switch (predict) {
    case PbtPredict::kPaper:
      return "paper";
    case PbtPredict::kCostMap:
      return "costmap";
  }
  return "?";
}

bool ParsePbtPredict(std::string_view name, PbtPredict* predict) {
  for (const PbtPredict p : {PbtPredict::kPaper, PbtPredict::kCostMap}) {
    if (name == PbtPredictName(p)) {
      *predict = p;
      return true;
    }
  }
  return false;
}

// ---------------------------------------------------------------------------------------------
// Deterministic tile work.

TileWork TileWorkDelta(const FrameStats& after, const FrameStats& before) {
  TileWork w;
  w.rays = after.TotalRays() - before.TotalRays();
  w.cell_steps = after.trace.cell_steps - before.trace.cell_steps;
  w.triangle_tests = after.trace.triangle_tests - before.trace.triangle_tests;
  w.shading_calls = after.shade.shading_calls - before.shade.shading_calls;
  return w;
}

// Calibration: `bench/sched/sched_bench --only calibrate` (bench/results/sched/calibrate.txt, one
// row per tile in calibrate.csv): one render thread of the tiles backend, 16x16 tiles, depth 4,
// frames 1-3 of the walk-throughs of erw6, cornell, spherebox and amphitheater:4 at 256x256
// (3072 tiles), release build with the batched frame engine (57fe039), AVX2 target, on the
// 2-core development machine, shared (load average 9.3: other builds and tests running);
// non-negative least squares without intercept of each tile's thread CPU time against its four
// counts: R^2 0.98, three runs within 7 % of each other (this is the median one). The shading
// calls' own fit came out negative (they go with the rays: one per hit), so their cost is in
// per_ray. The coefficients only have to be fixed, not exact: PBT compares a tile's cost with
// the same tile's cost one frame later.
const TileWorkCoefficients kTileWorkCoefficients = {
    /*per_ray=*/5.43e-8,
    /*per_cell_step=*/6.77e-9,
    /*per_triangle_test=*/1.82e-9,
    /*per_shading_call=*/0.0,
};

double TileWorkCost(const TileWork& w, const TileWorkCoefficients& c) {
  double cost = c.per_ray * static_cast<double>(w.rays);
  cost += c.per_cell_step * static_cast<double>(w.cell_steps);
  cost += c.per_triangle_test * static_cast<double>(w.triangle_tests);
  cost += c.per_shading_call * static_cast<double>(w.shading_calls);
  return cost;
}

// ---------------------------------------------------------------------------------------------
// Tiling.

std::vector<Tile> GridTiles(int width, int height, int tw, int th) {
  if (width < 1 || height < 1 || tw < 1 || th < 1) {
    throw Error(fmt::format("tiles: image {}x{} in {}x{} tiles: sizes must be at least 1", width,
                            height, tw, th));
  }
  std::vector<Tile> tiles;
  ImageTiles(width, height, tw, th, tiles);  // a tile larger than the image is clamped to it
  return tiles;
}

uint64_t PbtRandomSeed(uint64_t seed, uint64_t frame) {
  return seed ^ (0x9E3779B97F4A7C15ull * (frame + 1));
}

void ValidateTilePlanOptions(const TilePlanOptions& o) {
  auto fail = [](const std::string& what) { throw Error("tile plan: " + what); };
  if (o.tile_width < 1 || o.tile_height < 1) {
    fail(fmt::format("tile {}x{} must be at least 1x1", o.tile_width, o.tile_height));
  }
  if (o.pbt_tiles_per_worker < 0 || o.pbt_tiles_per_worker > 4096) {
    fail(fmt::format("pbt tiles per worker {} must be in [0, 4096]", o.pbt_tiles_per_worker));
  }
  if (o.workers < 1 || o.workers > 65536) {
    fail(fmt::format("workers {} must be in [1, 65536]", o.workers));
  }
  const int assign = static_cast<int>(o.assign);
  if (assign < 0 || assign > static_cast<int>(PbtAssign::kLpt)) {
    fail(fmt::format("unknown PBT assignment {}", assign));
  }
  const int cost = static_cast<int>(o.cost);
  if (cost < 0 || cost > static_cast<int>(PbtCost::kWork)) {
    fail(fmt::format("unknown PBT cost {}", cost));
  }
  const int predict = static_cast<int>(o.predict);
  if (predict < 0 || predict > static_cast<int>(PbtPredict::kCostMap)) {
    fail(fmt::format("unknown PBT predictor {}", predict));
  }
  if (o.cost_block < 1 || o.cost_block > 256) {
    fail(fmt::format("cost map block {} must be in [1, 256] pixels", o.cost_block));
  }
  if (o.steal && o.pbt_tiles_per_worker == 0) {
    fail("stealing needs a PBT tiling (pbt tiles per worker > 0)");
  }
  if (o.steal && o.assign == PbtAssign::kCounter) {
    fail("stealing needs per-worker lists; assignment counter has none (one shared counter)");
  }
  if (o.demand && o.pbt_tiles_per_worker == 0) {
    fail("the demand-driven master needs a PBT tiling (pbt tiles per worker > 0)");
  }
  if (o.demand && o.assign == PbtAssign::kCounter) {
    fail("the demand-driven master needs per-worker lists as its affinity; assignment counter "
         "has none");
  }
  if (o.demand && o.steal) {
    fail("stealing and the demand-driven master exclude each other (the master hands out every "
         "tile)");
  }
}

// ---------------------------------------------------------------------------------------------
// The plan.

TilePlan::TilePlan(int width, int height, const TilePlanOptions& options)
    : width_(width), height_(height), options_(options) {
  ValidateTilePlanOptions(options_);
  if (width < 1 || height < 1) {
    throw Error(fmt::format("tile plan: image {}x{} must be at least 1x1", width, height));
  }
  if (uses_pbt()) {
    pbt_ = std::make_unique<Pbt>(width, height, options_.workers, options_.pbt_tiles_per_worker);
  }
  if (uses_pbt()) {
    // End's LPT model runs from the second frame on: its buffers sized now.
    lpt_order_.reserve(pbt_->NumLeaves());
    if (options_.assign == PbtAssign::kLpt) {
      // LPT lists vary in length from frame to frame: room for 4 k + 16 tiles each (more only
      // when one worker gets that many tiny tiles).
      const size_t room = 4 * static_cast<size_t>(options_.pbt_tiles_per_worker) + 16;
      frame_.assignment.tiles.resize(static_cast<size_t>(options_.workers));
      for (std::vector<int32_t>& list : frame_.assignment.tiles) {
        list.reserve(std::min(room, pbt_->NumLeaves()));
      }
    }
    lpt_predicted_.reserve(static_cast<size_t>(options_.workers));
    loads_.reserve(static_cast<size_t>(options_.workers));
  }
  if (uses_cost_map()) {
    // Sized once: End fills them in place every frame.
    map_.Resize(width, height, options_.cost_block);
  }
  Plan();
}

bool UsesCostMap(const TilePlanOptions& options) {
  return options.pbt_tiles_per_worker > 0 && options.predict == PbtPredict::kCostMap &&
         options.assign != PbtAssign::kStatic;
}

bool TilePlan::uses_cost_map() const { return UsesCostMap(options_); }

TilePlan::~TilePlan() = default;

void TilePlan::Plan() {
  // Every vector is refilled in place, its capacity reused every frame (tile_plan.h).
  TilePlanFrame& f = frame_;
  f.frame = frames_;
  f.owner.clear();
  f.order.clear();
  if (!pbt_ || options_.assign == PbtAssign::kCounter) {
    f.assignment.tiles.clear();  // no lists
    f.assignment.predicted_load.clear();
  }
  if (!pbt_) {
    // The same tiles as GridTiles, into the frame's vector (its capacity reused every frame).
    ImageTiles(width_, height_, options_.tile_width, options_.tile_height, f.tiles);
    f.has_prediction = false;
    f.predicted.assign(f.tiles.size(), -1.0);
    f.order.resize(f.tiles.size());
    std::iota(f.order.begin(), f.order.end(), int32_t{0});
    f.weight.resize(f.tiles.size());
    for (size_t i = 0; i < f.tiles.size(); ++i) {
      f.weight[i] = static_cast<double>(f.tiles[i].NumPixels());
    }
    return;
  }
  const Pbt& pbt = *pbt_;
  const size_t m = pbt.NumLeaves();
  const int n = options_.workers;
  pbt.Tiles(f.tiles);
  f.has_prediction = frames_ > 0;
  // The prediction a tile is measured against: PBT's estimate, or for the never-updated static
  // tiling the same tile's cost in the previous frame.
  std::vector<double>& known = known_;  // predictions, 0 before the first
  if (!f.has_prediction) {
    known.assign(m, 0.0);
  } else if (options_.assign == PbtAssign::kStatic) {
    known = static_costs_;
  } else {
    pbt.Estimates(known);
  }
  if (f.has_prediction) {
    f.predicted = known;
  } else {
    f.predicted.assign(m, -1.0);
  }
  switch (options_.assign) {
    case PbtAssign::kGreedy:
      AssignPbtGreedy(pbt, f.assignment);
      break;
    case PbtAssign::kVisit:
      AssignPbtVisit(pbt, f.assignment);
      break;
    case PbtAssign::kStatic:
      // The permutation depends on m and the seed only: the same lists every frame.
      AssignRandom(known, n, options_.seed, f.assignment);
      break;
    case PbtAssign::kRandom:
      AssignRandom(known, n, PbtRandomSeed(options_.seed, frames_), f.assignment);
      break;
    case PbtAssign::kLpt:
      // Before the first prediction the tiles' pixels stand in (equal zeros would give every
      // tile to worker 0).
      if (f.has_prediction) {
        AssignLpt(known, n, f.assignment, lpt_order_);
      } else {
        lpt_known_.resize(m);
        for (size_t i = 0; i < m; ++i) {
          lpt_known_[i] = static_cast<double>(f.tiles[i].NumPixels());
        }
        AssignLpt(lpt_known_, n, f.assignment, lpt_order_);
        f.assignment.predicted_load.assign(static_cast<size_t>(n), 0.0);  // no prediction yet
      }
      break;
    case PbtAssign::kCounter: {
      // Decreasing prediction, ties by tile index: a strict total order (the predictions are
      // finite), so std::sort gives what a stable sort on the prediction alone gives, without
      // the stable sort's temporary buffer.
      f.order.resize(m);
      std::iota(f.order.begin(), f.order.end(), int32_t{0});
      std::sort(f.order.begin(), f.order.end(), [&](int32_t a, int32_t b) {
        const double ka = known[static_cast<size_t>(a)], kb = known[static_cast<size_t>(b)];
        return ka != kb ? ka > kb : a < b;
      });
      break;
    }
  }
  if (options_.assign != PbtAssign::kCounter) {
    f.owner.assign(m, -1);
    for (size_t w = 0; w < f.assignment.tiles.size(); ++w) {
      for (const int32_t t : f.assignment.tiles[w]) {
        f.owner[static_cast<size_t>(t)] = static_cast<int32_t>(w);
      }
    }
  }
  // Before the first measurement, stealing goes by area.
  f.weight.resize(m);
  for (size_t i = 0; i < m; ++i) {
    f.weight[i] = f.has_prediction ? known[i] : static_cast<double>(f.tiles[i].NumPixels());
  }
}

// List scheduling: each tile of `order` to the worker with the least load so far (ties: id),
// into loads_ (options_.workers of them).
std::span<const double> TilePlan::ListSchedule(std::span<const int32_t> order,
                                               std::span<const double> cost) {
  loads_.assign(static_cast<size_t>(options_.workers), 0.0);
  for (const int32_t t : order) {
    const size_t w =
        static_cast<size_t>(std::min_element(loads_.begin(), loads_.end()) - loads_.begin());
    loads_[w] += cost[static_cast<size_t>(t)];
  }
  return loads_;
}

const TilePlanFrame& TilePlan::Begin() {
  if (in_frame_) throw Error("tile plan: Begin while a frame is running (call End)");
  in_frame_ = true;
  return frame_;
}

TilePlanReport TilePlan::End(std::span<const double> costs, std::span<const int32_t> ran_by,
                             const TilePlanMeasure& measure) {
  if (!in_frame_) throw Error("tile plan: End without Begin");
  const size_t m = frame_.tiles.size();
  if (costs.size() != m) {
    throw Error(fmt::format("tile plan: {} costs for {} tiles", costs.size(), m));
  }
  for (size_t i = 0; i < m; ++i) {
    if (!std::isfinite(costs[i]) || costs[i] < 0.0) {
      throw Error(
          fmt::format("tile plan: tile {} has cost {} (must be finite and >= 0)", i, costs[i]));
    }
  }
  const bool counter = uses_pbt() && options_.assign == PbtAssign::kCounter;
  const bool demand = uses_pbt() && options_.demand;
  if ((counter || demand) && !ran_by.empty() && ran_by.size() != m) {
    throw Error(fmt::format("tile plan: {} workers given for {} tiles", ran_by.size(), m));
  }
  TilePlanReport r;
  if (uses_pbt()) {
    const int n = options_.workers;
    r.pbt = true;
    r.has_prediction = frame_.has_prediction;
    if (r.has_prediction) r.accuracy = MeasurePredictionAccuracy(frame_.predicted, costs);
    if (counter || demand) {
      if (counter) {
        r.demand_imbalance = FrameImbalance(ListSchedule(frame_.order, costs));
      } else {
        r.demand_imbalance = FrameImbalance(demand_model_.Master(frame_.owner, n, costs).finish);
      }
      r.worker_imbalance = r.demand_imbalance;
      if (!ran_by.empty()) {  // the workers that really took the tiles
        std::vector<double>& load = loads_;
        load.assign(static_cast<size_t>(n), 0.0);
        for (size_t i = 0; i < m; ++i) {
          if (ran_by[i] < 0 || ran_by[i] >= n) {
            throw Error(fmt::format("tile plan: tile {} ran on worker {} of {}", i, ran_by[i], n));
          }
          load[static_cast<size_t>(ran_by[i])] += costs[i];
        }
        r.worker_imbalance = FrameImbalance(load);
      }
      // A shared counter in decreasing order is LPT list scheduling on the predictions (the
      // counter's order is AssignLpt's: decreasing prediction, ties by index); the demand
      // master's preference is the lists.
      if (r.has_prediction) {
        if (counter) {
          const std::span<const double> loads = ListSchedule(frame_.order, frame_.predicted);
          r.predicted_makespan = std::max(0.0, *std::max_element(loads.begin(), loads.end()));
        } else {
          r.predicted_makespan = frame_.assignment.PredictedMakespan();
        }
      }
    } else {
      // WorkerTimes(frame_.assignment, costs), into loads_.
      loads_.assign(frame_.assignment.tiles.size(), 0.0);
      for (size_t w = 0; w < loads_.size(); ++w) {
        for (const int32_t t : frame_.assignment.tiles[w]) {
          loads_[w] += costs[static_cast<size_t>(t)];
        }
      }
      r.worker_imbalance = FrameImbalance(loads_);
      r.demand_imbalance =
          FrameImbalance(demand_model_.Driven(frame_.assignment, frame_.weight, costs).finish);
      if (r.has_prediction) r.predicted_makespan = frame_.assignment.PredictedMakespan();
    }
    if (r.has_prediction) {
      // AssignLpt's lists (decreasing prediction, ties by index, each to the least predicted
      // load, ties by id), kept as loads only: no per-worker lists to size.
      const std::vector<double>& p = frame_.predicted;
      lpt_order_.resize(m);
      std::iota(lpt_order_.begin(), lpt_order_.end(), int32_t{0});
      std::sort(lpt_order_.begin(), lpt_order_.end(), [&](int32_t a, int32_t b) {
        const double pa = p[static_cast<size_t>(a)], pb = p[static_cast<size_t>(b)];
        return pa != pb ? pa > pb : a < b;
      });
      lpt_predicted_.assign(static_cast<size_t>(n), 0.0);
      loads_.assign(static_cast<size_t>(n), 0.0);
      for (const int32_t t : lpt_order_) {
        const size_t w = static_cast<size_t>(
            std::min_element(lpt_predicted_.begin(), lpt_predicted_.end()) -
            lpt_predicted_.begin());
        lpt_predicted_[w] += p[static_cast<size_t>(t)];
        loads_[w] += costs[static_cast<size_t>(t)];
      }
      r.lpt_imbalance = FrameImbalance(loads_);
    }
    if (options_.assign == PbtAssign::kStatic) {
      static_costs_.assign(costs.begin(), costs.end());  // tiling and lists stay as they are
    } else if (uses_cost_map()) {
      BuildCostMap(costs, measure);
      r.update = pbt_->Update(costs, map_);  // Algorithm 1 with the cost-map predictor
    } else {
      r.update = pbt_->Update(costs);  // Algorithm 1 between frames
    }
  }
  ++frames_;
  in_frame_ = false;
  Plan();
  return r;
}

// The frame's cost map: the backend's block work (scaled to the tiles' total cost) or each
// tile's cost spread over its pixels; then moved to the next camera (cost_map.h).
void TilePlan::BuildCostMap(std::span<const double> costs, const TilePlanMeasure& measure) {
  const BlockWork* blocks = measure.blocks;
  if (blocks != nullptr && !blocks->Matches(width_, height_, options_.cost_block)) {
    throw Error(fmt::format("tile plan: block work of {}x{} in {}-pixel blocks for a {}x{} plan "
                            "in {}-pixel blocks",
                            blocks->width, blocks->height, blocks->block, width_, height_,
                            options_.cost_block));
  }
  double total = 0.0;
  for (const double c : costs) total += c;
  int64_t work = 0;
  if (blocks != nullptr) {
    for (const int64_t w : blocks->work) work += w;
  }
  if (blocks != nullptr && work > 0) {
    map_.SetFromWork(*blocks, total / (static_cast<double>(work) * kBlockWorkUnit));
  } else {
    map_.Clear();
    for (size_t i = 0; i < frame_.tiles.size(); ++i) map_.AddTile(frame_.tiles[i], costs[i]);
  }
  if (measure.camera == nullptr || measure.next_camera == nullptr) return;
  if (measure.pixel_depth.size() != static_cast<size_t>(width_) * static_cast<size_t>(height_)) {
    return;
  }
  map_.Reproject(*measure.camera, *measure.next_camera, measure.pixel_depth);
}

}  // namespace rs
