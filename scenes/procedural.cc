// Procedural scenes that need no file: "erw6" (the PBT paper's small room, the default scene),
// "spherebox" (the Cell paper's incoherent-ray test), "amphitheater:N" (the PBT paper's
// spatial-coherence series), "cornell" (a tiny room for fast tests) and "farsphere" /
// "nearsphere" (issue 13's closed sphere of 81,920 triangles far from the origin, and the same
// scene at the origin). Deterministic: only fixed arithmetic and the integer hash in
// mesh_builder.h, never std:: random distributions.
#include <fmt/format.h>

#include <algorithm>
#include <charconv>
#include <cmath>
#include <glm/gtc/matrix_transform.hpp>
#include <numbers>

#include "scenes/icosphere.h"
#include "scenes/mesh_builder.h"
#include "scenes/scene_internal.h"

namespace rs::detail {
namespace {

constexpr float kPi = std::numbers::pi_v<float>;

Material Mat(const char* name, glm::vec3 diffuse, float reflectivity = 0.0f,
             glm::vec3 specular = glm::vec3(0.0f), float shininess = 0.0f) {
  Material m;
  m.name = name;
  m.diffuse = diffuse;
  m.reflectivity = reflectivity;
  m.specular = specular;
  m.shininess = shininess;
  return m;
}

Camera Cam(glm::vec3 eye, glm::vec3 look_at, float fov = 60.0f, glm::vec3 up = {0, 1, 0}) {
  Camera c;
  c.eye = eye;
  c.look_at = look_at;
  c.up = up;
  c.fov_y_deg = fov;
  return c;
}

glm::mat4 Place(glm::vec3 position, float yaw_deg) {
  return glm::rotate(glm::translate(glm::mat4(1.0f), position), glm::radians(yaw_deg),
                     glm::vec3(0, 1, 0));
}

// ERW6-like room (PBT paper, Figure 1): ~1100 triangles, diffuse walls in four colours, a
// reflective checkered floor, a reflective table and chairs, four lights under the ceiling.
void MakeErw6(Scene& scene) {
  MeshBuilder b(scene, /*with_normals=*/true);
  const uint32_t cream = b.AddMaterial(Mat("wall_cream", {0.85f, 0.80f, 0.68f}));
  const uint32_t blue = b.AddMaterial(Mat("wall_blue", {0.42f, 0.55f, 0.78f}));
  const uint32_t green = b.AddMaterial(Mat("wall_green", {0.52f, 0.70f, 0.50f}));
  const uint32_t rose = b.AddMaterial(Mat("wall_rose", {0.82f, 0.56f, 0.52f}));
  const uint32_t ceiling = b.AddMaterial(Mat("ceiling", {0.92f, 0.92f, 0.90f}));
  const uint32_t floor_light =
      b.AddMaterial(Mat("floor_light", {0.78f, 0.74f, 0.66f}, 0.35f, glm::vec3(0.3f), 60.0f));
  const uint32_t floor_dark =
      b.AddMaterial(Mat("floor_dark", {0.22f, 0.20f, 0.19f}, 0.35f, glm::vec3(0.3f), 60.0f));
  const uint32_t wood =
      b.AddMaterial(Mat("table_wood", {0.50f, 0.28f, 0.13f}, 0.5f, glm::vec3(0.6f), 80.0f));
  const uint32_t chair =
      b.AddMaterial(Mat("chair_lacquer", {0.72f, 0.12f, 0.10f}, 0.45f, glm::vec3(0.7f), 100.0f));
  const uint32_t chrome =
      b.AddMaterial(Mat("chrome", {0.30f, 0.30f, 0.32f}, 0.8f, glm::vec3(0.9f), 200.0f));
  const uint32_t lamp = b.AddMaterial(Mat("lamp", {1.0f, 1.0f, 0.95f}));
  const uint32_t mirror_ball =
      b.AddMaterial(Mat("mirror_ball", {0.08f, 0.08f, 0.1f}, 0.9f, glm::vec3(1.0f), 300.0f));
  const uint32_t cabinet =
      b.AddMaterial(Mat("cabinet", {0.33f, 0.38f, 0.50f}, 0.3f, glm::vec3(0.4f), 40.0f));
  const uint32_t vase =
      b.AddMaterial(Mat("vase", {0.10f, 0.35f, 0.45f}, 0.4f, glm::vec3(0.8f), 120.0f));
  const uint32_t picture = b.AddMaterial(Mat("picture", {0.90f, 0.62f, 0.20f}));

  constexpr float kW = 3.0f;  // half width (x and z)
  constexpr float kH = 2.7f;  // ceiling height
  // Floor (checkered, facing up), ceiling (facing down), four walls facing inward.
  b.Quad({-kW, 0, kW}, {kW, 0, kW}, {kW, 0, -kW}, {-kW, 0, -kW}, floor_light, 10, 10, floor_dark);
  b.Quad({-kW, kH, -kW}, {kW, kH, -kW}, {kW, kH, kW}, {-kW, kH, kW}, ceiling, 4, 4);
  b.Quad({-kW, 0, -kW}, {kW, 0, -kW}, {kW, kH, -kW}, {-kW, kH, -kW}, cream, 6, 3);  // back
  b.Quad({kW, 0, kW}, {-kW, 0, kW}, {-kW, kH, kW}, {kW, kH, kW}, blue, 6, 3);       // front
  b.Quad({-kW, 0, kW}, {-kW, 0, -kW}, {-kW, kH, -kW}, {-kW, kH, kW}, green, 6, 3);  // left
  b.Quad({kW, 0, -kW}, {kW, 0, kW}, {kW, kH, kW}, {kW, kH, -kW}, rose, 6, 3);       // right

  // Table: top and four legs.
  b.Box({-0.9f, 0.72f, -0.55f}, {0.9f, 0.78f, 0.55f}, wood);
  for (const float x : {-0.8f, 0.74f}) {
    for (const float z : {-0.48f, 0.42f}) b.Box({x, 0.0f, z}, {x + 0.06f, 0.72f, z + 0.06f}, wood);
  }
  // Four chairs (8 boxes each), two per long side, facing the table; slightly turned.
  const struct {
    glm::vec3 position;
    float yaw;
  } chairs[] = {{{-0.45f, 0, 0.85f}, 6.0f},
                {{0.5f, 0, 0.9f}, -9.0f},
                {{-0.5f, 0, -0.88f}, 174.0f},
                {{0.45f, 0, -0.85f}, 189.0f}};
  for (const auto& c : chairs) {
    b.SetTransform(Place(c.position, c.yaw));
    b.Box({-0.22f, 0.44f, -0.22f}, {0.22f, 0.49f, 0.22f}, chair);  // seat
    for (const float x : {-0.21f, 0.17f}) {
      for (const float z : {-0.21f, 0.17f}) {
        b.Box({x, 0.0f, z}, {x + 0.04f, 0.44f, z + 0.04f}, chrome);  // legs
      }
    }
    for (const float x : {-0.21f, 0.17f}) {
      b.Box({x, 0.49f, 0.17f}, {x + 0.04f, 0.95f, 0.21f}, chrome);  // back posts
    }
    b.Box({-0.17f, 0.66f, 0.175f}, {0.17f, 0.92f, 0.205f}, chair);  // back rest
  }
  b.SetTransform(glm::mat4(1.0f));
  // On the table: a mirror ball; against the back wall: a cabinet with a vase.
  b.Sphere({0.3f, 0.93f, 0.08f}, 0.15f, 12, 8, mirror_ball);
  b.Box({-2.2f, 0.0f, -3.0f}, {-0.8f, 1.1f, -2.55f}, cabinet);
  b.Cylinder({-1.5f, 1.1f, -2.78f}, 0.12f, 0.35f, 16, vase);
  // Picture on the left wall; lamp housings under the ceiling above the four lights.
  b.Box({-3.0f, 1.2f, -0.8f}, {-2.97f, 1.9f, 0.8f}, picture);
  const glm::vec3 light_pos[4] = {
      {-1.5f, 2.45f, -1.5f}, {1.5f, 2.45f, -1.5f}, {-1.5f, 2.45f, 1.5f}, {1.5f, 2.45f, 1.5f}};
  for (const glm::vec3& p : light_pos) {
    b.Box({p.x - 0.2f, 2.62f, p.z - 0.2f}, {p.x + 0.2f, kH, p.z + 0.2f}, lamp);
    PointLight light;
    light.position = p;
    light.color = glm::vec3(0.30f, 0.29f, 0.27f);
    scene.lights.push_back(light);
  }

  scene.camera = Cam({2.3f, 1.55f, 2.4f}, {0.0f, 0.75f, 0.0f});
  // Walk-through with translations in all directions and turns (PBT paper, Section 5).
  scene.path.frames = 60;
  scene.path.keys = {
      Cam({2.3f, 1.55f, 2.4f}, {0.0f, 0.75f, 0.0f}), Cam({0.4f, 1.7f, 2.5f}, {-0.6f, 0.7f, -0.5f}),
      Cam({-2.2f, 1.3f, 1.8f}, {0.4f, 0.8f, -1.0f}), Cam({-2.4f, 1.9f, -1.2f}, {0.8f, 0.6f, 0.6f}),
      Cam({-0.2f, 1.2f, -2.3f}, {0.3f, 0.9f, 1.5f}), Cam({2.2f, 1.6f, -1.6f}, {-0.5f, 0.7f, 0.8f})};
  scene.background = glm::vec3(0.0f);
  scene.ambient = 0.1f;
}

// Spherebox (Cell paper, Figure 7): a closed box with the camera inside, filled with 48 mirror
// and glass spheres (1024 triangles each): ~50k triangles and many incoherent secondary rays.
void MakeSphereBox(Scene& scene) {
  MeshBuilder b(scene, /*with_normals=*/true);
  const uint32_t floor_a = b.AddMaterial(Mat("floor_a", {0.80f, 0.80f, 0.78f}));
  const uint32_t floor_b = b.AddMaterial(Mat("floor_b", {0.15f, 0.15f, 0.18f}));
  const uint32_t wall_red = b.AddMaterial(Mat("wall_red", {0.75f, 0.25f, 0.20f}));
  const uint32_t wall_blue = b.AddMaterial(Mat("wall_blue", {0.22f, 0.35f, 0.75f}));
  const uint32_t wall_white = b.AddMaterial(Mat("wall_white", {0.80f, 0.80f, 0.80f}));
  const uint32_t wall_yellow = b.AddMaterial(Mat("wall_yellow", {0.85f, 0.75f, 0.30f}));
  uint32_t mirror[3], glass[2];
  mirror[0] = b.AddMaterial(Mat("mirror_gold", {0.25f, 0.18f, 0.05f}, 0.85f, glm::vec3(0.9f), 120));
  mirror[1] = b.AddMaterial(Mat("mirror_silver", {0.1f, 0.1f, 0.1f}, 0.9f, glm::vec3(1.0f), 200));
  mirror[2] = b.AddMaterial(Mat("mirror_teal", {0.05f, 0.2f, 0.2f}, 0.8f, glm::vec3(0.9f), 120));
  for (int g = 0; g < 2; ++g) {
    Material m = Mat(g == 0 ? "glass_clear" : "glass_tinted",
                     g == 0 ? glm::vec3(0.9f) : glm::vec3(0.6f, 0.85f, 0.7f), 0.08f,
                     glm::vec3(1.0f), 250.0f);
    m.transmission = 0.9f;
    m.ior = 1.5f;
    glass[g] = b.AddMaterial(m);
  }
  constexpr float kS = 5.0f;   // half size in x and z
  constexpr float kH = 10.0f;  // height
  b.Quad({-kS, 0, kS}, {kS, 0, kS}, {kS, 0, -kS}, {-kS, 0, -kS}, floor_a, 8, 8, floor_b);
  b.Quad({-kS, kH, -kS}, {kS, kH, -kS}, {kS, kH, kS}, {-kS, kH, kS}, wall_white, 8, 8);
  b.Quad({-kS, 0, -kS}, {kS, 0, -kS}, {kS, kH, -kS}, {-kS, kH, -kS}, wall_white, 8, 8);
  b.Quad({kS, 0, kS}, {-kS, 0, kS}, {-kS, kH, kS}, {kS, kH, kS}, wall_yellow, 8, 8);
  b.Quad({-kS, 0, kS}, {-kS, 0, -kS}, {-kS, kH, -kS}, {-kS, kH, kS}, wall_red, 8, 8);
  b.Quad({kS, 0, -kS}, {kS, 0, kS}, {kS, kH, kS}, {kS, kH, -kS}, wall_blue, 8, 8);
  // 4 x 3 x 4 spheres; spacing >= 1.9, radius <= 0.7 and jitter <= 0.15 keep them apart.
  uint64_t index = 0;
  for (int iy = 0; iy < 3; ++iy) {
    for (int iz = 0; iz < 4; ++iz) {
      for (int ix = 0; ix < 4; ++ix, ++index) {
        const glm::vec3 jitter(SceneHashUnit(1, index) - 0.5f, SceneHashUnit(2, index) - 0.5f,
                               SceneHashUnit(3, index) - 0.5f);
        const glm::vec3 center(-3.6f + 2.4f * static_cast<float>(ix),
                               1.1f + 2.6f * static_cast<float>(iy),
                               -4.0f + 1.9f * static_cast<float>(iz));
        const float radius = 0.5f + 0.2f * SceneHashUnit(4, index);
        const uint32_t kind = static_cast<uint32_t>(SceneHash64(index * 7 + 5) % 5);
        const uint32_t material = kind < 3 ? mirror[kind] : glass[kind - 3];
        b.Sphere(center + 0.3f * jitter, radius, 32, 17, material);
      }
    }
  }
  for (const glm::vec3 p : {glm::vec3(-2.5f, 9.3f, 2.5f), glm::vec3(2.5f, 9.3f, -2.5f)}) {
    PointLight light;
    light.position = p;
    light.color = glm::vec3(0.55f);
    scene.lights.push_back(light);
  }
  scene.camera = Cam({0.0f, 5.5f, 4.6f}, {0.0f, 4.5f, -1.5f});
  scene.path.frames = 60;
  scene.path.keys = {
      Cam({0.0f, 5.5f, 4.6f}, {0.0f, 4.5f, -1.5f}),  Cam({3.8f, 7.5f, 4.2f}, {-1.0f, 4.0f, -1.5f}),
      Cam({4.4f, 3.0f, 3.5f}, {-1.5f, 5.0f, -2.0f}), Cam({0.0f, 2.0f, 4.5f}, {0.0f, 6.0f, -2.0f}),
      Cam({-4.2f, 6.0f, 4.0f}, {1.5f, 3.5f, -2.0f}), Cam({-2.0f, 8.5f, 4.4f}, {0.5f, 3.5f, -1.0f})};
  scene.background = glm::vec3(0.0f);
  scene.ambient = 0.1f;
}

// Amphitheater geometry parameters; one copy has exactly kAmphitheaterTriangles triangles
// (PBT paper Table 2: "1 Amphitheater" = 29,759 with the shared ground quad).
constexpr int kTiers = 30;         // rows of seats
constexpr int kArcSegments = 186;  // segments along the seating arc
constexpr int kAisles = 7;         // radial stairways
constexpr int kPorticoColumns = 40;
constexpr int kStageColumns = 12;  // per storey, two storeys
constexpr int kOrchestraSegments = 110;
constexpr float kTierDepth = 0.8f;
constexpr float kTierRise = 0.4f;
constexpr float kInnerRadius = 8.5f;
constexpr float kArc0 = -0.12f;  // seating arc, radians from +x towards -z
constexpr float kArc1 = kPi + 0.12f;

float OuterRadius() { return kInnerRadius + kTiers * kTierDepth; }

void AddAmphitheater(MeshBuilder& b, const glm::vec3& origin, uint32_t stone, uint32_t seat,
                     uint32_t marble, uint32_t plaster) {
  b.SetTransform(glm::translate(glm::mat4(1.0f), origin));
  const glm::vec3 c(0.0f);
  // Orchestra: a paved ring 2 cm above the ground (no coplanar faces) and the altar covering
  // its centre.
  b.RingSector({0.0f, 0.02f, 0.0f}, 0.5f, kInnerRadius, 0.0f, 2.0f * kPi, kOrchestraSegments,
               marble);
  b.Cylinder(c, 0.6f, 0.9f, 16, marble);
  // Tiers: riser (facing the stage) and tread, each tier a step up and back.
  for (int k = 0; k < kTiers; ++k) {
    const float r = kInnerRadius + static_cast<float>(k) * kTierDepth;
    const float y1 = static_cast<float>(k + 1) * kTierRise;
    b.WallSector(c, r, y1 - kTierRise, y1, kArc0, kArc1, kArcSegments, stone, /*inward=*/true);
    b.RingSector(glm::vec3(0, y1, 0), r, r + kTierDepth, kArc0, kArc1, kArcSegments, seat);
  }
  // Aisle stairs: a half step on every tier, radial, at kAisles angles.
  for (int a = 0; a < kAisles; ++a) {
    const float angle =
        kArc0 + (kArc1 - kArc0) * (static_cast<float>(a) + 0.5f) / static_cast<float>(kAisles);
    const glm::mat4 rot =
        glm::rotate(glm::translate(glm::mat4(1.0f), origin), angle, glm::vec3(0, 1, 0));
    b.SetTransform(rot);
    for (int k = 0; k < kTiers; ++k) {
      const float r = kInnerRadius + static_cast<float>(k) * kTierDepth;
      const float y1 = static_cast<float>(k + 1) * kTierRise;
      // After the rotation, +x points along the aisle's radial direction.
      b.Box({r - 0.1f, y1 - kTierRise, -0.45f}, {r + 0.4f, y1 - 0.5f * kTierRise, 0.45f}, stone);
    }
  }
  b.SetTransform(glm::translate(glm::mat4(1.0f), origin));
  // Outer wall with a parapet at the top of the cavea.
  const float ro = OuterRadius();
  const float top = kTiers * kTierRise;
  b.WallSector(c, ro, 0.0f, top + 1.2f, kArc0, kArc1, kArcSegments, plaster, /*inward=*/false);
  b.WallSector(c, ro - 0.3f, top, top + 1.2f, kArc0, kArc1, kArcSegments, plaster, true);
  b.RingSector(glm::vec3(0, top + 1.2f, 0), ro - 0.3f, ro, kArc0, kArc1, kArcSegments, plaster);
  // Portico columns along the top.
  for (int i = 0; i < kPorticoColumns; ++i) {
    const float a = kArc0 + (kArc1 - kArc0) * (static_cast<float>(i) + 0.5f) /
                                static_cast<float>(kPorticoColumns);
    const float r = ro - 1.2f;
    b.Cylinder({r * std::cos(a), top, -r * std::sin(a)}, 0.25f, 3.0f, 12, marble);
  }
  // Stage building (scaenae frons): platform, back wall, side wings, two storeys of columns,
  // and a pediment.
  b.Box({-14.0f, 0.0f, 8.5f}, {14.0f, 1.2f, 12.0f}, stone);
  b.Box({-16.0f, 0.0f, 12.0f}, {16.0f, 11.0f, 13.5f}, plaster);
  b.Box({-19.0f, 0.0f, 6.0f}, {-16.0f, 9.0f, 13.5f}, plaster);
  b.Box({16.0f, 0.0f, 6.0f}, {19.0f, 9.0f, 13.5f}, plaster);
  b.Box({-16.0f, 10.2f, 10.8f}, {16.0f, 10.8f, 12.0f}, marble);  // cornice
  for (int storey = 0; storey < 2; ++storey) {
    const float y = storey == 0 ? 1.2f : 5.9f;
    for (int i = 0; i < kStageColumns; ++i) {
      const float x = -13.2f + 24.0f * static_cast<float>(i) / (kStageColumns - 1);
      b.Cylinder({x, y, 11.4f}, 0.35f, 4.5f, 16, marble);
    }
  }
  b.Triangle({-5.0f, 11.0f, 11.95f}, {5.0f, 11.0f, 11.95f}, {0.0f, 13.0f, 11.95f}, marble);
  b.SetTransform(glm::mat4(1.0f));
}

// N amphitheaters on a grid (cols = smallest divisor of N >= sqrt(N)), sharing one ground quad.
void MakeAmphitheaters(Scene& scene, int n) {
  MeshBuilder b(scene, /*with_normals=*/false);
  const uint32_t ground = b.AddMaterial(Mat("ground", {0.62f, 0.55f, 0.42f}));
  const uint32_t stone = b.AddMaterial(Mat("stone", {0.70f, 0.66f, 0.58f}));
  const uint32_t seat = b.AddMaterial(Mat("seat_stone", {0.80f, 0.76f, 0.68f}));
  const uint32_t marble = b.AddMaterial(Mat("marble", {0.90f, 0.88f, 0.85f}));
  const uint32_t plaster = b.AddMaterial(Mat("plaster", {0.78f, 0.60f, 0.45f}));
  int cols = n;
  for (int c = 1; c <= n; ++c) {
    if (n % c == 0 && c * c >= n) {
      cols = c;
      break;
    }
  }
  const int rows = n / cols;
  constexpr float kDx = 74.0f;  // footprint: x in [-33, 33], z in [-33, 14]
  constexpr float kDz = 56.0f;
  const float margin = 40.0f;
  const float x_lo = -35.0f - margin;
  const float x_hi = kDx * static_cast<float>(cols - 1) + 35.0f + margin;
  const float z_hi = 15.0f + margin;
  const float z_lo = -kDz * static_cast<float>(rows - 1) - 35.0f - margin;
  b.Quad({x_lo, 0, z_hi}, {x_hi, 0, z_hi}, {x_hi, 0, z_lo}, {x_lo, 0, z_lo}, ground);
  for (int r = 0; r < rows; ++r) {
    for (int c = 0; c < cols; ++c) {
      AddAmphitheater(b, {kDx * static_cast<float>(c), 0.0f, -kDz * static_cast<float>(r)}, stone,
                      seat, marble, plaster);
    }
  }
  PointLight sun;
  sun.position = glm::vec3(0.5f * (x_lo + x_hi) + 300.0f, 600.0f, z_hi + 400.0f);
  sun.color = glm::vec3(0.78f, 0.74f, 0.66f);
  PointLight fill;
  fill.position = glm::vec3(0.5f * (x_lo + x_hi) - 400.0f, 300.0f, z_lo - 200.0f);
  fill.color = glm::vec3(0.22f, 0.25f, 0.32f);
  scene.lights = {sun, fill};
  // Fly along the first row from above the stage side (looking down into the tiers), rising
  // and turning; the look-at point drifts over the grid.
  const float x_last = kDx * static_cast<float>(cols - 1);
  const float z_far = -kDz * static_cast<float>(rows - 1);
  scene.camera = Cam({0.0f, 40.0f, 45.0f}, {0.0f, 3.0f, -10.0f});
  scene.path.frames = 60;
  scene.path.keys.clear();
  constexpr int kKeys = 6;
  for (int k = 0; k < kKeys; ++k) {
    const float t = static_cast<float>(k) / (kKeys - 1);
    const float swing = std::sin(kPi * t);
    const glm::vec3 eye(t * x_last + 35.0f * swing, 40.0f + 30.0f * t, 45.0f - 25.0f * swing);
    const glm::vec3 look(t * x_last - 20.0f * swing, 3.0f, -10.0f + 0.5f * t * z_far);
    scene.path.keys.push_back(Cam(eye, look));
  }
  scene.background = glm::vec3(0.55f, 0.70f, 0.90f);
  scene.ambient = 0.15f;
}

// A Cornell-box-like room (< 100 triangles): red and green side walls, a mirror box, a glass
// box, one light under the ceiling; open at the front where the camera stands.
void MakeCornell(Scene& scene) {
  MeshBuilder b(scene, /*with_normals=*/true);
  const uint32_t white = b.AddMaterial(Mat("white", {0.75f, 0.75f, 0.75f}));
  const uint32_t red = b.AddMaterial(Mat("red", {0.63f, 0.065f, 0.05f}));
  const uint32_t green = b.AddMaterial(Mat("green", {0.14f, 0.45f, 0.091f}));
  const uint32_t mirror =
      b.AddMaterial(Mat("mirror", {0.05f, 0.05f, 0.05f}, 0.9f, glm::vec3(0.9f), 200.0f));
  Material glass_mat = Mat("glass", {0.9f, 0.9f, 0.9f}, 0.05f, glm::vec3(1.0f), 250.0f);
  glass_mat.transmission = 0.9f;
  glass_mat.ior = 1.5f;
  const uint32_t glass = b.AddMaterial(glass_mat);
  const uint32_t lamp = b.AddMaterial(Mat("lamp", {1.0f, 1.0f, 1.0f}));
  b.Quad({-1, 0, 1}, {1, 0, 1}, {1, 0, -1}, {-1, 0, -1}, white);    // floor
  b.Quad({-1, 2, -1}, {1, 2, -1}, {1, 2, 1}, {-1, 2, 1}, white);    // ceiling
  b.Quad({-1, 0, -1}, {1, 0, -1}, {1, 2, -1}, {-1, 2, -1}, white);  // back
  b.Quad({-1, 0, 1}, {-1, 0, -1}, {-1, 2, -1}, {-1, 2, 1}, red);    // left
  b.Quad({1, 0, -1}, {1, 0, 1}, {1, 2, 1}, {1, 2, -1}, green);      // right
  b.Quad({-0.25f, 1.99f, -0.25f}, {0.25f, 1.99f, -0.25f}, {0.25f, 1.99f, 0.25f},
         {-0.25f, 1.99f, 0.25f}, lamp);  // light panel, facing down
  b.SetTransform(Place({-0.35f, 0.0f, -0.3f}, 17.0f));
  b.Box({-0.3f, 0.0f, -0.3f}, {0.3f, 1.2f, 0.3f}, mirror);
  b.SetTransform(Place({0.38f, 0.0f, 0.35f}, -18.0f));
  b.Box({-0.3f, 0.0f, -0.3f}, {0.3f, 0.6f, 0.3f}, glass);
  b.SetTransform(glm::mat4(1.0f));
  PointLight light;
  light.position = glm::vec3(0.0f, 1.9f, 0.0f);
  light.color = glm::vec3(1.0f);
  scene.lights = {light};
  scene.camera = Cam({0.0f, 1.0f, 3.9f}, {0.0f, 1.0f, 0.0f}, 40.0f);
  scene.path.frames = 30;
  scene.path.keys = {Cam({0.0f, 1.0f, 3.9f}, {0.0f, 1.0f, 0.0f}, 40.0f),
                     Cam({0.5f, 1.2f, 3.4f}, {0.0f, 0.9f, 0.0f}, 40.0f),
                     Cam({-0.4f, 0.8f, 3.0f}, {0.1f, 0.7f, -0.2f}, 40.0f)};
  scene.background = glm::vec3(0.0f);
  scene.ambient = 0.1f;
}

// A closed icosphere of radius 1 (level 6: 81,920 triangles) centred at `c`, on a 12 x 12 floor
// 1 below it, under a small lamp panel 5 above it (it lifts the bounds' top above the sphere, so
// that a light "near the top of the bounds" is outside it), one point light. At c = (148376,
// 1234, -223423) x and z are in [2^17, 2^18), where floats are multiples of 1/64: the
// vertices' float rounding makes slivers of many triangles, the case of issue 13's exploding
// grid. Positions are computed in double and rounded once.
void MakeSphereScene(Scene& scene, const glm::dvec3& c) {
  MeshBuilder b(scene, /*with_normals=*/true);
  const uint32_t glaze =
      b.AddMaterial(Mat("glaze", {0.70f, 0.12f, 0.10f}, 0.0f, glm::vec3(0.8f), 100));
  const uint32_t floor_a = b.AddMaterial(Mat("floor_a", {0.80f, 0.80f, 0.78f}));
  const uint32_t floor_b = b.AddMaterial(Mat("floor_b", {0.15f, 0.15f, 0.18f}));
  const uint32_t lamp = b.AddMaterial(Mat("lamp", {1.0f, 1.0f, 1.0f}));
  const auto at = [&](double x, double y, double z) {
    return glm::vec3(glm::dvec3(x, y, z) + c);  // rounded once
  };
  const Icosphere ico = MakeIcosphere(6, 1.0, {c.x, c.y, c.z}, 0.0);
  const uint32_t first = static_cast<uint32_t>(scene.positions.size());
  for (const std::array<float, 3>& v : ico.v) {
    scene.positions.emplace_back(v[0], v[1], v[2]);
    scene.normals.push_back(
        glm::vec3(glm::normalize(glm::dvec3(v[0], v[1], v[2]) - c)));  // radial
  }
  for (const std::array<uint32_t, 3>& t : ico.tri) {
    scene.triangles.emplace_back(first + t[0], first + t[1], first + t[2]);
    scene.material_ids.push_back(glaze);
  }
  b.Quad(at(-6, -1, 6), at(6, -1, 6), at(6, -1, -6), at(-6, -1, -6), floor_a, 8, 8, floor_b);
  b.Quad(at(-0.5, 5, -0.5), at(0.5, 5, -0.5), at(0.5, 5, 0.5), at(-0.5, 5, 0.5), lamp);
  PointLight light;
  light.position = at(2.0, 4.0, 2.5);
  light.color = glm::vec3(1.0f);
  scene.lights = {light};
  scene.camera = Cam(at(0.0, 1.0, 4.0), at(0.0, 0.0, 0.0), 50.0f);
  scene.path.frames = 30;
  scene.path.keys = {Cam(at(0.0, 1.0, 4.0), at(0.0, 0.0, 0.0), 50.0f),
                     Cam(at(3.0, 1.5, 2.5), at(0.0, 0.0, 0.0), 50.0f),
                     Cam(at(-2.5, 0.5, 3.0), at(0.0, -0.2, 0.0), 50.0f)};
  scene.background = glm::vec3(0.05f, 0.06f, 0.08f);
  scene.ambient = 0.1f;
}

}  // namespace

bool MakeProceduralScene(std::string_view name, Scene& scene) {
  const size_t colon = name.find(':');
  const std::string_view base = name.substr(0, colon);
  const bool has_param = colon != std::string_view::npos;
  const std::string_view param = has_param ? name.substr(colon + 1) : std::string_view();
  if (base != "erw6" && base != "spherebox" && base != "amphitheater" && base != "cornell" &&
      base != "farsphere" && base != "nearsphere") {
    return false;
  }
  scene = Scene();
  if (base == "amphitheater") {
    constexpr int kMaxCopies = 64;
    int n = 1;
    if (has_param) {
      const auto r = std::from_chars(param.data(), param.data() + param.size(), n);
      if (param.empty() || r.ec != std::errc() || r.ptr != param.data() + param.size() || n < 1 ||
          n > kMaxCopies) {
        Fail("scene '{}': N in amphitheater:N must be a whole number from 1 to {}", name,
             kMaxCopies);
      }
    }
    MakeAmphitheaters(scene, n);
    return true;
  }
  if (has_param) Fail("scene '{}': '{}' takes no ':' parameter", name, base);
  if (base == "erw6") {
    MakeErw6(scene);
  } else if (base == "spherebox") {
    MakeSphereBox(scene);
  } else if (base == "farsphere") {
    MakeSphereScene(scene, {148376.0, 1234.0, -223423.0});
  } else if (base == "nearsphere") {
    MakeSphereScene(scene, {0.0, 0.0, 0.0});
  } else {
    MakeCornell(scene);
  }
  return true;
}

}  // namespace rs::detail
