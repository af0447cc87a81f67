// Primary ray generation: tile coverage in both orders, partial 4x2 blocks, camera geometry,
// and bit-identical rays whatever the tiling (the backend-independence precondition).
#include "streams/raygen.h"

#include <doctest/doctest.h>

#include <cmath>
#include <cstring>
#include <limits>
#include <map>
#include <utility>
#include <random>
#include <vector>

#include "tests/test_util.h"

namespace rs {
namespace {

Camera TestCamera() {
  Camera c;
  c.eye = glm::vec3(1.0f, 2.0f, 3.0f);
  c.look_at = glm::vec3(-0.5f, 0.25f, -4.0f);
  c.up = glm::vec3(0.1f, 1.0f, 0.0f);
  c.fov_y_deg = 55.0f;
  return c;
}

std::vector<std::pair<int, int>> Pixels(const Tile& tile, RayOrder order, int width) {
  const CameraBasis basis = MakeCameraBasis(TestCamera(), width, tile.y1 + 1);
  RayStream s;
  AppendPrimaryRays(basis, tile, order, s);
  std::vector<std::pair<int, int>> px;
  const RayStreamView v = s.view();
  for (size_t i = 0; i < v.size; ++i) {
    px.emplace_back(static_cast<int>(v.pixel[i] % width), static_cast<int>(v.pixel[i] / width));
  }
  return px;
}

TEST_CASE("tile coverage: every pixel exactly once, both orders, odd tiles") {
  const int width = 23;
  for (const RayOrder order : {RayOrder::kScanline, RayOrder::kBlock4x2, RayOrder::kBlock8x8}) {
    for (int x0 : {0, 3}) {
      for (int y0 : {0, 5}) {
        for (int tw = 0; tw <= 11; ++tw) {
          for (int th = 0; th <= 5; ++th) {
            const Tile tile{x0, y0, x0 + tw, y0 + th};
            INFO("order ", RayOrderName(order), " tile ", x0, ",", y0, " ", tw, "x", th);
            const auto px = Pixels(tile, order, width);
            REQUIRE(px.size() == static_cast<size_t>(tw * th));
            std::vector<int> seen(static_cast<size_t>(tw * th), 0);
            for (const auto& [x, y] : px) {
              REQUIRE(x >= tile.x0);
              REQUIRE(x < tile.x1);
              REQUIRE(y >= tile.y0);
              REQUIRE(y < tile.y1);
              ++seen[static_cast<size_t>((y - y0) * tw + (x - x0))];
            }
            for (const int s : seen) CHECK(s == 1);
          }
        }
      }
    }
  }
}

TEST_CASE("scanline order is row by row") {
  const auto px = Pixels(Tile{2, 1, 5, 3}, RayOrder::kScanline, 10);
  const std::vector<std::pair<int, int>> want = {{2, 1}, {3, 1}, {4, 1}, {2, 2}, {3, 2}, {4, 2}};
  CHECK(px == want);
}

TEST_CASE("4x2 block order with partial blocks at the right and bottom edges") {
  // Tile 6 x 3 at (1, 1): block row 0 = block [1,5)x[1,3) then partial [5,7)x[1,3);
  // block row 1 (1 high) = [1,5)x[3,4) then [5,7)x[3,4).
  const auto px = Pixels(Tile{1, 1, 7, 4}, RayOrder::kBlock4x2, 9);
  const std::vector<std::pair<int, int>> want = {
      {1, 1}, {2, 1}, {3, 1}, {4, 1}, {1, 2}, {2, 2}, {3, 2}, {4, 2},  // full block
      {5, 1}, {6, 1}, {5, 2}, {6, 2},                                  // 2 wide
      {1, 3}, {2, 3}, {3, 3}, {4, 3},                                  // 1 high
      {5, 3}, {6, 3}};                                                 // 2 x 1
  CHECK(px == want);
  // A tile narrower than a block: 3 wide, 4 high -> blocks of 3 x 2.
  const auto narrow = Pixels(Tile{0, 0, 3, 4}, RayOrder::kBlock4x2, 3);
  const std::vector<std::pair<int, int>> want_narrow = {{0, 0}, {1, 0}, {2, 0}, {0, 1},
                                                        {1, 1}, {2, 1}, {0, 2}, {1, 2},
                                                        {2, 2}, {0, 3}, {1, 3}, {2, 3}};
  CHECK(narrow == want_narrow);
}

TEST_CASE("8x8 block order: full blocks, then the partial ones at the right and bottom edges") {
  // Tile 11 x 10 at (2, 3): block row 0 = [2,10)x[3,11) (64 rays) then [10,13)x[3,11) (3 wide);
  // block row 1 (2 high) = [2,10)x[11,13) then [10,13)x[11,13).
  const auto px = Pixels(Tile{2, 3, 13, 13}, RayOrder::kBlock8x8, 14);
  REQUIRE(px.size() == 110);
  std::vector<std::pair<int, int>> want;
  auto block = [&](int x0, int y0, int x1, int y1) {
    for (int y = y0; y < y1; ++y) {
      for (int x = x0; x < x1; ++x) want.emplace_back(x, y);
    }
  };
  block(2, 3, 10, 11);
  block(10, 3, 13, 11);
  block(2, 11, 10, 13);
  block(10, 11, 13, 13);
  CHECK(px == want);
}

TEST_CASE("generation in chunks walks TilePixel's order from any first pixel") {
  // GeneratePrimaryRays steps from pixel to pixel; TilePixel computes each one on its own.
  const int width = 31, height = 25;
  const CameraBasis basis = MakeCameraBasis(TestCamera(), width, height);
  for (const RayOrder order : {RayOrder::kScanline, RayOrder::kBlock4x2, RayOrder::kBlock8x8}) {
    for (const Tile tile : {Tile{0, 0, 31, 25}, Tile{3, 2, 20, 19}, Tile{5, 7, 6, 25},
                            Tile{1, 1, 30, 2}, Tile{8, 8, 16, 16}, Tile{2, 3, 9, 12}}) {
      const size_t n = tile.NumPixels();
      for (const size_t chunk : {size_t{1}, size_t{5}, size_t{64}, size_t{300}}) {
        INFO("order ", RayOrderName(order), " tile ", tile.x0, ",", tile.y0, "-", tile.x1, ",",
             tile.y1, " chunk ", chunk);
        RayStream s;
        s.Resize(n);
        for (size_t first = 0; first < n; first += chunk) {
          GeneratePrimaryRays(basis, tile, order, first, std::min(chunk, n - first), s.view(),
                              first);
        }
        const RayStreamView v = s.view();
        size_t same = 0;
        for (size_t i = 0; i < n; ++i) {
          int x = -1, y = -1;
          TilePixel(tile, order, i, x, y);
          same += v.pixel[i] == static_cast<uint32_t>(y * width + x) ? 1 : 0;
        }
        CHECK(same == n);
      }
    }
  }
}

TEST_CASE("ray fields: origin, normalized direction, tmin, tmax, pixel id, weight, kind") {
  const Camera cam = TestCamera();
  const CameraBasis basis = MakeCameraBasis(cam, 37, 21);
  RayStream s;
  AppendPrimaryRays(basis, Tile{0, 0, 37, 21}, RayOrder::kScanline, s);
  const RayStreamView v = s.view();
  REQUIRE(v.size == 37u * 21u);
  for (size_t i = 0; i < v.size; ++i) {
    CHECK(v.ox[i] == cam.eye.x);
    CHECK(v.oy[i] == cam.eye.y);
    CHECK(v.oz[i] == cam.eye.z);
    const float len = std::sqrt(v.dx[i] * v.dx[i] + v.dy[i] * v.dy[i] + v.dz[i] * v.dz[i]);
    CHECK(len == doctest::Approx(1.0f).epsilon(1e-6));
    CHECK(v.tmin[i] == 0.0f);
    CHECK(v.tmax[i] == std::numeric_limits<float>::infinity());
    CHECK(v.pixel[i] == i);  // scanline over the whole image: id = y * width + x = i
    CHECK(v.wr[i] == 1.0f);
    CHECK(v.wg[i] == 1.0f);
    CHECK(v.wb[i] == 1.0f);
    CHECK(v.depth[i] == 0);
    CHECK(v.kind[i] == static_cast<int32_t>(RayKind::kPrimary));
  }
}

TEST_CASE("camera geometry: centre ray hits look_at, field of view, orientation") {
  const Camera cam = TestCamera();
  const int w = 41, h = 31;  // odd: a pixel centre lies on the optical axis
  const CameraBasis basis = MakeCameraBasis(cam, w, h);
  const glm::vec3 centre = PrimaryDirection(basis, w / 2, h / 2);
  const glm::vec3 want = glm::normalize(cam.look_at - cam.eye);
  CHECK(centre.x == doctest::Approx(want.x).epsilon(1e-6));
  CHECK(centre.y == doctest::Approx(want.y).epsilon(1e-6));
  CHECK(centre.z == doctest::Approx(want.z).epsilon(1e-6));

  // The angle to the centre ray of pixel (w/2, 0) is atan((1 - 1/h) tan(fov/2)).
  const glm::vec3 top = PrimaryDirection(basis, w / 2, 0);
  const double angle = std::acos(std::min(1.0, static_cast<double>(glm::dot(top, centre))));
  const double want_angle =
      std::atan((1.0 - 1.0 / h) * std::tan(cam.fov_y_deg * 3.14159265358979 / 360.0));
  CHECK(angle == doctest::Approx(want_angle).epsilon(1e-4));
  // Square pixels: pixel (w-1, h/2) is as far horizontally as (w/2 + (w-1)/2) predicts.
  const glm::vec3 right = PrimaryDirection(basis, w - 1, h / 2);
  const double hangle = std::atan(static_cast<double>(w - 1) / w *
                                  std::tan(cam.fov_y_deg * 3.14159265358979 / 360.0) * w / h);
  CHECK(std::acos(static_cast<double>(glm::dot(right, centre))) ==
        doctest::Approx(hangle).epsilon(1e-4));

  // Orientation: row 0 is the top (towards up), column 0 is the left (against right).
  const glm::vec3 up_dir = glm::normalize(cam.up - glm::dot(cam.up, want) * want);
  const glm::vec3 right_dir = glm::normalize(glm::cross(want, cam.up));
  CHECK(glm::dot(top, up_dir) > 0.1f);
  CHECK(glm::dot(PrimaryDirection(basis, w / 2, h - 1), up_dir) < -0.1f);
  CHECK(glm::dot(PrimaryDirection(basis, 0, h / 2), right_dir) < -0.1f);
  CHECK(glm::dot(right, right_dir) > 0.1f);
}

TEST_CASE("rays are bit-identical whatever the tile split and order") {
  const int w = 29, h = 17;
  const CameraBasis basis = MakeCameraBasis(TestCamera(), w, h);
  auto key = [](const RayStreamView& v, size_t i) {
    std::vector<uint32_t> bits(6);
    const float f[6] = {v.ox[i], v.oy[i], v.oz[i], v.dx[i], v.dy[i], v.dz[i]};
    std::memcpy(bits.data(), f, sizeof(f));
    return bits;
  };
  std::map<uint32_t, std::vector<uint32_t>> whole;
  {
    RayStream s;
    AppendPrimaryRays(basis, Tile{0, 0, w, h}, RayOrder::kScanline, s);
    const RayStreamView v = s.view();
    for (size_t i = 0; i < v.size; ++i) whole[v.pixel[i]] = key(v, i);
  }
  REQUIRE(whole.size() == static_cast<size_t>(w * h));
  for (const RayOrder order : {RayOrder::kScanline, RayOrder::kBlock4x2, RayOrder::kBlock8x8}) {
    for (const int ts : {1, 3, 4, 7, 16}) {
      INFO("order ", RayOrderName(order), " tile size ", ts);
      RayStream s;
      for (int y = 0; y < h; y += ts) {
        for (int x = 0; x < w; x += ts) {
          AppendPrimaryRays(basis, Tile{x, y, std::min(x + ts, w), std::min(y + ts, h)}, order,
                            s);
        }
      }
      const RayStreamView v = s.view();
      REQUIRE(v.size == static_cast<size_t>(w * h));
      size_t same = 0;
      for (size_t i = 0; i < v.size; ++i) same += whole.at(v.pixel[i]) == key(v, i) ? 1 : 0;
      CHECK(same == v.size);
    }
  }
  // Generating a tile in chunks (as tasks do) gives the same rays as generating it at once.
  const Tile tile{3, 2, 26, 15};
  RayStream all, chunks;
  AppendPrimaryRays(basis, tile, RayOrder::kBlock4x2, all);
  chunks.Resize(tile.NumPixels());
  for (size_t first = 0; first < tile.NumPixels(); first += 7) {
    const size_t count = std::min<size_t>(7, tile.NumPixels() - first);
    GeneratePrimaryRays(basis, tile, RayOrder::kBlock4x2, first, count, chunks.view(), first);
  }
  const RayStreamView a = all.view(), c = chunks.view();
  for (size_t i = 0; i < a.size; ++i) {
    CHECK(a.pixel[i] == c.pixel[i]);
    CHECK(key(a, i) == key(c, i));
  }
}

TEST_CASE("PrimaryDirections == PrimaryDirection bit for bit on every SIMD target") {
  // Cameras of several shapes, up to images far wider than 2^24 / 2 pixels (where x no longer
  // converts exactly to float), random pixels and every length around a vector's width.
  struct Shape {
    int w, h;
    float fov;
  };
  const Shape shapes[] = {{29, 17, 55.0f}, {1024, 1024, 30.0f}, {33554431, 2, 90.0f},
                          {3, 65521, 1.0f}, {4096, 4096, 179.0f}};
  std::mt19937 rng(8);
  test::ForEachTarget([&](const char* target) {
    CAPTURE(target);
    size_t bad = 0, checked = 0;
    for (const Shape& sh : shapes) {
      Camera cam = TestCamera();
      cam.fov_y_deg = sh.fov;
      const CameraBasis basis = MakeCameraBasis(cam, sh.w, sh.h);
      for (const size_t n : {size_t{1}, size_t{3}, size_t{8}, size_t{15}, size_t{16},
                             size_t{17}, size_t{1000}}) {
        std::vector<int32_t> x(n), y(n);
        for (size_t i = 0; i < n; ++i) {
          x[i] = i == 0 ? sh.w - 1 : static_cast<int32_t>(rng() % static_cast<uint32_t>(sh.w));
          y[i] = i == 1 ? sh.h - 1 : static_cast<int32_t>(rng() % static_cast<uint32_t>(sh.h));
        }
        std::vector<float> dx(n), dy(n), dz(n);
        PrimaryDirections(basis, x.data(), y.data(), n, dx.data(), dy.data(), dz.data());
        for (size_t i = 0; i < n; ++i) {
          const glm::vec3 want = PrimaryDirection(basis, x[i], y[i]);
          const float got[3] = {dx[i], dy[i], dz[i]};
          bad += std::memcmp(got, &want[0], sizeof(got)) != 0 ? 1 : 0;
          ++checked;
        }
      }
    }
    CHECK(checked > 5000);
    CHECK(bad == 0);
    // GeneratePrimaryRays from a start in the middle of a row, across row ends, in chunks.
    const CameraBasis basis = MakeCameraBasis(TestCamera(), 700, 9);
    const Tile tile{5, 1, 610, 8};
    RayStream s;
    s.Resize(tile.NumPixels());
    for (size_t first = 0; first < tile.NumPixels(); first += 333) {
      const size_t count = std::min<size_t>(333, tile.NumPixels() - first);
      GeneratePrimaryRays(basis, tile, RayOrder::kScanline, first, count, s.view(), first);
    }
    const RayStreamView v = s.view();
    size_t wrong = 0;
    for (size_t i = 0; i < v.size; ++i) {
      int px = 0, py = 0;
      TilePixel(tile, RayOrder::kScanline, i, px, py);
      const glm::vec3 want = PrimaryDirection(basis, px, py);
      const float got[3] = {v.dx[i], v.dy[i], v.dz[i]};
      wrong += std::memcmp(got, &want[0], sizeof(got)) != 0 ? 1 : 0;
      wrong += v.pixel[i] != static_cast<uint32_t>(py * 700 + px) ? 1 : 0;
    }
    CHECK(wrong == 0);
  });
}

TEST_CASE("camera errors and degenerate up vector") {
  Camera cam = TestCamera();
  CHECK_THROWS_AS(MakeCameraBasis(cam, 0, 10), Error);
  CHECK_THROWS_AS(MakeCameraBasis(cam, 10, -1), Error);
  CHECK_THROWS_AS(MakeCameraBasis(cam, 70000, 70000), Error);  // >= 2^32 pixel ids
  Camera same = cam;
  same.look_at = same.eye;
  CHECK_THROWS_AS(MakeCameraBasis(same, 10, 10), Error);
  for (const float fov : {0.0f, -5.0f, 180.0f, std::numeric_limits<float>::quiet_NaN()}) {
    Camera bad = cam;
    bad.fov_y_deg = fov;
    CHECK_THROWS_AS(MakeCameraBasis(bad, 10, 10), Error);
  }
  Camera nan_eye = cam;
  nan_eye.eye.y = std::numeric_limits<float>::quiet_NaN();
  CHECK_THROWS_AS(MakeCameraBasis(nan_eye, 10, 10), Error);

  // Looking straight down with up = +y: a fallback up is chosen, rays stay finite and unit.
  Camera down;
  down.eye = glm::vec3(0, 5, 0);
  down.look_at = glm::vec3(0, 0, 0);
  down.up = glm::vec3(0, 1, 0);
  const CameraBasis b = MakeCameraBasis(down, 5, 5);
  const glm::vec3 c = PrimaryDirection(b, 2, 2);
  CHECK(c.y == doctest::Approx(-1.0f).epsilon(1e-6));
  const glm::vec3 corner = PrimaryDirection(b, 0, 0);
  CHECK(std::isfinite(corner.x));
  CHECK(glm::length(corner) == doctest::Approx(1.0f).epsilon(1e-6));
  CHECK(glm::dot(b.right, b.up) == doctest::Approx(0.0f).epsilon(1e-6));
}

}  // namespace
}  // namespace rs
