// One interface for every backend the command runs (the host schedulers, the Cell simulator, the
// MPI cluster), registered by name. The command's one frame loop (tools/raystream.cc) drives it:
//   registry.Make(name, config) -> Setup(load the scene, Build the structure) ->
//   per frame: BeginFrame(ctx), EndFrame() -> FrameReport, image() -> Finish() -> statistics.
// A backend owns its framebuffer (the storage it needs); a FrameReport has the host statistics'
// form (sched/backends.h HostFrameStats: counters, one entry per worker, one record per tile, the
// PBT's fields), so one writer (WriteHostStats) serves every backend, plus the backend's own
// fields after them.
#pragma once

#include <functional>
#include <memory>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "include/raystream/raystream.h"
#include "scenes/scene.h"
#include "sched/backends.h"
#include "sched/framebuffer.h"
#include "sched/render.h"

namespace rs {

// One frame of any backend.
struct FrameReport {
  // Host form. Workers are render threads (host), SPEs (cell) or worker ranks (mpi).
  HostFrameStats stats;
  StatsFields extra;                      // the backend's own per-frame fields
  std::vector<StatsFields> worker_extra;  // empty, or one per stats.threads entry
};

// Everything the command hands a backend's factory. Each backend reads what applies to it (the
// command rejects an option a backend cannot honour before it makes one).
struct BackendConfig {
  BackendOptions host;  // threads, tiles, PBT; `kind` is set by the host backends' factories
  RenderOptions render;  // the frames' options, for checks at Setup (mpi: PBT tiles vs pixels)
  std::string scene;     // the scene's name or file, for messages
  int spes = 6;                      // cell: simulated SPEs
  double mpi_timeout_seconds = 120;  // mpi: bound on every wait of the master for a worker
  int mpi_prefetch = 2;              // mpi: tiles in flight per worker
  bool fixed_sums = false;  // the caller reads the fixed-point sums (Framebuffer::kFixed)
};

class Backend {
 public:
  virtual ~Backend() = default;

  // "serial", "tiles", "cell", ...: the registry's name and the statistics' "backend".
  virtual std::string_view name() const = 0;
  // For the command's `image` line: "tiles, 2 thread(s), tiles 32x32".
  virtual std::string Describe() const = 0;
  // The options in the host statistics' form (for cell and mpi: the tiles backend's equivalent,
  // threads = its workers) and the backend's own options after them.
  virtual const BackendOptions& options() const = 0;
  virtual StatsFields StatsOptions() const { return {}; }

  // Runs `setup` (load the scene, call Build) on this process and returns true to go on. The
  // mpi backend runs it on every rank and agrees on the outcome: the lowest failing rank
  // rethrows its error, every other rank returns false (leave with status 1, print nothing).
  virtual bool Setup(const std::function<void()>& setup) {
    setup();
    return true;
  }
  // The structure this backend traces the scene with. *note: a sentence saying what was changed
  // from `build` (cell: a lower lambda so that the occupancy bits fit the local store), or empty.
  virtual Accel Build(const Scene& scene, const BuildOptions& build, int image_width,
                      std::string* note) const;

  // One frame of ctx's whole image into the backend's framebuffer (cleared first). ctx's scene
  // and accel must outlive EndFrame. Host threads render between BeginFrame and EndFrame; the
  // cell and mpi backends render inside BeginFrame.
  virtual void BeginFrame(const FrameContext& ctx) = 0;
  // The frame's report, valid until the next BeginFrame.
  virtual const FrameReport& EndFrame() = 0;
  // The last frame's image; nullptr on a process that renders without owning the image (an mpi
  // worker rank: it writes no image and no statistics).
  virtual const Framebuffer* image() const = 0;
  // False on a process that renders without owning the image (an mpi worker rank): it writes
  // no image and no statistics, and image() stays nullptr.
  virtual bool owns_image() const { return true; }
  // After the last frame, before its image and the statistics are written (mpi: every worker
  // stopped and has said goodbye). Frames written before it are complete.
  virtual void Finish() {}

  // A short note for the per-frame progress line ("0.42 ms simulated"), or empty.
  virtual std::string ProgressNote(const FrameReport&) const { return {}; }
  // Lines the command prints after its summary (each ends in '\n'), or empty.
  virtual std::string Summary(std::span<const FrameReport> frames) const;
};

// The statistics of a run (the frames `backend` reported, in order) in one format for every
// backend: WriteHostStats with the backend's name, its host-form options and its own fields.
// JSON if path ends in ".json", CSV if ".csv". Throws rs::Error as WriteHostStats does.
void WriteFrameReports(const std::string& path, const std::string& scene, const Backend& backend,
                       std::span<const FrameReport> frames);
// The same file's text (HostStatsText), for staging.
std::string FrameReportsText(const std::string& path, const std::string& scene,
                             const Backend& backend, std::span<const FrameReport> frames);

// The backends by name. The command registers what it links (RegisterHostBackends,
// sim::RegisterCellBackend, RegisterMpiBackend); tests may register their own.
class BackendRegistry {
 public:
  using Factory = std::function<std::unique_ptr<Backend>(const BackendConfig&)>;
  struct Entry {
    std::string name;
    std::string help;  // one phrase for --help
    Factory make;
  };

  // Throws rs::Error if the name is empty or already registered.
  void Add(std::string name, std::string help, Factory make);
  const Entry* Find(std::string_view name) const;  // nullptr if unknown
  std::vector<std::string> Names() const;          // in registration order
  // Throws rs::Error naming the backend and the registered names if unknown, or whatever the
  // factory throws (invalid options).
  std::unique_ptr<Backend> Make(std::string_view name, const BackendConfig& config) const;

 private:
  std::vector<Entry> entries_;
};

// serial, lock, lfree, local, tiles: HostRenderer (sched/backends.h) behind the interface.
void RegisterHostBackends(BackendRegistry& registry);
// The host backend of `config.host.kind` (validated: ValidateBackendOptions).
std::unique_ptr<Backend> MakeHostBackend(const BackendConfig& config);

}  // namespace rs
