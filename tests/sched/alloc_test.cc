// No heap allocation in the steady state of a frame: this binary replaces operator new and the
// malloc family and counts the calls made while a later frame of every host backend renders.
// Under ThreadSanitizer, whose runtime owns malloc (and calls it before the program's atomics
// may be touched), and under AddressSanitizer, which owns it too, nothing is replaced and
// nothing counted: the same frames run for the sanitizers' checks only.
#include <doctest/doctest.h>

#include <atomic>
#include <cstdlib>
#include <new>
#include <string>

#include "sched/backends.h"
#include "tests/support/hand_scenes.h"
#include "tests/test_util.h"  // RS_TEST_TSAN, RS_TEST_ASAN

#define RS_ALLOC_COUNTED (!RS_TEST_TSAN && !RS_TEST_ASAN)

extern "C" {
void* __libc_malloc(size_t size);
void* __libc_calloc(size_t n, size_t size);
void* __libc_realloc(void* p, size_t size);
void* __libc_memalign(size_t align, size_t size);
void __libc_free(void* p);
}

namespace {

std::atomic<bool> g_counting{false};
std::atomic<uint64_t> g_allocations{0};

[[maybe_unused]] void Count() {
  if (g_counting.load(std::memory_order_relaxed)) {
    g_allocations.fetch_add(1, std::memory_order_relaxed);
  }
}

}  // namespace

#if RS_ALLOC_COUNTED
extern "C" {
void* malloc(size_t size) {
  Count();
  return __libc_malloc(size);
}
void* calloc(size_t n, size_t size) {
  Count();
  return __libc_calloc(n, size);
}
void* realloc(void* p, size_t size) {
  Count();
  return __libc_realloc(p, size);
}
void* aligned_alloc(size_t align, size_t size) {
  Count();
  return __libc_memalign(align, size);
}
int posix_memalign(void** out, size_t align, size_t size) {
  Count();
  *out = __libc_memalign(align, size);
  return *out != nullptr ? 0 : ENOMEM;
}
void free(void* p) { __libc_free(p); }
}

void* operator new(size_t size) {
  void* p = malloc(size);
  if (p == nullptr) throw std::bad_alloc();
  return p;
}
void* operator new[](size_t size) { return operator new(size); }
void operator delete(void* p) noexcept { free(p); }
void operator delete[](void* p) noexcept { free(p); }
void operator delete(void* p, size_t) noexcept { free(p); }
void operator delete[](void* p, size_t) noexcept { free(p); }
#endif  // RS_ALLOC_COUNTED

namespace rs {
namespace {

// Renders `frames` frames of ctx; the allocations on every thread (the application thread and
// the render threads) counted during the whole BeginFrame / EndFrame of all but the first.
uint64_t LaterFrameAllocations(HostRenderer& r, const FrameContext& ctx, Framebuffer& fb,
                               int frames) {
  uint64_t allocations = 0;
  for (int frame = 0; frame < frames; ++frame) {
    fb.Clear();
    g_allocations.store(0);
    g_counting.store(frame >= 1);
    r.BeginFrame(ctx, fb);
    r.EndFrame();
    g_counting.store(false);
    allocations += g_allocations.load();
  }
  return allocations;
}

TEST_CASE("the counter sees allocations") {
  if (!RS_ALLOC_COUNTED) return;  // nothing is counted
  g_allocations.store(0);
  g_counting.store(true);
  auto* p = new std::string(100, 'x');
  g_counting.store(false);
  delete p;
  CHECK(g_allocations.load() >= 1);
}

TEST_CASE("no heap allocation while a later frame renders, on every host backend") {
  const Scene s = test::HandScene();
  const Accel accel(test::MeshOf(s));
  const std::vector<LightBuffer> lights = BuildLightBuffers(s, accel);
  REQUIRE(!lights.empty());
  RenderOptions o;
  o.width = 96;
  o.height = 80;
  o.max_depth = 4;
  for (const char* name : {"serial", "lock", "lfree", "local", "tiles"}) {
    for (const int batch : {20, 64, 1024}) {
      for (const bool with_lights : {false, true}) {  // shadow rays through light buffers
        INFO("backend ", std::string(name), " batch ", batch, " light buffers ", with_lights);
        BackendOptions b;
        REQUIRE(ParseBackendKind(name, &b.kind));
        b.threads = b.kind == BackendKind::kSerial ? 1 : 2;
        o.batch = batch;
        HostRenderer r(b);
        Framebuffer fb(o.width, o.height);
        FrameContext ctx = MakeFrameContext(s, accel, s.camera, o);
        if (with_lights) ctx.light_buffers = lights;
        CHECK(LaterFrameAllocations(r, ctx, fb, 3) == 0);
      }
    }
  }
}

TEST_CASE("no heap allocation when light buffers are rebuilt at the same size") {
  // (the references index the Accel's interleaved vertices, TriangleSoA::verts: a new Accel
  // costs the light buffers nothing)
  const Scene s = test::HandScene();
  const Accel accel(test::MeshOf(s));
  std::vector<LightBuffer> lights = BuildLightBuffers(s, accel);
  REQUIRE(!lights.empty());
  RebuildLightBuffers(s, accel, &lights);  // the scratch reaches its size
  g_allocations.store(0);
  g_counting.store(true);
  RebuildLightBuffers(s, accel, &lights);
  Accel again(test::MeshOf(s));  // (allocates: not counted below)
  g_counting.store(false);
  // the counter works: the Accel allocated
  CHECK((g_allocations.load() > 0 || !RS_ALLOC_COUNTED));
  g_allocations.store(0);
  g_counting.store(true);
  RebuildLightBuffers(s, again, &lights);  // another Accel, the same sizes
  g_counting.store(false);
  CHECK(g_allocations.load() == 0);
  again.Rebuild(test::MeshOf(s));  // in place, as a moving scene's frames do (not counted)
  g_allocations.store(0);
  g_counting.store(true);
  RebuildLightBuffers(s, again, &lights);  // the rebuilt Accel
  g_counting.store(false);
  CHECK(g_allocations.load() == 0);
}

// PBT tiles feeding the queues, and the tiles backend's PBT lists (static, stealing, the
// demand-driven master): nothing allocates in a later frame, on any thread. Counted: the whole
// BeginFrame / EndFrame of frames 1-3, so on the application thread also the tile plan's work
// between frames (TilePlan::End: the Table 1 measures, the frame models, PBT-Update; Plan: the
// next tiles, predictions and lists), which reuses buffers sized in frame 0 (pbt.h, tile_plan.h).
// Frame 0 is the warm-up: the render threads' counters, feed slots, steal ranges, the master's
// state and the pixel -> tile lookup, the cost map's block records and hit distances (every
// backend here runs the default cost-map predictor, so the queue backends' engines charge their
// rays to blocks too), and the plan's buffers, are sized there.
TEST_CASE("no heap allocation in a later PBT frame on any thread, queue and tiles") {
  const Scene s = test::HandScene();
  const Accel accel(test::MeshOf(s));
  RenderOptions o;
  o.width = 96;
  o.height = 80;
  o.max_depth = 4;
  struct Mode {
    const char* name;
    PbtAssign assign;
    bool steal;
    bool demand;
  };
  const Mode modes[] = {{"lock", PbtAssign::kGreedy, true, false},
                        {"lock", PbtAssign::kCounter, false, false},
                        {"lfree", PbtAssign::kGreedy, true, false},
                        {"lfree", PbtAssign::kCounter, false, false},
                        {"local", PbtAssign::kGreedy, true, false},
                        {"local", PbtAssign::kCounter, false, false},
                        {"tiles", PbtAssign::kGreedy, false, false},
                        {"tiles", PbtAssign::kGreedy, true, false},
                        {"tiles", PbtAssign::kGreedy, false, true},
                        {"tiles", PbtAssign::kRandom, false, true},
                        {"tiles", PbtAssign::kCounter, false, false},
                        {"tiles", PbtAssign::kRandom, false, false},
                        {"tiles", PbtAssign::kStatic, false, false},
                        {"tiles", PbtAssign::kVisit, false, false},
                        {"tiles", PbtAssign::kLpt, false, false},
                        {"local", PbtAssign::kLpt, false, false}};
  for (const Mode& mode : modes) {
    INFO("backend ", std::string(mode.name), " assign ", std::string(PbtAssignName(mode.assign)),
         " steal ", mode.steal, " demand ", mode.demand);
    BackendOptions b;
    REQUIRE(ParseBackendKind(mode.name, &b.kind));
    b.threads = 2;
    b.pbt_tiles_per_worker = 4;
    b.pbt_workers = mode.demand ? 3 : 0;  // the master: lists not one per thread
    b.assign = mode.assign;
    b.pbt_cost = PbtCost::kWork;
    b.pbt_steal = mode.steal;
    b.pbt_demand = mode.demand;
    HostRenderer r(b);
    Framebuffer fb(o.width, o.height);
    // A known next camera, moved a little: the cost map (the default predictor) is reprojected
    // in every frame's End.
    FrameContext ctx = MakeFrameContext(s, accel, s.camera, o);
    Camera next = s.camera;
    next.eye.x += 0.05f;
    next.look_at.x += 0.05f;
    SetNextCamera(ctx, next);
    CHECK(LaterFrameAllocations(r, ctx, fb, 4) == 0);
  }
}

}  // namespace
}  // namespace rs
