// Image files: rendered frames out (PNG 8-bit sRGB with libpng here; EXR half and the other
// formats through OpenImageIO), textures in (any format OIIO reads, decoded to linear rgb), and
// the output files every result goes through. OpenImageIO lives in a module loaded on first use
// (scenes/image_module.h). Images are encoded into memory, so every byte that reaches the disk
// goes through our own checked write / fsync / close / rename: the image libraries do not report
// all write errors (libpng leaves a cut-off PNG on a full disk and says nothing).
#include "scenes/image_io.h"

#include <dlfcn.h>
#include <fcntl.h>
#include <fmt/format.h>
#include <limits.h>
#include <png.h>
#include <zlib.h>
#include <sys/resource.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <bit>
#include <cerrno>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <mutex>
#include <new>
#include <system_error>

#include "scenes/image_module.h"
#include "scenes/scene_internal.h"

namespace rs {
namespace {

using detail::Fail;

// ---- Registry of temporaries (async-signal-safe removal) ---------------------------------------
//
// Fixed slots in static storage (untouched pages cost no memory), each a path and a state:
// kFree -> kFilling (the owner copies the path) -> kLive -> kFree (the owner renamed or removed
// it), or kLive -> kRemoving -> kFree when RemoveTemporaries claims it. Only lock-free atomics
// and unlink() are used on the removal side, so a signal handler may call it.
constexpr int kMaxTemporaries = 256;
enum SlotState : int { kFree = 0, kFilling = 1, kLive = 2, kRemoving = 3 };
struct TempSlot {
  std::atomic<int> state{kFree};
  char path[PATH_MAX];
};
static_assert(std::atomic<int>::is_always_lock_free, "signal handlers need lock-free atomics");
TempSlot g_slots[kMaxTemporaries];

// Registers `tmp` before it is created; -1 if every slot is taken or the path is too long.
int RegisterTemporary(const std::string& tmp) {
  if (tmp.size() >= PATH_MAX) return -1;
  for (int i = 0; i < kMaxTemporaries; ++i) {
    int expected = kFree;
    if (g_slots[i].state.compare_exchange_strong(expected, kFilling, std::memory_order_acquire)) {
      std::memcpy(g_slots[i].path, tmp.c_str(), tmp.size() + 1);
      g_slots[i].state.store(kLive, std::memory_order_release);
      return i;
    }
  }
  return -1;
}

// The temporary no longer exists under its name (renamed or removed): frees the slot. If a
// signal handler on another thread is removing it right now, waits for that to finish.
void ReleaseTemporary(int slot) {
  if (slot < 0) return;
  int expected = kLive;
  while (!g_slots[slot].state.compare_exchange_weak(expected, kFree, std::memory_order_acq_rel)) {
    if (expected == kFree) return;  // RemoveTemporaries removed it already
    expected = kLive;
  }
}

// True if the slot still holds our temporary (RemoveTemporaries has not taken it).
bool TemporaryAlive(int slot) {
  return slot >= 0 && g_slots[slot].state.load(std::memory_order_acquire) == kLive;
}

void RemoveFile(const std::string& path) noexcept { ::unlink(path.c_str()); }


std::string Errno(int err) { return std::strerror(err); }

// ".<name>.tmp<pid>-<n>" beside `path` (the name shortened so the result stays within NAME_MAX).
std::string TemporaryName(const std::string& path) {
  static std::atomic<unsigned> counter{0};
  const std::filesystem::path target(path);
  std::string name = target.filename().string();
  if (name.size() > 200) name.resize(200);
  const std::string tmp_name = fmt::format(".{}.tmp{}-{}", name, static_cast<long>(getpid()),
                                           counter.fetch_add(1, std::memory_order_relaxed));
  return (target.parent_path() / tmp_name).string();
}

std::string FolderOf(const std::string& path) {
  const std::string dir = std::filesystem::path(path).parent_path().string();
  return dir.empty() ? std::string(".") : dir;
}

void FsyncFolder(const std::string& dir, int& err) {
  err = 0;
  const int fd = ::open(dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  if (fd < 0) {
    err = errno;
    return;
  }
  // EINVAL: the file system does not sync folders (nothing to do).
  if (::fsync(fd) != 0 && errno != EINVAL) err = errno;
  ::close(fd);
}


// Piecewise sRGB transfer function (IEC 61966-2-1) on [0, 1], in double.
double SrgbOfLinear(double x) {
  return x <= 0.0031308 ? 12.92 * x : 1.055 * std::pow(x, 1.0 / 2.4) - 0.055;
}

// LinearToSrgb8's tables. Code k (1..255) starts at the smallest float x in (0, 1] with
// SrgbOfLinear(x) x 255 >= k - 0.5, found by bisection over the floats' bit patterns (the
// function is increasing; in double its rounding is far below a float's spacing). The floats in
// [0, 1) are cut into buckets of 2^kShift consecutive bit patterns, each holding the code of its
// first float; a value's code is its bucket's, stepped up past the starts it has reached (a
// bucket is 1/256 of a binade, over which the code moves by one at most).
struct Srgb8Table {
  static constexpr int kShift = 15;
  static constexpr uint32_t kOne = 0x3f800000u;  // 1.0f
  float start[257];                               // start[0] = 0, start[256] = +inf
  uint8_t bucket[kOne >> kShift];

  Srgb8Table() {
    start[0] = 0.0f;
    start[256] = INFINITY;
    for (int k = 1; k <= 255; ++k) {
      const double half = double(k) - 0.5;
      uint32_t lo = 0, hi = kOne;  // the code of 0 is below k, that of 1 is 255
      while (hi - lo > 1) {
        const uint32_t mid = lo + (hi - lo) / 2;
        if (SrgbOfLinear(double(std::bit_cast<float>(mid))) * 255.0 >= half) {
          hi = mid;
        } else {
          lo = mid;
        }
      }
      start[k] = std::bit_cast<float>(hi);
    }
    int code = 0;
    for (uint32_t b = 0; b < (kOne >> kShift); ++b) {
      const float first = std::bit_cast<float>(b << kShift);
      while (first >= start[code + 1]) ++code;
      bucket[b] = static_cast<uint8_t>(code);
    }
  }

  uint8_t Code(float x) const {
    if (!(x > 0.0f)) return 0;  // also NaN
    if (x >= 1.0f) return 255;
    int code = bucket[std::bit_cast<uint32_t>(x) >> kShift];
    while (x >= start[code + 1]) ++code;
    return static_cast<uint8_t>(code);
  }
};

const Srgb8Table& Srgb8() {
  static const Srgb8Table table;
  return table;
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

Encoding ImageEncodingOrFail(const std::string& path) {
  const std::string ext = detail::LowerExtension(path);
  Encoding encoding;
  if (!EncodingForExtension(ext, encoding)) {
    Fail(
        "{}: unknown image extension '{}' (use .png for 8-bit sRGB or .exr for linear half "
        "floats; also .jpg .bmp .tga .ppm .hdr .tif)",
        path, ext.empty() ? std::string("(none)") : "." + ext);
  }
  return encoding;
}


// OpenEXR sizes its line-offset table from the header's dataWindow inside ImageInput::open,
// before OIIO hands us a spec: a 299-byte file claiming 2^28 lines allocates 1.8 GB there (a
// texture_fuzz finding). So the dataWindow of every header (multi-part files have several) is
// read here first. Layout: magic 76 2f 31 01, version word, then per header attributes
// "name\0type\0<int32 size><value>" ending with an empty name; dataWindow is a box2i (4 int32
// LE: xmin ymin xmax ymax). Returns false if the file is not EXR or no dataWindow was found
// (OIIO then reports the error); `pixels` is the largest window, UINT64_MAX for a corrupt header.
bool ExrLargestWindow(const std::string& path, uint64_t file_size, uint64_t& pixels,
                      std::string& why) {
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) return false;
  unsigned char buf[1 << 16];
  ssize_t n = 0, got;
  while (n < static_cast<ssize_t>(sizeof(buf)) &&
         (got = ::read(fd, buf + n, sizeof(buf) - static_cast<size_t>(n))) > 0) {
    n += got;
  }
  ::close(fd);
  const size_t size = static_cast<size_t>(std::max<ssize_t>(n, 0));
  if (size < 8 || std::memcmp(buf, "v/1\x01", 4) != 0) return false;
  const bool multipart = (buf[5] & 0x10) != 0;  // version word bit 12
  auto le32 = [&](size_t at) {
    return static_cast<int32_t>(
        static_cast<uint32_t>(buf[at]) | static_cast<uint32_t>(buf[at + 1]) << 8 |
        static_cast<uint32_t>(buf[at + 2]) << 16 | static_cast<uint32_t>(buf[at + 3]) << 24);
  };
  auto cstring = [&](size_t& at, std::string_view& out) {
    const void* end = std::memchr(buf + at, 0, size - at);
    if (end == nullptr) return false;
    const size_t len = static_cast<size_t>(static_cast<const unsigned char*>(end) - (buf + at));
    out = std::string_view(reinterpret_cast<const char*>(buf + at), len);
    at += len + 1;
    return true;
  };
  size_t at = 8;
  bool found = false;
  pixels = 0;
  for (;;) {  // headers
    bool header_empty = true;
    for (;;) {  // attributes
      std::string_view name, type;
      if (at >= size || !cstring(at, name)) return found;
      if (name.empty()) break;
      header_empty = false;
      if (!cstring(at, type) || at + 4 > size) return found;
      const int32_t len = le32(at);
      at += 4;
      // OpenEXR allocates an attribute's declared size before reading it (a texture_fuzz
      // finding: 'capDate' claiming 1.7 GB in a 299-byte file).
      if (len < 0 || static_cast<uint64_t>(len) > file_size - at) {
        why = fmt::format("EXR attribute '{}' claims {} bytes", name.substr(0, 40), len);
        pixels = UINT64_MAX;
        return true;
      }
      if (static_cast<size_t>(len) > size - at) return found;  // beyond what was read
      if (name == "dataWindow" && type == "box2i" && len == 16) {
        const int64_t w = static_cast<int64_t>(le32(at + 8)) - le32(at) + 1;
        const int64_t h = static_cast<int64_t>(le32(at + 12)) - le32(at + 4) + 1;
        if (w <= 0 || h <= 0) {
          why = fmt::format("EXR dataWindow is empty ({}x{})", w, h);
          pixels = UINT64_MAX;
          return true;
        }
        pixels = std::max(pixels, static_cast<uint64_t>(w) * static_cast<uint64_t>(h));
        why = fmt::format("EXR dataWindow {}x{}", w, h);
        found = true;
      }
      at += static_cast<size_t>(len);
    }
    if (!multipart || header_empty) return found;
  }
}

// ---- PNG (libpng) --------------------------------------------------------------------------------

// libpng reports errors through a callback that must not return: it longjmps back into
// EncodePng with the message kept here (no allocation on that path).
struct PngSink {
  std::vector<unsigned char>* out;
  char message[200];
};

void PngWrite(png_structp png, png_bytep data, size_t n) {
  auto* sink = static_cast<PngSink*>(png_get_io_ptr(png));
  try {
    sink->out->insert(sink->out->end(), data, data + n);
  } catch (...) {  // no exception may cross libpng's C frames
    png_error(png, "out of memory");
  }
}
void PngFlush(png_structp) {}
[[noreturn]] void PngError(png_structp png, png_const_charp message) {
  auto* sink = static_cast<PngSink*>(png_get_error_ptr(png));
  std::snprintf(sink->message, sizeof sink->message, "%s", message);
  png_longjmp(png, 1);
}
void PngWarning(png_structp, png_const_charp) {}

// 8-bit sRGB rgb rows (row 0 at the top) as a PNG with an sRGB chunk, into `out`. Returns "" or
// libpng's reason. Nothing with a destructor lives between setjmp and png_destroy_write_struct.
std::string EncodePng(int width, int height, const unsigned char* rgb,
                      std::vector<unsigned char>* out) {
  std::vector<png_bytep> rows(static_cast<size_t>(height));
  for (size_t y = 0; y < rows.size(); ++y) {
    rows[y] = const_cast<png_bytep>(rgb + y * static_cast<size_t>(width) * 3);
  }
  PngSink sink{out, {}};
  png_structp png = png_create_write_struct(PNG_LIBPNG_VER_STRING, &sink, PngError, PngWarning);
  png_infop info = png != nullptr ? png_create_info_struct(png) : nullptr;
  if (info == nullptr) {
    png_destroy_write_struct(&png, nullptr);
    return "out of memory";
  }
  if (setjmp(png_jmpbuf(png)) != 0) {
    png_destroy_write_struct(&png, &info);
    return sink.message[0] != '\0' ? std::string(sink.message) : std::string("libpng failed");
  }
  png_set_write_fn(png, &sink, PngWrite, PngFlush);
  png_set_IHDR(png, info, static_cast<png_uint_32>(width), static_cast<png_uint_32>(height), 8,
               PNG_COLOR_TYPE_RGB, PNG_INTERLACE_NONE, PNG_COMPRESSION_TYPE_DEFAULT,
               PNG_FILTER_TYPE_DEFAULT);
  png_set_sRGB_gAMA_and_cHRM(png, info, PNG_sRGB_INTENT_PERCEPTUAL);
  // Paeth-filtered rows, run-length deflate: 3-4x faster than libpng's defaults (every filter
  // tried per row, deflate level 6) for 11-19 % larger files (1024x1024 renders: bunny 47 -> 14
  // ms, sponza 77 -> 18 ms; erw6, bunny, sponza and conference 11-19 % larger). A render's
  // image is written on the application thread after the frame, so this was up to half the
  // frame's time on 2 threads.
  png_set_filter(png, PNG_FILTER_TYPE_BASE, PNG_FILTER_PAETH);
  png_set_compression_strategy(png, Z_RLE);
  png_write_info(png, info);
  png_write_image(png, rows.data());
  png_write_end(png, nullptr);
  png_destroy_write_struct(&png, &info);
  return std::string();
}

// ---- The OpenImageIO module --------------------------------------------------------------------

// Address space the module needs above what is mapped when it loads: OpenImageIO's ~270
// libraries, their initialisers and a small texture read (measured here, Debian 12, OpenImageIO
// 2.4.7: the command with 26 MB mapped reads a 2x2 PNG texture from a 528 MB limit on; 496-520
// MB end in "out of memory"), rounded up. The initialisers of those libraries may abort instead
// of failing under a tighter limit (ulimit -v), so the module is not loaded there.
constexpr unsigned long long kModuleAddressSpaceMb = 512;

// Megabytes of address space mapped by the process now (0 if unknown).
unsigned long long MappedMb() {
  unsigned long long pages = 0;
  if (std::FILE* f = std::fopen("/proc/self/statm", "re")) {
    if (std::fscanf(f, "%llu", &pages) != 1) pages = 0;
    std::fclose(f);
  }
  return pages * static_cast<unsigned long long>(::sysconf(_SC_PAGESIZE)) >> 20;
}

// Candidate module files: $RAYSTREAM_IMAGE_MODULE alone if set; else the build tree's module
// first for programs in the build tree (RS_BUILD_ROOT), the installed one first for the others.
std::vector<std::string> ModuleCandidates() {
  if (const char* env = std::getenv("RAYSTREAM_IMAGE_MODULE"); env != nullptr && *env != '\0') {
    return {env};
  }
  char exe[PATH_MAX];
  const ssize_t n = ::readlink("/proc/self/exe", exe, sizeof exe - 1);
  const std::string self = n > 0 ? std::string(exe, static_cast<size_t>(n)) : std::string();
  const std::string root = std::string(RS_BUILD_ROOT) + "/";
  if (self.compare(0, root.size(), root) == 0) return {RS_IMAGE_MODULE_BUILD, RS_IMAGE_MODULE_INSTALL};
  return {RS_IMAGE_MODULE_INSTALL, RS_IMAGE_MODULE_BUILD};
}

// The OpenImageIO module (image_module.h), loaded on first use and kept for the process. Throws
// rs::Error "<path>: cannot <what>: <reason>" when no candidate loads (and again on the next
// call, which tries again).
const image_module::Functions& ImageModule(const std::string& path, std::string_view what) {
  static std::mutex mutex;
  static const image_module::Functions* loaded = nullptr;
  std::lock_guard<std::mutex> lock(mutex);
  if (loaded != nullptr) return *loaded;
  rlimit limit{};
  if (::getrlimit(RLIMIT_AS, &limit) == 0 && limit.rlim_cur != RLIM_INFINITY) {
    const unsigned long long limit_mb = limit.rlim_cur >> 20, mapped_mb = MappedMb();
    if (limit_mb < mapped_mb + kModuleAddressSpaceMb) {
      Fail("{}: cannot {}: the address-space limit (ulimit -v) of {} MB leaves {} MB, below the "
           "{} MB OpenImageIO and its libraries need to load",
           path, what, limit_mb, limit_mb > mapped_mb ? limit_mb - mapped_mb : 0,
           kModuleAddressSpaceMb);
    }
  }
  std::string reasons;
  for (const std::string& file : ModuleCandidates()) {
    void* handle = ::dlopen(file.c_str(), RTLD_NOW | RTLD_LOCAL);
    if (handle == nullptr) {
      const char* why = ::dlerror();
      reasons += (reasons.empty() ? "" : "; ") + std::string(why != nullptr ? why : file);
      continue;
    }
    using Entry = const image_module::Functions* (*)();
    const auto entry = reinterpret_cast<Entry>(::dlsym(handle, "raystream_image_module"));
    const image_module::Functions* functions = entry != nullptr ? entry() : nullptr;
    if (functions == nullptr || functions->version != image_module::kVersion) {
      reasons += (reasons.empty() ? "" : "; ") + file + ": not a raystream " RS_VERSION " image module";
      ::dlclose(handle);
      continue;
    }
    loaded = functions;
    return *loaded;
  }
  Fail("{}: cannot {}: cannot load the OpenImageIO module ({})", path, what, reasons);
}

std::atomic<uint64_t> g_max_pixels{ImageReadLimits{}.max_pixels};
std::atomic<uint64_t> g_max_pixels_per_byte{ImageReadLimits{}.max_pixels_per_byte};

}  // namespace

// ---- Output files ------------------------------------------------------------------------------

void CheckOutputPath(const std::string& path) {
  if (path.empty()) Fail("output path is empty");
  if (path.back() == '/') Fail("{}: output path names a folder, not a file", path);
  struct stat st;
  if (::stat(path.c_str(), &st) == 0 && !S_ISREG(st.st_mode)) {
    Fail("{}: exists and is {}; give a file name", path, detail::FileTypeName(st.st_mode));
  }
  const std::string dir = FolderOf(path);
  if (::stat(dir.c_str(), &st) != 0) {
    const int err = errno;
    if (err == ENOENT) Fail("{}: folder '{}' does not exist", path, dir);
    Fail("{}: folder '{}': {}", path, dir, Errno(err));
  }
  if (!S_ISDIR(st.st_mode)) Fail("{}: '{}' is not a folder", path, dir);
  // Probe: create and remove a temporary, exactly what the real write will do first.
  const std::string tmp = TemporaryName(path);
  const int slot = RegisterTemporary(tmp);
  const int fd = ::open(tmp.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, 0666);
  const int err = errno;
  if (fd >= 0) {
    ::close(fd);
    RemoveFile(tmp);
  }
  ReleaseTemporary(slot);
  if (fd < 0) Fail("{}: cannot create files in folder '{}': {}", path, dir, Errno(err));
}

void CheckImageOutputPath(const std::string& path) {
  if (path.empty()) Fail("output path is empty");
  ImageEncodingOrFail(path);
  CheckOutputPath(path);
  // every format but PNG is written by the OpenImageIO module: load it now, before any work
  if (detail::LowerExtension(path) != "png") ImageModule(path, "write image");
}

StagedFile::StagedFile(StagedFile&& other) noexcept
    : path_(std::move(other.path_)),
      tmp_(std::move(other.tmp_)),
      what_(std::move(other.what_)),
      slot_(other.slot_) {
  other.tmp_.clear();
  other.slot_ = -1;
}

StagedFile& StagedFile::operator=(StagedFile&& other) noexcept {
  if (this != &other) {
    Discard();
    path_ = std::move(other.path_);
    tmp_ = std::move(other.tmp_);
    what_ = std::move(other.what_);
    slot_ = other.slot_;
    other.tmp_.clear();
    other.slot_ = -1;
  }
  return *this;
}

StagedFile::~StagedFile() { Discard(); }

void StagedFile::Discard() noexcept {
  if (tmp_.empty()) return;
  RemoveFile(tmp_);
  ReleaseTemporary(slot_);
  tmp_.clear();
  slot_ = -1;
}

void StagedFile::Commit() {
  if (tmp_.empty()) Fail("{}: cannot write {}: nothing staged", path_, what_);
  if (!TemporaryAlive(slot_)) {
    tmp_.clear();
    slot_ = -1;
    Fail("{}: cannot write {}: temporary removed (interrupted)", path_, what_);
  }
  struct stat st;
  if (::stat(path_.c_str(), &st) == 0 && !S_ISREG(st.st_mode)) {
    Discard();
    Fail("{}: cannot write {}: exists and is {}", path_, what_, detail::FileTypeName(st.st_mode));
  }
  if (::rename(tmp_.c_str(), path_.c_str()) != 0) {
    const int err = errno;
    Discard();
    Fail("{}: cannot write {}: {}", path_, what_, Errno(err));
  }
  ReleaseTemporary(slot_);
  tmp_.clear();
  slot_ = -1;
  int err = 0;
  FsyncFolder(FolderOf(path_), err);
  if (err != 0) {
    RemoveFile(path_);  // not durable: a failed run leaves nothing
    Fail("{}: cannot write {}: syncing folder '{}': {}", path_, what_, FolderOf(path_), Errno(err));
  }
}

StagedFile StageFile(const std::string& path, std::string_view bytes, std::string_view what) {
  if (path.empty()) Fail("output path is empty");
  StagedFile staged;
  staged.path_ = path;
  staged.what_ = std::string(what);
  const std::string tmp = TemporaryName(path);
  staged.slot_ = RegisterTemporary(tmp);  // before the file exists: a signal cannot leak it
  if (staged.slot_ < 0) {
    Fail("{}: cannot write {}: too many outputs pending (limit {}) or path too long", path, what,
         kMaxTemporaries);
  }
  const int fd = ::open(tmp.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, 0666);
  if (fd < 0) {
    const int err = errno;
    ReleaseTemporary(staged.slot_);
    staged.slot_ = -1;
    const std::string dir = FolderOf(path);
    struct stat st;
    if (err == ENOENT && ::stat(dir.c_str(), &st) != 0) {
      Fail("{}: cannot write {}: folder '{}' does not exist", path, what, dir);
    }
    if (err == ENOTDIR) Fail("{}: cannot write {}: '{}' is not a folder", path, what, dir);
    Fail("{}: cannot write {}: {}", path, what, Errno(err));
  }
  staged.tmp_ = tmp;
  // Past RLIMIT_FSIZE the kernel sends SIGXFSZ, whose default kills the process and leaves the
  // temporary behind; ignored, write() fails with EFBIG and is reported like a full disk.
  struct sigaction ignore = {}, previous = {};
  ignore.sa_handler = SIG_IGN;
  sigemptyset(&ignore.sa_mask);
  const bool swapped = ::sigaction(SIGXFSZ, &ignore, &previous) == 0;
  struct RestoreXfsz {
    bool swapped;
    const struct sigaction& previous;
    ~RestoreXfsz() {
      if (swapped) ::sigaction(SIGXFSZ, &previous, nullptr);
    }
  } restore{swapped, previous};
  auto fail = [&](int err, const char* during) {
    ::close(fd);
    staged.Discard();
    Fail("{}: cannot write {}: {}{}", path, what, Errno(err), during);
  };
  size_t done = 0;
  while (done < bytes.size()) {
    const ssize_t n = ::write(fd, bytes.data() + done, bytes.size() - done);
    if (n < 0) {
      if (errno == EINTR) continue;
      fail(errno, "");
    }
    if (n == 0) fail(EIO, " (write returned 0)");
    done += static_cast<size_t>(n);
  }
  if (::fsync(fd) != 0 && errno != EINVAL) fail(errno, " (fsync)");
  if (::close(fd) != 0) {
    const int err = errno;
    staged.Discard();
    Fail("{}: cannot write {}: {} (close)", path, what, Errno(err));
  }
  return staged;
}

void WriteFileAtomically(const std::string& path, std::string_view bytes, std::string_view what) {
  StageFile(path, bytes, what).Commit();
}

uint8_t LinearToSrgb8(float x) { return Srgb8().Code(x); }

void LinearToSrgb8(const float* linear, size_t n, uint8_t* out) {
  const Srgb8Table& table = Srgb8();
  for (size_t i = 0; i < n; ++i) out[i] = table.Code(linear[i]);
}

StagedFile StageImage(const std::string& path, int width, int height,
                      const std::vector<float>& rgb) {
  if (path.empty()) Fail("output path is empty");
  if (width <= 0 || height <= 0) Fail("{}: cannot write a {}x{} image", path, width, height);
  const size_t pixels = static_cast<size_t>(width) * static_cast<size_t>(height);
  if (rgb.size() != pixels * 3) {
    Fail("{}: {} floats for a {}x{} rgb image (expected {})", path, rgb.size(), width, height,
         pixels * 3);
  }
  const std::string ext = detail::LowerExtension(path);
  const Encoding encoding = ImageEncodingOrFail(path);
  std::vector<unsigned char> bytes;
  if (encoding == Encoding::kSrgb8) {
    bytes.resize(rgb.size());
    LinearToSrgb8(rgb.data(), rgb.size(), bytes.data());
  }
  std::vector<unsigned char> encoded;
  std::string why;
  if (ext == "png") {
    why = EncodePng(width, height, bytes.data(), &encoded);
  } else {
    const image_module::Functions& module = ImageModule(path, "write image");
    why = module.encode(path, ext, width, height,
                        encoding == Encoding::kSrgb8  ? image_module::FileType::kUint8
                        : encoding == Encoding::kHalf ? image_module::FileType::kHalf
                                                      : image_module::FileType::kFloat,
                        encoding == Encoding::kSrgb8 ? static_cast<const void*>(bytes.data())
                                                     : static_cast<const void*>(rgb.data()),
                        &encoded);
  }
  if (!why.empty()) Fail("{}: cannot write image: {}", path, why);
  if (encoded.empty()) Fail("{}: cannot write image: the encoder produced no data", path);
  return StageFile(path,
                   std::string_view(reinterpret_cast<const char*>(encoded.data()), encoded.size()),
                   "image");
}

void WriteImage(const std::string& path, int width, int height, const std::vector<float>& rgb) {
  StageImage(path, width, height, rgb).Commit();
}

int RemoveTemporaries() noexcept {
  int removed = 0;
  for (TempSlot& slot : g_slots) {
    int expected = kLive;
    if (slot.state.compare_exchange_strong(expected, kRemoving, std::memory_order_acq_rel)) {
      if (::unlink(slot.path) == 0) ++removed;
      slot.state.store(kFree, std::memory_order_release);
    }
  }
  return removed;
}

int PendingTemporaries() noexcept {
  int n = 0;
  for (const TempSlot& slot : g_slots) {
    if (slot.state.load(std::memory_order_acquire) == kLive) ++n;
  }
  return n;
}

// ---- Textures ----------------------------------------------------------------------------------

void SetImageReadLimits(const ImageReadLimits& limits) {
  g_max_pixels.store(limits.max_pixels, std::memory_order_relaxed);
  g_max_pixels_per_byte.store(limits.max_pixels_per_byte, std::memory_order_relaxed);
}

ImageReadLimits GetImageReadLimits() {
  ImageReadLimits limits;
  limits.max_pixels = g_max_pixels.load(std::memory_order_relaxed);
  limits.max_pixels_per_byte = g_max_pixels_per_byte.load(std::memory_order_relaxed);
  return limits;
}

Texture ReadImage(const std::string& path) { return ReadImage(path, GetImageReadLimits()); }

Texture ReadImage(const std::string& path, const ImageReadLimits& limits) {
  // Only regular files: OIIO would block forever on a FIFO and read /dev/zero without end.
  const uint64_t file_size = detail::RegularFileSize(path, "image");
  if (file_size == 0) Fail("{}: cannot read image: the file is empty", path);
  uint64_t exr_pixels = 0;
  std::string exr_what;
  if (ExrLargestWindow(path, file_size, exr_pixels, exr_what) &&
      (exr_pixels > limits.max_pixels ||
       (limits.max_pixels_per_byte > 0 && exr_pixels / limits.max_pixels_per_byte >= file_size))) {
    Fail("{}: {} in a {}-byte file: corrupt, or more than the limit of {} pixels for textures",
         path, exr_what, file_size, limits.max_pixels);
  }
  const image_module::Functions& module = ImageModule(path, "read image");
  Texture tex;
  const std::string why = module.read(path, file_size, limits, &tex);
  if (!why.empty()) throw Error(why);
  return tex;
}

}  // namespace rs
