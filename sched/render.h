// What every backend's frame is made of: render options, the per-frame context workers read,
// frame statistics, image tiling, and the serial reference renderer's entry points (the frame
// engine itself is sched/engine.h). Each ray carries its pixel and weight (Santos et al.,
// iterative ray tree), so any worker can finish any ray and the image never depends on order.
#pragma once

#include <cstddef>
#include <cstdint>
#include <deque>
#include <span>
#include <vector>

#include "include/raystream/raystream.h"
#include "kernels/shade.h"
#include "scenes/scene.h"
#include "sched/framebuffer.h"
#include "sched/tracer.h"
#include "streams/ray_stream.h"
#include "streams/raygen.h"

namespace rs {

struct RenderOptions {
  int width = 300;
  int height = 300;
  int max_depth = 4;            // bounces; 0 = primary rays only (ray casting + shadows)
  int task_size = 20;           // rays per task (the paper's 20): the unit of queues and stats
  // Rays per kernel call: a worker traces up to `batch` rays of one generation as one stream
  // (primary rays of a tile, or bounce rays of one depth), so coherent rays reach the 64-ray
  // packets. Queue backends pop ceil(batch / task_size) tasks at once. `--task-size 20 --batch
  // 20` is the iRT paper's configuration. Any value gives the same image.
  int batch = 1024;
  static constexpr int kMaxBatch = 65536;
  // Rays traced per primary ray of a batch (all kinds, its whole ray tree) before its bounce
  // rays stop being traced: the guard against exponential ray trees (reflectivity and
  // transmission 1 at depth 64 with no cutoff). FrameStats::budget_dropped counts the bounce
  // rays dropped; the image is then incomplete (and may depend on how rays were batched).
  int ray_budget = 1024;
  float weight_cutoff = 1e-3f;  // bounce rays with max weight channel below this are dropped
  // Ray order inside a primary tile: 8x8 blocks make every 64-ray packet a square of pixels
  // (callgrind, render_bench 512x512: 6-8 % fewer instructions per frame than scanline on bunny
  // and conference, whose 64 rays were two rows of a 32-pixel tile). The image does not depend
  // on it.
  RayOrder order = RayOrder::kBlock8x8;
  int tile_size = 32;  // primary generation tiles: tile_size x tile_size, row-major
};

// Throws rs::Error naming the option if width/height < 1 (or >= 2^32 pixels), max_depth < 0
// or > 64, task_size < 1, batch < 1 or > 65536, ray_budget < 1, weight_cutoff not finite or
// < 0, tile_size < 1, or order unknown.
void ValidateRenderOptions(const RenderOptions& options);

// Per-frame (or per-thread, merged) figures.
struct FrameStats {
  uint64_t rays[kNumRayKinds] = {};  // rays traced, by RayKind
  uint64_t tasks = 0;                // tasks processed (task_size rays, or fewer at the end)
  // Kernel calls (Tracer::Intersect / Occluded) that traced rays of kind k: rays[k] /
  // trace_calls[k] is the mean stream length a kind reached (bounce calls may mix kinds).
  uint64_t trace_calls[kNumRayKinds] = {};
  uint64_t budget_dropped = 0;       // bounce rays not traced: RenderOptions::ray_budget reached
  uint64_t hits = 0;                 // Intersect results with a hit
  uint64_t occluded = 0;             // shadow rays found blocked
  ShadeStats shade;                  // shading calls, spawned rays per kind, texture fetches
  TraceStats trace;                  // cell steps, triangle tests (accumulated by Accel)
  double generate_seconds = 0;       // primary rays (queue backends: and cutting them into tasks)
  double trace_seconds = 0;          // Accel::Intersect + Accel::Occluded
  // trace_seconds by the kind of the rays traced: a call's time shared by its rays' kinds in
  // proportion to their counts (a bounce call may mix reflection and refraction rays). Kept by
  // the host frame engine (RayEngine); the MPI backend does not carry it between ranks.
  double trace_kind_seconds[kNumRayKinds] = {};
  double shade_seconds = 0;          // the Shade kernel (shadow-ray adds and partitions: neither)
  // Queue backends: a batch's tasks gathered into streams, its secondary rays cut into tasks,
  // pushed (their queue operations also in ThreadStats::queue_seconds) and the tasks returned
  // (0 for serial and tiles, which have no tasks to move).
  double schedule_seconds = 0;
  double total_seconds = 0;          // frame wall time (set by the backend)

  uint64_t TotalRays() const;
  // TotalRays / total_seconds / 1e6 (0 if no time was measured).
  double MraysPerSecond() const;
  // Sums counters and the stage seconds (thread-seconds); total_seconds becomes the max.
  void Merge(const FrameStats& other);
};

// Everything a worker needs to process tasks of one frame; read-only while the frame runs.
struct FrameContext {
  const Scene* scene = nullptr;
  const Accel* accel = nullptr;
  // What the host engine traces with; nullptr: accel (through AccelTracer). Same image for
  // any Tracer that returns the same hits.
  const Tracer* tracer = nullptr;
  // One rs::LightBuffer per scene light (light_buffers[l] for scene->lights[l], over accel),
  // or none: the host engine then traces shadow rays through the LightBuffers (same image, only
  // faster; BuildLightBuffers). Ignored when `tracer` is set.
  std::span<const LightBuffer> light_buffers;
  CameraBasis camera;
  // The next frame's camera, when the frame loop knows it (a camera path): PBT's cost-map
  // predictor moves this frame's costs to where their content lands in the next frame. Only
  // the tiling of the next frame depends on it, never this frame's image.
  bool has_next_camera = false;
  CameraBasis next_camera;
  RenderOptions options;
  ShadeOptions shade;
};

// Validates the options and precomputes the camera basis. Throws rs::Error (options, camera).
// The scene must have its features computed (ComputeFeatures) and outlive the context.
FrameContext MakeFrameContext(const Scene& scene, const Accel& accel, const Camera& camera,
                              const RenderOptions& options);

// One rs::LightBuffer per light of `scene` over `accel` (built from scene.mesh()), for
// FrameContext::light_buffers; none for a scene without lights. threads > 1: up to that many
// lights are built at once, on the calling thread and the build threads (RunParts,
// kernels/build_threads.h). Throws rs::Error if memory runs out.
std::vector<LightBuffer> BuildLightBuffers(const Scene& scene, const Accel& accel,
                                           int threads = 1);
// The same into *buffers, rebuilding the ones it holds in place (LightBuffer::Rebuild: no fresh
// memory for a rebuild of the same size on the same threads), for a scene whose Accel is
// rebuilt every frame.
void RebuildLightBuffers(const Scene& scene, const Accel& accel, std::vector<LightBuffer>* buffers,
                         int threads = 1);

// Sets ctx.next_camera (and has_next_camera) to `next` for ctx's image. Throws as
// MakeCameraBasis.
void SetNextCamera(FrameContext& ctx, const Camera& next);

// The image split into tile_size x tile_size tiles (partial at the right and bottom), in
// row-major order.
std::vector<Tile> ImageTiles(int width, int height, int tile_size);
// The same for tile_width x tile_height tiles, into `out` (cleared; its capacity is reused, so a
// frame loop that keeps `out` allocates only when the tile count grows).
void ImageTiles(int width, int height, int tile_width, int tile_height, std::vector<Tile>& out);

// One frame with a fresh SerialRenderer.
FrameStats RenderSerial(const FrameContext& ctx, Framebuffer& fb);

struct RenderResult {
  std::vector<float> rgb;  // width * height * 3 linear floats, row 0 at the top
  FrameStats stats;
};

// Convenience: context, framebuffer, serial render, conversion to floats. Throws rs::Error on
// bad options or camera.
RenderResult RenderImage(const Scene& scene, const Accel& accel, const Camera& camera,
                         const RenderOptions& options);

}  // namespace rs
