// Cell backend vs the serial backend: bit-identical framebuffers (the fixed-point sums) and the
// same ray, hit, occlusion, shading and cell-step counts on every procedural scene and every
// shared mesh, under many simulator settings (SPE counts, micro-cache off, secondary rays at once
// on and off, spills, chunked cells, tile shapes, PBT, explicit tile lists); the image comes out
// of the SPEs' LS pixel buffers through main memory (clamp counts too, overlapping tiles
// refused); the tile times PBT gets are the simulated cycles and it re-tiles, with the shared
// counter or per-SPE lists (the tile plan's assignments), its cost map from the SPEs' cycles
// per block, the primaries' hit distances and the cameras; deterministic simulated cycles;
// refusal of grids whose occupancy bits do not fit the local store.
#include <doctest/doctest.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <iterator>
#include <string>
#include <vector>

#include "scenes/load.h"
#include "sched/backends.h"
#include "sched/cost_map.h"
#include "sched/pbt.h"
#include "sched/render.h"
#include "sched/tile_plan.h"
#include "sim/cell_renderer.h"
#include "tests/test_util.h"

namespace rs {
namespace {

using sim::CellPlanOptions;
using sim::CellFrameStats;
using sim::CellRenderer;
using sim::SimConfig;

struct Reference {
  Framebuffer fb;
  FrameStats stats;
};

// The serial image and counts, at the paper's 20-ray batches: the cell steps of the SPEs'
// resumable DDA are checked against that configuration (larger batches reach the coherent
// packets, which count cells per slice, and the stream DDA's counts shift slightly with how rays
// share a call). The image is the same for any batch.
Reference RenderReference(const FrameContext& ctx) {
  Reference r{Framebuffer(ctx.options.width, ctx.options.height), {}};
  FrameContext per_ray = ctx;
  per_ray.options.batch = 20;
  r.stats = RenderSerial(per_ray, r.fb);
  return r;
}

size_t DifferingPixels(const Framebuffer& a, const Framebuffer& b) {
  size_t n = 0;
  for (size_t p = 0; p < a.num_pixels(); ++p) {
    n += std::memcmp(a.sums() + 3 * p, b.sums() + 3 * p, 3 * sizeof(int64_t)) != 0 ? 1 : 0;
  }
  return n;
}

// Renders with the cell backend and checks it against the reference bit for bit.
CellFrameStats CheckCell(const FrameContext& ctx, const Reference& ref, const SimConfig& config,
                         const std::string& what) {
  INFO(what);
  Framebuffer fb(ctx.options.width, ctx.options.height);
  CellRenderer renderer(config);
  const CellFrameStats s = renderer.Render(ctx, fb);
  CHECK(DifferingPixels(ref.fb, fb) == 0);
  CHECK(fb.dropped_nan() == ref.fb.dropped_nan());
  CHECK(fb.clamped() == ref.fb.clamped());
  for (int k = 0; k < kNumRayKinds; ++k) {
    INFO("ray kind ", RayKindName(RayKind(k)));
    CHECK(s.frame.rays[k] == ref.stats.rays[k]);
  }
  CHECK(s.frame.hits == ref.stats.hits);
  CHECK(s.frame.occluded == ref.stats.occluded);
  CHECK(s.frame.shade.shading_calls == ref.stats.shade.shading_calls);
  CHECK(s.frame.shade.light_tests == ref.stats.shade.light_tests);
  CHECK(s.frame.shade.texture_fetches == ref.stats.shade.texture_fetches);
  // The resumable DDA examines exactly the reference's cells.
  CHECK(s.frame.trace.cell_steps == ref.stats.trace.cell_steps);
  CHECK(s.cycles > 0);
  return s;
}

FrameContext Context(const Scene& scene, const Accel& accel, int w, int h, int depth) {
  RenderOptions o;
  o.width = w;
  o.height = h;
  o.max_depth = depth;
  return MakeFrameContext(scene, accel, scene.camera, o);
}

SimConfig AtOnceOff() {
  SimConfig c;
  c.secondary_at_once = false;
  return c;
}

TEST_CASE("procedural scenes: bit-identical to the serial backend") {
  // Every procedural scene (ProceduralSceneNames), amphitheater also with several copies;
  // farsphere's Accel is built in a shifted frame (kernels/accel_impl.h) with sub-grids.
  for (const char* name : {"cornell", "erw6", "spherebox", "amphitheater", "amphitheater:3",
                           "nearsphere", "farsphere"}) {
    INFO("scene ", std::string(name));
    const Scene scene = LoadScene(name);
    // the SPEs step every cell; so does the reference without empty-space jumps (the spheres'
    // grids are empty enough to enable them)
    BuildOptions options;
    options.empty_skip = false;
    const Accel accel(scene.mesh(), options);
    const FrameContext ctx = Context(scene, accel, 64, 48, 4);
    const Reference ref = RenderReference(ctx);
    const CellFrameStats s = CheckCell(ctx, ref, SimConfig{}, "default config");
    CHECK(s.totals.visits > 0);
    CHECK(s.totals.tiles == 2 * 2);  // 32x32 tiles over 64x48
    CheckCell(ctx, ref, AtOnceOff(), "secondary rays at once off");
  }
}

// Paper 3.7: secondary rays tested at once against the triangles still in the triangle buffers.
// Both settings give the serial image; on, the counters show the path ran and fewer cells had
// to be loaded; off, it never runs.
TEST_CASE("secondary rays intersected at once with the loaded triangles") {
  BuildOptions two;
  two.grid = GridKind::kTwoLevel;
  two.lambda = 0.5f;
  two.subgrid_threshold = 8;
  struct Case {
    const char* scene;
    bool two_level;
    int depth;
  };
  for (const Case k : {Case{"cornell", false, 4}, Case{"erw6", false, 2},
                       Case{"spherebox", false, 3}, Case{"spherebox", true, 3},
                       Case{"erw6", true, 2}}) {
    INFO("scene ", std::string(k.scene), k.two_level ? " two-level" : " uniform");
    const Scene scene = LoadScene(k.scene);
    REQUIRE(!scene.lights.empty());
    const Accel accel = k.two_level ? Accel(scene.mesh(), two) : Accel(scene.mesh());
    const FrameContext ctx = Context(scene, accel, 48, 40, k.depth);
    const Reference ref = RenderReference(ctx);
    REQUIRE(ref.stats.rays[int(RayKind::kShadow)] > 0);
    const CellFrameStats on = CheckCell(ctx, ref, SimConfig{}, "at once on");
    const CellFrameStats off = CheckCell(ctx, ref, AtOnceOff(), "at once off");
    const std::string label = std::string(k.scene) + (k.two_level ? " two-level" : " uniform");
    MESSAGE(label, ": ", on.totals.at_once_tested, " secondary rays tested at once, ",
            on.totals.at_once_resolved, " resolved, cycles on ", on.cycles, " off ", off.cycles);
    CHECK(on.totals.at_once_tested > 0);
    CHECK(on.totals.at_once_resolved > 0);
    CHECK(on.totals.at_once_visits >= on.totals.at_once_tested);
    CHECK(on.totals.cell_loads < off.totals.cell_loads);
    CHECK(off.totals.at_once_tested == 0);
    CHECK(off.totals.at_once_resolved == 0);
    CHECK(off.totals.at_once_visits == 0);
    // The report names the counter.
    const std::string report = sim::FormatCellReport(on, SimConfig{});
    CHECK(report.find("intersected at once") != std::string::npos);
  }
  // With tight buffers (cells chunked, so many are not whole in a buffer) and a tiny ring.
  const Scene scene = LoadScene("spherebox");
  const Accel accel(scene.mesh(), two);
  const FrameContext ctx = Context(scene, accel, 40, 32, 3);
  const Reference ref = RenderReference(ctx);
  SimConfig tight;
  tight.triangle_buffer_bundles = 1;
  tight.ring_rays = 16;
  tight.staging_rays = 8;
  tight.num_spes = 2;
  const CellFrameStats s = CheckCell(ctx, ref, tight, "two-level, 1-bundle buffers, at once");
  CHECK(s.totals.at_once_tested > 0);
  tight.micro_cache = false;
  CheckCell(ctx, ref, tight, "two-level, 1-bundle buffers, micro-cache off, at once");
  tight.rays_per_iteration = 1;
  CheckCell(ctx, ref, tight, "one ray per iteration, at once");
}

TEST_CASE("simulator settings do not change the image") {
  const Scene scene = LoadScene("cornell");  // reflection + refraction + a light
  const Accel accel(scene.mesh());
  const FrameContext ctx = Context(scene, accel, 40, 36, 6);
  const Reference ref = RenderReference(ctx);
  {
    SimConfig c;
    c.num_spes = 1;
    CheckCell(ctx, ref, c, "1 SPE");
  }
  {
    SimConfig c;
    c.num_spes = 8;
    c.tile_width = 8;
    c.tile_height = 8;
    CheckCell(ctx, ref, c, "8 SPEs, 8x8 tiles");
  }
  {
    SimConfig c;
    c.micro_cache = false;
    CheckCell(ctx, ref, c, "micro-cache off");
    c.secondary_at_once = false;
    CheckCell(ctx, ref, c, "micro-cache and secondary rays at once off");
  }
  {
    SimConfig c;
    c.ring_rays = 16;
    c.staging_rays = 8;
    const CellFrameStats s = CheckCell(ctx, ref, c, "tiny ring: rays spill to main memory");
    CHECK(s.totals.spilled_rays > 0);
  }
  {
    SimConfig c;
    c.triangle_buffer_bundles = 1;
    const CellFrameStats s = CheckCell(ctx, ref, c, "1-bundle triangle buffers: chunked cells");
    CHECK(s.totals.chunk_loads > 0);
  }
  {
    SimConfig c;
    c.rays_per_iteration = 1;
    CheckCell(ctx, ref, c, "one ray per iteration");
  }
  {
    SimConfig c;
    c.tile_width = 640;
    c.tile_height = 2;
    c.pixel_buffers = 1;
    c.pixel_buffer_pixels = 24;  // sub-tiles of 24x1
    CheckCell(ctx, ref, c, "640x2 tiles, small pixel buffer");
  }
  {
    SimConfig c;
    c.memory.mfc_bus_slots = 16;
    c.memory.mfc_queue_depth = 2;
    CheckCell(ctx, ref, c, "pipelined DMA, 2-entry queue");
  }
}

TEST_CASE("two-level grids: sub-grid records, shared refined cells, chunked leaves") {
  // A coarse top level with 8x8x8 sub-grids in every cell holding more than 8 triangles
  // (paper 3.8), so rays enter, leave and resume inside sub-grids.
  BuildOptions two;
  two.grid = GridKind::kTwoLevel;
  two.lambda = 0.5f;
  two.subgrid_threshold = 8;
  for (const char* name : {"spherebox", "erw6"}) {
    INFO("scene ", std::string(name));
    const Scene scene = LoadScene(name);
    const Accel accel(scene.mesh(), two);
    REQUIRE(std::string(accel.Info().kind) == "two-level");
    CHECK(accel.Info().subgrids > 0);
    const FrameContext ctx = Context(scene, accel, 48, 40, 3);
    const Reference ref = RenderReference(ctx);
    const CellFrameStats s = CheckCell(ctx, ref, SimConfig{}, "two-level, default config");
    CHECK(s.totals.subgrid_loads > 0);
    CHECK(s.totals.micro_cache_hits > 0);
    SimConfig off;
    off.micro_cache = false;
    CheckCell(ctx, ref, off, "two-level, micro-cache off");
    SimConfig tight;
    tight.triangle_buffer_bundles = 1;
    tight.ring_rays = 16;
    tight.staging_rays = 8;
    tight.num_spes = 3;
    CheckCell(ctx, ref, tight, "two-level, 1-bundle buffers, tiny ring");
  }
}

TEST_CASE("textured materials through the software cache") {
  // A textured floor (checker with a gradient, so bilinear filtering and wrap-around matter) and
  // a textured mirror-ish wall, one light; UVs outside [0, 1].
  Scene s;
  s.name = "textured";
  s.source = "test";
  Texture tex;
  tex.width = 7;
  tex.height = 5;
  for (int y = 0; y < tex.height; ++y) {
    for (int x = 0; x < tex.width; ++x) {
      const float c = ((x + y) & 1) ? 0.9f : 0.2f;
      tex.rgb.insert(tex.rgb.end(), {c, 0.1f * float(x), 0.15f * float(y)});
    }
  }
  s.textures = {tex};
  Material floor;
  floor.diffuse = glm::vec3(0.8f, 0.7f, 0.6f);
  floor.texture = 0;
  Material wall;
  wall.diffuse = glm::vec3(0.5f);
  wall.texture = 0;
  wall.reflectivity = 0.3f;
  wall.specular = glm::vec3(0.5f);
  wall.shininess = 10.0f;
  s.materials = {floor, wall};
  auto quad = [&](glm::vec3 a, glm::vec3 b, glm::vec3 c, glm::vec3 d, uint32_t m, float uvs) {
    const uint32_t i = static_cast<uint32_t>(s.positions.size());
    s.positions.insert(s.positions.end(), {a, b, c, d});
    s.uvs.insert(s.uvs.end(), {{-uvs, -uvs}, {uvs, -uvs}, {uvs, uvs}, {-uvs, uvs}});
    s.triangles.push_back(glm::uvec3(i, i + 1, i + 2));
    s.triangles.push_back(glm::uvec3(i, i + 2, i + 3));
    s.material_ids.insert(s.material_ids.end(), {m, m});
  };
  quad({-5, 0, 5}, {5, 0, 5}, {5, 0, -5}, {-5, 0, -5}, 0, 2.3f);
  quad({-5, 0, -4}, {5, 0, -4}, {5, 6, -4}, {-5, 6, -4}, 1, 1.7f);
  PointLight light;
  light.position = glm::vec3(1, 4, 2);
  s.lights = {light};
  s.camera.eye = glm::vec3(0, 3, 6);
  s.camera.look_at = glm::vec3(0, 1, -2);
  s.features = ComputeFeatures(s);
  ValidateScene(s);
  REQUIRE(s.features.textures);
  const Accel accel(s.mesh());
  const FrameContext ctx = Context(s, accel, 40, 30, 2);
  const Reference ref = RenderReference(ctx);
  REQUIRE(ref.stats.shade.texture_fetches > 0);
  const CellFrameStats st = CheckCell(ctx, ref, SimConfig{}, "textured");
  uint64_t reads = 0;
  for (const auto& spe : st.spes) reads += spe.cache.reads;
  CHECK(reads >= 4 * st.totals.texture_fetches);  // 4 texels (+ materials) per sample
}

TEST_CASE("explicit tile lists and PBT tiling") {
  const Scene scene = LoadScene("erw6");
  const Accel accel(scene.mesh());
  const FrameContext ctx = Context(scene, accel, 50, 30, 3);
  const Reference ref = RenderReference(ctx);
  {
    // Odd tiles in a scrambled order, one of them a single column.
    const std::vector<Tile> tiles = {{10, 0, 50, 30}, {0, 0, 9, 30}, {9, 0, 10, 30}};
    Framebuffer fb(50, 30);
    CellRenderer r(SimConfig{});
    const CellFrameStats s = r.Render(ctx, fb, tiles);
    CHECK(DifferingPixels(ref.fb, fb) == 0);
    CHECK(s.tiles.size() == 3);
    for (const auto& t : s.tiles) CHECK(t.spe >= 0);
  }
  {
    SimConfig c;
    c.pbt_tiles_per_spe = 2;
    CellRenderer r(c);
    for (int frame = 0; frame < 3; ++frame) {
      INFO("PBT frame ", frame);
      Framebuffer fb(50, 30);
      const CellFrameStats s = r.Render(ctx, fb);
      CHECK(DifferingPixels(ref.fb, fb) == 0);
      CHECK(s.pbt);
      CHECK(s.tiles.size() == 12);
      CHECK(s.has_prediction == (frame > 0));
      double sum = 0;
      for (const auto& t : s.tiles) sum += t.cycles;
      CHECK(sum > 0);
    }
    CHECK(r.pbt()->Validate().empty());
  }
  {
    // The SPEs put whole tiles back by DMA, so overlapping tiles are refused.
    const std::vector<Tile> tiles = {{0, 0, 30, 30}, {20, 0, 50, 30}};
    Framebuffer fb(50, 30);
    CellRenderer r(SimConfig{});
    CHECK_THROWS_WITH_AS(r.Render(ctx, fb, tiles), doctest::Contains("tiles 0 and 1 overlap"),
                         Error);
  }
  {
    // Pixels outside every tile are left as they were.
    const std::vector<Tile> tiles = {{0, 0, 25, 30}};
    Framebuffer fb(50, 30);
    CellRenderer r(SimConfig{});
    r.Render(ctx, fb, tiles);
    size_t inside = 0, outside = 0;
    for (int y = 0; y < 30; ++y) {
      for (int x = 0; x < 50; ++x) {
        const size_t p = size_t(y) * 50 + size_t(x);
        const bool same = std::memcmp(fb.sums() + 3 * p, ref.fb.sums() + 3 * p, 24) == 0;
        const bool zero =
            fb.sums()[3 * p] == 0 && fb.sums()[3 * p + 1] == 0 && fb.sums()[3 * p + 2] == 0;
        inside += x < 25 && same ? 1 : 0;
        outside += x >= 25 && zero ? 1 : 0;
      }
    }
    CHECK(inside == 25 * 30);
    CHECK(outside == 25 * 30);
  }
}

// The PBT assignments of the tile plan (sched/tile_plan.h) on the SPEs: with per-worker lists
// SPE s takes exactly the tiles of the lists s, s + spes, ... from its own counter (no
// stealing), the default counter hands every tile to whichever SPE asks first; the image is the
// serial one either way, and the same configuration gives the same cycles.
TEST_CASE("PBT lists: each SPE runs its own workers' lists through a counter of its own") {
  const Scene scene = LoadScene("cornell");
  const Accel accel(scene.mesh());
  const FrameContext ctx = Context(scene, accel, 48, 32, 3);
  const Reference ref = RenderReference(ctx);
  struct Case {
    PbtAssign assign;
    int workers;  // 0: one per SPE
  };
  const Case cases[] = {{PbtAssign::kRandom, 0},  {PbtAssign::kGreedy, 0},
                        {PbtAssign::kVisit, 8},   {PbtAssign::kStatic, 0},
                        {PbtAssign::kCounter, 0}, {PbtAssign::kCounter, 6}};
  for (const Case& c : cases) {
    INFO("assign ", std::string(PbtAssignName(c.assign)), " workers ", c.workers);
    SimConfig config;
    config.num_spes = 3;
    config.pbt_tiles_per_spe = 2;
    CellPlanOptions plan;
    plan.assign = c.assign;
    plan.pbt_workers = c.workers;
    plan.seed = 5;
    CellRenderer r(config, plan), twin(config, plan);
    const int n = c.workers > 0 ? c.workers : config.num_spes;
    for (int frame = 0; frame < 3; ++frame) {
      INFO("frame ", frame);
      Framebuffer fb(48, 32), fb2(48, 32);
      const CellFrameStats s = r.Render(ctx, fb);
      const CellFrameStats s2 = twin.Render(ctx, fb2);
      CHECK(DifferingPixels(ref.fb, fb) == 0);
      CHECK(s.pbt);
      CHECK(s.has_prediction == (frame > 0));
      REQUIRE(s.tiles.size() == size_t(n) * 2);
      CHECK(s.cycles == s2.cycles);
      for (size_t i = 0; i < s.tiles.size(); ++i) {
        const sim::CellTileRecord& t = s.tiles[i];
        CHECK(t.cycles == s2.tiles[i].cycles);
        CHECK(t.spe >= 0);
        CHECK(t.cycles > 0);
        if (c.assign == PbtAssign::kCounter) {
          CHECK(t.worker == -1);
        } else {
          REQUIRE(t.worker >= 0);
          CHECK(t.worker < n);
          CHECK(t.spe == t.worker % config.num_spes);  // its own lists only
        }
      }
      CHECK(s.worker_imbalance >= 1.0);
    }
    REQUIRE(r.pbt() != nullptr);
    CHECK(r.pbt()->Validate().empty());
  }
  CellPlanOptions bad_assign;
  bad_assign.assign = static_cast<PbtAssign>(9);
  CHECK_THROWS_AS(CellRenderer(SimConfig{}, bad_assign), Error);
  CHECK_THROWS_AS(CellRenderer(SimConfig{}, CellPlanOptions{.pbt_workers = -1}), Error);
}

// What PBT is fed: CellTileRecord::cycles, each pipeline iteration's simulated cycles shared
// among its rays' tiles. Every busy cycle of an SPE (its clock when its program ends) lies in
// an iteration, its program start or its tail (SpeCounters), so the tile times add up to the
// SPEs' busy cycles less start and tail. A second PBT updated with exactly those times gives
// the next frame's tiles and predictions; PBT-Update only halves and sums estimates (the paper's
// predictor) or sums the cost map of the SPEs' cycles per block (the default; the backend's
// record, scaled to the tiles' total as the plan does; no next camera here, so not moved), so
// the predictions add up to the measured total.
TEST_CASE("PBT is fed the simulated tile cycles and re-tiles between frames") {
  const Scene scene = LoadScene("cornell");  // glass and mirror: uneven cost over the image
  const Accel accel(scene.mesh());
  const FrameContext ctx = Context(scene, accel, 64, 48, 6);
  const Reference ref = RenderReference(ctx);
  for (const PbtPredict predict : {PbtPredict::kPaper, PbtPredict::kCostMap}) {
    INFO("predict ", std::string(PbtPredictName(predict)));
    SimConfig c;
    c.pbt_tiles_per_spe = 2;
    CellPlanOptions plan;
    plan.predict = predict;
    CellRenderer r(c, plan);
    Pbt mirror(64, 48, c.num_spes, c.pbt_tiles_per_spe);
    std::vector<Tile> first_tiles;
    for (int frame = 0; frame < 4; ++frame) {
      INFO("frame ", frame);
      const std::vector<Tile> tiles = mirror.Tiles();
      const std::vector<double> estimates = mirror.Estimates();
      Framebuffer fb(64, 48);
      const CellFrameStats s = r.Render(ctx, fb);
      CHECK(DifferingPixels(ref.fb, fb) == 0);
      REQUIRE(s.tiles.size() == tiles.size());
      std::vector<double> measured;
      double tile_sum = 0, busy = 0, overhead = 0, predicted = 0;
      for (size_t i = 0; i < tiles.size(); ++i) {
        const sim::CellTileRecord& t = s.tiles[i];
        CHECK(t.tile.x0 == tiles[i].x0);
        CHECK(t.tile.y0 == tiles[i].y0);
        CHECK(t.tile.x1 == tiles[i].x1);
        CHECK(t.tile.y1 == tiles[i].y1);
        CHECK(t.spe >= 0);
        CHECK(t.cycles > 0);
        if (frame > 0) CHECK(t.predicted == estimates[i]);
        measured.push_back(t.cycles);
        tile_sum += t.cycles;
        predicted += t.predicted;
      }
      for (const auto& spe : s.spes) {
        CHECK(spe.finish == spe.cycles.Total() - spe.cycles[sim::Cost::kIdle]);
        busy += double(spe.finish);
        overhead += double(spe.counters.startup_cycles + spe.counters.tail_cycles);
      }
      CHECK(tile_sum == doctest::Approx(busy - overhead).epsilon(1e-12));
      CHECK(overhead < 0.2 * busy);  // start (grid bits into LS) and tail are short
      if (frame > 0) {
        double last = 0;
        for (const double e : estimates) last += e;
        CHECK(predicted == doctest::Approx(last).epsilon(1e-12));
      }
      CostMap map;
      map.Resize(64, 48, TilePlanOptions{}.cost_block);
      if (predict == PbtPredict::kCostMap) {
        const TilePlanMeasure& m = r.cost_map_measure();
        REQUIRE(m.blocks != nullptr);
        CHECK(m.next_camera == nullptr);
        int64_t work = 0;
        for (const int64_t b : m.blocks->work) work += b;
        double total = 0;
        for (const double c : measured) total += c;
        map.SetFromWork(*m.blocks, total / (double(work) * kBlockWorkUnit));
      }
      const PbtUpdateStats u =
          predict == PbtPredict::kPaper ? mirror.Update(measured) : mirror.Update(measured, map);
      CHECK(u.steps == s.update.steps);
      CHECK(r.pbt()->Estimates() == mirror.Estimates());
      if (frame == 0) {
        CHECK(s.update.steps > 0);  // uneven cost: PBT-Update splits and merges
        first_tiles = tiles;
      }
      if (frame == 1) {
        size_t moved = 0;  // tiles of this frame that the first frame did not have
        for (const Tile& a : tiles) {
          bool found = false;
          for (const Tile& b : first_tiles) {
            found |= a.x0 == b.x0 && a.y0 == b.y0 && a.x1 == b.x1 && a.y1 == b.y1;
          }
          moved += found ? 0 : 1;
        }
        MESSAGE(moved, " of ", tiles.size(), " tiles are new after the first frame");
        CHECK(moved > 0);  // re-tiled
      }
    }
    CHECK(r.pbt()->Validate().empty());
  }
}

// Contributions beyond the framebuffer's range are clamped and counted on the SPE (shader
// contributions and shadow rays alike) and the counts reach the framebuffer through the SPEs'
// status records in main memory.
TEST_CASE("clamped contributions are counted through main memory") {
  Scene scene = LoadScene("cornell");
  for (PointLight& l : scene.lights) l.color *= 1e5f;  // shadow-ray contributions > 4096
  scene.background = glm::vec3(1e5f);                  // escaping rays' background too
  ValidateScene(scene);
  const Accel accel(scene.mesh());
  const FrameContext ctx = Context(scene, accel, 40, 30, 3);
  const Reference ref = RenderReference(ctx);
  REQUIRE(ref.fb.clamped() > 0);
  MESSAGE("clamped contributions: ", ref.fb.clamped());
  CheckCell(ctx, ref, SimConfig{}, "bright light, bright background");
  SimConfig c;
  c.num_spes = 3;
  c.secondary_at_once = false;
  CheckCell(ctx, ref, c, "3 SPEs, secondary rays at once off");
}

TEST_CASE("simulated cycles are deterministic") {
  const Scene scene = LoadScene("spherebox");
  const Accel accel(scene.mesh());
  const FrameContext ctx = Context(scene, accel, 48, 40, 5);
  SimConfig c;
  c.tile_width = 16;
  c.tile_height = 8;
  std::vector<uint64_t> first;
  for (int run = 0; run < 2; ++run) {
    Framebuffer fb(48, 40);
    CellRenderer r(c);
    const CellFrameStats s = r.Render(ctx, fb);
    std::vector<uint64_t> cycles = {s.cycles, s.mic_lines, s.mic_queue_cycles,
                                    s.totals.tile_counter_retries};
    for (const auto& spe : s.spes) {
      for (const uint64_t x : spe.cycles.cycles) cycles.push_back(x);
      cycles.push_back(spe.counters.TotalRays());
    }
    if (run == 0) {
      first = cycles;
    } else {
      CHECK(cycles == first);
    }
  }
}

TEST_CASE("more SPEs render faster; the breakdown adds up") {
  const Scene scene = LoadScene("erw6");
  const Accel accel(scene.mesh());
  const FrameContext ctx = Context(scene, accel, 64, 64, 2);
  uint64_t one = 0;
  for (const int spes : {1, 6}) {
    SimConfig c;
    c.num_spes = spes;
    c.tile_width = c.tile_height = 8;
    Framebuffer fb(64, 64);
    CellRenderer r(c);
    const CellFrameStats s = r.Render(ctx, fb);
    for (const auto& spe : s.spes) CHECK(spe.cycles.Total() == s.cycles);
    if (spes == 1) {
      one = s.cycles;
    } else {
      const double speedup = double(one) / double(s.cycles);
      INFO("speed-up at 6 SPEs: ", speedup);
      CHECK(speedup > 4.0);
      CHECK(speedup <= 6.0);
    }
  }
}

TEST_CASE("shared scenes: bit-identical at small resolution") {
  // Every shared scene (BuiltinSceneFileNames); missing ones are skipped, or fail under CI=true.
  struct Shared {
    const char* name;
    const char* file;
  };
  const Shared scenes[] = {{"teapot", "teapot/teapot.obj"},
                           {"bunny", "bunny/bun_zipper.ply"},
                           {"office-graz", "office-graz/office-graz.obj"},
                           {"sponza", "sponza/sponza.obj"},
                           {"sibenik", "sibenik/sibenik.obj"},
                           {"conference", "conference/conference.obj"}};
  CHECK(std::size(scenes) == BuiltinSceneFileNames().size());
  for (const Shared& sh : scenes) {
    const std::string name = sh.name;
    INFO("scene ", name);
    if (!test::HaveSharedScene(sh.file)) continue;
    const Scene scene = LoadScene(name);
    std::string note;
    // BuildCellAccel fits the grid to the local store (conference: a two-level grid, 3.8).
    const Accel accel = sim::BuildCellAccel(scene, BuildOptions{}, SimConfig{}, 40, &note);
    MESSAGE(name, ": ", std::string(accel.Info().kind), " ", accel.Info().cells, " cells, ",
            scene.lights.size(), " lights ", note);
    const FrameContext ctx = Context(scene, accel, 40, 32, 2);
    const Reference ref = RenderReference(ctx);
    const CellFrameStats s = CheckCell(ctx, ref, SimConfig{}, name);
    if (!scene.lights.empty()) CHECK(s.totals.at_once_tested > 0);
    CheckCell(ctx, ref, AtOnceOff(), name + ", secondary rays at once off");
  }
}

TEST_CASE("a grid whose occupancy bits do not fit the local store is refused") {
  if (!test::HaveSharedScene("conference/conference.obj")) return;
  const Scene scene = LoadScene("conference");
  // The uniform grid at lambda 4: 193x47x123 = 1.1 M cells, 139 KiB of bits (paper 3.8: about
  // 100 KiB of LS are left for them, ~800,000 cells).
  BuildOptions uniform;
  uniform.grid = GridKind::kUniform;
  const Accel accel(scene.mesh(), uniform);
  REQUIRE(accel.Info().cells > sim::OccupancyBudgetCells(SimConfig{}, 4, 8, true));
  const FrameContext ctx = Context(scene, accel, 8, 8, 0);
  Framebuffer fb(8, 8);
  CellRenderer r(SimConfig{});
  CHECK_THROWS_WITH_AS(r.Render(ctx, fb), doctest::Contains("occupancy bits of the 193x47x123"),
                       Error);
  // BuildCellAccel lowers lambda until the top level fits; dense cells get sub-grids (3.8).
  BuildOptions two = uniform;
  two.grid = GridKind::kTwoLevel;
  std::string note;
  const Accel coarse = sim::BuildCellAccel(scene, two, SimConfig{}, 24, &note);
  CHECK(!note.empty());
  CHECK(std::string(coarse.Info().kind) == "two-level");
  CHECK(coarse.Info().cells <= sim::OccupancyBudgetCells(SimConfig{}, 4, 24, true));
  MESSAGE("conference: ", note);
  const FrameContext ctx2 = Context(scene, coarse, 24, 16, 1);
  const Reference ref = RenderReference(ctx2);
  const CellFrameStats s = CheckCell(ctx2, ref, SimConfig{}, "conference, fitted grid");
  CHECK(s.totals.subgrid_loads > 0);
}

TEST_CASE("the local-store budget shrinks as buffers grow") {
  const SimConfig base;
  const uint64_t cells = sim::OccupancyBudgetCells(base, 4, 512, false);
  // Paper 3.8: about 100 KiB of LS for the bits, ~800,000 cells, with pixel buffers of 16-B
  // pixels (4 floats). Ours hold the framebuffer's fixed-point sums (sim::PixelSums, 32 B), so
  // the two 1280-pixel buffers take 40 KiB more and leave room for fewer cells.
  const uint64_t extra = uint64_t{2} * 1280 * (sizeof(sim::PixelSums) - 16) * 8;
  CHECK(extra == 40 * 1024 * 8);
  CHECK(cells + extra > 700000);
  CHECK(cells + extra < 900000);
  SimConfig one_buffer = base;
  one_buffer.pixel_buffers = 1;
  // One buffer less: its 1280 pixels and its DMA list (64 rows of one 16 KiB element each).
  CHECK(sim::OccupancyBudgetCells(one_buffer, 4, 512, false) ==
        cells + (1280 * sizeof(sim::PixelSums) + 64 * 8) * 8);
  SimConfig bigger = base;
  bigger.ring_rays = 256;  // +16 KiB
  CHECK(sim::OccupancyBudgetCells(bigger, 4, 512, false) == cells - 16 * 1024 * 8);
  CHECK(sim::OccupancyBudgetCells(base, 4, 512, true) == cells - 1024 * 8);  // sub-grid lines
  SimConfig full = base;
  full.code_stack_bytes = 250 * 1024;
  CHECK_THROWS_WITH_AS(sim::OccupancyBudgetCells(full, 4, 512, false),
                       doctest::Contains("local store overflow"), Error);
}

// Paper 3.2: "the procedure continues until less than eight rays are left and no more primary
// rays can be generated ... these last rays are processed individually, without any interleaving
// of the memory accesses" (SimConfig::drain_individually). With one pixel buffer the ring runs
// low at the end of every sub-tile (32x4 pixels here). On, an iteration takes rays_per_iteration rays, or 1 when
// fewer are left, never a number in between; off, the tails are interleaved (the scene must have
// some, or the test would prove nothing). Either way every ray finishes and the image is the
// serial one; draining costs cycles (no latency hidden).
TEST_CASE("drain_individually: the last rays one at a time, same rays and image") {
  const Scene scene = LoadScene("cornell");
  const Accel accel(scene.mesh());
  const FrameContext ctx = Context(scene, accel, 48, 40, 3);
  const Reference ref = RenderReference(ctx);
  for (const int per_iteration : {8, 4}) {
    INFO("rays per iteration ", per_iteration);
    SimConfig off;
    off.pixel_buffers = 1;
    off.pixel_buffer_pixels = 128;  // sub-tiles of 32x4: many tails
    off.rays_per_iteration = per_iteration;
    SimConfig on = off;
    on.drain_individually = true;
    const CellFrameStats a = CheckCell(ctx, ref, off, "tails interleaved");
    const CellFrameStats b = CheckCell(ctx, ref, on, "tails drained one ray at a time");
    const auto by = [](const CellFrameStats& s, int k) { return s.totals.iterations_by_rays[k]; };
    uint64_t tails_off = 0, iterations_on = 0, rays_on = 0;
    for (int k = 0; k <= 8; ++k) {
      INFO("iterations of ", k, " rays: off ", by(a, k), ", on ", by(b, k));
      if (k > per_iteration) CHECK(by(a, k) + by(b, k) == 0);  // never more than asked for
      if (k >= 2 && k < per_iteration) {
        tails_off += by(a, k);
        CHECK(by(b, k) == 0);  // drained: 1 ray, never a partial interleaved batch
      }
      iterations_on += by(b, k);
      rays_on += uint64_t(k) * by(b, k);
    }
    CHECK(by(a, 0) == 0);
    CHECK(by(b, 0) == 0);
    CHECK(iterations_on == b.totals.iterations);
    CHECK(rays_on == b.totals.rays_in_flight);
    CHECK(tails_off > 0);                        // the scene has interleaved tails to drain
    CHECK(by(b, 1) > by(a, 1));                  // and they were drained one ray at a time
    CHECK(by(b, per_iteration) > 0);             // full batches still run while rays are there
    CHECK(b.totals.iterations > a.totals.iterations);
    CHECK(b.totals.TotalRays() == a.totals.TotalRays());  // every ray finished (CheckCell: = serial)
    CHECK(b.totals.subtiles == a.totals.subtiles);
    MESSAGE("rays per iteration ", per_iteration, ": ", tails_off, " interleaved tail iterations; ",
            "drained: ", by(b, 1), " single-ray iterations, cycles ", a.cycles, " -> ", b.cycles);
    CHECK(b.cycles > a.cycles);  // the drained rays hide no memory latency
  }
}

// The cost map of the cell backend's PBT (CellPlanOptions::predict kCostMap): each pipeline
// iteration's cycles charged to the blocks of its rays' pixels in the shares of the tile cycles
// (FrameOutputs::block_work), the primaries' hit distances and the cameras, so the plan's map
// is moved to the next camera like the host backends'. Per block of one pixel, a tile's pixels
// hold exactly its cycles (up to the doubles' rounding of the tile cycles); the blocks sum to
// the SPEs' attributed cycles; the hit distances are the tiles backend's bit for bit (the same
// primary rays); the record is the same in every run of a configuration. It is not the same at
// every SPE count: the tile cycles themselves are not (DMA waits on the shared MIC, and which
// rays share an iteration, depend on how many SPEs run and which tiles each took). The images
// stay the serial ones.
TEST_CASE("PBT cost map: the SPEs' cycles per block, hit distances, cameras") {
  const Scene scene = LoadScene("erw6");  // a closed room: every primary hits
  const Accel accel(scene.mesh());
  const int w = 48, h = 40, frames = 3;
  const float speed = 2.0f;
  RenderOptions ro;
  ro.width = w;
  ro.height = h;
  ro.max_depth = 4;
  auto context = [&](int f, bool next) {
    FrameContext ctx = MakeFrameContext(scene, accel, scene.path.At(f, speed, scene.camera), ro);
    if (next) SetNextCamera(ctx, scene.path.At(f + 1, speed, scene.camera));
    return ctx;
  };
  // The tiles backend's hit distances and the serial images of the walk-through.
  std::vector<std::vector<float>> host_depth;
  std::vector<Framebuffer> serial;
  {
    BackendOptions o;
    o.kind = BackendKind::kTiles;
    o.threads = 1;
    o.pbt_tiles_per_worker = 2;
    o.pbt_cost = PbtCost::kWork;
    HostRenderer host(o);
    for (int f = 0; f < frames; ++f) {
      const FrameContext ctx = context(f, true);
      Framebuffer fb(w, h);
      host.RenderFrame(ctx, fb);
      const TilePlanMeasure m = host.cost_map_measure();
      REQUIRE(m.pixel_depth.size() == size_t(w * h));
      host_depth.emplace_back(m.pixel_depth.begin(), m.pixel_depth.end());
      serial.emplace_back(w, h);
      RenderSerial(ctx, serial.back());
    }
  }
  struct Frame {
    std::vector<int64_t> work;
    std::vector<float> depth;
    std::vector<double> predicted;
  };
  auto run = [&](int spes, PbtAssign assign, int block, bool next) {
    SimConfig c;
    c.num_spes = spes;
    c.pbt_tiles_per_spe = 2;
    CellPlanOptions plan;
    plan.assign = assign;
    plan.pbt_workers = 4;  // the same 8 PBT tiles at every SPE count
    plan.cost_block = block;
    CellRenderer r(c, plan);
    const uint64_t units_per_cycle = uint64_t(std::llround(1.0 / (c.clock_hz * kBlockWorkUnit)));
    std::vector<Frame> out;
    for (int f = 0; f < frames; ++f) {
      INFO("SPEs ", spes, " assign ", std::string(PbtAssignName(assign)), " block ", block,
           " frame ", f);
      const FrameContext ctx = context(f, next);
      Framebuffer fb(w, h);
      const CellFrameStats s = r.Render(ctx, fb);
      CHECK(DifferingPixels(serial[size_t(f)], fb) == 0);
      const TilePlanMeasure& m = r.cost_map_measure();
      REQUIRE(m.blocks != nullptr);
      REQUIRE(m.blocks->Matches(w, h, block));
      CHECK(m.camera == &ctx.camera);
      CHECK((m.next_camera != nullptr) == next);
      REQUIRE(m.pixel_depth.size() == size_t(w * h));
      CHECK(std::equal(m.pixel_depth.begin(), m.pixel_depth.end(), host_depth[size_t(f)].begin()));
      // The blocks hold exactly the attributed cycles, units_per_cycle units each.
      int64_t total = 0;
      for (const int64_t b : m.blocks->work) total += b;
      double cycles = 0;
      for (const sim::CellTileRecord& t : s.tiles) cycles += t.cycles;
      CHECK(double(total) == doctest::Approx(cycles * double(units_per_cycle)).epsilon(1e-12));
      if (block == 1) {  // a block per pixel: each tile's pixels hold its own cycles
        for (const sim::CellTileRecord& t : s.tiles) {
          int64_t tile_units = 0;
          for (int y = t.tile.y0; y < t.tile.y1; ++y) {
            for (int x = t.tile.x0; x < t.tile.x1; ++x) {
              tile_units += m.blocks->work[size_t(y) * size_t(w) + size_t(x)];
            }
          }
          CHECK(double(tile_units) ==
                doctest::Approx(t.cycles * double(units_per_cycle)).epsilon(1e-9));
        }
      }
      Frame fr;
      fr.work = m.blocks->work;
      fr.depth.assign(m.pixel_depth.begin(), m.pixel_depth.end());
      for (const sim::CellTileRecord& t : s.tiles) fr.predicted.push_back(t.predicted);
      out.push_back(std::move(fr));
    }
    return out;
  };
  for (const PbtAssign assign : {PbtAssign::kCounter, PbtAssign::kGreedy}) {
    const std::vector<Frame> one = run(1, assign, 4, true);
    const std::vector<Frame> again = run(1, assign, 4, true);
    for (int f = 0; f < frames; ++f) {
      CHECK(again[size_t(f)].work == one[size_t(f)].work);  // deterministic
      CHECK(again[size_t(f)].predicted == one[size_t(f)].predicted);
    }
    for (const int spes : {3, 8}) {
      const std::vector<Frame> many = run(spes, assign, 4, true);
      double diff = 0, sum = 0;
      for (size_t b = 0; b < one[0].work.size(); ++b) {
        diff += std::abs(double(many[0].work[b]) - double(one[0].work[b]));
        sum += double(one[0].work[b]);
      }
      MESSAGE("assign ", std::string(PbtAssignName(assign)), ": block work at ", spes,
              " SPEs differs from 1 SPE's by ", 100.0 * diff / sum, " % (sum of |difference|)");
      CHECK(many[0].depth == one[0].depth);
    }
    run(3, assign, 1, true);
  }
  // Without the next camera the map is not moved: the same first frame's record, other
  // predictions for the second (the camera moves along the path).
  const std::vector<Frame> moved = run(2, PbtAssign::kCounter, 4, true);
  const std::vector<Frame> still = run(2, PbtAssign::kCounter, 4, false);
  CHECK(still[0].work == moved[0].work);
  CHECK(still[1].predicted != moved[1].predicted);
  // No record without the cost map: regular tiles, the paper's predictor, static.
  for (const int k : {0, 2}) {
    for (const PbtPredict predict : {PbtPredict::kPaper, PbtPredict::kCostMap}) {
      for (const PbtAssign assign : {PbtAssign::kCounter, PbtAssign::kStatic}) {
        SimConfig c;
        c.num_spes = 2;
        c.pbt_tiles_per_spe = k;
        CellPlanOptions plan;
        plan.predict = predict;
        plan.assign = assign;
        CellRenderer r(c, plan);
        Framebuffer fb(w, h);
        r.Render(context(0, true), fb);
        const bool on = k > 0 && predict == PbtPredict::kCostMap && assign != PbtAssign::kStatic;
        INFO("k ", k, " predict ", std::string(PbtPredictName(predict)), " assign ",
             std::string(PbtAssignName(assign)));
        CHECK((r.cost_map_measure().blocks != nullptr) == on);
        CHECK(r.cost_map_measure().pixel_depth.empty() == !on);
        CHECK(DifferingPixels(serial[0], fb) == 0);
      }
    }
  }
}

}  // namespace
}  // namespace rs
