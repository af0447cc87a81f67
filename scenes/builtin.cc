// Built-in scene files for the shared meshes (found on the scene search path), as JSON raw
// strings: materials, 4 point lights (as in the iRT paper, where every scene has 4), a camera
// framing the model (outside for objects, inside for rooms) and a ~60-frame walk-through.
// The meshes are used as they are: no extra geometry, so triangle counts match the files.
#include <string_view>

#include "scenes/load.h"

namespace rs {
namespace {

struct BuiltinScene {
  std::string_view name;
  std::string_view json;
};

// Stanford bunny (Y up, ~0.155 m across): glazed porcelain, orbit with a dolly.
constexpr std::string_view kBunny = R"json({
  "name": "bunny",
  "materials": [
    {"name": "porcelain", "diffuse": [0.85, 0.80, 0.72], "specular": 0.5, "shininess": 60,
     "reflectivity": 0.2}
  ],
  "meshes": [{"file": "bunny/bun_zipper.ply", "material": "porcelain"}],
  "lights": [
    {"position": [0.35, 0.45, 0.45], "color": [0.45, 0.43, 0.40]},
    {"position": [-0.45, 0.30, 0.30], "color": [0.25, 0.26, 0.30]},
    {"position": [-0.20, 0.40, -0.45], "color": [0.20, 0.20, 0.22]},
    {"position": [0.10, 0.80, 0.00], "color": [0.15, 0.15, 0.15]}
  ],
  "camera": {"eye": [-0.017, 0.15, 0.30], "look_at": [-0.017, 0.105, 0.0], "fov": 50},
  "path": {"frames": 60, "keys": [
    {"eye": [-0.017, 0.15, 0.30], "look_at": [-0.017, 0.105, 0.0]},
    {"eye": [0.20, 0.19, 0.19], "look_at": [-0.02, 0.11, 0.0]},
    {"eye": [0.27, 0.12, -0.05], "look_at": [-0.03, 0.10, 0.0]},
    {"eye": [0.10, 0.22, -0.24], "look_at": [-0.02, 0.11, 0.0]},
    {"eye": [-0.22, 0.16, -0.18], "look_at": [-0.01, 0.11, 0.01]},
    {"eye": [-0.25, 0.10, 0.12], "look_at": [-0.02, 0.10, 0.0]},
    {"eye": [-0.06, 0.17, 0.22], "look_at": [-0.017, 0.11, 0.0]}
  ]},
  "background": [0.10, 0.12, 0.16],
  "ambient": 0.1
})json";

// Utah teapot (Y up, 6.4 x 3.15 x 4): glossy red glaze, orbit.
constexpr std::string_view kTeapot = R"json({
  "name": "teapot",
  "materials": [
    {"name": "glaze", "diffuse": [0.70, 0.12, 0.10], "specular": 0.8, "shininess": 100,
     "reflectivity": 0.25}
  ],
  "meshes": [{"file": "teapot/teapot.obj", "material": "glaze"}],
  "lights": [
    {"position": [6.0, 8.0, 8.0], "color": [0.45, 0.43, 0.40]},
    {"position": [-8.0, 5.0, 5.0], "color": [0.25, 0.26, 0.30]},
    {"position": [-4.0, 7.0, -8.0], "color": [0.20, 0.20, 0.22]},
    {"position": [1.0, 12.0, 0.0], "color": [0.15, 0.15, 0.15]}
  ],
  "camera": {"eye": [0.2, 4.6, 8.6], "look_at": [0.2, 1.4, 0.0], "fov": 50},
  "path": {"frames": 60, "keys": [
    {"eye": [0.2, 4.6, 8.6], "look_at": [0.2, 1.4, 0.0]},
    {"eye": [6.5, 3.5, 5.5], "look_at": [0.3, 1.5, 0.0]},
    {"eye": [8.0, 5.5, -2.0], "look_at": [0.0, 1.3, 0.0]},
    {"eye": [1.0, 7.5, -7.5], "look_at": [0.2, 1.2, 0.0]},
    {"eye": [-6.5, 3.0, -4.5], "look_at": [0.4, 1.6, 0.2]},
    {"eye": [-7.0, 4.5, 4.0], "look_at": [0.2, 1.5, 0.0]},
    {"eye": [-1.5, 3.0, 6.5], "look_at": [0.2, 1.6, 0.0]}
  ]},
  "background": [0.12, 0.12, 0.14],
  "ambient": 0.1
})json";

// Dabrovic Sponza atrium (Y up, 34.8 x 16.6 x 15.6): no MTL in the file, so materials are
// assigned by OBJ group; the floor is polished (reflective). Walk along the atrium.
constexpr std::string_view kSponza = R"json({
  "name": "sponza",
  "materials": [
    {"name": "sandstone", "diffuse": [0.78, 0.70, 0.56]},
    {"name": "floor", "diffuse": [0.55, 0.50, 0.42], "specular": 0.3, "shininess": 40,
     "reflectivity": 0.3},
    {"name": "pillar", "diffuse": [0.85, 0.80, 0.70], "specular": 0.2, "shininess": 30,
     "reflectivity": 0.1},
    {"name": "arcs", "diffuse": [0.80, 0.72, 0.60]},
    {"name": "relief", "diffuse": [0.70, 0.66, 0.60]},
    {"name": "wood", "diffuse": [0.45, 0.28, 0.15], "specular": 0.2, "shininess": 20},
    {"name": "window", "diffuse": [0.30, 0.35, 0.40], "reflectivity": 0.5, "specular": 0.8,
     "shininess": 150},
    {"name": "roof", "diffuse": [0.60, 0.30, 0.20]}
  ],
  "meshes": [{"file": "sponza/sponza.obj", "material": "sandstone",
              "group_materials": {"floors": "floor", "pillar*": "pillar", "puillar*": "pillar",
                                  "arcs*": "arcs", "relief": "relief", "doors": "wood",
                                  "windows": "window", "ceiling": "roof"}}],
  "lights": [
    {"position": [-10.0, 12.0, 0.0], "color": [0.32, 0.30, 0.27]},
    {"position": [0.0, 13.0, 0.0], "color": [0.32, 0.30, 0.27]},
    {"position": [10.0, 12.0, 0.0], "color": [0.32, 0.30, 0.27]},
    {"position": [0.0, 4.0, 0.0], "color": [0.15, 0.15, 0.16]}
  ],
  "camera": {"eye": [-14.0, 3.0, 0.0], "look_at": [0.0, 5.0, 0.0], "fov": 60},
  "path": {"frames": 60, "keys": [
    {"eye": [-14.0, 3.0, 0.0], "look_at": [0.0, 5.0, 0.0]},
    {"eye": [-8.0, 2.0, -2.5], "look_at": [2.0, 6.0, 3.0]},
    {"eye": [-1.0, 1.8, 2.5], "look_at": [8.0, 4.0, -3.0]},
    {"eye": [6.0, 5.5, -2.0], "look_at": [-5.0, 3.0, 2.0]},
    {"eye": [12.0, 2.5, 1.5], "look_at": [0.0, 8.0, -1.0]},
    {"eye": [14.0, 3.0, 0.0], "look_at": [0.0, 4.0, 0.0]}
  ]},
  "background": [0.45, 0.60, 0.85],
  "ambient": 0.12
})json";

// TU Graz office (Z up, 5.6 x 5.0 x 2.66 m) with its MTL; Ks is the mirror coefficient as in
// the iRT paper ("ks_reflects"). Walk through the room.
constexpr std::string_view kOfficeGraz = R"json({
  "name": "office-graz",
  "meshes": [{"file": "office-graz/office-graz.obj", "ks_reflects": true}],
  "lights": [
    {"position": [1.4, 1.2, 2.4], "color": [0.30, 0.29, 0.27]},
    {"position": [3.8, 1.2, 2.4], "color": [0.30, 0.29, 0.27]},
    {"position": [1.4, 3.4, 2.4], "color": [0.30, 0.29, 0.27]},
    {"position": [3.8, 3.4, 2.4], "color": [0.30, 0.29, 0.27]}
  ],
  "camera": {"eye": [4.7, 0.35, 1.7], "look_at": [2.0, 3.0, 0.8], "up": [0, 0, 1], "fov": 60},
  "path": {"frames": 60, "keys": [
    {"eye": [4.7, 0.35, 1.7], "look_at": [2.0, 3.0, 0.8]},
    {"eye": [3.5, 0.3, 1.5], "look_at": [1.0, 3.5, 1.0]},
    {"eye": [1.7, 0.93, 1.53], "look_at": [1.72, 1.92, 1.4]},
    {"eye": [0.5, 1.5, 1.8], "look_at": [4.0, 3.5, 0.7]},
    {"eye": [0.6, 4.0, 1.4], "look_at": [4.5, 1.0, 1.0]},
    {"eye": [2.2, 0.45, 1.8], "look_at": [2.6, 4.0, 0.9]}
  ]},
  "background": [0.0, 0.0, 0.0],
  "ambient": 0.12
})json";

// Conference room (Y up, model units; 2706 x 653 x 1724): one material (the mesh has none),
// lights under the ceiling, walk around the table.
constexpr std::string_view kConference = R"json({
  "name": "conference",
  "materials": [
    {"name": "room", "diffuse": [0.62, 0.56, 0.48], "specular": 0.2, "shininess": 20,
     "reflectivity": 0.12}
  ],
  "meshes": [{"file": "conference/conference.obj", "material": "room"}],
  "lights": [
    {"position": [-400.0, 580.0, -600.0], "color": [0.30, 0.29, 0.27]},
    {"position": [1100.0, 580.0, -600.0], "color": [0.30, 0.29, 0.27]},
    {"position": [-400.0, 580.0, 300.0], "color": [0.30, 0.29, 0.27]},
    {"position": [1100.0, 580.0, 300.0], "color": [0.30, 0.29, 0.27]}
  ],
  "camera": {"eye": [1550.0, 380.0, 500.0], "look_at": [200.0, 150.0, -300.0], "fov": 60},
  "path": {"frames": 60, "keys": [
    {"eye": [1550.0, 380.0, 500.0], "look_at": [200.0, 150.0, -300.0]},
    {"eye": [900.0, 300.0, 550.0], "look_at": [0.0, 180.0, -700.0]},
    {"eye": [-100.0, 420.0, 450.0], "look_at": [900.0, 120.0, -500.0]},
    {"eye": [-300.0, 300.0, -50.0], "look_at": [1000.0, 180.0, -200.0]},
    {"eye": [-300.0, 450.0, -650.0], "look_at": [900.0, 100.0, 300.0]},
    {"eye": [1400.0, 320.0, -700.0], "look_at": [0.0, 150.0, 300.0]}
  ]},
  "background": [0.0, 0.0, 0.0],
  "ambient": 0.12
})json";

// Sibenik cathedral (Y up, 40.3 x 30.6 x 17; nave along x, floor at y = -15.3): stone,
// lights along the nave, walk down the nave.
constexpr std::string_view kSibenik = R"json({
  "name": "sibenik",
  "materials": [
    {"name": "stone", "diffuse": [0.78, 0.74, 0.66], "specular": 0.15, "shininess": 20,
     "reflectivity": 0.1}
  ],
  "meshes": [{"file": "sibenik/sibenik.obj", "material": "stone"}],
  "lights": [
    {"position": [-12.0, -4.0, 0.0], "color": [0.30, 0.29, 0.27]},
    {"position": [-2.0, -2.0, 0.0], "color": [0.30, 0.29, 0.27]},
    {"position": [8.0, -4.0, 0.0], "color": [0.30, 0.29, 0.27]},
    {"position": [0.0, 6.0, 0.0], "color": [0.20, 0.20, 0.22]}
  ],
  "camera": {"eye": [-17.0, -10.5, 0.0], "look_at": [10.0, -9.0, 0.0], "fov": 60},
  "path": {"frames": 60, "keys": [
    {"eye": [-17.0, -10.5, 0.0], "look_at": [10.0, -9.0, 0.0]},
    {"eye": [-11.0, -12.0, 3.5], "look_at": [5.0, -6.0, -3.0]},
    {"eye": [-4.0, -13.0, -3.5], "look_at": [6.0, -2.0, 3.0]},
    {"eye": [3.0, -9.0, 0.0], "look_at": [-10.0, -7.0, 0.0]},
    {"eye": [8.0, -12.5, 2.5], "look_at": [18.0, -8.0, -1.0]},
    {"eye": [12.0, -11.0, 0.0], "look_at": [-15.0, -5.0, 0.0]}
  ]},
  "background": [0.0, 0.0, 0.0],
  "ambient": 0.12
})json";

constexpr BuiltinScene kBuiltins[] = {{"bunny", kBunny},
                                      {"teapot", kTeapot},
                                      {"sponza", kSponza},
                                      {"office-graz", kOfficeGraz},
                                      {"conference", kConference},
                                      {"sibenik", kSibenik}};

}  // namespace

std::string_view BuiltinSceneJson(std::string_view name) {
  for (const BuiltinScene& s : kBuiltins) {
    if (s.name == name) return s.json;
  }
  return {};
}

}  // namespace rs
