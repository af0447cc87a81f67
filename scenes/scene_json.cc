// The raystream scene file (JSON, nlohmann): meshes with transforms and material overrides,
// materials, point lights, camera and walk-through path. Every error names the file and the JSON
// pointer of the element ("bunny.json: /lights/2/position: expected 3 numbers"); syntax errors
// name line:column. Format (all keys optional except "meshes"; unknown keys are errors):
//
//   {"name": "bunny",
//    "materials": [{"name": "white", "diffuse": [r,g,b] | grey, "specular": [r,g,b] | grey,
//                   "shininess": 40, "reflectivity": 0..1, "transmission": 0..1, "ior": 1.5,
//                   "texture": "file.png"}],
//    "meshes": [{"file": "bunny/bun_zipper.ply",        // or "box": {"min": [..], "max": [..]},
//                                                      // "quad": [[..],[..],[..],[..]],
//                                                      // "sphere": {"center": [..], "radius": r,
//                                                      //            "slices": 32, "stacks": 16}
//                "transform": {"scale": s | [sx,sy,sz], "rotate": [rx,ry,rz] (degrees, X then
//                              Y then Z), "translate": [x,y,z]},   // applied scale, rotate, move
//                "material": "white",                 // every triangle of this mesh
//                "group_materials": {"floor*": "marble"},  // OBJ group/object names; "*" suffix
//                                                           // = prefix match, first match wins
//                "ks_reflects": true}],               // iRT convention: reflectivity = max(Ks)
//    "lights": [{"position": [..], "color": [..] | grey, "intensity": 1, "falloff": 0}],
//    "camera": {"eye": [..], "look_at": [..], "up": [0,1,0], "fov": 60},
//    "path": {"frames": 60, "keys": [{"eye": [..], "look_at": [..], "up": .., "fov": ..}]},
//    "background": [r,g,b], "ambient": 0.1}
//
// Without "camera" (or without its "eye") the view frames the bounds as for a bare mesh, using
// the camera's "up" and "fov" if given, and the default orbit path unless "path" is given;
// without "lights" one default light is placed. Relative files resolve against the scene file's
// directory, then the scene search path. Comments (// and /* */) are allowed.
#include <fmt/format.h>

#include <algorithm>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <cstdlib>
#include <glm/gtc/matrix_transform.hpp>
#include <initializer_list>
#include <map>
#include <nlohmann/json.hpp>
#include <optional>
#include <set>

#include "scenes/image_io.h"
#include "scenes/load.h"
#include "scenes/mesh_builder.h"
#include "scenes/scene_internal.h"

namespace rs {
namespace {

using detail::Fail;
using Json = nlohmann::ordered_json;

// What nlohmann does not check with a position: duplicate keys (it silently keeps one), numbers
// beyond a double's range (an exception without line:column) and integer literals beyond 64
// bits (silently a double). A lenient scan over the text reports them as
// "<origin>:<line>:<column>: ..."; anything it does not understand ends the scan, and the
// parser proper reports the syntax error.
class JsonPreScan {
 public:
  JsonPreScan(std::string_view text, const std::string& origin) : text_(text), origin_(origin) {}

  void Run() {
    while (pos_ < text_.size()) {
      const char c = text_[pos_];
      if (c == ' ' || c == '\t' || c == '\n' || c == '\r') {
        ++pos_;
      } else if (c == '/' && pos_ + 1 < text_.size() && text_[pos_ + 1] == '/') {
        const size_t end = text_.find('\n', pos_);
        pos_ = end == std::string_view::npos ? text_.size() : end;
      } else if (c == '/' && pos_ + 1 < text_.size() && text_[pos_ + 1] == '*') {
        const size_t end = text_.find("*/", pos_ + 2);
        if (end == std::string_view::npos) return;
        pos_ = end + 2;
      } else if (c == '{' || c == '[') {
        frames_.push_back(Frame{c == '{', true, {}});
        ++pos_;
      } else if (c == '}' || c == ']') {
        if (frames_.empty()) return;
        frames_.pop_back();
        ++pos_;
      } else if (c == ',') {
        if (!frames_.empty()) frames_.back().expect_key = frames_.back().object;
        ++pos_;
      } else if (c == ':') {
        ++pos_;
      } else if (c == '"') {
        if (!String()) return;
      } else if (c == '-' || (c >= '0' && c <= '9')) {
        Number();
      } else if (c >= 'a' && c <= 'z') {
        while (pos_ < text_.size() && text_[pos_] >= 'a' && text_[pos_] <= 'z') ++pos_;
      } else {
        return;
      }
    }
  }

 private:
  struct Frame {
    bool object;
    bool expect_key;
    std::set<std::string> keys;
  };

  template <typename... Args>
  [[noreturn]] void FailAt(size_t byte, fmt::format_string<Args...> format, Args&&... args) {
    const detail::TextPosition at = detail::PositionOfByte(text_, byte);
    Fail("{}:{}:{}: {}", origin_, at.line, at.column,
         fmt::format(format, std::forward<Args>(args)...));
  }

  bool String() {
    const size_t start = pos_++;
    bool escaped = false;
    while (pos_ < text_.size() && text_[pos_] != '"') {
      if (text_[pos_] == '\\') {
        escaped = true;
        ++pos_;
      }
      ++pos_;
    }
    if (pos_ >= text_.size()) return false;
    ++pos_;
    if (frames_.empty() || !frames_.back().object || !frames_.back().expect_key) return true;
    frames_.back().expect_key = false;
    const std::string_view raw = text_.substr(start, pos_ - start);
    std::string key(raw.substr(1, raw.size() - 2));
    if (escaped) {  // compare keys as the parser will see them
      try {
        key = Json::parse(raw).get<std::string>();
      } catch (const Json::exception&) {
        return false;  // the parser proper reports it
      }
    }
    if (!frames_.back().keys.insert(key).second) {
      FailAt(start, "duplicate key \"{}\" in this object (each key may appear once)",
             key.substr(0, 60));
    }
    return true;
  }

  void Number() {
    const size_t start = pos_;
    bool integer = true;
    while (pos_ < text_.size()) {
      const char c = text_[pos_];
      if (c == '.' || c == 'e' || c == 'E') {
        integer = false;
      } else if (!(c == '-' || c == '+' || (c >= '0' && c <= '9'))) {
        break;
      }
      ++pos_;
    }
    const std::string token(text_.substr(start, pos_ - start));
    if (integer) {
      const bool negative = token[0] == '-';
      const std::string_view digits = std::string_view(token).substr(negative ? 1 : 0);
      uint64_t v = 0;
      const auto r = std::from_chars(digits.data(), digits.data() + digits.size(), v);
      if (r.ec == std::errc::result_out_of_range ||
          (negative && r.ec == std::errc() && v > uint64_t{1} << 63)) {
        FailAt(start, "integer {} out of range (64 bits)", token.substr(0, 40));
      }
      return;
    }
    errno = 0;
    const double d = std::strtod(token.c_str(), nullptr);
    if (errno == ERANGE && std::isinf(d)) {
      FailAt(start, "number {} out of range (largest: 1.8e308)", token.substr(0, 40));
    }
  }

  std::string_view text_;
  const std::string& origin_;
  size_t pos_ = 0;
  std::vector<Frame> frames_;
};

class SceneFileParser {
 public:
  SceneFileParser(const std::string& origin, const std::string& base_dir, bool allow_files)
      : origin_(origin), base_dir_(base_dir), allow_files_(allow_files) {}

  Scene Parse(std::string_view text) {
    JsonPreScan(text, origin_).Run();
    Json root;
    try {
      root = Json::parse(text.begin(), text.end(), nullptr, /*allow_exceptions=*/true,
                         /*ignore_comments=*/true);
    } catch (const Json::parse_error& e) {
      const detail::TextPosition pos =
          detail::PositionOfByte(text, e.byte > 0 ? static_cast<size_t>(e.byte - 1) : 0);
      // Drop nlohmann's "[json.exception.parse_error.101] parse error at line 1, column 2: ".
      std::string what = e.what();
      if (const size_t colon = what.find(": "); colon != std::string::npos) {
        what = what.substr(colon + 2);
      }
      Fail("{}:{}:{}: JSON syntax error: {}", origin_, pos.line, pos.column, what);
    } catch (const Json::exception& e) {
      std::string what = e.what();  // without nlohmann's "[json.exception.<kind>.<id>] "
      if (what.rfind("[json.exception.", 0) == 0) {
        if (const size_t end = what.find("] "); end != std::string::npos) what.erase(0, end + 2);
      }
      Fail("{}: JSON error: {}", origin_, what);
    }
    return Build(root);
  }

 private:
  template <typename... Args>
  [[noreturn]] void At(const std::string& ptr, fmt::format_string<Args...> format, Args&&... args) {
    Fail("{}: {}: {}", origin_, ptr.empty() ? "/" : ptr,
         fmt::format(format, std::forward<Args>(args)...));
  }

  void Keys(const Json& obj, const std::string& ptr, std::initializer_list<std::string_view> keys) {
    if (!obj.is_object()) At(ptr, "expected an object");
    for (const auto& [key, value] : obj.items()) {
      if (std::find(keys.begin(), keys.end(), key) == keys.end()) {
        At(ptr + "/" + key, "unknown key (allowed: {})", fmt::join(keys, ", "));
      }
    }
  }

  float Number(const Json& j, const std::string& ptr) {
    if (!j.is_number()) At(ptr, "expected a number");
    const double d = j.get<double>();
    const float f = static_cast<float>(d);
    if (!std::isfinite(d) || !std::isfinite(f)) At(ptr, "number out of range");
    return f;
  }

  float Range(const Json& j, const std::string& ptr, float lo, float hi) {
    const float f = Number(j, ptr);
    if (!(f >= lo && f <= hi)) At(ptr, "{} outside [{}, {}]", f, lo, hi);
    return f;
  }

  int Integer(const Json& j, const std::string& ptr, int lo, int hi) {
    if (!j.is_number_integer()) At(ptr, "expected a whole number");
    if (j.is_number_unsigned()) {  // may be above INT64_MAX: compare and print it as it is
      const uint64_t u = j.get<uint64_t>();
      if (u > static_cast<uint64_t>(hi) || static_cast<int64_t>(u) < lo) {
        At(ptr, "{} outside [{}, {}]", u, lo, hi);
      }
      return static_cast<int>(u);
    }
    const int64_t v = j.get<int64_t>();
    if (v < lo || v > hi) At(ptr, "{} outside [{}, {}]", v, lo, hi);
    return static_cast<int>(v);
  }

  glm::vec3 Vec3(const Json& j, const std::string& ptr) {
    if (!j.is_array() || j.size() != 3) At(ptr, "expected 3 numbers");
    glm::vec3 v;
    for (int k = 0; k < 3; ++k) {
      const auto idx = static_cast<size_t>(k);
      if (!j[idx].is_number()) At(ptr, "expected 3 numbers");
      v[k] = Number(j[idx], ptr + "/" + std::to_string(k));
    }
    return v;
  }

  // A colour: [r, g, b] or one grey number; components >= 0.
  glm::vec3 Colour(const Json& j, const std::string& ptr) {
    const glm::vec3 c = j.is_number() ? glm::vec3(Number(j, ptr)) : Vec3(j, ptr);
    if (std::min({c.x, c.y, c.z}) < 0.0f) At(ptr, "colour components must be >= 0");
    return c;
  }

  std::string String(const Json& j, const std::string& ptr) {
    if (!j.is_string()) At(ptr, "expected a string");
    return j.get<std::string>();
  }

  const Json* Find(const Json& obj, const char* key) {
    const auto it = obj.find(key);
    return it == obj.end() ? nullptr : &*it;
  }

  Scene Build(const Json& root) {
    Keys(root, "",
         {"name", "materials", "meshes", "lights", "camera", "path", "background", "ambient"});
    scene_.source = origin_;
    scene_.name = origin_;
    if (const Json* j = Find(root, "name")) scene_.name = String(*j, "/name");
    if (const Json* j = Find(root, "materials")) Materials(*j);
    const Json* meshes = Find(root, "meshes");
    if (meshes == nullptr) At("/meshes", "missing: a scene needs at least one mesh");
    if (!meshes->is_array() || meshes->empty()) At("/meshes", "expected a non-empty array");
    for (size_t i = 0; i < meshes->size(); ++i) {
      Mesh((*meshes)[i], fmt::format("/meshes/{}", i));
    }
    if (scene_.triangles.empty()) Fail("{}: scene has no triangles", origin_);
    if (!detail::AnyPositiveArea(scene_)) {
      Fail("{}: every triangle has zero area ({} triangles); nothing to render", origin_,
           scene_.triangles.size());
    }
    if (const Json* j = Find(root, "background")) scene_.background = Colour(*j, "/background");
    if (const Json* j = Find(root, "ambient")) scene_.ambient = Range(*j, "/ambient", 0.0f, 1e6f);
    CameraAndLights(root);
    NormalizeScale(scene_);
    scene_.features = ComputeFeatures(scene_);
    ValidateScene(scene_);
    return std::move(scene_);
  }

  void Materials(const Json& list) {
    if (!list.is_array()) At("/materials", "expected an array");
    for (size_t i = 0; i < list.size(); ++i) {
      const std::string ptr = fmt::format("/materials/{}", i);
      const Json& m = list[i];
      Keys(m, ptr,
           {"name", "diffuse", "specular", "shininess", "reflectivity", "transmission", "ior",
            "texture"});
      Material mat;
      const Json* name = Find(m, "name");
      if (name == nullptr) At(ptr, "material needs a \"name\"");
      mat.name = String(*name, ptr + "/name");
      if (material_index_.count(mat.name)) At(ptr + "/name", "duplicate material '{}'", mat.name);
      if (const Json* j = Find(m, "diffuse")) mat.diffuse = Colour(*j, ptr + "/diffuse");
      if (const Json* j = Find(m, "specular")) mat.specular = Colour(*j, ptr + "/specular");
      if (const Json* j = Find(m, "shininess")) {
        mat.shininess = Range(*j, ptr + "/shininess", 0.0f, 1e5f);
      }
      if (const Json* j = Find(m, "reflectivity")) {
        mat.reflectivity = Range(*j, ptr + "/reflectivity", 0.0f, 1.0f);
      }
      if (const Json* j = Find(m, "transmission")) {
        mat.transmission = Range(*j, ptr + "/transmission", 0.0f, 1.0f);
      }
      if (const Json* j = Find(m, "ior")) mat.ior = Range(*j, ptr + "/ior", 0.01f, 100.0f);
      if (const Json* j = Find(m, "texture")) {
        const std::string file = String(*j, ptr + "/texture");
        if (!allow_files_) At(ptr + "/texture", "textures need file access");
        std::string path;
        try {
          path = detail::ResolveRelative(file, base_dir_);
          scene_.textures.push_back(ReadImage(path));
        } catch (const Error& e) {
          At(ptr + "/texture", "{}", e.what());
        }
        mat.texture = static_cast<int>(scene_.textures.size()) - 1;
      }
      material_index_[mat.name] = static_cast<uint32_t>(scene_.materials.size());
      scene_.materials.push_back(std::move(mat));
    }
  }

  uint32_t MaterialByName(const Json& j, const std::string& ptr) {
    const std::string name = String(j, ptr);
    const auto it = material_index_.find(name);
    if (it == material_index_.end()) At(ptr, "unknown material '{}'", name);
    return it->second;
  }

  uint32_t DefaultMaterial() {
    if (default_material_ == UINT32_MAX) {
      Material m;
      m.name = "default";
      default_material_ = static_cast<uint32_t>(scene_.materials.size());
      scene_.materials.push_back(m);
    }
    return default_material_;
  }

  glm::mat4 Transform(const Json& t, const std::string& ptr) {
    Keys(t, ptr, {"scale", "rotate", "translate"});
    glm::mat4 m(1.0f);
    if (const Json* j = Find(t, "translate")) m = glm::translate(m, Vec3(*j, ptr + "/translate"));
    if (const Json* j = Find(t, "rotate")) {
      const glm::vec3 deg = Vec3(*j, ptr + "/rotate");
      m = glm::rotate(m, glm::radians(deg.z), glm::vec3(0, 0, 1));
      m = glm::rotate(m, glm::radians(deg.y), glm::vec3(0, 1, 0));
      m = glm::rotate(m, glm::radians(deg.x), glm::vec3(1, 0, 0));
    }
    if (const Json* j = Find(t, "scale")) {
      const glm::vec3 s =
          j->is_number() ? glm::vec3(Number(*j, ptr + "/scale")) : Vec3(*j, ptr + "/scale");
      if (std::min({std::fabs(s.x), std::fabs(s.y), std::fabs(s.z)}) < 1e-12f) {
        At(ptr + "/scale", "scale must not be zero");
      }
      m = glm::scale(m, s);
    }
    return m;
  }

  static bool GlobMatch(const std::string& pattern, const std::string& name) {
    if (!pattern.empty() && pattern.back() == '*') {
      return name.compare(0, pattern.size() - 1, pattern, 0, pattern.size() - 1) == 0;
    }
    return pattern == name;
  }

  void Mesh(const Json& m, const std::string& ptr) {
    Keys(m, ptr,
         {"file", "box", "quad", "sphere", "transform", "material", "group_materials",
          "ks_reflects"});
    const int kinds = static_cast<int>(m.contains("file")) + static_cast<int>(m.contains("box")) +
                      static_cast<int>(m.contains("quad")) + static_cast<int>(m.contains("sphere"));
    if (kinds != 1) At(ptr, "needs exactly one of \"file\", \"box\", \"quad\", \"sphere\"");
    const glm::mat4 xf =
        m.contains("transform") ? Transform(m["transform"], ptr + "/transform") : glm::mat4(1.0f);
    std::optional<uint32_t> material;
    if (const Json* j = Find(m, "material")) material = MaterialByName(*j, ptr + "/material");
    Scene part;
    part.source = origin_;
    detail::MeshGroups groups;
    bool from_file = false;
    if (const Json* j = Find(m, "file")) {
      from_file = true;
      const std::string file = String(*j, ptr + "/file");
      if (!allow_files_) At(ptr + "/file", "mesh files need file access");
      detail::MeshLoadOptions options;
      if (const Json* k = Find(m, "ks_reflects")) {
        if (!k->is_boolean()) At(ptr + "/ks_reflects", "expected true or false");
        options.ks_reflects = k->get<bool>();
      }
      std::string path;
      try {
        path = detail::ResolveRelative(file, base_dir_);
      } catch (const Error& e) {
        At(ptr + "/file", "{}", e.what());
      }
      const std::string ext = detail::LowerExtension(path);
      if (ext == "json") At(ptr + "/file", "scene files cannot include scene files");
      // Loader errors name the mesh file and its line or element; add where it is used.
      try {
        if (ext == "obj") {
          detail::LoadObjFile(path, options, part, &groups);
        } else {
          detail::LoadAssimpFile(path, options, part, &groups);
        }
      } catch (const Error& e) {
        At(ptr + "/file", "{}", e.what());
      }
    } else {
      if (m.contains("group_materials") || m.contains("ks_reflects")) {
        At(ptr, "\"group_materials\" and \"ks_reflects\" apply to mesh files only");
      }
      detail::MeshBuilder builder(part, /*with_normals=*/false);
      part.materials.push_back(Material{});  // placeholder id 0, replaced below
      if (const Json* j = Find(m, "box")) {
        const std::string p = ptr + "/box";
        Keys(*j, p, {"min", "max"});
        if (!j->contains("min") || !j->contains("max")) At(p, "needs \"min\" and \"max\"");
        const glm::vec3 lo = Vec3((*j)["min"], p + "/min");
        const glm::vec3 hi = Vec3((*j)["max"], p + "/max");
        if (!(lo.x < hi.x && lo.y < hi.y && lo.z < hi.z)) At(p, "min must be below max");
        builder.Box(lo, hi, 0);
      } else if (const Json* q = Find(m, "quad")) {
        const std::string p = ptr + "/quad";
        if (!q->is_array() || q->size() != 4) At(p, "expected 4 corners");
        glm::vec3 c[4];
        for (size_t k = 0; k < 4; ++k) c[k] = Vec3((*q)[k], fmt::format("{}/{}", p, k));
        builder.Quad(c[0], c[1], c[2], c[3], 0);
        if (!detail::AnyPositiveArea(part)) At(p, "the 4 corners span no area");
      } else if (const Json* s = Find(m, "sphere")) {
        const std::string p = ptr + "/sphere";
        Keys(*s, p, {"center", "radius", "slices", "stacks"});
        if (!s->contains("center") || !s->contains("radius")) {
          At(p, "needs \"center\" and \"radius\"");
        }
        const glm::vec3 center = Vec3((*s)["center"], p + "/center");
        const float radius = Range((*s)["radius"], p + "/radius", 1e-15f, 1e18f);
        const int slices =
            s->contains("slices") ? Integer((*s)["slices"], p + "/slices", 3, 256) : 32;
        const int stacks =
            s->contains("stacks") ? Integer((*s)["stacks"], p + "/stacks", 2, 256) : 16;
        builder.Sphere(center, radius, slices, stacks, 0);
      }
      part.materials.clear();
      const uint32_t id = material ? *material : DefaultMaterial();
      for (uint32_t& mid : part.material_ids) mid = id;
    }
    ApplyTransform(part, xf);
    // Material overrides, by mesh or by group; ids are in scene_ numbering (offset below).
    std::vector<int64_t> override_of(part.triangles.size(), -1);
    if (from_file && material) std::fill(override_of.begin(), override_of.end(), *material);
    if (const Json* g = Find(m, "group_materials")) {
      const std::string p = ptr + "/group_materials";
      if (!g->is_object()) At(p, "expected an object of \"group pattern\": \"material\"");
      std::vector<std::pair<std::string, uint32_t>> rules;
      for (const auto& [pattern, value] : g->items()) {
        rules.emplace_back(pattern, MaterialByName(value, p + "/" + pattern));
      }
      std::vector<int64_t> group_material(groups.names.size(), -1);
      std::vector<char> rule_used(rules.size(), 0);
      for (size_t gi = 0; gi < groups.names.size(); ++gi) {
        for (size_t r = 0; r < rules.size(); ++r) {
          if (GlobMatch(rules[r].first, groups.names[gi])) {
            group_material[gi] = rules[r].second;
            rule_used[r] = 1;
            break;
          }
        }
      }
      for (size_t r = 0; r < rules.size(); ++r) {
        if (!rule_used[r]) {
          scene_.warnings.push_back(
              fmt::format("{}: {}/{}: matches no group in the mesh", origin_, p, rules[r].first));
        }
      }
      for (size_t t = 0; t < part.triangles.size() && t < groups.of_triangle.size(); ++t) {
        const int64_t gm = group_material[groups.of_triangle[t]];
        if (gm >= 0) override_of[t] = gm;
      }
    }
    if (!from_file) {
      // Primitive ids already point into scene_.materials: append without offset.
      for (size_t t = 0; t < part.material_ids.size(); ++t) {
        override_of[t] = part.material_ids[t];
      }
    }
    detail::AppendScene(scene_, std::move(part));
    const size_t first = scene_.triangles.size() - override_of.size();
    for (size_t t = 0; t < override_of.size(); ++t) {
      if (override_of[t] >= 0) {
        scene_.material_ids[first + t] = static_cast<uint32_t>(override_of[t]);
      }
    }
  }

  static void ApplyTransform(Scene& part, const glm::mat4& xf) {
    if (xf == glm::mat4(1.0f)) return;
    const glm::mat3 linear(xf);
    const glm::mat3 normal_matrix = glm::transpose(glm::inverse(linear));
    for (glm::vec3& p : part.positions) p = glm::vec3(xf * glm::vec4(p, 1.0f));
    for (glm::vec3& n : part.normals) n = glm::normalize(normal_matrix * n);
    if (glm::determinant(linear) < 0.0f) {
      for (glm::uvec3& t : part.triangles) std::swap(t.y, t.z);
    }
  }

  Camera ReadCamera(const Json& c, const std::string& ptr, const Camera& defaults, bool& has_eye) {
    Keys(c, ptr, {"eye", "look_at", "up", "fov"});
    Camera cam = defaults;
    has_eye = c.contains("eye");
    if (has_eye != c.contains("look_at")) At(ptr, "give both \"eye\" and \"look_at\" or neither");
    if (has_eye) {
      cam.eye = Vec3(c["eye"], ptr + "/eye");
      cam.look_at = Vec3(c["look_at"], ptr + "/look_at");
      if (cam.eye == cam.look_at) At(ptr, "eye equals look_at");
    }
    if (const Json* j = Find(c, "up")) {
      cam.up = Vec3(*j, ptr + "/up");
      if (glm::dot(cam.up, cam.up) <= 0.0f) At(ptr + "/up", "up must not be zero");
    }
    if (const Json* j = Find(c, "fov")) {
      cam.fov_y_deg = Number(*j, ptr + "/fov");
      if (!(cam.fov_y_deg > 0.0f && cam.fov_y_deg < 180.0f)) {
        At(ptr + "/fov", "{} outside (0, 180) degrees", cam.fov_y_deg);
      }
    }
    return cam;
  }

  void CameraAndLights(const Json& root) {
    Camera cam;
    bool has_eye = false;
    if (const Json* c = Find(root, "camera")) cam = ReadCamera(*c, "/camera", cam, has_eye);
    // Default framing for what is missing, with the requested up vector.
    Scene framed;
    framed.positions = scene_.positions;
    const float up_len = glm::length(cam.up);
    detail::SetDefaultView(framed, up_len > 0.0f ? cam.up / up_len : glm::vec3(0, 1, 0));
    if (!has_eye) {
      const float fov = cam.fov_y_deg;
      scene_.camera = framed.camera;
      scene_.camera.up = cam.up;
      if (fov != framed.camera.fov_y_deg) {
        // Re-frame for the requested field of view: same direction, adjusted distance.
        const glm::vec3 dir = framed.camera.eye - framed.camera.look_at;
        const float scale = std::sin(glm::radians(0.5f * framed.camera.fov_y_deg)) /
                            std::sin(glm::radians(0.5f * fov));
        scene_.camera.eye = framed.camera.look_at + dir * scale;
        scene_.camera.fov_y_deg = fov;
      }
    } else {
      scene_.camera = cam;
    }
    if (const Json* p = Find(root, "path")) {
      Keys(*p, "/path", {"frames", "keys"});
      scene_.path.frames =
          p->contains("frames") ? Integer((*p)["frames"], "/path/frames", 1, 10000000) : 60;
      if (const Json* keys = Find(*p, "keys")) {
        if (!keys->is_array()) At("/path/keys", "expected an array");
        for (size_t k = 0; k < keys->size(); ++k) {
          const std::string kp = fmt::format("/path/keys/{}", k);
          bool key_eye = false;
          const Camera key = ReadCamera((*keys)[k], kp, scene_.camera, key_eye);
          if (!key_eye) At(kp, "a path key needs \"eye\" and \"look_at\"");
          scene_.path.keys.push_back(key);
        }
      }
    } else if (!has_eye) {
      scene_.path = framed.path;
      for (Camera& key : scene_.path.keys) {
        const glm::vec3 offset = key.eye - framed.camera.look_at;
        const glm::vec3 base = framed.camera.eye - framed.camera.look_at;
        const float scale =
            glm::length(scene_.camera.eye - scene_.camera.look_at) / glm::length(base);
        key.eye = framed.camera.look_at + offset * scale;
        key.up = scene_.camera.up;
        key.fov_y_deg = scene_.camera.fov_y_deg;
      }
    }
    if (const Json* l = Find(root, "lights")) {
      if (!l->is_array()) At("/lights", "expected an array");
      for (size_t i = 0; i < l->size(); ++i) {
        const std::string ptr = fmt::format("/lights/{}", i);
        const Json& lj = (*l)[i];
        Keys(lj, ptr, {"position", "color", "intensity", "falloff"});
        PointLight light;
        if (!lj.contains("position")) At(ptr, "light needs a \"position\"");
        light.position = Vec3(lj["position"], ptr + "/position");
        if (const Json* j = Find(lj, "color")) light.color = Colour(*j, ptr + "/color");
        if (const Json* j = Find(lj, "intensity")) {
          light.color *= Range(*j, ptr + "/intensity", 0.0f, 1e12f);
        }
        if (const Json* j = Find(lj, "falloff")) {
          light.falloff = Range(*j, ptr + "/falloff", 0.0f, 1e12f);
        }
        scene_.lights.push_back(light);
      }
    } else {
      scene_.lights = framed.lights;
    }
  }

  const std::string& origin_;
  const std::string& base_dir_;
  bool allow_files_;
  Scene scene_;
  std::map<std::string, uint32_t> material_index_;
  uint32_t default_material_ = UINT32_MAX;
};

}  // namespace

Scene LoadSceneJson(std::string_view json_text, const std::string& origin,
                    const std::string& base_dir) {
  return SceneFileParser(origin, base_dir, /*allow_files=*/true).Parse(json_text);
}

Scene ParseSceneJsonText(std::string_view json_text, const std::string& origin) {
  const std::string no_dir;
  return SceneFileParser(origin, no_dir, /*allow_files=*/false).Parse(json_text);
}

}  // namespace rs
