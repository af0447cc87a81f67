// Discrete-event loop over the simulated SPEs, frame setup in main memory, statistics and PBT
// re-tiling (see cell_renderer.h).
#include "sim/cell_renderer.h"

#include <algorithm>
#include <chrono>
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

CellRenderer::CellRenderer(const SimConfig& config) : config_(config) { ValidateConfig(config_); }
CellRenderer::~CellRenderer() = default;

CellFrameStats CellRenderer::Render(const FrameContext& ctx, Framebuffer& fb) {
  if (config_.pbt_tiles_per_spe > 0) {
    const int w = ctx.options.width, h = ctx.options.height;
    if (!pbt_ || pbt_->width() != w || pbt_->height() != h) {
      pbt_ = std::make_unique<Pbt>(w, h, config_.num_spes, config_.pbt_tiles_per_spe);
    }
    const std::vector<Tile> pbt_tiles = pbt_->Tiles();
    const std::vector<double> estimates = pbt_->Estimates();
    const bool predicted =
        std::any_of(estimates.begin(), estimates.end(), [](double e) { return e > 0; });
    // The counter hands the costliest tiles out first (ties: tile order).
    std::vector<size_t> order(pbt_tiles.size());
    std::iota(order.begin(), order.end(), size_t{0});
    std::stable_sort(order.begin(), order.end(),
                     [&](size_t a, size_t b) { return estimates[a] > estimates[b]; });
    std::vector<Tile> list(order.size());
    for (size_t i = 0; i < order.size(); ++i) list[i] = pbt_tiles[order[i]];
    CellFrameStats stats = RenderTiles(ctx, fb, list, true);
    // Back to PBT tile indices.
    std::vector<CellTileRecord> by_index(order.size());
    std::vector<double> measured(order.size()), predicted_times(order.size());
    for (size_t i = 0; i < order.size(); ++i) {
      by_index[order[i]] = stats.tiles[i];
      by_index[order[i]].predicted = predicted ? estimates[order[i]] : -1.0;
      measured[order[i]] = stats.tiles[i].cycles;
      predicted_times[order[i]] = estimates[order[i]];
    }
    stats.tiles = std::move(by_index);
    stats.pbt = true;
    stats.has_prediction = predicted;
    if (predicted) stats.accuracy = MeasurePredictionAccuracy(predicted_times, measured);
    stats.update = pbt_->Update(measured);
    return stats;
  }
  const int w = ctx.options.width, h = ctx.options.height;
  const int tw = std::min(config_.tile_width, w), th = std::min(config_.tile_height, h);
  const int tiles_x = (w + tw - 1) / tw, tiles_y = (h + th - 1) / th;
  std::vector<Tile> tiles;
  tiles.reserve(size_t(tiles_x) * size_t(tiles_y));
  for (int y = 0; y < h; y += th) {
    for (int x = 0; x < w; x += tw) {
      tiles.push_back(Tile{x, y, std::min(x + tw, w), std::min(y + th, h)});
    }
  }
  return RenderTiles(ctx, fb, tiles, false);
}

CellFrameStats CellRenderer::Render(const FrameContext& ctx, Framebuffer& fb,
                                    std::span<const Tile> tiles) {
  return RenderTiles(ctx, fb, tiles, true);
}

CellFrameStats CellRenderer::RenderTiles(const FrameContext& ctx, Framebuffer& fb,
                                         std::span<const Tile> tiles, bool explicit_tiles) {
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

  // Main memory of the frame: the scene image at its planned EAs, then the frame's buffers.
  Machine machine(config_);
  image_->Register(machine.memory);
  AlignedBuffer constants(sizeof(FrameConstants));
  const Ea constants_ea =
      machine.memory.Register(constants.data(), constants.size(), "frame constants");
  FrameConstants& fc = *constants.As<FrameConstants>();
  fc = FrameConstants{};
  image_->FillConstants(&fc);
  fc.camera = ctx.camera;
  fc.shade = ctx.shade;
  fc.image_width = width;
  fc.image_height = height;
  AlignedBuffer tile_buffer(std::max<size_t>(tiles.size(), 1) * sizeof(Tile));
  if (explicit_tiles) {
    std::copy(tiles.begin(), tiles.end(), tile_buffer.As<Tile>());
    fc.explicit_tiles = 1;
    fc.tile_width = fc.tile_height = fc.tiles_x = 1;
  } else {
    fc.explicit_tiles = 0;
    fc.tile_width = std::min(config_.tile_width, width);
    fc.tile_height = std::min(config_.tile_height, height);
    fc.tiles_x = (width + fc.tile_width - 1) / fc.tile_width;
  }
  fc.num_tiles = static_cast<uint32_t>(tiles.size());
  fc.tiles = machine.memory.Register(tile_buffer.data(), tile_buffer.size(), "tile list");
  AlignedBuffer counter(128);
  fc.tile_counter = machine.memory.Register(counter.data(), counter.size(), "tile counter", true);
  // The pixel image the SPEs put their pixel buffers into (zero where no tile lies).
  const size_t num_pixels = size_t(width) * size_t(height);
  const size_t pixel_bytes = (num_pixels * sizeof(PixelSums) + 127) / 128 * 128;
  if (pixels_.size() < pixel_bytes) pixels_.Resize(pixel_bytes);
  std::memset(pixels_.data(), 0, pixel_bytes);
  fc.pixels = machine.memory.Register(pixels_.data(), pixel_bytes, "pixel image", true);
  AlignedBuffer status(size_t(config_.num_spes) * sizeof(SpeStatus));
  fc.status = machine.memory.Register(status.data(), status.size(), "SPE status records", true);

  std::vector<double> tile_cycles(tiles.size(), 0.0);
  std::vector<int32_t> tile_spe(tiles.size(), -1);
  FrameOutputs outputs;
  outputs.tile_cycles = &tile_cycles;
  outputs.tile_spe = &tile_spe;
  std::vector<std::unique_ptr<Spe>> spes;
  for (int i = 0; i < config_.num_spes; ++i) {
    spes.push_back(std::make_unique<Spe>(i, machine, constants_ea, outputs));
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
  for (size_t i = 0; i < tiles.size(); ++i) {
    stats.tiles[i].tile = tiles[i];
    stats.tiles[i].spe = tile_spe[i];
    stats.tiles[i].cycles = tile_cycles[i];
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
  const uint64_t budget = OccupancyBudgetCells(config, static_cast<uint32_t>(scene.lights.size()),
                                               image_width, /*two_level=*/true);
  Accel accel(scene.mesh(), options);
  AccelInfo info = accel.Info();
  if (info.cells <= budget) return accel;
  const size_t wanted = info.cells;
  float lambda = info.lambda > 0 ? info.lambda : options.lambda;
  for (int attempt = 0; attempt < 40; ++attempt) {
    lambda *= 0.9f * float(double(budget) / double(std::max<size_t>(info.cells, 1)));
    options.auto_lambda = false;
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
      "%llu packet tests, %llu tiles (%llu counter retries), %llu rays spilled\n",
      static_cast<unsigned long long>(rays), static_cast<unsigned long long>(c.cell_steps),
      static_cast<unsigned long long>(c.visits),
      c.visits ? 100.0 * double(c.micro_cache_hits) / double(c.visits) : 0.0,
      static_cast<unsigned long long>(c.packets), static_cast<unsigned long long>(c.tiles),
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
