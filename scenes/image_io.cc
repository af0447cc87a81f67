// Image files through OpenImageIO: rendered frames out (PNG 8-bit sRGB, EXR half), textures in
// (any format OIIO reads, decoded to linear rgb). Writes go to a temporary file beside the target
// and are renamed on success, so a failed write never leaves a partial image.
#include "scenes/image_io.h"

#include <OpenImageIO/imageio.h>
#include <fmt/format.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cctype>
#include <cmath>
#include <filesystem>
#include <system_error>

#include "scenes/scene_internal.h"

namespace rs {
namespace {

using detail::Fail;

// Piecewise sRGB transfer function (IEC 61966-2-1).
float LinearToSrgb(float x) {
  if (!(x > 0.0f)) return 0.0f;  // also NaN
  if (x >= 1.0f) return 1.0f;
  return x <= 0.0031308f ? 12.92f * x : 1.055f * std::pow(x, 1.0f / 2.4f) - 0.055f;
}

float SrgbToLinear(float x) {
  return x <= 0.04045f ? x / 12.92f : std::pow((x + 0.055f) / 1.055f, 2.4f);
}

enum class Encoding { kSrgb8, kHalf, kFloat };

bool EncodingForExtension(const std::string& ext, Encoding& encoding) {
  if (ext == "png" || ext == "jpg" || ext == "jpeg" || ext == "bmp" || ext == "tga" ||
      ext == "ppm" || ext == "pnm") {
    encoding = Encoding::kSrgb8;
  } else if (ext == "exr") {
    encoding = Encoding::kHalf;
  } else if (ext == "hdr" || ext == "tif" || ext == "tiff") {
    encoding = Encoding::kFloat;
  } else {
    return false;
  }
  return true;
}

std::string Lower(std::string s) {
  std::transform(s.begin(), s.end(), s.begin(),
                 [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  return s;
}

}  // namespace

void WriteImage(const std::string& path, int width, int height, const std::vector<float>& rgb) {
  namespace fs = std::filesystem;
  if (width <= 0 || height <= 0) Fail("{}: cannot write a {}x{} image", path, width, height);
  const size_t pixels = static_cast<size_t>(width) * static_cast<size_t>(height);
  if (rgb.size() != pixels * 3) {
    Fail("{}: {} floats for a {}x{} rgb image (expected {})", path, rgb.size(), width, height,
         pixels * 3);
  }
  const std::string ext = detail::LowerExtension(path);
  Encoding encoding;
  if (!EncodingForExtension(ext, encoding)) {
    Fail(
        "{}: unknown image extension '{}' (use .png for 8-bit sRGB or .exr for linear half "
        "floats; also .jpg .bmp .tga .ppm .hdr .tif)",
        path, ext.empty() ? std::string("(none)") : "." + ext);
  }
  // The plugin is chosen by the target's extension; the data goes to a temporary name.
  auto out = OIIO::ImageOutput::create(path);
  if (!out) Fail("{}: no image writer for '.{}': {}", path, ext, OIIO::geterror());
  static std::atomic<unsigned> counter{0};
  const fs::path target(path);
  const fs::path tmp =
      target.parent_path() / fmt::format(".{}.tmp{}-{}", target.filename().string(),
                                         static_cast<long>(getpid()), counter.fetch_add(1));
  OIIO::ImageSpec spec(width, height, 3,
                       encoding == Encoding::kSrgb8  ? OIIO::TypeDesc::UINT8
                       : encoding == Encoding::kHalf ? OIIO::TypeDesc::HALF
                                                     : OIIO::TypeDesc::FLOAT);
  std::vector<unsigned char> bytes;
  const void* data = rgb.data();
  OIIO::TypeDesc data_type = OIIO::TypeDesc::FLOAT;
  if (encoding == Encoding::kSrgb8) {
    spec.attribute("oiio:ColorSpace", "sRGB");
    bytes.resize(rgb.size());
    for (size_t i = 0; i < rgb.size(); ++i) {
      bytes[i] = static_cast<unsigned char>(std::lround(LinearToSrgb(rgb[i]) * 255.0f));
    }
    data = bytes.data();
    data_type = OIIO::TypeDesc::UINT8;
  } else {
    spec.attribute("oiio:ColorSpace", "Linear");
    if (ext == "exr") spec.attribute("compression", "zip");
  }
  auto discard = [&](const std::string& why) {
    std::error_code ec;
    fs::remove(tmp, ec);
    Fail("{}: cannot write image: {}", path, why);
  };
  if (!out->open(tmp.string(), spec)) discard(out->geterror());
  if (!out->write_image(data_type, data)) {
    const std::string why = out->geterror();
    out->close();
    discard(why);
  }
  if (!out->close()) discard(out->geterror());
  std::error_code ec;
  fs::rename(tmp, target, ec);
  if (ec) discard(ec.message());
}

Texture ReadImage(const std::string& path) {
  // Keep colours as stored: OIIO would premultiply by alpha, darkening a texture's rgb.
  OIIO::ImageSpec config;
  config.attribute("oiio:UnassociatedAlpha", 1);
  auto in = OIIO::ImageInput::open(path, &config);
  if (!in) {
    std::string why = OIIO::geterror();
    if (why.empty()) why = "cannot open";
    Fail("{}: cannot read image: {}", path, why);
  }
  const OIIO::ImageSpec& spec = in->spec();
  const int channels = spec.nchannels;
  if (spec.width <= 0 || spec.height <= 0 || channels <= 0) {
    Fail("{}: image has size {}x{} with {} channels", path, spec.width, spec.height, channels);
  }
  const size_t pixels = static_cast<size_t>(spec.width) * static_cast<size_t>(spec.height);
  if (pixels > (size_t{1} << 28) || channels > 64) {
    Fail("{}: image too large ({}x{}, {} channels)", path, spec.width, spec.height, channels);
  }
  std::vector<float> all(pixels * static_cast<size_t>(channels));
  if (!in->read_image(0, 0, 0, channels, OIIO::TypeDesc::FLOAT, all.data())) {
    Fail("{}: cannot read image: {}", path, in->geterror());
  }
  // Transfer function: the file's colour space if it says so, else sRGB for integer data.
  const std::string cs = Lower(spec.get_string_attribute("oiio:ColorSpace"));
  const bool integer = spec.format.basetype != OIIO::TypeDesc::FLOAT &&
                       spec.format.basetype != OIIO::TypeDesc::HALF &&
                       spec.format.basetype != OIIO::TypeDesc::DOUBLE;
  enum { kLinear, kSrgb, kGamma } transfer = integer ? kSrgb : kLinear;
  float gamma = 1.0f;
  if (cs == "linear" || cs == "scene_linear" || cs == "lin_srgb") {
    transfer = kLinear;
  } else if (cs == "srgb") {
    transfer = kSrgb;
  } else if (cs.rfind("gammacorrected", 0) == 0 || cs.rfind("gamma", 0) == 0) {
    gamma = spec.get_float_attribute("oiio:Gamma", 2.2f);
    transfer = gamma > 0.0f ? kGamma : kSrgb;
  }
  Texture tex;
  tex.path = path;
  tex.width = spec.width;
  tex.height = spec.height;
  tex.rgb.resize(pixels * 3);
  for (size_t p = 0; p < pixels; ++p) {
    const float* src = &all[p * static_cast<size_t>(channels)];
    for (int c = 0; c < 3; ++c) {
      // Grey (1 channel) and grey + alpha (2) repeat the first channel; alpha is dropped.
      float x = channels >= 3 ? src[c] : src[0];
      if (!std::isfinite(x)) x = 0.0f;
      if (transfer == kSrgb) {
        x = SrgbToLinear(x);
      } else if (transfer == kGamma) {
        x = x > 0.0f ? std::pow(x, gamma) : 0.0f;
      }
      tex.rgb[p * 3 + static_cast<size_t>(c)] = x;
    }
  }
  return tex;
}

}  // namespace rs
