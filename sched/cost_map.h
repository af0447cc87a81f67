// The cost-map predictor of PBT-Update: a frame's cost per block of pixels (what the workers'
// frame engines attribute to each block), reprojected to the next frame's camera, predicts any
// rectangle (a split half, a merged pair, an unchanged tile) as the sum of the blocks it covers.
// Replaces the paper's e(a) / 2 for split halves and stale sums for merges (tile_plan.h).
#pragma once

#include <cstddef>
#include <cstdint>
#include <span>
#include <vector>

#include "sched/pbt.h"
#include "streams/raygen.h"  // rs::Tile, rs::CameraBasis

namespace rs {

// Seconds per unit of BlockWork::work (2^-50 s, about 9e-16 s): a ray of the calibrated work
// cost is about 6e7 units, so a frame of 10^4 core-seconds still fits an int64.
inline constexpr double kBlockWorkUnit = 0x1p-50;

// One frame's per-block record of a frame engine (RayEngine::SetBlockWork): the work of every
// trace call charged to the blocks of its rays' pixels, in kBlockWorkUnit (a tile's own batches,
// RenderTile: TileWorkCost of the call's rays, cell steps and triangle tests in equal shares per
// ray; generations a queue backend grouped, TraceGeneration: each ray's own TileWorkCost, a ray
// and a shading call if it hit), and each primary ray's hit distance. Work is fixed point, so
// sums over threads do not depend on which thread ran which tile or ray: the same frame gives
// the same record at any thread count (the tiles backend's, or the queue backends' one, which
// is the same on lock, lfree and local). Blocks are block x block pixels in row-major order,
// partial at the right and bottom.
struct BlockWork {
  int width = 0;
  int height = 0;
  int block = 0;  // 0: not sized
  int blocks_x = 0;
  int blocks_y = 0;
  std::vector<int64_t> work;  // per block: work in kBlockWorkUnit
  // Per pixel (y * width + x), not owned, may be null: the engine stores the distance t of the
  // pixel's primary hit, +inf for a miss. Every pixel has one primary ray per frame, traced by
  // one thread, so the engines of all threads can share one array without a race.
  float* pixel_depth = nullptr;

  // Sizes `work` for a width x height image in block x block blocks and zeroes it (allocates
  // only when the block count grows). Throws rs::Error if a size is < 1.
  void Resize(int width, int height, int block);
  bool Matches(int w, int h, int b) const { return width == w && height == h && block == b; }
  void Clear();                      // zeroes `work`, keeps the sizes
  void Add(const BlockWork& other);  // element-wise sum of `work`; sizes must match (asserted)
  size_t NumBlocks() const { return work.size(); }
  // The block of pixel y * width + x (inside the image).
  size_t BlockOf(uint32_t pixel) const {
    const uint32_t w = static_cast<uint32_t>(width);
    const uint32_t y = pixel / w;
    const uint32_t x = pixel - y * w;
    const uint32_t b = static_cast<uint32_t>(block);
    return static_cast<size_t>(y / b) * static_cast<size_t>(blocks_x) + x / b;
  }
};

// Per-block costs of a width x height image in block x block blocks (row-major, partial at the
// right and bottom), in the units of the costs PBT-Update gets. Predict(t) is the sum over the
// blocks t overlaps of cost x (overlapped pixels / block pixels): a block's cost is taken as
// spread evenly over its pixels. For a rectangle on block boundaries every factor is 1, so the
// prediction is exactly the row-major sum of its blocks' costs, and a tree's predictions are
// additive up to rounding. Resize allocates; everything else allocates nothing.
class CostMap final : public PbtPredictor {
 public:
  // Throws rs::Error if a size is < 1.
  void Resize(int width, int height, int block);
  int width() const { return width_; }
  int height() const { return height_; }
  int block() const { return block_; }
  int blocks_x() const { return blocks_x_; }
  int blocks_y() const { return blocks_y_; }
  size_t NumBlocks() const { return cost_.size(); }
  std::span<double> costs() { return cost_; }
  std::span<const double> costs() const { return cost_; }
  double Cost(int bx, int by) const { return cost_[Index(bx, by)]; }
  double& Cost(int bx, int by) { return cost_[Index(bx, by)]; }
  // The pixel rectangle of block (bx, by).
  Tile BlockTile(int bx, int by) const;

  void Clear();                                // every cost 0
  void AddTile(const Tile& tile, double cost);  // `cost` spread evenly over tile's pixels
  // costs[b] = work[b] * kBlockWorkUnit * scale (sizes must match; asserted).
  void SetFromWork(const BlockWork& work, double scale);
  double Total() const;  // sum of the block costs

  double Predict(const Tile& tile) const override;

  // Moves the costs to where their content lands in the next frame. Each block is cut into
  // samples of ReprojectStep() x ReprojectStep() pixels; a sample's content is the point at the
  // distance depth[p] of its centre pixel p along the primary ray through the sample's centre
  // with camera `from` (+inf: at infinity, only the direction counts; NaN: unknown, the sample
  // stays where it is), projected with camera `to`. The sample lands as a rectangle around the
  // projected point, its size scaled by the ratio of its depth along the old and the new view
  // axis (content that comes closer covers more pixels; clamped to [1/4, 4], at least a pixel),
  // carrying its block's cost per pixel onto the pixels whose centres it covers; a per-pixel
  // z-buffer keeps the nearest content. A block's new cost is the sum over its pixels of what
  // landed there, its own old cost per pixel where nothing did (disocclusions, content
  // entering at the image edges). Content behind the new camera or outside the
  // image is dropped. Cameras that are bit-identical leave the map unchanged. depth.size() must
  // be width x height and both cameras of this map's image (asserted).
  int ReprojectStep() const { return block_ >= 4 ? block_ / 4 : 1; }
  void Reproject(const CameraBasis& from, const CameraBasis& to, std::span<const float> depth);

 private:
  size_t Index(int bx, int by) const {
    return static_cast<size_t>(by) * static_cast<size_t>(blocks_x_) + static_cast<size_t>(bx);
  }
  int width_ = 0;
  int height_ = 0;
  int block_ = 0;
  int blocks_x_ = 0;
  int blocks_y_ = 0;
  std::vector<double> cost_;
  // Reproject's per-pixel scratch (8 bytes a pixel, sized by Resize): the nearest content's
  // distance along the new view axis and its cost per pixel.
  std::vector<float> z_;
  std::vector<float> density_;
};

}  // namespace rs
