#include "sched/backend.h"

#include <fmt/core.h>

#include "scenes/image_io.h"  // WriteFileAtomically

#include <thread>
#include <utility>

namespace rs {

Accel Backend::Build(const Scene& scene, const BuildOptions& build, int /*image_width*/,
                     std::string* note) const {
  if (note) note->clear();
  return Accel(scene.mesh(), build);
}

std::string Backend::Summary(std::span<const FrameReport>) const { return {}; }

std::string FrameReportsText(const std::string& path, const std::string& scene,
                             const Backend& backend, std::span<const FrameReport> frames) {
  std::vector<HostFrameStats> stats;
  StatsExtra extra;
  extra.backend = std::string(backend.name());
  extra.options = backend.StatsOptions();
  bool frame_fields = false, worker_fields = false;
  for (const FrameReport& f : frames) {
    stats.push_back(f.stats);
    extra.frames.push_back(f.extra);
    extra.threads.push_back(f.worker_extra);
    frame_fields = frame_fields || !f.extra.empty();
    worker_fields = worker_fields || !f.worker_extra.empty();
  }
  if (!frame_fields) extra.frames.clear();
  if (!worker_fields) extra.threads.clear();
  return HostStatsText(path, scene, backend.options(), stats, extra);
}

void WriteFrameReports(const std::string& path, const std::string& scene, const Backend& backend,
                       std::span<const FrameReport> frames) {
  WriteFileAtomically(path, FrameReportsText(path, scene, backend, frames), "statistics");
}

void BackendRegistry::Add(std::string name, std::string help, Factory make) {
  if (name.empty()) throw Error("backend registry: empty backend name");
  if (Find(name)) throw Error(fmt::format("backend registry: {} registered twice", name));
  entries_.push_back(Entry{std::move(name), std::move(help), std::move(make)});
}

const BackendRegistry::Entry* BackendRegistry::Find(std::string_view name) const {
  for (const Entry& e : entries_) {
    if (e.name == name) return &e;
  }
  return nullptr;
}

std::vector<std::string> BackendRegistry::Names() const {
  std::vector<std::string> names;
  for (const Entry& e : entries_) names.push_back(e.name);
  return names;
}

std::unique_ptr<Backend> BackendRegistry::Make(std::string_view name,
                                               const BackendConfig& config) const {
  const Entry* e = Find(name);
  if (!e) {
    std::string names;
    for (const Entry& entry : entries_) names += (names.empty() ? "" : ", ") + entry.name;
    throw Error(fmt::format("--backend {}: unknown backend (available: {})", name, names));
  }
  return e->make(config);
}

namespace {

// HostRenderer behind the interface, with the framebuffer its kind needs: serial and tiles set
// each pixel once per frame, so they keep the float image only (kResolved, 12 bytes per pixel)
// unless the caller reads the fixed-point sums; the queue backends add in fixed point.
class HostBackend final : public Backend {
 public:
  explicit HostBackend(const BackendConfig& config)
      : renderer_(config.host),
        storage_((config.host.kind == BackendKind::kSerial ||
                  config.host.kind == BackendKind::kTiles) &&
                         !config.fixed_sums
                     ? Framebuffer::Storage::kResolved
                     : Framebuffer::Storage::kFixed) {}

  std::string_view name() const override { return BackendName(renderer_.options().kind); }

  std::string Describe() const override {
    const BackendOptions& o = renderer_.options();
    std::string how = BackendName(o.kind);
    if (o.kind != BackendKind::kSerial) how += fmt::format(", {} thread(s)", o.threads);
    if (o.pbt_tiles_per_worker > 0) {
      how += fmt::format(", PBT k={} assign {} cost {}{}", o.pbt_tiles_per_worker,
                         PbtAssignName(o.assign), PbtCostName(o.pbt_cost),
                         o.pbt_steal ? " + steal" : o.pbt_demand ? " + demand" : "");
      if (o.kind != BackendKind::kTiles) how += " (tiles feed the queues)";
    } else if (o.kind == BackendKind::kTiles) {
      how += fmt::format(", tiles {}x{}", o.tile_width, o.tile_height);
    }
    return how;
  }

  const BackendOptions& options() const override { return renderer_.options(); }

  void BeginFrame(const FrameContext& ctx) override {
    const int w = ctx.options.width, h = ctx.options.height;
    if (!fb_ || fb_->width() != w || fb_->height() != h) {
      fb_ = std::make_unique<Framebuffer>(w, h, storage_);
    }
    fb_->Clear();
    renderer_.BeginFrame(ctx, *fb_);
  }

  // Copy-assigned into the report, whose vectors keep their capacity across frames.
  const FrameReport& EndFrame() override {
    report_.stats = renderer_.EndFrame();
    return report_;
  }

  const Framebuffer* image() const override { return fb_.get(); }

  std::string Summary(std::span<const FrameReport> frames) const override {
    const BackendOptions& o = renderer_.options();
    if (o.kind == BackendKind::kSerial || frames.empty()) return {};
    double idle = 0, queue = 0, imbalance = 0, seconds = 0;
    for (const FrameReport& f : frames) {
      idle += f.stats.IdleSeconds();
      queue += f.stats.QueueSeconds();
      imbalance += f.stats.imbalance;
      seconds += f.stats.total.total_seconds;
    }
    const double n = static_cast<double>(frames.size());
    std::string out = fmt::format(
        "threads    {:.2f} fps, per frame: {:.2f} ms idle at the barrier (all threads), {:.2f} ms "
        "in queue operations, imbalance {:.3f}\n",
        seconds > 0 ? n / seconds : 0.0, 1e3 * idle / n, 1e3 * queue / n, imbalance / n);
    const unsigned hw = std::thread::hardware_concurrency();
    if (hw > 0 && o.threads > static_cast<int>(hw)) {
      out += fmt::format("note       {} threads oversubscribe the {} hardware threads of this "
                         "machine\n",
                         o.threads, hw);
    }
    return out;
  }

 private:
  HostRenderer renderer_;
  Framebuffer::Storage storage_;
  std::unique_ptr<Framebuffer> fb_;
  FrameReport report_;
};

}  // namespace

std::unique_ptr<Backend> MakeHostBackend(const BackendConfig& config) {
  return std::make_unique<HostBackend>(config);
}

void RegisterHostBackends(BackendRegistry& registry) {
  const struct {
    BackendKind kind;
    const char* help;
  } kinds[] = {
      {BackendKind::kSerial, "the reference, one thread"},
      {BackendKind::kLock, "threads sharing a two-lock queue of tasks"},
      {BackendKind::kLockFree, "threads sharing a lock-free queue of tasks"},
      {BackendKind::kLocal, "a private task queue per thread"},
      {BackendKind::kTiles, "image tiles from a counter or a PBT (the default)"},
  };
  for (const auto& k : kinds) {
    const BackendKind kind = k.kind;
    registry.Add(BackendName(kind), k.help, [kind](const BackendConfig& config) {
      BackendConfig c = config;
      c.host.kind = kind;
      return MakeHostBackend(c);
    });
  }
}

}  // namespace rs
