// Discrete-event loop over the simulated SPEs, frame setup in main memory, statistics and PBT
// re-tiling (see cell_renderer.h).
#include "sim/cell_renderer.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <limits>
#include <numeric>

namespace rs::sim {
namespace {

using Clock = std::chrono::steady_clock;

double Seconds(Clock::time_point a, Clock::time_point b) {
  return std::chrono::duration<double>(b - a).count();
}

// Framebuffer keeps its drop and clamp counters private; Add counts a contribution with a NaN
// channel as dropped and one with a negative channel as clamped, and adds nothing to the sums in
// either case.
void AddCounters(Framebuffer& fb, uint64_t dropped_nan, uint64_t clamped) {
  const float nan = std::numeric_limits<float>::quiet_NaN();
  for (uint64_t i = 0; i < dropped_nan; ++i) fb.Add(0, nan, 0.0f, 0.0f);
  for (uint64_t i = 0; i < clamped; ++i) fb.Add(0, -1.0f, 0.0f, 0.0f);
}

}  // namespace

double CellFrameStats::SimulatedMraysPerSecond() const {
  return seconds > 0 ? double(totals.TotalRays()) / seconds * 1e-6 : 0.0;
}

CellRenderer::CellRenderer(const SimConfig& config, const CellPlanOptions& plan)
    : config_(config), plan_options_(plan) {
  ValidateConfig(config_);
  const int assign = static_cast<int>(plan.assign);
  if (assign < 0 || assign > static_cast<int>(PbtAssign::kLpt)) {
    throw Error("cell backend: unknown PBT assignment " + std::to_string(assign));
  }
  if (plan.pbt_workers < 0 || plan.pbt_workers > 65536) {
    throw Error("cell backend: pbt workers " + std::to_string(plan.pbt_workers) +
                " must be in [0, 65536]");
  }
}
CellRenderer::~CellRenderer() = default;

CellFrameStats CellRenderer::Render(const FrameContext& ctx, Framebuffer& fb) {
  const int w = ctx.options.width, h = ctx.options.height;
  measure_ = TilePlanMeasure{};
  if (config_.pbt_tiles_per_spe == 0) {
    // Regular tiles: the SPEs compute a tile's rectangle from its counter value.
    return RenderTiles(ctx, fb, GridTiles(w, h, config_.tile_width, config_.tile_height), false);
  }
  if (!plan_ || plan_->width() != w || plan_->height() != h) {
    TilePlanOptions p;
    p.pbt_tiles_per_worker = config_.pbt_tiles_per_spe;
    p.workers = plan_options_.pbt_workers > 0 ? plan_options_.pbt_workers : config_.num_spes;
    p.assign = plan_options_.assign;
    p.seed = plan_options_.seed;
    p.predict = plan_options_.predict;
    p.cost_block = plan_options_.cost_block;
    p.cost = PbtCost::kWork;  // the simulated tile cycles: deterministic
    plan_.reset();
    plan_ = std::make_unique<TilePlan>(w, h, p);
  }
  const TilePlanFrame& frame = plan_->Begin();
  BlockWork* record = nullptr;
  if (plan_->uses_cost_map()) {
    const int block = plan_->options().cost_block;
    if (!block_work_.Matches(w, h, block)) {
      block_work_.Resize(w, h, block);
    } else {
      block_work_.Clear();
    }
    // NaN (unknown) where no primary ray reports: the plan's tiles cover every pixel.
    pixel_depth_.assign(size_t(w) * size_t(h), std::numeric_limits<float>::quiet_NaN());
    block_work_.pixel_depth = pixel_depth_.data();
    record = &block_work_;
  }
  std::vector<std::vector<int32_t>> queues;
  if (frame.assignment.tiles.empty()) {
    queues.push_back(frame.order);  // one counter, costliest predicted first
  } else {
    queues.resize(size_t(config_.num_spes));
    const auto& lists = frame.assignment.tiles;
    for (size_t v = 0; v < lists.size(); ++v) {
      auto& q = queues[v % queues.size()];
      q.insert(q.end(), lists[v].begin(), lists[v].end());
    }
  }
  CellFrameStats stats;
  try {
    stats = RenderTiles(ctx, fb, frame.tiles, true, queues, record);
  } catch (...) {
    plan_->Cancel();
    throw;
  }
  std::vector<double> cycles(stats.tiles.size());
  std::vector<int32_t> ran_by(stats.tiles.size());
  for (size_t i = 0; i < stats.tiles.size(); ++i) {
    CellTileRecord& t = stats.tiles[i];
    t.predicted = frame.predicted[i];
    t.worker = frame.owner.empty() ? -1 : frame.owner[i];
    cycles[i] = t.cycles;
    ran_by[i] = t.spe;
  }
  // Counter: the SPEs are the workers only when there are as many (else a model of n).
  if (plan_->options().workers != config_.num_spes) ran_by.clear();
  if (record != nullptr) {
    measure_.blocks = record;
    measure_.pixel_depth = pixel_depth_;
    measure_.camera = &ctx.camera;
    measure_.next_camera = ctx.has_next_camera ? &ctx.next_camera : nullptr;
  }
  const TilePlanReport report = plan_->End(cycles, ran_by, measure_);
  stats.pbt = true;
  stats.has_prediction = report.has_prediction;
  stats.accuracy = report.accuracy;
  stats.worker_imbalance = report.worker_imbalance;
  stats.predicted_makespan = report.predicted_makespan;
  stats.update = report.update;
  return stats;
}

CellFrameStats CellRenderer::Render(const FrameContext& ctx, Framebuffer& fb,
                                    std::span<const Tile> tiles) {
  measure_ = TilePlanMeasure{};
  return RenderTiles(ctx, fb, tiles, true);
}

CellFrameStats CellRenderer::RenderTiles(const FrameContext& ctx, Framebuffer& fb,
                                         std::span<const Tile> tiles, bool explicit_tiles,
                                         const std::vector<std::vector<int32_t>>& queues_in,
                                         BlockWork* block_work) {
  const int width = ctx.options.width, height = ctx.options.height;
  if (fb.width() != width || fb.height() != height) {
    throw Error("cell backend: framebuffer is " + std::to_string(fb.width()) + "x" +
                std::to_string(fb.height()) + " but the frame is " + std::to_string(width) + "x" +
                std::to_string(height));
  }
  // The SPEs put whole pixel buffers into the pixel image, so a pixel must belong to one tile.
  uint64_t covered = 0;
  std::vector<uint32_t> owner;  // explicit lists: 1 + the tile holding each pixel, 0 for none
  if (explicit_tiles) owner.assign(size_t(width) * size_t(height), 0);
  for (size_t i = 0; i < tiles.size(); ++i) {
    const Tile& t = tiles[i];
    if (t.x0 < 0 || t.y0 < 0 || t.x1 > width || t.y1 > height) {
      throw Error("cell backend: tile " + std::to_string(i) + " lies outside the image");
    }
    if (t.x1 <= t.x0 || t.y1 <= t.y0) continue;
    covered += uint64_t(t.NumPixels());
    if (!explicit_tiles) continue;
    for (int y = t.y0; y < t.y1; ++y) {
      for (int x = t.x0; x < t.x1; ++x) {
        uint32_t& o = owner[size_t(y) * size_t(width) + size_t(x)];
        if (o != 0) {
          throw Error("cell backend: tiles " + std::to_string(o - 1) + " and " + std::to_string(i) +
                      " overlap at pixel (" + std::to_string(x) + ", " + std::to_string(y) +
                      "); the SPEs write whole tiles back by DMA");
        }
        o = static_cast<uint32_t>(i + 1);
      }
    }
  }
  CellFrameStats stats;
  // The PPE's layout of the scene for the SPEs: once per (scene, accel).
  if (!image_ || &image_->scene() != ctx.scene || &image_->accel() != ctx.accel) {
    image_.reset();
    image_ = std::make_unique<CellImage>(*ctx.scene, *ctx.accel);
    stats.image_seconds = image_->build_seconds();
  }
  stats.image_bytes = image_->Bytes();
  const auto t0 = Clock::now();

  // The tile counters: one queue that every SPE takes from, or one per SPE (PBT lists).
  std::vector<std::vector<int32_t>> queues = queues_in;
  if (queues.empty()) {
    queues.emplace_back(tiles.size());
    std::iota(queues[0].begin(), queues[0].end(), int32_t{0});
  }
  const size_t nq = queues.size();
  if (nq != 1 && nq != size_t(config_.num_spes)) {
    throw Error("cell backend: " + std::to_string(nq) + " tile queues for " +
                std::to_string(config_.num_spes) + " SPEs");
  }

  // Main memory of the frame: the scene image at its planned EAs, then the frame's buffers (per
  // queue: its frame constants, tile list and counter line; with one queue the layout is the
  // one-counter program's).
  Machine machine(config_);
  image_->Register(machine.memory);
  std::vector<AlignedBuffer> constants;
  std::vector<Ea> constants_ea;
  constants.reserve(nq);
  for (size_t q = 0; q < nq; ++q) {
    constants.emplace_back(sizeof(FrameConstants));
    constants_ea.push_back(
        machine.memory.Register(constants[q].data(), constants[q].size(), "frame constants"));
  }
  FrameConstants fc{};
  image_->FillConstants(&fc);
  fc.camera = ctx.camera;
  fc.shade = ctx.shade;
  fc.image_width = width;
  fc.image_height = height;
  if (explicit_tiles) {
    fc.explicit_tiles = 1;
    fc.tile_width = fc.tile_height = fc.tiles_x = 1;
  } else {
    fc.explicit_tiles = 0;
    fc.tile_width = std::min(config_.tile_width, width);
    fc.tile_height = std::min(config_.tile_height, height);
    fc.tiles_x = (width + fc.tile_width - 1) / fc.tile_width;
  }
  std::vector<AlignedBuffer> tile_buffers, counters;
  std::vector<Ea> tiles_ea, counter_ea;
  tile_buffers.reserve(nq);
  counters.reserve(nq);
  for (size_t q = 0; q < nq; ++q) {
    const std::vector<int32_t>& queue = queues[q];
    tile_buffers.emplace_back(std::max<size_t>(queue.size(), 1) * sizeof(Tile));
    Tile* list = tile_buffers[q].As<Tile>();
    for (size_t p = 0; p < queue.size(); ++p) list[p] = tiles[size_t(queue[p])];
    tiles_ea.push_back(
        machine.memory.Register(tile_buffers[q].data(), tile_buffers[q].size(), "tile list"));
    counters.emplace_back(128);
    counter_ea.push_back(
        machine.memory.Register(counters[q].data(), counters[q].size(), "tile counter", true));
  }
  // The pixel image the SPEs put their pixel buffers into (zero where no tile lies).
  const size_t num_pixels = size_t(width) * size_t(height);
  const size_t pixel_bytes = (num_pixels * sizeof(PixelSums) + 127) / 128 * 128;
  if (pixels_.size() < pixel_bytes) pixels_.Resize(pixel_bytes);
  std::memset(pixels_.data(), 0, pixel_bytes);
  fc.pixels = machine.memory.Register(pixels_.data(), pixel_bytes, "pixel image", true);
  AlignedBuffer status(size_t(config_.num_spes) * sizeof(SpeStatus));
  fc.status = machine.memory.Register(status.data(), status.size(), "SPE status records", true);
  for (size_t q = 0; q < nq; ++q) {
    FrameConstants& mine = *constants[q].As<FrameConstants>();
    mine = fc;
    mine.num_tiles = static_cast<uint32_t>(queues[q].size());
    mine.tiles = tiles_ea[q];
    mine.tile_counter = counter_ea[q];
  }

  // Per queue: the cycles and SPE of its tiles, by position in the queue.
  std::vector<std::vector<double>> queue_cycles(nq);
  std::vector<std::vector<int32_t>> queue_spe(nq);
  std::vector<FrameOutputs> outputs(nq);
  for (size_t q = 0; q < nq; ++q) {
    queue_cycles[q].assign(queues[q].size(), 0.0);
    queue_spe[q].assign(queues[q].size(), -1);
    outputs[q].tile_cycles = &queue_cycles[q];
    outputs[q].tile_spe = &queue_spe[q];
    outputs[q].block_work = block_work;
    // A cycle in kBlockWorkUnit, rounded: the blocks' work is simulated seconds (3.2 GHz:
    // 351844 units a cycle, 8e-7 relative).
    outputs[q].block_units_per_cycle =
        static_cast<uint64_t>(std::max(1.0, std::round(1.0 / (config_.clock_hz * kBlockWorkUnit))));
  }
  std::vector<std::unique_ptr<Spe>> spes;
  for (int i = 0; i < config_.num_spes; ++i) {
    const size_t q = nq == 1 ? 0 : size_t(i);
    spes.push_back(std::make_unique<Spe>(i, machine, constants_ea[q], outputs[q]));
  }

  // Discrete-event loop: always step the SPE with the earliest clock (lowest id on ties). Each
  // step ends where the SPE would next touch shared state, so the MIC sees lines in (nearly)
  // global time order and the tile counter's reservations are exact.
  for (;;) {
    Spe* next = nullptr;
    for (auto& s : spes) {
      if (!s->done() && (next == nullptr || s->now() < next->now())) next = s.get();
    }
    if (next == nullptr) break;
    machine.mic.AdvanceFloor(next->now());
    next->Step();
  }

  // The PPE's part: the image as it arrived in main memory (the pixel-buffer write-backs) into
  // the framebuffer, with the drop and clamp counts of the SPEs' status records.
  const PixelSums* px = pixels_.As<const PixelSums>();
  int64_t* sums = fb.sums();
  for (size_t p = 0; p < num_pixels; ++p) {
    for (int c = 0; c < 3; ++c) sums[3 * p + size_t(c)] += px[p].rgb[c];
  }
  uint64_t written = 0;
  for (int i = 0; i < config_.num_spes; ++i) {
    const SpeStatus& st = status.As<const SpeStatus>()[i];
    AddCounters(fb, st.dropped_nan, st.clamped);
    written += st.pixels_written;
  }
  if (written != covered) {
    throw Error("cell backend: the SPEs wrote back " + std::to_string(written) +
                " pixels but the tiles hold " + std::to_string(covered));
  }

  uint64_t frame_end = 0;
  for (auto& s : spes) frame_end = std::max(frame_end, s->now());
  stats.cycles = frame_end;
  stats.clock_hz = config_.clock_hz;
  stats.seconds = double(frame_end) / config_.clock_hz;
  for (auto& s : spes) {
    SpeReport r;
    r.id = s->id();
    r.finish = s->now();
    s->IdleUntil(frame_end);
    r.cycles = s->clock().spent();
    r.counters = s->counters();
    r.mfc = s->mfc_stats();
    r.atomic = s->atomic_stats();
    r.cache = s->cache_stats();
    r.ls_used = s->local_store().used();
    r.ls_layout = s->local_store().Describe();
    stats.totals.Merge(r.counters);
    stats.breakdown.Merge(r.cycles);
    stats.spes.push_back(std::move(r));
  }
  stats.mic_lines = machine.mic.lines();
  stats.mic_queue_cycles = machine.mic.queue_cycles();
  stats.tiles.resize(tiles.size());
  for (size_t i = 0; i < tiles.size(); ++i) stats.tiles[i].tile = tiles[i];
  for (size_t q = 0; q < nq; ++q) {
    for (size_t p = 0; p < queues[q].size(); ++p) {
      CellTileRecord& r = stats.tiles[size_t(queues[q][p])];
      r.spe = queue_spe[q][p];
      r.cycles = queue_cycles[q][p];
    }
  }

  FrameStats& f = stats.frame;
  const SpeCounters& c = stats.totals;
  for (int k = 0; k < kNumRayKinds; ++k) f.rays[k] = c.rays[k];
  f.tasks = c.iterations;
  f.hits = c.hits;
  f.occluded = c.occluded;
  f.shade = c.shade;
  f.trace.rays = c.TotalRays();
  f.trace.cell_steps = c.cell_steps;
  f.trace.triangle_tests = c.triangle_tests;
  stats.host_seconds = Seconds(t0, Clock::now());
  f.total_seconds = stats.host_seconds;
  ++frames_;
  return stats;
}

Accel BuildCellAccel(const Scene& scene, BuildOptions options, const SimConfig& config,
                     int image_width, std::string* note) {
  if (note != nullptr) note->clear();
  if (options.grid == GridKind::kIrregular) {
    throw Error("--grid irregular: the cell backend simulates the paper's uniform and two-level "
                "grids on the SPEs, not the irregular grid; use --grid auto, uniform or "
                "two-level");
  }
  const uint64_t budget = OccupancyBudgetCells(config, static_cast<uint32_t>(scene.lights.size()),
                                               image_width, /*two_level=*/true);
  Accel accel(scene.mesh(), options);
  AccelInfo info = accel.Info();
  if (info.cells <= budget) return accel;
  const size_t wanted = info.cells;
  float lambda = info.lambda > 0 ? info.lambda : options.lambda;
  for (int attempt = 0; attempt < 40; ++attempt) {
    lambda *= 0.9f * float(double(budget) / double(std::max<size_t>(info.cells, 1)));
    options.lambda = lambda;
    accel = Accel(scene.mesh(), options);
    info = accel.Info();
    if (info.cells <= budget) {
      if (note != nullptr) {
        char buf[256];
        std::snprintf(buf, sizeof(buf),
                      "grid of %zu cells does not fit the SPE local store (%llu cells of "
                      "occupancy bits); rebuilt with lambda %.3g: %zu cells, %s",
                      wanted, static_cast<unsigned long long>(budget), double(lambda), info.cells,
                      info.kind);
        *note = buf;
      }
      return accel;
    }
  }
  throw Error("cell backend: no grid of scene '" + scene.name + "' fits the local store's " +
              std::to_string(budget) + " cells of occupancy bits");
}

std::string FormatCellReport(const CellFrameStats& s, const SimConfig& config) {
  std::string out;
  char line[512];
  const uint64_t rays = s.totals.TotalRays();
  std::snprintf(line, sizeof(line),
                "cell       %d SPEs: %.3f ms simulated (%llu cycles at %.1f GHz), %.2f Mrays/s "
                "simulated; host %.1f ms (%.1f ns per simulated cycle)\n",
                config.num_spes, 1e3 * s.seconds, static_cast<unsigned long long>(s.cycles),
                s.clock_hz * 1e-9, s.SimulatedMraysPerSecond(), 1e3 * s.host_seconds,
                s.cycles ? 1e9 * s.host_seconds / double(s.cycles) : 0.0);
  out += line;
  out +=
      "           SPE  compute%   dma%  atomic%  cache%   idle%      rays  visits  "
      "ucache%  LS used\n";
  for (const SpeReport& r : s.spes) {
    const double total = double(std::max<uint64_t>(r.cycles.Total(), 1));
    const double visits = double(std::max<uint64_t>(r.counters.visits, 1));
    std::snprintf(line, sizeof(line),
                  "           %3d  %7.1f  %6.1f  %7.1f  %6.1f  %6.1f  %8llu  %6llu  %7.1f  %u\n",
                  r.id, 100.0 * double(r.cycles[Cost::kCompute]) / total,
                  100.0 * double(r.cycles[Cost::kDma]) / total,
                  100.0 * double(r.cycles[Cost::kAtomic]) / total,
                  100.0 * double(r.cycles[Cost::kCache]) / total,
                  100.0 * double(r.cycles[Cost::kIdle]) / total,
                  static_cast<unsigned long long>(r.counters.TotalRays()),
                  static_cast<unsigned long long>(r.counters.visits),
                  100.0 * double(r.counters.micro_cache_hits) / visits, r.ls_used);
    out += line;
  }
  const SpeCounters& c = s.totals;
  uint64_t dma_commands = 0, dma_bytes = 0, getllar = 0, atomic_hits = 0, reads = 0, hits = 0;
  uint64_t retries = c.tile_counter_retries;
  for (const SpeReport& r : s.spes) {
    dma_commands += r.mfc.commands;
    dma_bytes += r.mfc.bytes;
    getllar += r.atomic.getllar;
    atomic_hits += r.atomic.cache_hits;
    reads += r.cache.reads;
    hits += r.cache.hits;
  }
  std::snprintf(line, sizeof(line),
                "memory     %llu DMA commands (%.1f MiB), %llu MIC lines (%.1f cycles queueing "
                "per line), %llu atomic loads (%.1f %% atomic-cache hits), SW cache %.1f %% "
                "hits of %llu reads\n",
                static_cast<unsigned long long>(dma_commands), double(dma_bytes) / 1048576.0,
                static_cast<unsigned long long>(s.mic_lines),
                s.mic_lines ? double(s.mic_queue_cycles) / double(s.mic_lines) : 0.0,
                static_cast<unsigned long long>(getllar),
                getllar ? 100.0 * double(atomic_hits) / double(getllar) : 0.0,
                reads ? 100.0 * double(hits) / double(reads) : 0.0,
                static_cast<unsigned long long>(reads));
  out += line;
  std::snprintf(
      line, sizeof(line),
      "pipeline   %llu rays, %llu cell steps, %llu visits (%.1f %% micro-cache), "
      "%llu bundle tests, %llu tiles (%llu counter retries), %llu rays spilled\n",
      static_cast<unsigned long long>(rays), static_cast<unsigned long long>(c.cell_steps),
      static_cast<unsigned long long>(c.visits),
      c.visits ? 100.0 * double(c.micro_cache_hits) / double(c.visits) : 0.0,
      static_cast<unsigned long long>(c.bundles), static_cast<unsigned long long>(c.tiles),
      static_cast<unsigned long long>(retries), static_cast<unsigned long long>(c.spilled_rays));
  out += line;
  const uint64_t secondary = rays - c.rays[static_cast<int>(RayKind::kPrimary)];
  std::snprintf(line, sizeof(line),
                "at once    %llu of %llu secondary rays intersected at once with the loaded "
                "triangles (%llu cell visits), %llu resolved there%s\n",
                static_cast<unsigned long long>(c.at_once_tested),
                static_cast<unsigned long long>(secondary),
                static_cast<unsigned long long>(c.at_once_visits),
                static_cast<unsigned long long>(c.at_once_resolved),
                config.secondary_at_once ? "" : " (off)");
  out += line;
  if (s.pbt && s.has_prediction) {
    std::snprintf(line, sizeof(line),
                  "pbt        %zu tiles, %.1f %% of predictions within 10 %%, update %d steps\n",
                  s.accuracy.tiles, 100.0 * s.accuracy.within10, s.update.steps);
    out += line;
  }
  return out;
}

}  // namespace rs::sim
