// Image files through OpenImageIO: rendered frames out (PNG 8-bit sRGB, EXR half), textures in
// (any format OIIO reads, decoded to linear rgb), and the output files every result goes through.
// Images are encoded into memory (OIIO's IOProxy), so every byte that reaches the disk goes
// through our own checked write / fsync / close / rename: OIIO's plugins do not report all write
// errors (libpng leaves a cut-off PNG on a full disk and says nothing).
#include "scenes/image_io.h"

#include <OpenImageIO/filesystem.h>
#include <OpenImageIO/imageio.h>
#include <fcntl.h>
#include <fmt/format.h>
#include <limits.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cctype>
#include <cerrno>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <mutex>
#include <new>
#include <system_error>

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

std::string Lower(std::string s) {
  std::transform(s.begin(), s.end(), s.begin(),
                 [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  return s;
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
  // Encode into memory; the plugin is chosen by the target's extension, nothing touches disk.
  std::vector<unsigned char> encoded;
  {
    QuietStderr quiet;
    auto out = OIIO::ImageOutput::create(path);
    if (!out)
      Fail("{}: cannot write image: no writer for '.{}': {}", path, ext, OneLine(OIIO::geterror()));
    OIIO::Filesystem::IOVecOutput proxy(encoded);
    if (!out->supports("ioproxy") || !out->set_ioproxy(&proxy)) {
      Fail("{}: cannot write image: the '.{}' writer cannot encode to memory", path, ext);
    }
    if (!out->open(path, spec) || !out->write_image(data_type, data) || !out->close()) {
      const std::string why = OneLine(out->geterror());
      Fail("{}: cannot write image: {}", path, why);
    }
  }
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
  return tex;
}

}  // namespace rs
