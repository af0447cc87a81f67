// The per-task work every backend runs (ProcessTask) and the serial reference renderer: primary
// rays cut into tasks of task_size rays, a FIFO of tasks, breadth-first secondary rays (Santos
// et al., iterative ray tree: each ray carries its pixel and weight, so any worker can finish it).
#pragma once

#include <cstddef>
#include <cstdint>
#include <deque>
#include <vector>

#include "include/raystream/raystream.h"
#include "kernels/shade.h"
#include "scenes/scene.h"
#include "sched/framebuffer.h"
#include "streams/ray_stream.h"
#include "streams/raygen.h"

namespace rs {

struct RenderOptions {
  int width = 300;
  int height = 300;
  int max_depth = 4;            // bounces; 0 = primary rays only (ray casting + shadows)
  int task_size = 20;           // rays per task (the paper's 20)
  float weight_cutoff = 1e-3f;  // bounce rays with max weight channel below this are dropped
  RayOrder order = RayOrder::kScanline;  // ray order inside a primary tile
  int tile_size = 32;  // primary generation tiles: tile_size x tile_size, row-major
};

// Throws rs::Error naming the option if width/height < 1 (or >= 2^32 pixels), max_depth < 0
// or > 64, task_size < 1, weight_cutoff not finite or < 0, tile_size < 1, or order unknown.
void ValidateRenderOptions(const RenderOptions& options);

// Per-frame (or per-thread, merged) figures.
struct FrameStats {
  uint64_t rays[kNumRayKinds] = {};  // rays traced, by RayKind
  uint64_t tasks = 0;                // tasks processed
  uint64_t hits = 0;                 // Intersect results with a hit
  uint64_t occluded = 0;             // shadow rays found blocked
  ShadeStats shade;                  // shading calls, spawned rays per kind, texture fetches
  TraceStats trace;                  // cell steps, triangle tests (accumulated by Accel)
  double generate_seconds = 0;       // primary rays + cutting them into tasks
  double trace_seconds = 0;          // Accel::Intersect + Accel::Occluded
  double shade_seconds = 0;          // Shade + shadow-ray adds + cutting secondaries into tasks
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
  CameraBasis camera;
  RenderOptions options;
  ShadeOptions shade;
};

// Validates the options and precomputes the camera basis. Throws rs::Error (options, camera).
// The scene must have its features computed (ComputeFeatures) and outlive the context.
FrameContext MakeFrameContext(const Scene& scene, const Accel& accel, const Camera& camera,
                              const RenderOptions& options);

// Where ProcessTask and GeneratePrimaryTasks put new tasks. A task is a RayStream of 1 to
// task_size rays with its padding filled (RayStream::FillPadding), of one kind class: only
// shadow rays, or only non-shadow rays (ProcessTask also accepts mixed tasks).
class TaskSink {
 public:
  virtual ~TaskSink() = default;
  // An empty stream to fill: backends may hand out recycled streams to avoid allocation.
  virtual RayStream NewTask() { return RayStream(); }
  // Takes ownership of a filled task.
  virtual void Push(RayStream&& task) = 0;
};

// A free list of task streams for a single-threaded owner (serial backend, per-thread queues).
class TaskPool {
 public:
  RayStream Get();
  void Put(RayStream&& task);
  size_t size() const { return free_.size(); }

 private:
  std::vector<RayStream> free_;
};

// Per-worker scratch buffers, reused across tasks so ProcessTask allocates only while they grow.
struct TaskScratch {
  HitStream hits;
  AlignedArray<int32_t> occluded;
  RayStream spawned;  // secondary rays of the current task, before cutting
  // Shade's contributions for the current task, added to fb right after the call.
  ContributionStream contributions;
  RayStream shadow;   // partitions of a mixed task
  RayStream trace;
  RayStream open_shadow;  // tasks being filled by CutIntoTasks
  RayStream open_bounce;
};

// The unit of work of every backend. For the rays of `task` (padding filled):
//   shadow rays -> Accel::Occluded; an unoccluded ray adds its weight to its pixel;
//   other rays  -> Accel::Intersect, then Shade (contributions into fb);
// the secondary rays spawned are cut into tasks of options.task_size rays (shadow and
// non-shadow rays in separate tasks) and pushed to `out`. Counters and stage times are
// accumulated into `stats`. Thread-safe as long as each thread has its own scratch and stats
// (fb takes concurrent adds). A ray's contributions depend on that ray only, so any backend
// that processes the same rays produces the same image bit for bit.
void ProcessTask(const FrameContext& ctx, const RayStreamView& task, Framebuffer& fb, TaskSink& out,
                 TaskScratch& scratch, FrameStats& stats);

// Cuts rays[0, size) into tasks of at most task_size rays (shadow and non-shadow rays kept
// apart, order preserved within each class) and pushes them to `out`. The open tasks live in
// scratch.open_shadow / open_bounce and are always flushed before returning.
void CutIntoTasks(const RayStreamView& rays, size_t task_size, TaskSink& out, TaskScratch& scratch);

// The image split into tile_size x tile_size tiles (partial at the right and bottom), in
// row-major order.
std::vector<Tile> ImageTiles(int width, int height, int tile_size);

// Generates the primary rays of `tile` in ctx.options.order directly into tasks of task_size
// rays (a task never spans two tiles) and pushes them to `out`. Adds the time to
// stats.generate_seconds.
void GeneratePrimaryTasks(const FrameContext& ctx, const Tile& tile, TaskSink& out,
                          FrameStats& stats);

// The serial reference backend: all primary tasks (tiles in row-major order) into a FIFO
// (std::deque), then pop-process until empty. Keeps its task pool and scratch buffers between
// frames, so a walk-through allocates only in its first frame. Not thread-safe.
class SerialRenderer final : public TaskSink {
 public:
  // Renders one frame into fb (not cleared first) and returns its stats.
  FrameStats Render(const FrameContext& ctx, Framebuffer& fb);
  // The whole ray tree of `tiles` on this thread: their primary tasks in order, then the FIFO
  // until empty. Counters go to `stats` (total_seconds untouched). This is also the unit of
  // work of the tiles backend's threads and of an MPI worker.
  void RenderTiles(const FrameContext& ctx, const Tile* tiles, size_t num_tiles, Framebuffer& fb,
                   FrameStats& stats);

  RayStream NewTask() override { return pool_.Get(); }
  void Push(RayStream&& task) override { fifo_.push_back(std::move(task)); }

 private:
  std::deque<RayStream> fifo_;
  TaskPool pool_;
  TaskScratch scratch_;
};

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
