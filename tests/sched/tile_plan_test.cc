// The tile plan (sched/tile_plan.h): fixed tiles, the per-frame PBT policy against a mirror Pbt
// driven by hand (PBT-Update, every assignment, PBT-Random seeding, static predictions, the
// counter order, steal weights), the Table 1 measures, misuse, and the deterministic work cost:
// a moving-camera walk-through's prediction accuracy with --pbt-cost work is the same in every
// run and for any number of threads.
#include "sched/tile_plan.h"

#include <doctest/doctest.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <memory>
#include <numeric>
#include <string>
#include <vector>

#include "include/raystream/raystream.h"
#include "scenes/load.h"
#include "sched/backends.h"
#include "sched/engine.h"
#include "sched/render.h"

namespace rs {
namespace {

bool SameTiles(const std::vector<Tile>& a, const std::vector<Tile>& b) {
  if (a.size() != b.size()) return false;
  for (size_t i = 0; i < a.size(); ++i) {
    if (a[i].x0 != b[i].x0 || a[i].y0 != b[i].y0 || a[i].x1 != b[i].x1 || a[i].y1 != b[i].y1) {
      return false;
    }
  }
  return true;
}

// A deterministic uneven cost per tile: its area times a weight that grows to the right.
std::vector<double> Costs(const std::vector<Tile>& tiles, double skew) {
  std::vector<double> c;
  for (const Tile& t : tiles) {
    c.push_back(static_cast<double>(t.NumPixels()) * (1.0 + skew * (t.x0 + t.x1) / 2.0));
  }
  return c;
}

TEST_CASE("names of assignments and costs") {
  for (const PbtAssign a : {PbtAssign::kRandom, PbtAssign::kGreedy, PbtAssign::kVisit,
                            PbtAssign::kStatic, PbtAssign::kCounter, PbtAssign::kLpt}) {
    PbtAssign b = PbtAssign::kRandom;
    CHECK(ParsePbtAssign(PbtAssignName(a), &b));
    CHECK(b == a);
  }
  PbtAssign keep = PbtAssign::kVisit;
  CHECK_FALSE(ParsePbtAssign("sjf", &keep));
  CHECK(keep == PbtAssign::kVisit);
  for (const PbtCost c : {PbtCost::kWall, PbtCost::kCpu, PbtCost::kWork}) {
    PbtCost d = PbtCost::kWall;
    CHECK(ParsePbtCost(PbtCostName(c), &d));
    CHECK(d == c);
  }
  PbtCost cost = PbtCost::kCpu;
  CHECK_FALSE(ParsePbtCost("cycles", &cost));
  CHECK(cost == PbtCost::kCpu);
  for (const PbtPredict p : {PbtPredict::kPaper, PbtPredict::kCostMap}) {
    PbtPredict q = PbtPredict::kPaper;
    CHECK(ParsePbtPredict(PbtPredictName(p), &q));
    CHECK(q == p);
  }
  PbtPredict predict = PbtPredict::kPaper;
  CHECK_FALSE(ParsePbtPredict("cost-map", &predict));  // an unknown value is refused
  CHECK_FALSE(ParsePbtPredict("", &predict));
  CHECK(predict == PbtPredict::kPaper);
  CHECK(TilePlanOptions{}.predict == PbtPredict::kCostMap);  // the default
}

TEST_CASE("GridTiles: row-major, partial at the edges, clamped, covering every pixel once") {
  const std::vector<Tile> t = GridTiles(10, 7, 4, 3);
  REQUIRE(t.size() == 9);
  CHECK(t[0].x0 == 0);
  CHECK(t[0].x1 == 4);
  CHECK(t[2].x0 == 8);
  CHECK(t[2].x1 == 10);  // partial at the right
  CHECK(t[8].y0 == 6);
  CHECK(t[8].y1 == 7);  // partial at the bottom
  size_t pixels = 0;
  for (const Tile& x : t) pixels += x.NumPixels();
  CHECK(pixels == 70);
  const std::vector<Tile> clamped = GridTiles(10, 7, 640, 2);  // wider than the image
  REQUIRE(clamped.size() == 4);
  CHECK(clamped[0].x1 == 10);
  CHECK(GridTiles(5, 5, 1, 1).size() == 25);
  CHECK_THROWS_AS(GridTiles(0, 5, 1, 1), Error);
  CHECK_THROWS_AS(GridTiles(5, 5, 0, 1), Error);
}

TEST_CASE("TileWorkCost: the counts times the coefficients; TileWorkDelta: the counters added") {
  const TileWorkCoefficients c{1.0, 2.0, 3.0, 4.0};
  CHECK(TileWorkCost(TileWork{1, 10, 100, 1000}, c) == 1.0 + 20.0 + 300.0 + 4000.0);
  CHECK(TileWorkCost(TileWork{}) == 0.0);
  CHECK(kTileWorkCoefficients.per_ray > 0);
  CHECK(kTileWorkCoefficients.per_cell_step > 0);
  CHECK(kTileWorkCoefficients.per_triangle_test > 0);
  CHECK(kTileWorkCoefficients.per_shading_call >= 0);  // 0: fitted into per_ray
  FrameStats before, after;
  before.rays[0] = 5;
  before.trace.cell_steps = 7;
  after.rays[0] = 9;
  after.rays[1] = 3;
  after.trace.cell_steps = 17;
  after.trace.triangle_tests = 4;
  after.shade.shading_calls = 2;
  const TileWork w = TileWorkDelta(after, before);
  CHECK(w.rays == 7);
  CHECK(w.cell_steps == 10);
  CHECK(w.triangle_tests == 4);
  CHECK(w.shading_calls == 2);
}

TEST_CASE("fixed tiles: the grid in row-major order every frame, no PBT report") {
  TilePlanOptions o;
  o.tile_width = 16;
  o.tile_height = 8;
  TilePlan plan(40, 20, o);
  CHECK_FALSE(plan.uses_pbt());
  CHECK(plan.pbt() == nullptr);
  for (int f = 0; f < 2; ++f) {
    const TilePlanFrame& frame = plan.Begin();
    CHECK(frame.frame == static_cast<uint64_t>(f));
    CHECK(SameTiles(frame.tiles, GridTiles(40, 20, 16, 8)));
    CHECK_FALSE(frame.has_prediction);
    CHECK(frame.assignment.tiles.empty());
    REQUIRE(frame.order.size() == frame.tiles.size());
    for (size_t i = 0; i < frame.order.size(); ++i) CHECK(frame.order[i] == static_cast<int>(i));
    for (const double p : frame.predicted) CHECK(p == -1.0);
    const TilePlanReport r = plan.End(std::vector<double>(frame.tiles.size(), 1.0));
    CHECK_FALSE(r.pbt);
  }
  CHECK(plan.frames() == 2);
}

// The plan against a Pbt of its own driven by hand with the same costs: tiles, predictions,
// lists, update steps and measures must agree frame by frame for every assignment.
TEST_CASE("PBT: the plan runs Algorithm 1 and the assignments as a hand-driven mirror does") {
  const int w = 64, h = 48, n = 5, k = 3;
  for (const PbtPredict predict : {PbtPredict::kPaper, PbtPredict::kCostMap})
  for (const PbtAssign assign : {PbtAssign::kRandom, PbtAssign::kGreedy, PbtAssign::kVisit,
                                 PbtAssign::kStatic, PbtAssign::kCounter, PbtAssign::kLpt}) {
    INFO("assign ", std::string(PbtAssignName(assign)), " predict ",
         std::string(PbtPredictName(predict)));
    TilePlanOptions o;
    o.pbt_tiles_per_worker = k;
    o.workers = n;
    o.assign = assign;
    o.predict = predict;
    o.seed = 99;
    o.steal = assign != PbtAssign::kCounter;
    TilePlan plan(w, h, o);
    Pbt mirror(w, h, n, k);
    std::vector<double> previous;  // static: the last frame's costs
    for (uint64_t f = 0; f < 5; ++f) {
      INFO("frame ", f);
      const TilePlanFrame& frame = plan.Begin();
      CHECK(frame.frame == f);
      REQUIRE(SameTiles(frame.tiles, mirror.Tiles()));
      const size_t m = frame.tiles.size();
      CHECK(m == static_cast<size_t>(n * k));
      CHECK(frame.has_prediction == (f > 0));
      std::vector<double> known(m, 0.0);
      if (f > 0) known = assign == PbtAssign::kStatic ? previous : mirror.Estimates();
      for (size_t i = 0; i < m; ++i) {
        CHECK(frame.predicted[i] == (f > 0 ? known[i] : -1.0));
        CHECK(frame.weight[i] ==
              (f > 0 ? known[i] : static_cast<double>(frame.tiles[i].NumPixels())));
      }
      Assignment want;
      switch (assign) {
        case PbtAssign::kRandom:
          want = AssignRandom(known, n, PbtRandomSeed(99, f));
          break;
        case PbtAssign::kGreedy:
          want = AssignPbtGreedy(mirror);
          break;
        case PbtAssign::kVisit:
          want = AssignPbtVisit(mirror);
          break;
        case PbtAssign::kStatic:
          want = AssignRandom(known, n, 99);  // the same lists every frame
          break;
        case PbtAssign::kCounter:
          break;
        case PbtAssign::kLpt: {
          // Before the first prediction by the tiles' pixels.
          std::vector<double> by = known;
          if (f == 0) {
            for (size_t i = 0; i < m; ++i) by[i] = static_cast<double>(frame.tiles[i].NumPixels());
          }
          want = AssignLpt(by, n);
          break;
        }
      }
      CHECK(frame.assignment.tiles == want.tiles);
      if (assign == PbtAssign::kCounter) {
        CHECK(frame.owner.empty());
        REQUIRE(frame.order.size() == m);
        for (size_t i = 1; i < m; ++i) {  // decreasing prediction, ties by index
          const double a = known[static_cast<size_t>(frame.order[i - 1])];
          const double b = known[static_cast<size_t>(frame.order[i])];
          CHECK((a > b || (a == b && frame.order[i - 1] < frame.order[i])));
        }
      } else {
        CHECK(frame.order.empty());
        for (size_t v = 0; v < want.tiles.size(); ++v) {
          for (const int32_t t : want.tiles[v]) {
            CHECK(frame.owner[static_cast<size_t>(t)] == static_cast<int32_t>(v));
          }
        }
      }
      const std::vector<double> costs = Costs(frame.tiles, 0.05 + 0.01 * static_cast<double>(f));
      std::vector<int32_t> ran_by(m);
      for (size_t i = 0; i < m; ++i) ran_by[i] = static_cast<int32_t>(i % n);
      const std::vector<double> weight = frame.weight;  // End re-plans `frame`
      // The cost map without block work: each tile's cost spread over its pixels.
      CostMap map;
      map.Resize(w, h, o.cost_block);
      for (size_t i = 0; i < m; ++i) map.AddTile(frame.tiles[i], costs[i]);
      const TilePlanReport r = plan.End(costs, ran_by);
      CHECK(r.pbt);
      CHECK(r.has_prediction == (f > 0));
      if (f > 0) {
        const PredictionAccuracy acc = MeasurePredictionAccuracy(known, costs);
        CHECK(r.accuracy.within10 == acc.within10);
        CHECK(r.accuracy.tiles == m);
      }
      CHECK(r.worker_imbalance >= 1.0);
      CHECK(r.demand_imbalance >= 1.0);
      if (assign == PbtAssign::kCounter) {
        std::vector<double> load(n, 0.0);
        for (size_t i = 0; i < m; ++i) load[i % n] += costs[i];
        CHECK(r.worker_imbalance == doctest::Approx(FrameImbalance(load)));
      } else {
        CHECK(r.worker_imbalance == FrameImbalance(WorkerTimes(want, costs)));
        CHECK(r.demand_imbalance ==
              FrameImbalance(SimulateDemandDriven(want, weight, costs).finish));
      }
      if (assign == PbtAssign::kStatic) {
        CHECK(r.update.steps == 0);
        previous = costs;
      } else {
        const PbtUpdateStats u = predict == PbtPredict::kPaper ? mirror.Update(costs)
                                                               : mirror.Update(costs, map);
        CHECK(r.update.steps == u.steps);
      }
      REQUIRE(plan.pbt() != nullptr);
      CHECK(plan.pbt()->Validate() == "");
    }
    if (assign != PbtAssign::kStatic) {
      CHECK_FALSE(SameTiles(plan.pbt()->Tiles(), Pbt(w, h, n, k).Tiles()));  // re-tiled
    }
  }
}

TEST_CASE("counter: costliest first; without the real workers the worker imbalance is a model") {
  TilePlanOptions o;
  o.pbt_tiles_per_worker = 4;
  o.workers = 2;
  o.assign = PbtAssign::kCounter;
  TilePlan plan(32, 32, o);
  const std::vector<Tile> tiles0 = plan.Begin().tiles;
  plan.End(Costs(tiles0, 0.2));
  const TilePlanFrame frame = plan.Begin();  // a copy: End re-plans
  REQUIRE(frame.has_prediction);
  const std::vector<double>& p = frame.predicted;
  const TilePlanReport r = plan.End(p);  // exact predictions, no ran_by
  CHECK(r.accuracy.within5 == 1.0);
  std::vector<double> finish(2, 0.0);  // list scheduling in the counter's order
  for (const int32_t t : frame.order) {
    *std::min_element(finish.begin(), finish.end()) += p[static_cast<size_t>(t)];
  }
  CHECK(r.demand_imbalance == FrameImbalance(finish));
  CHECK(r.worker_imbalance == r.demand_imbalance);
  CHECK(r.predicted_makespan == AssignLpt(p, 2).PredictedMakespan());
  CHECK(r.predicted_makespan == *std::max_element(finish.begin(), finish.end()));
}

TEST_CASE("demand: the lists as the affinity, the demand master's model, real workers charged") {
  TilePlanOptions o;
  o.pbt_tiles_per_worker = 3;
  o.workers = 2;
  o.assign = PbtAssign::kGreedy;
  o.demand = true;
  TilePlan plan(32, 32, o);
  const std::vector<Tile> tiles0 = plan.Begin().tiles;
  plan.End(Costs(tiles0, 0.2));
  const TilePlanFrame frame = plan.Begin();  // a copy: End re-plans
  REQUIRE(frame.has_prediction);
  REQUIRE(frame.owner.size() == 6u);
  CHECK(frame.order.empty());  // the master's order is the PBT's (tile index)
  const std::vector<double>& p = frame.predicted;
  const TilePlanReport r = plan.End(p);  // exact predictions, no ran_by: the model's workers
  CHECK(r.demand_imbalance == FrameImbalance(SimulateDemandMaster(frame.owner, 2, p).finish));
  CHECK(r.worker_imbalance == r.demand_imbalance);
  CHECK(r.predicted_makespan == frame.assignment.PredictedMakespan());
  // The workers that really ran the tiles: charged by ran_by, not by the lists' owners.
  const TilePlanFrame next = plan.Begin();
  std::vector<int32_t> ran_by(next.tiles.size(), 0);
  const std::vector<double> ones(next.tiles.size(), 1.0);
  CHECK(plan.End(ones, ran_by).worker_imbalance == 2.0);  // all on worker 0: 6 / mean 3
  plan.Begin();
  CHECK_THROWS_AS(plan.End(ones, std::vector<int32_t>(6, 2)), Error);  // no worker 2
  CHECK_THROWS_AS(plan.End(ones, std::vector<int32_t>(5, 0)), Error);  // sizes differ

  auto bad = [](TilePlanOptions x) { CHECK_THROWS_AS(ValidateTilePlanOptions(x), Error); };
  TilePlanOptions b;
  b.demand = true;  // without PBT
  bad(b);
  b.pbt_tiles_per_worker = 2;
  b.assign = PbtAssign::kCounter;  // no lists to prefer
  bad(b);
  b.assign = PbtAssign::kVisit;
  b.steal = true;  // the master hands out every tile
  bad(b);
  b.steal = false;
  CHECK_NOTHROW(ValidateTilePlanOptions(b));
}

TEST_CASE("misuse: Begin twice, End without Begin, bad costs, bad options; Cancel") {
  TilePlanOptions o;
  o.pbt_tiles_per_worker = 2;
  o.workers = 2;
  TilePlan plan(16, 16, o);
  CHECK_THROWS_AS(plan.End(std::vector<double>(4, 1.0)), Error);
  const std::vector<Tile> first = plan.Begin().tiles;
  CHECK_THROWS_AS(plan.Begin(), Error);
  CHECK_THROWS_AS(plan.End(std::vector<double>(3, 1.0)), Error);  // wrong size
  const double nan = std::numeric_limits<double>::quiet_NaN();
  CHECK_THROWS_AS(plan.End(std::vector<double>{1.0, nan, 1.0, 1.0}), Error);
  CHECK_THROWS_AS(plan.End(std::vector<double>{1.0, -1.0, 1.0, 1.0}), Error);
  // A failed frame: Cancel, then the same frame again.
  plan.Cancel();
  const TilePlanFrame& again = plan.Begin();
  CHECK(again.frame == 0);
  CHECK(SameTiles(again.tiles, first));
  CHECK(plan.End(std::vector<double>{1.0, 9.0, 1.0, 1.0}).pbt);
  CHECK(plan.frames() == 1);

  auto bad = [](TilePlanOptions x) { CHECK_THROWS_AS(ValidateTilePlanOptions(x), Error); };
  TilePlanOptions b;
  b.workers = 0;
  bad(b);
  b = TilePlanOptions{};
  b.tile_width = 0;
  bad(b);
  b = TilePlanOptions{};
  b.steal = true;  // without PBT
  bad(b);
  b.pbt_tiles_per_worker = 2;
  b.assign = PbtAssign::kCounter;  // no lists to steal from
  bad(b);
  b = TilePlanOptions{};
  b.pbt_tiles_per_worker = 4097;
  bad(b);
  b = TilePlanOptions{};
  b.cost = static_cast<PbtCost>(7);
  bad(b);
  b = TilePlanOptions{};
  b.predict = static_cast<PbtPredict>(7);
  CHECK_THROWS_WITH_AS(ValidateTilePlanOptions(b), "tile plan: unknown PBT predictor 7", Error);
  b = TilePlanOptions{};
  b.cost_block = 0;
  bad(b);
  CHECK_THROWS_AS(TilePlan(4, 4, TilePlanOptions{.pbt_tiles_per_worker = 5, .workers = 4}),
                  Error);  // 20 tiles > 16 pixels
}

// What --pbt-cost work is for: the tiles' work counts do not depend on timing, so PBT-Update,
// the tiling and the prediction accuracy of a walk-through are the same in every run, with any
// number of threads and with stealing; and on a procedural scene with a moving camera the
// predictions are mostly within 10 %.
TEST_CASE("work cost: a walk-through's prediction accuracy is reproducible, whatever the threads") {
  const Scene scene = LoadScene("erw6");
  const Accel accel(scene.mesh());
  RenderOptions ro;
  ro.width = 64;
  ro.height = 64;
  ro.max_depth = 3;
  const int frames = 6;
  struct Run {
    std::vector<PredictionAccuracy> accuracy;
    std::vector<int> steps;
    std::vector<std::vector<Tile>> tiles;
    std::vector<std::vector<double>> work;
  };
  auto walk = [&](int threads, bool steal) {
    BackendOptions o;
    o.kind = BackendKind::kTiles;
    o.threads = threads;
    o.pbt_tiles_per_worker = 2;
    o.pbt_workers = 8;
    o.assign = PbtAssign::kVisit;
    o.pbt_steal = steal;
    o.pbt_cost = PbtCost::kWork;
    HostRenderer r(o);
    Framebuffer fb(ro.width, ro.height);
    Run run;
    for (int f = 0; f < frames; ++f) {
      fb.Clear();
      FrameContext ctx = MakeFrameContext(scene, accel, scene.path.At(f, 2.0f, scene.camera), ro);
      // The cost map (the default predictor) is moved to the next camera.
      if (f + 1 < frames) SetNextCamera(ctx, scene.path.At(f + 1, 2.0f, scene.camera));
      const HostFrameStats& s = r.RenderFrame(ctx, fb);
      run.accuracy.push_back(s.accuracy);
      run.steps.push_back(s.update.steps);
      std::vector<Tile> tiles;
      std::vector<double> work;
      for (const TileRecord& t : s.tiles) {
        tiles.push_back(t.tile);
        work.push_back(t.work);
        CHECK(t.work == TileWorkCost(t.counts));
        CHECK(t.counts.rays == t.rays);
        if (f > 0) CHECK(t.predicted >= 0.0);
      }
      run.tiles.push_back(tiles);
      run.work.push_back(work);
    }
    return run;
  };
  const Run one = walk(1, false);
  const Run again = walk(1, false);
  const Run three = walk(3, true);
  double within10 = 0;
  int moved = 0;
  for (int f = 0; f < frames; ++f) {
    INFO("frame ", f);
    for (const Run* other : {&again, &three}) {
      CHECK(SameTiles(other->tiles[f], one.tiles[f]));
      CHECK(other->work[f] == one.work[f]);  // exact: the same doubles
      CHECK(other->steps[f] == one.steps[f]);
      CHECK(other->accuracy[f].within5 == one.accuracy[f].within5);
      CHECK(other->accuracy[f].within10 == one.accuracy[f].within10);
      CHECK(other->accuracy[f].within15 == one.accuracy[f].within15);
    }
    if (f > 0) within10 += one.accuracy[f].within10 / (frames - 1);
    moved += one.steps[f];
  }
  MESSAGE("mean share of predictions within 10 %: ", within10, ", update steps ", moved);
  CHECK(moved > 0);        // the walk-through re-tiles
  CHECK(within10 >= 0.6);  // a modest bound (64x64, camera speed 2, 16 tiles; 0.80 measured)
}

}  // namespace
}  // namespace rs

namespace rs {
namespace {

// The cost-map tests' frame: erw6 at 48x40, depth 3, `batch` rays per kernel call.
struct CostMapFrame {
  explicit CostMapFrame(int batch) : scene(LoadScene("erw6")), accel(scene.mesh()) {
    ro.width = 48;
    ro.height = 40;
    ro.max_depth = 3;
    ro.batch = batch;
    ctx = MakeFrameContext(scene, accel, scene.camera, ro);
  }
  const Scene scene;
  const Accel accel;
  RenderOptions ro;
  FrameContext ctx;
};

// The engine's block record: a tile's work lands in the blocks of its pixels, in total the
// tile's work cost (up to the fixed point's rounding), none outside; every pixel of the tile
// gets its primary hit distance.
TEST_CASE("cost map: the engine charges a tile's work to its blocks and stores hit distances") {
  const CostMapFrame frame(20);
  const RenderOptions& ro = frame.ro;
  const FrameContext& ctx = frame.ctx;
  BlockWork blocks;
  blocks.Resize(ro.width, ro.height, 8);
  CHECK(blocks.NumBlocks() == 6 * 5);
  std::vector<float> depth(static_cast<size_t>(ro.width * ro.height), -1.0f);
  blocks.pixel_depth = depth.data();
  SerialRenderer renderer;
  renderer.engine().SetBlockWork(&blocks);
  Framebuffer fb(ro.width, ro.height);
  const Tile tile{5, 3, 29, 21};  // not on block boundaries
  FrameStats stats;
  renderer.RenderTiles(ctx, &tile, 1, fb, stats);
  const double cost = TileWorkCost(TileWorkDelta(stats, FrameStats()));
  double charged = 0.0;
  for (int by = 0; by < blocks.blocks_y; ++by) {
    for (int bx = 0; bx < blocks.blocks_x; ++bx) {
      const int64_t w = blocks.work[static_cast<size_t>(by * blocks.blocks_x + bx)];
      const bool overlaps = bx * 8 < tile.x1 && (bx + 1) * 8 > tile.x0 && by * 8 < tile.y1 &&
                            (by + 1) * 8 > tile.y0;
      INFO("block ", bx, ",", by);
      CHECK((overlaps ? w > 0 : w == 0));
      charged += static_cast<double>(w) * kBlockWorkUnit;
    }
  }
  CHECK(charged == doctest::Approx(cost).epsilon(1e-9));
  for (int y = 0; y < ro.height; ++y) {
    for (int x = 0; x < ro.width; ++x) {
      const float t = depth[static_cast<size_t>(y * ro.width + x)];
      const bool inside = x >= tile.x0 && x < tile.x1 && y >= tile.y0 && y < tile.y1;
      CHECK((inside ? t > 0.0f : t == -1.0f));  // erw6 is a closed room: every ray hits
    }
  }
  // A plan fed this record predicts the tile's own rectangle as its cost (scaled to the
  // tiles' total: here the whole frame's work is this tile's).
  TilePlanOptions o;
  o.pbt_tiles_per_worker = 1;
  o.workers = 2;
  o.cost_block = 8;
  TilePlan plan(ro.width, ro.height, o);
  REQUIRE(plan.uses_cost_map());
  const std::vector<Tile> tiles = plan.Begin().tiles;
  std::vector<double> costs(tiles.size(), 0.0);
  for (size_t i = 0; i < tiles.size(); ++i) costs[i] = plan.cost_map().Predict(tiles[i]);
  costs[0] = cost;  // all of it in the first tile's list of costs: only the total matters
  TilePlanMeasure measure;
  measure.blocks = &blocks;
  plan.End(costs, {}, measure);
  CHECK(plan.cost_map().Total() == doctest::Approx(cost).epsilon(1e-12));
  double sum_blocks = 0.0;
  for (const int64_t w : blocks.work) sum_blocks += static_cast<double>(w) * kBlockWorkUnit;
  const CostMap& map = plan.cost_map();
  CHECK(map.Cost(1, 1) == doctest::Approx(static_cast<double>(blocks.work[1 * 6 + 1]) *
                                          kBlockWorkUnit * cost / sum_blocks));
  // Block work of another layout is refused.
  BlockWork other;
  other.Resize(ro.width, ro.height, 4);
  plan.Begin();
  measure.blocks = &other;
  CHECK_THROWS_AS(plan.End(costs, {}, measure), Error);
}

// The queue backends' path (TraceGeneration: rays carry their pixels, the caller grouped them):
// every ray is charged its own work (one ray, plus a shading call if it hit) to its pixel's
// block, so the record is the same however the rays are cut into calls and in whatever order
// the calls come (the threads of a queue backend pop different tasks together in every run;
// a call's cell steps and triangle tests depend on its packets, so sharing them out as
// RenderTile does would not be). Primary hit distances land at the rays' pixels.
TEST_CASE("cost map: a queue generation charges each ray its own work, in any grouping") {
  const CostMapFrame frame(64);
  const RenderOptions& ro = frame.ro;
  const FrameContext& ctx = frame.ctx;
  const Tile tile{5, 3, 13, 11};  // 64 pixels, not on block boundaries
  RayStream primaries;
  primaries.Resize(tile.NumPixels());
  GeneratePrimaryRays(ctx.camera, tile, ro.order, 0, tile.NumPixels(), primaries.view(), 0);
  primaries.SealTail();
  // `rays` traced as one generation, or cut into `cuts` parts traced last part first (each its
  // own sealed stream); returns the record, the hit distances and the shadow rays spawned.
  struct Record {
    BlockWork blocks;
    std::vector<float> depth;
    RayStream shadow;
    FrameStats stats;
  };
  auto trace = [&](RayStream& rays, bool shadow, int cuts) {
    Record r;
    r.blocks.Resize(ro.width, ro.height, 8);
    r.depth.assign(static_cast<size_t>(ro.width * ro.height), -1.0f);
    r.blocks.pixel_depth = r.depth.data();
    RayEngine engine;
    engine.SetBlockWork(&r.blocks);
    Framebuffer fb(ro.width, ro.height);
    RayStream bounce;
    const size_t n = rays.size();
    const size_t part = (n + static_cast<size_t>(cuts) - 1) / static_cast<size_t>(cuts);
    for (int c = cuts - 1; c >= 0; --c) {
      const size_t first = static_cast<size_t>(c) * part;
      if (first >= n) continue;
      RayStream piece;
      piece.Append(rays.view(), first, std::min(part, n - first));
      piece.SealTail();
      const RayStreamView none{};
      engine.TraceGeneration(ctx, shadow ? piece.view() : none, shadow ? none : piece.view(), fb,
                             r.shadow, bounce, r.stats);
    }
    return r;
  };
  TileWork one;
  one.rays = 1;
  const int64_t ray = std::llround(TileWorkCost(one) / kBlockWorkUnit);
  one.shading_calls = 1;
  const int64_t shaded = std::llround(TileWorkCost(one) / kBlockWorkUnit);
  REQUIRE(ray > 0);

  Record whole = trace(primaries, false, 1);
  const Record halves = trace(primaries, false, 2);
  const Record fifths = trace(primaries, false, 5);
  CHECK(whole.blocks.work == halves.blocks.work);
  CHECK(whole.blocks.work == fifths.blocks.work);
  CHECK(whole.depth == halves.depth);
  // The grouping does change the kernels' counts (a 64-ray packet against shorter streams), so
  // a share of each call's counts would not give these equal records.
  MESSAGE("cell steps traced whole ", whole.stats.trace.cell_steps, ", in halves ",
          halves.stats.trace.cell_steps, ", in fifths ", fifths.stats.trace.cell_steps);
  // erw6 is a closed room: every primary hits and is shaded; each block holds its pixels' rays.
  int64_t total = 0;
  for (int by = 0; by < whole.blocks.blocks_y; ++by) {
    for (int bx = 0; bx < whole.blocks.blocks_x; ++bx) {
      const int x0 = std::max(bx * 8, tile.x0), x1 = std::min((bx + 1) * 8, tile.x1);
      const int y0 = std::max(by * 8, tile.y0), y1 = std::min((by + 1) * 8, tile.y1);
      const int64_t pixels = x1 > x0 && y1 > y0 ? (x1 - x0) * (y1 - y0) : 0;
      INFO("block ", bx, ",", by);
      CHECK(whole.blocks.work[static_cast<size_t>(by * whole.blocks.blocks_x + bx)] ==
            pixels * shaded);
      total += whole.blocks.work[static_cast<size_t>(by * whole.blocks.blocks_x + bx)];
    }
  }
  CHECK(total == static_cast<int64_t>(tile.NumPixels()) * shaded);
  for (int y = 0; y < ro.height; ++y) {
    for (int x = 0; x < ro.width; ++x) {
      const float t = whole.depth[static_cast<size_t>(y * ro.width + x)];
      const bool inside = x >= tile.x0 && x < tile.x1 && y >= tile.y0 && y < tile.y1;
      CHECK((inside ? t > 0.0f && std::isfinite(t) : t == -1.0f));
    }
  }
  // The next generation, shadow rays only (Occlude): one ray's work each, at its pixel's block;
  // no hit distances (not primaries).
  REQUIRE(whole.shadow.size() > 0);
  const Record shadow = trace(whole.shadow, true, 1);
  const Record shadow3 = trace(whole.shadow, true, 3);
  CHECK(shadow.blocks.work == shadow3.blocks.work);
  int64_t shadow_total = 0;
  for (const int64_t w : shadow.blocks.work) shadow_total += w;
  CHECK(shadow_total == static_cast<int64_t>(whole.shadow.size()) * ray);
  CHECK(std::all_of(shadow.depth.begin(), shadow.depth.end(), [](float t) { return t == -1.0f; }));
}

// Options: an unknown --pbt-predict value is an error that names it (the backend's check).
TEST_CASE("cost map: backend options refuse an unknown predictor and a bad block") {
  BackendOptions o;
  o.kind = BackendKind::kTiles;
  o.threads = 2;
  o.pbt_tiles_per_worker = 2;
  CHECK(o.pbt_predict == PbtPredict::kCostMap);
  CHECK_NOTHROW(ValidateBackendOptions(o));
  o.pbt_predict = static_cast<PbtPredict>(9);
  CHECK_THROWS_WITH_AS(ValidateBackendOptions(o), "backend options: unknown PBT predictor 9",
                       Error);
  o.pbt_predict = PbtPredict::kPaper;
  o.pbt_cost_block = 0;
  CHECK_THROWS_AS(ValidateBackendOptions(o), Error);
}

// UsesCostMap is the plan's uses_cost_map for its options (what an MPI worker, which holds no
// plan, records by): PBT, the cost-map predictor, not static.
TEST_CASE("cost map: UsesCostMap(options) == TilePlan::uses_cost_map") {
  int on = 0;
  for (const int k : {0, 2}) {
    for (const PbtPredict predict : {PbtPredict::kPaper, PbtPredict::kCostMap}) {
      for (int a = 0; a <= static_cast<int>(PbtAssign::kLpt); ++a) {
        TilePlanOptions o;
        o.pbt_tiles_per_worker = k;
        o.workers = 2;
        o.predict = predict;
        o.assign = static_cast<PbtAssign>(a);
        const TilePlan plan(16, 16, o);
        INFO("k ", k, " predict ", std::string(PbtPredictName(predict)), " assign ",
             std::string(PbtAssignName(o.assign)));
        CHECK(UsesCostMap(o) == plan.uses_cost_map());
        CHECK(UsesCostMap(o) == (k > 0 && predict == PbtPredict::kCostMap &&
                                 o.assign != PbtAssign::kStatic));
        on += UsesCostMap(o) ? 1 : 0;
      }
    }
  }
  CHECK(on == static_cast<int>(PbtAssign::kLpt));  // every assignment but static
}

}  // namespace
}  // namespace rs
