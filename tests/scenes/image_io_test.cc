// Image I/O: PNG (8-bit sRGB, clamped) and EXR (half) round trips with tolerances, grey and
// RGBA input, and failed writes that leave nothing behind.
#include "scenes/image_io.h"

#include <OpenImageIO/imageio.h>
#include <doctest/doctest.h>
#include <unistd.h>

#include <bit>
#include <cmath>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <limits>
#include <string>
#include <vector>

namespace rs {
namespace {

namespace fs = std::filesystem;

class TempDir {
 public:
  TempDir() {
    static int counter = 0;
    path_ = fs::temp_directory_path() /
            ("raystream_image_test_" + std::to_string(getpid()) + "_" + std::to_string(counter++));
    fs::remove_all(path_);
    fs::create_directories(path_);
  }
  ~TempDir() {
    std::error_code ec;
    fs::remove_all(path_, ec);
  }
  std::string File(const std::string& name) const { return (path_ / name).string(); }
  size_t Entries() const {
    size_t n = 0;
    for ([[maybe_unused]] const auto& e : fs::directory_iterator(path_)) ++n;
    return n;
  }

 private:
  fs::path path_;
};

float ToSrgb(float x) {
  x = std::clamp(x, 0.0f, 1.0f);
  return x <= 0.0031308f ? 12.92f * x : 1.055f * std::pow(x, 1.0f / 2.4f) - 0.055f;
}

// A w x h test pattern: gradients in each channel, values in [0, 1].
std::vector<float> Pattern(int w, int h) {
  std::vector<float> rgb(static_cast<size_t>(w) * h * 3);
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) {
      float* p = &rgb[(static_cast<size_t>(y) * w + x) * 3];
      p[0] = static_cast<float>(x) / static_cast<float>(w - 1);
      p[1] = static_cast<float>(y) / static_cast<float>(h - 1);
      p[2] = static_cast<float>((x * 7 + y * 3) % 11) / 10.0f;
    }
  }
  return rgb;
}

template <typename F>
std::string ExpectError(F&& f) {
  try {
    f();
  } catch (const Error& e) {
    return e.what();
  }
  FAIL("no rs::Error thrown");
  return "";
}

TEST_CASE("PNG round trip: 8-bit sRGB within half a code value") {
  TempDir dir;
  const int w = 17, h = 9;  // odd sizes: no row padding assumptions
  const std::vector<float> rgb = Pattern(w, h);
  const std::string path = dir.File("pattern.png");
  WriteImage(path, w, h, rgb);
  CHECK(dir.Entries() == 1);  // no temporary left
  const Texture t = ReadImage(path);
  CHECK(t.path == path);
  REQUIRE(t.width == w);
  REQUIRE(t.height == h);
  REQUIRE(t.rgb.size() == rgb.size());
  float max_code_error = 0.0f;
  for (size_t i = 0; i < rgb.size(); ++i) {
    max_code_error = std::max(max_code_error, std::fabs(ToSrgb(t.rgb[i]) - ToSrgb(rgb[i])) * 255);
  }
  CHECK(max_code_error <= 0.5f + 1e-3f);
  // Row 0 is the top: pixel (16, 0) has r = 1, g = 0.
  CHECK(t.rgb[16 * 3 + 0] == doctest::Approx(1.0f).epsilon(1e-6));
  CHECK(t.rgb[16 * 3 + 1] == doctest::Approx(0.0f));
  // Linear mid grey 0.5 is stored as sRGB code 188 (not 128) and decoded back.
  WriteImage(path, 1, 1, {0.5f, 0.5f, 0.5f});
  auto in = OIIO::ImageInput::open(path);
  REQUIRE(in);
  unsigned char code[3];
  REQUIRE(in->read_image(0, 0, 0, 3, OIIO::TypeDesc::UINT8, code));
  CHECK(code[0] == 188);
  CHECK(ReadImage(path).rgb[0] == doctest::Approx(0.5f).epsilon(0.005));
}

// The reference LinearToSrgb8 must equal: the transfer function in double, the nearest code
// (halves up), clamped.
int ReferenceSrgb8(float x) {
  if (!(x > 0.0f)) return 0;
  if (x >= 1.0f) return 255;
  const double d = x;
  const double s = d <= 0.0031308 ? 12.92 * d : 1.055 * std::pow(d, 1.0 / 2.4) - 0.055;
  return static_cast<int>(std::floor(s * 255.0 + 0.5));
}

TEST_CASE("8-bit sRGB codes: the nearest code of the double-precision transfer function") {
  // Every code's first float and the 64 floats on either side of it (where a table lookup
  // would go wrong first), a million random floats in (0, 1), and special values.
  const auto next = [](float x, int steps) {
    return std::bit_cast<float>(static_cast<uint32_t>(
        static_cast<int64_t>(std::bit_cast<uint32_t>(x)) + steps));
  };
  size_t checked = 0, wrong = 0;
  const auto check = [&](float x) {
    ++checked;
    if (LinearToSrgb8(x) != ReferenceSrgb8(x)) {
      if (++wrong <= 5) MESSAGE("x = ", x, ": ", int(LinearToSrgb8(x)), " != ", ReferenceSrgb8(x));
    }
  };
  int code = 0;
  for (uint32_t bits = 0; bits <= 0x3f800000u; bits += 1u << 12) {  // coarse sweep, monotone
    const float x = std::bit_cast<float>(bits);
    const int c = LinearToSrgb8(x);
    CHECK(c >= code);
    code = c;
    check(x);
  }
  for (int k = 1; k <= 255; ++k) {
    // the first float of code k: bisection on the reference
    uint32_t lo = 0, hi = 0x3f800000u;
    while (hi - lo > 1) {
      const uint32_t mid = lo + (hi - lo) / 2;
      (ReferenceSrgb8(std::bit_cast<float>(mid)) >= k ? hi : lo) = mid;
    }
    for (int d = -64; d <= 64; ++d) check(next(std::bit_cast<float>(hi), d));
  }
  uint64_t state = 0x9E3779B97F4A7C15ull;
  for (int i = 0; i < 1000000; ++i) {
    state = state * 6364136223846793005ull + 1442695040888963407ull;
    check(static_cast<float>(state >> 40) * 0x1p-24f);
  }
  const float inf = std::numeric_limits<float>::infinity();
  for (const float x : {0.0f, -0.0f, -1.0f, -inf, inf, 1.0f, 2.0f, 1e-45f, 1e-38f, 0.0031308f,
                        std::nextafter(1.0f, 0.0f), std::numeric_limits<float>::quiet_NaN()}) {
    check(x);
  }
  CHECK(wrong == 0);
  CHECK(checked > 1000000);
  CHECK(LinearToSrgb8(0.5f) == 188);  // linear mid grey
  CHECK(LinearToSrgb8(0.18f) == 118);
  // the bulk form gives the same codes
  const std::vector<float> in = {0.5f, -1.0f, 0.18f, 1.0f, 0.0f, 0.999f, 1e-4f};
  std::vector<uint8_t> out(in.size());
  LinearToSrgb8(in.data(), in.size(), out.data());
  for (size_t i = 0; i < in.size(); ++i) CHECK(out[i] == LinearToSrgb8(in[i]));
}

TEST_CASE("PNG clamps out-of-range values; NaN becomes black") {
  TempDir dir;
  const std::string path = dir.File("clamp.png");
  const float nan = std::numeric_limits<float>::quiet_NaN();
  WriteImage(path, 2, 1, {-1.0f, 7.0f, nan, 1e30f, 0.0f, -0.0f});
  const Texture t = ReadImage(path);
  REQUIRE(t.rgb.size() == 6);
  CHECK(t.rgb[0] == 0.0f);
  CHECK(t.rgb[1] == doctest::Approx(1.0f));
  CHECK(t.rgb[2] == 0.0f);
  CHECK(t.rgb[3] == doctest::Approx(1.0f));
  CHECK(t.rgb[4] == 0.0f);
}

TEST_CASE("EXR round trip: half floats, values above 1 kept") {
  TempDir dir;
  const int w = 5, h = 3;
  std::vector<float> rgb = Pattern(w, h);
  rgb[0] = 7.5f;
  rgb[1] = 1e-3f;
  rgb[2] = 250.0f;
  const std::string path = dir.File("hdr.exr");
  WriteImage(path, w, h, rgb);
  const Texture t = ReadImage(path);
  REQUIRE(t.width == w);
  REQUIRE(t.height == h);
  for (size_t i = 0; i < rgb.size(); ++i) {
    INFO("i = ", i);
    CHECK(t.rgb[i] == doctest::Approx(rgb[i]).epsilon(1e-3).scale(1e-4));  // half: 11 bits
  }
}

TEST_CASE("failed writes throw naming the path and leave no file") {
  TempDir dir;
  const std::vector<float> rgb = Pattern(4, 4);
  SUBCASE("directory does not exist") {
    const std::string path = dir.File("no/such/dir/out.png");
    const std::string what = ExpectError([&] { WriteImage(path, 4, 4, rgb); });
    CHECK(what.find(path) != std::string::npos);
    CHECK(dir.Entries() == 0);
  }
  SUBCASE("parent is a regular file") {
    std::ofstream(dir.File("plain")) << "x";
    const std::string path = dir.File("plain/out.png");
    const std::string what = ExpectError([&] { WriteImage(path, 4, 4, rgb); });
    CHECK(what.find(path) != std::string::npos);
    CHECK(dir.Entries() == 1);
  }
  SUBCASE("target is a directory: the finished temporary is removed") {
    fs::create_directories(dir.File("taken.png/inside"));
    const std::string path = dir.File("taken.png");
    const std::string what = ExpectError([&] { WriteImage(path, 4, 4, rgb); });
    CHECK(what.find(path) != std::string::npos);
    CHECK(dir.Entries() == 1);  // only the directory itself
    CHECK(fs::is_directory(path));
  }
  SUBCASE("read-only directory") {
    if (geteuid() == 0) return;  // root writes anyway
    fs::create_directories(dir.File("ro"));
    fs::permissions(dir.File("ro"), fs::perms::owner_read | fs::perms::owner_exec);
    const std::string path = dir.File("ro/out.png");
    const std::string what = ExpectError([&] { WriteImage(path, 4, 4, rgb); });
    CHECK(what.find(path) != std::string::npos);
    CHECK(fs::is_empty(dir.File("ro")));
    fs::permissions(dir.File("ro"), fs::perms::owner_all);
  }
  SUBCASE("unknown or missing extension") {
    std::string what = ExpectError([&] { WriteImage(dir.File("out.xyz"), 4, 4, rgb); });
    CHECK(what.find("out.xyz") != std::string::npos);
    CHECK(what.find(".xyz") != std::string::npos);
    what = ExpectError([&] { WriteImage(dir.File("noext"), 4, 4, rgb); });
    CHECK(what.find("noext") != std::string::npos);
    CHECK(dir.Entries() == 0);
  }
  SUBCASE("size mismatch") {
    const std::string what = ExpectError([&] { WriteImage(dir.File("a.png"), 5, 4, rgb); });
    CHECK(what.find("expected 60") != std::string::npos);
    ExpectError([&] { WriteImage(dir.File("a.png"), 0, 4, {}); });
    CHECK(dir.Entries() == 0);
  }
}

TEST_CASE("writing over an existing image replaces it") {
  TempDir dir;
  const std::string path = dir.File("frame.png");
  WriteImage(path, 2, 2, std::vector<float>(12, 0.0f));
  WriteImage(path, 3, 1, std::vector<float>(9, 1.0f));
  const Texture t = ReadImage(path);
  CHECK(t.width == 3);
  CHECK(t.rgb[0] == doctest::Approx(1.0f));
  CHECK(dir.Entries() == 1);
}

TEST_CASE("ReadImage: grey and RGBA inputs become rgb; missing files name the path") {
  TempDir dir;
  {
    const std::string path = dir.File("grey.png");
    auto out = OIIO::ImageOutput::create(path);
    REQUIRE(out);
    const OIIO::ImageSpec spec(2, 1, 1, OIIO::TypeDesc::UINT8);
    REQUIRE(out->open(path, spec));
    const unsigned char px[2] = {0, 255};
    REQUIRE(out->write_image(OIIO::TypeDesc::UINT8, px));
    out->close();
    const Texture t = ReadImage(path);
    REQUIRE(t.rgb.size() == 6);
    CHECK(t.rgb[0] == 0.0f);
    CHECK(t.rgb[3] == doctest::Approx(1.0f));
    CHECK(t.rgb[4] == doctest::Approx(1.0f));
    CHECK(t.rgb[5] == doctest::Approx(1.0f));
  }
  {
    const std::string path = dir.File("rgba.png");
    auto out = OIIO::ImageOutput::create(path);
    REQUIRE(out);
    OIIO::ImageSpec spec(1, 1, 4, OIIO::TypeDesc::UINT8);
    spec.attribute("oiio:UnassociatedAlpha", 1);  // store the bytes as given
    REQUIRE(out->open(path, spec));
    const unsigned char px[4] = {255, 188, 0, 10};
    REQUIRE(out->write_image(OIIO::TypeDesc::UINT8, px));
    out->close();
    const Texture t = ReadImage(path);
    REQUIRE(t.rgb.size() == 3);
    CHECK(t.rgb[0] == doctest::Approx(1.0f));
    CHECK(t.rgb[1] == doctest::Approx(0.5f).epsilon(0.01));  // sRGB 188 -> linear 0.5
    CHECK(t.rgb[2] == 0.0f);
  }
  const std::string missing = dir.File("missing.png");
  CHECK(ExpectError([&] { ReadImage(missing); }).find(missing) != std::string::npos);
  std::ofstream(dir.File("junk.png")) << "not an image";
  CHECK(ExpectError([&] { ReadImage(dir.File("junk.png")); }).find("junk.png") !=
        std::string::npos);
}

}  // namespace
}  // namespace rs
