// Scene loaders: OBJ + MTL, PLY (ASCII and binary), scene files (JSON), the search path and
// LoadScene's dispatch. Small inputs are written to a temporary directory by the test; broken
// ones must give an rs::Error naming the file and the line or element. The shared scenes load
// with their known triangle counts.
#include <doctest/doctest.h>
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <string>

#include "scenes/image_io.h"
#include "scenes/load.h"
#include "tests/test_util.h"

namespace rs {
namespace {

namespace fs = std::filesystem;

// A fresh directory under the system temp dir, removed with its contents at the end.
class TempDir {
 public:
  TempDir() {
    static int counter = 0;
    path_ = fs::temp_directory_path() /
            ("raystream_loader_test_" + std::to_string(getpid()) + "_" + std::to_string(counter++));
    fs::remove_all(path_);
    fs::create_directories(path_);
  }
  ~TempDir() {
    std::error_code ec;
    fs::remove_all(path_, ec);
  }
  std::string Write(const std::string& name, const std::string& text) const {
    const fs::path p = path_ / name;
    fs::create_directories(p.parent_path());
    std::ofstream(p, std::ios::binary) << text;
    return p.string();
  }
  std::string path() const { return path_.string(); }

 private:
  fs::path path_;
};

// Sets an environment variable for the scope, restoring the old value afterwards.
class ScopedEnv {
 public:
  ScopedEnv(const char* name, const std::string& value) : name_(name) {
    if (const char* old = std::getenv(name)) {
      had_ = true;
      old_ = old;
    }
    setenv(name, value.c_str(), 1);
  }
  ~ScopedEnv() {
    if (had_) {
      setenv(name_, old_.c_str(), 1);
    } else {
      unsetenv(name_);
    }
  }

 private:
  const char* name_;
  bool had_ = false;
  std::string old_;
};

// Runs `f`, which must throw rs::Error whose message contains every fragment.
template <typename F>
std::string ExpectError(F&& f, std::initializer_list<std::string> fragments) {
  try {
    f();
  } catch (const Error& e) {
    const std::string what = e.what();
    INFO("message: ", what);
    for (const std::string& frag : fragments) CHECK(what.find(frag) != std::string::npos);
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

Scene LoadPlyFile(const std::string& path) {
  Scene s;
  s.source = path;
  LoadWithAssimp(path, s);
  return s;
}

constexpr const char* kQuadObj =
    "# a unit quad and a triangle, two materials\n"
    "mtllib quad.mtl\n"
    "v 0 0 0\n"
    "v 1 0 0\n"
    "v 1 1 0\n"
    "v 0 1 0\n"
    "v 0 0 1\n"
    "usemtl shiny\n"
    "f 1 2 3 4\n"
    "usemtl glass\n"
    "f -5 -3 -1\n";

constexpr const char* kQuadMtl =
    "newmtl shiny\n"
    "Kd 0.5 0.25 0.125\n"
    "Ks 0.6 0.6 0.6\n"
    "Ns 80\n"
    "illum 3\n"
    "newmtl glass\n"
    "Kd 0.9 0.9 0.9\n"
    "d 0.25\n"
    "Ni 1.33\n"
    "newmtl custom\n"
    "Kd 0.1 0.2 0.3\n"
    "rs_reflectivity 0.4\n";

TEST_CASE("OBJ: faces, triangulation, MTL materials and raystream conventions") {
  TempDir dir;
  dir.Write("quad.mtl", kQuadMtl);
  const Scene s = LoadObjFile(dir.Write("quad.obj", kQuadObj));
  REQUIRE(s.triangles.size() == 3);  // quad -> 2, triangle -> 1
  CHECK(s.positions.size() == 5);
  CHECK(s.uvs.empty());
  CHECK(s.normals.empty());
  CHECK(s.warnings.empty());
  const Material& shiny = s.materials[s.material_ids[0]];
  CHECK(shiny.name == "shiny");
  CHECK(s.material_ids[1] == s.material_ids[0]);
  CHECK(shiny.diffuse.y == doctest::Approx(0.25f));
  CHECK(shiny.specular.x == doctest::Approx(0.6f));
  CHECK(shiny.shininess == doctest::Approx(80.0f));
  CHECK(shiny.reflectivity == doctest::Approx(0.6f));  // illum 3: max(Ks)
  CHECK(shiny.transmission == 0.0f);
  const Material& glass = s.materials[s.material_ids[2]];
  CHECK(glass.name == "glass");
  CHECK(glass.transmission == doctest::Approx(0.75f));  // 1 - d
  CHECK(glass.ior == doctest::Approx(1.33f));
  CHECK(glass.shininess == 0.0f);                // no Ns: no highlight
  CHECK(s.triangles[2] == glm::uvec3(0, 2, 4));  // -5 -3 -1 relative to 5 vertices
  // The unused "custom" material is still converted (extension key honoured).
  bool found_custom = false;
  for (const Material& m : s.materials) {
    if (m.name == "custom") {
      found_custom = true;
      CHECK(m.reflectivity == doctest::Approx(0.4f));
    }
  }
  CHECK(found_custom);
}

TEST_CASE("OBJ: uvs and normals indexed separately are unwelded per vertex") {
  TempDir dir;
  // One quad whose corners share positions with a second quad but not texcoords.
  const std::string obj =
      "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\n"
      "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nvt 0.5 0.5\n"
      "vn 0 0 2\n"
      "f 1/1/1 2/2/1 3/3/1\n"
      "f 1/5/1 3/3/1 4/4/1\n";
  const Scene s = LoadObjFile(dir.Write("uv.obj", obj));
  REQUIRE(s.triangles.size() == 2);
  // Corners: (1,1) (2,2) (3,3) (1,5) (4,4): vertex 1 appears with two uvs -> 5 vertices.
  CHECK(s.positions.size() == 5);
  REQUIRE(s.uvs.size() == s.positions.size());
  REQUIRE(s.normals.size() == s.positions.size());
  CHECK(s.normals[0].z == doctest::Approx(1.0f));  // normalised
  const glm::uvec3 t1 = s.triangles[1];
  CHECK(s.positions[t1.x] == glm::vec3(0, 0, 0));
  CHECK(s.uvs[t1.x] == glm::vec2(0.5f, 0.5f));
  CHECK(s.uvs[s.triangles[0].x] == glm::vec2(0.0f, 0.0f));
  CHECK(s.positions[s.triangles[0].x] == s.positions[t1.x]);
}

TEST_CASE("OBJ: a missing MTL gives the default material and a warning") {
  TempDir dir;
  const Scene s = LoadObjFile(dir.Write("nomtl.obj",
                                        "mtllib missing.mtl\nusemtl red\nv 0 0 0\nv 1 0 0\n"
                                        "v 0 1 0\nf 1 2 3\n"));
  REQUIRE(s.triangles.size() == 1);
  REQUIRE(s.materials.size() == 1);
  CHECK(s.materials[0].name == "default");
  REQUIRE(!s.warnings.empty());
  CHECK(s.warnings[0].find("missing.mtl") != std::string::npos);
  CHECK(s.warnings[0].find("default material") != std::string::npos);
}

TEST_CASE("OBJ: map_Kd textures are read and enable the texture feature") {
  TempDir dir;
  std::vector<float> rgb(4 * 2 * 3, 0.5f);
  WriteImage(dir.path() + "/tex.png", 4, 2, rgb);
  dir.Write("t.mtl", "newmtl tex\nKd 1 1 1\nmap_Kd tex.png\n");
  const std::string path =
      dir.Write("t.obj",
                "mtllib t.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nusemtl tex\n"
                "f 1/1 2/2 3/3\n");
  const Scene s = LoadScene(path);
  REQUIRE(s.textures.size() == 1);
  CHECK(s.textures[0].width == 4);
  CHECK(s.textures[0].height == 2);
  CHECK(s.textures[0].rgb[0] == doctest::Approx(0.5f).epsilon(0.01));
  CHECK(s.features.textures);
  // A texture that cannot be read: warning, untextured.
  dir.Write("t.mtl", "newmtl tex\nKd 1 1 1\nmap_Kd nothere.png\n");
  const Scene u = LoadObjFile(path);
  CHECK(u.textures.empty());
  CHECK(u.materials[u.material_ids[0]].texture == -1);
  REQUIRE(!u.warnings.empty());
  CHECK(u.warnings[0].find("nothere.png") != std::string::npos);
}

TEST_CASE("OBJ: malformed input names the file and the line") {
  TempDir dir;
  struct Case {
    const char* text;
    const char* line;     // ":<line>:"
    const char* message;  // fragment
  };
  const Case cases[] = {
      {"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n", ":4:", "vertex index 9 out of range (3 vertices"},
      {"v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n", ":2:", "not finite"},
      {"v 0 0 0\nv 1 0 0\nv 0 inf 0\nf 1 2 3\n", ":3:", "not finite"},
      {"v 0 0 0\nv 1 0 1e39\nv 0 1 0\nf 1 2 3\n", ":2:", "not finite"},
      {"v 0 0 0\nv 1 0 1e25\nv 0 1 0\nf 1 2 3\n", ":2:", "too large"},
      {"v 0 0\n", ":1:", "3 coordinates"},
      {"v 0 abc 0\n", ":1:", "bad number 'abc'"},
      {"v 0 0 0\nv 1 0 0\nv 0 1 0\nhello world\nf 1 2 3\n", ":4:", "unknown statement 'hello'"},
      {"v 0 0 0\nv 1 0 0\nf 1 2\n", ":3:", "need at least 3"},
      {"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", ":4:", "index 0"},
      {"v 0 0 0\nv 1 0 0\nv 0 1 0\nf -1 -2 -4\n", ":4:", "relative vertex index -4"},
      {"v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1 2/2 3/1\n", ":5:", "texture coordinate index 2"},
      {"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1/x 2 3\n", ":4:", "bad texture coordinate index 'x'"},
      {"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1/1/1/1 2 3\n", ":4:", "bad face vertex"},
      {"v 0 0 0\n\x01\x02garbage\n", ":2:", "control character"},
      {"# comment only\n\n", "", "scene has no triangles"},
      {"v 0 0 0\nv 1 0 0\nv 0 1 0\n", "", "scene has no triangles"},
  };
  for (const Case& c : cases) {
    const std::string path = dir.Write("bad.obj", c.text);
    INFO("input: ", std::string(c.text));
    ExpectError([&] { LoadObjFile(path); }, {path + c.line, c.message});
  }
  // Windows line ends and a lone CR count lines like tinyobjloader does.
  const std::string crlf = dir.Write("crlf.obj", "v 0 0 0\r\nv 1 0 0\r\nv 0 nan 0\r\nf 1 2 3\r\n");
  ExpectError([&] { LoadObjFile(crlf); }, {crlf + ":3:", "not finite"});
}

TEST_CASE("OBJ and PLY from memory: same checks, origin in messages") {
  Scene s;
  ParseObjText("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "mem.obj", s);
  CHECK(s.triangles.size() == 1);
  Scene t;
  ExpectError([&] { ParseObjText("v 0 0 0\nf 1 2 3\n", "mem.obj", t); },
              {"mem.obj:2:", "vertex index 3 out of range"});
  Scene p;
  ParsePlyText(
      "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
      "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
      "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n",
      "mem.ply", p);
  CHECK(p.triangles.size() == 1);
  CHECK(p.materials.size() == 1);
}

constexpr const char* kPlyHeader =
    "ply\n"
    "format ascii 1.0\n"
    "comment a tetrahedron plus a quad\n"
    "element vertex 5\n"
    "property float x\n"
    "property float y\n"
    "property float z\n"
    "property float confidence\n"
    "element face 5\n"
    "property list uchar int vertex_indices\n"
    "end_header\n";  // line 11

TEST_CASE("PLY: ASCII loads, polygons are triangulated") {
  TempDir dir;
  const std::string body =
      "0 0 0 1\n1 0 0 1\n0 1 0 1\n0 0 1 1\n1 1 1 0.5\n"
      "3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n4 1 4 3 0\n";
  const Scene s = LoadPlyFile(dir.Write("tet.ply", std::string(kPlyHeader) + body));
  CHECK(s.triangles.size() == 6);
  CHECK(s.positions.size() == 5);
  glm::vec3 lo, hi;
  s.Bounds(lo, hi);
  CHECK(lo == glm::vec3(0.0f));
  CHECK(hi == glm::vec3(1.0f));
}

TEST_CASE("PLY: normals and texture coordinates are read") {
  TempDir dir;
  const std::string text =
      "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
      "property float z\nproperty float nx\nproperty float ny\nproperty float nz\n"
      "property float s\nproperty float t\nelement face 1\n"
      "property list uchar int vertex_index\nend_header\n"
      "0 0 0 0 0 2 0 0\n1 0 0 0 0 1 1 0\n0 1 0 0 0 0 0 1\n3 0 1 2\n";
  const Scene s = LoadPlyFile(dir.Write("nuv.ply", text));
  REQUIRE(s.normals.size() == 3);
  REQUIRE(s.uvs.size() == 3);
  CHECK(s.normals[0] == glm::vec3(0, 0, 1));  // normalised
  CHECK(s.normals[2] == glm::vec3(0, 0, 1));  // zero normal replaced by the face normal
  CHECK(s.uvs[2] == glm::vec2(0, 1));
  REQUIRE(s.warnings.size() == 1);
  CHECK(s.warnings[0].find("1 zero-length vertex normals") != std::string::npos);
}

TEST_CASE("PLY: binary little-endian loads") {
  TempDir dir;
  std::string data =
      "ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n"
      "property float y\nproperty float z\nelement face 1\n"
      "property list uchar uint vertex_indices\nend_header\n";
  const float v[9] = {0, 0, 0, 2, 0, 0, 0, 3, 0};
  data.append(reinterpret_cast<const char*>(v), sizeof(v));
  data.push_back(3);
  const uint32_t idx[3] = {0, 1, 2};
  data.append(reinterpret_cast<const char*>(idx), sizeof(idx));
  const Scene s = LoadPlyFile(dir.Write("bin.ply", data));
  REQUIRE(s.triangles.size() == 1);
  glm::vec3 lo, hi;
  s.Bounds(lo, hi);
  CHECK(hi == glm::vec3(2, 3, 0));
  // Truncated binary body, NaN vertex, index out of range: element named.
  ExpectError([&] { LoadPlyFile(dir.Write("t.ply", data.substr(0, data.size() - 5))); },
              {"t.ply", "face 0: unexpected end of file"});
  std::string nan_data = data;
  const float nan = std::nanf("");
  std::memcpy(&nan_data[nan_data.size() - 13 - 3 * 4 + 4], &nan, 4);  // vertex 2, y
  ExpectError([&] { LoadPlyFile(dir.Write("n.ply", nan_data)); },
              {"n.ply", "vertex 2", "not finite"});
  std::string bad_index = data;
  bad_index[bad_index.size() - 4] = 7;
  ExpectError([&] { LoadPlyFile(dir.Write("i.ply", bad_index)); },
              {"i.ply", "face 0: vertex index 7 out of range (3 vertices)"});
}

// Regression (fuzz finding): assimp 5.2.4 skipped a data byte 0x0A right after "end_header\n"
// and then aborted in its triangulation; binary data may start with any byte.
TEST_CASE("PLY: binary data starting with a newline byte reads exactly") {
  TempDir dir;
  std::string data =
      "ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n"
      "property float y\nproperty float z\nelement face 1\n"
      "property list uchar int vertex_indices\nend_header\n";
  const unsigned char x0[4] = {0x0A, 0x00, 0x80, 0x3F};  // 1.0000012f, first byte '\n'
  float x;
  std::memcpy(&x, x0, 4);
  const float v[9] = {x, 0, 0, 0, 2, 0, 0, 0, 3};
  data.append(reinterpret_cast<const char*>(v), sizeof(v));
  data.push_back(3);
  const int32_t idx[3] = {0, 1, 2};
  data.append(reinterpret_cast<const char*>(idx), sizeof(idx));
  const Scene s = LoadPlyFile(dir.Write("nl.ply", data));
  REQUIRE(s.positions.size() == 3);
  CHECK(s.positions[0].x == x);
  CHECK(s.positions[2].z == 3.0f);
  CHECK(s.triangles[0] == glm::uvec3(0, 1, 2));
  // Big-endian too.
  std::string be = data;
  be.replace(be.find("binary_little_endian"), 20, "binary_big_endian   ");
  be.replace(be.find("binary_big_endian   "), 20, "binary_big_endian");
  const size_t body = be.find("end_header\n") + 11;
  for (size_t k = body; k + 4 <= body + 36; k += 4) std::reverse(&be[k], &be[k + 4]);
  for (size_t k = body + 37; k + 4 <= be.size(); k += 4) std::reverse(&be[k], &be[k + 4]);
  const Scene t = LoadPlyFile(dir.Write("be.ply", be));
  CHECK(t.positions[0].x == x);
  CHECK(t.triangles[0] == glm::uvec3(0, 1, 2));
}

TEST_CASE("PLY: malformed input names the file and the line") {
  TempDir dir;
  const std::string verts = "0 0 0 1\n1 0 0 1\n0 1 0 1\n0 0 1 1\n1 1 1 0.5\n";  // lines 12-16
  const std::string faces = "3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n";             // lines 17-20
  struct Case {
    std::string text;
    std::string fragment;
  };
  const Case cases[] = {
      {std::string(kPlyHeader) + verts + faces + "3 0 1 7\n",
       ":21: face 4: vertex index 7 out of range (5 vertices)"},
      {std::string(kPlyHeader) + "0 0 0 1\n1 nan 0 1\n0 1 0 1\n0 0 1 1\n1 1 1 1\n" + faces +
           "3 0 1 2\n",
       ":13: vertex 1: value 'nan' is not finite"},
      {std::string(kPlyHeader) + "0 0 0 1\n1 zz 0 1\n0 1 0 1\n0 0 1 1\n1 1 1 1\n" + faces +
           "3 0 1 2\n",
       ":13: vertex 1: bad number 'zz'"},
      {std::string(kPlyHeader) + verts + faces + "2 0 1\n", ":21: face 4: 2 vertices"},
      {std::string(kPlyHeader) + verts + faces, ":21: unexpected end of file in face 4"},
      {std::string(kPlyHeader) + verts + faces + "3 0 1 2\n4 4 4\n", "data after the last"},
      {std::string(kPlyHeader) + verts + "3 0 2 1 9\n3 0 1 3\n3 0 3 2\n3 1 2 3\n3 0 1 2\n",
       ":17: face 0: 1 values beyond"},
      {"ply\nformat ascii 1.0\nelement vertex 4000000000\n", ":3: bad element count"},
      {"ply\nformat ascii 1.0\nelement vertex 300000\nproperty float x\nproperty float y\n"
       "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
       "0 0 0\n",
       "needs more data than the file holds"},
      {"ply\nformat ascii 2.0\n", ":2: expected 'format <type> 1.0'"},
      {"plx\n", ":1: not a PLY file"},
      {"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
       "property float z\nend_header\n0 0 0\n",
       "scene has no triangles"},
  };
  for (const Case& c : cases) {
    const std::string path = dir.Write("bad.ply", c.text);
    INFO("expect: ", c.fragment);
    ExpectError([&] { LoadPlyFile(path); }, {path, c.fragment});
  }
}

TEST_CASE("other formats go through assimp; its errors become rs::Error") {
  TempDir dir;
  const Scene off =
      LoadPlyFile(dir.Write("q.off", "OFF\n4 1 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n"));
  CHECK(off.triangles.size() == 2);  // quad triangulated
  const Scene stl =
      LoadScene(dir.Write("t.stl",
                          "solid t\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\n"
                          "vertex 0 1 0\nendloop\nendfacet\nendsolid t\n"));
  CHECK(stl.triangles.size() == 1);
  // Truncated body: assimp's own messages; an out-of-range index assimp would clamp (and
  // only log) is an error; NaN vertices are caught before assimp's post-processing.
  ExpectError([&] { LoadPlyFile(dir.Write("t.off", "OFF\n4 2 0\n0 0 0\n1 0 0\n")); },
              {"t.off", "number of verts"});
  ExpectError(
      [&] { LoadPlyFile(dir.Write("i.off", "OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 9\n")); },
      {"i.off", "out of range"});
  ExpectError(
      [&] { LoadPlyFile(dir.Write("n.off", "OFF\n3 1 0\n0 0 0\nnan 0 0\n0 1 0\n3 0 1 2\n")); },
      {"n.off", "vertex 1", "not finite"});
  ExpectError([&] { LoadPlyFile(dir.Write("x.xyz123", "hello")); }, {"x.xyz123"});
}

TEST_CASE("missing files name the path") {
  ExpectError([] { LoadObjFile("/nonexistent/dir/x.obj"); }, {"/nonexistent/dir/x.obj"});
  ExpectError([] { LoadPlyFile("/nonexistent/dir/x.ply"); }, {"/nonexistent/dir/x.ply"});
  ExpectError([] { LoadScene("/nonexistent/dir/x.obj"); }, {"/nonexistent/dir/x.obj"});
  ExpectError([] { LoadScene("no/such/scene.obj"); }, {"no/such/scene.obj", "RAYSTREAM_SCENES"});
}

TEST_CASE("search path: $RAYSTREAM_SCENES first, then the built-in directory") {
  TempDir a, b;
  b.Write("meshes/tri.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n");
  ScopedEnv env("RAYSTREAM_SCENES", a.path() + "::" + b.path());
  const std::vector<std::string> dirs = SceneSearchPath();
  REQUIRE(dirs.size() >= 2);
  CHECK(dirs[0] == a.path());
  CHECK(dirs[1] == b.path());  // empty entries skipped
  CHECK(FindSceneFile("meshes/tri.obj") == b.path() + "/meshes/tri.obj");
  // The same name in an earlier directory wins.
  a.Write("meshes/tri.obj", "v 0 0 0\nv 2 0 0\nv 0 2 0\nf 1 2 3\n");
  CHECK(FindSceneFile("meshes/tri.obj") == a.path() + "/meshes/tri.obj");
  const Scene s = LoadScene("meshes/tri.obj");
  glm::vec3 lo, hi;
  s.Bounds(lo, hi);
  CHECK(hi.x == 2.0f);
  const std::string what =
      ExpectError([] { FindSceneFile("meshes/nothere.obj"); },
                  {"meshes/nothere.obj", a.path(), b.path(), "RAYSTREAM_SCENES"});
  (void)what;
}

TEST_CASE("LoadScene: bare meshes get a default camera, material, light and orbit") {
  TempDir dir;
  const std::string path =
      dir.Write("box.obj", "v -1 0 -1\nv 1 0 -1\nv 1 2 1\nv -1 2 1\nf 1 2 3 4\n");
  const Scene s = LoadScene(path);
  CHECK(s.name == path);
  CHECK(s.source == path);
  REQUIRE(s.materials.size() == 1);
  REQUIRE(s.lights.size() == 1);
  CHECK(s.lights[0].position.y > 2.0f);  // above the mesh
  CHECK(s.camera.fov_y_deg == 60.0f);
  CHECK(s.camera.look_at.x == doctest::Approx(0.0f));
  CHECK(s.camera.look_at.y == doctest::Approx(1.0f));
  CHECK(s.camera.eye.z > 1.0f);  // outside the bounds, on the +z side
  CHECK(s.path.frames == 60);
  CHECK(s.path.keys.size() >= 2);
  // The orbit keeps the distance to the centre.
  for (const Camera& k : s.path.keys) {
    CHECK(glm::length(k.eye - k.look_at) ==
          doctest::Approx(glm::length(s.camera.eye - s.camera.look_at)).epsilon(1e-4));
  }
  CHECK(s.features.lights);
  CHECK(s.features.triangles == 2);
}

TEST_CASE("LoadScene: names and parameters") {
  CHECK(LoadScene("cornell").triangles.size() < 100);
  ExpectError([] { LoadScene("nonsense"); }, {"nonsense", "erw6", "bunny"});
  ExpectError([] { LoadScene(""); }, {"empty scene name"});
  ExpectError([] { LoadScene("amphitheater:0"); }, {"amphitheater:0", "1 to"});
  ExpectError([] { LoadScene("amphitheater:x"); }, {"amphitheater:x"});
  CHECK(!BuiltinSceneJson("bunny").empty());
  CHECK(BuiltinSceneJson("nope").empty());
  CHECK(BuiltinSceneFileNames().size() == 6);
}

constexpr const char* kSceneJson = R"json({
  // comments are allowed
  "name": "test scene",
  "materials": [
    {"name": "red", "diffuse": [0.8, 0.1, 0.1], "specular": 0.5, "shininess": 30},
    {"name": "mirror", "diffuse": 0.1, "reflectivity": 0.9},
    {"name": "glass", "transmission": 0.9, "ior": 1.5}
  ],
  "meshes": [
    {"file": "parts/quad.obj", "transform": {"scale": 2, "translate": [10, 0, 0]},
     "material": "red"},
    {"file": "parts/quad.obj", "group_materials": {"top*": "mirror"}},
    {"box": {"min": [0, 0, 0], "max": [1, 1, 1]}, "material": "glass"},
    {"sphere": {"center": [0, 5, 0], "radius": 1, "slices": 8, "stacks": 4}}
  ],
  "lights": [{"position": [0, 10, 0], "color": [1, 0.5, 0.25], "intensity": 2}],
  "camera": {"eye": [0, 3, 20], "look_at": [0, 1, 0], "fov": 45},
  "path": {"frames": 30, "keys": [{"eye": [0, 3, 20], "look_at": [0, 1, 0]},
                                  {"eye": [5, 3, 20], "look_at": [0, 1, 0]}]},
  "background": [0.1, 0.2, 0.3],
  "ambient": 0.05
})json";

TEST_CASE("scene file: meshes, transforms, material overrides, lights, camera, path") {
  TempDir dir;
  dir.Write("parts/quad.obj",
            "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\ng bottom\nf 1 2 3\ng top_part\nf 1 3 4\n");
  const std::string path = dir.Write("scene.json", kSceneJson);
  const Scene s = LoadScene(path);
  CHECK(s.name == path);
  CHECK(s.source == path);
  // 2 + 2 + 12 + 2 * 8 * 3 triangles.
  REQUIRE(s.triangles.size() == 2 + 2 + 12 + 48);
  auto mat = [&](size_t t) { return s.materials[s.material_ids[t]].name; };
  CHECK(mat(0) == "red");
  CHECK(mat(1) == "red");
  CHECK(mat(2) == "default");  // OBJ without MTL
  CHECK(mat(3) == "mirror");   // group "top_part" matched "top*"
  CHECK(mat(4) == "glass");
  CHECK(mat(16) == "default");  // sphere without material
  // Transform: scale 2 then translate 10 along x.
  CHECK(s.positions[s.triangles[0].y] == glm::vec3(12, 0, 0));
  REQUIRE(s.lights.size() == 1);
  CHECK(s.lights[0].color == glm::vec3(2, 1, 0.5f));
  CHECK(s.camera.fov_y_deg == 45.0f);
  CHECK(s.path.frames == 30);
  REQUIRE(s.path.keys.size() == 2);
  CHECK(s.path.keys[1].fov_y_deg == 45.0f);  // from the camera
  CHECK(s.background == glm::vec3(0.1f, 0.2f, 0.3f));
  CHECK(s.ambient == doctest::Approx(0.05f));
  CHECK(s.features.reflection);
  CHECK(s.features.transmission);
  CHECK(s.features.specular);
}

TEST_CASE("scene file: errors name the file and the JSON pointer or line:column") {
  TempDir dir;
  dir.Write("tri.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n");
  dir.Write("broken.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n");
  const std::string mesh = R"("meshes": [{"file": "tri.obj"}])";
  struct Case {
    std::string text;
    std::string fragment;
  };
  const Case cases[] = {
      {"{" + mesh + R"(, "lights": [{"position": [0,1,0]}, {"position": [0,1,0]},
                                   {"position": [0, 1]}]})",
       ": /lights/2/position: expected 3 numbers"},
      {"{" + mesh + R"(, "materials": [{"name": "a", "difuse": 1}]})",
       ": /materials/0/difuse: unknown key"},
      {"{" + mesh + R"(, "materials": [{"name": "a", "reflectivity": 2}]})",
       ": /materials/0/reflectivity: 2 outside [0, 1]"},
      {R"({"meshes": [{"file": "tri.obj", "material": "nope"}]})",
       ": /meshes/0/material: unknown material 'nope'"},
      {R"({"meshes": [{"file": "missing.obj"}]})", ": /meshes/0/file: scene file 'missing.obj'"},
      {R"({"meshes": [{"file": "broken.obj"}]})", "broken.obj:4: vertex index 4 out of range"},
      {R"({"meshes": []})", ": /meshes: expected a non-empty array"},
      {R"({"lights": []})", ": /meshes: missing"},
      {"{" + mesh + R"(, "camera": {"eye": [0,0,1], "look_at": [0,0,1]}})",
       ": /camera: eye equals look_at"},
      {"{" + mesh + R"(, "path": {"frames": 0}})", ": /path/frames: 0 outside"},
      {"{" + mesh + R"(, "ambient": "high"})", ": /ambient: expected a number"},
      {R"({"meshes": [{"box": {"min": [0,0,0], "max": [1,1,1]}, "file": "tri.obj"}]})",
       ": /meshes/0: needs exactly one of"},
      {"{\n  \"meshes\": [\n    {\"file\": \"tri.obj\",}\n  ]\n}", ":3:24: JSON syntax error"},
      {"{\"meshes\": [1e999]}", ":1:13: number 1e999 out of range"},
  };
  for (const Case& c : cases) {
    const std::string path = dir.Write("s.json", c.text);
    INFO("expect: ", c.fragment);
    ExpectError([&] { LoadScene(path); }, {path, c.fragment});
  }
}

TEST_CASE("scene file from memory: primitives only, no file access") {
  const Scene s = ParseSceneJsonText(R"({"meshes": [{"quad": [[0,0,0],[1,0,0],[1,1,0],[0,1,0]]}]})",
                                     "mem.json");
  CHECK(s.triangles.size() == 2);
  CHECK(s.lights.size() == 1);   // default light
  CHECK(s.camera.eye.z > 0.5f);  // default framing
  ExpectError([] { ParseSceneJsonText(R"({"meshes": [{"file": "x.obj"}]})", "mem.json"); },
              {"mem.json: /meshes/0/file: mesh files need file access"});
}

// Shared scenes: the built-in scene files load the meshes with their known counts; objects are
// viewed from outside, rooms from inside.
TEST_CASE("shared scenes load with the expected triangle counts") {
  struct Shared {
    const char* name;
    const char* file;
    size_t triangles;
    bool room;
  };
  const Shared shared[] = {{"bunny", "bunny/bun_zipper.ply", 69451, false},
                           {"teapot", "teapot/teapot.obj", 6320, false},
                           {"sponza", "sponza/sponza.obj", 66454, true},
                           {"office-graz", "office-graz/office-graz.obj", 26944, true},
                           {"conference", "conference/conference.obj", 331179, true},
                           {"sibenik", "sibenik/sibenik.obj", 75284, true}};
  for (const Shared& sh : shared) {
    INFO("scene: ", sh.name);
    if (!test::HaveSharedScene(sh.file)) continue;
    const Scene s = LoadScene(sh.name);
    CHECK(s.name == sh.name);
    CHECK(s.triangles.size() == sh.triangles);
    CHECK(s.features.triangles == sh.triangles);
    CHECK(s.lights.size() == 4);
    CHECK(s.path.frames >= 50);
    CHECK(s.path.keys.size() >= 4);
    CHECK(s.features.reflection);
    glm::vec3 lo, hi;
    s.Bounds(lo, hi);
    for (const Camera& c : s.path.keys) {
      const bool inside =
          glm::all(glm::greaterThan(c.eye, lo)) && glm::all(glm::lessThan(c.eye, hi));
      CHECK(inside == sh.room);
    }
  }
  if (test::HaveSharedScene("office-graz/office-graz.obj")) {
    const Scene office = LoadScene("office-graz");
    CHECK(office.camera.up == glm::vec3(0, 0, 1));  // Z up
    CHECK(office.materials.size() > 60);            // from the MTL
  }
  if (test::HaveSharedScene("bunny/bun_zipper.ply")) {
    const Scene bare = LoadScene("bunny/bun_zipper.ply");  // the file, default set-up
    CHECK(bare.triangles.size() == 69451);
    CHECK(bare.lights.size() == 1);
  }
}

}  // namespace
}  // namespace rs
