// One simulated SPE running the ray pipeline of the Cell paper (section 3.2) as a resumable
// program: refill the FIFO ring buffer (primary rays from tiles of the atomic tile counter),
// traverse 8 rays to their first occupied cell on the LS occupancy bits, load each cell's record
// (128-B atomic load; a refined cell's 8x8x8 sub-grid record is a second one, paper 3.8) and
// triangles (DMA) while the others traverse, intersect (VisitVoxel), load hit data, shade
// (materials and textures through the software cache) and write secondary rays back, after
// intersecting them at once with the triangles still in the triangle buffers (paper 3.7).
// Step() runs to the next point where the SPE touches shared state, so a discrete-event loop can
// always advance the SPE that is furthest behind.
#pragma once

#include <cstdint>
#include <memory>
#include <vector>

#include "include/raystream/raystream.h"
#include "kernels/shade.h"
#include "sched/cost_map.h"
#include "sim/config.h"
#include "sim/local_store.h"
#include "sim/mfc.h"
#include "sim/sw_cache.h"

namespace rs::sim {

// Work counters of one SPE (or all, merged).
struct SpeCounters {
  uint64_t rays[kNumRayKinds] = {};   // rays finished, by RayKind
  uint64_t hits = 0;                  // closest-hit rays that hit
  uint64_t occluded = 0;              // shadow rays blocked
  uint64_t cell_steps = 0;            // cells examined (same count as the reference DDA)
  uint64_t visits = 0;                // occupied cells intersected (VisitVoxel)
  uint64_t bundles = 0;               // 1 ray x 4 triangle bundle tests
  uint64_t triangle_tests = 0;        // live lanes tested
  uint64_t micro_cache_hits = 0;      // visits that reused a cell loaded in the same iteration
  uint64_t cell_loads = 0;            // cell records fetched (atomic loads) + triangle DMAs
  uint64_t chunk_loads = 0;           // extra synchronous loads for cells larger than a buffer
  uint64_t hit_loads = 0;             // hit-data DMAs
  uint64_t subgrid_loads = 0;         // sub-grid records loaded (two-level grid, paper 3.8)
  uint64_t iterations = 0;            // pipeline iterations
  uint64_t rays_in_flight = 0;        // sum over iterations of the rays taken (<= 8 each)
  // Pipeline iterations by the number of rays they took, 0..8: rays_per_iteration while the
  // ring holds that many, fewer only for the last rays (1 each with drain_individually).
  uint64_t iterations_by_rays[9] = {};
  uint64_t tiles = 0;                 // tiles taken from the tile counter
  uint64_t subtiles = 0;              // pixel-buffer sub-tiles rendered
  uint64_t tile_counter_retries = 0;  // failed putllc on the tile counter (contention)
  uint64_t spilled_rays = 0;          // rays written to main memory because the ring was full
  uint64_t texture_fetches = 0;
  // Secondary rays intersected at once against the triangles still in the triangle buffers
  // (paper 3.7; SimConfig::secondary_at_once): rays that tested at least one loaded cell, rays
  // whose traversal ended there (shadow rays finished, others left only to be shaded), and the
  // cells so visited (not counted in `visits`; their bundles are in `bundles`).
  uint64_t at_once_tested = 0;
  uint64_t at_once_resolved = 0;
  uint64_t at_once_visits = 0;
  // Where the SPE's busy cycles (its clock at the program's end) went, apart from the pipeline
  // iterations, whose cycles are attributed to the tiles of their rays (FrameOutputs::
  // tile_cycles): the program start (frame constants, lights, occupancy bits into LS) and the
  // tail (the last, empty refill that finds no tile left, the last write-backs and the final
  // wait). So over all tiles, sum of tile cycles = sum over SPEs of (finish - startup - tail).
  uint64_t startup_cycles = 0;
  uint64_t tail_cycles = 0;
  ShadeStats shade;
  void Merge(const SpeCounters& o);
  uint64_t TotalRays() const;
};

// The state all SPEs of one frame share: main memory, the MIC, the atomic lines.
struct Machine {
  explicit Machine(const SimConfig& c) : config(c), mic(c.memory.mic_line_cycles) {}
  const SimConfig& config;
  MainMemory memory;
  MemoryController mic;
  AtomicMemory atomic;
};

// Host-side statistics of the frame that are not part of the simulated program's data (the image
// itself goes through main memory: the SPE accumulates it in its LS pixel buffers, puts them into
// the pixel image at FrameConstants::pixels and its counters into FrameConstants::status).
struct FrameOutputs {
  // Per tile: SPE cycles attributed to its rays (each pipeline iteration's cycles shared equally
  // among the iteration's rays, from the refill that starts it to the end of its shading).
  std::vector<double>* tile_cycles = nullptr;
  std::vector<int32_t>* tile_spe = nullptr;  // per tile: the SPE that took it
  // PBT's cost map (sched/cost_map.h; nullptr: no record): each iteration's cycles charged to
  // the blocks of its rays' pixels in the same equal shares as tile_cycles, in fixed point
  // (block_units_per_cycle units a cycle; each ray gets units / n, the first units % n rays of
  // the iteration one more), so the blocks' sum is exactly the attributed cycles times
  // block_units_per_cycle and does not depend on the order the SPEs are stepped in. Each
  // primary ray's hit distance (+inf: a miss) goes to block_work->pixel_depth[pixel] if that is
  // not null. One host thread steps every SPE, so they all share one record.
  BlockWork* block_work = nullptr;
  uint64_t block_units_per_cycle = 1;
};

// Occupancy-bit capacity of an SPE's local store: the cells whose bits fit after the code/stack
// budget and every pipeline buffer (as laid out for `num_lights` lights, an image `image_width`
// pixels wide, and the sub-grid lines of a two-level grid). A grid with more cells is refused.
uint64_t OccupancyBudgetCells(const SimConfig& config, uint32_t num_lights, int image_width,
                              bool two_level);

class Spe {
 public:
  // The program starts by DMA-ing the FrameConstants at `constants` into its local store.
  Spe(int id, Machine& machine, Ea constants, const FrameOutputs& outputs);
  ~Spe();
  Spe(const Spe&) = delete;
  Spe& operator=(const Spe&) = delete;

  // Runs the program to its next yield point. Throws rs::Error on a local-store overflow (the
  // first Step lays out the LS), an illegal DMA or a grid whose bits do not fit.
  void Step();
  bool done() const;
  uint64_t now() const;
  int id() const;

  // Charges the cycles from this SPE's finish to `frame_end` as idle time.
  void IdleUntil(uint64_t frame_end);

  const SpuClock& clock() const;
  const SpeCounters& counters() const;
  const MfcStats& mfc_stats() const;
  const AtomicStats& atomic_stats() const;
  SoftwareCacheStats cache_stats() const;
  const LocalStore& local_store() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace rs::sim
