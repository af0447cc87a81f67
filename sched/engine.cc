// The per-worker frame engine (see engine.h): batched kernel calls and a depth-first walk over
// generations of a tile's ray tree in fixed arenas.
#include "sched/engine.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <span>

#include "sched/tile_plan.h"  // TileWorkCost

namespace rs {

namespace {

using Clock = std::chrono::steady_clock;

double Seconds(Clock::time_point a, Clock::time_point b) {
  return std::chrono::duration<double>(b - a).count();
}

constexpr int32_t kShadowKind = static_cast<int32_t>(RayKind::kShadow);

// Shade output per sub-chunk is at most chunk * (lights + 2) rays; chunks shrink with many lights
// so that this scratch stays near kMaxSpawned rays. A multiple of kStreamPad (sub-chunks start
// vector-aligned: Shade loads aligned vectors), at least one vector.
constexpr size_t kMaxSpawned = 16384;

size_t ShadeChunk(size_t batch, size_t lights) {
  const size_t chunk = std::min(kMaxSpawned / (lights + 2), batch) / kStreamPad * kStreamPad;
  return std::max(chunk, kStreamPad);
}

// Rays [from, from + kStreamPad) of v become rays that can never hit: the lanes a kernel may
// load past the end of a view that ends at `from`. v must have the room.
void SealLanes(const RayStreamView& v, size_t from) { SealRays(v, from, from + kStreamPad); }

// Moves rays [from, end) of v to [to, to + end - from), to <= from (memmove order).
void MoveRays(const RayStreamView& v, size_t from, size_t end, size_t to) {
  for (size_t i = from; i < end; ++i, ++to) CopyRay<true>(v, i, v, to);
}

// The light a shadow ray comes from: its origin is the light's position (kernels/shade.h), so
// the light at o. Shadow rays come in runs of one light, so `guess` (the previous ray's light)
// is tried first. (A ray whose origin is no light's, impossible from Shade, gets light 0.)
uint32_t LightOf(const RayStreamView& r, size_t i, std::span<const PointLight> lights,
                 uint32_t guess) {
  const auto at = [&](uint32_t l) {
    const glm::vec3& p = lights[l].position;
    return r.ox[i] == p.x && r.oy[i] == p.y && r.oz[i] == p.z;
  };
  if (at(guess)) return guess;
  for (uint32_t l = 0; l < lights.size(); ++l) {
    if (at(l)) return l;
  }
  return 0;
}

// The rays of `from` (a RayStream's view, a generation of mixed kinds) appended by class, in one
// counting and one copying pass: its shadow rays to `shadow_to` grouped by light (stable within
// a light), the others to `bounce_to` in order. Ungrouped, a 64-ray run would mix several
// lights and miss the coherent packets; grouped, each run shares its light. The two may be one
// stream (the shadow rays first). Capacities must hold the rays (arenas: no
// growth in the steady state). Order never changes the image.
void Partition(const RayStreamView& from, std::span<const PointLight> lights,
               std::vector<uint32_t>& light_of, std::vector<size_t>& start, RayStream& shadow_to,
               RayStream& bounce_to) {
  const size_t groups = std::max<size_t>(lights.size(), 1);
  light_of.resize(from.size);
  start.assign(groups + 1, 0);
  size_t bounce = 0;
  uint32_t guess = 0;
  for (size_t i = 0; i < from.size; ++i) {
    if (from.kind[i] != kShadowKind) {
      ++bounce;
      continue;
    }
    if (lights.size() > 1) guess = LightOf(from, i, lights, guess);
    light_of[i] = guess;
    ++start[guess + 1];
  }
  for (size_t l = 1; l <= groups; ++l) start[l] += start[l - 1];
  const size_t s0 = shadow_to.size();
  shadow_to.Resize(s0 + start[groups]);
  const size_t b0 = bounce_to.size();  // after the shadow rays if it is the same stream
  bounce_to.Resize(b0 + bounce);
  const RayStreamView s = shadow_to.view();
  const RayStreamView b = bounce_to.view();
  size_t j = b0;
  for (size_t i = 0; i < from.size; ++i) {
    if (from.kind[i] != kShadowKind) {
      CopyRay<true>(from, i, b, j++);
    } else {
      CopyRay<true>(from, i, s, s0 + start[light_of[i]]++);
    }
  }
}

uint64_t TasksOf(size_t rays, int task_size) {
  const size_t t = static_cast<size_t>(task_size);
  return (rays + t - 1) / t;
}

}  // namespace

namespace {

// The arena sizes (in rays) for a frame of `o` with `lights` lights. A generation handed to
// TraceGeneration holds up to ceil(batch / task_size) tasks; every stream keeps kStreamPad lanes
// after its rays for the seal.
struct ArenaPlan {
  size_t primary, level, light, shadow, bounce, hits, contributions;
  size_t levels;
};

ArenaPlan PlanArenas(size_t batch, int max_depth, int task_size, size_t lights) {
  const size_t ts = static_cast<size_t>(task_size);
  const size_t generation = std::max(batch, (batch + ts - 1) / ts * ts);
  const size_t chunk = ShadeChunk(batch, lights);
  ArenaPlan p;
  p.levels = static_cast<size_t>(max_depth) + 1;
  p.primary = batch + kStreamPad;
  p.level = 2 * batch + kStreamPad;
  p.light = chunk + kStreamPad;  // one light's shadow rays of a sub-chunk
  p.shadow = std::max(generation, chunk * lights) + kStreamPad;
  p.bounce = std::max(generation, 2 * chunk) + kStreamPad;  // a mixed generation, or Shade's
  p.hits = generation + kStreamPad;
  p.contributions = 2 * chunk + kStreamPad;  // background or ambient, per ray
  return p;
}

}  // namespace

size_t EngineRayBudget(const RenderOptions& o, size_t lights) {
  const ArenaPlan p =
      PlanArenas(static_cast<size_t>(o.batch), o.max_depth, o.task_size, lights);
  return PaddedSize(p.primary) + (p.levels - 1) * PaddedSize(p.level) +
         std::max<size_t>(lights, 1) * PaddedSize(p.light) + PaddedSize(p.shadow) +
         PaddedSize(p.bounce);
}

size_t EngineShadowBatch(const RenderOptions& o, size_t lights) {
  const size_t batch = static_cast<size_t>(o.batch);
  return std::max(batch, ShadeChunk(batch, lights) * lights);  // <= PlanArenas' shadow
}

void RayEngine::Reserve(const FrameContext& ctx) {
  const size_t batch = static_cast<size_t>(ctx.options.batch);
  const int depth = ctx.options.max_depth;
  const size_t lights = ctx.scene->lights.size();
  if (batch <= batch_ && depth <= depth_ && lights <= lights_ &&
      ctx.options.task_size >= task_size_) {
    return;
  }
  batch_ = std::max(batch, batch_);
  depth_ = std::max(depth, depth_);
  lights_ = std::max(lights, lights_);
  task_size_ = std::min(ctx.options.task_size, task_size_);
  const ArenaPlan p = PlanArenas(batch_, depth_, task_size_, lights_);
  levels_.resize(p.levels);
  levels_[0].Reserve(p.primary);
  for (size_t d = 1; d < levels_.size(); ++d) levels_[d].Reserve(p.level);
  light_rays_.resize(std::max<size_t>(lights_, 1));
  light_to_.resize(light_rays_.size());
  for (RayStream& l : light_rays_) l.Reserve(p.light);
  shadow_.Reserve(p.shadow);
  bounce_.Reserve(p.bounce);
  hits_.Reserve(p.hits);
  occluded_.Reserve(p.shadow);
  contributions_.Reserve(p.contributions);
  light_of_.reserve(p.shadow);  // a mixed generation
  local_sums_.resize(3 * batch_);
  batch_pixels_.resize(batch_);
  light_start_.reserve(lights_ + 2);  // Partition: max(lights, 1) + 1
}

size_t RayEngine::capacity_rays() const {
  size_t n = shadow_.capacity() + bounce_.capacity();
  for (const RayStream& l : light_rays_) n += l.capacity();
  for (const RayStream& l : levels_) n += l.capacity();
  return n;
}

void RayEngine::ChargeBlocks(const RayStreamView& rays, const int32_t* prim, uint64_t cell_steps,
                             uint64_t triangle_tests) {
  BlockWork& b = *block_work_;
  const size_t n = rays.size;
  if (!local_) {
    // TraceGeneration: the caller grouped these rays (whatever a thread popped), and a packet's
    // cell steps and triangle tests depend on its other rays; so each ray is charged only what
    // it decides alone: itself, and a shading call if it hit. Fixed per ray, so the record does
    // not depend on the grouping, the order of the calls or the thread.
    TileWork one;
    one.rays = 1;
    const int64_t ray = std::llround(TileWorkCost(one) / kBlockWorkUnit);
    one.shading_calls = 1;
    const int64_t shaded = std::llround(TileWorkCost(one) / kBlockWorkUnit);
    for (size_t i = 0; i < n; ++i) {
      b.work[b.BlockOf(PixelOf(rays, i))] += prim != nullptr && prim[i] >= 0 ? shaded : ray;
    }
    return;
  }
  // RenderTile: the calls are the tile's own batches (the same rays together in every run), so
  // the call's counters are charged. Fixed point: every ray gets units / n, the first units % n
  // one more, so the call's units are charged exactly and the sums do not depend on the order
  // of the calls.
  TileWork w;
  w.rays = n;
  w.cell_steps = cell_steps;
  w.triangle_tests = triangle_tests;
  const uint64_t units = static_cast<uint64_t>(std::llround(TileWorkCost(w) / kBlockWorkUnit));
  const uint64_t share = units / n;
  const uint64_t extra = units - share * n;
  for (size_t i = 0; i < n; ++i) {
    b.work[b.BlockOf(PixelOf(rays, i))] += static_cast<int64_t>(share + (i < extra ? 1 : 0));
  }
}

void RayEngine::AddContributions(Framebuffer& fb, const uint32_t* pixel, const float* r,
                                 const float* g, const float* b, const int32_t* skip, size_t n) {
  if (local_) {
    AddFixedContributions<false>(local_sums_.data(), pixel, r, g, b, skip, n, &local_nan_,
                                 &local_clamped_);
  } else if (shared_pixels_ && combine_lock_ != nullptr) {
    combined_.Add(fb, *combine_lock_, pixel, r, g, b, skip, n);
    size_t added = n;
    if (skip != nullptr) added = static_cast<size_t>(std::count(skip, skip + n, 0));
    table_adds_ += added;
  } else if (shared_pixels_) {
    fb.Add(pixel, r, g, b, skip, n);
  } else {
    fb.Add<false>(pixel, r, g, b, skip, n);
  }
}

void RayEngine::Occlude(const FrameContext& ctx, const RayStreamView& rays, Framebuffer& fb,
                        FrameStats& stats) {
  const size_t n = rays.size;
  if (n == 0) return;
  occluded_.Reserve(n);
  int32_t* occluded = occluded_.data();
  const AccelTracer accel(*ctx.accel);
  const LightAccelTracer lights(*ctx.accel, ctx.scene->lights, ctx.light_buffers);
  const Tracer& tracer = ctx.tracer != nullptr      ? *ctx.tracer
                         : ctx.light_buffers.empty() ? static_cast<const Tracer&>(accel)
                                                     : lights;
  const uint64_t steps0 = stats.trace.cell_steps, tests0 = stats.trace.triangle_tests;
  const auto t0 = Clock::now();
  tracer.Occluded(rays, occluded, &stats.trace);
  const auto t1 = Clock::now();
  if (block_work_ != nullptr) {
    ChargeBlocks(rays, nullptr, stats.trace.cell_steps - steps0,
                 stats.trace.triangle_tests - tests0);
  }
  uint64_t blocked = 0;
  for (size_t i = 0; i < n; ++i) blocked += occluded[i] != 0 ? 1 : 0;
  AddContributions(fb, rays.pixel, rays.wr, rays.wg, rays.wb, occluded, n);
  stats.rays[kShadowKind] += n;
  ++stats.trace_calls[kShadowKind];
  stats.tasks += TasksOf(n, ctx.options.task_size);
  stats.occluded += blocked;
  const double traced = Seconds(t0, t1);
  stats.trace_seconds += traced;
  stats.trace_kind_seconds[kShadowKind] += traced;
}

void RayEngine::TraceAndShade(const FrameContext& ctx, const RayStreamView& rays,
                              Framebuffer& fb, RayStream& bounce, RayStream* shadow_out,
                              FrameStats& stats) {
  const size_t n = rays.size;
  if (n == 0) return;
  hits_.Resize(n);
  const HitStreamView hits = hits_.view();
  const AccelTracer accel(*ctx.accel);
  const Tracer& tracer = ctx.tracer != nullptr ? *ctx.tracer : accel;
  const uint64_t steps0 = stats.trace.cell_steps, tests0 = stats.trace.triangle_tests;
  const auto t0 = Clock::now();
  tracer.Intersect(rays, hits, &stats.trace);
  const auto t1 = Clock::now();
  if (block_work_ != nullptr) {
    ChargeBlocks(rays, hits.prim, stats.trace.cell_steps - steps0,
                 stats.trace.triangle_tests - tests0);
    if (float* depth = block_work_->pixel_depth; depth != nullptr) {
      const float inf = std::numeric_limits<float>::infinity();
      for (size_t i = 0; i < n; ++i) {
        if (rays.kind[i] != static_cast<int32_t>(RayKind::kPrimary)) continue;
        depth[PixelOf(rays, i)] = hits.prim[i] >= 0 ? hits.t[i] : inf;
      }
    }
  }
  // Lanes past n: misses (Shade may load them; stale prims could index another scene).
  for (size_t i = n; i < PaddedSize(n); ++i) {
    hits.t[i] = std::numeric_limits<float>::infinity();
    hits.u[i] = hits.v[i] = 0.0f;
    hits.prim[i] = -1;
  }
  uint64_t kinds[kNumRayKinds] = {};
  for (size_t i = 0; i < n; ++i) {
    stats.hits += hits.prim[i] >= 0 ? 1 : 0;
    const int32_t kind = rays.kind[i];
    if (kind >= 0 && kind < kNumRayKinds) ++kinds[kind];
  }
  const double traced = Seconds(t0, t1);
  for (int k = 0; k < kNumRayKinds; ++k) {
    stats.rays[k] += kinds[k];
    stats.trace_calls[k] += kinds[k] != 0 ? 1 : 0;
    stats.trace_kind_seconds[k] += traced * static_cast<double>(kinds[k]) / static_cast<double>(n);
  }
  stats.tasks += TasksOf(n, ctx.options.task_size);
  stats.trace_seconds += traced;

  // Shade splits its output: bounce rays straight to `bounce`, light 0's shadow rays straight
  // to their destination (unless it is `bounce` too), the other lights' to scratch streams
  // appended after them (bulk copies), so each light's rays form one run.
  const size_t lights = ctx.scene->lights.size();
  RayStream& shadow = shadow_out != nullptr ? *shadow_out : shadow_;
  const size_t direct = &shadow == &bounce ? 0 : 1;  // lights written in place
  for (size_t l = 0; l < lights; ++l) light_to_[l] = l < direct ? &shadow : &light_rays_[l];
  const size_t chunk = ShadeChunk(batch_, lights_);
  for (size_t first = 0; first < n; first += chunk) {
    const size_t m = std::min(chunk, n - first);
    if (shadow_out == nullptr) shadow_.Clear();
    for (size_t l = direct; l < lights; ++l) light_rays_[l].Clear();
    const auto s0 = Clock::now();
    contributions_.Clear();
    Shade(*ctx.scene, ctx.shade, SubView(rays, first, m), SubView(hits, first, m),
          contributions_, std::span<RayStream* const>(light_to_.data(), lights), bounce,
          &stats.shade);
    stats.shade_seconds += Seconds(s0, Clock::now());
    const ContributionView c = contributions_.view();
    AddContributions(fb, c.pixel, c.r, c.g, c.b, nullptr, c.size);
    for (size_t l = direct; l < lights; ++l) {
      shadow.Append(light_rays_[l].view(), 0, light_rays_[l].size());
    }
    if (shadow_out != nullptr) continue;
    SealLanes(shadow_.view(), shadow_.size());
    Occlude(ctx, shadow_.view(), fb, stats);
  }
}

void RayEngine::Drain(const FrameContext& ctx, size_t primaries, Framebuffer& fb,
                      FrameStats& stats) {
  const uint64_t budget = static_cast<uint64_t>(ctx.options.ray_budget) * primaries;
  const uint64_t rays0 = stats.TotalRays();
  const size_t batch = static_cast<size_t>(ctx.options.batch);
  const size_t top = static_cast<size_t>(ctx.options.max_depth);
  size_t d = 0;  // the deepest level that may hold rays
  for (;;) {
    while (levels_[d].empty() && d > 0) --d;
    RayStream& level = levels_[d];
    if (level.empty()) return;
    if (d > 0 && stats.TotalRays() - rays0 >= budget) {
      // The batch's tree has used its ray budget: its pending bounce rays are dropped.
      for (size_t e = 1; e <= top; ++e) {
        stats.budget_dropped += levels_[e].size();
        levels_[e].Clear();
      }
      continue;
    }
    // k rays at the end of the level, from a vector-aligned start (Shade loads aligned
    // vectors); its earlier rays wait until the children are done. The fewer than kStreamPad
    // rays after the chunk move down into its place afterwards.
    const size_t s = level.size();
    const size_t k = std::min(batch, s);
    const size_t start = (s - k) / kStreamPad * kStreamPad;
    const RayStreamView all = level.view();
    SealLanes(all, s);
    RayStream* children = d < top ? &levels_[d + 1] : &bounce_;
    TraceAndShade(ctx, SubView(all, start, k), fb, *children, nullptr, stats);
    HWY_DASSERT(d < top || bounce_.empty());
    bounce_.Clear();
    MoveRays(all, start + k, s, start);
    level.Resize(s - k);
    if (d < top && !levels_[d + 1].empty()) ++d;
  }
}

void RayEngine::RenderTile(const FrameContext& ctx, const Tile& tile, Framebuffer& fb,
                           FrameStats& stats) {
  Reserve(ctx);
  // A batch's ray tree contributes only to the batch's own pixels: its rays carry the index of
  // their primary ray in the batch, their contributions are summed here in fixed point, and
  // each pixel's sums go to the framebuffer once, when the batch's tree is done.
  local_ = true;
  const size_t n = tile.NumPixels();
  const size_t batch = static_cast<size_t>(ctx.options.batch);
  for (size_t first = 0; first < n; first += batch) {
    const auto t0 = Clock::now();
    const size_t k = std::min(batch, n - first);
    RayStream& primary = levels_[0];
    primary.Resize(k);
    const RayStreamView v = primary.view();
    GeneratePrimaryRays(ctx.camera, tile, ctx.options.order, first, k, v, 0);
    SealLanes(v, k);
    for (size_t i = 0; i < k; ++i) {
      batch_pixels_[i] = v.pixel[i];
      v.pixel[i] = static_cast<uint32_t>(i);
    }
    std::fill(local_sums_.begin(), local_sums_.begin() + 3 * k, 0);
    local_nan_ = local_clamped_ = 0;
    stats.generate_seconds += Seconds(t0, Clock::now());
    Drain(ctx, k, fb, stats);
    for (size_t i = 0; i < k; ++i) fb.SetPixelSums(batch_pixels_[i], &local_sums_[3 * i]);
    fb.AddCounters(local_nan_, local_clamped_);
  }
}

void RayEngine::TraceGeneration(const FrameContext& ctx, const RayStreamView& shadow,
                                const RayStreamView& rays, Framebuffer& fb, RayStream& shadow_out,
                                RayStream& bounce_out, FrameStats& stats) {
  Reserve(ctx);
  local_ = false;  // a generation may hold any pixels another thread also adds to
  Occlude(ctx, shadow, fb, stats);
  TraceAndShade(ctx, rays, fb, bounce_out, &shadow_out, stats);
}

void RayEngine::TraceGeneration(const FrameContext& ctx, const RayStreamView& rays,
                                Framebuffer& fb, RayStream& spawned, FrameStats& stats) {
  Reserve(ctx);
  // Split by class (a ray's result does not depend on its neighbours).
  shadow_.Clear();
  bounce_.Clear();
  Partition(rays, ctx.scene->lights, light_of_, light_start_, shadow_, bounce_);
  SealLanes(shadow_.view(), shadow_.size());
  SealLanes(bounce_.view(), bounce_.size());
  TraceGeneration(ctx, shadow_.view(), bounce_.view(), fb, spawned, spawned, stats);
  shadow_.Clear();
  bounce_.Clear();
}

}  // namespace rs
