// Reading textures and writing images (PNG with libpng; EXR and the other formats, and every texture,
// through OpenImageIO in a module loaded on first use), and the crash-safe output files every result
// goes through (temporary beside the target, fsync, rename).
#pragma once

#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

#include "scenes/scene.h"

namespace rs {

// ---- Output files ------------------------------------------------------------------------------
//
// Every output is written to a temporary ".<name>.tmp<pid>-<n>" in the target's folder, each
// write and the close checked, fsynced, renamed over the target, and the folder fsynced. On any
// failure the temporary is removed and rs::Error says, in one line, "<final path>: cannot write
// <what>: <reason>" (strerror where there is one). Nothing partial is ever left at the target.

// Checks before any work that `path` can be written: not empty, not a directory or other
// non-regular file, its folder exists, is a folder, and a file can be created in it (probed by
// creating and removing a temporary). Throws rs::Error "<path>: <reason>". Does not write `path`.
void CheckOutputPath(const std::string& path);
// CheckOutputPath plus a known image extension (what WriteImage accepts), and for every format but
// PNG the OpenImageIO module loaded (scenes/image_module.h).
void CheckImageOutputPath(const std::string& path);

// A complete, fsynced temporary waiting to be renamed over its final path. Commit() puts it in
// place (throws rs::Error naming path() on failure, temporary removed); destroying an uncommitted
// one removes the temporary. Lets a caller write several outputs and place them only when all
// succeeded (image + statistics, every frame of a run). Move-only.
class StagedFile {
 public:
  StagedFile() = default;
  StagedFile(StagedFile&& other) noexcept;
  StagedFile& operator=(StagedFile&& other) noexcept;
  StagedFile(const StagedFile&) = delete;
  StagedFile& operator=(const StagedFile&) = delete;
  ~StagedFile();

  void Commit();
  // Removes the temporary now (no-op when committed or empty).
  void Discard() noexcept;
  const std::string& path() const { return path_; }
  const std::string& temporary() const { return tmp_; }

 private:
  friend StagedFile StageFile(const std::string&, std::string_view, std::string_view);
  std::string path_;
  std::string tmp_;
  std::string what_;
  int slot_ = -1;  // temporaries registry slot, -1 when none
};

// Writes `bytes` to a temporary beside `path` (checked, fsynced, closed). `what` names the
// content in messages ("image", "statistics"). Throws rs::Error naming `path`.
StagedFile StageFile(const std::string& path, std::string_view bytes,
                     std::string_view what = "file");
// StageFile(...).Commit(): the whole file or nothing at `path`.
void WriteFileAtomically(const std::string& path, std::string_view bytes,
                         std::string_view what = "file");

// The 8-bit sRGB code of a linear value: the code nearest to 255 x the sRGB transfer function
// (IEC 61966-2-1) of x evaluated in double, halves up; 0 for x <= 0 or NaN, 255 for x >= 1.
// A table lookup (the codes' first floats, found once by bisection), about 4x faster than a
// float pow per channel; what PNG and the other 8-bit formats are written with.
uint8_t LinearToSrgb8(float x);
// The same for n values into out[0, n).
void LinearToSrgb8(const float* linear, size_t n, uint8_t* out);

// Encodes width x height linear rgb floats (row 0 at the top) in memory and stages the file.
// 8-bit formats (PNG, JPEG, BMP, TGA, PPM) get sRGB encoding and clamping; EXR gets half floats,
// HDR/TIFF floats. OIIO and its libraries print nothing; their reasons go into the rs::Error.
StagedFile StageImage(const std::string& path, int width, int height,
                      const std::vector<float>& rgb);
// StageImage(...).Commit(). Throws rs::Error naming `path` (folder missing or unwritable,
// unknown extension, disk full, file size limit, ...).
void WriteImage(const std::string& path, int width, int height, const std::vector<float>& rgb);

// Removes every temporary output currently open or staged by this process (by unlink only).
// Async-signal-safe: for SIGINT / SIGTERM handlers, which should call it and then _exit. Also
// safe to call from normal code (staged files then fail to commit with a clear error).
// Returns how many were removed.
int RemoveTemporaries() noexcept;
// How many temporaries are registered now (tests).
int PendingTemporaries() noexcept;

// ---- Textures ----------------------------------------------------------------------------------

// Limits on an image read as a texture, checked from its header before any pixel is allocated.
struct ImageReadLimits {
  // Largest width * height accepted (default 8192 x 8192; 3 floats per pixel are kept).
  uint64_t max_pixels = uint64_t{1} << 26;
  // A header claiming more pixels than this per byte of file is corrupt: deflate compresses at
  // most ~1032:1, so even a constant 1-bit PNG stays below 8,300 pixels per byte.
  uint64_t max_pixels_per_byte = 16384;
};
// Process-wide limits used by ReadImage(path) and so by every scene loader (default above).
void SetImageReadLimits(const ImageReadLimits& limits);
ImageReadLimits GetImageReadLimits();

// Reads an image as linear rgb floats (sRGB 8-bit input is decoded). Throws rs::Error
// "<path>: <reason>" in one line: not a regular file, header too large for the limits or the
// file's size, corrupt or truncated data (libpng and friends print nothing to stderr).
Texture ReadImage(const std::string& path);
Texture ReadImage(const std::string& path, const ImageReadLimits& limits);

}  // namespace rs
