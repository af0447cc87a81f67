// Fuzz target: texture files through ReadImage (OpenImageIO and the codec libraries behind it,
// raystream's header checks before allocating). The input is written to a file whose extension
// follows its magic bytes (else .png); rs::Error is the expected outcome for bad input, any
// other exception or a crash is a finding. Accepted textures must be finite, of the claimed
// size, and the process must print nothing (run the target with 2>file to check).
#include <unistd.h>

#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>

#include "scenes/image_io.h"

namespace {

const char* ExtensionFor(const uint8_t* d, size_t n) {
  auto starts = [&](const char* magic) {
    const size_t m = std::strlen(magic);
    return n >= m && std::memcmp(d, magic, m) == 0;
  };
  if (starts("\x89PNG")) return "png";
  if (starts("\xff\xd8")) return "jpg";
  if (starts("BM")) return "bmp";
  if (starts("v/1\x01")) return "exr";
  if (starts("#?")) return "hdr";
  if (starts("II*") || starts("MM")) return "tif";
  if (n >= 2 && d[0] == 'P' && d[1] >= '1' && d[1] <= '6') return "ppm";
  if (n >= 3 && (d[2] == 2 || d[2] == 10 || d[2] == 3 || d[2] == 11)) return "tga";
  return "png";
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  // One file per process (pid) in the working directory, rewritten for every input.
  static const std::string stem = "texture_fuzz_input_" + std::to_string(getpid()) + ".";
  const std::string path = stem + ExtensionFor(data, size);
  if (FILE* f = std::fopen(path.c_str(), "wb")) {
    if (size > 0) std::fwrite(data, 1, size, f);
    std::fclose(f);
  } else {
    std::abort();
  }
  rs::ImageReadLimits limits;
  limits.max_pixels = uint64_t{1} << 16;  // larger claims are refused early: fast runs
  try {
    const rs::Texture t = rs::ReadImage(path, limits);
    const size_t expected = static_cast<size_t>(t.width) * static_cast<size_t>(t.height) * 3;
    if (t.width <= 0 || t.height <= 0 || t.rgb.size() != expected) std::abort();
    for (const float x : t.rgb) {
      if (!std::isfinite(x)) std::abort();
    }
  } catch (const rs::Error&) {
  }
  std::remove(path.c_str());
  return 0;
}
