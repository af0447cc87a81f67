// The Cell backend: renders a frame on 1..8 simulated SPEs (sim/spe.h) under a deterministic
// discrete-event loop on one host thread that always advances the SPE furthest behind in
// simulated time. Produces the serial backend's image bit for bit, plus the simulated frame time
// at 3.2 GHz and a per-SPE cycle breakdown (compute, DMA, atomic, software cache, idle).
#pragma once

#include <cstdint>
#include <memory>
#include <span>
#include <string>
#include <vector>

#include "sched/framebuffer.h"
#include "sched/pbt.h"
#include "sched/render.h"
#include "sim/cell_image.h"
#include "sim/config.h"
#include "sim/mfc.h"
#include "sim/spe.h"
#include "sim/sw_cache.h"

namespace rs::sim {

struct SpeReport {
  int id = 0;
  CycleBreakdown cycles;  // sums to the frame's cycles (idle = after its last ray)
  uint64_t finish = 0;    // cycle its program ended
  SpeCounters counters;
  MfcStats mfc;
  AtomicStats atomic;
  SoftwareCacheStats cache;
  uint32_t ls_used = 0;  // local-store bytes allocated (code/stack budget included)
  std::string ls_layout;
};

struct CellTileRecord {
  Tile tile;
  int32_t spe = -1;       // the SPE that took it from the counter
  double cycles = 0;      // SPE cycles attributed to its rays (FrameOutputs::tile_cycles)
  double predicted = -1;  // PBT: the estimate it was tiled with (-1: none)
};

struct CellFrameStats {
  // Counters in the host backends' form (rays by kind, hits, occluded, shading, cell steps,
  // triangle tests); total_seconds is the host wall time of the simulation.
  FrameStats frame;
  uint64_t cycles = 0;  // simulated frame time: the last SPE's finish
  double seconds = 0;   // cycles / clock_hz
  double clock_hz = 3.2e9;
  std::vector<SpeReport> spes;
  SpeCounters totals;
  CycleBreakdown breakdown;  // summed over SPEs
  uint64_t mic_lines = 0;
  uint64_t mic_queue_cycles = 0;  // lines' waiting at the shared MIC (contention)
  double host_seconds = 0;        // wall time of Render (image build excluded)
  double image_seconds = 0;       // PPE layout of the main-memory image (when (re)built)
  size_t image_bytes = 0;
  std::vector<CellTileRecord> tiles;
  // PBT tiling (config.pbt_tiles_per_spe > 0).
  bool pbt = false;
  bool has_prediction = false;
  PredictionAccuracy accuracy;
  PbtUpdateStats update;

  // Rays per simulated second / 1e6.
  double SimulatedMraysPerSecond() const;
};

class CellRenderer {
 public:
  // Throws rs::Error if the config is invalid (ValidateConfig).
  explicit CellRenderer(const SimConfig& config);
  ~CellRenderer();
  CellRenderer(const CellRenderer&) = delete;
  CellRenderer& operator=(const CellRenderer&) = delete;

  // Renders the whole image into fb (added to it, not cleared first; fb must be width x height
  // of ctx): regular tiles of config.tile_width x tile_height from the atomic tile counter, or
  // the PBT's tiles (handed out by the counter in order of decreasing estimate; the PBT is
  // updated with the simulated tile cycles after the frame, CellTileRecord::cycles). The SPEs
  // accumulate the image in their local-store pixel buffers and put them into a main-memory
  // pixel image by DMA; fb receives that image (and the drop and clamp counts of the SPEs'
  // status records) after the frame. Throws rs::Error if fb's size differs, a local store
  // overflows (e.g. the grid's occupancy bits do not fit), or a DMA is illegal.
  CellFrameStats Render(const FrameContext& ctx, Framebuffer& fb);
  // The same with an explicit tile list (inside the image, not overlapping: throws rs::Error
  // naming the two tiles otherwise), handed out in list order. Pixels outside every tile stay
  // unchanged in fb.
  CellFrameStats Render(const FrameContext& ctx, Framebuffer& fb, std::span<const Tile> tiles);

  const SimConfig& config() const { return config_; }
  const Pbt* pbt() const { return pbt_.get(); }
  // The main-memory image of the last frame's scene (nullptr before the first frame).
  const CellImage* image() const { return image_.get(); }

 private:
  CellFrameStats RenderTiles(const FrameContext& ctx, Framebuffer& fb, std::span<const Tile> tiles,
                             bool explicit_tiles);

  SimConfig config_;
  std::unique_ptr<CellImage> image_;
  std::unique_ptr<Pbt> pbt_;
  AlignedBuffer pixels_;
  uint64_t frames_ = 0;
};

// The acceleration structure for the cell backend: built with `options` when its top-level
// occupancy bits fit the SPE's local store (OccupancyBudgetCells); otherwise rebuilt with a lower
// lambda (auto_lambda off, the grid kind kept, so kAuto may refine dense cells into 8x8x8
// sub-grids, as paper 3.8 does for large scenes) until they fit. *note (if given) is set to a
// sentence saying what was changed, or cleared. Throws rs::Error if no lambda fits.
Accel BuildCellAccel(const Scene& scene, BuildOptions options, const SimConfig& config,
                     int image_width, std::string* note = nullptr);

// A multi-line human-readable report: simulated time, rays/s, per-SPE breakdown table, loads,
// caches, tile counter contention.
std::string FormatCellReport(const CellFrameStats& stats, const SimConfig& config);

}  // namespace rs::sim
