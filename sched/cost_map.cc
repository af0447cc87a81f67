// The per-block cost map and its reprojection (cost_map.h). Scalar code run once per frame by
// the master (the engines only fill BlockWork).
#include "sched/cost_map.h"

#include <fmt/core.h>

#include <algorithm>
#include <cassert>
#include <cmath>
#include <cstring>
#include <limits>

#include "include/raystream/raystream.h"

namespace rs {
namespace {

int CeilDiv(int a, int b) { return (a + b - 1) / b; }

// The block counts of a width x height image in block x block blocks (partial at the right and
// bottom) into *bx, *by; returns bx * by. Throws rs::Error naming `what` if a size is < 1.
size_t BlockCounts(const char* what, int width, int height, int block, int* bx, int* by) {
  if (width < 1 || height < 1 || block < 1) {
    throw Error(fmt::format("{}: image {}x{} in {}x{} blocks: sizes must be at least 1", what,
                            width, height, block, block));
  }
  *bx = CeilDiv(width, block);
  *by = CeilDiv(height, block);
  return static_cast<size_t>(*bx) * static_cast<size_t>(*by);
}

bool SameCamera(const CameraBasis& a, const CameraBasis& b) {
  return a.eye == b.eye && a.forward == b.forward && a.right == b.right && a.up == b.up &&
         a.tan_half_x == b.tan_half_x && a.tan_half_y == b.tan_half_y && a.width == b.width &&
         a.height == b.height;
}

}  // namespace

void BlockWork::Resize(int w, int h, int b) {
  const size_t n = BlockCounts("block work", w, h, b, &blocks_x, &blocks_y);
  width = w;
  height = h;
  block = b;
  work.assign(n, 0);
}

void BlockWork::Clear() { std::fill(work.begin(), work.end(), 0); }

void BlockWork::Add(const BlockWork& o) {
  assert(o.work.size() == work.size());
  for (size_t i = 0; i < work.size(); ++i) work[i] += o.work[i];
}

void CostMap::Resize(int width, int height, int block) {
  const size_t n = BlockCounts("cost map", width, height, block, &blocks_x_, &blocks_y_);
  width_ = width;
  height_ = height;
  block_ = block;
  cost_.assign(n, 0.0);
  const size_t pixels = static_cast<size_t>(width) * static_cast<size_t>(height);
  z_.assign(pixels, 0.0f);
  density_.assign(pixels, 0.0f);
}

Tile CostMap::BlockTile(int bx, int by) const {
  Tile t;
  t.x0 = bx * block_;
  t.y0 = by * block_;
  t.x1 = std::min(width_, t.x0 + block_);
  t.y1 = std::min(height_, t.y0 + block_);
  return t;
}

void CostMap::Clear() { std::fill(cost_.begin(), cost_.end(), 0.0); }

void CostMap::AddTile(const Tile& tile, double cost) {
  const size_t pixels = tile.NumPixels();
  if (pixels == 0) return;
  const double per_pixel = cost / static_cast<double>(pixels);
  const int bx0 = tile.x0 / block_, bx1 = CeilDiv(tile.x1, block_);
  const int by0 = tile.y0 / block_, by1 = CeilDiv(tile.y1, block_);
  for (int by = by0; by < by1; ++by) {
    const int y0 = std::max(tile.y0, by * block_), y1 = std::min(tile.y1, (by + 1) * block_);
    for (int bx = bx0; bx < bx1; ++bx) {
      const int x0 = std::max(tile.x0, bx * block_), x1 = std::min(tile.x1, (bx + 1) * block_);
      cost_[Index(bx, by)] += per_pixel * static_cast<double>((x1 - x0) * (y1 - y0));
    }
  }
}

void CostMap::SetFromWork(const BlockWork& work, double scale) {
  assert(work.Matches(width_, height_, block_));
  for (size_t i = 0; i < cost_.size(); ++i) {
    cost_[i] = static_cast<double>(work.work[i]) * kBlockWorkUnit * scale;
  }
}

double CostMap::Total() const {
  double sum = 0.0;
  for (const double c : cost_) sum += c;
  return sum;
}

double CostMap::Predict(const Tile& tile) const {
  if (tile.NumPixels() == 0) return 0.0;
  const int bx0 = tile.x0 / block_, bx1 = CeilDiv(tile.x1, block_);
  const int by0 = tile.y0 / block_, by1 = CeilDiv(tile.y1, block_);
  double sum = 0.0;
  for (int by = by0; by < by1; ++by) {
    const int cy0 = by * block_, cy1 = std::min(height_, cy0 + block_);
    const int y0 = std::max(tile.y0, cy0), y1 = std::min(tile.y1, cy1);
    for (int bx = bx0; bx < bx1; ++bx) {
      const int cx0 = bx * block_, cx1 = std::min(width_, cx0 + block_);
      const int x0 = std::max(tile.x0, cx0), x1 = std::min(tile.x1, cx1);
      const double c = cost_[Index(bx, by)];
      const int covered = (x1 - x0) * (y1 - y0);
      const int all = (cx1 - cx0) * (cy1 - cy0);
      // A whole block adds its cost as it is (exact sums on block boundaries).
      sum += covered == all ? c : c * (static_cast<double>(covered) / static_cast<double>(all));
    }
  }
  return sum;
}

// Forward mapping of cost per pixel (not cost): content that the next camera sees larger
// (moving closer) covers more pixels and so more rays, each as costly as before. A z-buffer per
// pixel keeps the nearest content where several samples land (the foreground hides what moved
// behind it).
void CostMap::Reproject(const CameraBasis& from, const CameraBasis& to,
                        std::span<const float> depth) {
  assert(depth.size() == static_cast<size_t>(width_) * static_cast<size_t>(height_));
  assert(from.width == width_ && from.height == height_);
  assert(to.width == width_ && to.height == height_);
  if (SameCamera(from, to)) return;
  const float inf = std::numeric_limits<float>::infinity();
  const float nan = std::numeric_limits<float>::quiet_NaN();
  std::fill(z_.begin(), z_.end(), inf);
  std::fill(density_.begin(), density_.end(), nan);  // NaN: nothing landed
  const int step = ReprojectStep();
  const double half_w = 0.5 * to.width, half_h = 0.5 * to.height;
  // Every pixel whose centre lies in [x0, x1) x [y0, y1) gets `rho` unless it holds nearer
  // content (at infinity: only where nothing landed).
  auto land = [&](double x0, double x1, double y0, double y1, float z, float rho) {
    const int px0 = std::max(0, static_cast<int>(std::ceil(x0 - 0.5)));
    const int px1 = std::min(width_, static_cast<int>(std::ceil(x1 - 0.5)));
    const int py0 = std::max(0, static_cast<int>(std::ceil(y0 - 0.5)));
    const int py1 = std::min(height_, static_cast<int>(std::ceil(y1 - 0.5)));
    for (int qy = py0; qy < py1; ++qy) {
      for (int qx = px0; qx < px1; ++qx) {
        const size_t q = static_cast<size_t>(qy) * static_cast<size_t>(width_) +
                         static_cast<size_t>(qx);
        if (z < z_[q] || std::isnan(density_[q])) {  // nothing there yet: z_[q] is +inf
          z_[q] = z;
          density_[q] = rho;
        }
      }
    }
  };
  for (int by = 0; by < blocks_y_; ++by) {
    for (int bx = 0; bx < blocks_x_; ++bx) {
      const size_t i = Index(bx, by);
      const Tile b = BlockTile(bx, by);
      const float rho = static_cast<float>(cost_[i] / static_cast<double>(b.NumPixels()));
      for (int y = b.y0; y < b.y1; y += step) {
        const int h = std::min(step, b.y1 - y);
        for (int x = b.x0; x < b.x1; x += step) {
          const int w = std::min(step, b.x1 - x);
          const int ix = x + w / 2, iy = y + h / 2;  // the pixel whose depth the sample takes
          const float t =
              depth[static_cast<size_t>(iy) * static_cast<size_t>(width_) + static_cast<size_t>(ix)];
          if (std::isnan(t)) {  // unknown depth: stays where it is, behind everything
            land(x, x + w, y, y + h, inf, rho);
            continue;
          }
          // The primary ray of that pixel (its centre, continuous pixel coordinates), the ray
          // the depth was measured along.
          const double cx = ix + 0.5, cy = iy + 0.5;
          const double sx = (2.0 * cx / from.width - 1.0) * from.tan_half_x;
          const double sy = (1.0 - 2.0 * cy / from.height) * from.tan_half_y;
          double d[3], v[3];
          double len = 0.0;
          for (int k = 0; k < 3; ++k) {
            d[k] = from.forward[k] + sx * from.right[k] + sy * from.up[k];
            len += d[k] * d[k];
          }
          len = std::sqrt(len);
          const bool at_infinity = std::isinf(t);
          // A finite hit: the point relative to the new eye; at infinity: the direction.
          for (int k = 0; k < 3; ++k) {
            d[k] /= len;
            v[k] = at_infinity ? d[k] : from.eye[k] + static_cast<double>(t) * d[k] - to.eye[k];
          }
          double z = 0.0, xr = 0.0, yu = 0.0, vv = 0.0;
          for (int k = 0; k < 3; ++k) {
            z += v[k] * to.forward[k];
            xr += v[k] * to.right[k];
            yu += v[k] * to.up[k];
            vv += v[k] * v[k];
          }
          if (!(z > 1e-6 * std::sqrt(vv))) continue;  // behind the new camera: dropped
          const double px = (xr / z / to.tan_half_x + 1.0) * half_w;
          const double py = (1.0 - yu / z / to.tan_half_y) * half_h;
          // The sample's footprint: its pixels scaled by the depth ratio (content that comes
          // closer covers more pixels; clamped), at least a pixel wide so zooming out leaves
          // no holes, centred where the sample's centre lands (it lies x + w / 2 - cx pixels
          // from the pixel's).
          const double z_from = static_cast<double>(t) / len;  // t * dot(d, forward)
          const double scale = at_infinity ? 1.0 : std::clamp(z_from / z, 0.25, 4.0);
          const double fcx = px + scale * (x + 0.5 * w - cx);
          const double fcy = py + scale * (y + 0.5 * h - cy);
          const double hw = std::max(0.5 * w * scale, 0.5);
          const double hh = std::max(0.5 * h * scale, 0.5);
          if (!(fcx + hw > 0.0 && fcx - hw < width_ && fcy + hh > 0.0 && fcy - hh < height_)) {
            continue;  // outside the image: dropped
          }
          land(fcx - hw, fcx + hw, fcy - hh, fcy + hh, at_infinity ? inf : static_cast<float>(z),
               rho);
        }
      }
    }
  }
  // A block's new cost: what landed on its pixels, its old cost per pixel where nothing did.
  for (int by = 0; by < blocks_y_; ++by) {
    for (int bx = 0; bx < blocks_x_; ++bx) {
      const size_t i = Index(bx, by);
      const Tile b = BlockTile(bx, by);
      const double old = cost_[i] / static_cast<double>(b.NumPixels());
      double sum = 0.0;
      for (int y = b.y0; y < b.y1; ++y) {
        for (int x = b.x0; x < b.x1; ++x) {
          const float r = density_[static_cast<size_t>(y) * static_cast<size_t>(width_) +
                                   static_cast<size_t>(x)];
          sum += std::isnan(r) ? old : static_cast<double>(r);
        }
      }
      cost_[i] = sum;
    }
  }
}

}  // namespace rs
