// The SPE ray pipeline (see spe.h). Everything the program reads about the scene comes out of its
// local store, filled by DMA (triangles, cell records, hit data, lights, occupancy bits) or by
// the software cache (materials, texels); the program holds main-memory addresses only as
// integers. The per-ray maths is raystream's: DdaBegin/DdaAdvance/DdaStep mirror the reference
// DDA, IntersectWatertightPermuted tests the triangles, GeneratePrimaryRays and rs::Shade make
// and shade the rays, so the image is the serial backend's bit for bit. The image leaves the SPE
// the way it would on a Cell: contributions are added, as the framebuffer's 64-bit fixed-point
// values, into the sub-tile's pixel buffer in LS, which a DMA list puts into the main-memory
// pixel image when the sub-tile's last ray is done.
#include "sim/spe.h"

#include <algorithm>
#include <cstring>
#include <iterator>
#include <limits>
#include <span>
#include <string>
#include <type_traits>

#include "scenes/scene.h"
#include "sched/framebuffer.h"
#include "sim/aligned_buffer.h"
#include "sim/cell_image.h"
#include "sim/spe_dda.h"
#include "streams/ray_stream.h"
#include "streams/raygen.h"

namespace rs::sim {
namespace {

// DMA tag plan: 0..7 triangle buffers (one per ray in flight), 8..15 hit data, then the rest.
constexpr uint32_t kHitTagBase = 8;
constexpr uint32_t kSetupTag = 16;
constexpr uint32_t kSpillTag = 17;
constexpr uint32_t kChunkTag = 18;
constexpr uint32_t kTileTag = 19;
constexpr uint32_t kPixelTagBase = 20;  // + pixel buffer (< 8)
constexpr int kMaxInFlight = 8;
static_assert(std::size(SpeCounters{}.iterations_by_rays) == kMaxInFlight + 1);
constexpr int32_t kShadowKind = static_cast<int32_t>(RayKind::kShadow);
constexpr int32_t kPrimaryKind = static_cast<int32_t>(RayKind::kPrimary);
constexpr uint32_t kBundleBytes = sizeof(TriangleBundle);

static_assert(std::is_trivially_copyable_v<FrameConstants>);
static_assert(std::is_trivially_copyable_v<RayRecord>);

enum class Phase {
  kStart,
  kRefill,
  kTileGetllar,
  kTilePutllc,
  kTraverse,
  kVisit,
  kShade,
  kFinish,
  kDone
};

enum class Flight : uint8_t {
  kVisit,           // waiting for its cell's triangles
  kContinue,        // written back into the ring buffer
  kDoneMiss,        // closest-hit ray that hit nothing
  kDoneHit,         // closest-hit ray with a hit (hit data requested)
  kDoneOccluded,    // shadow ray blocked
  kDoneUnoccluded,  // shadow ray reached its light
};

struct FlightInfo {
  Flight status = Flight::kVisit;
  int slot = 0;                // triangle buffer holding this ray's leaf (its own or a sharer's)
  bool leaf_load = false;      // the pending atomic load is a leaf record (else a cell record)
  uint32_t record_offset = 0;  // of the record inside its atomic line
  // Owner of a triangle buffer (slot == this ray):
  uint32_t leaf = UINT32_MAX;  // leaf whose triangles are (being) loaded into the buffer
  uint32_t first_bundle = 0;
  uint32_t count = 0;
  bool refined_top = false;  // its top-level cell turned out refined (sharers re-resolve)
  Lsa sub_lsa = 0;           // LS line holding the SubGridRecord of the ray's sub-grid
  int32_t tile = -1;         // tile the ray belongs to, for the tile times
  uint32_t pixel = 0;        // its image pixel, for the cost map's block work
};

struct PixelSlot {
  bool busy = false;      // a sub-tile is being rendered into it
  bool draining = false;  // its write-back DMA may still be in flight
  Tile rect;
  int32_t tile = -1;
  uint32_t next = 0;  // primaries generated so far
  uint32_t total = 0;
  int64_t outstanding = 0;  // rays of the sub-tile not yet finished
};

struct MicroCacheEntry {
  uint32_t cell;
  int slot;
};

// A unit (leaf) whose triangles are whole in a triangle buffer after this iteration's visits:
// the units secondary rays can be intersected with at once (paper 3.7). A sub-cell leaf also
// names the LS line holding its sub-grid's record.
struct LoadedUnit {
  uint32_t leaf;
  uint32_t count;       // triangles (all in the buffer)
  int slot;             // triangle buffer
  uint32_t top;         // top-level cell the leaf lies in
  uint32_t sub_record;  // its SubGridRecord index (sub-cell leaves only)
  Lsa sub_lsa;          // 0: a top-level cell; else the LS line of that record
};

// How far a secondary ray got at once.
enum class AtOnce : uint8_t {
  kResume,      // written back mid-traversal (or fresh set up) at a unit not loaded
  kTraced,      // closest-hit ray whose traversal ended: only shading is left
  kOccluded,    // shadow ray blocked
  kUnoccluded,  // shadow ray reached its light
};

}  // namespace

void SpeCounters::Merge(const SpeCounters& o) {
  for (int k = 0; k < kNumRayKinds; ++k) rays[k] += o.rays[k];
  hits += o.hits;
  occluded += o.occluded;
  cell_steps += o.cell_steps;
  visits += o.visits;
  bundles += o.bundles;
  triangle_tests += o.triangle_tests;
  micro_cache_hits += o.micro_cache_hits;
  cell_loads += o.cell_loads;
  chunk_loads += o.chunk_loads;
  hit_loads += o.hit_loads;
  subgrid_loads += o.subgrid_loads;
  iterations += o.iterations;
  rays_in_flight += o.rays_in_flight;
  for (int k = 0; k <= kMaxInFlight; ++k) iterations_by_rays[k] += o.iterations_by_rays[k];
  tiles += o.tiles;
  subtiles += o.subtiles;
  tile_counter_retries += o.tile_counter_retries;
  spilled_rays += o.spilled_rays;
  texture_fetches += o.texture_fetches;
  at_once_tested += o.at_once_tested;
  at_once_resolved += o.at_once_resolved;
  at_once_visits += o.at_once_visits;
  startup_cycles += o.startup_cycles;
  tail_cycles += o.tail_cycles;
  shade.Merge(o.shade);
}

uint64_t SpeCounters::TotalRays() const {
  uint64_t n = 0;
  for (const uint64_t r : rays) n += r;
  return n;
}

struct Spe::Impl {
  Impl(int spe, Machine& m, Ea constants, const FrameOutputs& outputs)
      : id(spe),
        machine(m),
        config(m.config),
        costs(m.config.costs),
        constants_ea(constants),
        out(outputs),
        ls(m.config.local_store_bytes, spe),
        mfc(spe, ls, m.memory, m.mic, clock, m.config.memory),
        atomic(spe, ls, m.memory, m.mic, m.atomic, clock, m.config.memory) {}

  void Compute(uint64_t cycles) { clock.Charge(Cost::kCompute, cycles); }
  RayRecord& FlightRecord(int r) { return *ls.As<RayRecord>(flight_lsa + uint32_t(r) * 128); }
  RayRecord& RingRecord(uint32_t i) { return *ls.As<RayRecord>(ring_lsa + i * 128); }
  RayRecord& StagingRecord(uint32_t i) { return *ls.As<RayRecord>(staging_lsa + i * 128); }

  void Step();
  void Start();
  void Refill();
  void TileGetllar();
  void TilePutllc();
  void TakeTile(uint32_t index);
  bool OpenSubtile();
  void GeneratePrimaries(int slot);
  void PushRay(const RayRecord& rec);
  void FlushStaging();
  void FetchSpillBlock();
  void Traverse();
  void AtomicSync(Lsa ls, Ea ea);
  const SubGridRecord& LoadSubGrid(int r, uint32_t index);
  void RequestUnit(int r, uint32_t key, bool leaf);
  void CompleteCellLoad(int q);
  bool ResolveSharedRefined(int r);
  void AfterUnit(int r);
  void LoadTriangles(int q, const CellRecord& cr, uint32_t leaf);
  void FinishTraversal(int r);
  void Visit();
  void RegisterLoaded(int s, const RayRecord& visitor, Lsa visitor_sub_lsa);
  const SubGridRecord* LoadedSubGrid(uint32_t top, uint32_t* index) const;
  AtOnce TraceAtOnce(RayRecord& rec, bool* tested);
  void Shade();
  void AddContribution(int slot, uint32_t pixel, float r, float g, float b);
  void AddFixed(int slot, uint32_t pixel, const int64_t* sums);
  void RetireSubtiles();
  void Finish();
  glm::vec3 SampleTextureCached(const MaterialRecord& m, glm::vec2 uv);
  glm::vec3 Texel(const MaterialRecord& m, int tx, int ty);

  const int id;
  Machine& machine;
  const SimConfig& config;
  const ComputeCosts& costs;
  const Ea constants_ea;
  FrameOutputs out;
  LocalStore ls;
  SpuClock clock;
  Mfc mfc;
  AtomicUnit atomic;
  std::unique_ptr<SoftwareCache> cache;
  Phase phase = Phase::kStart;

  // Local-store layout.
  Lsa fc_lsa = 0, lights_lsa = 0, occ_lsa = 0, ring_lsa = 0, flight_lsa = 0, staging_lsa = 0;
  Lsa tri_lsa = 0, record_lsa = 0, sub_lsa = 0, tile_line_lsa = 0, tile_rec_lsa = 0, hit_lsa = 0;
  Lsa pixel_lsa = 0, list_lsa = 0, status_lsa = 0;
  uint32_t tri_slot_bytes = 0, pixel_slot_bytes = 0, list_slot_bytes = 0;
  uint32_t elements_per_row = 1;
  FrameConstants fc{};                  // the LS copy, in "registers"
  const uint64_t* occupancy = nullptr;  // LS

  // Ray buffer (FIFO ring in LS), staging block and blocks spilled to main memory.
  uint32_t ring_head = 0, ring_count = 0;
  uint32_t staging_count = 0;
  bool staging_put_pending = false;
  std::vector<std::unique_ptr<AlignedBuffer>> spill_blocks;
  std::vector<Ea> spill_ea;  // per block: its EA
  std::vector<size_t> spill_used, spill_free;

  // Tiles.
  bool tiles_exhausted = false;
  bool tile_active = false;
  Tile tile;
  int32_t tile_index = -1;
  int sub_x = 0, sub_y = 0, sub_w = 1, sub_h = 1;
  std::vector<PixelSlot> pixel_slots;
  int gen_slot = -1;
  // Contributions dropped (NaN) or clamped on their way into the pixel buffers ("registers",
  // reported through the status record at the end).
  uint64_t dropped_nan = 0, clamped = 0, pixels_written = 0;
  uint64_t tail_start = 0;  // clock at the start of the last, empty refill

  // The current iteration.
  bool in_iteration = false;
  uint64_t iteration_start = 0;
  int n = 0;
  int cursor = 0;
  int pending_atomic = -1;
  int visited = 0;  // rays visited so far in this iteration
  FlightInfo flight[kMaxInFlight];
  MicroCacheEntry micro_cache[kMaxInFlight];
  int micro_cache_size = 0;
  LoadedUnit loaded[kMaxInFlight];
  int loaded_count = 0;

  // Shading scratch ("registers" and stack of the shader). rs::Shade reads shade_scene, a view
  // of the arrays below (copied out of LS: the hit triangles' records, their materials, the
  // lights), and emits each batch ray's contribution with pixel id i for batch ray i (the rays'
  // pixel ids are their batch indices while they are shaded); the contributions then go into
  // the LS pixel buffers with the framebuffer's fixed-point add (AddContribution).
  ShadeScene shade_scene;
  glm::vec3 shade_positions[3 * kMaxInFlight];
  glm::vec3 shade_normals[3 * kMaxInFlight];
  glm::uvec3 shade_triangles[kMaxInFlight];
  uint32_t shade_material_ids[kMaxInFlight] = {};
  Material shade_materials[kMaxInFlight];
  std::vector<PointLight> shade_lights;
  ContributionStream shade_contributions;
  RayStream shade_rays;
  HitStream shade_hits;
  RayStream secondary;
  RayStream primaries;
  uint32_t batch_pixel[kMaxInFlight] = {};
  uint16_t batch_subtile[kMaxInFlight] = {};

  SpeCounters counters;
};

void Spe::Impl::Step() {
  switch (phase) {
    case Phase::kStart:
      Start();
      break;
    case Phase::kRefill:
      Refill();
      break;
    case Phase::kTileGetllar:
      TileGetllar();
      break;
    case Phase::kTilePutllc:
      TilePutllc();
      break;
    case Phase::kTraverse:
      Traverse();
      break;
    case Phase::kVisit:
      Visit();
      break;
    case Phase::kShade:
      Shade();
      break;
    case Phase::kFinish:
      Finish();
      break;
    case Phase::kDone:
      break;
  }
}

namespace {

// The LS layout of the pipeline's buffers, in allocation order; the occupancy bits come last.
struct LsLayout {
  Lsa fc = 0, ring = 0, flight = 0, staging = 0, tri = 0, record = 0, sub = 0, tile_line = 0;
  Lsa tile_rec = 0, hit = 0, pixel = 0, list = 0, status = 0, lights = 0;
  uint32_t tri_slot_bytes = 0, pixel_slot_bytes = 0, list_slot_bytes = 0, elements_per_row = 1;
};

LsLayout LayOut(const SimConfig& config, LocalStore& ls, Mfc& mfc, SpuClock& clock,
                uint32_t num_lights, int image_width, bool two_level,
                std::unique_ptr<SoftwareCache>* cache) {
  LsLayout l;
  ls.Allocate("code and stack", config.code_stack_bytes, 16);
  l.fc = ls.Allocate("frame constants", sizeof(FrameConstants), 128);
  const uint32_t rays = static_cast<uint32_t>(config.rays_per_iteration);
  l.ring = ls.Allocate("ray ring buffer", uint64_t{config.ring_rays} * 128, 128);
  l.flight = ls.Allocate("rays in flight", uint64_t{rays} * 128, 128);
  l.staging = ls.Allocate("ray staging block", uint64_t{config.staging_rays} * 128, 128);
  l.tri_slot_bytes = config.triangle_buffer_bundles * kBundleBytes;
  l.tri = ls.Allocate("triangle buffers", uint64_t{rays} * l.tri_slot_bytes, 128);
  l.record = ls.Allocate("cell record lines", uint64_t{rays} * 128, 128);
  if (two_level) l.sub = ls.Allocate("sub-grid record lines", uint64_t{rays} * 128, 128);
  l.tile_line = ls.Allocate("tile counter line", 128, 128);
  l.tile_rec = ls.Allocate("tile record", sizeof(Tile), 16);
  l.hit = ls.Allocate("hit data", uint64_t{rays} * sizeof(ShadingRecord), 128);
  *cache = std::make_unique<SoftwareCache>(config.sw_cache, ls, mfc, clock);
  l.pixel_slot_bytes = config.pixel_buffer_pixels * uint32_t{sizeof(PixelSums)};
  l.pixel = ls.Allocate("pixel buffers", uint64_t(config.pixel_buffers) * l.pixel_slot_bytes, 128);
  const uint32_t row_px = std::min<uint32_t>(config.pixel_buffer_pixels,
                                             static_cast<uint32_t>(std::max(image_width, 1)));
  l.elements_per_row = (row_px * uint32_t{sizeof(PixelSums)} + kMaxDmaSize - 1) / kMaxDmaSize;
  l.list_slot_bytes = config.max_subtile_rows * l.elements_per_row * 8;
  l.list = ls.Allocate("DMA lists", uint64_t(config.pixel_buffers) * l.list_slot_bytes, 16);
  l.status = ls.Allocate("status record", sizeof(SpeStatus), 128);
  if (num_lights > 0) {
    l.lights = ls.Allocate("lights (" + std::to_string(num_lights) + ")",
                           uint64_t{num_lights} * sizeof(LightRecord), 128);
  }
  return l;
}

}  // namespace

uint64_t OccupancyBudgetCells(const SimConfig& config, uint32_t num_lights, int image_width,
                              bool two_level) {
  ValidateConfig(config);
  LocalStore ls(config.local_store_bytes, 0);
  MainMemory memory;
  MemoryController mic(config.memory.mic_line_cycles);
  SpuClock clock;
  Mfc mfc(0, ls, memory, mic, clock, config.memory);
  std::unique_ptr<SoftwareCache> cache;
  LayOut(config, ls, mfc, clock, num_lights, image_width, two_level, &cache);
  const uint32_t start = (ls.used() + 127) & ~127u;
  return start >= ls.size() ? 0 : uint64_t{ls.size() - start} / 128 * 128 * 8;
}

void Spe::Impl::Start() {
  // Fixed buffers first, the occupancy bits last: a grid too large for what is left is refused
  // with a message naming the bits. The frame constants come first (their DMA tells the sizes).
  {
    LocalStore probe(config.local_store_bytes, id);
    probe.Allocate("code and stack", config.code_stack_bytes, 16);
    const Lsa at = probe.Allocate("frame constants", sizeof(FrameConstants), 128);
    mfc.MfcGet(at, constants_ea, sizeof(FrameConstants), kSetupTag);
    mfc.WaitTagsAll(1u << kSetupTag);
    std::memcpy(&fc, ls.Bytes(at, sizeof(FrameConstants)), sizeof(FrameConstants));
  }
  const LsLayout l =
      LayOut(config, ls, mfc, clock, fc.num_lights, fc.image_width, fc.grid.two_level != 0, &cache);
  fc_lsa = l.fc;
  ring_lsa = l.ring;
  flight_lsa = l.flight;
  staging_lsa = l.staging;
  tri_lsa = l.tri;
  record_lsa = l.record;
  sub_lsa = l.sub;
  tile_line_lsa = l.tile_line;
  tile_rec_lsa = l.tile_rec;
  hit_lsa = l.hit;
  pixel_lsa = l.pixel;
  list_lsa = l.list;
  status_lsa = l.status;
  lights_lsa = l.lights;
  tri_slot_bytes = l.tri_slot_bytes;
  pixel_slot_bytes = l.pixel_slot_bytes;
  list_slot_bytes = l.list_slot_bytes;
  elements_per_row = l.elements_per_row;
  if (fc.num_lights > 0) {
    const uint64_t bytes = uint64_t{fc.num_lights} * sizeof(LightRecord);
    for (uint64_t off = 0; off < bytes; off += kMaxDmaSize) {
      const uint32_t size = static_cast<uint32_t>(std::min<uint64_t>(kMaxDmaSize, bytes - off));
      mfc.MfcGet(lights_lsa + uint32_t(off), fc.lights + off, size, kSetupTag);
    }
  }
  if (fc.grid.empty == 0) {
    const std::string what = "occupancy bits of the " + std::to_string(fc.grid.res[0]) + "x" +
                             std::to_string(fc.grid.res[1]) + "x" + std::to_string(fc.grid.res[2]) +
                             " grid (" + std::to_string(fc.grid.num_cells) + " cells)";
    occ_lsa = ls.Allocate(what, fc.occupancy_bytes, 128);
    for (uint64_t off = 0; off < fc.occupancy_bytes; off += kMaxDmaSize) {
      const uint32_t size =
          static_cast<uint32_t>(std::min<uint64_t>(kMaxDmaSize, fc.occupancy_bytes - off));
      mfc.MfcGet(occ_lsa + uint32_t(off), fc.occupancy + off, size, kSetupTag);
    }
  }
  mfc.WaitTagsAll(1u << kSetupTag);
  occupancy = ls.As<uint64_t>(occ_lsa, std::max<uint64_t>(fc.occupancy_bytes / 8, 1));

  // The shader's view of the scene constants, from LS.
  shade_scene = ShadeScene{};
  shade_scene.features = fc.features;
  shade_scene.background = glm::vec3(fc.background[0], fc.background[1], fc.background[2]);
  shade_scene.ambient = fc.ambient;
  shade_lights.resize(fc.num_lights);
  for (uint32_t i = 0; i < fc.num_lights; ++i) {
    LightRecord lr;
    std::memcpy(&lr, ls.Bytes(lights_lsa + i * sizeof(LightRecord), sizeof(lr)), sizeof(lr));
    PointLight& l = shade_lights[i];
    l.position = glm::vec3(lr.position[0], lr.position[1], lr.position[2]);
    l.color = glm::vec3(lr.color[0], lr.color[1], lr.color[2]);
    l.falloff = lr.falloff;
  }
  shade_scene.lights = shade_lights;
  // No UVs and no textures: Shade never samples; texels come through the software cache and
  // are folded into each hit's diffuse colour before the call (Spe::Impl::Shade).
  shade_contributions.Reserve(kMaxInFlight + kStreamPad);  // Shade never reallocates it
  shade_rays.Reserve(kMaxInFlight);
  shade_hits.Reserve(kMaxInFlight);
  primaries.Reserve(kMaxInFlight);
  pixel_slots.assign(static_cast<size_t>(config.pixel_buffers), PixelSlot{});
  counters.startup_cycles = clock.now();  // the program started at cycle 0
  phase = Phase::kRefill;
}

void Spe::Impl::Refill() {
  if (!in_iteration) {
    in_iteration = true;
    iteration_start = clock.now();
    Compute(costs.iteration);
    RetireSubtiles();
  }
  const uint32_t want = static_cast<uint32_t>(config.rays_per_iteration);
  // Secondary rays that overflowed the ring come back first (bounded memory).
  while (ring_count < want && (staging_count > 0 || !spill_used.empty())) {
    if (staging_count == 0) FetchSpillBlock();
    const uint32_t move = std::min(staging_count, config.ring_rays - ring_count);
    for (uint32_t i = 0; i < move; ++i) {
      const RayRecord& rec = StagingRecord(--staging_count);
      std::memcpy(&RingRecord((ring_head + ring_count) % config.ring_rays), &rec, 128);
      ++ring_count;
      Compute(costs.ray_copy);
    }
  }
  // Fewer than 8 rays: new primary rays (paper 3.2).
  while (ring_count < want) {
    if (gen_slot >= 0) {
      GeneratePrimaries(gen_slot);
      continue;
    }
    if (tile_active && OpenSubtile()) continue;
    if (tile_active) break;  // all pixel buffers busy: finish their rays first
    if (!tiles_exhausted) {
      phase = Phase::kTileGetllar;
      return;
    }
    break;
  }
  n = static_cast<int>(std::min(want, ring_count));
  if (config.drain_individually && ring_count < want && n > 1) n = 1;
  if (n == 0) {
    if (tile_active || gen_slot >= 0 || staging_count > 0 || !spill_used.empty()) {
      throw Error("SPE " + std::to_string(id) + ": ray pipeline stalled with work left");
    }
    in_iteration = false;
    tail_start = iteration_start;
    phase = Phase::kFinish;
    return;
  }
  for (int r = 0; r < n; ++r) {
    std::memcpy(&FlightRecord(r), &RingRecord(ring_head), 128);
    ring_head = (ring_head + 1) % config.ring_rays;
    --ring_count;
    Compute(costs.ray_copy);
    flight[r] = FlightInfo{};
    flight[r].tile = pixel_slots[FlightRecord(r).subtile].tile;
    flight[r].pixel = FlightRecord(r).pixel;
  }
  micro_cache_size = 0;
  loaded_count = 0;
  pending_atomic = -1;
  cursor = 0;
  phase = Phase::kTraverse;
}

// The atomic tile counter (paper 3.9): getllar, +1, putllc; a failed putllc (another SPE took a
// tile in between) retries. The two halves run as separate steps so the scheduler orders them
// against the other SPEs' counter accesses in simulated time.
void Spe::Impl::TileGetllar() {
  atomic.Getllar(tile_line_lsa, fc.tile_counter);
  atomic.ReadStatus();
  phase = Phase::kTilePutllc;
}

void Spe::Impl::TilePutllc() {
  uint32_t* line = ls.As<uint32_t>(tile_line_lsa, 32);
  const uint32_t value = line[0];
  if (value >= fc.num_tiles) {
    tiles_exhausted = true;
    phase = Phase::kRefill;
    return;
  }
  line[0] = value + 1;
  atomic.Putllc(tile_line_lsa, fc.tile_counter);
  if ((atomic.ReadStatus() & kPutllcFailed) != 0) {
    ++counters.tile_counter_retries;
    phase = Phase::kTileGetllar;
    return;
  }
  TakeTile(value);
  phase = Phase::kRefill;
}

void Spe::Impl::TakeTile(uint32_t index) {
  Compute(costs.tile_setup);
  ++counters.tiles;
  if (fc.explicit_tiles != 0) {
    mfc.MfcGet(tile_rec_lsa, fc.tiles + uint64_t{index} * sizeof(Tile), sizeof(Tile), kTileTag);
    mfc.WaitTagsAll(1u << kTileTag);
    std::memcpy(&tile, ls.Bytes(tile_rec_lsa, sizeof(Tile)), sizeof(Tile));
  } else {
    const int tx = static_cast<int>(index % uint32_t(fc.tiles_x));
    const int ty = static_cast<int>(index / uint32_t(fc.tiles_x));
    tile.x0 = tx * fc.tile_width;
    tile.y0 = ty * fc.tile_height;
    tile.x1 = std::min(tile.x0 + fc.tile_width, fc.image_width);
    tile.y1 = std::min(tile.y0 + fc.tile_height, fc.image_height);
  }
  tile_index = static_cast<int32_t>(index);
  if (out.tile_spe != nullptr) (*out.tile_spe)[index] = id;
  const int w = tile.Width(), h = tile.Height();
  tile_active = w > 0 && h > 0;
  if (!tile_active) return;
  // Sub-tiles: whole rows of at most pixel_buffer_pixels pixels and max_subtile_rows rows.
  sub_w = std::min(w, static_cast<int>(config.pixel_buffer_pixels));
  sub_h = std::max(1, std::min({h, static_cast<int>(config.max_subtile_rows),
                                static_cast<int>(config.pixel_buffer_pixels) / sub_w}));
  sub_x = tile.x0;
  sub_y = tile.y0;
}

bool Spe::Impl::OpenSubtile() {
  if (sub_y >= tile.y1) {
    tile_active = false;
    return false;
  }
  int b = -1;
  for (int i = 0; i < static_cast<int>(pixel_slots.size()); ++i) {
    if (!pixel_slots[i].busy) {
      b = i;
      break;
    }
  }
  if (b < 0) return false;
  PixelSlot& s = pixel_slots[b];
  if (s.draining) {  // its previous contents must have left before new pixels go in
    mfc.WaitTagsAll(1u << (kPixelTagBase + uint32_t(b)));
    s.draining = false;
  }
  s.busy = true;
  s.rect = Tile{sub_x, sub_y, std::min(sub_x + sub_w, tile.x1), std::min(sub_y + sub_h, tile.y1)};
  s.tile = tile_index;
  s.next = 0;
  s.total = static_cast<uint32_t>(s.rect.NumPixels());
  s.outstanding = 0;
  sub_x += sub_w;
  if (sub_x >= tile.x1) {
    sub_x = tile.x0;
    sub_y += sub_h;
  }
  const uint64_t bytes = uint64_t{s.total} * sizeof(PixelSums);
  std::memset(ls.Bytes(pixel_lsa + uint32_t(b) * pixel_slot_bytes, bytes), 0, bytes);
  Compute(costs.iteration);
  ++counters.subtiles;
  gen_slot = b;
  return true;
}

// 8 rays in 4x2 blocks of the sub-tile (paper 3.9: "more efficient to generate 4x2 rays").
void Spe::Impl::GeneratePrimaries(int slot) {
  PixelSlot& s = pixel_slots[slot];
  const uint32_t count = std::min<uint32_t>(kMaxInFlight, s.total - s.next);
  primaries.Resize(count);
  const RayStreamView v = primaries.view();
  GeneratePrimaryRays(fc.camera, s.rect, RayOrder::kBlock4x2, s.next, count, v, 0);
  for (uint32_t i = 0; i < count; ++i) {
    RayRecord rec{};
    rec.o[0] = v.ox[i];
    rec.o[1] = v.oy[i];
    rec.o[2] = v.oz[i];
    rec.d[0] = v.dx[i];
    rec.d[1] = v.dy[i];
    rec.d[2] = v.dz[i];
    rec.tmin = v.tmin[i];
    rec.tmax = v.tmax[i];
    rec.pixel = v.pixel[i];
    rec.w[0] = v.wr[i];
    rec.w[1] = v.wg[i];
    rec.w[2] = v.wb[i];
    rec.depth = v.depth[i];
    rec.kind = v.kind[i];
    rec.subtile = static_cast<uint16_t>(slot);
    rec.state = kRayFresh;
    Compute(costs.primary_ray);
    PushRay(rec);
  }
  s.next += count;
  s.outstanding += count;
  if (s.next == s.total) gen_slot = -1;
}

void Spe::Impl::PushRay(const RayRecord& rec) {
  if (ring_count < config.ring_rays) {
    std::memcpy(&RingRecord((ring_head + ring_count) % config.ring_rays), &rec, 128);
    ++ring_count;
    Compute(costs.ray_copy);
    return;
  }
  if (staging_put_pending) {  // the staging block's previous contents are still going out
    mfc.WaitTagsAll(1u << kSpillTag);
    staging_put_pending = false;
  }
  std::memcpy(&StagingRecord(staging_count++), &rec, 128);
  Compute(costs.ray_copy);
  if (staging_count == config.staging_rays) FlushStaging();
}

void Spe::Impl::FlushStaging() {
  size_t block;
  if (spill_free.empty()) {
    // The PPE hands out spill memory on demand (main memory is not simulated for capacity).
    spill_blocks.push_back(std::make_unique<AlignedBuffer>(size_t{config.staging_rays} * 128));
    spill_ea.push_back(
        machine.memory.Register(spill_blocks.back()->data(), spill_blocks.back()->size(),
                                "SPE " + std::to_string(id) + " ray spill block", true));
    block = spill_blocks.size() - 1;
  } else {
    block = spill_free.back();
    spill_free.pop_back();
  }
  mfc.MfcPut(staging_lsa, spill_ea[block], config.staging_rays * 128, kSpillTag);
  staging_put_pending = true;
  spill_used.push_back(block);
  counters.spilled_rays += staging_count;
  staging_count = 0;
}

void Spe::Impl::FetchSpillBlock() {
  const size_t block = spill_used.back();
  spill_used.pop_back();
  if (staging_put_pending) {
    mfc.WaitTagsAll(1u << kSpillTag);
    staging_put_pending = false;
  }
  mfc.MfcGet(staging_lsa, spill_ea[block], config.staging_rays * 128, kSpillTag);
  mfc.WaitTagsAll(1u << kSpillTag);
  staging_count = config.staging_rays;
  spill_free.push_back(block);
}

// One ray of the iteration: DDA to the first occupied cell on the LS bits (Listing 1), or, inside
// a sub-grid, to the first occupied sub-cell; then the micro-cache or the unit's loads. The
// previous ray's atomic load completed while this one traversed; its triangles are requested now.
void Spe::Impl::Traverse() {
  const int r = cursor;
  RayRecord& rec = FlightRecord(r);
  bool at_cell;
  if (rec.state == kRayTraced) {  // traced at once by the shader (paper 3.7): shade it
    at_cell = false;
  } else if (rec.state == kRayFresh) {
    Compute(costs.ray_setup);
    at_cell = DdaBegin(fc.grid, rec);
  } else {
    Compute(costs.ray_resume);
    at_cell = true;
  }
  while (at_cell) {
    uint64_t steps = 0;
    if (rec.in_sub != 0) {  // resumed inside a sub-grid: its record again (atomic cache)
      const SubGridRecord& sg = LoadSubGrid(r, rec.sub_record);
      flight[r].sub_lsa = sub_lsa + uint32_t(r) * 128;
      uint32_t leaf = 0;
      const SubResult res = SubAdvance(sg, rec, fc.grid.shift, &steps, &leaf);
      Compute(steps * costs.dda_step + costs.dda_exit);
      counters.cell_steps += steps;
      if (res == SubResult::kOccupied) {
        RequestUnit(r, leaf, true);
        break;
      }
      if (res == SubResult::kDone || !DdaStep(fc.grid, rec, rec.t_exit)) {
        at_cell = false;
        break;
      }
      steps = 0;
    }
    at_cell = DdaAdvance(fc.grid, occupancy, rec, &steps);
    Compute(steps * costs.dda_step + costs.dda_exit);
    counters.cell_steps += steps;
    if (at_cell) RequestUnit(r, rec.idx, false);
    break;
  }
  if (!at_cell) FinishTraversal(r);
  if (++cursor == n) {
    cursor = 0;
    visited = 0;
    phase = Phase::kVisit;
  }
}

// A synchronous atomic load (the unit does one command at a time: a pending one completes first).
void Spe::Impl::AtomicSync(Lsa ls_line, Ea ea) {
  if (pending_atomic >= 0) CompleteCellLoad(pending_atomic);
  atomic.Getllar(ls_line, ea);
  atomic.ReadStatus();
}

const SubGridRecord& Spe::Impl::LoadSubGrid(int r, uint32_t index) {
  const Lsa line = sub_lsa + uint32_t(r) * 128;
  AtomicSync(line, fc.subgrids + uint64_t{index} * sizeof(SubGridRecord));
  ++counters.subgrid_loads;
  return *ls.As<const SubGridRecord>(line);
}

// The ray is at an occupied unit: a top-level cell (key = cell index, which is also its leaf id
// unless the cell turns out refined) or a sub-cell (key = its leaf id). A unit already loaded in
// this iteration is shared (micro-cache, paper 3.5); otherwise its record is requested with an
// asynchronous 128-B atomic load (paper 3.4).
void Spe::Impl::RequestUnit(int r, uint32_t key, bool leaf) {
  FlightInfo& f = flight[r];
  f.status = Flight::kVisit;
  if (config.micro_cache) {
    Compute(costs.micro_cache_lookup);
    for (int e = 0; e < micro_cache_size; ++e) {
      if (micro_cache[e].cell == key) {
        f.slot = micro_cache[e].slot;
        ++counters.micro_cache_hits;
        return;
      }
    }
  }
  f.slot = r;
  if (config.micro_cache && micro_cache_size < kMaxInFlight) {
    micro_cache[micro_cache_size++] = MicroCacheEntry{key, r};
  }
  if (pending_atomic >= 0) CompleteCellLoad(pending_atomic);
  const Ea ea = leaf ? fc.leaf_records + (uint64_t{key} - fc.grid.num_cells) * sizeof(CellRecord)
                     : fc.cell_records + uint64_t{key} * sizeof(CellRecord);
  f.leaf_load = leaf;
  f.leaf = leaf ? key : UINT32_MAX;
  f.record_offset = static_cast<uint32_t>(ea & 127);
  atomic.Getllar(record_lsa + uint32_t(r) * 128, ea & ~Ea{127});
  pending_atomic = r;
}

void Spe::Impl::LoadTriangles(int q, const CellRecord& cr, uint32_t leaf) {
  FlightInfo& f = flight[q];
  f.leaf = leaf;
  f.first_bundle = cr.first_bundle;
  f.count = cr.count;
  const uint32_t bundles = std::min((cr.count + 3) / 4, config.triangle_buffer_bundles);
  if (bundles > 0) {
    mfc.MfcGet(tri_lsa + uint32_t(q) * tri_slot_bytes,
               fc.bundles + uint64_t{cr.first_bundle} * kBundleBytes, bundles * kBundleBytes,
               uint32_t(q));
  }
  ++counters.cell_loads;
}

// The pending record arrived: request the leaf's triangles. A refined top-level cell first loads
// its sub-grid record (the second 128-B load of paper 3.8) and walks it to the first occupied
// sub-cell, whose leaf record follows (both dependent, hence synchronous).
void Spe::Impl::CompleteCellLoad(int q) {
  pending_atomic = -1;
  atomic.ReadStatus();
  FlightInfo& f = flight[q];
  CellRecord cr;
  std::memcpy(&cr, ls.Bytes(record_lsa + uint32_t(q) * 128 + f.record_offset, 8), 8);
  RayRecord& rec = FlightRecord(q);
  if (f.leaf_load || cr.count != kRefinedCell) {
    LoadTriangles(q, cr, f.leaf_load ? f.leaf : rec.idx);
    return;
  }
  f.refined_top = true;
  rec.sub_record = cr.first_bundle;
  const SubGridRecord& sg = LoadSubGrid(q, rec.sub_record);
  f.sub_lsa = sub_lsa + uint32_t(q) * 128;
  SubInit(sg, rec, fc.grid.shift);
  uint64_t steps = 0;
  uint32_t leaf = 0;
  const SubResult res = SubAdvance(sg, rec, fc.grid.shift, &steps, &leaf);
  Compute(steps * costs.dda_step + costs.dda_exit);
  counters.cell_steps += steps;
  if (res != SubResult::kOccupied) {
    f.leaf = UINT32_MAX;
    if (res == SubResult::kLeft && DdaStep(fc.grid, rec, rec.t_exit)) {
      f.status = Flight::kContinue;
      PushRay(rec);
    } else {
      FinishTraversal(q);
    }
    return;
  }
  // Re-key this buffer's micro-cache entry to the leaf it will hold.
  for (int e = 0; e < micro_cache_size; ++e) {
    if (micro_cache[e].slot == q) micro_cache[e].cell = leaf;
  }
  const Ea ea = fc.leaf_records + (uint64_t{leaf} - fc.grid.num_cells) * sizeof(CellRecord);
  AtomicSync(record_lsa + uint32_t(q) * 128, ea & ~Ea{127});
  std::memcpy(&cr, ls.Bytes(record_lsa + uint32_t(q) * 128 + uint32_t(ea & 127), 8), 8);
  LoadTriangles(q, cr, leaf);
}

// A ray that shared a top-level cell with the ray that loaded it, which turned out refined: it
// walks the sub-grid itself (the record is already in the owner's LS line) and uses the owner's
// buffer if it reaches the same sub-cell, else loads its own (synchronously). Returns false if
// the ray has nothing to visit (finished or written back).
bool Spe::Impl::ResolveSharedRefined(int r) {
  FlightInfo& f = flight[r];
  const int s = f.slot;
  RayRecord& rec = FlightRecord(r);
  const SubGridRecord& sg = *ls.As<const SubGridRecord>(flight[s].sub_lsa);
  rec.sub_record = FlightRecord(s).sub_record;
  f.sub_lsa = flight[s].sub_lsa;
  SubInit(sg, rec, fc.grid.shift);
  uint64_t steps = 0;
  uint32_t leaf = 0;
  const SubResult res = SubAdvance(sg, rec, fc.grid.shift, &steps, &leaf);
  Compute(steps * costs.dda_step + costs.dda_exit);
  counters.cell_steps += steps;
  if (res != SubResult::kOccupied) {
    if (res == SubResult::kLeft && DdaStep(fc.grid, rec, rec.t_exit)) {
      f.status = Flight::kContinue;
      PushRay(rec);
    } else {
      FinishTraversal(r);
    }
    return false;
  }
  if (flight[s].leaf == leaf) {
    ++counters.micro_cache_hits;
    return true;
  }
  f.slot = r;
  const Ea ea = fc.leaf_records + (uint64_t{leaf} - fc.grid.num_cells) * sizeof(CellRecord);
  AtomicSync(record_lsa + uint32_t(r) * 128, ea & ~Ea{127});
  CellRecord cr;
  std::memcpy(&cr, ls.Bytes(record_lsa + uint32_t(r) * 128 + uint32_t(ea & 127), 8), 8);
  LoadTriangles(r, cr, leaf);
  return true;
}

void Spe::Impl::FinishTraversal(int r) {
  RayRecord& rec = FlightRecord(r);
  FlightInfo& f = flight[r];
  if (rec.kind == kShadowKind) {
    f.status = Flight::kDoneUnoccluded;
  } else if (rec.best_prim != UINT32_MAX) {
    f.status = Flight::kDoneHit;
    // Hit data (vertices, normals, UVs, material id) arrives while the others are visited.
    mfc.MfcGet(hit_lsa + uint32_t(r) * sizeof(ShadingRecord),
               fc.shading + uint64_t{rec.best_prim} * sizeof(ShadingRecord), sizeof(ShadingRecord),
               kHitTagBase + uint32_t(r));
    ++counters.hit_loads;
  } else {
    f.status = Flight::kDoneMiss;
  }
}

// VisitVoxel for one ray: wait for its cell's triangles, 1 ray x 4 triangles per bundle, then
// finish the ray or write it back into the ring buffer.
void Spe::Impl::Visit() {
  while (cursor < n && flight[cursor].status != Flight::kVisit) ++cursor;
  if (cursor == n) {
    cursor = 0;
    phase = Phase::kShade;
    return;
  }
  // The last requested record arrives while the first ray is visited (its triangles came long
  // ago), unless this ray needs it.
  if (pending_atomic >= 0 && (visited > 0 || flight[cursor].slot == pending_atomic)) {
    CompleteCellLoad(pending_atomic);
    if (flight[cursor].status != Flight::kVisit) return;  // refined cell: finished or written back
  }
  ++visited;
  const int r = cursor++;
  RayRecord& rec = FlightRecord(r);
  if (flight[r].slot != r && flight[flight[r].slot].refined_top && rec.in_sub == 0 &&
      !ResolveSharedRefined(r)) {
    return;
  }
  const int s = flight[r].slot;
  const FlightInfo& owner = flight[s];
  mfc.WaitTagsAll(1u << uint32_t(s));
  Compute(costs.visit_setup);
  ++counters.visits;
  const WatertightRay wr =
      PrepareWatertightRay(rec.o[0] - fc.grid.shift[0], rec.o[1] - fc.grid.shift[1],
                           rec.o[2] - fc.grid.shift[2], rec.d[0], rec.d[1], rec.d[2]);
  const bool shadow = rec.kind == kShadowKind;
  const uint32_t bundles = (owner.count + 3) / 4;
  const uint32_t cap = config.triangle_buffer_bundles;
  const Lsa slot_lsa = tri_lsa + uint32_t(s) * tri_slot_bytes;
  if (config.secondary_at_once && bundles <= cap) RegisterLoaded(s, rec, flight[r].sub_lsa);
  bool found = false;
  uint64_t tested = 0;
  for (uint32_t p0 = 0; p0 < bundles; p0 += cap) {
    const uint32_t chunk = std::min(cap, bundles - p0);
    // A cell larger than the buffer streams through it; only the owner's first chunk came with
    // the asynchronous load (a micro-cache sharer finds the owner's last chunk there).
    if (bundles > cap && !(p0 == 0 && r == s)) {
      mfc.MfcGet(slot_lsa, fc.bundles + uint64_t{owner.first_bundle + p0} * kBundleBytes,
                 chunk * kBundleBytes, kChunkTag);
      mfc.WaitTagsAll(1u << kChunkTag);
      ++counters.chunk_loads;
    }
    const TriangleBundle* tp = ls.As<const TriangleBundle>(slot_lsa, chunk);
    tested += chunk;
    if (shadow) {
      found = IntersectBundles<true>(wr, tp, chunk, rec, &counters.triangle_tests);
      if (found) break;
    } else {
      IntersectBundles<false>(wr, tp, chunk, rec, &counters.triangle_tests);
    }
  }
  Compute(tested * costs.triangle_bundle);
  counters.bundles += tested;
  if (shadow && found) {
    flight[r].status = Flight::kDoneOccluded;
    return;
  }
  AfterUnit(r);
}

// After a visited unit: the reference's stop test and step, in the sub-grid (back to the top
// level when the ray leaves it) or in the top level. The ray finishes or goes back to the ring.
void Spe::Impl::AfterUnit(int r) {
  RayRecord& rec = FlightRecord(r);
  FlightInfo& f = flight[r];
  bool more;
  if (rec.in_sub != 0) {
    const SubResult res = SubStep(*ls.As<const SubGridRecord>(f.sub_lsa), rec, fc.grid.shift);
    more = res == SubResult::kOccupied ||
           (res == SubResult::kLeft && DdaStep(fc.grid, rec, rec.t_exit));
  } else {
    more = DdaStep(fc.grid, rec, rec.t_exit);
  }
  if (more) {
    f.status = Flight::kContinue;
    PushRay(rec);
  } else {
    FinishTraversal(r);
  }
}

// Notes that triangle buffer `s` holds its unit whole (its DMA has completed), as `visitor`
// (a ray visiting it, so at that unit) saw it.
void Spe::Impl::RegisterLoaded(int s, const RayRecord& visitor, Lsa visitor_sub_lsa) {
  for (int e = 0; e < loaded_count; ++e) {
    if (loaded[e].slot == s) return;
  }
  LoadedUnit& u = loaded[loaded_count++];
  u.leaf = flight[s].leaf;
  u.count = flight[s].count;
  u.slot = s;
  u.top = visitor.idx;
  u.sub_record = visitor.in_sub != 0 ? visitor.sub_record : 0;
  u.sub_lsa = visitor.in_sub != 0 ? visitor_sub_lsa : 0;
}

// The sub-grid record of refined top-level cell `top` if a loaded unit lies in it (its LS line
// still holds it: lines are only rewritten before the visits), else nullptr.
const SubGridRecord* Spe::Impl::LoadedSubGrid(uint32_t top, uint32_t* index) const {
  for (int e = 0; e < loaded_count; ++e) {
    const LoadedUnit& u = loaded[e];
    if (u.sub_lsa == 0 || u.top != top) continue;
    const SubGridRecord* sg = ls.As<const SubGridRecord>(u.sub_lsa);
    if (sg->parent != top) continue;
    *index = u.sub_record;
    return sg;
  }
  return nullptr;
}

// Paper 3.7: a secondary ray just spawned is set up and walked, with the pipeline's own DDA,
// triangle test and stop rule (so the image stays the serial backend's), through the units
// whose triangles are still whole in the triangle buffers. It stops at the first unit that is
// not loaded, left in the state the pipeline resumes from (that unit not yet examined), or
// when it is finished. *tested: at least one unit was intersected.
AtOnce Spe::Impl::TraceAtOnce(RayRecord& rec, bool* tested) {
  const bool shadow = rec.kind == kShadowKind;
  const AtOnce finished = shadow ? AtOnce::kUnoccluded : AtOnce::kTraced;
  *tested = false;
  Compute(costs.ray_setup);
  if (!DdaBegin(fc.grid, rec)) return finished;
  const SubGridRecord* sg = nullptr;  // while rec.in_sub
  WatertightRay wr{};
  for (;;) {
    // To the next occupied unit, as Traverse / CompleteCellLoad walk it.
    uint64_t steps = 0;
    uint32_t leaf = 0;
    if (rec.in_sub != 0) {
      const SubResult res = SubAdvance(*sg, rec, fc.grid.shift, &steps, &leaf);
      Compute(steps * costs.dda_step + costs.dda_exit);
      counters.cell_steps += steps;
      if (res == SubResult::kDone) return finished;
      if (res == SubResult::kLeft) {
        if (!DdaStep(fc.grid, rec, rec.t_exit)) return finished;
        continue;
      }
    } else {
      const bool at_cell = DdaAdvance(fc.grid, occupancy, rec, &steps);
      Compute(steps * costs.dda_step + costs.dda_exit);
      counters.cell_steps += steps;
      if (!at_cell) return finished;
      leaf = rec.idx;
    }
    // Loaded? (8 leaf ids in 2 vectors, like the micro-cache.)
    Compute(costs.micro_cache_lookup);
    int e = 0;
    while (e < loaded_count && loaded[e].leaf != leaf) ++e;
    if (e == loaded_count && rec.in_sub == 0 && fc.grid.two_level != 0) {
      // A refined cell whose sub-grid record is in LS: walk its sub-cells.
      uint32_t index = 0;
      if (const SubGridRecord* rec_sg = LoadedSubGrid(rec.idx, &index)) {
        sg = rec_sg;
        rec.sub_record = index;
        SubInit(*sg, rec, fc.grid.shift);
        continue;
      }
    }
    if (e == loaded_count) {
      // The pipeline examines this unit again when the ray resumes: count it once.
      --counters.cell_steps;
      return AtOnce::kResume;
    }
    // VisitVoxel on the buffer, then AfterUnit's stop test and step.
    const LoadedUnit& u = loaded[e];
    if (!*tested) {
      wr = PrepareWatertightRay(rec.o[0] - fc.grid.shift[0], rec.o[1] - fc.grid.shift[1],
                                rec.o[2] - fc.grid.shift[2], rec.d[0], rec.d[1], rec.d[2]);
      *tested = true;
    }
    const uint32_t bundles = (u.count + 3) / 4;
    const TriangleBundle* tp =
        ls.As<const TriangleBundle>(tri_lsa + uint32_t(u.slot) * tri_slot_bytes, bundles);
    Compute(costs.visit_setup + bundles * costs.triangle_bundle);
    counters.bundles += bundles;
    ++counters.at_once_visits;
    if (shadow) {
      if (IntersectBundles<true>(wr, tp, bundles, rec, &counters.triangle_tests)) {
        return AtOnce::kOccluded;
      }
    } else {
      IntersectBundles<false>(wr, tp, bundles, rec, &counters.triangle_tests);
    }
    if (rec.in_sub != 0) {
      const SubResult res = SubStep(*sg, rec, fc.grid.shift);
      if (res == SubResult::kDone) return finished;
      if (res == SubResult::kLeft && !DdaStep(fc.grid, rec, rec.t_exit)) return finished;
    } else if (!DdaStep(fc.grid, rec, rec.t_exit)) {
      return finished;
    }
  }
}

glm::vec3 Spe::Impl::Texel(const MaterialRecord& m, int tx, int ty) {
  float p[3];
  cache->Read(m.texels + ((static_cast<uint64_t>(ty) * uint64_t(m.tex_width) + uint64_t(tx)) * 3) *
                             sizeof(float),
              sizeof(p), p);
  return glm::vec3(p[0], p[1], p[2]);
}

// rs::SampleTexture with the texels read through the software cache: the same arithmetic
// (SampleBilinear, kernels/shade.h).
glm::vec3 Spe::Impl::SampleTextureCached(const MaterialRecord& m, glm::vec2 uv) {
  if (m.tex_width <= 0 || m.tex_height <= 0) return glm::vec3(1.0f);
  return SampleBilinear(m.tex_width, m.tex_height, uv,
                        [&](int tx, int ty) { return Texel(m, tx, ty); });
}

// Shading of the iteration's finished closest-hit rays (paper 3.7) with raystream's shader on a
// scene view built from local store: the hit triangles' records, materials from the software
// cache (textures sampled through it and folded into the diffuse colour, exactly as rs::Shade
// would), lights and constants from the frame-constant block. Secondary rays go to the ring.
void Spe::Impl::Shade() {
  int nb = 0, nh = 0;
  for (int r = 0; r < n; ++r) {
    if (flight[r].status == Flight::kDoneHit || flight[r].status == Flight::kDoneMiss) ++nb;
  }
  if (nb > 0) {
    shade_rays.Resize(static_cast<size_t>(nb));
    shade_hits.Resize(static_cast<size_t>(nb));
    const RayStreamView rv = shade_rays.view();
    const HitStreamView hv = shade_hits.view();
    const bool normals = fc.has_normals != 0;
    int i = 0;
    for (int r = 0; r < n; ++r) {
      const Flight st = flight[r].status;
      if (st != Flight::kDoneHit && st != Flight::kDoneMiss) continue;
      const RayRecord& rec = FlightRecord(r);
      rv.ox[i] = rec.o[0];
      rv.oy[i] = rec.o[1];
      rv.oz[i] = rec.o[2];
      rv.dx[i] = rec.d[0];
      rv.dy[i] = rec.d[1];
      rv.dz[i] = rec.d[2];
      rv.tmin[i] = rec.tmin;
      rv.tmax[i] = rec.tmax;
      rv.pixel[i] = static_cast<uint32_t>(i);  // batch index: contribution pixel id
      rv.wr[i] = rec.w[0];
      rv.wg[i] = rec.w[1];
      rv.wb[i] = rec.w[2];
      rv.depth[i] = rec.depth;
      rv.kind[i] = rec.kind;
      batch_pixel[i] = rec.pixel;
      batch_subtile[i] = rec.subtile;
      if (rec.kind == kPrimaryKind && out.block_work != nullptr &&
          out.block_work->pixel_depth != nullptr) {  // host-side record: no cycles
        out.block_work->pixel_depth[rec.pixel] =
            st == Flight::kDoneHit ? rec.best_t : std::numeric_limits<float>::infinity();
      }
      if (st == Flight::kDoneHit) {
        mfc.WaitTagsAll(1u << (kHitTagBase + uint32_t(r)));
        ShadingRecord sr;
        std::memcpy(&sr, ls.Bytes(hit_lsa + uint32_t(r) * sizeof(ShadingRecord), sizeof(sr)),
                    sizeof(sr));
        MaterialRecord mr;
        cache->Read(fc.materials + uint64_t{sr.material} * sizeof(MaterialRecord), sizeof(mr), &mr);
        const size_t k = size_t(nh);
        for (int v = 0; v < 3; ++v) {
          shade_positions[3 * k + size_t(v)] = glm::vec3(sr.p[v][0], sr.p[v][1], sr.p[v][2]);
          if (normals)
            shade_normals[3 * k + size_t(v)] = glm::vec3(sr.n[v][0], sr.n[v][1], sr.n[v][2]);
        }
        shade_triangles[k] = glm::uvec3(3 * k, 3 * k + 1, 3 * k + 2);
        shade_material_ids[k] = static_cast<uint32_t>(k);
        Material& mat = shade_materials[k];
        glm::vec3 kd(mr.diffuse[0], mr.diffuse[1], mr.diffuse[2]);
        if (fc.features.textures && fc.has_uvs != 0 && mr.texture >= 0 &&
            static_cast<uint32_t>(mr.texture) < fc.num_textures) {
          const float u = rec.best_u;
          const float v = rec.best_v;
          const float b0 = 1.0f - u - v;
          const glm::vec2 uv = b0 * glm::vec2(sr.uv[0][0], sr.uv[0][1]) +
                               u * glm::vec2(sr.uv[1][0], sr.uv[1][1]) +
                               v * glm::vec2(sr.uv[2][0], sr.uv[2][1]);
          kd *= SampleTextureCached(mr, uv);
          Compute(costs.shade_texture);
          ++counters.texture_fetches;
        }
        mat.diffuse = kd;
        mat.specular = glm::vec3(mr.specular[0], mr.specular[1], mr.specular[2]);
        mat.shininess = mr.shininess;
        mat.reflectivity = mr.reflectivity;
        mat.transmission = mr.transmission;
        mat.ior = mr.ior;
        mat.texture = -1;  // sampled above
        hv.t[i] = rec.best_t;
        hv.u[i] = rec.best_u;
        hv.v[i] = rec.best_v;
        hv.prim[i] = nh++;
      } else {
        hv.t[i] = std::numeric_limits<float>::infinity();
        hv.u[i] = hv.v[i] = 0.0f;
        hv.prim[i] = -1;
      }
      ++i;
    }
    const size_t hits = size_t(nh);
    shade_scene.positions = std::span<const glm::vec3>(shade_positions, 3 * hits);
    shade_scene.normals = std::span<const glm::vec3>(shade_normals, normals ? 3 * hits : 0);
    shade_scene.triangles = std::span<const glm::uvec3>(shade_triangles, hits);
    shade_scene.material_ids = std::span<const uint32_t>(shade_material_ids, hits);
    shade_scene.materials = std::span<const Material>(shade_materials, hits);
    secondary.Clear();
    shade_contributions.Clear();
    ShadeStats s;
    rs::Shade(shade_scene, fc.shade, rv, hv, shade_contributions, secondary, &s);
    // Each batch ray's contribution into its sub-tile's pixel buffer, as Framebuffer::Add would
    // add it (fixed point, NaN dropped and counted, clamps counted).
    const ContributionView cv = shade_contributions.view();
    for (size_t j = 0; j < cv.size; ++j) {
      const uint32_t b = cv.pixel[j];  // the batch ray
      AddContribution(batch_subtile[b], batch_pixel[b], cv.r[j], cv.g[j], cv.b[j]);
    }
    uint64_t spawned = 0;
    for (const uint64_t c : s.spawned) spawned += c;
    Compute(uint64_t(nb) * costs.shade_ray + s.shading_calls * costs.shade_hit +
            s.light_tests * costs.shade_light + spawned * costs.shade_spawn);
    counters.shade.Merge(s);
    counters.shade.texture_fetches = counters.texture_fetches;
    const RayStreamView sv = secondary.view();
    for (size_t j = 0; j < secondary.size(); ++j) {
      RayRecord rec{};
      rec.o[0] = sv.ox[j];
      rec.o[1] = sv.oy[j];
      rec.o[2] = sv.oz[j];
      rec.d[0] = sv.dx[j];
      rec.d[1] = sv.dy[j];
      rec.d[2] = sv.dz[j];
      rec.tmin = sv.tmin[j];
      rec.tmax = sv.tmax[j];
      const uint32_t b = sv.pixel[j];  // the batch ray that spawned it
      rec.pixel = batch_pixel[b];
      rec.subtile = batch_subtile[b];
      rec.w[0] = sv.wr[j];
      rec.w[1] = sv.wg[j];
      rec.w[2] = sv.wb[j];
      rec.depth = sv.depth[j];
      rec.kind = sv.kind[j];
      rec.state = kRayFresh;
      if (config.secondary_at_once && loaded_count > 0) {
        bool tested = false;
        const AtOnce res = TraceAtOnce(rec, &tested);
        counters.at_once_tested += tested ? 1 : 0;
        if (res != AtOnce::kResume) ++counters.at_once_resolved;
        if (res == AtOnce::kOccluded || res == AtOnce::kUnoccluded) {
          if (res == AtOnce::kUnoccluded) {
            AddContribution(rec.subtile, rec.pixel, rec.w[0], rec.w[1], rec.w[2]);
            Compute(costs.shadow_add);
          }
          ++counters.rays[kShadowKind];
          counters.occluded += res == AtOnce::kOccluded ? 1 : 0;
          continue;
        }
        if (res == AtOnce::kTraced) rec.state = kRayTraced;
      }
      ++pixel_slots[rec.subtile].outstanding;
      PushRay(rec);
    }
  }
  for (int r = 0; r < n; ++r) {
    const Flight st = flight[r].status;
    if (st == Flight::kContinue) continue;
    const RayRecord& rec = FlightRecord(r);
    if (st == Flight::kDoneUnoccluded) {
      AddContribution(rec.subtile, rec.pixel, rec.w[0], rec.w[1], rec.w[2]);
      Compute(costs.shadow_add);
    }
    const int32_t kind = rec.kind;
    if (kind >= 0 && kind < kNumRayKinds) ++counters.rays[kind];
    counters.hits += st == Flight::kDoneHit ? 1 : 0;
    counters.occluded += st == Flight::kDoneOccluded ? 1 : 0;
    --pixel_slots[rec.subtile].outstanding;
  }
  // Tile times: the iteration's cycles shared among its rays' tiles.
  if (out.tile_cycles != nullptr) {
    const double share = double(clock.now() - iteration_start) / double(n);
    for (int r = 0; r < n; ++r) {
      if (flight[r].tile >= 0) (*out.tile_cycles)[size_t(flight[r].tile)] += share;
    }
  }
  // The same shares per ray for the cost map's blocks, in fixed point (FrameOutputs).
  if (out.block_work != nullptr) {
    BlockWork& b = *out.block_work;
    const uint64_t units = (clock.now() - iteration_start) * out.block_units_per_cycle;
    const uint64_t share = units / uint64_t(n);
    const uint64_t extra = units - share * uint64_t(n);
    for (int r = 0; r < n; ++r) {
      if (flight[r].tile < 0) continue;
      b.work[b.BlockOf(flight[r].pixel)] +=
          static_cast<int64_t>(share + (uint64_t(r) < extra ? 1 : 0));
    }
  }
  ++counters.iterations;
  counters.rays_in_flight += uint64_t(n);
  ++counters.iterations_by_rays[n];
  in_iteration = false;
  phase = Phase::kRefill;
}

// Framebuffer::Add on the LS pixel buffer of sub-tile slot `slot`: the same fixed-point values
// (Framebuffer::ToFixed per channel), a contribution with a NaN channel dropped entirely and
// counted, one with a clamped channel counted.
void Spe::Impl::AddContribution(int slot, uint32_t pixel, float r, float g, float b) {
  bool nan = false, clamp = false;
  const int64_t sums[3] = {Framebuffer::ToFixed(r, &nan, &clamp),
                           Framebuffer::ToFixed(g, &nan, &clamp),
                           Framebuffer::ToFixed(b, &nan, &clamp)};
  if (nan) {
    ++dropped_nan;
    return;
  }
  clamped += clamp ? 1 : 0;
  AddFixed(slot, pixel, sums);
}

// Adds fixed-point sums to `pixel` (an image pixel id) in the pixel buffer of slot `slot`, whose
// sub-tile must hold the pixel (every ray carries the slot of its primary's sub-tile).
void Spe::Impl::AddFixed(int slot, uint32_t pixel, const int64_t* sums) {
  const PixelSlot& s = pixel_slots[static_cast<size_t>(slot)];
  const int x = static_cast<int>(pixel % uint32_t(fc.image_width));
  const int y = static_cast<int>(pixel / uint32_t(fc.image_width));
  if (!s.busy || x < s.rect.x0 || x >= s.rect.x1 || y < s.rect.y0 || y >= s.rect.y1) {
    throw Error("SPE " + std::to_string(id) + ": contribution to pixel " + std::to_string(pixel) +
                " outside the sub-tile of pixel buffer " + std::to_string(slot));
  }
  const uint32_t offset = static_cast<uint32_t>((y - s.rect.y0) * s.rect.Width() + (x - s.rect.x0));
  PixelSums& p = *ls.As<PixelSums>(pixel_lsa + uint32_t(slot) * pixel_slot_bytes +
                                   offset * uint32_t{sizeof(PixelSums)});
  for (int c = 0; c < 3; ++c) p.rgb[c] += sums[c];
}

// Sub-tiles whose rays have all finished write their pixel buffer back (one DMA list of rows).
void Spe::Impl::RetireSubtiles() {
  for (int b = 0; b < static_cast<int>(pixel_slots.size()); ++b) {
    PixelSlot& s = pixel_slots[b];
    if (!s.busy || s.next != s.total || s.outstanding != 0) continue;
    const Lsa buffer = pixel_lsa + uint32_t(b) * pixel_slot_bytes;
    const Lsa list = list_lsa + uint32_t(b) * list_slot_bytes;
    DmaListElement* e = ls.As<DmaListElement>(list, list_slot_bytes / 8);
    constexpr uint64_t kPx = sizeof(PixelSums);
    const uint32_t row_bytes = static_cast<uint32_t>(s.rect.Width() * kPx);
    const Ea first =
        fc.pixels + (uint64_t(s.rect.y0) * uint64_t(fc.image_width) + uint64_t(s.rect.x0)) * kPx;
    const Ea last =
        fc.pixels +
        (uint64_t(s.rect.y1 - 1) * uint64_t(fc.image_width) + uint64_t(s.rect.x1)) * kPx;
    if ((first >> 32) == ((last - 1) >> 32)) {
      uint32_t count = 0;
      for (int y = s.rect.y0; y < s.rect.y1; ++y) {
        const Ea row =
            fc.pixels + (uint64_t(y) * uint64_t(fc.image_width) + uint64_t(s.rect.x0)) * kPx;
        for (uint32_t off = 0; off < row_bytes; off += kMaxDmaSize) {
          e[count].size = std::min(kMaxDmaSize, row_bytes - off);
          e[count].eal = static_cast<uint32_t>(row + off);
          ++count;
        }
      }
      mfc.MfcPutList(buffer, static_cast<uint32_t>(first >> 32), list, count * 8,
                     kPixelTagBase + uint32_t(b));
    } else {  // rows straddle a 4 GiB boundary: one put per row piece
      Lsa at = buffer;
      for (int y = s.rect.y0; y < s.rect.y1; ++y) {
        const Ea row =
            fc.pixels + (uint64_t(y) * uint64_t(fc.image_width) + uint64_t(s.rect.x0)) * kPx;
        for (uint32_t off = 0; off < row_bytes; off += kMaxDmaSize) {
          const uint32_t size = std::min(kMaxDmaSize, row_bytes - off);
          mfc.MfcPut(at, row + off, size, kPixelTagBase + uint32_t(b));
          at += size;
        }
      }
    }
    pixels_written += s.total;
    s.busy = false;
    s.draining = true;
  }
}

// The last sub-tiles go out, then the status record; the program ends when every DMA is done.
void Spe::Impl::Finish() {
  RetireSubtiles();
  SpeStatus& st = *ls.As<SpeStatus>(status_lsa);
  st = SpeStatus{};
  st.dropped_nan = dropped_nan;
  st.clamped = clamped;
  st.pixels_written = pixels_written;
  mfc.MfcPut(status_lsa, fc.status + uint64_t(id) * sizeof(SpeStatus), sizeof(SpeStatus),
             kSetupTag);
  mfc.WaitAll();
  counters.tail_cycles = clock.now() - tail_start;
  phase = Phase::kDone;
}

Spe::Spe(int id, Machine& machine, Ea constants, const FrameOutputs& outputs)
    : impl_(std::make_unique<Impl>(id, machine, constants, outputs)) {}
Spe::~Spe() = default;
void Spe::Step() { impl_->Step(); }
bool Spe::done() const { return impl_->phase == Phase::kDone; }
uint64_t Spe::now() const { return impl_->clock.now(); }
int Spe::id() const { return impl_->id; }
void Spe::IdleUntil(uint64_t frame_end) { impl_->clock.WaitUntil(Cost::kIdle, frame_end); }
const SpuClock& Spe::clock() const { return impl_->clock; }
const SpeCounters& Spe::counters() const { return impl_->counters; }
const MfcStats& Spe::mfc_stats() const { return impl_->mfc.stats(); }
const AtomicStats& Spe::atomic_stats() const { return impl_->atomic.stats(); }
SoftwareCacheStats Spe::cache_stats() const {
  return impl_->cache ? impl_->cache->stats() : SoftwareCacheStats{};
}
const LocalStore& Spe::local_store() const { return impl_->ls; }

}  // namespace rs::sim
