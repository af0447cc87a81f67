// Helpers shared by the doctest suites: per-SIMD-target loops and access to the shared scenes.
#pragma once

#include <doctest/doctest.h>
#include <hwy/targets.h>

#include <cstdint>
#include <cstdlib>
#include <string>

#include "scenes/load.h"

namespace rs::test {

// True in unoptimised or address/thread-sanitized builds, where the largest stress tests run a
// tenth of their rays (the same code paths) to keep a sanitizer run of the suite short.
#if !defined(__OPTIMIZE__) || defined(__SANITIZE_ADDRESS__) || defined(__SANITIZE_THREAD__)
inline constexpr bool kSlowBuild = true;
#else
inline constexpr bool kSlowBuild = false;
#endif

}  // namespace rs::test

// 1 in a ThreadSanitizer build (GCC's __SANITIZE_THREAD__ or Clang's feature), else 0.
#if defined(__SANITIZE_THREAD__)
#define RS_TEST_TSAN 1
#elif defined(__has_feature)
#if __has_feature(thread_sanitizer)
#define RS_TEST_TSAN 1
#endif
#endif
#ifndef RS_TEST_TSAN
#define RS_TEST_TSAN 0
#endif
// 1 in an AddressSanitizer build, else 0.
#if defined(__SANITIZE_ADDRESS__)
#define RS_TEST_ASAN 1
#elif defined(__has_feature)
#if __has_feature(address_sanitizer)
#define RS_TEST_ASAN 1
#endif
#endif
#ifndef RS_TEST_ASAN
#define RS_TEST_ASAN 0
#endif

namespace rs::test {

// Runs f(target_name) once per SIMD target that is both compiled and supported here, with
// dynamic dispatch forced to that target; restores normal dispatch afterwards.
template <class F>
void ForEachTarget(const F& f) {
  for (const int64_t target : hwy::SupportedAndGeneratedTargets()) {
    hwy::SetSupportedTargetsForTest(target);
    f(hwy::TargetName(target));
  }
  hwy::SetSupportedTargetsForTest(0);
}

inline bool InCi() {
  const char* ci = std::getenv("CI");
  return ci != nullptr && std::string(ci) == "true";
}

// True if the shared scene file (e.g. "bunny/bun_zipper.ply") is on the search path. When it
// is missing, the calling test is skipped with a message, except under CI=true, where a
// missing scene is a failure (CI must test the real meshes).
inline bool HaveSharedScene(const std::string& file) {
  try {
    FindSceneFile(file);
    return true;
  } catch (const rs::Error& e) {
    if (InCi()) {
      FAIL("shared scene missing under CI=true: ", e.what());
    } else {
      MESSAGE("skipped, shared scene missing: ", e.what());
    }
    return false;
  }
}

}  // namespace rs::test
