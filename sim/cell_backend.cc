// The Cell simulator (CellRenderer) behind the command's backend interface (sched/backend.h).
// Its frame report has the host statistics' form, in simulated time: the frame's seconds are the
// simulated frame time (the host's wall time is host_seconds), one "thread" per SPE (busy and
// idle), one tile record per tile (seconds = work = its SPE cycles / clock, the cost its PBT gets
// up to that constant; predicted likewise), the PBT's fields; then the simulator's own fields.
#include <fmt/core.h>

#include <memory>
#include <string>

#include "sched/backend.h"
#include "sim/cell_renderer.h"

namespace rs::sim {
namespace {

class CellBackend final : public Backend {
 public:
  explicit CellBackend(const BackendConfig& c)
      : config_(MakeConfig(c)), plan_(MakePlan(c)), renderer_(config_, plan_) {
    options_.kind = BackendKind::kTiles;  // the same tiling, run by SPEs
    options_.threads = config_.num_spes;
    options_.tile_width = config_.tile_width;
    options_.tile_height = config_.tile_height;
    options_.pbt_tiles_per_worker = config_.pbt_tiles_per_spe;
    options_.pbt_workers = plan_.pbt_workers;
    options_.assign = plan_.assign;
    options_.seed = plan_.seed;
    options_.pbt_cost = PbtCost::kWork;  // its simulated tile cycles
    options_.queue_stats = false;
  }

  std::string_view name() const override { return "cell"; }

  std::string Describe() const override {
    return fmt::format("cell, {} SPEs, {}", config_.num_spes,
                       config_.pbt_tiles_per_spe > 0
                           ? fmt::format("PBT k={} assign {}", config_.pbt_tiles_per_spe,
                                         PbtAssignName(plan_.assign))
                           : fmt::format("tiles {}x{}", config_.tile_width, config_.tile_height));
  }

  const BackendOptions& options() const override { return options_; }

  StatsFields StatsOptions() const override {
    return {{"spes", int64_t{config_.num_spes}}, {"config", DescribeConfig(config_)}};
  }

  Accel Build(const Scene& scene, const BuildOptions& build, int image_width,
              std::string* note) const override {
    return BuildCellAccel(scene, build, config_, image_width, note);
  }

  void BeginFrame(const FrameContext& ctx) override {
    const int w = ctx.options.width, h = ctx.options.height;
    if (!fb_ || fb_->width() != w || fb_->height() != h) fb_ = std::make_unique<Framebuffer>(w, h);
    fb_->Clear();
    last_ = renderer_.Render(ctx, *fb_);
    image_seconds_ += last_.image_seconds;
    image_bytes_ = last_.image_bytes;
    Report(last_);
    ++frames_;
  }

  const FrameReport& EndFrame() override { return report_; }
  const Framebuffer* image() const override { return fb_.get(); }

  std::string ProgressNote(const FrameReport&) const override {
    return fmt::format("(simulated; host {:.1f} ms)", 1e3 * last_.host_seconds);
  }

  // The last frame's cycle report (FormatCellReport) after the PPE's image layout.
  std::string Summary(std::span<const FrameReport> frames) const override {
    if (frames.empty()) return {};
    return fmt::format("cell image {:.1f} ms ({:.1f} MiB), the PPE's layout of the scene in main "
                       "memory\n",
                       1e3 * image_seconds_, double(image_bytes_) / 1048576.0) +
           FormatCellReport(last_, config_);
  }

 private:
  static SimConfig MakeConfig(const BackendConfig& c) {
    SimConfig config;
    config.num_spes = c.spes;
    config.tile_width = c.host.tile_width;
    config.tile_height = c.host.tile_height;
    config.pbt_tiles_per_spe = c.host.pbt_tiles_per_worker;
    ValidateConfig(config);
    return config;
  }
  static CellPlanOptions MakePlan(const BackendConfig& c) {
    CellPlanOptions plan;
    plan.assign = c.host.assign;
    plan.seed = c.host.seed;
    plan.pbt_workers = c.host.pbt_workers;
    plan.predict = c.host.pbt_predict;
    plan.cost_block = c.host.pbt_cost_block;
    return plan;
  }

  void Report(const CellFrameStats& s) {
    HostFrameStats& f = report_.stats;
    const double hz = s.clock_hz;
    f.frame = frames_;
    f.backend = BackendKind::kTiles;
    f.total = s.frame;
    f.total.total_seconds = s.seconds;
    f.render_seconds = s.seconds;
    f.threads.assign(s.spes.size(), ThreadStats{});
    report_.worker_extra.resize(s.spes.size());
    std::vector<double> busy;
    for (size_t i = 0; i < s.spes.size(); ++i) {
      const SpeReport& r = s.spes[i];
      ThreadStats& t = f.threads[i];
      t.idle_seconds = double(r.cycles[Cost::kIdle]) / hz;
      t.busy_seconds = double(r.cycles.Total() - r.cycles[Cost::kIdle]) / hz;
      t.tiles = r.counters.tiles;
      for (int k = 0; k < kNumRayKinds; ++k) t.work.rays[k] = r.counters.rays[k];
      t.work.trace.cell_steps = r.counters.cell_steps;
      t.work.trace.triangle_tests = r.counters.triangle_tests;
      busy.push_back(t.busy_seconds);
      StatsFields& e = report_.worker_extra[i];
      e.clear();
      e.push_back({"spe", int64_t{r.id}});
      e.push_back({"finish_cycle", r.finish});
      for (int c = 0; c < kNumCosts; ++c) {
        e.push_back({fmt::format("{}_cycles", CostName(Cost(c))), r.cycles.cycles[c]});
      }
      e.push_back({"visits", r.counters.visits});
      e.push_back({"micro_cache_hits", r.counters.micro_cache_hits});
      e.push_back({"dma_commands", r.mfc.commands});
      e.push_back({"dma_bytes", r.mfc.bytes});
      e.push_back({"atomic_loads", r.atomic.getllar});
      e.push_back({"ls_bytes", uint64_t{r.ls_used}});
    }
    f.imbalance = FrameImbalance(busy);
    f.tiles.resize(s.tiles.size());
    for (size_t i = 0; i < s.tiles.size(); ++i) {
      const CellTileRecord& t = s.tiles[i];
      TileRecord& r = f.tiles[i];
      r = TileRecord{};
      r.tile = t.tile;
      r.thread = t.spe;
      r.worker = t.worker >= 0 ? t.worker : t.spe;
      r.seconds = r.work = t.cycles / hz;
      r.predicted = t.predicted >= 0 ? t.predicted / hz : -1;
    }
    f.pbt = s.pbt;
    f.has_prediction = s.has_prediction;
    f.accuracy = s.accuracy;
    f.worker_imbalance = s.worker_imbalance;
    f.predicted_makespan = s.predicted_makespan / hz;
    f.update = s.update;
    report_.extra = {{"cycles", s.cycles},
                     {"simulated_seconds", s.seconds},
                     {"host_seconds", s.host_seconds},
                     {"mic_lines", s.mic_lines},
                     {"mic_queue_cycles", s.mic_queue_cycles}};
  }

  SimConfig config_;
  CellPlanOptions plan_;
  CellRenderer renderer_;
  BackendOptions options_;
  std::unique_ptr<Framebuffer> fb_;
  CellFrameStats last_;
  FrameReport report_;
  uint64_t frames_ = 0;
  double image_seconds_ = 0;
  size_t image_bytes_ = 0;
};

}  // namespace

void RegisterCellBackend(BackendRegistry& registry) {
  registry.Add("cell", "the Cell/B.E. simulator: SPEs with local stores and DMA",
               [](const BackendConfig& c) { return std::make_unique<CellBackend>(c); });
}

}  // namespace rs::sim
