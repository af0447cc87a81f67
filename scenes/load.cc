// Finding scene files (search path) and LoadScene's dispatch: procedural names, built-in scene
// files, then user files by extension. Also the small file and mesh helpers the loaders share.
#include "scenes/load.h"

#include <fcntl.h>
#include <fmt/format.h>
#include <fmt/ranges.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <numbers>
#include <sstream>
#include <system_error>

#include "scenes/scene_internal.h"

#ifndef RS_DEFAULT_SCENES_DIR
#define RS_DEFAULT_SCENES_DIR ""
#endif

namespace rs {
namespace fs = std::filesystem;

namespace detail {

TextPosition PositionOfByte(std::string_view text, size_t byte) {
  TextPosition pos;
  const size_t end = std::min(byte, text.size());
  for (size_t i = 0; i < end; ++i) {
    if (text[i] == '\n') {
      ++pos.line;
      pos.column = 1;
    } else {
      ++pos.column;
    }
  }
  return pos;
}

const char* FileTypeName(unsigned mode) {
  switch (mode & S_IFMT) {
    case S_IFREG:
      return "a regular file";
    case S_IFDIR:
      return "a directory";
    case S_IFIFO:
      return "a named pipe (FIFO)";
    case S_IFCHR:
      return "a character device";
    case S_IFBLK:
      return "a block device";
    case S_IFSOCK:
      return "a socket";
    default:
      return "not a regular file";
  }
}

uint64_t RegularFileSize(const std::string& path, std::string_view what) {
  struct stat st;
  if (::stat(path.c_str(), &st) != 0) {
    const int err = errno;
    if (err == ENOENT) Fail("{}: no such file", path);
    Fail("{}: cannot open {} file: {}", path, what, std::strerror(err));
  }
  if (!S_ISREG(st.st_mode)) {
    Fail("{}: is {}, not a {} file", path, FileTypeName(st.st_mode), what);
  }
  return static_cast<uint64_t>(st.st_size);
}

std::string ReadFileText(const std::string& path, std::string_view what) {
  RegularFileSize(path, what);  // a FIFO would block open(), /dev/zero never end
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC | O_NONBLOCK);
  if (fd < 0) Fail("{}: cannot open {} file: {}", path, what, std::strerror(errno));
  struct stat st;
  if (::fstat(fd, &st) != 0 || !S_ISREG(st.st_mode)) {  // replaced since the check
    ::close(fd);
    Fail("{}: is not a regular file", path);
  }
  std::string text;
  try {
    text.reserve(static_cast<size_t>(st.st_size));
    char buf[1 << 16];
    for (;;) {
      const ssize_t n = ::read(fd, buf, sizeof(buf));
      if (n == 0) break;
      if (n < 0) {
        if (errno == EINTR) continue;
        const int err = errno;
        ::close(fd);
        Fail("{}: read error: {}", path, std::strerror(err));
      }
      text.append(buf, static_cast<size_t>(n));
    }
  } catch (const std::bad_alloc&) {
    ::close(fd);
    Fail("{}: out of memory reading {} bytes", path, static_cast<uint64_t>(st.st_size));
  }
  ::close(fd);
  return text;
}

std::string LowerExtension(std::string_view path) {
  std::string ext = fs::path(path).extension().string();
  if (!ext.empty() && ext[0] == '.') ext.erase(0, 1);
  std::transform(ext.begin(), ext.end(), ext.begin(),
                 [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  return ext;
}

std::string DirectoryOf(std::string_view path) { return fs::path(path).parent_path().string(); }

std::string JoinPath(std::string_view dir, std::string_view rel) {
  if (dir.empty() || fs::path(rel).is_absolute()) return std::string(rel);
  return (fs::path(dir) / fs::path(rel)).string();
}

bool IsRegularFile(const std::string& path) {
  std::error_code ec;
  return fs::is_regular_file(path, ec);
}

namespace {

// True if `path` is a regular file, false if nothing is there; anything else that exists (a
// directory, FIFO, device) is an error saying what it is, not a misleading "not found".
bool ExistingRegularFile(const std::string& path) {
  struct stat st;
  if (::stat(path.c_str(), &st) != 0) return false;
  if (!S_ISREG(st.st_mode)) Fail("{}: is {}, not a regular file", path, FileTypeName(st.st_mode));
  return true;
}

bool UsedAsGiven(const fs::path& p) {
  if (p.is_absolute()) return true;
  const std::string s = p.generic_string();
  return s.rfind("./", 0) == 0 || s.rfind("../", 0) == 0;
}

// Looks `file` up in `dirs` (then the search path); throws listing every place tried.
std::string FindIn(std::string_view file, const std::vector<std::string>& first_dirs) {
  if (file.empty()) Fail("empty scene file name");
  const fs::path p(file);
  if (p.is_absolute()) {
    if (ExistingRegularFile(p.string())) return p.string();
    Fail("scene file '{}' not found", file);
  }
  std::vector<std::string> tried;
  auto attempt = [&](const std::string& dir) -> bool {
    const std::string candidate = JoinPath(dir, file);
    tried.push_back(candidate);
    return ExistingRegularFile(candidate);
  };
  for (const std::string& dir : first_dirs) {
    if (!dir.empty() && attempt(dir)) return tried.back();
  }
  if (UsedAsGiven(p)) {  // "./x", "../x": relative to the working directory only
    if (attempt("")) return tried.back();
    Fail("scene file '{}' not found; tried {}", file, fmt::join(tried, ", "));
  }
  // The working directory, so `raystream render --scene mine.obj` finds a local file.
  if (attempt("")) return tried.back();
  const std::vector<std::string> search = SceneSearchPath();
  for (const std::string& dir : search) {
    if (attempt(dir)) return tried.back();
  }
  std::string hint =
      search.empty()
          ? "the scene search path is empty: RAYSTREAM_SCENES is not set and the built-in "
            "default directory '" RS_DEFAULT_SCENES_DIR "' does not exist"
          : fmt::format("scene search path: {}", fmt::join(search, ":"));
  Fail(
      "scene file '{}' not found; tried {}; {} (set RAYSTREAM_SCENES to a colon-separated "
      "list of directories holding the scenes)",
      file, fmt::join(tried, ", "), hint);
}

}  // namespace

std::string ResolveRelative(std::string_view rel, const std::string& base_dir) {
  return FindIn(rel, {base_dir});
}

void AppendScene(Scene& scene, Scene&& part) {
  const bool scene_empty = scene.positions.empty();
  const size_t offset_v = scene.positions.size();
  const size_t offset_m = scene.materials.size();
  const int offset_t = static_cast<int>(scene.textures.size());
  // UVs: kept if either side has them; the side without gets (0, 0).
  if (!scene.uvs.empty() || !part.uvs.empty()) {
    scene.uvs.resize(offset_v, glm::vec2(0.0f));
    if (part.uvs.empty()) {
      scene.uvs.resize(offset_v + part.positions.size(), glm::vec2(0.0f));
    } else {
      scene.uvs.insert(scene.uvs.end(), part.uvs.begin(), part.uvs.end());
    }
  }
  // Normals: smooth shading needs one per vertex everywhere, so a flat part makes all flat.
  const bool keep_normals =
      scene_empty ? !part.normals.empty() : (!scene.normals.empty() && !part.normals.empty());
  if (keep_normals) {
    scene.normals.insert(scene.normals.end(), part.normals.begin(), part.normals.end());
  } else {
    scene.normals.clear();
  }
  scene.positions.insert(scene.positions.end(), part.positions.begin(), part.positions.end());
  scene.triangles.reserve(scene.triangles.size() + part.triangles.size());
  const glm::uvec3 vo(static_cast<uint32_t>(offset_v));
  for (const glm::uvec3& t : part.triangles) scene.triangles.push_back(t + vo);
  scene.material_ids.reserve(scene.material_ids.size() + part.material_ids.size());
  for (const uint32_t m : part.material_ids) {
    scene.material_ids.push_back(m + static_cast<uint32_t>(offset_m));
  }
  for (Material& m : part.materials) {
    if (m.texture >= 0) m.texture += offset_t;
    scene.materials.push_back(std::move(m));
  }
  for (Texture& t : part.textures) scene.textures.push_back(std::move(t));
  scene.lights.insert(scene.lights.end(), part.lights.begin(), part.lights.end());
  scene.warnings.insert(scene.warnings.end(), part.warnings.begin(), part.warnings.end());
}

bool AnyPositiveArea(const Scene& scene) {
  const size_t nv = scene.positions.size();
  for (const glm::uvec3& t : scene.triangles) {
    if (t.x >= nv || t.y >= nv || t.z >= nv) continue;  // validated elsewhere
    const glm::vec3 n = glm::cross(scene.positions[t.y] - scene.positions[t.x],
                                   scene.positions[t.z] - scene.positions[t.x]);
    // Components, not the squared length: that underflows for tiny (but valid) triangles.
    if ((n.x != 0.0f || n.y != 0.0f || n.z != 0.0f) && std::isfinite(n.x + n.y + n.z)) {
      return true;
    }
  }
  return false;
}

size_t RepairNormals(Scene& scene) {
  if (scene.normals.empty()) return 0;
  std::vector<char> bad(scene.normals.size(), 0);
  size_t num_bad = 0;
  for (size_t i = 0; i < scene.normals.size(); ++i) {
    const float len = glm::length(scene.normals[i]);
    if (len > 0.0f && std::isfinite(len)) {
      scene.normals[i] /= len;
    } else {
      bad[i] = 1;
      ++num_bad;
    }
  }
  if (num_bad == 0) return 0;
  for (const glm::uvec3& t : scene.triangles) {
    if (t.x >= bad.size() || t.y >= bad.size() || t.z >= bad.size()) continue;  // validated later
    const glm::vec3 n = glm::cross(scene.positions[t.y] - scene.positions[t.x],
                                   scene.positions[t.z] - scene.positions[t.x]);
    const float len = glm::length(n);
    if (!(len > 0.0f) || !std::isfinite(len)) continue;
    for (int k = 0; k < 3; ++k) {
      if (bad[t[k]]) {
        scene.normals[t[k]] = n / len;
        bad[t[k]] = 0;
      }
    }
  }
  for (size_t i = 0; i < bad.size(); ++i) {
    if (bad[i]) scene.normals[i] = glm::vec3(0, 1, 0);
  }
  return num_bad;
}

void SetDefaultView(Scene& scene, const glm::vec3& up_in) {
  glm::vec3 lo, hi;
  scene.Bounds(lo, hi);
  const glm::vec3 center = 0.5f * (lo + hi);
  float radius = 0.5f * glm::length(hi - lo);
  if (!(radius > 0.0f)) radius = 1.0f;
  const glm::vec3 up = glm::normalize(up_in);
  // "Front": +z for a Y-up mesh, -y for a Z-up mesh (both face the camera of a right-handed
  // view with that up vector).
  const glm::vec3 front = std::fabs(up.y) > 0.5f ? glm::vec3(0, 0, 1) : glm::vec3(0, -1, 0);
  Camera cam;
  cam.fov_y_deg = 60.0f;
  cam.up = up;
  cam.look_at = center;
  const float half_fov = 0.5f * cam.fov_y_deg * std::numbers::pi_v<float> / 180.0f;
  const float distance = 1.1f * radius / std::sin(half_fov);
  const glm::vec3 view_dir = glm::normalize(front + 0.25f * up);
  cam.eye = center + distance * view_dir;
  scene.camera = cam;
  PointLight light;
  light.position = center + up * (2.0f * radius) + front * radius;
  light.color = glm::vec3(1.0f);
  scene.lights.assign(1, light);
  // Orbit 90 degrees around the up axis through the centre, one key per 15 degrees.
  scene.path.keys.clear();
  scene.path.frames = 60;
  const glm::vec3 offset = cam.eye - center;
  for (int k = 0; k <= 6; ++k) {
    const float a = static_cast<float>(k) * (std::numbers::pi_v<float> / 12.0f);
    // Rodrigues rotation of `offset` about `up`.
    const glm::vec3 rotated = offset * std::cos(a) + glm::cross(up, offset) * std::sin(a) +
                              up * glm::dot(up, offset) * (1.0f - std::cos(a));
    Camera key = cam;
    key.eye = center + rotated;
    scene.path.keys.push_back(key);
  }
}

void FinishScene(Scene& scene) {
  const std::string& label = scene.source.empty() ? scene.name : scene.source;
  if (scene.triangles.empty()) Fail("{}: scene has no triangles", label);
  NormalizeScale(scene);
  if (!AnyPositiveArea(scene)) {
    Fail("{}: every triangle has zero area ({} triangles); nothing to render", label,
         scene.triangles.size());
  }
  scene.features = ComputeFeatures(scene);
  ValidateScene(scene);
}

}  // namespace detail

std::vector<std::string> SceneSearchPath() {
  std::vector<std::string> dirs;
  if (const char* env = std::getenv("RAYSTREAM_SCENES")) {
    std::string_view rest(env);
    while (!rest.empty()) {
      const size_t colon = rest.find(':');
      const std::string_view dir = rest.substr(0, colon);
      if (!dir.empty()) dirs.emplace_back(dir);
      if (colon == std::string_view::npos) break;
      rest.remove_prefix(colon + 1);
    }
  }
  const std::string builtin = RS_DEFAULT_SCENES_DIR;
  std::error_code ec;
  if (!builtin.empty() && fs::is_directory(builtin, ec)) dirs.push_back(builtin);
  return dirs;
}

std::string FindSceneFile(std::string_view file) { return detail::FindIn(file, {}); }

std::vector<std::string> ProceduralSceneNames() {
  // "amphitheater" is amphitheater:1; "amphitheater:N" gives N copies.
  return {"erw6", "spherebox", "amphitheater", "cornell", "farsphere", "nearsphere"};
}

std::vector<std::string> BuiltinSceneFileNames() {
  return {"bunny", "teapot", "sponza", "office-graz", "conference", "sibenik"};
}

void LoadObj(const std::string& path, Scene& scene) {
  detail::LoadObjFile(path, {}, scene, nullptr);
}

void LoadWithAssimp(const std::string& path, Scene& scene) {
  detail::LoadAssimpFile(path, {}, scene, nullptr);
}

void ParseObjText(std::string_view obj_text, const std::string& origin, Scene& scene) {
  detail::ParseObj(obj_text, origin, "", {}, scene, nullptr);
}

std::vector<Material> ParseMtlText(std::string_view mtl_text, const std::string& origin) {
  std::vector<Material> materials;
  detail::ParseMtl(mtl_text, origin, materials);
  return materials;
}

void ParsePlyText(std::string_view ply_text, const std::string& origin, Scene& scene) {
  detail::LoadAssimpMemory(ply_text, origin, "ply", {}, scene, nullptr);
}

Scene LoadScene(std::string_view name_or_path) {
  using detail::Fail;
  const std::string name(name_or_path);
  if (name.empty()) {
    Fail("empty scene name (procedural: {}; built-in: {}; or a .json/.obj/.ply file)",
         fmt::join(ProceduralSceneNames(), ", "), fmt::join(BuiltinSceneFileNames(), ", "));
  }
  Scene scene;
  if (detail::MakeProceduralScene(name, scene)) {
    scene.name = name;
    scene.source = "procedural";
    detail::FinishScene(scene);
  } else if (const std::string_view json = BuiltinSceneJson(name); !json.empty()) {
    scene = LoadSceneJson(json, fmt::format("built-in scene '{}'", name), "");
    scene.name = name;
  } else {
    const std::string ext = detail::LowerExtension(name);
    struct stat st;
    if (ext.empty() && ::stat(name.c_str(), &st) == 0 && !S_ISREG(st.st_mode)) {
      Fail("{}: is {}, not a scene file", name, detail::FileTypeName(st.st_mode));
    }
    if (ext.empty()) {
      Fail(
          "unknown scene '{}': not a procedural scene ({}), not a built-in scene file ({}), and "
          "no file extension (.json, .obj, .ply, ...)",
          name, fmt::join(ProceduralSceneNames(), ", "), fmt::join(BuiltinSceneFileNames(), ", "));
    }
    const std::string path = FindSceneFile(name);
    if (ext == "json") {
      scene = LoadSceneJson(detail::ReadFileText(path), path, detail::DirectoryOf(path));
    } else {
      scene.source = path;
      if (ext == "obj") {
        LoadObj(path, scene);
      } else {
        LoadWithAssimp(path, scene);
      }
      detail::SetDefaultView(scene);
      detail::FinishScene(scene);
    }
    scene.name = name;
  }
  for (const std::string& w : scene.warnings) fmt::print(stderr, "raystream: warning: {}\n", w);
  return scene;
}

}  // namespace rs
