// Every mesh format assimp reads (.ply is routed to raystream's strict reader, ply.cc). Assimp's
// raw output is checked (indices, finite vertices) before post-processing, so errors name the
// mesh and face as in the file and assimp's own asserts never see a broken mesh.
#include <assimp/material.h>
#include <assimp/postprocess.h>
#include <assimp/scene.h>
#include <fmt/format.h>
#include <fmt/ranges.h>

#include <algorithm>
#include <assimp/DefaultLogger.hpp>
#include <assimp/Importer.hpp>
#include <assimp/LogStream.hpp>
#include <cmath>
#include <functional>
#include <map>
#include <new>
#include <string>
#include <vector>

#include "scenes/image_io.h"
#include "scenes/scene_internal.h"

namespace rs::detail {
namespace {

// Triangulate polygons, weld vertices the file repeats per face (PLY loader output), and nothing
// else: no degenerate removal (zero-area triangles are legal and counted), kept fast for the
// 69,451-triangle bunny.
constexpr unsigned kPostProcess = aiProcess_Triangulate | aiProcess_JoinIdenticalVertices;

// Assimp reports some input errors only to its logger and repairs the data (OFF clamps an
// out-of-range vertex index); we capture the log per thread and treat errors as fatal.
thread_local std::vector<std::string>* t_log_errors = nullptr;
thread_local std::vector<std::string>* t_log_warnings = nullptr;

class CaptureStream : public Assimp::LogStream {
 public:
  explicit CaptureStream(bool errors) : errors_(errors) {}
  void write(const char* message) override {
    // The calling thread's sink (thread_local looked up here, not when attached).
    std::vector<std::string>* out = errors_ ? t_log_errors : t_log_warnings;
    if (out == nullptr || out->size() >= 8) return;
    std::string m = message;
    while (!m.empty() && (m.back() == '\n' || m.back() == '\r')) m.pop_back();
    // Drop assimp's "Error, T0: " / "Warn,  T0: " prefix.
    if (const size_t colon = m.find(": "); colon != std::string::npos && colon < 16) {
      m.erase(0, colon + 2);
    }
    out->push_back(std::move(m));
  }

 private:
  bool errors_;
};

void InstallLogCapture() {
  static const bool installed = [] {
    if (!Assimp::DefaultLogger::isNullLogger()) return false;  // someone else owns the logger
    Assimp::DefaultLogger::create(nullptr, Assimp::Logger::NORMAL, 0);
    Assimp::Logger* logger = Assimp::DefaultLogger::get();
    logger->attachStream(new CaptureStream(true), Assimp::Logger::Err);
    logger->attachStream(new CaptureStream(false), Assimp::Logger::Warn);
    return true;
  }();
  (void)installed;
}

// One importer per thread: constructing one registers every format (~100 us), which matters
// for the fuzz driver's thousands of calls.
Assimp::Importer& ThreadImporter() {
  thread_local Assimp::Importer importer;
  return importer;
}

// Frees the importer's scene when leaving the loader, also on exceptions.
struct SceneRelease {
  Assimp::Importer& importer;
  ~SceneRelease() { importer.FreeScene(); }
};

// Checks the importer's raw meshes and makes aiMesh::mPrimitiveTypes match the faces: some
// importers (OFF with a truncated body) flag polygons that are not there, and assimp's
// triangulation then aborts on an ai_assert.
void CheckRaw(const aiScene& s, const std::string& origin) {
  if (s.mNumMeshes > 0 && s.mMeshes == nullptr) Fail("{}: no mesh data", origin);
  for (unsigned m = 0; m < s.mNumMeshes; ++m) {
    if (s.mMeshes[m] == nullptr) Fail("{}: mesh {} missing", origin, m);
    aiMesh& mesh = *s.mMeshes[m];
    if ((mesh.mNumVertices > 0 && mesh.mVertices == nullptr) ||
        (mesh.mNumFaces > 0 && mesh.mFaces == nullptr)) {
      Fail("{}: mesh {} ('{}'): missing vertex or face data", origin, m, mesh.mName.C_Str());
    }
    unsigned types = 0;
    for (unsigned f = 0; f < mesh.mNumFaces; ++f) {
      const unsigned n = mesh.mFaces[f].mNumIndices;
      if (n == 0 || mesh.mFaces[f].mIndices == nullptr) {
        Fail("{}: mesh {} ('{}'): face {} has no vertices", origin, m, mesh.mName.C_Str(), f);
      }
      types |= n == 1   ? aiPrimitiveType_POINT
               : n == 2 ? aiPrimitiveType_LINE
               : n == 3 ? aiPrimitiveType_TRIANGLE
                        : aiPrimitiveType_POLYGON;
    }
    mesh.mPrimitiveTypes = types;
    for (unsigned i = 0; i < mesh.mNumVertices; ++i) {
      const aiVector3D& p = mesh.mVertices[i];
      if (!std::isfinite(p.x) || !std::isfinite(p.y) || !std::isfinite(p.z)) {
        Fail("{}: mesh {} ('{}'): vertex {}: position ({}, {}, {}) is not finite", origin, m,
             mesh.mName.C_Str(), i, p.x, p.y, p.z);
      }
    }
    for (unsigned f = 0; f < mesh.mNumFaces; ++f) {
      const aiFace& face = mesh.mFaces[f];
      for (unsigned k = 0; k < face.mNumIndices; ++k) {
        if (face.mIndices[k] >= mesh.mNumVertices) {
          Fail("{}: mesh {} ('{}'): face {}: vertex index {} out of range ({} vertices)", origin, m,
               mesh.mName.C_Str(), f, face.mIndices[k], mesh.mNumVertices);
        }
      }
    }
  }
}

Material ConvertMaterial(const aiMaterial& am, const MeshLoadOptions& options) {
  Material out;
  aiString name;
  if (am.Get(AI_MATKEY_NAME, name) == AI_SUCCESS) out.name = name.C_Str();
  aiColor3D c;
  if (am.Get(AI_MATKEY_COLOR_DIFFUSE, c) == AI_SUCCESS) out.diffuse = glm::vec3(c.r, c.g, c.b);
  if (am.Get(AI_MATKEY_COLOR_SPECULAR, c) == AI_SUCCESS) out.specular = glm::vec3(c.r, c.g, c.b);
  out.diffuse = glm::clamp(out.diffuse, 0.0f, 1.0f);
  out.specular = glm::clamp(out.specular, 0.0f, 1.0f);
  float f = 0.0f;
  if (am.Get(AI_MATKEY_SHININESS, f) == AI_SUCCESS && std::isfinite(f)) {
    out.shininess = std::max(f, 0.0f);
  }
  if (am.Get(AI_MATKEY_REFLECTIVITY, f) == AI_SUCCESS && std::isfinite(f)) {
    out.reflectivity = std::clamp(f, 0.0f, 1.0f);
  }
  if (am.Get(AI_MATKEY_OPACITY, f) == AI_SUCCESS && std::isfinite(f) && f < 1.0f) {
    out.transmission = std::clamp(1.0f - f, 0.0f, 1.0f);
  }
  if (am.Get(AI_MATKEY_REFRACTI, f) == AI_SUCCESS && std::isfinite(f) && f > 1.0f) out.ior = f;
  if (options.ks_reflects) {
    out.reflectivity = std::max({out.specular.x, out.specular.y, out.specular.z});
  }
  return out;
}

void Convert(const aiScene& s, const std::string& origin, const std::string& file_dir,
             bool use_file_materials, const MeshLoadOptions& options, Scene& scene,
             MeshGroups* groups) {
  Scene part;
  part.source = origin;
  std::vector<uint32_t> material_of_mesh(s.mNumMeshes, 0);
  if (use_file_materials && s.mNumMaterials > 0) {
    std::map<std::string, int> textures;
    for (unsigned i = 0; i < s.mNumMaterials; ++i) {
      part.materials.push_back(ConvertMaterial(*s.mMaterials[i], options));
      aiString tex;
      if (file_dir.empty() ||
          s.mMaterials[i]->GetTexture(aiTextureType_DIFFUSE, 0, &tex) != AI_SUCCESS ||
          tex.length == 0 || tex.C_Str()[0] == '*') {
        continue;  // none, no file access, or embedded
      }
      const std::string path = JoinPath(file_dir, tex.C_Str());
      auto it = textures.find(path);
      if (it == textures.end()) {
        int index = -1;
        try {
          part.textures.push_back(ReadImage(path));
          index = static_cast<int>(part.textures.size()) - 1;
        } catch (const Error& e) {
          part.warnings.push_back(fmt::format(
              "{}: material {}: texture not loaded ({}); untextured", origin, i, e.what()));
        }
        it = textures.emplace(path, index).first;
      }
      part.materials.back().texture = it->second;
    }
    for (unsigned m = 0; m < s.mNumMeshes; ++m) {
      material_of_mesh[m] = std::min(s.mMeshes[m]->mMaterialIndex, s.mNumMaterials - 1);
    }
  } else {
    Material fallback;
    fallback.name = "default";
    part.materials.push_back(fallback);
  }

  // Which attributes every mesh has: uvs are kept if any mesh has them, normals if all do.
  bool any_uv = false;
  bool all_normals = s.mNumMeshes > 0;
  for (unsigned m = 0; m < s.mNumMeshes; ++m) {
    any_uv |= s.mMeshes[m]->HasTextureCoords(0);
    all_normals &= s.mMeshes[m]->HasNormals();
  }

  std::map<std::string, uint32_t> group_index;
  size_t skipped = 0;
  // Depth-first over the node tree with accumulated transforms.
  struct Item {
    const aiNode* node;
    aiMatrix4x4 transform;
  };
  std::vector<Item> stack;
  if (s.mRootNode) stack.push_back({s.mRootNode, s.mRootNode->mTransformation});
  size_t visited = 0;
  while (!stack.empty()) {
    const Item item = stack.back();
    stack.pop_back();
    if (++visited > 1000000) Fail("{}: node tree too large or cyclic", origin);
    const aiNode& node = *item.node;
    aiMatrix3x3 normal_matrix(item.transform);
    normal_matrix.Inverse().Transpose();
    const bool flip = item.transform.Determinant() < 0.0f;
    for (unsigned k = 0; k < node.mNumMeshes; ++k) {
      if (node.mMeshes[k] >= s.mNumMeshes)
        Fail("{}: node '{}': bad mesh index", origin, node.mName.C_Str());
      const aiMesh& mesh = *s.mMeshes[node.mMeshes[k]];
      const uint32_t base = static_cast<uint32_t>(part.positions.size());
      for (unsigned i = 0; i < mesh.mNumVertices; ++i) {
        const aiVector3D p = item.transform * mesh.mVertices[i];
        part.positions.emplace_back(p.x, p.y, p.z);
        if (any_uv) {
          part.uvs.push_back(mesh.HasTextureCoords(0) ? glm::vec2(mesh.mTextureCoords[0][i].x,
                                                                  mesh.mTextureCoords[0][i].y)
                                                      : glm::vec2(0.0f));
        }
        if (all_normals) {
          aiVector3D n = normal_matrix * mesh.mNormals[i];
          n.Normalize();
          part.normals.emplace_back(n.x, n.y, n.z);
        }
      }
      uint32_t group = 0;
      if (groups) {
        std::string gname = node.mName.C_Str();
        if (gname.empty()) gname = mesh.mName.C_Str();
        const auto [it, inserted] =
            group_index.try_emplace(gname, static_cast<uint32_t>(groups->names.size()));
        if (inserted) groups->names.push_back(gname);
        group = it->second;
      }
      for (unsigned f = 0; f < mesh.mNumFaces; ++f) {
        const aiFace& face = mesh.mFaces[f];
        if (face.mNumIndices != 3) {  // points and lines: nothing to hit
          ++skipped;
          continue;
        }
        glm::uvec3 tri(base + face.mIndices[0], base + face.mIndices[1], base + face.mIndices[2]);
        if (flip) std::swap(tri.y, tri.z);  // mirrored node: keep the winding outward
        part.triangles.push_back(tri);
        part.material_ids.push_back(material_of_mesh[node.mMeshes[k]]);
        if (groups) groups->of_triangle.push_back(group);
      }
    }
    for (unsigned c = 0; c < node.mNumChildren; ++c) {
      stack.push_back({node.mChildren[c], item.transform * node.mChildren[c]->mTransformation});
    }
  }
  if (skipped > 0) {
    part.warnings.push_back(
        fmt::format("{}: {} point or line primitives ignored (not triangles)", origin, skipped));
  }
  if (part.triangles.empty()) Fail("{}: scene has no triangles", origin);
  if (!AnyPositiveArea(part)) {
    Fail("{}: every face has zero area ({} triangles); nothing to render", origin,
         part.triangles.size());
  }
  for (const glm::vec3& n : part.normals) {
    if (!std::isfinite(n.x) || !std::isfinite(n.y) || !std::isfinite(n.z)) {
      part.warnings.push_back(fmt::format("{}: degenerate vertex normal; flat shading", origin));
      part.normals.clear();
      break;
    }
  }
  ValidateSceneAs(part, origin);
  AppendScene(scene, std::move(part));
}

// Runs assimp (raw read, raw checks, post-processing) and converts the result.
void Import(const std::function<const aiScene*(Assimp::Importer&)>& read, const std::string& origin,
            const std::string& file_dir, bool use_file_materials, const MeshLoadOptions& options,
            Scene& scene, MeshGroups* groups) {
  InstallLogCapture();
  std::vector<std::string> log_errors, log_warnings;
  struct LogScope {
    LogScope(std::vector<std::string>* e, std::vector<std::string>* w) {
      t_log_errors = e;
      t_log_warnings = w;
    }
    ~LogScope() {
      t_log_errors = nullptr;
      t_log_warnings = nullptr;
    }
  } log_scope(&log_errors, &log_warnings);
  Assimp::Importer& importer = ThreadImporter();
  SceneRelease release{importer};
  const aiScene* raw = nullptr;
  try {
    raw = read(importer);
  } catch (const std::bad_alloc&) {
    Fail("{}: out of memory while reading (corrupt sizes in the file?)", origin);
  }
  if (raw == nullptr) Fail("{}: {}", origin, importer.GetErrorString());
  if (!log_errors.empty()) Fail("{}: {}", origin, fmt::join(log_errors, "; "));
  for (const std::string& w : log_warnings) {
    scene.warnings.push_back(fmt::format("{}: assimp: {}", origin, w));
  }
  if (raw->mFlags & AI_SCENE_FLAGS_INCOMPLETE) Fail("{}: incomplete scene (no meshes?)", origin);
  CheckRaw(*const_cast<aiScene*>(raw), origin);  // may correct mPrimitiveTypes in place
  const aiScene* s = importer.ApplyPostProcessing(kPostProcess);
  if (s == nullptr) Fail("{}: {}", origin, importer.GetErrorString());
  Convert(*s, origin, file_dir, use_file_materials, options, scene, groups);
}

}  // namespace

void LoadAssimpMemory(std::string_view data, const std::string& origin, const char* hint,
                      const MeshLoadOptions& options, Scene& scene, MeshGroups* groups) {
  if (std::string_view(hint) == "ply") {
    ReadPly(data, origin, scene);  // see ply.cc for why not assimp
    return;
  }
  Import(
      [&](Assimp::Importer& importer) {
        return importer.ReadFileFromMemory(data.data(), data.size(), 0, hint);
      },
      origin, "", true, options, scene, groups);
}

void LoadAssimpFile(const std::string& path, const MeshLoadOptions& options, Scene& scene,
                    MeshGroups* groups) {
  const std::string ext = LowerExtension(path);
  if (ext == "ply") {
    const size_t before = scene.triangles.size();
    ReadPly(ReadFileText(path, "mesh"), path, scene);
    if (groups) {  // PLY has no groups: one unnamed group
      groups->of_triangle.insert(groups->of_triangle.end(), scene.triangles.size() - before,
                                 static_cast<uint32_t>(groups->names.size()));
      groups->names.emplace_back();
    }
    return;
  }
  RegularFileSize(path, "mesh");  // missing, a directory, a FIFO or a device: say which
  std::string dir = DirectoryOf(path);
  if (dir.empty()) dir.push_back('.');  // not = ".": GCC 12 -Wrestrict false positive
  Import([&](Assimp::Importer& importer) { return importer.ReadFile(path, 0); }, path, dir, true,
         options, scene, groups);
}

}  // namespace rs::detail
