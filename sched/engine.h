// The frame engine of one worker: traces rays in batches of RenderOptions::batch rays (so
// primary and shadow rays reach the coherent packets) and walks a tile's ray tree deepest
// generation first, so the rays in flight are bounded by the batch and the depth, never by the
// image. All ray, hit and contribution buffers are the worker's arenas, sized once and reused
// across tiles and frames: no heap allocation in the steady state of a frame.
#pragma once

#include <cstddef>
#include <cstdint>
#include <mutex>
#include <vector>

#include "sched/cost_map.h"
#include "sched/framebuffer.h"
#include "sched/render.h"
#include "streams/ray_stream.h"
#include "streams/raygen.h"

namespace rs {

// Rays one worker holds at most for a frame of `options` in a scene with `lights` lights
// (primary batch, one pending bounce generation per depth, shadow and spawned scratch). The
// budget does not depend on the image size.
size_t EngineRayBudget(const RenderOptions& options, size_t lights);

// Shadow rays one Occlude call of an engine sized for `options` and `lights` takes without
// growing its scratch: what one Shade sub-chunk spawns (RenderTile traces them in one call), at
// least a batch. Queue backends gather up to this many popped shadow rays into one call.
size_t EngineShadowBatch(const RenderOptions& options, size_t lights);

class RayEngine {
 public:
  // Sizes the arenas for ctx (no-op when they are large enough already). Called by RenderTile
  // and TraceGeneration; call it up front to move the first frame's allocations out of the
  // frame loop.
  void Reserve(const FrameContext& ctx);

  // The whole ray tree of `tile` (inside the image): its primary rays in ctx.options.order, in
  // batches, each batch's tree finished (deepest pending generation first) before the next
  // batch is generated. Shadow rays are traced as soon as they are spawned; an unoccluded one
  // adds its weight to its pixel. Counters and stage times go to `stats`. The tile's pixels
  // must be this caller's for the frame (Framebuffer::SetPixelSums): no other thread renders
  // an overlapping tile or adds to them concurrently; fb may be kResolved.
  void RenderTile(const FrameContext& ctx, const Tile& tile, Framebuffer& fb, FrameStats& stats);

  // One generation of a backend that schedules the secondary rays itself (queue backends),
  // already split by class: `shadow` (shadow rays only; up to EngineShadowBatch rays, or a
  // batch rounded up to whole tasks, without growing the scratch) occluded and added to fb,
  // `rays` (no shadow rays; at most ctx.options.batch rays rounded up to whole tasks, for
  // bounded scratch) intersected and shaded. Their secondary rays are appended: shadow rays to
  // `shadow_out` grouped by light within each Shade sub-chunk (Shade writes each light's rays
  // to its own stream; interleaved, a 64-ray run would mix lights and miss the coherent
  // packets), the others to `bounce_out` in Shade's order. Both inputs padded with the lanes
  // after their size sealed (RayStream::FillPadding or SealTail); they must not alias the
  // outputs. The outputs may be one stream (each Shade sub-chunk's other rays, then its shadow
  // rays light by light).
  void TraceGeneration(const FrameContext& ctx, const RayStreamView& shadow,
                       const RayStreamView& rays, Framebuffer& fb, RayStream& shadow_out,
                       RayStream& bounce_out, FrameStats& stats);
  // The same for one generation of any kinds mixed (split by class here, one copy), its
  // secondary rays appended to `spawned` as above. `rays` must not alias `spawned`.
  void TraceGeneration(const FrameContext& ctx, const RayStreamView& rays, Framebuffer& fb,
                       RayStream& spawned, FrameStats& stats);

  // Rays the arenas can hold (for tests of the memory bound).
  size_t capacity_rays() const;

  // The cost-map predictor's record (cost_map.h): with a sink, the work of every trace call is
  // charged to the blocks of its rays' pixels, and each primary ray's hit distance (+inf: a
  // miss) is stored at its pixel in sink->pixel_depth (if not null). RenderTile charges each
  // call's TileWorkCost (its rays, cell steps and triangle tests) in equal shares to its rays:
  // its calls are the tile's own batches, the same rays together in every run. TraceGeneration
  // charges each ray TileWorkCost of one ray, plus one shading call if it hit: its caller
  // groups the rays (a queue backend: whatever a thread popped), and a coherent packet's cell
  // steps and triangle tests depend on which rays share it, so only per-ray counts give the
  // same record whichever thread traced what. The sink must be sized for ctx's image
  // (BlockWork::Resize) and is only added to (the caller clears it per frame); nullptr (the
  // default) records nothing. Costs one pass over each call's rays; the image and the
  // counters do not change.
  void SetBlockWork(BlockWork* sink) { block_work_ = sink; }

  // TraceGeneration's framebuffer adds: true (the default) atomic, as rays of one pixel may be
  // traced by several threads; false plain, while no other thread adds to the caller's pixels
  // (LOCAL: a tile's whole ray tree stays on the thread that took it; LOCK and LFREE until the
  // thread pushes or pops a task). May change between calls. The sums are the same either
  // way.
  void SetSharedPixels(bool shared) { shared_pixels_ = shared; }

  // Shared pixels, non-null `lock`: TraceGeneration sums its contributions per pixel in the
  // engine's PixelSumTable (framebuffer.h) and adds them to the framebuffer a table at a time
  // holding *lock, which every engine adding to the frame's framebuffer must share (instead of
  // an atomic add per contribution channel). The caller must call FlushContributions(fb) once
  // its thread is done with the frame (before the frame's image is read), and
  // DiscardContributions() before the next frame if a frame was abandoned. Off (nullptr) by
  // default; *lock must outlive the engine's frames.
  void SetCombinePixels(std::mutex* lock) {
    combine_lock_ = lock;
    if (lock != nullptr) combined_.Reserve();
  }
  void FlushContributions(Framebuffer& fb) {
    if (combine_lock_ != nullptr) combined_.Flush(fb, *combine_lock_);
  }
  void DiscardContributions() { combined_.Clear(); }
  // Contributions (not skipped) added through the PixelSumTable since the last reset.
  uint64_t table_adds() const { return table_adds_; }
  void ResetTableAdds() { table_adds_ = 0; }

 private:
  // Intersects rays (no shadow rays), shades them in sub-chunks; each sub-chunk's bounce rays
  // are appended to `bounce`, its shadow rays light by light and traced in one call (or, when
  // shadow_out is non-null, appended to it).
  void TraceAndShade(const FrameContext& ctx, const RayStreamView& rays, Framebuffer& fb,
                     RayStream& bounce, RayStream* shadow_out, FrameStats& stats);
  void Occlude(const FrameContext& ctx, const RayStreamView& rays, Framebuffer& fb,
               FrameStats& stats);
  void Drain(const FrameContext& ctx, size_t primaries, Framebuffer& fb, FrameStats& stats);
  // Contributions i < n (skip[i] != 0 skipped; skip may be null): RenderTile's batch sums
  // (local_), else combined_ (SetCombinePixels), else the framebuffer, atomic unless
  // SetSharedPixels(false).
  void AddContributions(Framebuffer& fb, const uint32_t* pixel, const float* r, const float* g,
                        const float* b, const int32_t* skip, size_t n);
  // Charges one trace call of `rays` to block_work_ (SetBlockWork): RenderTile its counter
  // deltas, TraceGeneration each ray its own count (prim: the hits, nullptr for shadow rays).
  void ChargeBlocks(const RayStreamView& rays, const int32_t* prim, uint64_t cell_steps,
                    uint64_t triangle_tests);
  uint32_t PixelOf(const RayStreamView& rays, size_t i) const {
    return local_ ? batch_pixels_[rays.pixel[i]] : rays.pixel[i];
  }

  BlockWork* block_work_ = nullptr;

  std::vector<RayStream> levels_;  // pending non-shadow rays by depth (0: primary)
  std::vector<RayStream> light_rays_;  // Shade's shadow rays of one sub-chunk, per light
  std::vector<RayStream*> light_to_;   // where Shade writes each light's shadow rays
  RayStream shadow_;               // shadow rays of one sub-chunk, or of a mixed generation
  RayStream bounce_;               // non-shadow rays of a mixed generation
  HitStream hits_;
  ContributionStream contributions_;
  AlignedArray<int32_t> occluded_;
  std::vector<uint32_t> light_of_;   // per spawned ray: its light (shadow rays only)
  std::vector<size_t> light_start_;  // per light: the next slot of its group
  // The arenas are sized for the largest batch, depth and light count and the smallest task
  // size seen so far.
  size_t batch_ = 0;
  int depth_ = -1;
  size_t lights_ = 0;
  int task_size_ = 1 << 30;
  // RenderTile: rays carry their primary's index in the batch, contributions are summed here.
  bool local_ = false;
  bool shared_pixels_ = true;  // TraceGeneration: atomic framebuffer adds
  std::mutex* combine_lock_ = nullptr;  // ... combined per pixel in combined_ first
  PixelSumTable combined_;
  uint64_t table_adds_ = 0;
  std::vector<int64_t> local_sums_;     // 3 per primary ray of the batch
  std::vector<uint32_t> batch_pixels_;  // the batch's pixels
  uint64_t local_nan_ = 0, local_clamped_ = 0;
};

// The serial reference backend: the image's tiles (tile_size x tile_size, row-major) one after
// the other on the calling thread, each tile's whole ray tree by the frame engine (RayEngine:
// batches of RenderOptions::batch rays, deepest generation first, bounded memory). Keeps its
// arenas between frames, so a walk-through allocates only in its first frame. Not thread-safe.
class SerialRenderer {
 public:
  // Renders one frame into fb (not cleared first) and returns its stats.
  FrameStats Render(const FrameContext& ctx, Framebuffer& fb);
  // The whole ray tree of `tiles` on this thread, tile by tile. Counters go to `stats`
  // (total_seconds untouched). This is also the unit of work of the tiles backend's threads
  // and of an MPI worker.
  void RenderTiles(const FrameContext& ctx, const Tile* tiles, size_t num_tiles, Framebuffer& fb,
                   FrameStats& stats);
  RayEngine& engine() { return engine_; }

 private:
  RayEngine engine_;
  std::vector<Tile> tiles_;
};

}  // namespace rs
