// Wavefront OBJ + MTL loading with tinyobjloader, behind a strict line-by-line pre-scan.
// tinyobjloader is lenient (NaN and garbage become 0, out-of-range indices are only a warning
// naming the last line), so we scan first and report the exact line; then tinyobj triangulates
// faces and reads the MTL. Positions come from our own exact parse (std::from_chars).
//
// MTL conventions (documented for scene authors):
//   Kd -> diffuse (clamped to [0, 1]); Ks -> specular; Ns -> shininess (no Ns: no highlight);
//   illum 3, 5, 8 -> mirror reflection with reflectivity max(Ks) (or 1 if Ks is 0);
//   d < 1 (or Tr > 0) -> transmission 1 - d; illum 4, 6, 7, 9 with d = 1 -> transmission max(Tf);
//   Ni -> ior (default 1.5); Ke > 0 with black Kd -> diffuse = Ke normalised (lamps show white);
//   raystream extensions: "rs_reflectivity w" and "rs_transmission w" (0..1) override the above;
//   map_Kd -> diffuse texture (read with OpenImageIO; missing file -> warning, untextured).
// A missing .mtl gives the default material and a warning.
#include <fmt/format.h>
#include <tiny_obj_loader.h>

#include <algorithm>
#include <charconv>
#include <cmath>
#include <cstdlib>
#include <map>
#include <sstream>
#include <unordered_map>

#include "scenes/image_io.h"
#include "scenes/load.h"
#include "scenes/scene_internal.h"

namespace rs::detail {
namespace {

bool IsBlank(char c) { return c == ' ' || c == '\t'; }

// Splits `line` into whitespace-separated tokens.
void Tokenize(std::string_view line, std::vector<std::string_view>& tokens) {
  tokens.clear();
  size_t i = 0;
  while (i < line.size()) {
    while (i < line.size() && IsBlank(line[i])) ++i;
    const size_t start = i;
    while (i < line.size() && !IsBlank(line[i])) ++i;
    if (i > start) tokens.push_back(line.substr(start, i - start));
  }
}

// Parses a whole token as a float (leading '+' allowed); false if it is not a number.
bool ParseFloat(std::string_view token, float& out) {
  if (token.size() > 1 && token[0] == '+' && token[1] != '-') token.remove_prefix(1);
  const char* end = token.data() + token.size();
  const auto result = std::from_chars(token.data(), end, out);
  if (result.ec == std::errc::result_out_of_range && result.ptr == end) {
    // Tiny values underflow to 0 (fine); huge ones become +-inf and are reported.
    const double d = std::strtod(std::string(token).c_str(), nullptr);
    out = std::fabs(d) < 1.0 ? 0.0f : static_cast<float>(d > 0 ? HUGE_VAL : -HUGE_VAL);
    return true;
  }
  return result.ec == std::errc() && result.ptr == end;
}

bool ParseInt(std::string_view token, int64_t& out) {
  if (token.size() > 1 && token[0] == '+' && token[1] != '-') token.remove_prefix(1);
  const char* end = token.data() + token.size();
  const auto result = std::from_chars(token.data(), end, out);
  return result.ec == std::errc() && result.ptr == end;
}

// What the pre-scan learned: exact positions, uvs and normals in file order.
struct ObjScan {
  std::vector<glm::vec3> positions;
  std::vector<glm::vec2> texcoords;
  std::vector<glm::vec3> normals;
  size_t expected_triangles = 0;
};

// Statements we accept and leave to tinyobjloader or ignore (free-form geometry, display
// attributes); anything else is reported as garbage with its line.
bool IsKnownStatement(std::string_view k) {
  static constexpr std::string_view kKnown[] = {
      "usemtl", "mtllib",   "o",        "g",          "s",         "vp",    "cstype",
      "deg",    "bmat",     "step",     "curv",       "curv2",     "surf",  "parm",
      "trim",   "hole",     "scrv",     "sp",         "end",       "con",   "mg",
      "lod",    "usemap",   "maplib",   "shadow_obj", "trace_obj", "ctech", "stech",
      "bevel",  "c_interp", "d_interp", "call",       "csh"};
  return std::find(std::begin(kKnown), std::end(kKnown), k) != std::end(kKnown);
}

class ObjScanner {
 public:
  ObjScanner(std::string_view text, const std::string& origin) : text_(text), origin_(origin) {}

  ObjScan Run() {
    size_t pos = 0;
    std::vector<std::string_view> tokens;
    while (pos < text_.size()) {
      // Line terminators as tinyobjloader reads them: "\n", "\r\n" or a lone "\r".
      size_t end = pos;
      while (end < text_.size() && text_[end] != '\n' && text_[end] != '\r') ++end;
      ++line_;
      ScanLine(text_.substr(pos, end - pos), tokens);
      pos = end + 1;
      if (end + 1 < text_.size() && text_[end] == '\r' && text_[end + 1] == '\n') ++pos;
    }
    // Positive indices may point forward; check them against the final counts.
    CheckForward(max_v_, max_v_line_, scan_.positions.size(), "vertex", "vertices");
    CheckForward(max_vt_, max_vt_line_, scan_.texcoords.size(), "texture coordinate",
                 "texture coordinates");
    CheckForward(max_vn_, max_vn_line_, scan_.normals.size(), "normal", "normals");
    return std::move(scan_);
  }

 private:
  template <typename... Args>
  [[noreturn]] void LineFail(fmt::format_string<Args...> format, Args&&... args) {
    Fail("{}:{}: {}", origin_, line_, fmt::format(format, std::forward<Args>(args)...));
  }

  void CheckForward(int64_t max_index, size_t line, size_t count, const char* what,
                    const char* plural) {
    if (max_index > static_cast<int64_t>(count)) {
      Fail("{}:{}: {} index {} out of range ({} {} in the file)", origin_, line, what, max_index,
           count, plural);
    }
  }

  void ScanLine(std::string_view line, std::vector<std::string_view>& tokens) {
    for (const char c : line) {
      const auto u = static_cast<unsigned char>(c);
      if ((u < 0x20 && c != '\t') || u == 0x7f) {
        LineFail("unexpected control character 0x{:02x} (binary data?)", static_cast<int>(u));
      }
    }
    Tokenize(line, tokens);
    if (tokens.empty() || tokens[0][0] == '#') return;
    const std::string_view key = tokens[0];
    if (key == "v") {
      if (tokens.size() < 4 || tokens.size() > 8) {
        LineFail("vertex needs 3 coordinates (optionally w or r g b), got {} values",
                 tokens.size() - 1);
      }
      glm::vec3 p;
      for (int k = 0; k < 3; ++k) p[k] = Number(tokens[static_cast<size_t>(k) + 1], "vertex");
      for (size_t k = 4; k < tokens.size(); ++k) Number(tokens[k], "vertex");
      if (std::max({std::fabs(p.x), std::fabs(p.y), std::fabs(p.z)}) > kMaxCoordinate) {
        LineFail("vertex {} coordinate too large ({}, {}, {}); limit {}",
                 scan_.positions.size() + 1, p.x, p.y, p.z, kMaxCoordinate);
      }
      scan_.positions.push_back(p);
    } else if (key == "vt") {
      if (tokens.size() < 2 || tokens.size() > 4) {
        LineFail("texture coordinate needs 1 to 3 values, got {}", tokens.size() - 1);
      }
      glm::vec2 uv(0.0f);
      for (size_t k = 1; k < tokens.size(); ++k) {
        const float x = Number(tokens[k], "texture coordinate");
        if (k <= 2) uv[static_cast<int>(k) - 1] = x;
      }
      scan_.texcoords.push_back(uv);
    } else if (key == "vn") {
      if (tokens.size() != 4) LineFail("normal needs 3 values, got {}", tokens.size() - 1);
      glm::vec3 n;
      for (int k = 0; k < 3; ++k) n[k] = Number(tokens[static_cast<size_t>(k) + 1], "normal");
      scan_.normals.push_back(n);
    } else if (key == "f" || key == "l" || key == "p") {
      const size_t corners = tokens.size() - 1;
      const size_t need = key == "f" ? 3 : key == "l" ? 2 : 1;
      if (corners < need) {
        LineFail("'{}' statement has {} vertices (need at least {})", key, corners, need);
      }
      for (size_t k = 1; k < tokens.size(); ++k) Corner(tokens[k]);
      if (key == "f") scan_.expected_triangles += corners - 2;
    } else if (!IsKnownStatement(key)) {
      LineFail("unknown statement '{}'", key.substr(0, 40));
    }
  }

  float Number(std::string_view token, const char* what) {
    float x = 0.0f;
    if (!ParseFloat(token, x)) LineFail("bad number '{}' in {}", token.substr(0, 40), what);
    if (!std::isfinite(x)) {
      LineFail("{} value '{}' is not finite", what, token.substr(0, 40));
    }
    return x;
  }

  // One face corner: "v", "v/vt", "v//vn" or "v/vt/vn".
  void Corner(std::string_view token) {
    std::string_view parts[3];
    size_t n = 0;
    size_t start = 0;
    for (size_t i = 0; i <= token.size(); ++i) {
      if (i == token.size() || token[i] == '/') {
        if (n == 3) LineFail("bad face vertex '{}' (expected v, v/vt, v//vn or v/vt/vn)", token);
        parts[n++] = token.substr(start, i - start);
        start = i + 1;
      }
    }
    // Empty parts: only the uv of "v//vn" may be missing.
    if (parts[0].empty() || (n == 2 && parts[1].empty()) || (n == 3 && parts[2].empty())) {
      LineFail("bad face vertex '{}' (expected v, v/vt, v//vn or v/vt/vn)", token.substr(0, 40));
    }
    Index(parts[0], scan_.positions.size(), "vertex", max_v_, max_v_line_);
    if (n >= 2 && !parts[1].empty()) {
      Index(parts[1], scan_.texcoords.size(), "texture coordinate", max_vt_, max_vt_line_);
    }
    if (n == 3) Index(parts[2], scan_.normals.size(), "normal", max_vn_, max_vn_line_);
  }

  void Index(std::string_view token, size_t count, const char* what, int64_t& max_index,
             size_t& max_line) {
    int64_t i = 0;
    if (!ParseInt(token, i)) LineFail("bad {} index '{}'", what, token.substr(0, 40));
    if (i == 0) LineFail("{} index 0 is invalid (OBJ indices start at 1)", what);
    if (i > static_cast<int64_t>(std::numeric_limits<int32_t>::max())) {
      LineFail("{} index {} out of range", what, i);
    }
    if (i < 0) {
      // Relative: -1 is the last one defined so far.
      if (-i > static_cast<int64_t>(count)) {
        LineFail("relative {} index {} out of range ({} defined so far)", what, i, count);
      }
    } else if (i > max_index) {
      max_index = i;
      max_line = line_;
    }
  }

  std::string_view text_;
  const std::string& origin_;
  size_t line_ = 0;
  ObjScan scan_;
  int64_t max_v_ = 0, max_vt_ = 0, max_vn_ = 0;
  size_t max_v_line_ = 0, max_vt_line_ = 0, max_vn_line_ = 0;
};

// Which materials of an MTL set Ns / Ni explicitly (tinyobj fills defaults), indexed like
// tinyobj's material vector: one entry per "newmtl" with a non-empty name, in order.
struct MtlPresence {
  std::vector<char> has_ns;
  std::vector<char> has_ni;
};

MtlPresence ScanMtlPresence(std::string_view text) {
  MtlPresence presence;
  int current = -1;
  size_t pos = 0;
  while (pos < text.size()) {
    size_t end = pos;
    while (end < text.size() && text[end] != '\n' && text[end] != '\r') ++end;
    std::string_view line = text.substr(pos, end - pos);
    pos = end + 1;
    while (!line.empty() && IsBlank(line.back())) line.remove_suffix(1);
    while (!line.empty() && IsBlank(line.front())) line.remove_prefix(1);
    if (line.size() > 7 && line.substr(0, 6) == "newmtl" && IsBlank(line[6])) {
      // tinyobj keeps everything after "newmtl " as the name; an empty name starts no material.
      if (line.size() > 7) {
        presence.has_ns.push_back(0);
        presence.has_ni.push_back(0);
        current = static_cast<int>(presence.has_ns.size()) - 1;
      } else {
        current = -1;
      }
    } else if (current >= 0 && line.size() > 2 && line[0] == 'N' && IsBlank(line[2])) {
      if (line[1] == 's') presence.has_ns[static_cast<size_t>(current)] = 1;
      if (line[1] == 'i') presence.has_ni[static_cast<size_t>(current)] = 1;
    }
  }
  return presence;
}

// Reads mtllib files relative to the OBJ's directory; a missing one is a warning.
class MtlReader : public tinyobj::MaterialReader {
 public:
  MtlReader(std::string dir, const std::string& origin, std::vector<std::string>& warnings)
      : dir_(std::move(dir)), origin_(origin), warnings_(warnings) {}

  bool operator()(const std::string& mat_id, std::vector<tinyobj::material_t>* materials,
                  std::map<std::string, int>* mat_map, std::string* warn,
                  std::string* err) override {
    (void)err;
    if (dir_.empty()) {
      warnings_.push_back(
          fmt::format("{}: material library '{}' not read (no file access); "
                      "using the default material",
                      origin_, mat_id));
      return false;
    }
    const std::string path = JoinPath(dir_, mat_id);
    if (!IsRegularFile(path)) {
      warnings_.push_back(fmt::format(
          "{}: material library '{}' not found; using the default material", origin_, path));
      return false;
    }
    const std::string text = ReadFileText(path);
    const MtlPresence presence = ScanMtlPresence(text);
    const size_t first = materials->size();
    std::istringstream in(text);
    std::string mtl_warn, mtl_err;
    tinyobj::LoadMtl(mat_map, materials, &in, &mtl_warn, &mtl_err);
    if (!mtl_warn.empty()) *warn += mtl_warn;
    if (!mtl_err.empty()) Fail("{}: {}", path, mtl_err);
    for (size_t i = 0; i < presence.has_ns.size() && first + i < materials->size(); ++i) {
      has_ns.resize(first + i + 1, 0);
      has_ni.resize(first + i + 1, 0);
      has_ns[first + i] = presence.has_ns[i];
      has_ni[first + i] = presence.has_ni[i];
    }
    mtl_path = path;
    return true;
  }

  std::vector<char> has_ns, has_ni;
  std::string mtl_path;

 private:
  std::string dir_;
  const std::string& origin_;
  std::vector<std::string>& warnings_;
};

float Max3(const tinyobj::real_t v[3]) { return std::max({v[0], v[1], v[2]}); }

float Clamp01(float x) { return std::isfinite(x) ? std::clamp(x, 0.0f, 1.0f) : x; }

Material ConvertMaterial(const tinyobj::material_t& m, bool has_ns, bool has_ni,
                         const MeshLoadOptions& options, const std::string& where) {
  Material out;
  out.name = m.name;
  out.diffuse = glm::vec3(Clamp01(m.diffuse[0]), Clamp01(m.diffuse[1]), Clamp01(m.diffuse[2]));
  out.specular = glm::vec3(Clamp01(m.specular[0]), Clamp01(m.specular[1]), Clamp01(m.specular[2]));
  out.shininess = has_ns ? std::max(m.shininess, 0.0f) : 0.0f;
  const float emission = Max3(m.emission);
  if (emission > 0.0f && Max3(m.diffuse) <= 0.0f) {
    out.diffuse = glm::vec3(m.emission[0], m.emission[1], m.emission[2]) / emission;
  }
  const float ks = Clamp01(Max3(m.specular));
  if (m.illum == 3 || m.illum == 5 || m.illum == 8) out.reflectivity = ks > 0.0f ? ks : 1.0f;
  if (options.ks_reflects) out.reflectivity = ks;
  if (m.dissolve < 1.0f) out.transmission = Clamp01(1.0f - m.dissolve);
  if (out.transmission == 0.0f && (m.illum == 4 || m.illum == 6 || m.illum == 7 || m.illum == 9)) {
    out.transmission = Clamp01(Max3(m.transmittance));
  }
  if (has_ni && m.ior > 0.0f) out.ior = m.ior;
  auto extension = [&](const char* key, float& field) {
    const auto it = m.unknown_parameter.find(key);
    if (it == m.unknown_parameter.end()) return;
    float x = 0.0f;
    std::string_view s = it->second;
    while (!s.empty() && IsBlank(s.back())) s.remove_suffix(1);
    if (!ParseFloat(s, x) || !(x >= 0.0f && x <= 1.0f)) {
      Fail("{}: material '{}': {} '{}' is not a number in [0, 1]", where, m.name, key, it->second);
    }
    field = x;
  };
  extension("rs_reflectivity", out.reflectivity);
  extension("rs_transmission", out.transmission);
  return out;
}

struct CornerKey {
  int v, vt, vn;
  bool operator==(const CornerKey& o) const { return v == o.v && vt == o.vt && vn == o.vn; }
};
struct CornerHash {
  size_t operator()(const CornerKey& k) const {
    uint64_t h = static_cast<uint32_t>(k.v);
    h = h * 0x9E3779B97F4A7C15ull ^ static_cast<uint32_t>(k.vt);
    h = h * 0x9E3779B97F4A7C15ull ^ static_cast<uint32_t>(k.vn);
    return static_cast<size_t>(h ^ (h >> 29));
  }
};

}  // namespace

void ParseObj(std::string_view text, const std::string& origin, const std::string& file_dir,
              const MeshLoadOptions& options, Scene& scene, MeshGroups* groups) {
  // A UTF-8 byte order mark is not part of the first statement.
  if (text.size() >= 3 && text.substr(0, 3) == "\xEF\xBB\xBF") text.remove_prefix(3);
  const ObjScan scan = ObjScanner(text, origin).Run();

  Scene part;
  part.source = origin;
  tinyobj::attrib_t attrib;
  std::vector<tinyobj::shape_t> shapes;
  std::vector<tinyobj::material_t> tmaterials;
  std::string warn, err;
  MtlReader reader(file_dir, origin, part.warnings);
  {
    std::istringstream in{std::string(text)};
    const bool ok = tinyobj::LoadObj(&attrib, &shapes, &tmaterials, &warn, &err, &in, &reader,
                                     /*triangulate=*/true, /*default_vcols_fallback=*/false);
    if (!ok) Fail("{}: {}", origin, err.empty() ? std::string("tinyobjloader failed") : err);
  }
  if (attrib.vertices.size() != 3 * scan.positions.size()) {
    Fail("{}: internal error: tinyobjloader read {} vertices, the pre-scan {}", origin,
         attrib.vertices.size() / 3, scan.positions.size());
  }
  // Keep tinyobj's notes that matter (unknown usemtl names) as warnings.
  {
    std::istringstream lines(warn + err);
    std::string line;
    while (std::getline(lines, line)) {
      if (line.find("not found in .mtl") != std::string::npos ||
          line.find("Failed to load material") != std::string::npos) {
        part.warnings.push_back(fmt::format("{}: {} (using the default material)", origin, line));
      }
    }
  }

  // Materials: every MTL material in order, then the default for faces without one.
  const std::string mtl_where = reader.mtl_path.empty() ? origin : reader.mtl_path;
  for (size_t i = 0; i < tmaterials.size(); ++i) {
    const bool has_ns = i < reader.has_ns.size() && reader.has_ns[i];
    const bool has_ni = i < reader.has_ni.size() && reader.has_ni[i];
    part.materials.push_back(ConvertMaterial(tmaterials[i], has_ns, has_ni, options, mtl_where));
  }
  uint32_t default_material = UINT32_MAX;

  // Which per-corner attributes exist: uvs if any corner has one, normals if all have one.
  bool any_uv = false;
  bool all_normals = !scan.normals.empty();
  for (const tinyobj::shape_t& shape : shapes) {
    for (const tinyobj::index_t& idx : shape.mesh.indices) {
      any_uv |= idx.texcoord_index >= 0;
      all_normals &= idx.normal_index >= 0;
    }
  }
  const bool unweld = any_uv || all_normals;
  if (!unweld) part.positions = scan.positions;

  std::unordered_map<CornerKey, uint32_t, CornerHash> corner_vertex;
  auto vertex_of = [&](const tinyobj::index_t& idx) -> uint32_t {
    if (idx.vertex_index < 0 || static_cast<size_t>(idx.vertex_index) >= scan.positions.size() ||
        idx.texcoord_index >= static_cast<int>(scan.texcoords.size()) ||
        idx.normal_index >= static_cast<int>(scan.normals.size())) {
      Fail("{}: internal error: tinyobjloader index out of range", origin);
    }
    if (!unweld) return static_cast<uint32_t>(idx.vertex_index);
    const CornerKey key{idx.vertex_index, any_uv ? idx.texcoord_index : -1,
                        all_normals ? idx.normal_index : -1};
    const auto [it, inserted] =
        corner_vertex.try_emplace(key, static_cast<uint32_t>(part.positions.size()));
    if (inserted) {
      part.positions.push_back(scan.positions[static_cast<size_t>(key.v)]);
      if (any_uv) {
        part.uvs.push_back(key.vt >= 0 ? scan.texcoords[static_cast<size_t>(key.vt)]
                                       : glm::vec2(0.0f));
      }
      if (all_normals) part.normals.push_back(scan.normals[static_cast<size_t>(key.vn)]);
    }
    return it->second;
  };

  std::map<std::string, uint32_t> group_index;
  part.triangles.reserve(scan.expected_triangles);
  part.material_ids.reserve(scan.expected_triangles);
  for (const tinyobj::shape_t& shape : shapes) {
    const auto& indices = shape.mesh.indices;
    const size_t faces = shape.mesh.num_face_vertices.size();
    uint32_t group = 0;
    if (groups) {
      const auto [it, inserted] =
          group_index.try_emplace(shape.name, static_cast<uint32_t>(groups->names.size()));
      if (inserted) groups->names.push_back(shape.name);
      group = it->second;
    }
    for (size_t f = 0; f < faces; ++f) {
      if (shape.mesh.num_face_vertices[f] != 3 || 3 * f + 2 >= indices.size()) {
        Fail("{}: internal error: tinyobjloader returned a non-triangle", origin);
      }
      glm::uvec3 tri;
      for (int k = 0; k < 3; ++k) tri[k] = vertex_of(indices[3 * f + static_cast<size_t>(k)]);
      part.triangles.push_back(tri);
      const int mat = f < shape.mesh.material_ids.size() ? shape.mesh.material_ids[f] : -1;
      if (mat >= 0 && static_cast<size_t>(mat) < tmaterials.size()) {
        part.material_ids.push_back(static_cast<uint32_t>(mat));
      } else {
        if (default_material == UINT32_MAX) {
          default_material = static_cast<uint32_t>(part.materials.size());
          Material fallback;
          fallback.name = "default";
          part.materials.push_back(fallback);
        }
        part.material_ids.push_back(default_material);
      }
      if (groups) groups->of_triangle.push_back(group);
    }
  }
  if (part.triangles.empty()) Fail("{}: scene has no triangles", origin);
  if (part.triangles.size() != scan.expected_triangles) {
    part.warnings.push_back(fmt::format(
        "{}: {} triangles from polygon triangulation, expected {} (degenerate polygons?)", origin,
        part.triangles.size(), scan.expected_triangles));
  }

  // Normals: normalised; a zero one is replaced by the face normal of a triangle using it.
  if (const size_t repaired = RepairNormals(part); repaired > 0) {
    part.warnings.push_back(fmt::format(
        "{}: {} zero-length vertex normals replaced by face normals", origin, repaired));
  }

  // Diffuse textures (only useful when the mesh has uvs).
  if (any_uv && !file_dir.empty()) {
    std::map<std::string, int> loaded;
    const std::string tex_dir = reader.mtl_path.empty() ? file_dir : DirectoryOf(reader.mtl_path);
    for (size_t i = 0; i < tmaterials.size(); ++i) {
      const std::string& name = tmaterials[i].diffuse_texname;
      if (name.empty()) continue;
      const std::string path = JoinPath(tex_dir, name);
      auto it = loaded.find(path);
      if (it == loaded.end()) {
        int index = -1;
        try {
          part.textures.push_back(ReadImage(path));
          index = static_cast<int>(part.textures.size()) - 1;
        } catch (const Error& e) {
          part.warnings.push_back(
              fmt::format("{}: material '{}': texture not loaded ({}); "
                          "untextured",
                          mtl_where, tmaterials[i].name, e.what()));
        }
        it = loaded.emplace(path, index).first;
      }
      part.materials[i].texture = it->second;
    }
  }
  ValidateSceneAs(part, origin);
  AppendScene(scene, std::move(part));
}

void LoadObjFile(const std::string& path, const MeshLoadOptions& options, Scene& scene,
                 MeshGroups* groups) {
  const std::string text = ReadFileText(path);
  std::string dir = DirectoryOf(path);
  if (dir.empty()) dir.push_back('.');  // not = ".": GCC 12 -Wrestrict false positive
  ParseObj(text, path, dir, options, scene, groups);
}

}  // namespace rs::detail
