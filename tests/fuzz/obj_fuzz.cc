// Fuzz target: OBJ text through the pre-scan and tinyobjloader (ParseObjText, no file access).
// rs::Error is the expected outcome for bad input; any other exception or a crash is a finding.
#include <cstddef>
#include <cstdint>
#include <string_view>

#include "scenes/load.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string_view text(reinterpret_cast<const char*>(data), size);
  try {
    rs::Scene scene;
    rs::ParseObjText(text, "fuzz.obj", scene);
    rs::ValidateScene(scene);  // what the loader accepts must be a valid scene
  } catch (const rs::Error&) {
  }
  return 0;
}
