// Primary ray generation: pinhole-camera rays for a rectangular tile, in scanline or 4x2-block
// order. A pixel's ray depends only on (x, y, width, height, camera), never on the tile or the
// order, so every backend and every tiling produce bit-identical rays.
#pragma once

#include <glm/glm.hpp>

#include <cstddef>
#include <cstdint>

#include "include/raystream/raystream.h"
#include "scenes/scene.h"
#include "streams/ray_stream.h"

namespace rs {

// The order of the rays of one tile in the stream.
enum class RayOrder : int {
  kScanline = 0,  // row by row, x fastest
  kBlock4x2 = 1,  // blocks of 4 wide x 2 high in scanline order of blocks (x fastest inside a
                  // block); blocks start at the tile's (x0, y0), partial blocks at the right
                  // and bottom tile edges hold the remaining 1..3 columns / 1 row
  kBlock8x8 = 2,  // the same with blocks of 8 x 8: a 64-ray packet is a square of pixels, not
                  // two rows of a tile, so its footprint in the grid is smallest
};
const char* RayOrderName(RayOrder order);

// Pixel rectangle [x0, x1) x [y0, y1) of the image; empty if x1 <= x0 or y1 <= y0.
struct Tile {
  int x0 = 0;
  int y0 = 0;
  int x1 = 0;
  int y1 = 0;
  int Width() const { return x1 > x0 ? x1 - x0 : 0; }
  int Height() const { return y1 > y0 ? y1 - y0 : 0; }
  size_t NumPixels() const { return static_cast<size_t>(Width()) * static_cast<size_t>(Height()); }
};

// The camera basis precomputed once per frame (and per image size). A pixel's direction is
//   d = normalize(forward + sx * right + sy * up),
//   sx = ((2x + 1) / width - 1) * tan_half_x,   sy = (1 - (2y + 1) / height) * tan_half_y,
// evaluated in float, with a true division (so the centre pixel of an odd-sized image gets
// sx = 0 exactly) and no contraction (the build uses -std=c++20: no FMA contraction).
struct CameraBasis {
  glm::vec3 eye{0.0f};
  glm::vec3 forward{0.0f, 0.0f, -1.0f};  // unit, eye -> look_at
  glm::vec3 right{1.0f, 0.0f, 0.0f};     // unit, forward x up
  glm::vec3 up{0.0f, 1.0f, 0.0f};        // unit, right x forward
  float tan_half_x = 0.0f;  // tan(fov_y / 2) * width / height
  float tan_half_y = 0.0f;  // tan(fov_y / 2)
  float fwidth = 0.0f;   // width as float
  float fheight = 0.0f;  // height as float
  int width = 0;
  int height = 0;
};

// Builds the basis for a width x height image. If camera.up is (nearly) parallel to the view
// direction, the world axis least aligned with it is used instead (so a camera looking
// straight down still works). Throws rs::Error if width/height < 1, width * height >= 2^32,
// eye/look_at/up/fov are not finite, eye == look_at, or fov_y_deg is outside (0, 180).
CameraBasis MakeCameraBasis(const Camera& camera, int width, int height);

// The normalized primary direction through the centre of pixel (x, y). Pure function of
// (x, y, basis): the single definition of primary directions (PrimaryDirections is its vector
// form, bit for bit).
glm::vec3 PrimaryDirection(const CameraBasis& basis, int x, int y);

// PrimaryDirection(basis, x[i], y[i]) for i < n, bit for bit, a vector of pixels at a time on
// the best SIMD target, into (dx[i], dy[i], dz[i]). No alignment required.
void PrimaryDirections(const CameraBasis& basis, const int32_t* x, const int32_t* y, size_t n,
                       float* dx, float* dy, float* dz);

// The pixel of the i-th ray of `tile` in `order` (0 <= i < tile.NumPixels()), O(1).
void TilePixel(const Tile& tile, RayOrder order, size_t i, int& x, int& y);

// Writes the rays i in [first, first + count) of `tile` in `order` to out[offset, offset +
// count): origin = eye, normalized direction, tmin 0, tmax +inf, pixel y * width + x, weight 1,
// depth 0, kind primary. `out` must have room for offset + count rays (all optional arrays
// non-null). The tile must lie inside the image. Never allocates.
void GeneratePrimaryRays(const CameraBasis& basis, const Tile& tile, RayOrder order,
                         size_t first, size_t count, const RayStreamView& out, size_t offset);

// Appends all rays of `tile` in `order` to `out` (grows it; padding is not refilled).
void AppendPrimaryRays(const CameraBasis& basis, const Tile& tile, RayOrder order,
                       RayStream& out);

}  // namespace rs
