// ProcessTask (the per-task work every backend calls) and the serial reference renderer
// (see render.h).
#include "sched/render.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <string>
#include <utility>

namespace rs {

namespace {

using Clock = std::chrono::steady_clock;

double Seconds(Clock::time_point a, Clock::time_point b) {
  return std::chrono::duration<double>(b - a).count();
}

constexpr int32_t kShadowKind = static_cast<int32_t>(RayKind::kShadow);

void AddTrace(TraceStats& to, const TraceStats& from) {
  to.rays += from.rays;
  to.cell_steps += from.cell_steps;
  to.triangle_tests += from.triangle_tests;
}

// Shadow rays: an unoccluded ray carries its light contribution to the pixel.
void OccludeAndAdd(const FrameContext& ctx, const RayStreamView& rays, Framebuffer& fb,
                   TaskScratch& scratch, FrameStats& stats) {
  const size_t n = rays.size;
  if (n == 0) return;
  scratch.occluded.Reserve(n);
  int32_t* occluded = scratch.occluded.data();
  const auto t0 = Clock::now();
  ctx.accel->Occluded(rays, occluded, &stats.trace);
  const auto t1 = Clock::now();
  uint64_t blocked = 0;
  for (size_t i = 0; i < n; ++i) {
    if (occluded[i] != 0) {
      ++blocked;
      continue;
    }
    fb.Add(rays.pixel[i], rays.wr[i], rays.wg[i], rays.wb[i]);
  }
  const auto t2 = Clock::now();
  stats.rays[kShadowKind] += n;
  stats.occluded += blocked;
  stats.trace_seconds += Seconds(t0, t1);
  stats.shade_seconds += Seconds(t1, t2);
}

// Primary, reflection and refraction rays: closest hit, then shading into fb and scratch.spawned.
void TraceAndShade(const FrameContext& ctx, const RayStreamView& rays, Framebuffer& fb,
                   TaskScratch& scratch, FrameStats& stats) {
  const size_t n = rays.size;
  if (n == 0) return;
  scratch.hits.Resize(n);
  scratch.hits.Reset();
  const HitStreamView hits = scratch.hits.view();
  const auto t0 = Clock::now();
  ctx.accel->Intersect(rays, hits, &stats.trace);
  const auto t1 = Clock::now();
  for (size_t i = 0; i < n; ++i) {
    stats.hits += hits.prim[i] >= 0 ? 1 : 0;
    const int32_t kind = rays.kind[i];
    if (kind >= 0 && kind < kNumRayKinds) ++stats.rays[kind];
  }
  scratch.contributions.Clear();
  Shade(*ctx.scene, ctx.shade, rays, hits, scratch.contributions, scratch.spawned, &stats.shade);
  fb.Add(scratch.contributions.view());
  stats.trace_seconds += Seconds(t0, t1);
  stats.shade_seconds += Seconds(t1, Clock::now());
}

void FlushOpen(RayStream& open, TaskSink& out) {
  if (open.empty()) return;
  open.FillPadding();
  out.Push(std::move(open));
  open = RayStream();
}

}  // namespace

void ValidateRenderOptions(const RenderOptions& o) {
  auto fail = [](const std::string& what) { throw Error("render options: " + what); };
  if (o.width < 1 || o.height < 1) {
    fail("image size " + std::to_string(o.width) + "x" + std::to_string(o.height) +
         " must be at least 1x1");
  }
  if (static_cast<uint64_t>(o.width) * static_cast<uint64_t>(o.height) >= (uint64_t{1} << 32)) {
    fail("image size " + std::to_string(o.width) + "x" + std::to_string(o.height) +
         " has >= 2^32 pixels");
  }
  if (o.max_depth < 0 || o.max_depth > 64) {
    fail("max_depth " + std::to_string(o.max_depth) + " must be in [0, 64]");
  }
  if (o.task_size < 1) fail("task_size " + std::to_string(o.task_size) + " must be >= 1");
  if (!std::isfinite(o.weight_cutoff) || o.weight_cutoff < 0.0f) {
    fail("weight_cutoff " + std::to_string(o.weight_cutoff) + " must be finite and >= 0");
  }
  if (o.tile_size < 1) fail("tile_size " + std::to_string(o.tile_size) + " must be >= 1");
  if (o.order != RayOrder::kScanline && o.order != RayOrder::kBlock4x2) {
    fail("unknown ray order " + std::to_string(static_cast<int>(o.order)));
  }
}

uint64_t FrameStats::TotalRays() const {
  uint64_t n = 0;
  for (const uint64_t r : rays) n += r;
  return n;
}

double FrameStats::MraysPerSecond() const {
  return total_seconds > 0 ? static_cast<double>(TotalRays()) / total_seconds * 1e-6 : 0.0;
}

void FrameStats::Merge(const FrameStats& o) {
  for (int k = 0; k < kNumRayKinds; ++k) rays[k] += o.rays[k];
  tasks += o.tasks;
  hits += o.hits;
  occluded += o.occluded;
  shade.Merge(o.shade);
  AddTrace(trace, o.trace);
  generate_seconds += o.generate_seconds;
  trace_seconds += o.trace_seconds;
  shade_seconds += o.shade_seconds;
  total_seconds = std::max(total_seconds, o.total_seconds);
}

FrameContext MakeFrameContext(const Scene& scene, const Accel& accel, const Camera& camera,
                              const RenderOptions& options) {
  ValidateRenderOptions(options);
  FrameContext ctx;
  ctx.scene = &scene;
  ctx.accel = &accel;
  ctx.camera = MakeCameraBasis(camera, options.width, options.height);
  ctx.options = options;
  ctx.shade.max_depth = options.max_depth;
  ctx.shade.weight_cutoff = options.weight_cutoff;
  ctx.shade.stages = ShadeStagesFor(scene, ctx.shade);  // the shading pipeline, once per frame
  return ctx;
}

RayStream TaskPool::Get() {
  if (free_.empty()) return RayStream();
  RayStream task = std::move(free_.back());
  free_.pop_back();
  task.Clear();
  return task;
}

void TaskPool::Put(RayStream&& task) {
  task.Clear();
  free_.push_back(std::move(task));
}

void CutIntoTasks(const RayStreamView& rays, size_t task_size, TaskSink& out,
                  TaskScratch& scratch) {
  HWY_DASSERT(task_size >= 1);
  for (size_t i = 0; i < rays.size; ++i) {
    RayStream& open = rays.kind[i] == kShadowKind ? scratch.open_shadow : scratch.open_bounce;
    if (open.capacity() == 0) {
      open = out.NewTask();
      open.Reserve(task_size);
    }
    open.PushFrom(rays, i);
    if (open.size() >= task_size) FlushOpen(open, out);
  }
  FlushOpen(scratch.open_shadow, out);
  FlushOpen(scratch.open_bounce, out);
}

void ProcessTask(const FrameContext& ctx, const RayStreamView& task, Framebuffer& fb,
                 TaskSink& out, TaskScratch& scratch, FrameStats& stats) {
  ++stats.tasks;
  if (task.size == 0) return;
  size_t shadow = 0;
  for (size_t i = 0; i < task.size; ++i) shadow += task.kind[i] == kShadowKind ? 1 : 0;

  scratch.spawned.Clear();
  if (shadow == task.size) {
    OccludeAndAdd(ctx, task, fb, scratch, stats);
  } else if (shadow == 0) {
    TraceAndShade(ctx, task, fb, scratch, stats);
  } else {
    // Mixed task: split by class (each ray's result does not depend on its neighbours).
    scratch.shadow.Clear();
    scratch.trace.Clear();
    for (size_t i = 0; i < task.size; ++i) {
      (task.kind[i] == kShadowKind ? scratch.shadow : scratch.trace).PushFrom(task, i);
    }
    scratch.shadow.FillPadding();
    scratch.trace.FillPadding();
    OccludeAndAdd(ctx, scratch.shadow.view(), fb, scratch, stats);
    TraceAndShade(ctx, scratch.trace.view(), fb, scratch, stats);
  }
  if (!scratch.spawned.empty()) {
    const auto t0 = Clock::now();
    CutIntoTasks(scratch.spawned.view(), static_cast<size_t>(ctx.options.task_size), out,
                 scratch);
    stats.shade_seconds += Seconds(t0, Clock::now());
  }
}

std::vector<Tile> ImageTiles(int width, int height, int tile_size) {
  std::vector<Tile> tiles;
  if (width < 1 || height < 1 || tile_size < 1) return tiles;
  for (int y = 0; y < height; y += tile_size) {
    for (int x = 0; x < width; x += tile_size) {
      tiles.push_back(Tile{x, y, std::min(x + tile_size, width), std::min(y + tile_size, height)});
    }
  }
  return tiles;
}

void GeneratePrimaryTasks(const FrameContext& ctx, const Tile& tile, TaskSink& out,
                          FrameStats& stats) {
  const auto t0 = Clock::now();
  const size_t n = tile.NumPixels();
  const size_t task_size = static_cast<size_t>(ctx.options.task_size);
  for (size_t first = 0; first < n; first += task_size) {
    const size_t count = std::min(task_size, n - first);
    RayStream task = out.NewTask();
    task.Resize(count);
    GeneratePrimaryRays(ctx.camera, tile, ctx.options.order, first, count, task.view(), 0);
    task.FillPadding();
    out.Push(std::move(task));
  }
  stats.generate_seconds += Seconds(t0, Clock::now());
}

FrameStats SerialRenderer::Render(const FrameContext& ctx, Framebuffer& fb) {
  const auto t0 = Clock::now();
  FrameStats stats;
  const std::vector<Tile> tiles =
      ImageTiles(ctx.options.width, ctx.options.height, ctx.options.tile_size);
  RenderTiles(ctx, tiles.data(), tiles.size(), fb, stats);
  stats.total_seconds = Seconds(t0, Clock::now());
  return stats;
}

void SerialRenderer::RenderTiles(const FrameContext& ctx, const Tile* tiles, size_t num_tiles,
                                 Framebuffer& fb, FrameStats& stats) {
  fifo_.clear();
  for (size_t i = 0; i < num_tiles; ++i) GeneratePrimaryTasks(ctx, tiles[i], *this, stats);
  while (!fifo_.empty()) {
    RayStream task = std::move(fifo_.front());
    fifo_.pop_front();
    ProcessTask(ctx, task.view(), fb, *this, scratch_, stats);
    pool_.Put(std::move(task));
  }
}

FrameStats RenderSerial(const FrameContext& ctx, Framebuffer& fb) {
  SerialRenderer renderer;
  return renderer.Render(ctx, fb);
}

RenderResult RenderImage(const Scene& scene, const Accel& accel, const Camera& camera,
                         const RenderOptions& options) {
  const FrameContext ctx = MakeFrameContext(scene, accel, camera, options);
  Framebuffer fb(options.width, options.height);
  RenderResult result;
  result.stats = RenderSerial(ctx, fb);
  fb.ToRgb(result.rgb);
  return result;
}

}  // namespace rs
