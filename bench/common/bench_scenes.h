// Which benchmark scenes can run on this machine: a shared mesh needs its file on the scene
// search path (scenes/load.h), a procedural scene always runs. Shared by trace_bench and
// render_bench, which register no benchmarks for a scene whose file is missing.
#pragma once

#include <cstdio>
#include <map>
#include <string>

#include "scenes/load.h"

namespace rs::bench {

// A shared scene's file, to test for presence without loading; "" for procedural scenes.
inline std::string ProbeFile(const std::string& scene) {
  static const std::map<std::string, std::string> files = {
      {"bunny", "bunny/bun_zipper.ply"},
      {"teapot", "teapot/teapot.obj"},
      {"sponza", "sponza/sponza.obj"},
      {"office-graz", "office-graz/office-graz.obj"},
      {"conference", "conference/conference.obj"},
      {"sibenik", "sibenik/sibenik.obj"}};
  const auto it = files.find(scene);
  return it == files.end() ? std::string() : it->second;
}

// True if `scene` is procedural or its file is found; otherwise prints "[who] skipping
// <scene>: <why>" to stderr and returns false. Does not load the scene.
inline bool SceneAvailable(const char* who, const std::string& scene) {
  const std::string probe = ProbeFile(scene);
  if (probe.empty()) return true;
  try {
    FindSceneFile(probe);
    return true;
  } catch (const Error& e) {
    std::fprintf(stderr, "[%s] skipping %s: %s\n", who, scene.c_str(), e.what());
    return false;
  }
}

}  // namespace rs::bench
