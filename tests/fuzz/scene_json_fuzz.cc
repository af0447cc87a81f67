// Fuzz target: raystream scene files (JSON) from memory, without file access
// (ParseSceneJsonText). rs::Error is the expected outcome for bad input; any other exception or
// a crash is a finding.
#include <cstddef>
#include <cstdint>
#include <string_view>

#include "scenes/load.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string_view text(reinterpret_cast<const char*>(data), size);
  try {
    const rs::Scene scene = rs::ParseSceneJsonText(text, "fuzz.json");
    rs::ValidateScene(scene);  // what the parser accepts must be a valid scene
  } catch (const rs::Error&) {
  }
  return 0;
}
