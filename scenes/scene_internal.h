// Helpers shared by the scene loaders (scenes/*.cc only, not part of the library API): error
// formatting, text positions, appending meshes, default cameras, and the per-format entry points.
#pragma once

#include <fmt/format.h>

#include <cstddef>
#include <cstdint>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "include/raystream/raystream.h"
#include "scenes/scene.h"

namespace rs::detail {

// Throws rs::Error with an fmt-formatted message.
template <typename... Args>
[[noreturn]] void Fail(fmt::format_string<Args...> format, Args&&... args) {
  throw Error(fmt::format(format, std::forward<Args>(args)...));
}

// Coordinates beyond this magnitude are rejected: grid setup squares extents, and 1e30^2 still
// fits a float's range while bigger values overflow to inf.
inline constexpr float kMaxCoordinate = 1e18f;

// 1-based line and column of byte offset `byte` in `text` (offsets past the end: last position).
struct TextPosition {
  size_t line = 1;
  size_t column = 1;
};
TextPosition PositionOfByte(std::string_view text, size_t byte);

// "a directory", "a named pipe (FIFO)", "a character device", ... for a stat() st_mode.
const char* FileTypeName(unsigned mode);
// Size of the regular file `path`. Throws rs::Error "<path>: <reason>" when it does not exist,
// cannot be accessed, or is not a regular file ("<path>: is a directory, not a <what> file").
uint64_t RegularFileSize(const std::string& path, std::string_view what);
// Reads a whole regular file; throws rs::Error naming `path` (and saying why: missing, a
// directory, a FIFO or device, unreadable) if it cannot be read.
std::string ReadFileText(const std::string& path, std::string_view what = "scene");
// Lower-case extension without the dot ("ply"), or "".
std::string LowerExtension(std::string_view path);
// Directory part of a path ("a/b.obj" -> "a", "b.obj" -> "").
std::string DirectoryOf(std::string_view path);
// Joins a directory and a relative path; absolute `rel` is returned unchanged.
std::string JoinPath(std::string_view dir, std::string_view rel);
bool IsRegularFile(const std::string& path);
// Resolves `rel` against `base_dir` first (when non-empty), then FindSceneFile.
std::string ResolveRelative(std::string_view rel, const std::string& base_dir);

// Options a scene file may set for one mesh file.
struct MeshLoadOptions {
  // iRT convention (workload-distribution paper): a material's specular coefficient Ks is its
  // mirror reflectivity (max component, clamped to [0, 1]).
  bool ks_reflects = false;
};

// Group names per triangle, as named in the file (OBJ 'g'/'o', assimp node and mesh names), so a
// scene file can assign materials by group. `of_triangle` has one entry per appended triangle.
struct MeshGroups {
  std::vector<std::string> names;
  std::vector<uint32_t> of_triangle;
};

// Format loaders. `origin` names the text in messages. Each appends to `scene` (materials,
// textures appended with offsets) and validates what it appended; an input without triangles
// is an error ("<origin>: scene has no triangles"). `groups` may be null.
// `file_dir`: directory for mtllib and texture files; empty means no file access (fuzzing).
void ParseObj(std::string_view text, const std::string& origin, const std::string& file_dir,
              const MeshLoadOptions& options, Scene& scene, MeshGroups* groups);
void LoadObjFile(const std::string& path, const MeshLoadOptions& options, Scene& scene,
                 MeshGroups* groups);
// One MTL material library from memory (`origin` names it in "<origin>:<line>: ..." errors):
// strict values, converted as for an OBJ; appends one Material per "newmtl".
void ParseMtl(std::string_view text, const std::string& origin, std::vector<Material>& out);
// Strict PLY reader (ASCII and binary): header, counts, numbers, finite coordinates and index
// ranges are checked, naming the line (ASCII) or element (binary). Used for PLY instead of
// assimp, which silently accepts truncated files, NaN vertices and out-of-range indices,
// misreads some binary files and aborts on some malformed faces (see ply.cc).
void ReadPly(std::string_view data, const std::string& origin, Scene& scene);
// `hint` "ply" is routed to ReadPly; other formats go through assimp.
void LoadAssimpMemory(std::string_view data, const std::string& origin, const char* hint,
                      const MeshLoadOptions& options, Scene& scene, MeshGroups* groups);
void LoadAssimpFile(const std::string& path, const MeshLoadOptions& options, Scene& scene,
                    MeshGroups* groups);

// Appends `part` to `scene`: vertex indices, material ids and texture indices are offset. UVs
// are kept if either side has them (missing ones become (0, 0)); normals only if both have them
// (or `scene` is empty). Warnings are appended.
void AppendScene(Scene& scene, Scene&& part);

// True if some triangle of `scene` has a non-zero area (|cross| > 0 in float). A mesh without
// one draws nothing: the loaders report it instead of rendering an empty image.
bool AnyPositiveArea(const Scene& scene);

// Normalises scene.normals; zero-length or non-finite ones are replaced by the face normal of
// a triangle using the vertex (or +y for vertices on zero-area triangles only). Returns how many
// were replaced.
size_t RepairNormals(Scene& scene);

// Checks `scene` like ValidateScene, naming `label` instead of scene.source.
void ValidateSceneAs(const Scene& scene, const std::string& label);

// Default set-up for a bare mesh: camera looking at the centre of the bounds from +z with a
// 60 degree field of view, framing the bounding sphere; one white light above and in front;
// a 60-frame orbit path of 90 degrees around the vertical axis (`up`).
void SetDefaultView(Scene& scene, const glm::vec3& up = glm::vec3(0, 1, 0));

// Procedural scenes ("erw6", "spherebox", "amphitheater:N", "cornell"). Returns false if
// `name` is not procedural; throws rs::Error for a bad parameter.
bool MakeProceduralScene(std::string_view name, Scene& scene);

// Computes features and validates; used by every top-level loader.
void FinishScene(Scene& scene);

}  // namespace rs::detail
