// Hostile input and output faults: strict MTL values, non-regular files, degenerate
// faces, JSON numbers and duplicate keys, textures whose header lies about their size, corrupt
// textures (no library text on stderr), and output files (checked up front, size limits, no
// temporary left behind, temporaries removable from a signal handler).
#include <doctest/doctest.h>
#include <fcntl.h>
#include <sys/resource.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <csignal>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include "scenes/image_io.h"
#include "scenes/load.h"

namespace rs {
namespace {

namespace fs = std::filesystem;

class TempDir {
 public:
  TempDir() {
    static int counter = 0;
    path_ = fs::temp_directory_path() / ("raystream_hostile_test_" + std::to_string(getpid()) +
                                         "_" + std::to_string(counter++));
    fs::remove_all(path_);
    fs::create_directories(path_);
  }
  ~TempDir() {
    std::error_code ec;
    fs::remove_all(path_, ec);
  }
  std::string Write(const std::string& name, const std::string& bytes) const {
    const fs::path p = path_ / name;
    fs::create_directories(p.parent_path());
    std::ofstream(p, std::ios::binary) << bytes;
    return p.string();
  }
  std::string File(const std::string& name) const { return (path_ / name).string(); }
  std::string path() const { return path_.string(); }
  // Names in the directory (hidden temporaries included).
  std::vector<std::string> Names() const {
    std::vector<std::string> names;
    for (const auto& e : fs::directory_iterator(path_))
      names.push_back(e.path().filename().string());
    std::sort(names.begin(), names.end());
    return names;
  }

 private:
  fs::path path_;
};

template <typename F>
std::string ExpectError(F&& f, std::initializer_list<std::string> fragments) {
  try {
    f();
  } catch (const Error& e) {
    const std::string what = e.what();
    INFO("message: ", what);
    for (const std::string& frag : fragments) CHECK(what.find(frag) != std::string::npos);
    CHECK(what.find('\n') == std::string::npos);  // one line
    return what;
  }
  FAIL("no rs::Error thrown; expected one mentioning ", *fragments.begin());
  return "";
}

Scene LoadObjFile(const std::string& path) {
  Scene s;
  s.source = path;
  LoadObj(path, s);
  return s;
}

constexpr const char* kTriObj = "mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl a\nf 1 2 3\n";

// Captures what is written to fd 2 while alive (libraries print there directly).
class CaptureStderr {
 public:
  explicit CaptureStderr(const std::string& file) : file_(file) {
    std::fflush(stderr);
    saved_ = dup(2);
    const int fd = open(file.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
    dup2(fd, 2);
    close(fd);
  }
  std::string Stop() {
    if (saved_ >= 0) {
      std::fflush(stderr);
      dup2(saved_, 2);
      close(saved_);
      saved_ = -1;
    }
    std::ifstream in(file_, std::ios::binary);
    return std::string((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  }
  ~CaptureStderr() { Stop(); }

 private:
  std::string file_;
  int saved_ = -1;
};

std::string Be32(uint32_t v) {
  return std::string{static_cast<char>(v >> 24), static_cast<char>(v >> 16),
                     static_cast<char>(v >> 8), static_cast<char>(v)};
}

// One PNG chunk: length, type, data, CRC-32 of type + data (as zlib computes it).
std::string PngChunk(const std::string& type, const std::string& data) {
  const std::string body = type + data;
  uint32_t c = 0xFFFFFFFFu;
  for (const unsigned char b : body) {
    c ^= b;
    for (int k = 0; k < 8; ++k) c = (c >> 1) ^ (0xEDB88320u & (0u - (c & 1u)));
  }
  return Be32(static_cast<uint32_t>(data.size())) + body + Be32(c ^ 0xFFFFFFFFu);
}

// A well-formed 8-bit rgb PNG claiming w x h whose IDAT holds `rows` (filter byte + pixels per
// row) as one stored zlib block: `rows` may be far shorter than the header claims.
std::string Png(uint32_t w, uint32_t h, const std::string& rows) {
  uint32_t a = 1, b = 0;  // adler-32
  for (const unsigned char x : rows) {
    a = (a + x) % 65521u;
    b = (b + a) % 65521u;
  }
  const auto len = static_cast<uint16_t>(rows.size());
  std::string zlib("\x78\x01\x01", 3);  // zlib header; final stored block
  zlib += static_cast<char>(len & 0xff);
  zlib += static_cast<char>(len >> 8);
  zlib += static_cast<char>(~len & 0xff);
  zlib += static_cast<char>((~len >> 8) & 0xff);
  zlib += rows + Be32((b << 16) | a);
  return std::string("\x89PNG\r\n\x1a\n", 8) +
         PngChunk("IHDR", Be32(w) + Be32(h) + std::string("\x08\x02\x00\x00\x00", 5)) +
         PngChunk("IDAT", zlib) + PngChunk("IEND", "");
}

// ---- Row 12, 13: MTL values parsed strictly, errors name the .mtl and its line --------------

TEST_CASE("MTL: NaN, garbage, out-of-range values and binary data name the .mtl and its line") {
  TempDir dir;
  const std::string obj = dir.Write("m.obj", kTriObj);
  struct Case {
    const char* mtl;
    const char* where;    // ":<line>:"
    const char* message;  // fragment
  };
  const Case cases[] = {
      {"newmtl a\nKd nan 1 1\n", ":2:", "Kd value 'nan' is not a finite number"},
      {"newmtl a\nKd abc 1 1\n", ":2:", "Kd: bad number 'abc'"},
      {"newmtl a\nKd 1 1\n", ":2:", "Kd needs 3 numbers"},
      {"newmtl a\nKd -0.5 1 1\n", ":2:", "outside [0"},
      {"newmtl a\nKs inf 0 0\n", ":2:", "not a finite number"},
      {"newmtl a\nKd spectral x.rfl\n", ":2:", "spectral colours are not supported"},
      {"# header\nnewmtl a\nNs 1e39\n", ":3:", "Ns value '1e39' is not a finite number"},
      {"newmtl a\nNs 1e6\n", ":2:", "Ns value 1000000 outside [0, 100000]"},
      {"newmtl a\nNi -1\n", ":2:", "Ni value -1 outside"},
      {"newmtl a\nd 1.5\n", ":2:", "d value 1.5 outside [0, 1]"},
      {"newmtl a\nTr x\n", ":2:", "Tr: bad number 'x'"},
      {"newmtl a\nillum 2.5\n", ":2:", "illum: bad number '2.5'"},
      {"newmtl a\nillum 99\n", ":2:", "illum 99 outside [0, 10]"},
      {"newmtl a\nrs_reflectivity 2\n", ":2:", "rs_reflectivity value 2 outside [0, 1]"},
      {"newmtl a\r\nKd 1 1 1\r\nNs 1e40\r\n", ":3:", "not a finite number"},
      {"newmtl a\nKd 1 1 1\n\x89PNG\r\n\x1a\n", ":4:", "control character 0x1a (binary data"},
  };
  for (const Case& c : cases) {
    const std::string mtl = dir.Write("m.mtl", c.mtl);
    INFO("mtl: ", std::string(c.mtl));
    ExpectError([&] { LoadObjFile(obj); }, {mtl + c.where, c.message});
  }
  // Random bytes as .mtl: an error naming the .mtl (not "material not found").
  std::string noise(300, '\0');
  for (size_t i = 0; i < noise.size(); ++i) noise[i] = static_cast<char>((i * 7919u) >> 3);
  const std::string mtl = dir.Write("m.mtl", noise);
  ExpectError([&] { LoadObjFile(obj); }, {mtl + ":", "binary data"});
}

TEST_CASE("MTL: valid files read as before; a grey Kd is grey; comments after values") {
  TempDir dir;
  const std::string obj = dir.Write("m.obj", kTriObj);
  dir.Write("m.mtl",
            "newmtl a\nKd 0.5 # grey, one value\nKs 0.25 0.25 0.25\nNs 40\nNi 1.4\nTr 0.25\n"
            "illum 2\nKe 2257.5 1777.3 1703.5\n");
  const Scene s = LoadObjFile(obj);
  REQUIRE(s.materials.size() == 1);
  const Material& m = s.materials[0];
  CHECK(m.diffuse == glm::vec3(0.5f));  // tinyobjloader alone reads (0.5, 0, 0)
  CHECK(m.specular == glm::vec3(0.25f));
  CHECK(m.shininess == 40.0f);
  CHECK(m.ior == doctest::Approx(1.4f));
  CHECK(m.transmission == doctest::Approx(0.25f));
  // d wins over Tr (tinyobjloader's rule), in either order.
  dir.Write("m.mtl", "newmtl a\nd 0.5\nTr 0.9\n");
  CHECK(LoadObjFile(obj).materials[0].transmission == doctest::Approx(0.5f));
  dir.Write("m.mtl", "newmtl a\nTr 0.9\nd 0.5\n");
  CHECK(LoadObjFile(obj).materials[0].transmission == doctest::Approx(0.5f));
}

TEST_CASE("MTL from memory (the fuzz entry point): same checks") {
  const std::vector<Material> m = ParseMtlText("newmtl a\nKd 1 0 0\nnewmtl b\nd 0.5\n", "mem.mtl");
  REQUIRE(m.size() == 2);
  CHECK(m[0].diffuse == glm::vec3(1, 0, 0));
  CHECK(m[1].transmission == doctest::Approx(0.5f));
  ExpectError([] { ParseMtlText("newmtl a\nKd 1 nan 0\n", "mem.mtl"); }, {"mem.mtl:2: "});
}

// ---- Row 14: non-regular files are rejected saying what they are -----------------------------

TEST_CASE("a directory, a FIFO or a device as scene, mesh, .mtl or texture file") {
  TempDir dir;
  fs::create_directories(dir.File("d.obj"));
  ExpectError([&] { LoadScene(dir.File("d.obj")); }, {"d.obj", "is a directory"});
  REQUIRE(mkfifo(dir.File("p.obj").c_str(), 0644) == 0);
  ExpectError([&] { LoadScene(dir.File("p.obj")); }, {"p.obj", "is a named pipe (FIFO)"});
  ExpectError([&] { LoadObjFile(dir.File("p.obj")); }, {"p.obj", "FIFO"});
  ExpectError([] { LoadScene("/dev/zero"); }, {"/dev/zero", "is a character device"});
  ExpectError([] { LoadScene("/dev/null"); }, {"/dev/null", "is a character device"});
  // In a scene file: "file": "." and a directory named like a mesh.
  const std::string json = dir.Write("s.json", R"({"meshes": [{"file": "."}]})");
  ExpectError([&] { LoadScene(json); }, {"s.json: /meshes/0/file: ", "is a directory"});
  // A .mtl that is a directory: an error, not "not found".
  const std::string obj = dir.Write("m.obj", kTriObj);
  fs::create_directories(dir.File("m.mtl"));
  ExpectError([&] { LoadObjFile(obj); }, {"m.mtl", "is a directory"});
  // A texture that is a FIFO: a warning naming it, immediately (OIIO would block on it).
  fs::remove(dir.File("m.mtl"));
  REQUIRE(mkfifo(dir.File("t.png").c_str(), 0644) == 0);
  dir.Write("m.mtl", "newmtl a\nmap_Kd t.png\n");
  dir.Write("uv.obj",
            "mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nusemtl a\n"
            "f 1/1 2/2 3/3\n");
  const Scene s = LoadObjFile(dir.File("uv.obj"));
  REQUIRE(s.warnings.size() == 1);
  CHECK(s.warnings[0].find("t.png: is a named pipe (FIFO), not a image file") != std::string::npos);
  ExpectError([&] { ReadImage(dir.File("t.png")); }, {"t.png", "FIFO"});
}

// ---- Row 15, 19: degenerate faces and all-degenerate meshes name the line --------------------

TEST_CASE("OBJ: repeated corners and zero-area meshes name the line") {
  TempDir dir;
  // Every face degenerate: an error at the first such face.
  std::string path = dir.Write("d.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3 1 2 3\n");
  ExpectError([&] { LoadObjFile(path); }, {path + ":4: ", "degenerate", "vertex 1"});
  path = dir.Write("d.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 1 1\n");
  ExpectError([&] { LoadObjFile(path); }, {path + ":4: "});
  // Relative and absolute indices naming the same vertex are the same corner.
  path = dir.Write("d.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 3 -1 2\n");
  Scene s = LoadObjFile(path);
  REQUIRE(!s.warnings.empty());
  CHECK(s.warnings.back().find(path + ":5: face names vertex 3 twice (1 such faces") !=
        std::string::npos);
  // Only zero-area triangles: nothing to render is an error naming the first face.
  path = dir.Write("z.obj", "v 0 0 0\nv 1 0 0\nv 2 0 0\n# collinear\nf 1 2 3\nf 3 2 1\n");
  ExpectError([&] { LoadObjFile(path); }, {path + ":5: every triangle has zero area"});
  // Some zero-area triangles among good ones are legal (the shared conference has 53,627).
  path = dir.Write("ok.obj", "v 0 0 0\nv 1 0 0\nv 2 0 0\nv 0 1 0\nf 1 2 3\nf 1 2 4\n");
  CHECK(LoadObjFile(path).triangles.size() == 2);
  // Tiny but valid triangles are not zero area (no squared-length underflow).
  path = dir.Write("tiny.obj", "v 0 0 0\nv 1e-15 0 0\nv 0 1e-15 0\nf 1 2 3\n");
  CHECK(LoadObjFile(path).triangles.size() == 1);
}

TEST_CASE("PLY and scene files: zero-area meshes are errors") {
  TempDir dir;
  const std::string ply = dir.Write(
      "z.ply",
      "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
      "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
      "0 0 0\n1 1 1\n2 2 2\n3 0 1 2\n");
  ExpectError([&] { LoadScene(ply); }, {ply + ": every face has zero area"});
  ExpectError(
      [] {
        ParseSceneJsonText(R"({"meshes": [{"quad": [[0,0,0],[1,0,0],[2,0,0],[3,0,0]]}]})",
                           "q.json");
      },
      {"q.json: /meshes/0/quad: the 4 corners span no area"});
}

// ---- Row 18: JSON numbers and duplicate keys, with line:column -------------------------------

TEST_CASE("scene file: 1e400, integers beyond 64 bits, above 2^63, duplicate keys") {
  const std::string box = R"("meshes": [{"box": {"min": [0,0,0], "max": [1,1,1]}}])";
  struct Case {
    std::string text;
    std::string fragment;
  };
  const Case cases[] = {
      {"{" + box + ",\n \"ambient\": 1e400}", "j.json:2:13: number 1e400 out of range"},
      {"{" + box + ",\n \"ambient\": -1e400}", "j.json:2:13: number -1e400 out of range"},
      {"{" + box + ",\n \"path\": {\"frames\": 18446744073709551616}}",
       "j.json:2:21: integer 18446744073709551616 out of range (64 bits)"},
      {"{" + box + ",\n \"path\": {\"frames\": -9223372036854775809}}",
       "j.json:2:21: integer -9223372036854775809 out of range"},
      {"{" + box + ", \"path\": {\"frames\": 18446744073709551615}}",
       "j.json: /path/frames: 18446744073709551615 outside [1, 10000000]"},
      {"{" + box + ", \"path\": {\"frames\": 9223372036854775808}}",
       "/path/frames: 9223372036854775808 outside"},
      {"{" + box + ",\n  \"ambient\": 0.5,\n  \"ambient\": 0.7}",
       "j.json:3:3: duplicate key \"ambient\""},
      {"{" + box + ", \"camera\": {\"fov\": 40,\n \"fov\": 50}}",
       "j.json:2:2: duplicate key \"fov\""},
      // Escapes: "\u0061mbient" is "ambient".
      {"{" + box + ",\"ambient\": 0.5, \"\\u0061mbient\": 0.7}", "duplicate key \"ambient\""},
  };
  for (const Case& c : cases) {
    INFO("json: ", c.text);
    ExpectError([&] { ParseSceneJsonText(c.text, "j.json"); }, {c.fragment});
  }
  // The same key in different objects, keys inside strings, comments: all fine.
  const Scene s = ParseSceneJsonText(
      R"({"meshes": [{"box": {"min": [0,0,0], "max": [1,1,1]}},
                     {"box": {"min": [2,0,0], "max": [3,1,1]}}],
          // "ambient": 1e400 in a comment /* and "ambient" */
          "name": "ambient\"ambient", "ambient": 0.25, "path": {"frames": 3}})",
      "ok.json");
  CHECK(s.ambient == 0.25f);
  CHECK(s.path.frames == 3);
}

// ---- Row 5: a camera path whose eye meets look_at between keys is a load-time error -------

TEST_CASE("scene file: a path through its own look_at names the keys and the frame") {
  const std::string box = R"("meshes": [{"box": {"min": [0,0,0], "max": [1,1,1]}}])";
  // The eye moves from z = 5 to z = -5 through the fixed look_at (0, 0, 0): frame 2 of 5.
  ExpectError(
      [&] {
        ParseSceneJsonText("{" + box + R"(, "path": {"frames": 5, "keys": [
            {"eye": [0,0,5], "look_at": [0,0,0]}, {"eye": [0,0,-5], "look_at": [0,0,0]}]}})",
                           "p.json");
      },
      {"p.json: path keys 0 and 1: the eye meets look_at between them (frame 2 at speed 1)"});
  // Passing beside the target is fine.
  const Scene s = ParseSceneJsonText("{" + box + R"(, "path": {"frames": 5, "keys": [
      {"eye": [0,1,5], "look_at": [0,0,0]}, {"eye": [0,1,-5], "look_at": [0,0,0]}]}})",
                                     "p.json");
  CHECK(s.path.keys.size() == 2);
}

// ---- Row 10, 16: texture headers checked before allocating; corrupt files print nothing -------

TEST_CASE("texture: a 16000x16000 header in a small file is refused before any allocation") {
  TempDir dir;
  const std::string path = dir.Write("big.png", Png(16000, 16000, std::string(100, '\0')));
  CHECK(fs::file_size(path) < 300);
  // Bounded memory: this test fails with bad_alloc (not rs::Error) if 3 GB are allocated.
  struct rlimit old;
  getrlimit(RLIMIT_AS, &old);
  const bool sanitized =
#if defined(__SANITIZE_ADDRESS__)
      true;
#elif defined(__has_feature)
#if __has_feature(address_sanitizer)
      true;
#else
      false;
#endif
#else
      false;
#endif
  if (!sanitized) {
    struct rlimit lim = old;
    lim.rlim_cur = 1536ull << 20;
    setrlimit(RLIMIT_AS, &lim);
  }
  ExpectError([&] { ReadImage(path); }, {path, "16000x16000", "limit of 67108864"});
  // Above the default pixel limit too, the file's size gives it away (deflate: <= ~1032:1).
  ImageReadLimits huge;
  huge.max_pixels = uint64_t{1} << 32;
  ExpectError([&] { ReadImage(path, huge); },
              {path, "claims 16000x16000", "only 168 bytes (corrupt or truncated)"});
  // An EXR attribute claiming 1.7 GB (found by texture_fuzz) would make OpenEXR allocate it
  // inside OIIO's open(), before any spec: ReadImage checks the header first.
  const std::string exr =
      dir.Write("attr.exr", std::string("v/1\x01\x02\0\0\0capDate\0string\0\x61\x74\x6e\x65", 27) +
                                std::string(200, '\x0d'));
  ExpectError([&] { ReadImage(exr); },
              {exr, "EXR attribute 'capDate' claims 1701737569 bytes", "corrupt"});
  // A TIFF of 15620x4 pixels claiming 65312 rows per strip (found by texture_fuzz): OIIO 2.4
  // would allocate a 4 GB strip buffer for it (under the 1.5 GB limit above: bad_alloc).
  const std::string tif_hex =
      "49492a00080000000e000001030001000000043d00000101030001000000040000000201030003000000b600"
      "00000301030001000000080000000601030001000000020000001101040001000000d6000000120103000100"
      "000001000100001500030100000003000000160103000100000020fffc001701040001000000880000001c01"
      "030001000000010000003101020014000000c20000083501030001000000030000005301030003000000bc00"
      "000000000000200020002000030003000300323032363a31323a303220303a353434323a3000789c63b0b1b5"
      "65ffffffffffffffffffffffffffffffffff7a6669ffffffffffffffffffffffffffffffffffffffffffffff"
      "ffffffffffffffffffffffffffffffffffffffffffffffff3838383838383838383838383838383838383838"
      "38383838383838383838383838383838ffffffffffffffffffffffffffffffffffffffffffffff052cb1";
  std::string tif_bytes;
  for (size_t i = 0; i + 1 < tif_hex.size(); i += 2) {
    tif_bytes.push_back(static_cast<char>(std::stoi(tif_hex.substr(i, 2), nullptr, 16)));
  }
  const std::string tif = dir.Write("strip.tif", tif_bytes);
  ExpectError([&] { ReadImage(tif); }, {tif, "65312 rows per strip", "15620x4"});
  // The configurable limit: a real 64x64 image above a 1000-pixel limit.
  WriteImage(dir.File("small.png"), 64, 64, std::vector<float>(64 * 64 * 3, 0.5f));
  ImageReadLimits limits;
  limits.max_pixels = 1000;
  ExpectError([&] { ReadImage(dir.File("small.png"), limits); },
              {"small.png", "64x64", "4096 pixels", "limit of 1000"});
  CHECK(ReadImage(dir.File("small.png")).width == 64);
  const ImageReadLimits saved = GetImageReadLimits();
  SetImageReadLimits(limits);
  ExpectError([&] { ReadImage(dir.File("small.png")); }, {"limit of 1000"});
  SetImageReadLimits(saved);
  if (!sanitized) setrlimit(RLIMIT_AS, &old);
}

TEST_CASE("texture: corrupt and truncated files give one line and print nothing") {
  TempDir dir;
  // 2x2 rgb: per row a filter byte (0: none) and 6 bytes.
  const std::string rows = std::string("\0", 1) + "abcdef" + std::string("\0", 1) + "ghijkl";
  const std::string good = Png(2, 2, rows);
  REQUIRE(ReadImage(dir.Write("good.png", good)).width == 2);
  std::string bad_filter = rows;
  bad_filter[7] = 9;  // filter types are 0..4
  std::string bad_crc = good;
  bad_crc[good.find("IDAT") + 8] ^= 0x40;  // a data byte: the chunk's CRC no longer matches
  const std::string cases[] = {
      dir.Write("bad_filter.png", Png(2, 2, bad_filter)),
      dir.Write("bad_crc.png", bad_crc),
      dir.Write("short_data.png", Png(2, 2, rows.substr(0, 9))),
      dir.Write("trunc_header.png", good.substr(0, 30)),
      dir.Write("trunc_data.png", good.substr(0, good.size() / 2)),
      dir.Write("empty.png", ""),
      dir.Write("text.png", "hello, not a png"),
      dir.Write("bad.jpg", "\xff\xd8\xff\xe0 not really a jpeg"),
      dir.Write("bad.exr", "v/1\x01 not really an exr file"),
  };
  for (const std::string& path : cases) {
    INFO("file: ", path);
    CaptureStderr capture(dir.File("stderr.txt"));
    ExpectError([&] { ReadImage(path); }, {path});
    CHECK(capture.Stop().empty());
  }
  // Through a material: one warning line naming the .mtl and the texture, nothing else printed.
  dir.Write("m.mtl", "newmtl a\nmap_Kd bad_filter.png\n");
  dir.Write("uv.obj",
            "mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nusemtl a\n"
            "f 1/1 2/2 3/3\n");
  CaptureStderr capture(dir.File("stderr.txt"));
  const Scene s = LoadObjFile(dir.File("uv.obj"));
  CHECK(capture.Stop().empty());
  REQUIRE(s.warnings.size() == 1);
  CHECK(s.warnings[0].find("m.mtl") != std::string::npos);
  CHECK(s.warnings[0].find("bad_filter.png") != std::string::npos);
  CHECK(s.warnings[0].find('\n') == std::string::npos);
}

// ---- Rows 1, 2, 17: output files ---------------------------------------------------------------

TEST_CASE("CheckOutputPath: missing folder, a file as folder, a directory as target, empty") {
  TempDir dir;
  ExpectError([] { CheckOutputPath(""); }, {"output path is empty"});
  const std::string missing = dir.File("no/such/x.png");
  ExpectError([&] { CheckOutputPath(missing); }, {missing, "folder", "does not exist"});
  dir.Write("plain", "x");
  ExpectError([&] { CheckOutputPath(dir.File("plain/x.png")); },
              {dir.File("plain/x.png"), "is not a folder"});
  fs::create_directories(dir.File("taken.png"));
  ExpectError([&] { CheckOutputPath(dir.File("taken.png")); }, {"taken.png", "is a directory"});
  ExpectError([&] { CheckOutputPath(dir.path() + "/"); }, {"names a folder"});
  ExpectError([] { CheckOutputPath("/dev/null"); }, {"/dev/null", "character device"});
  ExpectError([&] { CheckImageOutputPath(dir.File("x.bogus")); }, {"x.bogus", "extension"});
  // /proc refuses new files even for root.
  ExpectError([] { CheckOutputPath("/proc/x.png"); }, {"/proc/x.png", "cannot create files"});
  if (geteuid() != 0) {
    fs::create_directories(dir.File("ro"));
    fs::permissions(dir.File("ro"), fs::perms::owner_read | fs::perms::owner_exec);
    ExpectError([&] { CheckOutputPath(dir.File("ro/x.png")); }, {"Permission denied"});
    fs::permissions(dir.File("ro"), fs::perms::owner_all);
  }
  CHECK_NOTHROW(CheckOutputPath(dir.File("fine.png")));
  CHECK_NOTHROW(CheckImageOutputPath(dir.File("fine.exr")));
  CHECK(!fs::exists(dir.File("fine.png")));
  CHECK(PendingTemporaries() == 0);
  const std::vector<std::string> expected = {"plain", "taken.png"};
  CHECK(dir.Names() == expected);
}

// Noise does not compress: the encoded image is about width * height * 3 bytes.
std::vector<float> Noise(int w, int h) {
  std::vector<float> rgb(static_cast<size_t>(w) * h * 3);
  uint32_t x = 12345;
  for (float& v : rgb) {
    x = x * 1664525u + 1013904223u;
    v = static_cast<float>(x >> 8) / 16777216.0f;
  }
  return rgb;
}

TEST_CASE(
    "a write beyond the file size limit (a full disk) fails naming the path, leaves nothing") {
  TempDir dir;
  const std::vector<float> rgb = Noise(64, 64);  // ~12 KB as PNG
  WriteImage(dir.File("keep.png"), 4, 4, std::vector<float>(48, 1.0f));
  const auto before = fs::file_size(dir.File("keep.png"));
  struct rlimit old;
  REQUIRE(getrlimit(RLIMIT_FSIZE, &old) == 0);
  const auto old_handler = std::signal(SIGXFSZ, SIG_IGN);  // write() then fails with EFBIG
  struct rlimit lim = old;
  lim.rlim_cur = 4096;
  REQUIRE(setrlimit(RLIMIT_FSIZE, &lim) == 0);
  for (const char* name : {"x.png", "x.jpg", "x.bmp", "x.tga", "x.exr", "keep.png"}) {
    const std::string path = dir.File(name);
    INFO("file: ", path);
    ExpectError([&] { WriteImage(path, 64, 64, rgb); },
                {path + ": cannot write image: File too large"});
  }
  const std::string stats(10000, '{');
  ExpectError([&] { WriteFileAtomically(dir.File("s.json"), stats, "statistics"); },
              {dir.File("s.json") + ": cannot write statistics: File too large"});
  setrlimit(RLIMIT_FSIZE, &old);
  std::signal(SIGXFSZ, old_handler);
  // Nothing new, no temporary, and the old image untouched.
  const std::vector<std::string> expected = {"keep.png"};
  CHECK(dir.Names() == expected);
  CHECK(fs::file_size(dir.File("keep.png")) == before);
  CHECK(PendingTemporaries() == 0);
}

TEST_CASE("staged files: commit places them, discard and destruction remove them") {
  TempDir dir;
  {
    StagedFile a = StageImage(dir.File("a.png"), 4, 4, std::vector<float>(48, 0.5f));
    StagedFile b = StageFile(dir.File("b.json"), "{}\n", "statistics");
    CHECK(PendingTemporaries() == 2);
    CHECK(fs::exists(a.temporary()));
    CHECK(fs::path(a.temporary()).parent_path() == fs::path(dir.path()));
    CHECK(fs::path(a.temporary()).filename().string().rfind(".a.png.tmp", 0) == 0);
    CHECK(!fs::exists(dir.File("a.png")));
    a.Commit();
    CHECK(fs::exists(dir.File("a.png")));
    CHECK(ReadImage(dir.File("a.png")).width == 4);
    StagedFile moved = std::move(b);
    CHECK(PendingTemporaries() == 1);
  }  // `moved` destroyed uncommitted: its temporary goes
  CHECK(PendingTemporaries() == 0);
  const std::vector<std::string> expected = {"a.png"};
  CHECK(dir.Names() == expected);
  // A commit whose target became a directory fails naming it and removes the temporary.
  StagedFile c = StageFile(dir.File("c.txt"), "x", "file");
  fs::create_directories(dir.File("c.txt"));
  ExpectError([&] { c.Commit(); }, {dir.File("c.txt"), "is a directory"});
  CHECK(PendingTemporaries() == 0);
  CHECK(dir.Names().size() == 2);
}

TEST_CASE("RemoveTemporaries: what a SIGINT handler calls removes every temporary") {
  TempDir dir;
  StagedFile a = StageFile(dir.File("f0000.png"), "x", "image");
  StagedFile b = StageFile(dir.File("f0001.png"), "y", "image");
  CHECK(dir.Names().size() == 2);
  CHECK(RemoveTemporaries() == 2);
  CHECK(dir.Names().empty());
  CHECK(PendingTemporaries() == 0);
  // Committing after an interrupt fails clearly and writes nothing.
  ExpectError([&] { a.Commit(); }, {"f0000.png", "interrupted"});
  CHECK(dir.Names().empty());
  CHECK(RemoveTemporaries() == 0);
}

// The real thing: a handler that calls RemoveTemporaries() and _exit, raised mid-sequence in a
// child process (fork: the registry is per process).
extern "C" void RemoveAndExit(int) {
  RemoveTemporaries();
  _exit(130);
}

TEST_CASE("RemoveTemporaries from a signal handler in a child process") {
  TempDir dir;
  const pid_t pid = fork();
  REQUIRE(pid >= 0);
  if (pid == 0) {
    std::signal(SIGINT, RemoveAndExit);
    StagedFile a = StageFile(dir.File("a.png"), "x", "image");
    StagedFile b = StageImage(dir.File("b.png"), 2, 2, std::vector<float>(12, 0.0f));
    raise(SIGINT);
    _exit(0);  // not reached
  }
  int status = 0;
  REQUIRE(waitpid(pid, &status, 0) == pid);
  CHECK(WIFEXITED(status));
  CHECK(WEXITSTATUS(status) == 130);
  CHECK(dir.Names().empty());
}

}  // namespace
}  // namespace rs
