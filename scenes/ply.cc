// Strict PLY reader (ASCII, binary little- and big-endian): header, counts against the file
// size, numbers, finite coordinates and index ranges are checked, naming the line (ASCII) or the
// element (binary). Used instead of assimp for PLY because assimp 5.2.4 silently accepts
// truncated bodies, NaN vertices and out-of-range indices, misreads binary data whose first
// byte is 0x0A, and aborts (ai_assert in TriangulateProcess) on some malformed faces.
// Polygons are fan-triangulated; vertices are kept as in the file (no welding).
#include <algorithm>
#include <bit>
#include <charconv>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <string>

#include "scenes/scene_internal.h"

namespace rs::detail {
namespace {

enum class PlyType { kInt8, kUint8, kInt16, kUint16, kInt32, kUint32, kFloat32, kFloat64 };

bool ParsePlyType(std::string_view s, PlyType& t) {
  struct Entry {
    std::string_view name;
    PlyType type;
  };
  static constexpr Entry kTypes[] = {
      {"char", PlyType::kInt8},      {"int8", PlyType::kInt8},       {"uchar", PlyType::kUint8},
      {"uint8", PlyType::kUint8},    {"short", PlyType::kInt16},     {"int16", PlyType::kInt16},
      {"ushort", PlyType::kUint16},  {"uint16", PlyType::kUint16},   {"int", PlyType::kInt32},
      {"int32", PlyType::kInt32},    {"uint", PlyType::kUint32},     {"uint32", PlyType::kUint32},
      {"float", PlyType::kFloat32},  {"float32", PlyType::kFloat32}, {"double", PlyType::kFloat64},
      {"float64", PlyType::kFloat64}};
  for (const Entry& e : kTypes) {
    if (e.name == s) {
      t = e.type;
      return true;
    }
  }
  return false;
}

size_t TypeSize(PlyType t) {
  switch (t) {
    case PlyType::kInt8:
    case PlyType::kUint8:
      return 1;
    case PlyType::kInt16:
    case PlyType::kUint16:
      return 2;
    case PlyType::kInt32:
    case PlyType::kUint32:
    case PlyType::kFloat32:
      return 4;
    case PlyType::kFloat64:
      return 8;
  }
  return 1;
}

bool IsFloatType(PlyType t) { return t == PlyType::kFloat32 || t == PlyType::kFloat64; }

// Which vertex attribute a property feeds.
enum Slot { kNone = -1, kX, kY, kZ, kNx, kNy, kNz, kU, kV, kNumSlots };

Slot SlotOf(std::string_view name) {
  if (name == "x") return kX;
  if (name == "y") return kY;
  if (name == "z") return kZ;
  if (name == "nx") return kNx;
  if (name == "ny") return kNy;
  if (name == "nz") return kNz;
  if (name == "u" || name == "s" || name == "texture_u") return kU;
  if (name == "v" || name == "t" || name == "texture_v") return kV;
  return kNone;
}

struct PlyProperty {
  std::string name;
  bool is_list = false;
  PlyType count_type = PlyType::kUint8;
  PlyType type = PlyType::kFloat32;
  Slot slot = kNone;           // vertex attributes we keep (checked finite)
  bool is_face_index = false;  // the vertex index list of a face
};

enum class Kind { kVertex, kFace, kOther };

struct PlyElement {
  std::string name;
  Kind kind = Kind::kOther;
  uint64_t count = 0;
  std::vector<PlyProperty> properties;
};

enum class PlyFormat { kAscii, kBinaryLittle, kBinaryBig };

bool IsSpace(char c) { return c == ' ' || c == '\t'; }

void SplitWords(std::string_view line, std::vector<std::string_view>& words) {
  words.clear();
  size_t i = 0;
  while (i < line.size()) {
    while (i < line.size() && IsSpace(line[i])) ++i;
    const size_t start = i;
    while (i < line.size() && !IsSpace(line[i])) ++i;
    if (i > start) words.push_back(line.substr(start, i - start));
  }
}

class PlyReader {
 public:
  PlyReader(std::string_view data, const std::string& origin, Scene& part)
      : data_(data), origin_(origin), part_(part) {}

  void Run() {
    ParseHeader();
    if (format_ == PlyFormat::kAscii) {
      ReadAscii();
    } else {
      ReadBinary();
    }
    if (part_.triangles.empty()) Fail("{}: scene has no triangles", origin_);
  }

 private:
  // Next header/ASCII line without its terminator ("\n" or "\r\n"); false at the end.
  bool NextLine(std::string_view& line) {
    if (pos_ >= data_.size()) return false;
    size_t end = data_.find('\n', pos_);
    if (end == std::string_view::npos) end = data_.size();
    line = data_.substr(pos_, end - pos_);
    if (!line.empty() && line.back() == '\r') line.remove_suffix(1);
    pos_ = end + 1;
    ++line_;
    return true;
  }

  template <typename... Args>
  [[noreturn]] void LineFail(fmt::format_string<Args...> format, Args&&... args) {
    Fail("{}:{}: {}", origin_, line_, fmt::format(format, std::forward<Args>(args)...));
  }

  // ASCII errors name the line, binary ones the element.
  template <typename... Args>
  [[noreturn]] void ElementFail(fmt::format_string<Args...> format, Args&&... args) {
    if (format_ == PlyFormat::kAscii) LineFail(format, std::forward<Args>(args)...);
    Fail("{}: {}", origin_, fmt::format(format, std::forward<Args>(args)...));
  }

  void ParseHeader() {
    std::string_view line;
    std::vector<std::string_view> w;
    if (!NextLine(line) || line != "ply") {
      Fail("{}:1: not a PLY file (first line must be 'ply')", origin_);
    }
    bool have_format = false;
    for (;;) {
      if (!NextLine(line)) Fail("{}: PLY header has no 'end_header'", origin_);
      for (const char c : line) {
        if (static_cast<unsigned char>(c) < 0x20 && c != '\t') {
          LineFail("control character in the PLY header");
        }
      }
      SplitWords(line, w);
      if (w.empty()) continue;
      if (w[0] == "end_header") {
        if (w.size() != 1) LineFail("unexpected text after 'end_header'");
        break;
      }
      if (w[0] == "comment" || w[0] == "obj_info") continue;
      if (w[0] == "format") {
        if (w.size() != 3 || w[2] != "1.0") LineFail("expected 'format <type> 1.0'");
        if (w[1] == "ascii") {
          format_ = PlyFormat::kAscii;
        } else if (w[1] == "binary_little_endian") {
          format_ = PlyFormat::kBinaryLittle;
        } else if (w[1] == "binary_big_endian") {
          format_ = PlyFormat::kBinaryBig;
        } else {
          LineFail("unknown PLY format '{}'", w[1].substr(0, 40));
        }
        have_format = true;
      } else if (w[0] == "element") {
        if (w.size() != 3) LineFail("expected 'element <name> <count>'");
        PlyElement e;
        e.name = std::string(w[1]);
        const auto r = std::from_chars(w[2].data(), w[2].data() + w[2].size(), e.count);
        if (r.ec != std::errc() || r.ptr != w[2].data() + w[2].size() ||
            e.count > static_cast<uint64_t>(std::numeric_limits<int32_t>::max())) {
          LineFail("bad element count '{}'", w[2].substr(0, 40));
        }
        for (const PlyElement& other : elements_) {
          if (other.name == e.name) LineFail("duplicate element '{}'", e.name);
        }
        e.kind = e.name == "vertex" ? Kind::kVertex : e.name == "face" ? Kind::kFace : Kind::kOther;
        elements_.push_back(std::move(e));
      } else if (w[0] == "property") {
        if (elements_.empty()) LineFail("property before any element");
        PlyProperty p;
        if (w.size() == 5 && w[1] == "list") {
          p.is_list = true;
          if (!ParsePlyType(w[2], p.count_type) || !ParsePlyType(w[3], p.type)) {
            LineFail("unknown property type in list '{}'", line.substr(0, 80));
          }
          if (IsFloatType(p.count_type)) LineFail("list count type must be an integer type");
          p.name = std::string(w[4]);
        } else if (w.size() == 3) {
          if (!ParsePlyType(w[1], p.type))
            LineFail("unknown property type '{}'", w[1].substr(0, 40));
          p.name = std::string(w[2]);
        } else {
          LineFail("expected 'property <type> <name>' or 'property list <type> <type> <name>'");
        }
        PlyElement& e = elements_.back();
        for (const PlyProperty& other : e.properties) {
          if (other.name == p.name) LineFail("duplicate property '{}'", p.name);
        }
        if (e.kind == Kind::kVertex && !p.is_list) p.slot = SlotOf(p.name);
        if (e.kind == Kind::kFace && p.is_list &&
            (p.name == "vertex_indices" || p.name == "vertex_index")) {
          if (IsFloatType(p.type)) LineFail("face vertex indices must have an integer type");
          p.is_face_index = true;
        }
        e.properties.push_back(std::move(p));
      } else {
        LineFail("unknown PLY header line '{}'", w[0].substr(0, 40));
      }
    }
    if (!have_format) Fail("{}: PLY header has no 'format' line", origin_);
    const PlyElement* vertex = nullptr;
    const PlyElement* face = nullptr;
    for (const PlyElement& e : elements_) {
      if (e.kind == Kind::kVertex) vertex = &e;
      if (e.kind == Kind::kFace) face = &e;
    }
    if (vertex == nullptr) Fail("{}: PLY header declares no 'vertex' element", origin_);
    bool slots[kNumSlots] = {};
    for (const PlyProperty& p : vertex->properties) {
      if (p.slot != kNone) slots[p.slot] = true;
    }
    for (const Slot s : {kX, kY, kZ}) {
      if (!slots[s]) Fail("{}: PLY vertex element has no '{}' property", origin_, "xyz"[s]);
    }
    has_normals_ = slots[kNx] && slots[kNy] && slots[kNz];
    has_uvs_ = slots[kU];
    if (face == nullptr || face->count == 0) Fail("{}: scene has no triangles (no faces)", origin_);
    if (std::none_of(face->properties.begin(), face->properties.end(),
                     [](const PlyProperty& p) { return p.is_face_index; })) {
      Fail("{}: PLY face element has no 'vertex_indices' list", origin_);
    }
    num_vertices_ = vertex->count;
    // Every element instance needs at least one byte per property (binary) or two characters
    // (ASCII: a digit and a separator): reject counts the file cannot hold before allocating.
    const uint64_t remaining = data_.size() - std::min(pos_, data_.size());
    uint64_t needed = 0;
    for (const PlyElement& e : elements_) {
      uint64_t per = 0;
      for (const PlyProperty& p : e.properties) {
        per += format_ == PlyFormat::kAscii
                   ? 2
                   : (p.is_list ? TypeSize(p.count_type) : TypeSize(p.type));
      }
      needed += e.count * per;
      if (needed > remaining) {
        Fail(
            "{}: PLY element '{}' count {} needs more data than the file holds ({} bytes "
            "after the header): truncated file or bad header",
            origin_, e.name, e.count, remaining);
      }
    }
    part_.positions.reserve(num_vertices_);
    if (has_normals_) part_.normals.reserve(num_vertices_);
    if (has_uvs_) part_.uvs.reserve(num_vertices_);
    part_.triangles.reserve(face->count);
  }

  // One value of a vertex property: checked and stored in its slot.
  void VertexValue(const PlyProperty& p, double v, uint64_t i, std::string_view token) {
    if (p.slot == kNone) return;
    if (!std::isfinite(v)) {
      if (format_ == PlyFormat::kAscii) LineFail("vertex {}: value '{}' is not finite", i, token);
      Fail("{}: vertex {}: property '{}' is not finite ({})", origin_, i, p.name, v);
    }
    if (p.slot <= kZ && std::fabs(v) > kMaxCoordinate) {
      ElementFail("vertex {}: {} = {} too large (limit {})", i, p.name, v, kMaxCoordinate);
    }
    const float f = static_cast<float>(v);
    if (!std::isfinite(f)) ElementFail("vertex {}: {} = {} overflows a float", i, p.name, v);
    vertex_[p.slot] = f;
  }

  void EndVertex() {
    part_.positions.emplace_back(vertex_[kX], vertex_[kY], vertex_[kZ]);
    if (has_normals_) part_.normals.emplace_back(vertex_[kNx], vertex_[kNy], vertex_[kNz]);
    if (has_uvs_) part_.uvs.emplace_back(vertex_[kU], vertex_[kV]);
    std::fill(std::begin(vertex_), std::end(vertex_), 0.0f);
  }

  void FaceIndex(double v, uint64_t face) {
    if (!(v >= 0.0) || v >= static_cast<double>(num_vertices_)) {
      ElementFail("face {}: vertex index {} out of range ({} vertices)", face, v, num_vertices_);
    }
    polygon_.push_back(static_cast<uint32_t>(v));
  }

  void EndFace() {
    // Fan triangulation (PLY polygons are convex in practice); zero-area results are legal.
    for (size_t k = 1; k + 1 < polygon_.size(); ++k) {
      part_.triangles.emplace_back(polygon_[0], polygon_[k], polygon_[k + 1]);
    }
    polygon_.clear();
  }

  void CheckListCount(double n, const PlyProperty& p, const PlyElement& e, uint64_t i) {
    if (n < 0) ElementFail("{} {}: negative list count {}", e.name, i, n);
    if (p.is_face_index && n < 3) ElementFail("face {}: {} vertices (need at least 3)", i, n);
  }

  void ReadAscii() {
    std::string_view line;
    std::vector<std::string_view> w;
    for (const PlyElement& e : elements_) {
      for (uint64_t i = 0; i < e.count; ++i) {
        do {
          if (!NextLine(line)) {
            Fail("{}:{}: unexpected end of file in {} {} of {}", origin_, line_ + 1, e.name, i,
                 e.count);
          }
          SplitWords(line, w);
        } while (w.empty());
        size_t k = 0;
        auto next = [&](const std::string& what) -> std::string_view {
          if (k >= w.size()) LineFail("{} {}: too few values (missing {})", e.name, i, what);
          return w[k++];
        };
        for (const PlyProperty& p : e.properties) {
          if (p.is_list) {
            const int64_t n = Integer(next("list count"), e.name, i);
            CheckListCount(static_cast<double>(n), p, e, i);
            for (int64_t j = 0; j < n; ++j) {
              const std::string_view token = next(p.name);
              const double v = IsFloatType(p.type) ? Real(token, e.name, i)
                                                   : static_cast<double>(Integer(token, e.name, i));
              if (p.is_face_index) FaceIndex(v, i);
            }
          } else {
            const std::string_view token = next(p.name);
            const double v = IsFloatType(p.type) ? Real(token, e.name, i)
                                                 : static_cast<double>(Integer(token, e.name, i));
            if (e.kind == Kind::kVertex) VertexValue(p, v, i, token);
          }
        }
        if (k != w.size()) {
          LineFail("{} {}: {} values beyond the declared properties", e.name, i, w.size() - k);
        }
        EndInstance(e);
      }
    }
    while (NextLine(line)) {
      SplitWords(line, w);
      if (!w.empty()) LineFail("data after the last element");
    }
  }

  void EndInstance(const PlyElement& e) {
    if (e.kind == Kind::kVertex) EndVertex();
    if (e.kind == Kind::kFace) EndFace();
  }

  int64_t Integer(std::string_view token, const std::string& element, uint64_t i) {
    int64_t v = 0;
    const auto r = std::from_chars(token.data(), token.data() + token.size(), v);
    if (r.ec != std::errc() || r.ptr != token.data() + token.size()) {
      LineFail("{} {}: bad integer '{}'", element, i, token.substr(0, 40));
    }
    return v;
  }

  // A real number token; huge values become +-inf (rejected where finiteness matters).
  double Real(std::string_view token, const std::string& element, uint64_t i) {
    double v = 0.0;
    std::string_view t = token;
    if (t.size() > 1 && t[0] == '+' && t[1] != '-') t.remove_prefix(1);
    const auto r = std::from_chars(t.data(), t.data() + t.size(), v);
    if ((r.ec != std::errc() && r.ec != std::errc::result_out_of_range) ||
        r.ptr != t.data() + t.size()) {
      LineFail("{} {}: bad number '{}'", element, i, token.substr(0, 40));
    }
    if (r.ec == std::errc::result_out_of_range) {
      v = std::strtod(std::string(t).c_str(), nullptr);  // +-inf on overflow, ~0 on underflow
    }
    return v;
  }

  // Binary: one value of `type` at pos_ (bounds checked by the caller).
  double Binary(PlyType type) {
    unsigned char b[8];
    const size_t n = TypeSize(type);
    std::memcpy(b, data_.data() + pos_, n);
    pos_ += n;
    const bool swap =
        (format_ == PlyFormat::kBinaryBig) == (std::endian::native == std::endian::little);
    if (swap) std::reverse(b, b + n);
    switch (type) {
      case PlyType::kInt8:
        return static_cast<int8_t>(b[0]);
      case PlyType::kUint8:
        return b[0];
      case PlyType::kInt16: {
        int16_t v;
        std::memcpy(&v, b, 2);
        return v;
      }
      case PlyType::kUint16: {
        uint16_t v;
        std::memcpy(&v, b, 2);
        return v;
      }
      case PlyType::kInt32: {
        int32_t v;
        std::memcpy(&v, b, 4);
        return v;
      }
      case PlyType::kUint32: {
        uint32_t v;
        std::memcpy(&v, b, 4);
        return v;
      }
      case PlyType::kFloat32: {
        float v;
        std::memcpy(&v, b, 4);
        return v;
      }
      case PlyType::kFloat64: {
        double v;
        std::memcpy(&v, b, 8);
        return v;
      }
    }
    return 0.0;
  }

  void Need(uint64_t bytes, const std::string& element, uint64_t i) {
    if (pos_ > data_.size() || data_.size() - pos_ < bytes) {
      Fail("{}: {} {}: unexpected end of file (binary data truncated)", origin_, element, i);
    }
  }

  void ReadBinary() {
    for (const PlyElement& e : elements_) {
      for (uint64_t i = 0; i < e.count; ++i) {
        for (const PlyProperty& p : e.properties) {
          if (p.is_list) {
            Need(TypeSize(p.count_type), e.name, i);
            const double n = Binary(p.count_type);
            CheckListCount(n, p, e, i);
            const auto count = static_cast<uint64_t>(n);
            Need(count * TypeSize(p.type), e.name, i);
            for (uint64_t j = 0; j < count; ++j) {
              const double v = Binary(p.type);
              if (p.is_face_index) FaceIndex(v, i);
            }
          } else {
            Need(TypeSize(p.type), e.name, i);
            const double v = Binary(p.type);
            if (e.kind == Kind::kVertex) VertexValue(p, v, i, "");
          }
        }
        EndInstance(e);
      }
    }
    // Trailing whitespace (a final newline some writers add) is harmless; other data is not.
    for (size_t i = pos_; i < data_.size(); ++i) {
      if (data_[i] != '\n' && data_[i] != '\r' && data_[i] != ' ' && data_[i] != '\t') {
        Fail("{}: {} bytes after the last PLY element", origin_, data_.size() - pos_);
      }
    }
  }

  std::string_view data_;
  const std::string& origin_;
  Scene& part_;
  size_t pos_ = 0;
  size_t line_ = 0;
  PlyFormat format_ = PlyFormat::kAscii;
  std::vector<PlyElement> elements_;
  uint64_t num_vertices_ = 0;
  bool has_normals_ = false;
  bool has_uvs_ = false;
  float vertex_[kNumSlots] = {};
  std::vector<uint32_t> polygon_;
};

}  // namespace

void ReadPly(std::string_view data, const std::string& origin, Scene& scene) {
  Scene part;
  part.source = origin;
  PlyReader(data, origin, part).Run();
  Material fallback;
  fallback.name = "default";
  part.materials.push_back(fallback);
  part.material_ids.assign(part.triangles.size(), 0);
  if (!AnyPositiveArea(part)) {
    Fail("{}: every face has zero area ({} triangles); nothing to render", origin,
         part.triangles.size());
  }
  const size_t repaired = RepairNormals(part);
  if (repaired > 0) {
    part.warnings.push_back(fmt::format(
        "{}: {} zero-length vertex normals replaced by face normals", origin, repaired));
  }
  ValidateSceneAs(part, origin);
  AppendScene(scene, std::move(part));
}

}  // namespace rs::detail
