// Fuzz target: MTL material libraries from memory (ParseMtlText: the strict line scan, then
// tinyobjloader, then the conversion). rs::Error is the expected outcome for bad input; any other
// exception or a crash is a finding, and every accepted material must pass ValidateScene.
#include <cstddef>
#include <cstdint>
#include <string_view>
#include <vector>

#include "scenes/load.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string_view text(reinterpret_cast<const char*>(data), size);
  try {
    std::vector<rs::Material> materials = rs::ParseMtlText(text, "fuzz.mtl");
    // One triangle per material, so validation sees every material the parser accepted.
    rs::Scene scene;
    scene.positions = {{0, 0, 0}, {1, 0, 0}, {0, 1, 0}};
    for (uint32_t m = 0; m < materials.size(); ++m) {
      materials[m].texture = -1;  // textures need file access; none were read
      scene.triangles.push_back({0, 1, 2});
      scene.material_ids.push_back(m);
    }
    scene.materials = std::move(materials);
    if (scene.materials.empty()) scene.materials.resize(1);
    rs::ValidateScene(scene);
  } catch (const rs::Error&) {
  }
  return 0;
}
