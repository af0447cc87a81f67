// OpenImageIO's half of the image files (scenes/image_module.h): encoding every format but PNG
// into memory, and reading textures. Built as the loadable module raystream-oiio.so, so that
// only runs which need it map OpenImageIO and the libraries it pulls in.
#include "scenes/image_module.h"

#include <OpenImageIO/filesystem.h>
#include <OpenImageIO/imageio.h>
#include <fcntl.h>
#include <fmt/format.h>
#include <sys/mman.h>
#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstdio>
#include <mutex>
#include <new>
#include <stdexcept>
#include <string_view>

namespace rs::image_module {
namespace {

// The module does not link the library that defines rs::Error: its functions return messages,
// thrown here and caught at their boundary.
template <typename... Args>
[[noreturn]] void Fail(fmt::format_string<Args...> format, Args&&... args) {
  throw std::runtime_error(fmt::format(format, std::forward<Args>(args)...));
}

std::string OneLine(std::string s) {
  while (!s.empty() && (s.back() == '\n' || s.back() == '\r' || s.back() == ' ')) s.pop_back();
  std::string out;
  out.reserve(s.size());
  for (size_t i = 0; i < s.size(); ++i) {
    if (s[i] == '\n' || s[i] == '\r') {
      while (i + 1 < s.size() && (s[i + 1] == '\n' || s[i + 1] == '\r')) ++i;
      out += "; ";
    } else {
      out += s[i];
    }
  }
  return out.empty() ? std::string("unknown error") : out;
}

// libpng (and libjpeg, libtiff, OpenEXR) print their own messages to stderr while OIIO also
// returns the reason through geterror(). While OIIO runs, fd 2 goes to a memory file; afterwards
// lines that came from someone else are passed on, the image libraries' are dropped.
class QuietStderr {
 public:
  QuietStderr() : lock_(Mutex()) {
    if (::fcntl(2, F_GETFD) == -1) return;  // stderr closed: nothing to protect
    // One memory file for the process, emptied for each use (cheap: no syscalls to create).
    static const int mem = ::memfd_create("raystream-stderr", MFD_CLOEXEC);
    if (mem < 0 || ::ftruncate(mem, 0) != 0 || ::lseek(mem, 0, SEEK_SET) != 0) return;
    std::fflush(stderr);
    saved_ = ::fcntl(2, F_DUPFD_CLOEXEC, 3);
    if (saved_ < 0) return;
    if (::dup2(mem, 2) < 0) {
      ::close(saved_);
      saved_ = -1;
      return;
    }
    mem_ = mem;
  }
  ~QuietStderr() {
    if (mem_ < 0) return;
    std::fflush(stderr);
    ::dup2(saved_, 2);
    ::close(saved_);
    const off_t size = ::lseek(mem_, 0, SEEK_CUR);
    if (size <= 0) return;  // the usual case: nothing was printed
    std::string text;
    char buf[4096];
    if (::lseek(mem_, 0, SEEK_SET) == 0) {
      ssize_t n;
      while (text.size() < (1u << 16) && (n = ::read(mem_, buf, sizeof(buf))) > 0) {
        text.append(buf, static_cast<size_t>(n));
      }
    }
    size_t pos = 0;
    while (pos < text.size()) {
      size_t end = text.find('\n', pos);
      end = end == std::string::npos ? text.size() : end + 1;
      const std::string_view line(text.data() + pos, end - pos);
      pos = end;
      if (FromImageLibrary(line)) continue;
      [[maybe_unused]] const ssize_t r = ::write(2, line.data(), line.size());
    }
  }
  QuietStderr(const QuietStderr&) = delete;
  QuietStderr& operator=(const QuietStderr&) = delete;

 private:
  static std::mutex& Mutex() {
    static std::mutex m;
    return m;
  }
  static bool FromImageLibrary(std::string_view line) {
    for (const std::string_view p : {"libpng ", "libtiff", "JPEG", "Corrupt JPEG", "Premature end",
                                     "Warning:", "OpenImageIO", "TIFF", "Openexr", "OpenEXR"}) {
      if (line.substr(0, p.size()) == p) return true;
    }
    return line.find("TIFFRead") != std::string_view::npos;
  }

  std::lock_guard<std::mutex> lock_;
  int mem_ = -1;
  int saved_ = -1;
};

float SrgbToLinear(float x) {
  return x <= 0.04045f ? x / 12.92f : std::pow((x + 0.055f) / 1.055f, 2.4f);
}

std::string Lower(std::string s) {
  std::transform(s.begin(), s.end(), s.begin(),
                 [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  return s;
}

std::string Encode(const std::string& path, const std::string& ext, int width, int height,
                   FileType type, const void* data, std::vector<unsigned char>* encoded) try {
  const OIIO::TypeDesc file_type = type == FileType::kUint8  ? OIIO::TypeDesc::UINT8
                                   : type == FileType::kHalf ? OIIO::TypeDesc::HALF
                                                             : OIIO::TypeDesc::FLOAT;
  OIIO::ImageSpec spec(width, height, 3, file_type);
  if (type == FileType::kUint8) {
    spec.attribute("oiio:ColorSpace", "sRGB");
  } else {
    spec.attribute("oiio:ColorSpace", "Linear");
    if (ext == "exr") spec.attribute("compression", "zip");
  }
  const OIIO::TypeDesc data_type =
      type == FileType::kUint8 ? OIIO::TypeDesc::UINT8 : OIIO::TypeDesc::FLOAT;
  // Encode into memory; the plugin is chosen by the target's extension, nothing touches disk.
  QuietStderr quiet;
  auto out = OIIO::ImageOutput::create(path);
  if (!out) return fmt::format("no writer for '.{}': {}", ext, OneLine(OIIO::geterror()));
  OIIO::Filesystem::IOVecOutput proxy(*encoded);
  if (!out->supports("ioproxy") || !out->set_ioproxy(&proxy)) {
    return fmt::format("the '.{}' writer cannot encode to memory", ext);
  }
  if (!out->open(path, spec) || !out->write_image(data_type, data) || !out->close()) {
    return OneLine(out->geterror());
  }
  return std::string();
} catch (const std::bad_alloc&) {
  return "out of memory";
} catch (const std::exception& e) {
  return OneLine(e.what());
}

std::string Read(const std::string& path, uint64_t file_size, const ImageReadLimits& limits,
                 Texture* out) try {
  // Keep colours as stored: OIIO would premultiply by alpha, darkening a texture's rgb.
  OIIO::ImageSpec config;
  config.attribute("oiio:UnassociatedAlpha", 1);
  QuietStderr quiet;
  auto in = OIIO::ImageInput::open(path, &config);
  if (!in) {
    std::string why = OIIO::geterror();
    if (why.empty()) why = "not an image OpenImageIO can read";
    Fail("{}: cannot read image: {}", path, OneLine(why));
  }
  const OIIO::ImageSpec& spec = in->spec();
  const int channels = spec.nchannels;
  if (spec.width <= 0 || spec.height <= 0 || channels <= 0 || spec.depth > 1) {
    Fail("{}: image has size {}x{}x{} with {} channels", path, spec.width, spec.height, spec.depth,
         channels);
  }
  // Header checks before any pixel is allocated.
  const uint64_t pixels = static_cast<uint64_t>(spec.width) * static_cast<uint64_t>(spec.height);
  if (pixels > limits.max_pixels) {
    Fail("{}: image {}x{} has {} pixels, more than the limit of {} for textures", path, spec.width,
         spec.height, pixels, limits.max_pixels);
  }
  if (limits.max_pixels_per_byte > 0 && pixels / limits.max_pixels_per_byte >= file_size) {
    Fail("{}: header claims {}x{} pixels but the file has only {} bytes (corrupt or truncated)",
         path, spec.width, spec.height, file_size);
  }
  if (channels > 64) Fail("{}: image has {} channels (at most 64)", path, channels);
  // OpenImageIO 2.4 reads a TIFF through a buffer of whole strips: RowsPerStrip scanlines, even
  // when the image has fewer rows (a texture_fuzz finding: a 350-byte 15620x4 TIFF claiming 65312
  // rows per strip had it allocate 4 GB). libtiff clamps the strip to the image; OIIO does not.
  const int64_t rows_per_strip = spec.get_int_attribute("tiff:RowsPerStrip", 0);
  if (spec.tile_width == 0 && rows_per_strip > spec.height &&
      static_cast<uint64_t>(rows_per_strip) * static_cast<uint64_t>(spec.width) >
          limits.max_pixels) {
    Fail("{}: TIFF claims {} rows per strip for a {}x{} image (more than the limit of {} pixels "
         "for textures in one strip)",
         path, rows_per_strip, spec.width, spec.height, limits.max_pixels);
  }
  // Small images: decode on this thread (OIIO would start worker threads for each read).
  if (pixels < (uint64_t{1} << 20)) in->threads(1);
  // Read the colour channels only: rgb directly, or the first channel of grey (+ alpha).
  const int read_channels = channels >= 3 ? 3 : 1;
  Texture tex;
  std::vector<float> grey;
  try {
    tex.rgb.resize(static_cast<size_t>(pixels) * 3);
    if (read_channels == 1) grey.resize(static_cast<size_t>(pixels));
  } catch (const std::bad_alloc&) {
    Fail("{}: out of memory for a {}x{} texture ({} MiB)", path, spec.width, spec.height,
         pixels * 3 * sizeof(float) >> 20);
  }
  float* dst = read_channels == 3 ? tex.rgb.data() : grey.data();
  if (!in->read_image(0, 0, 0, read_channels, OIIO::TypeDesc::FLOAT, dst)) {
    Fail("{}: cannot read image: {}", path, OneLine(in->geterror()));
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
    transfer = gamma > 0.0f && std::isfinite(gamma) ? kGamma : kSrgb;
  }
  tex.path = path;
  tex.width = spec.width;
  tex.height = spec.height;
  for (size_t p = 0; p < pixels; ++p) {
    for (size_t c = 0; c < 3; ++c) {
      // Grey (1 channel) and grey + alpha (2) repeat the first channel; alpha is dropped.
      float x = read_channels == 3 ? tex.rgb[p * 3 + c] : grey[p];
      if (!std::isfinite(x)) x = 0.0f;
      if (transfer == kSrgb) {
        x = SrgbToLinear(x);
      } else if (transfer == kGamma) {
        x = x > 0.0f ? std::pow(x, gamma) : 0.0f;
      }
      tex.rgb[p * 3 + c] = std::isfinite(x) ? x : 0.0f;
    }
  }
  *out = std::move(tex);
  return std::string();
} catch (const std::bad_alloc&) {
  return fmt::format("{}: out of memory", path);
} catch (const std::exception& e) {
  return e.what();
}

constexpr Functions kFunctions = {kVersion, Encode, Read};

}  // namespace
}  // namespace rs::image_module

extern "C" __attribute__((visibility("default"))) const rs::image_module::Functions*
raystream_image_module() {
  return &rs::image_module::kFunctions;
}
