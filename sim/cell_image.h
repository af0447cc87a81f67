// The main-memory image the PPE lays out for the SPEs (paper 3.1, 3.4): per-cell records (first
// bundle, triangle count) read with the 128-B "atomic" load, the cells' triangles in bundles of 4
// (SoA, 160 B, DMA'd into the SPE's triangle buffers), per-triangle shading records (the "hit
// data"), material records and texels (software cache), lights and the occupancy bits. Built
// from raystream's own TriangleSoA and uniform grid, so the SPEs test the very same floats.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "include/raystream/raystream.h"
#include "kernels/shade.h"
#include "scenes/scene.h"
#include "sim/aligned_buffer.h"
#include "sim/mfc.h"
#include "streams/raygen.h"

namespace rs::sim {

// Four triangles of one cell, SoA: p[vertex][axis][lane] are the TriangleSoA floats; empty lanes
// have id UINT32_MAX and NaN vertices (never hit).
struct alignas(16) TriangleBundle {
  float p[3][3][4];
  uint32_t id[4];
};
static_assert(sizeof(TriangleBundle) == 160);

// One grid cell or sub-cell (a leaf): its triangles are bundles [first_bundle, first_bundle +
// ceil(count / 4)). 16 records share a 128-B line (one atomic load). A top-level cell refined
// into an 8x8x8 sub-grid has count = kRefinedCell and first_bundle = its SubGridRecord's index
// (kernels/two_level.h: one 128-B record, the second atomic load of paper 3.8); its occupied
// sub-cells' records are in the leaf-record array at (leaf id - top-level cells).
struct CellRecord {
  uint32_t first_bundle;
  uint32_t count;
};
static_assert(sizeof(CellRecord) == 8);
inline constexpr uint32_t kRefinedCell = 0xFFFFFFFFu;

// What shading needs of a hit triangle, one 128-B DMA: the mesh vertices (Scene::positions of
// its indices), per-vertex normals and UVs when the scene has them, its material id.
struct alignas(128) ShadingRecord {
  float p[3][3];
  float n[3][3];
  float uv[3][2];
  uint32_t material;
};
static_assert(sizeof(ShadingRecord) == 128);

// A material as the shader reads it through the software cache (two per 128-B line). The texture
// (if any) is described here so a miss on the material brings everything needed to sample it.
struct alignas(64) MaterialRecord {
  float diffuse[3];
  float specular[3];
  float shininess;
  float reflectivity;
  float transmission;
  float ior;
  int32_t texture;    // Scene texture index or -1
  int32_t tex_width;  // 0 if the texture has no usable texels (SampleTexture returns white)
  int32_t tex_height;
  uint32_t pad;
  Ea texels;  // rgb floats, row 0 at the top (main memory)
};
static_assert(sizeof(MaterialRecord) == 64);

struct alignas(16) LightRecord {
  float position[3];
  float falloff;
  float color[3];
  float pad;
};
static_assert(sizeof(LightRecord) == 32);

// One pixel of an SPE's local-store pixel buffer and of the main-memory pixel image the buffers
// are written back to: the framebuffer's 64-bit fixed-point sums (sched/framebuffer.h: the same
// round(c * 2^32) per contribution, r g b) and a pad word, so a pixel is two quadwords and every
// row of a sub-tile is a legal DMA (a multiple of 16 bytes on a 16-byte boundary).
struct alignas(16) PixelSums {
  int64_t rgb[3];
  int64_t pad;
};
static_assert(sizeof(PixelSums) == 32);

// What an SPE program reports at its end (one 128-B put into FrameConstants::status + 128 * SPE
// id): the contributions its pixel buffers dropped (a NaN channel) or clamped, counted as
// Framebuffer::Add counts them, so the PPE's framebuffer gets its counters from main memory too.
struct alignas(128) SpeStatus {
  uint64_t dropped_nan;
  uint64_t clamped;
  uint64_t pixels_written;  // pixels put back to the pixel image
  uint64_t pad[13];
};
static_assert(sizeof(SpeStatus) == 128);

// The uniform grid's geometry (kernels/grid.h Grid, without the arrays).
struct GridHeader {
  float lo[3];
  float hi[3];
  float cell_size[3];
  float inv_cell_size[3];
  int32_t res[3];
  uint32_t empty;  // 1 if the grid has no cells (nothing can be hit)
  uint64_t num_cells;
  uint32_t two_level;  // 1 if some cells are refined (sub-grid records exist)
  uint32_t pad;
  // the Accel's frame (kernels/accel_impl.h): the grid, the records and the triangles are at
  // world - shift; the rays stay in world coordinates and are translated where traversed
  float shift[3];
};

// Everything an SPE reads once per frame, one DMA into local store (trivially copyable).
struct alignas(128) FrameConstants {
  CameraBasis camera;
  GridHeader grid;
  ShadeOptions shade;
  SceneFeatures features;
  float background[3];
  float ambient;
  uint32_t has_normals;
  uint32_t has_uvs;
  uint32_t num_lights;
  uint32_t num_materials;
  uint32_t num_textures;
  int32_t image_width;
  int32_t image_height;
  int32_t tile_width;  // regular tiles: tile index -> rectangle
  int32_t tile_height;
  int32_t tiles_x;
  uint32_t num_tiles;
  uint32_t explicit_tiles;  // 1: tile rectangles are read from `tiles` (PBT, given lists)
  uint64_t occupancy_bytes;
  Ea cell_records;
  Ea subgrids;      // SubGridRecord[] (two-level grids)
  Ea leaf_records;  // CellRecord[] of the sub-cell leaves
  Ea bundles;
  Ea shading;
  Ea materials;
  Ea lights;
  Ea occupancy;
  Ea tile_counter;  // 128-B line, counter in its first 4 bytes
  Ea tiles;         // Tile[num_tiles] (16 B each) when explicit_tiles
  Ea pixels;        // PixelSums[image_width * image_height], row-major (write-back target)
  Ea status;        // SpeStatus[number of SPEs]
};
static_assert(sizeof(Tile) == 16);

// Built once per (scene, accel); read-only for the SPEs. Mirrors what the accel traverses: the
// flat grid, or the two-level grid (leaf lists of kernels/two_level.h) when it has one. The
// arrays get simulated effective addresses when they are laid out (from
// MainMemory::kMainMemoryBase, each on a MainMemory::kRegionAlign boundary, in a fixed order), so
// the EAs stored inside the image (a material's texels) and the FrameConstants are the same in
// every process.
class CellImage {
 public:
  // Lays out the arrays above. Throws rs::Error if the scene and the accel disagree (triangle
  // count) or a bundle index would overflow 32 bits.
  CellImage(const Scene& scene, const Accel& accel);
  CellImage(const CellImage&) = delete;  // the layout points at the members
  CellImage& operator=(const CellImage&) = delete;

  // Registers every array at its planned EA (`memory` must not hold regions there yet: register
  // the image first, then the frame's buffers with MainMemory::Register, which places them
  // after it).
  void Register(MainMemory& memory) const;

  const GridHeader& grid() const { return grid_; }
  size_t num_bundles() const { return num_bundles_; }
  size_t num_subgrids() const { return num_subgrids_; }
  size_t occupancy_bytes() const { return occupancy_.size(); }
  size_t Bytes() const;
  double build_seconds() const { return build_seconds_; }
  const Scene& scene() const { return *scene_; }
  const Accel& accel() const { return *accel_; }
  // Fills the scene and image parts of a FrameConstants (not camera, tiles or pixels).
  void FillConstants(FrameConstants* fc) const;

 private:
  const Scene* scene_;
  const Accel* accel_;
  GridHeader grid_{};
  AlignedBuffer cell_records_;
  AlignedBuffer subgrids_;
  AlignedBuffer leaf_records_;
  AlignedBuffer bundles_;
  AlignedBuffer shading_;
  AlignedBuffer materials_;
  AlignedBuffer lights_;
  AlignedBuffer occupancy_;
  std::vector<AlignedBuffer> texels_;
  // The planned EA of each array, in layout order.
  struct Placed {
    const AlignedBuffer* buffer;
    std::string name;
    Ea ea;
  };
  Ea Place(const AlignedBuffer& buffer, std::string name);
  std::vector<Placed> layout_;
  Ea next_ea_ = MainMemory::kMainMemoryBase;
  Ea cell_records_ea_ = 0, subgrids_ea_ = 0, leaf_records_ea_ = 0, bundles_ea_ = 0;
  Ea shading_ea_ = 0, materials_ea_ = 0, lights_ea_ = 0, occupancy_ea_ = 0;
  size_t num_bundles_ = 0;
  size_t num_subgrids_ = 0;
  double build_seconds_ = 0;
};

}  // namespace rs::sim
