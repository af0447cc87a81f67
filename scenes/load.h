// Finding and loading scenes by name: built-in procedural scenes, built-in scene files for
// the shared meshes, and user files (.json scene files, .obj + .mtl, .ply and what assimp reads).
#pragma once

#include <string>
#include <string_view>
#include <vector>

#include "scenes/scene.h"

namespace rs {

// The scene the `raystream render` command draws when no --scene is given. Procedural, so a
// fresh clone renders without any file beside it.
inline constexpr const char* kDefaultScene = "erw6";

// Directories searched for scene files, in order: $RAYSTREAM_SCENES (colon-separated), then
// the shared scenes directory next to the source tree when it exists (baked in at build time).
std::vector<std::string> SceneSearchPath();

// Resolves a relative file name against SceneSearchPath() (absolute or ./-relative paths are
// used as given). Throws rs::Error listing the directories tried when not found.
std::string FindSceneFile(std::string_view file);

// Loads a scene by name or path:
//   procedural: "erw6", "spherebox", "amphitheater:N" (N >= 1), "cornell" ...
//   built-in scene files: "bunny", "teapot", "sponza", "office-graz", "conference", "sibenik"
//   files: "*.json" (raystream scene file), "*.obj", "*.ply" and other assimp formats.
// Meshes given bare get a default camera (framing the bounds), material, light and path.
// The result is validated (ValidateScene) and has features computed. Throws rs::Error.
Scene LoadScene(std::string_view name_or_path);

// Names of the procedural and built-in scenes, for --help and tests.
std::vector<std::string> ProceduralSceneNames();
std::vector<std::string> BuiltinSceneFileNames();
// The JSON text of a built-in scene file ("bunny"), or empty if there is none.
std::string_view BuiltinSceneJson(std::string_view name);

// Lower-level loaders, each appending into `scene` (materials appended, ids offset).
// All throw rs::Error naming the file and the line or element on malformed input.
void LoadObj(const std::string& path, Scene& scene);
// .ply and others: PLY goes through raystream's strict PLY reader (scenes/ply.cc: assimp 5.2.4
// accepts broken PLYs silently), everything else through assimp (its logged errors are fatal).
void LoadWithAssimp(const std::string& path, Scene& scene);
// Parses a raystream scene file (format in scenes/scene_json.cc); relative mesh paths resolve
// against the file's directory, then the search path. `origin` names the text in messages;
// errors carry the JSON pointer of the element or line:column of a syntax error.
Scene LoadSceneJson(std::string_view json_text, const std::string& origin,
                    const std::string& base_dir);

// Parsing from memory, for the fuzz targets (same checks, no file system).
void ParseObjText(std::string_view obj_text, const std::string& origin, Scene& scene);
void ParsePlyText(std::string_view ply_text, const std::string& origin, Scene& scene);
// An MTL material library from memory, converted as for an OBJ (one Material per "newmtl");
// values parsed strictly, errors "<origin>:<line>: ...".
std::vector<Material> ParseMtlText(std::string_view mtl_text, const std::string& origin);
// A scene file from memory with no file access: mesh entries naming a "file" are an error,
// built-in primitives ("box", "quad", "sphere") are fine. Validated, features computed.
Scene ParseSceneJsonText(std::string_view json_text, const std::string& origin);

}  // namespace rs
