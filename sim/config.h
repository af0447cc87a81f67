// Every constant of the Cell/B.E. simulator in one struct: machine sizes, MFC/DMA and atomic-unit
// timing, software-cache geometry, the annotated compute-cost model of the SPE ray pipeline
// (Bingel & Hinkenjann, "Streamed Ray Tracing of Single Rays on the Cell Processor") and its
// buffer sizes. Sources: shared/CELL-FACTS.md (SDK-PT = IBM Cell SDK 3.0 Programming Tutorial).
#pragma once

#include <cstdint>
#include <string>

namespace rs::sim {

// Timing of the MFC, the memory interface controller (MIC) and the atomic unit, from the hardware
// facts of shared/CELL-FACTS.md section 1 (cited per field) at 3.2 GHz (1 cycle = 0.3125 ns,
// 25.6 GB/s = 8 B/cycle). Nothing here is fitted to the paper's Table 1:
// bench/sim/load_cost_bench.cc reports how far the Table 1 micro-benchmarks (sim/load_bench.h) land
// from it. The one latency figure is Kistler, Perrone, Petrini (IEEE Micro 26(3), 2006): one 128-B
// line in < 100 ns, about 320 cycles, issue to data in LS as the SPU sees it; kLineRoundTripCycles
// below.
struct MemoryTiming {
  // Kistler et al.: a 128-B DMA completes in < 100 ns = 320 cycles at 3.2 GHz (CELL-FACTS
  // section 1, "DMA latency"; section 4 rule 6: "calibrate L0 so that one line takes about
  // 320 cycles"). The latencies below are what is left of it after the other terms.
  static constexpr uint32_t kLineRoundTripCycles = 320;

  // SPU cycles to issue one MFC command: Kistler et al. "issue < 4 ns" = 12.8 cycles -> 13.
  uint32_t dma_issue_cycles = 13;
  // SPU cycles of a tag-group wait that finds the data already there: write the tag mask, read
  // the tag status channel, two channel instructions of 6 cycles (SDK-PT cbet_3pipedr, odd pipe
  // "CH channel 6").
  uint32_t dma_wait_cycles = 12;
  // Cycles from the serving of a command's last 128-B line by the MIC to its completion. A one-
  // line get on an idle machine: issue 13 + MIC line 16 + latency + wait 12 = 320 (Kistler et al.)
  // => 279. (The paper's "at least 800 - 900 cycles" for a DMA, section 3.4, is not used.)
  uint32_t dma_latency_cycles =
      kLineRoundTripCycles - /*issue*/ 13 - /*MIC line*/ 16 - /*wait*/ 12;
  // Commands one SPE's MFC has in flight to memory at once: the 16 entries of its command queue
  // (MFC_SPU_MAX_QUEUE_SPACE, cbe_mfc.h). Kistler et al.: one SPE reaches 25.6 GB/s "with
  // messages of a few KB in batches of non-blocking DMAs", which needs commands to overlap
  // (320 cycles x 8 B/cycle = 2.5 KiB in flight); the port limit of 8 B/cycle stays (one line per
  // mic_line_cycles per SPE). 1 = one command at a time (a slower MFC than the facts describe).
  int mfc_bus_slots = 16;
  // MFC command queue entries per SPE (MFC_SPU_MAX_QUEUE_SPACE = 16, cbe_mfc.h). Issuing into
  // a full queue stalls the SPU until the oldest command completes.
  int mfc_queue_depth = 16;
  // MIC service time of one 128-B line: 128 B at 25.6 GB/s (XDR, two 12.8 GB/s channels,
  // CELL-FACTS "Memory (MIC/XDR)") = 8 B/cycle = 16 cycles. One MIC for all SPEs: lines are
  // served in time order; queueing behind the other SPEs' lines is the contention of Fig. 2.
  // Also the SPE port limit (16-B port at half clock = 8 B/cycle, CELL-FACTS "EIB").
  uint32_t mic_line_cycles = 16;
  // Extra MFC cycles per DMA-list element (list element fetch from LS; an estimate: no
  // published figure, CELL-FACTS lists none).
  uint32_t dma_list_element_cycles = 4;

  // Atomic unit (getllar / putllc / putlluc on 128-B lines, one command at a time per SPE).
  // SPU cycles to issue: an MFC command like a DMA (Kistler et al. "issue < 4 ns" -> 13).
  uint32_t atomic_issue_cycles = 13;
  // Latency of a getllar that misses the SPE's atomic cache, after its MIC line. CELL-FACTS
  // section 4 rule 7: an atomic command that misses the atomic cache "pays a line fetch", the
  // same 320-cycle line as a DMA: issue 13 + MIC line 16 + latency + status read 6 = 320 => 285.
  // (The paper's "about 200 - 300 processor cycles", section 3.4, is not used.)
  uint32_t atomic_latency_cycles =
      kLineRoundTripCycles - /*issue*/ 13 - /*MIC line*/ 16 - /*status*/ 6;
  // getllar / putllc served by the 4-line atomic cache (line present, not invalidated by
  // another SPE's store): the atomic unit's pipeline only (an estimate: CELL-FACTS has no figure).
  uint32_t atomic_hit_cycles = 40;
  // SPU cycles to read the atomic status channel once the command completed (SDK-PT
  // cbet_3pipedr: channel instructions 6 cycles).
  uint32_t atomic_status_cycles = 6;
  int atomic_cache_lines = 4;  // 4 x 128 B per SPE (CELL-FACTS "Atomic unit": Dean Calver)
};
// The defaults add up to Kistler et al.'s one-line round trip, for a DMA and for an atomic load.
static_assert(MemoryTiming{}.dma_issue_cycles + MemoryTiming{}.mic_line_cycles +
                  MemoryTiming{}.dma_latency_cycles + MemoryTiming{}.dma_wait_cycles ==
              MemoryTiming::kLineRoundTripCycles);
static_assert(MemoryTiming{}.atomic_issue_cycles + MemoryTiming{}.mic_line_cycles +
                  MemoryTiming{}.atomic_latency_cycles + MemoryTiming{}.atomic_status_cycles ==
              MemoryTiming::kLineRoundTripCycles);

// IBM software cache (cache-api.h defaults): 2^7 = 128-B lines, 64 sets, 4-way => 32 KiB of data.
// Used read-only here (materials, textures), so no write-back. A miss fetches the line with a
// synchronous DMA (MemoryTiming) on a dedicated tag (IBM uses tag = set & 0x1f; a dedicated tag
// keeps the cache's wait from also waiting on the pipeline's DMAs).
struct SoftwareCacheConfig {
  uint32_t line_bytes = 128;
  uint32_t sets = 64;
  uint32_t ways = 4;  // IBM allows 1 or 4
  // Hit: address split, 4 tags compared at once with SIMD, LRU update, LS load. Codeplay
  // Offload's comparable cache: read hit 28 cycles (CELL-FACTS).
  uint32_t hit_cycles = 28;
  // Miss handling on top of the hit path and the DMA: victim choice, tag update (estimate;
  // Codeplay reports ~600 for a whole miss on a quieter memory model).
  uint32_t miss_extra_cycles = 40;
  uint32_t tag = 31;
};

// Annotated compute costs of the SPE ray pipeline, in SPU cycles. The DDA step is the paper's
// measured figure; the rest are estimates from the SPU latency table (SDK-PT cbet_3pipedr: SP
// float 6 cycles, LS load 6, shuffle 4, mispredicted branch 18) and instruction counts of
// straightforward SIMD code, as noted per field. All scale the simulated time linearly.
struct ComputeCosts {
  // One grid cell stepped by the branch-free loop of Listing 1 (paper section 3.3: "traverse a
  // ray in only 21 processor cycles per grid cell").
  uint32_t dda_step = 21;
  // Leaving the traversal loop: its back branch is hinted taken, so the exit mispredicts once
  // (18 cycles, SDK-PT cbet_3reducbrmis).
  uint32_t dda_exit = 18;
  // New ray: slab clip against the grid box (3 reciprocal estimates + Newton step, min/max),
  // start cell (float->int), step and t_next per axis, watertight shear constants: about 4
  // dependent chains of 6-cycle SP ops, ~70 instructions dual issued.
  uint32_t ray_setup = 70;
  // A ray taken back from the ring buffer mid-traversal: reload its state (8 quadwords) and
  // recompute 1/d and the shear constants (one reciprocal chain).
  uint32_t ray_resume = 30;
  // Moving one 128-B ray record between ring buffer / in-flight slots / staging: 8 quadword
  // loads + 8 stores on the odd pipe plus pointer arithmetic.
  uint32_t ray_copy = 16;
  // Micro-cache lookup (paper 3.5: 2 vectors of 4 cell indices, 2 compares + orx + branch).
  uint32_t micro_cache_lookup = 8;
  // Per visited cell: read the cell record out of the atomic line, permute the ray into the
  // watertight (kx, ky, kz) order, set up the bundle loop.
  uint32_t visit_setup = 24;
  // One ray against one bundle of 4 triangles (paper 3.6, 1 ray x 4 triangles, two bundles per
  // loop iteration): ~48 even-pipe SP/FX instructions for the 4-wide test (edge functions,
  // determinant, t) and the hit selection, loads and shuffles dual issued on the odd pipe; the
  // 2x unroll hides the 6-cycle latencies.
  uint32_t triangle_bundle = 48;
  // Primary ray generation, per ray (4-wide: pixel -> camera plane, rsqrt normalize, record
  // store).
  uint32_t primary_ray = 24;
  // Shading (paper 3.7), per ray handed to the shader (miss or hit): bookkeeping, background.
  uint32_t shade_ray = 20;
  // Per hit point: barycentric interpolation of position and normal, face normal (cross,
  // rsqrt), orientation, ambient term, contribution into the pixel buffer.
  uint32_t shade_hit = 160;
  // Per (hit point, light): light vector, rsqrt, two dots, phong highlight (pow via exp/log
  // estimates ~40 cycles), shadow-ray weight.
  uint32_t shade_light = 90;
  // Per bilinear texture sample on top of its 4 software-cache reads: wrap, floor, 3 lerps.
  uint32_t shade_texture = 60;
  // Per secondary ray written to the ray buffer: robust origin offset, reflect/refract
  // direction (sqrt for Snell), 128-B record store.
  uint32_t shade_spawn = 50;
  // Per unoccluded shadow ray: add its weight into the pixel buffer.
  uint32_t shadow_add = 12;
  // Per pipeline iteration: ring-buffer checks, loop control, the branch mispredicts between
  // the stages.
  uint32_t iteration = 60;
  // Per tile handed out: tile rectangle from the counter value (a division), sub-tile set up.
  uint32_t tile_setup = 120;
  // One local-store load whose result is used next (lqd / lqx): 6 cycles (SDK-PT cbet_3pipedr,
  // odd pipe "LS load/store 6"; paper section 1: the LS "can be accessed very fast (within 6
  // cycles)"). The Table 1 micro-benchmarks charge it for reading the loaded record.
  uint32_t ls_load = 6;
};

struct SimConfig {
  // --- machine ---
  int num_spes = 6;  // a PS3 exposes 6 SPEs (CELL-FACTS); 1..8
  double clock_hz = 3.2e9;
  uint32_t local_store_bytes = 256 * 1024;
  // LS reserved for the SPE program text and its stack. The paper's renderer had "about 100
  // KByte" left for the occupancy bits (3.8: ~800,000 cells); 40 KiB for code and stack plus the
  // buffers below would leave ~96 KiB with 16-B pixels, and leave ~57 KiB (~470,000 cells at 4
  // lights) with the 32-B fixed-point pixels the pixel buffers hold (see pixel_buffer_pixels).
  uint32_t code_stack_bytes = 40 * 1024;

  MemoryTiming memory;
  SoftwareCacheConfig sw_cache;
  ComputeCosts costs;

  // --- ray pipeline (paper 3.2) ---
  int rays_per_iteration = 8;  // rays in flight; 1..8 (tags and micro-cache have 8 entries)
  bool micro_cache = true;     // 8-entry micro-cache of loaded grid cells (3.5)
  uint32_t ring_rays = 128;    // FIFO ring buffer of 128-B ray records in LS
  // Rays that do not fit the ring go to an LS staging block, which is written to main memory
  // with one DMA when full and fetched back when the ring runs low (<= 128 rays = 16 KiB).
  uint32_t staging_rays = 32;
  // Triangle buffer per ray in flight, in bundles of 4 triangles (160 B each). Cells with more
  // triangles are streamed through the buffer in chunks.
  uint32_t triangle_buffer_bundles = 16;
  // Pixel buffers in LS; a tile is rendered in sub-tiles of at most pixel_buffer_pixels pixels
  // and max_subtile_rows rows (paper 3.9: "not possible to use tiles with more than 1280
  // pixels"). A pixel is the framebuffer's three 64-bit fixed-point sums plus a pad word
  // (sim::PixelSums, 32 B: two quadwords, so rows are legal DMAs), which keeps the image bit for
  // bit the serial backend's; 2 x 1280 pixels take 80 KiB (the paper's float pixels would take
  // half). Two buffers let a new sub-tile start while the previous one's secondary rays finish.
  uint32_t pixel_buffer_pixels = 1280;
  uint32_t max_subtile_rows = 64;
  int pixel_buffers = 2;
  // Paper 3.2: when fewer than 8 rays are left and no primary rays can be generated, "these last
  // rays are processed individually, without any interleaving of the memory accesses". With one
  // pixel buffer this happens at the end of every (sub-)tile. Off by default: the tail rays are
  // then still interleaved with each other.
  bool drain_individually = false;
  // Paper 3.7: secondary rays "emerge in a grid cell whose data is still in the triangle buffer,
  // [so] they are directly intersected with the triangles". When on, the shader sets up each
  // secondary ray at once and walks it (DDA on the LS bits) through every cell whose triangles
  // this iteration left whole in a triangle buffer, with the pipeline's own test and stop rule:
  // a shadow ray that hits ends there, a ray that leaves the scene or stops before its next cell
  // is finished without entering the ring buffer, and the others are written back mid-traversal
  // at the first cell that is not loaded. Off: every secondary ray starts fresh from the ring.
  bool secondary_at_once = true;

  // --- tiles ---
  int tile_width = 32;  // tiles handed out by the atomic tile counter (3.9), row-major
  int tile_height = 32;
  int pbt_tiles_per_spe = 0;  // > 0: PBT tiling with k tiles per SPE, re-tiled every frame
};

// Throws rs::Error naming the field if a value is out of range (num_spes outside 1..8, sizes
// that are zero or not multiples of 16 where DMA needs it, rays_per_iteration outside 1..8,
// software-cache ways not 1 or 4, sets not a power of two, ...).
void ValidateConfig(const SimConfig& config);

// One line per field group, for reports ("spes 6, LS 256 KiB, ...").
std::string DescribeConfig(const SimConfig& config);

}  // namespace rs::sim
