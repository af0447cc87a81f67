// The frame engine (sched/engine.h): any batch size gives the serial image bit for bit, the
// arenas do not grow with the image, exponential ray trees stop at the ray budget, and kernel
// calls reach the batch size.
#include "sched/engine.h"

#include <doctest/doctest.h>

#include <cstring>
#include <vector>

#include "sched/backends.h"
#include "tests/support/hand_scenes.h"

namespace rs {
namespace {

bool SameSums(const Framebuffer& a, const Framebuffer& b) {
  return a.num_pixels() == b.num_pixels() &&
         std::memcmp(a.sums(), b.sums(), sizeof(int64_t) * 3 * a.num_pixels()) == 0;
}

Framebuffer Render(const Scene& s, const Accel& accel, const RenderOptions& o, FrameStats* st,
                   SerialRenderer* renderer = nullptr) {
  SerialRenderer local;
  SerialRenderer& r = renderer != nullptr ? *renderer : local;
  const FrameContext ctx = MakeFrameContext(s, accel, s.camera, o);
  Framebuffer fb(o.width, o.height);
  *st = r.Render(ctx, fb);
  return fb;
}

// The camera inside a closed box inside a second closed box, every wall a perfect mirror that
// also transmits everything (reflectivity 1, transmission 1): rays inside or between the boxes
// split in two at every hit and never leave, so the ray tree grows like 2^depth.
Scene HallOfMirrors() {
  Scene s;
  s.name = "mirrors";
  Material m;
  m.diffuse = glm::vec3(0.5f);
  m.reflectivity = 1.0f;
  m.transmission = 1.0f;
  m.ior = 1.2f;
  s.materials = {m};
  for (const float h : {1.0f, 3.0f}) {
    const glm::vec3 p[8] = {{-h, -h, -h}, {h, -h, -h}, {h, h, -h}, {-h, h, -h},
                            {-h, -h, h},  {h, -h, h},  {h, h, h},  {-h, h, h}};
    test::AddQuad(s, p[0], p[1], p[2], p[3], 0);
    test::AddQuad(s, p[5], p[4], p[7], p[6], 0);
    test::AddQuad(s, p[4], p[0], p[3], p[7], 0);
    test::AddQuad(s, p[1], p[5], p[6], p[2], 0);
    test::AddQuad(s, p[3], p[2], p[6], p[7], 0);
    test::AddQuad(s, p[4], p[5], p[1], p[0], 0);
  }
  PointLight light;
  light.position = glm::vec3(0.3f, 0.4f, 0.2f);
  s.lights = {light};
  s.background = glm::vec3(0.2f);
  s.ambient = 0.1f;
  s.camera.eye = glm::vec3(0.1f, 0.2f, 0.5f);
  s.camera.look_at = glm::vec3(0.0f, 0.0f, -1.0f);
  s.camera.fov_y_deg = 60.0f;
  test::SetFeatures(s);
  return s;
}

TEST_CASE("every batch size gives the same image, rays and kernel-call lengths up to the batch") {
  const Scene s = test::HandScene();
  const Accel accel(test::MeshOf(s));
  RenderOptions o;
  o.width = 48;
  o.height = 40;
  o.max_depth = 5;
  FrameStats ref_stats;
  o.batch = 1;
  o.task_size = 1;
  const Framebuffer ref = Render(s, accel, o, &ref_stats);
  CHECK(ref_stats.trace_calls[0] == ref_stats.rays[0]);  // one primary ray per call
  for (const int batch : {7, 20, 64, 256, 1024, 5000}) {
    INFO("batch ", batch);
    o.batch = batch;
    o.task_size = 20;
    FrameStats st;
    const Framebuffer fb = Render(s, accel, o, &st);
    CHECK(SameSums(fb, ref));
    for (int k = 0; k < kNumRayKinds; ++k) CHECK(st.rays[k] == ref_stats.rays[k]);
    CHECK(st.budget_dropped == 0);
    // Primary rays: one call per batch of a 32x32 tile (the tile size caps the batch).
    const uint64_t per_tile = static_cast<uint64_t>(std::min(batch, 32 * 32));
    const uint64_t tiles = 2 * 2;  // 48x40 in 32x32 tiles
    uint64_t calls = 0;
    for (const int pixels : {32 * 32, 16 * 32, 32 * 8, 16 * 8}) {
      calls += (static_cast<uint64_t>(pixels) + per_tile - 1) / per_tile;
    }
    CHECK(tiles == 4);
    CHECK(st.trace_calls[0] == calls);
    CHECK(st.tasks > 0);
  }
}

TEST_CASE("the arenas do not grow with the image") {
  const Scene s = test::HandScene();
  const Accel accel(test::MeshOf(s));
  RenderOptions o;
  o.max_depth = 6;
  o.batch = 256;
  size_t capacity[2] = {};
  int i = 0;
  for (const int size : {40, 300}) {
    o.width = o.height = size;
    SerialRenderer r;
    FrameStats st;
    Render(s, accel, o, &st, &r);
    capacity[i++] = r.engine().capacity_rays();
    CHECK(r.engine().capacity_rays() <= EngineRayBudget(o, s.lights.size()));
  }
  CHECK(capacity[0] == capacity[1]);
}

TEST_CASE("an exponential ray tree stops at the ray budget, in bounded memory") {
  const Scene s = HallOfMirrors();
  const Accel accel(test::MeshOf(s));
  RenderOptions o;
  o.width = 12;
  o.height = 10;
  o.max_depth = 64;
  o.weight_cutoff = 0.0f;
  o.batch = 64;
  o.ray_budget = 256;
  SerialRenderer r;
  FrameStats st;
  const Framebuffer fb = Render(s, accel, o, &st, &r);
  CHECK(st.budget_dropped > 0);
  const uint64_t pixels = 12 * 10;
  // The budget is checked before each chunk of at most `batch` rays (plus their shadow rays).
  const uint64_t chunks = (pixels + 63) / 64;
  const uint64_t slack = chunks * 64 * (s.lights.size() + 1);
  CHECK(st.TotalRays() <= static_cast<uint64_t>(o.ray_budget) * pixels + slack);
  CHECK(st.TotalRays() >= static_cast<uint64_t>(o.ray_budget) * pixels);
  CHECK(r.engine().capacity_rays() <= EngineRayBudget(o, s.lights.size()));
  // Deterministic: the same batches drop the same rays.
  FrameStats again;
  CHECK(SameSums(Render(s, accel, o, &again), fb));
  CHECK(again.budget_dropped == st.budget_dropped);
  // Depth 8 stays below the budget: nothing dropped, and any batch gives the same image.
  o.max_depth = 8;
  o.ray_budget = 1024;
  FrameStats a, b;
  const Framebuffer fa = Render(s, accel, o, &a);
  o.batch = 1000;
  const Framebuffer fbb = Render(s, accel, o, &b);
  CHECK(a.budget_dropped == 0);
  CHECK(a.TotalRays() > 40 * pixels);  // the tree did branch (a chain would be ~18 per pixel)
  CHECK(SameSums(fa, fbb));
}

TEST_CASE("a resolved framebuffer (floats only) holds the fixed-point framebuffer's image") {
  const Scene s = test::HandScene();
  const Accel accel(test::MeshOf(s));
  RenderOptions o;
  o.width = 70;
  o.height = 45;
  o.max_depth = 4;
  const FrameContext ctx = MakeFrameContext(s, accel, s.camera, o);
  Framebuffer fixed(o.width, o.height);
  Framebuffer resolved(o.width, o.height, Framebuffer::Storage::kResolved);
  SerialRenderer r;
  r.Render(ctx, fixed);
  r.Render(ctx, resolved);
  CHECK(resolved.sums() == nullptr);
  const std::vector<float> a = fixed.ToRgb();
  REQUIRE(resolved.resolved().size() == a.size());
  CHECK(std::memcmp(a.data(), resolved.resolved().data(), a.size() * sizeof(float)) == 0);
  CHECK(resolved.dropped_nan() == fixed.dropped_nan());
  CHECK(resolved.clamped() == fixed.clamped());
  // The queue backends add from any thread to any pixel: they refuse it.
  BackendOptions b;
  b.kind = BackendKind::kLock;
  b.threads = 2;
  HostRenderer lock(b);
  CHECK_THROWS_AS(lock.BeginFrame(ctx, resolved), Error);
  b.kind = BackendKind::kTiles;
  HostRenderer tiles(b);
  resolved.Clear();
  tiles.RenderFrame(ctx, resolved);
  CHECK(std::memcmp(a.data(), resolved.resolved().data(), a.size() * sizeof(float)) == 0);
}

}  // namespace
}  // namespace rs
