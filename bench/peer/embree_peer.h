// Embree 3 as the peer we compare against (tests and benchmarks only, never the kernels): one
// robust-mode triangle scene built from an rs::MeshView, traced over rs SoA streams one ray at a
// time (rtcIntersect1), in packets of 16 (rtcIntersect16) or as streams (rtcIntersect1M).
#pragma once

#include <cstddef>
#include <cstdint>

#include "include/raystream/raystream.h"

// Opaque Embree handles, so users of the peer need not include <embree3/rtcore.h>.
typedef struct RTCSceneTy* RTCScene;

namespace rs::bench {

// How rays are handed to Embree (ANCHORS.md, columns "1 / 16 / 1M").
enum class EmbreeMode : int {
  k1 = 0,       // rtcIntersect1 / rtcOccluded1 per ray
  k16 = 1,      // rtcIntersect16 / rtcOccluded16 on 16 consecutive rays of the stream
  kStream = 2,  // rtcIntersect1M / rtcOccluded1M on chunks of kEmbreeStreamChunk rays
};
inline constexpr int kNumEmbreeModes = 3;
inline constexpr size_t kEmbreeStreamChunk = 256;
// "embree1", "embree16", "embree1M": the last part of the benchmark names.
const char* EmbreeModeName(EmbreeMode mode);

// The coherence hint of the intersect context (ANCHORS: coherent for primary and shadow rays,
// incoherent for diffuse rays). It is passed to every mode; Embree uses it for streams.
enum class Coherence : int { kIncoherent = 0, kCoherent = 1 };

// One Embree device (one thread, "threads=1") shared by the process, and one scene per peer:
// RTC_SCENE_FLAG_ROBUST, RTC_BUILD_QUALITY_MEDIUM, a single triangle geometry (geomID 0) whose
// primID is the triangle index of the MeshView. Zero-area triangles are kept in the buffer;
// Embree never reports them as hits. Not copyable; tracing is const and thread-safe.
class EmbreePeer {
 public:
  // Builds the scene (see Build). Throws rs::Error with Embree's error text on failure.
  explicit EmbreePeer(const MeshView& mesh);
  ~EmbreePeer();
  EmbreePeer(const EmbreePeer&) = delete;
  EmbreePeer& operator=(const EmbreePeer&) = delete;

  // (Re)builds the scene from `mesh` as a dynamic scene would each frame: releases the old
  // scene, creates a new one, copies vertices (any stride) and indices into Embree-owned
  // buffers and commits. Indices must be < num_vertices (not checked: validate the mesh
  // first, e.g. with rs::Accel or rs::ValidateScene). The mesh may be freed afterwards.
  void Build(const MeshView& mesh);
  // Rebuilds the same scene in place, as an Embree user animating a mesh would: the new
  // positions are copied into the geometry's vertex buffer (rtcUpdateGeometryBuffer,
  // rtcCommitGeometry) and the scene is committed again (Embree reuses its BVH memory). `mesh`
  // must have the last Build's vertex and triangle counts and indices (else this is Build).
  void Update(const MeshView& mesh);
  // Wall time of the last Build: geometry creation and copies plus rtcCommitScene.
  double build_seconds() const { return build_seconds_; }
  size_t num_triangles() const { return num_triangles_; }

  // Closest hit in [tmin, tmax] for rays [0, rays.size): writes t, u, v and prim (= primID)
  // to hits[0, rays.size), or t = +inf, u = v = 0, prim = -1 on a miss; u, v follow the
  // rs::HitStreamView convention (Embree's barycentrics of vertices 1 and 2). hits.size must
  // equal rays.size. Rays with tmin > tmax are inactive (miss). The rays are not modified.
  void Intersect(EmbreeMode mode, const RayStreamView& rays, const HitStreamView& hits,
                 Coherence hint = Coherence::kCoherent) const;
  // Any hit in [tmin, tmax]: occluded[i] = 1 if Embree finds one, else 0.
  void Occluded(EmbreeMode mode, const RayStreamView& rays, int32_t* occluded,
                Coherence hint = Coherence::kCoherent) const;

  // Closest hit of one ray (rtcIntersect1), for spot checks in tests.
  void Intersect1(const float o[3], const float d[3], float tmin, float tmax, float& t, float& u,
                  float& v, int32_t& prim) const;

 private:
  void Release();
  RTCScene scene_ = nullptr;
  size_t num_triangles_ = 0;
  size_t num_vertices_ = 0;
  double build_seconds_ = 0;
};

// The Embree version string ("3.13.5"), for the benchmark context and test messages.
const char* EmbreeVersion();

}  // namespace rs::bench
