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
#include <filesystem>
#include <map>
#include <optional>
#include <sstream>
#include <streambuf>
#include <unordered_map>

#include "scenes/image_io.h"
#include "scenes/load.h"
#include "scenes/scene_internal.h"

namespace rs::detail {
namespace {

bool IsBlank(char c) { return c == ' ' || c == '\t'; }

// A read-only stream over text in memory, for tinyobjloader's stream API without copying the
// text (a mesh's text is its largest input: a copy cost as much as the read, fresh pages and all).
class TextStreamBuf : public std::streambuf {
 public:
  explicit TextStreamBuf(std::string_view text) {
    char* const p = const_cast<char*>(text.data());  // a get area only: never written
    setg(p, p, p + text.size());
  }
};

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
  size_t first_face_line = 0;
  // Faces naming one vertex at two corners ("f 1 2 3 1 2 3"): triangulation drops or mangles
  // them, so they are reported with the first line.
  size_t repeated_corner_faces = 0;
  size_t first_repeated_line = 0;
  size_t first_repeated_vertex = 0;
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
      face_vertices_.clear();
      for (size_t k = 1; k < tokens.size(); ++k) Corner(tokens[k]);
      if (key == "f") {
        scan_.expected_triangles += corners - 2;
        if (scan_.first_face_line == 0) scan_.first_face_line = line_;
        CheckRepeatedCorners();
      }
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
    face_vertices_.push_back(
        Index(parts[0], scan_.positions.size(), "vertex", max_v_, max_v_line_));
    if (n >= 2 && !parts[1].empty()) {
      Index(parts[1], scan_.texcoords.size(), "texture coordinate", max_vt_, max_vt_line_);
    }
    if (n == 3) Index(parts[2], scan_.normals.size(), "normal", max_vn_, max_vn_line_);
  }

  // Positions are resolved (relative ones against the count so far): a repeated corner is the
  // same vertex named twice, whichever way it is written.
  void CheckRepeatedCorners() {
    sorted_.assign(face_vertices_.begin(), face_vertices_.end());
    std::sort(sorted_.begin(), sorted_.end());
    const auto dup = std::adjacent_find(sorted_.begin(), sorted_.end());
    if (dup == sorted_.end()) return;
    if (scan_.repeated_corner_faces++ == 0) {
      scan_.first_repeated_line = line_;
      scan_.first_repeated_vertex = static_cast<size_t>(*dup);
    }
  }

  // Returns the 1-based absolute index.
  int64_t Index(std::string_view token, size_t count, const char* what, int64_t& max_index,
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
      return static_cast<int64_t>(count) + i + 1;
    }
    if (i > max_index) {
      max_index = i;
      max_line = line_;
    }
    return i;
  }

  std::string_view text_;
  const std::string& origin_;
  size_t line_ = 0;
  ObjScan scan_;
  int64_t max_v_ = 0, max_vt_ = 0, max_vn_ = 0;
  size_t max_v_line_ = 0, max_vt_line_ = 0, max_vn_line_ = 0;
  std::vector<int64_t> face_vertices_, sorted_;
};

// What the strict MTL scan read for one material ("newmtl" with a non-empty name, indexed like
// tinyobj's material vector). Applied over tinyobjloader's parse, which turns NaN and garbage
// into 0, overflows to inf, reads "Kd 0.5" as (0.5, 0, 0) and knows no line numbers.
struct MtlValues {
  std::optional<glm::vec3> ka, kd, ks, ke, tf;
  std::optional<float> ns, ni, d, tr, rs_reflectivity, rs_transmission;
  std::optional<int> illum;
};

// Line-by-line check of an MTL file (same line ends as tinyobjloader: "\n", "\r\n", lone "\r").
// Every value raystream uses is parsed strictly and range-checked; errors name the MTL file and
// the line. Statements raystream does not use (maps, PBR extensions) are left to tinyobjloader.
class MtlScanner {
 public:
  MtlScanner(std::string_view text, const std::string& path) : text_(text), path_(path) {}

  std::vector<MtlValues> Run() {
    if (text_.size() >= 3 && text_.substr(0, 3) == "\xEF\xBB\xBF") text_.remove_prefix(3);
    size_t pos = 0;
    std::vector<std::string_view> tokens;
    while (pos < text_.size()) {
      size_t end = pos;
      while (end < text_.size() && text_[end] != '\n' && text_[end] != '\r') ++end;
      ++line_;
      ScanLine(text_.substr(pos, end - pos), tokens);
      pos = end + 1;
      if (end + 1 < text_.size() && text_[end] == '\r' && text_[end + 1] == '\n') ++pos;
    }
    return std::move(values_);
  }

 private:
  template <typename... Args>
  [[noreturn]] void LineFail(fmt::format_string<Args...> format, Args&&... args) {
    Fail("{}:{}: {}", path_, line_, fmt::format(format, std::forward<Args>(args)...));
  }

  void ScanLine(std::string_view line, std::vector<std::string_view>& tokens) {
    for (const char c : line) {
      const auto u = static_cast<unsigned char>(c);
      if ((u < 0x20 && c != '\t') || u == 0x7f) {
        LineFail("unexpected control character 0x{:02x} (binary data, not a material library?)",
                 static_cast<int>(u));
      }
    }
    while (!line.empty() && IsBlank(line.back())) line.remove_suffix(1);
    while (!line.empty() && IsBlank(line.front())) line.remove_prefix(1);
    if (line.empty() || line[0] == '#') return;
    if (line.size() > 6 && line.substr(0, 6) == "newmtl" && IsBlank(line[6])) {
      // tinyobj keeps everything after "newmtl " as the name; an empty name starts no material.
      if (line.size() > 7) {
        values_.emplace_back();
        current_ = &values_.back();
      } else {
        current_ = &orphan_;
      }
      return;
    }
    Tokenize(line, tokens);
    const std::string_view key = tokens[0];
    MtlValues& m = current_ ? *current_ : orphan_;  // values before any newmtl: checked, unused
    if (key == "Ka") {
      m.ka = Colour(tokens, 1e6f);
    } else if (key == "Kd") {
      m.kd = Colour(tokens, 1e6f);
    } else if (key == "Ks") {
      m.ks = Colour(tokens, 1e6f);
    } else if (key == "Ke") {
      m.ke = Colour(tokens, 1e12f);
    } else if (key == "Tf" || key == "Kt") {
      m.tf = Colour(tokens, 1e6f);
    } else if (key == "Ns") {
      m.ns = Scalar(tokens, 0.0f, 1e5f);
    } else if (key == "Ni") {
      m.ni = Scalar(tokens, 0.0f, 100.0f);
    } else if (key == "d") {
      m.d = Scalar(tokens, 0.0f, 1.0f);
    } else if (key == "Tr") {
      m.tr = Scalar(tokens, 0.0f, 1.0f);
    } else if (key == "rs_reflectivity") {
      m.rs_reflectivity = Scalar(tokens, 0.0f, 1.0f);
    } else if (key == "rs_transmission") {
      m.rs_transmission = Scalar(tokens, 0.0f, 1.0f);
    } else if (key == "illum") {
      if (tokens.size() != 2)
        LineFail("illum needs one whole number, got {} values", Count(tokens));
      int64_t v = 0;
      if (!ParseInt(tokens[1], v)) LineFail("illum: bad number '{}'", tokens[1].substr(0, 40));
      if (v < 0 || v > 10) LineFail("illum {} outside [0, 10]", v);
      m.illum = static_cast<int>(v);
    } else if (key == "Pr" || key == "Pm" || key == "Ps" || key == "Pc" || key == "Pcr" ||
               key == "aniso" || key == "anisor") {
      Scalar(tokens, -1e30f, 1e30f);  // unused, but a number
    }
  }

  // Values after the key, not counting a trailing comment.
  size_t Count(const std::vector<std::string_view>& tokens) const {
    size_t n = 0;
    while (n + 1 < tokens.size() && tokens[n + 1][0] != '#') ++n;
    return n;
  }

  float Value(std::string_view key, std::string_view token, float lo, float hi) {
    float x = 0.0f;
    if (!ParseFloat(token, x)) LineFail("{}: bad number '{}'", key, token.substr(0, 40));
    if (!std::isfinite(x)) {
      LineFail("{} value '{}' is not a finite number", key, token.substr(0, 40));
    }
    if (!(x >= lo && x <= hi)) LineFail("{} value {} outside [{}, {}]", key, x, lo, hi);
    return x;
  }

  float Scalar(const std::vector<std::string_view>& tokens, float lo, float hi) {
    if (Count(tokens) != 1)
      LineFail("{} needs one number, got {} values", tokens[0], Count(tokens));
    return Value(tokens[0], tokens[1], lo, hi);
  }

  // "K r g b" or "K grey" (the MTL spec: g and b default to r); spectral and CIE XYZ colours
  // are not supported (tinyobjloader would read them as black).
  glm::vec3 Colour(const std::vector<std::string_view>& tokens, float hi) {
    const std::string_view key = tokens[0];
    const size_t n = Count(tokens);
    if (n >= 1 && (tokens[1] == "spectral" || tokens[1] == "xyz")) {
      LineFail("{} {} colours are not supported (give r g b)", key, tokens[1]);
    }
    if (n != 1 && n != 3) LineFail("{} needs 3 numbers (r g b) or 1 (grey), got {}", key, n);
    glm::vec3 c;
    for (size_t k = 0; k < 3; ++k) {
      c[static_cast<int>(k)] = Value(key, tokens[n == 1 ? 1 : k + 1], 0.0f, hi);
    }
    return c;
  }

  std::string_view text_;
  const std::string& path_;
  size_t line_ = 0;
  std::vector<MtlValues> values_;
  MtlValues* current_ = nullptr;
  MtlValues orphan_;
};

// Applies the strict scan's values over tinyobjloader's (same material order).
void ApplyMtlValues(const MtlValues& v, tinyobj::material_t& m) {
  auto set3 = [](const std::optional<glm::vec3>& c, tinyobj::real_t out[3]) {
    if (c) {
      for (int k = 0; k < 3; ++k) out[k] = (*c)[k];
    }
  };
  set3(v.ka, m.ambient);
  set3(v.kd, m.diffuse);
  set3(v.ks, m.specular);
  set3(v.ke, m.emission);
  set3(v.tf, m.transmittance);
  if (v.ns) m.shininess = *v.ns;
  if (v.ni) m.ior = *v.ni;
  // tinyobjloader's rule (its issue 43): d wins over Tr, Tr is 1 - d.
  if (v.d) {
    m.dissolve = *v.d;
  } else if (v.tr) {
    m.dissolve = 1.0f - *v.tr;
  }
  if (v.illum) m.illum = *v.illum;
}

void ReadMtlText(std::string_view text, const std::string& path,
                 std::vector<tinyobj::material_t>& materials, std::map<std::string, int>& mat_map,
                 std::vector<MtlValues>& values, std::string& warn);

// Reads mtllib files relative to the OBJ's directory; a missing one is a warning, a broken one
// (bad values, binary data, a directory or device in its place) an error naming it.
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
    std::error_code ec;
    if (!std::filesystem::exists(path, ec)) {
      warnings_.push_back(fmt::format(
          "{}: material library '{}' not found; using the default material", origin_, path));
      return false;
    }
    ReadMtlText(ReadFileText(path, "material library"), path, *materials, *mat_map, values, *warn);
    mtl_path = path;
    return true;
  }

  std::vector<MtlValues> values;  // per material, as tinyobj numbers them
  std::string mtl_path;

 private:
  std::string dir_;
  const std::string& origin_;
  std::vector<std::string>& warnings_;
};

float Max3(const tinyobj::real_t v[3]) { return std::max({v[0], v[1], v[2]}); }

float Clamp01(float x) { return std::isfinite(x) ? std::clamp(x, 0.0f, 1.0f) : x; }

// `v`: what the file set explicitly (tinyobj fills defaults, e.g. Ns 1 and Ni 1).
Material ConvertMaterial(const tinyobj::material_t& m, const MtlValues& v,
                         const MeshLoadOptions& options) {
  Material out;
  out.name = m.name;
  out.diffuse = glm::vec3(Clamp01(m.diffuse[0]), Clamp01(m.diffuse[1]), Clamp01(m.diffuse[2]));
  out.specular = glm::vec3(Clamp01(m.specular[0]), Clamp01(m.specular[1]), Clamp01(m.specular[2]));
  out.shininess = v.ns ? std::max(m.shininess, 0.0f) : 0.0f;
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
  if (v.ni && m.ior > 0.0f) out.ior = m.ior;
  if (v.rs_reflectivity) out.reflectivity = *v.rs_reflectivity;
  if (v.rs_transmission) out.transmission = *v.rs_transmission;
  return out;
}

// One material library from memory: the strict scan, tinyobjloader, our values over its.
// `path` names it in messages. Appends to `materials` / `mat_map` and `values`.
void ReadMtlText(std::string_view text, const std::string& path,
                 std::vector<tinyobj::material_t>& materials, std::map<std::string, int>& mat_map,
                 std::vector<MtlValues>& values, std::string& warn) {
  std::vector<MtlValues> scanned = MtlScanner(text, path).Run();
  const size_t first = materials.size();
  TextStreamBuf buffer(text);
  std::istream in(&buffer);
  std::string mtl_warn, mtl_err;
  tinyobj::LoadMtl(&mat_map, &materials, &in, &mtl_warn, &mtl_err);
  warn += mtl_warn;
  if (!mtl_err.empty()) Fail("{}: {}", path, mtl_err);
  if (materials.size() - first != scanned.size()) {
    Fail("{}: internal error: tinyobjloader read {} materials, the pre-scan {}", path,
         materials.size() - first, scanned.size());
  }
  values.resize(first);
  for (size_t i = 0; i < scanned.size(); ++i) {
    ApplyMtlValues(scanned[i], materials[first + i]);
    values.push_back(scanned[i]);
  }
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
    TextStreamBuf buffer(text);
    std::istream in(&buffer);
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
    const MtlValues none;
    const MtlValues& v = i < reader.values.size() ? reader.values[i] : none;
    part.materials.push_back(ConvertMaterial(tmaterials[i], v, options));
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
  if (part.triangles.empty()) {
    if (scan.repeated_corner_faces > 0) {
      Fail(
          "{}:{}: scene has no triangles: every face is degenerate (this face names vertex {} "
          "twice; {} faces repeat a corner)",
          origin, scan.first_repeated_line, scan.first_repeated_vertex, scan.repeated_corner_faces);
    }
    Fail("{}: scene has no triangles", origin);
  }
  if (scan.repeated_corner_faces > 0) {
    part.warnings.push_back(fmt::format(
        "{}:{}: face names vertex {} twice ({} such faces in the file); degenerate corners "
        "dropped by triangulation",
        origin, scan.first_repeated_line, scan.first_repeated_vertex, scan.repeated_corner_faces));
  } else if (part.triangles.size() != scan.expected_triangles) {
    part.warnings.push_back(fmt::format(
        "{}: {} triangles from polygon triangulation, expected {} (degenerate polygons?)", origin,
        part.triangles.size(), scan.expected_triangles));
  }
  if (!AnyPositiveArea(part)) {
    Fail("{}:{}: every triangle has zero area ({} triangles from line {} on); nothing to render",
         origin, scan.first_face_line, part.triangles.size(), scan.first_face_line);
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
  const std::string text = ReadFileText(path, "mesh");
  std::string dir = DirectoryOf(path);
  if (dir.empty()) dir.push_back('.');  // not = ".": GCC 12 -Wrestrict false positive
  ParseObj(text, path, dir, options, scene, groups);
}

void ParseMtl(std::string_view text, const std::string& origin, std::vector<Material>& out) {
  std::vector<tinyobj::material_t> materials;
  std::map<std::string, int> mat_map;
  std::vector<MtlValues> values;
  std::string warn;
  ReadMtlText(text, origin, materials, mat_map, values, warn);
  for (size_t i = 0; i < materials.size(); ++i) {
    out.push_back(ConvertMaterial(materials[i], values[i], {}));
  }
}

}  // namespace rs::detail
