// SimConfig validation and description (see config.h).
#include "sim/config.h"

#include <string>

#include "include/raystream/raystream.h"

namespace rs::sim {
namespace {

void Require(bool ok, const std::string& what) {
  if (!ok) throw Error("cell simulator config: " + what);
}

bool PowerOfTwo(uint32_t x) { return x != 0 && (x & (x - 1)) == 0; }

}  // namespace

void ValidateConfig(const SimConfig& c) {
  Require(c.num_spes >= 1 && c.num_spes <= 8,
          "num_spes " + std::to_string(c.num_spes) + " must be 1..8");
  Require(c.clock_hz > 0, "clock_hz must be positive");
  Require(c.local_store_bytes >= 16 * 1024 && c.local_store_bytes % 128 == 0 &&
              c.local_store_bytes <= (1u << 24),
          "local_store_bytes " + std::to_string(c.local_store_bytes) +
              " must be a multiple of 128 in 16 KiB..16 MiB");
  Require(c.code_stack_bytes < c.local_store_bytes, "code_stack_bytes " +
                                                        std::to_string(c.code_stack_bytes) +
                                                        " must be less than the local store");
  const MemoryTiming& m = c.memory;
  Require(m.mfc_bus_slots >= 1 && m.mfc_bus_slots <= 64, "mfc_bus_slots must be 1..64");
  Require(m.mfc_queue_depth >= 1 && m.mfc_queue_depth <= 64, "mfc_queue_depth must be 1..64");
  Require(m.mic_line_cycles >= 1, "mic_line_cycles must be >= 1");
  Require(m.atomic_cache_lines >= 0 && m.atomic_cache_lines <= 64,
          "atomic_cache_lines must be 0..64");
  const SoftwareCacheConfig& s = c.sw_cache;
  Require(s.ways == 1 || s.ways == 4, "sw_cache.ways must be 1 or 4");
  Require(
      PowerOfTwo(s.sets) && PowerOfTwo(s.line_bytes) && s.line_bytes >= 16 && s.line_bytes <= 16384,
      "sw_cache sets and line_bytes must be powers of two (line 16..16384 B)");
  Require(s.tag < 32, "sw_cache.tag must be 0..31");
  Require(c.rays_per_iteration >= 1 && c.rays_per_iteration <= 8,
          "rays_per_iteration " + std::to_string(c.rays_per_iteration) + " must be 1..8");
  Require(c.ring_rays >= 16 && c.ring_rays <= 4096,
          "ring_rays " + std::to_string(c.ring_rays) + " must be 16..4096");
  Require(c.staging_rays >= 8 && c.staging_rays <= 128,
          "staging_rays must be 8..128 (one DMA of at most 16 KiB)");
  Require(c.triangle_buffer_bundles >= 1 && c.triangle_buffer_bundles * 160 <= 16384,
          "triangle_buffer_bundles must be 1..102 (one DMA of at most 16 KiB)");
  Require(c.pixel_buffer_pixels >= 1, "pixel_buffer_pixels must be >= 1");
  Require(c.max_subtile_rows >= 1 && c.max_subtile_rows <= 2048,
          "max_subtile_rows must be 1..2048 (one DMA list)");
  Require(c.pixel_buffers >= 1 && c.pixel_buffers <= 8, "pixel_buffers must be 1..8");
  Require(c.tile_width >= 1 && c.tile_height >= 1, "tile size " + std::to_string(c.tile_width) +
                                                       "x" + std::to_string(c.tile_height) +
                                                       " must be at least 1x1");
  Require(c.pbt_tiles_per_spe >= 0 && c.pbt_tiles_per_spe <= 4096,
          "pbt_tiles_per_spe must be 0..4096");
}

std::string DescribeConfig(const SimConfig& c) {
  const MemoryTiming& m = c.memory;
  std::string s;
  s += std::to_string(c.num_spes) + " SPEs at " + std::to_string(c.clock_hz / 1e9).substr(0, 4) +
       " GHz, LS " + std::to_string(c.local_store_bytes / 1024) + " KiB (" +
       std::to_string(c.code_stack_bytes / 1024) + " KiB code+stack); ";
  s += "DMA issue " + std::to_string(m.dma_issue_cycles) + " + latency " +
       std::to_string(m.dma_latency_cycles) + " cycles, " + std::to_string(m.mfc_bus_slots) +
       " bus slot(s), queue " + std::to_string(m.mfc_queue_depth) + ", MIC " +
       std::to_string(m.mic_line_cycles) + " cycles/line; atomic latency " +
       std::to_string(m.atomic_latency_cycles) + ", cache " + std::to_string(m.atomic_cache_lines) +
       " lines; ";
  s += "SW cache " + std::to_string(c.sw_cache.sets) + "x" + std::to_string(c.sw_cache.ways) + "x" +
       std::to_string(c.sw_cache.line_bytes) + " B, hit " + std::to_string(c.sw_cache.hit_cycles) +
       "; ";
  s += "pipeline " + std::to_string(c.rays_per_iteration) + " rays, micro-cache " +
       (c.micro_cache ? "on" : "off") + ", secondary rays at once " +
       (c.secondary_at_once ? "on" : "off") + ", DDA step " + std::to_string(c.costs.dda_step) +
       " cycles";
  return s;
}

}  // namespace rs::sim
