// Primary ray generation (see raygen.h). Scalar: generation is a small share of a frame; the
// per-pixel float sequence lives in PrimaryDirection only, so every tiling gives the same bits.
#include "streams/raygen.h"

// No FMA contraction in this file, whatever the flags (-march with FMA, clang's default
// fp-contract=on): a pixel's direction must be the same float sequence in every build and at
// every call site, so that every backend and every SIMD target gets bit-identical rays.
#if defined(__clang__)
#pragma clang fp contract(off)
#elif defined(__GNUC__)
#pragma GCC optimize("fp-contract=off")
#endif

#include <algorithm>
#include <cmath>
#include <limits>
#include <numbers>
#include <string>

namespace rs {

const char* RayOrderName(RayOrder order) {
  switch (order) {
    case RayOrder::kScanline: return "scanline";
    case RayOrder::kBlock4x2: return "block4x2";
    case RayOrder::kBlock8x8: return "block8x8";
  }
  return "unknown";
}

namespace {

bool Finite(const glm::vec3& v) {
  return std::isfinite(v.x) && std::isfinite(v.y) && std::isfinite(v.z);
}

std::string Vec(const glm::vec3& v) {
  return "(" + std::to_string(v.x) + ", " + std::to_string(v.y) + ", " + std::to_string(v.z) +
         ")";
}

// Normalizes in double and rounds once, so the basis does not depend on float summation order.
glm::vec3 NormalizeD(const glm::dvec3& v) { return glm::vec3(v / glm::length(v)); }

}  // namespace

CameraBasis MakeCameraBasis(const Camera& camera, int width, int height) {
  if (width < 1 || height < 1) {
    throw Error("camera: image size " + std::to_string(width) + "x" + std::to_string(height) +
                " must be at least 1x1");
  }
  if (static_cast<uint64_t>(width) * static_cast<uint64_t>(height) >=
      (uint64_t{1} << 32)) {
    throw Error("camera: image size " + std::to_string(width) + "x" + std::to_string(height) +
                " has >= 2^32 pixels (pixel ids are 32-bit)");
  }
  if (!Finite(camera.eye) || !Finite(camera.look_at) || !Finite(camera.up)) {
    throw Error("camera: eye " + Vec(camera.eye) + ", look_at " + Vec(camera.look_at) +
                " or up " + Vec(camera.up) + " is not finite");
  }
  if (!(camera.fov_y_deg > 0.0f && camera.fov_y_deg < 180.0f)) {
    throw Error("camera: fov_y_deg " + std::to_string(camera.fov_y_deg) +
                " must be in (0, 180)");
  }
  const glm::dvec3 eye(camera.eye);
  const glm::dvec3 to(glm::dvec3(camera.look_at) - eye);
  const double dist = glm::length(to);
  if (!(dist > 0.0)) throw Error("camera: eye and look_at are both " + Vec(camera.eye));
  const glm::dvec3 f = to / dist;

  glm::dvec3 up(camera.up);
  const double up_len = glm::length(up);
  // Up parallel to the view (or zero): take the world axis least aligned with f.
  if (!(up_len > 0.0) || glm::length(glm::cross(f, up / up_len)) < 1e-6) {
    const glm::dvec3 a = glm::abs(f);
    up = (a.y <= a.x && a.y <= a.z) ? glm::dvec3(0, 1, 0)
         : (a.z <= a.x)             ? glm::dvec3(0, 0, 1)
                                    : glm::dvec3(1, 0, 0);
  }
  const glm::dvec3 r = glm::normalize(glm::cross(f, up));
  const glm::dvec3 u = glm::cross(r, f);

  CameraBasis b;
  b.eye = camera.eye;
  b.forward = NormalizeD(f);
  b.right = NormalizeD(r);
  b.up = NormalizeD(u);
  const double tan_half = std::tan(static_cast<double>(camera.fov_y_deg) * (std::numbers::pi / 360.0));
  b.tan_half_y = static_cast<float>(tan_half);
  b.tan_half_x = static_cast<float>(tan_half * width / height);
  b.fwidth = static_cast<float>(width);
  b.fheight = static_cast<float>(height);
  b.width = width;
  b.height = height;
  return b;
}

glm::vec3 PrimaryDirection(const CameraBasis& b, int x, int y) {
  // Screen coordinates of the pixel centre in [-1, 1]; y grows downwards in the image.
  const float sx = ((2.0f * static_cast<float>(x) + 1.0f) / b.fwidth - 1.0f) * b.tan_half_x;
  const float sy = (1.0f - (2.0f * static_cast<float>(y) + 1.0f) / b.fheight) * b.tan_half_y;
  const float dx = b.forward.x + sx * b.right.x + sy * b.up.x;
  const float dy = b.forward.y + sx * b.right.y + sy * b.up.y;
  const float dz = b.forward.z + sx * b.right.z + sy * b.up.z;
  const float len = std::sqrt(dx * dx + dy * dy + dz * dz);  // >= 1 - eps: forward is unit
  return glm::vec3(dx / len, dy / len, dz / len);
}

namespace {

// Blocks of kW x kH pixels (see RayOrder): every block row but the last is kH high and every
// block but the last in its row kW wide, so the block and the position inside it follow from
// two divisions.
template <size_t kW, size_t kH>
void BlockPixel(const Tile& tile, size_t i, int& x, int& y) {
  const size_t tw = static_cast<size_t>(tile.Width());
  const size_t row = i / (kH * tw);
  const int row_y = tile.y0 + static_cast<int>(kH * row);
  const size_t bh = std::min(kH, static_cast<size_t>(tile.y1 - row_y));
  const size_t r = i - row * kH * tw;
  const size_t block = r / (kW * bh);
  const size_t p = r - block * kW * bh;
  const int bx = tile.x0 + static_cast<int>(kW * block);
  const size_t bw = std::min(kW, static_cast<size_t>(tile.x1 - bx));
  x = bx + static_cast<int>(p % bw);
  y = row_y + static_cast<int>(p / bw);
}

}  // namespace

void TilePixel(const Tile& tile, RayOrder order, size_t i, int& x, int& y) {
  switch (order) {
    case RayOrder::kScanline: {
      const size_t tw = static_cast<size_t>(tile.Width());
      x = tile.x0 + static_cast<int>(i % tw);
      y = tile.y0 + static_cast<int>(i / tw);
      return;
    }
    case RayOrder::kBlock4x2: return BlockPixel<4, 2>(tile, i, x, y);
    case RayOrder::kBlock8x8: return BlockPixel<8, 8>(tile, i, x, y);
  }
  HWY_ABORT("unknown ray order %d", static_cast<int>(order));
}

namespace {

// A tile's pixels in `order` from index i on, a step at a time: TilePixel(i), TilePixel(i + 1),
// ... without its divisions. Every order is a walk over blocks (scanline: blocks of one tile-wide
// row), row by row inside a block, blocks left to right, block rows top to bottom, the last
// block of a row and the last block row clipped to the tile.
class TileWalk {
 public:
  TileWalk(const Tile& tile, RayOrder order, size_t i) : tile_(tile) {
    kw_ = order == RayOrder::kScanline ? tile.Width() : order == RayOrder::kBlock4x2 ? 4 : 8;
    kh_ = order == RayOrder::kScanline ? 1 : order == RayOrder::kBlock4x2 ? 2 : 8;
    TilePixel(tile, order, i, x_, y_);
    bx_ = tile.x0 + (x_ - tile.x0) / kw_ * kw_;
    by_ = tile.y0 + (y_ - tile.y0) / kh_ * kh_;
    bx1_ = std::min(bx_ + kw_, tile.x1);
    by1_ = std::min(by_ + kh_, tile.y1);
  }
  int x() const { return x_; }
  int y() const { return y_; }
  // The next pixel (past the tile's last one: unspecified).
  void Next() {
    if (++x_ < bx1_) return;
    x_ = bx_;
    if (++y_ < by1_) return;
    bx_ += kw_;
    if (bx_ >= tile_.x1) {
      bx_ = tile_.x0;
      by_ += kh_;
      by1_ = std::min(by_ + kh_, tile_.y1);
    }
    bx1_ = std::min(bx_ + kw_, tile_.x1);
    x_ = bx_;
    y_ = by_;
  }

 private:
  const Tile& tile_;
  int kw_ = 1, kh_ = 1;    // block size
  int bx_ = 0, by_ = 0;    // the block's first pixel
  int bx1_ = 0, by1_ = 0;  // its end (clipped)
  int x_ = 0, y_ = 0;
};

}  // namespace

void GeneratePrimaryRays(const CameraBasis& basis, const Tile& tile, RayOrder order,
                         size_t first, size_t count, const RayStreamView& out, size_t offset) {
  HWY_DASSERT(tile.x0 >= 0 && tile.y0 >= 0 && tile.x1 <= basis.width &&
              tile.y1 <= basis.height);
  HWY_DASSERT(first + count <= tile.NumPixels());
  if (count == 0) return;
  const float inf = std::numeric_limits<float>::infinity();
  constexpr size_t kBlock = 256;
  int32_t xs[kBlock], ys[kBlock];
  TileWalk walk(tile, order, first);
  const uint32_t width = static_cast<uint32_t>(basis.width);
  for (size_t k0 = 0; k0 < count; k0 += kBlock) {
    const size_t m = std::min(kBlock, count - k0);
    const size_t j0 = offset + k0;
    for (size_t k = 0; k < m; ++k, walk.Next()) {
      xs[k] = walk.x();
      ys[k] = walk.y();
      out.pixel[j0 + k] = static_cast<uint32_t>(walk.y()) * width + static_cast<uint32_t>(walk.x());
    }
    PrimaryDirections(basis, xs, ys, m, out.dx + j0, out.dy + j0, out.dz + j0);
  }
  const size_t end = offset + count;
  std::fill(out.ox + offset, out.ox + end, basis.eye.x);
  std::fill(out.oy + offset, out.oy + end, basis.eye.y);
  std::fill(out.oz + offset, out.oz + end, basis.eye.z);
  std::fill(out.tmin + offset, out.tmin + end, 0.0f);
  std::fill(out.tmax + offset, out.tmax + end, inf);
  std::fill(out.wr + offset, out.wr + end, 1.0f);
  std::fill(out.wg + offset, out.wg + end, 1.0f);
  std::fill(out.wb + offset, out.wb + end, 1.0f);
  std::fill(out.depth + offset, out.depth + end, 0);
  std::fill(out.kind + offset, out.kind + end, static_cast<int32_t>(RayKind::kPrimary));
}

void AppendPrimaryRays(const CameraBasis& basis, const Tile& tile, RayOrder order,
                       RayStream& out) {
  const size_t n = tile.NumPixels();
  const size_t offset = out.size();
  out.Resize(offset + n);
  GeneratePrimaryRays(basis, tile, order, 0, n, out.view(), offset);
}

}  // namespace rs
