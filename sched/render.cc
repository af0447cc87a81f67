// Render options, frame statistics, image tiling and the serial reference renderer's entry
// points (see render.h).
#include "sched/render.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <optional>
#include <string>
#include <utility>

#include "kernels/build_threads.h"  // RunParts
#include "sched/engine.h"

namespace rs {

namespace {

using Clock = std::chrono::steady_clock;

double Seconds(Clock::time_point a, Clock::time_point b) {
  return std::chrono::duration<double>(b - a).count();
}

void AddTrace(TraceStats& to, const TraceStats& from) {
  to.rays += from.rays;
  to.cell_steps += from.cell_steps;
  to.triangle_tests += from.triangle_tests;
  to.cache_lookups += from.cache_lookups;
  to.cache_hits += from.cache_hits;
  to.empty_skips += from.empty_skips;
  to.packets += from.packets;
  to.packets_refused += from.packets_refused;
  to.packet_rays += from.packet_rays;
  to.packets_regrouped += from.packets_regrouped;
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
  if (o.batch < 1 || o.batch > RenderOptions::kMaxBatch) {
    fail("batch " + std::to_string(o.batch) + " must be in [1, " + std::to_string(RenderOptions::kMaxBatch) + "]");
  }
  if (o.ray_budget < 1) fail("ray_budget " + std::to_string(o.ray_budget) + " must be >= 1");
  if (!std::isfinite(o.weight_cutoff) || o.weight_cutoff < 0.0f) {
    fail("weight_cutoff " + std::to_string(o.weight_cutoff) + " must be finite and >= 0");
  }
  if (o.tile_size < 1) fail("tile_size " + std::to_string(o.tile_size) + " must be >= 1");
  if (o.order != RayOrder::kScanline && o.order != RayOrder::kBlock4x2 &&
      o.order != RayOrder::kBlock8x8) {
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
  for (int k = 0; k < kNumRayKinds; ++k) {
    rays[k] += o.rays[k];
    trace_calls[k] += o.trace_calls[k];
  }
  tasks += o.tasks;
  budget_dropped += o.budget_dropped;
  hits += o.hits;
  occluded += o.occluded;
  shade.Merge(o.shade);
  AddTrace(trace, o.trace);
  generate_seconds += o.generate_seconds;
  trace_seconds += o.trace_seconds;
  for (int k = 0; k < kNumRayKinds; ++k) trace_kind_seconds[k] += o.trace_kind_seconds[k];
  shade_seconds += o.shade_seconds;
  schedule_seconds += o.schedule_seconds;
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

std::vector<LightBuffer> BuildLightBuffers(const Scene& scene, const Accel& accel, int threads) {
  std::vector<LightBuffer> buffers;
  RebuildLightBuffers(scene, accel, &buffers, threads);
  return buffers;
}

void RebuildLightBuffers(const Scene& scene, const Accel& accel, std::vector<LightBuffer>* buffers,
                         int threads) {
  const size_t n = scene.lights.size();
  while (buffers->size() > n) buffers->pop_back();
  const size_t kept = buffers->size();
  std::vector<std::optional<LightBuffer>> added(n - kept);  // (no allocation when none is new)
  const auto build = [&](size_t l) {
    const glm::vec3& q = scene.lights[l].position;
    const float p[3] = {q.x, q.y, q.z};
    if (l < kept) {
      (*buffers)[l].Rebuild(accel, p);
    } else {
      added[l - kept].emplace(accel, p);
    }
  };
  const size_t parts = std::max<size_t>(1, std::min<size_t>(size_t(BuildThreadCount(threads)), n));
  RunParts(int(parts), [&](int part) {
    for (size_t l = size_t(part); l < n; l += parts) build(l);
  });
  buffers->reserve(n);
  for (std::optional<LightBuffer>& b : added) buffers->push_back(std::move(*b));
}

void SetNextCamera(FrameContext& ctx, const Camera& next) {
  ctx.next_camera = MakeCameraBasis(next, ctx.options.width, ctx.options.height);
  ctx.has_next_camera = true;
}

void ImageTiles(int width, int height, int tile_width, int tile_height, std::vector<Tile>& out) {
  out.clear();
  if (width < 1 || height < 1 || tile_width < 1 || tile_height < 1) return;
  for (int y = 0; y < height; y += tile_height) {
    for (int x = 0; x < width; x += tile_width) {
      out.push_back(Tile{x, y, std::min(x + tile_width, width), std::min(y + tile_height, height)});
    }
  }
}

std::vector<Tile> ImageTiles(int width, int height, int tile_size) {
  std::vector<Tile> tiles;
  ImageTiles(width, height, tile_size, tile_size, tiles);
  return tiles;
}

FrameStats SerialRenderer::Render(const FrameContext& ctx, Framebuffer& fb) {
  const auto t0 = Clock::now();
  FrameStats stats;
  ImageTiles(ctx.options.width, ctx.options.height, ctx.options.tile_size, ctx.options.tile_size,
             tiles_);
  RenderTiles(ctx, tiles_.data(), tiles_.size(), fb, stats);
  stats.total_seconds = Seconds(t0, Clock::now());
  return stats;
}

void SerialRenderer::RenderTiles(const FrameContext& ctx, const Tile* tiles, size_t num_tiles,
                                 Framebuffer& fb, FrameStats& stats) {
  for (size_t i = 0; i < num_tiles; ++i) engine_.RenderTile(ctx, tiles[i], fb, stats);
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
