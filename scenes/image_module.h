// The OpenImageIO half of scenes/image_io.cc, built as the loadable module raystream-oiio.so
// (scenes/image_module.cc). OpenImageIO 2.4 in Debian pulls in ~270 shared libraries (OpenCV,
// ffmpeg, GDAL, ...): linked into the command they cost every run ~0.3 s of symbol lookups and
// static initialisers and ~130 MB before main. image_io.cc writes PNG itself (libpng) and loads
// this module only to read a texture or write another format. Not part of the library API.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "scenes/image_io.h"
#include "scenes/scene.h"

namespace rs::image_module {

// Bumped with every change to Functions: a module of another version is not used.
inline constexpr int kVersion = 2;

// What StageImage hands over: 8-bit sRGB bytes, or linear floats stored as half or float.
enum class FileType { kUint8, kHalf, kFloat };

struct Functions {
  int version;
  // Encodes width x height rgb pixels into `encoded` with OpenImageIO's writer for `path`, whose
  // lower-case extension is `ext` (nothing touches the disk): `data` is width * height * 3 bytes
  // for kUint8, floats otherwise. Returns "" or the reason, one line ("<path>: cannot write
  // image: <reason>" is the caller's).
  std::string (*encode)(const std::string& path, const std::string& ext, int width, int height,
                        FileType type, const void* data, std::vector<unsigned char>* encoded);
  // Reads `path` (a regular file of file_size bytes) as linear rgb into *tex, its header checked
  // against `limits` before any pixel is allocated. Returns "" or the whole one-line message.
  std::string (*read)(const std::string& path, uint64_t file_size, const ImageReadLimits& limits,
                      Texture* tex);
};

}  // namespace rs::image_module

// The module's one entry point (dlsym name "raystream_image_module").
extern "C" const rs::image_module::Functions* raystream_image_module();
