// Embree 3 peer (see embree_peer.h): converts rs SoA streams to Embree's ray layouts and back.
// The conversions are part of what is timed, as they would be for any tracer fed rs streams.
#include "bench/peer/embree_peer.h"

#include <embree3/rtcore.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdlib>
#include <limits>
#include <mutex>
#include <string>

namespace rs::bench {

const char* EmbreeModeName(EmbreeMode mode) {
  switch (mode) {
    case EmbreeMode::k1: return "embree1";
    case EmbreeMode::k16: return "embree16";
    case EmbreeMode::kStream: return "embree1M";
  }
  return "embree?";
}

const char* EmbreeVersion() { return RTC_VERSION_STRING; }

namespace {

const char* ErrorName(RTCError code) {
  switch (code) {
    case RTC_ERROR_NONE: return "none";
    case RTC_ERROR_UNKNOWN: return "unknown";
    case RTC_ERROR_INVALID_ARGUMENT: return "invalid argument";
    case RTC_ERROR_INVALID_OPERATION: return "invalid operation";
    case RTC_ERROR_OUT_OF_MEMORY: return "out of memory";
    case RTC_ERROR_UNSUPPORTED_CPU: return "unsupported cpu";
    case RTC_ERROR_CANCELLED: return "cancelled";
  }
  return "?";
}

// The first error Embree reported since the last TakeError, with its message.
std::mutex error_mutex;
std::string first_error;

void OnEmbreeError(void* /*user*/, RTCError code, const char* message) {
  std::lock_guard<std::mutex> lock(error_mutex);
  if (first_error.empty()) {
    first_error = std::string(ErrorName(code)) + ": " + (message ? message : "");
  }
}

void ThrowIfError(const char* what) {
  std::string error;
  {
    std::lock_guard<std::mutex> lock(error_mutex);
    error.swap(first_error);
  }
  if (!error.empty()) throw Error(std::string("embree: ") + what + ": " + error);
}

// The process-wide device: one build and trace thread, as in ANCHORS.md. Created on first use
// and kept for the life of the process (rtcReleaseDevice at exit would race static dtors).
RTCDevice Device() {
  static RTCDevice device = [] {
    // RS_BENCH_ISA=avx2 (bench/common/bench_main.h) holds Embree to AVX2 as well.
    const char* isa = std::getenv("RS_BENCH_ISA");
    const std::string config = std::string("threads=1,verbose=0") +
                               (isa != nullptr && std::string(isa) == "avx2" ? ",isa=avx2" : "");
    RTCDevice d = rtcNewDevice(config.c_str());
    if (d == nullptr) {
      throw Error(std::string("embree: rtcNewDevice failed: ") +
                  ErrorName(rtcGetDeviceError(nullptr)));
    }
    rtcSetDeviceErrorFunction(d, OnEmbreeError, nullptr);
    return d;
  }();
  return device;
}

RTCIntersectContext Context(Coherence hint) {
  RTCIntersectContext ctx;
  rtcInitIntersectContext(&ctx);
  ctx.flags = hint == Coherence::kCoherent ? RTC_INTERSECT_CONTEXT_FLAG_COHERENT
                                           : RTC_INTERSECT_CONTEXT_FLAG_INCOHERENT;
  return ctx;
}

constexpr float kInf = std::numeric_limits<float>::infinity();

void StoreHit(const HitStreamView& hits, size_t i, unsigned geom_id, unsigned prim_id, float t,
              float u, float v) {
  if (geom_id == RTC_INVALID_GEOMETRY_ID) {
    hits.t[i] = kInf;
    hits.u[i] = hits.v[i] = 0.0f;
    hits.prim[i] = -1;
  } else {
    hits.t[i] = t;
    hits.u[i] = u;
    hits.v[i] = v;
    hits.prim[i] = static_cast<int32_t>(prim_id);
  }
}

void LoadRay(const RayStreamView& rays, size_t i, RTCRay& r) {
  r.org_x = rays.ox[i];
  r.org_y = rays.oy[i];
  r.org_z = rays.oz[i];
  r.tnear = rays.tmin[i];
  r.dir_x = rays.dx[i];
  r.dir_y = rays.dy[i];
  r.dir_z = rays.dz[i];
  r.time = 0.0f;
  r.tfar = rays.tmax[i];
  r.mask = ~0u;
  r.id = static_cast<unsigned>(i);
  r.flags = 0;
}

// Packet of 16: lane k holds ray first + k; lanes past `count` are invalid.
template <class Packet>
void LoadPacket(const RayStreamView& rays, size_t first, size_t count, Packet& p, int* valid) {
  for (size_t k = 0; k < 16; ++k) {
    const size_t i = first + (k < count ? k : 0);
    valid[k] = k < count ? -1 : 0;
    p.org_x[k] = rays.ox[i];
    p.org_y[k] = rays.oy[i];
    p.org_z[k] = rays.oz[i];
    p.tnear[k] = rays.tmin[i];
    p.dir_x[k] = rays.dx[i];
    p.dir_y[k] = rays.dy[i];
    p.dir_z[k] = rays.dz[i];
    p.time[k] = 0.0f;
    p.tfar[k] = rays.tmax[i];
    p.mask[k] = ~0u;
    p.id[k] = static_cast<unsigned>(i);
    p.flags[k] = 0;
  }
}

}  // namespace

EmbreePeer::EmbreePeer(const MeshView& mesh) { Build(mesh); }

EmbreePeer::~EmbreePeer() { Release(); }

void EmbreePeer::Release() {
  if (scene_ != nullptr) rtcReleaseScene(scene_);
  scene_ = nullptr;
  num_triangles_ = num_vertices_ = 0;
}

namespace {
// The mesh's positions (any stride) into an Embree FLOAT3 vertex buffer.
void CopyPositions(const MeshView& mesh, float* vertices) {
  for (size_t i = 0; i < mesh.num_vertices; ++i) {
    const float* p = mesh.positions + i * mesh.stride;
    vertices[3 * i + 0] = p[0];
    vertices[3 * i + 1] = p[1];
    vertices[3 * i + 2] = p[2];
  }
}
}  // namespace

void EmbreePeer::Build(const MeshView& mesh) {
  RTCDevice device = Device();
  Release();
  const auto start = std::chrono::steady_clock::now();
  scene_ = rtcNewScene(device);
  ThrowIfError("rtcNewScene");
  rtcSetSceneFlags(scene_, RTC_SCENE_FLAG_ROBUST);
  rtcSetSceneBuildQuality(scene_, RTC_BUILD_QUALITY_MEDIUM);
  if (mesh.num_triangles > 0 && mesh.num_vertices > 0) {
    RTCGeometry geom = rtcNewGeometry(device, RTC_GEOMETRY_TYPE_TRIANGLE);
    rtcSetGeometryBuildQuality(geom, RTC_BUILD_QUALITY_MEDIUM);
    // Embree-owned buffers: Embree pads them for its 16-byte vertex loads, and the copy
    // handles any stride of the MeshView.
    auto* vertices = static_cast<float*>(rtcSetNewGeometryBuffer(
        geom, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3, 3 * sizeof(float), mesh.num_vertices));
    auto* indices = static_cast<uint32_t*>(
        rtcSetNewGeometryBuffer(geom, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3,
                                3 * sizeof(uint32_t), mesh.num_triangles));
    ThrowIfError("rtcSetNewGeometryBuffer");
    CopyPositions(mesh, vertices);
    std::copy(mesh.indices, mesh.indices + 3 * mesh.num_triangles, indices);
    rtcCommitGeometry(geom);
    rtcAttachGeometryByID(scene_, geom, 0);
    rtcReleaseGeometry(geom);
  }
  rtcCommitScene(scene_);
  ThrowIfError("building the scene");
  build_seconds_ = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  num_triangles_ = mesh.num_triangles;
  num_vertices_ = mesh.num_vertices;
}

void EmbreePeer::Update(const MeshView& mesh) {
  if (scene_ == nullptr || mesh.num_triangles != num_triangles_ ||
      mesh.num_vertices != num_vertices_ || num_triangles_ == 0 || num_vertices_ == 0) {
    return Build(mesh);
  }
  const auto start = std::chrono::steady_clock::now();
  RTCGeometry geom = rtcGetGeometry(scene_, 0);
  auto* vertices = static_cast<float*>(rtcGetGeometryBufferData(geom, RTC_BUFFER_TYPE_VERTEX, 0));
  ThrowIfError("rtcGetGeometryBufferData");
  CopyPositions(mesh, vertices);
  rtcUpdateGeometryBuffer(geom, RTC_BUFFER_TYPE_VERTEX, 0);
  rtcCommitGeometry(geom);
  rtcCommitScene(scene_);
  ThrowIfError("rebuilding the scene");
  build_seconds_ = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
}

void EmbreePeer::Intersect(EmbreeMode mode, const RayStreamView& rays, const HitStreamView& hits,
                           Coherence hint) const {
  RTCIntersectContext ctx = Context(hint);
  const size_t n = rays.size;
  switch (mode) {
    case EmbreeMode::k1: {
      for (size_t i = 0; i < n; ++i) {
        RTCRayHit rh;
        LoadRay(rays, i, rh.ray);
        rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
        rh.hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
        rtcIntersect1(scene_, &ctx, &rh);
        StoreHit(hits, i, rh.hit.geomID, rh.hit.primID, rh.ray.tfar, rh.hit.u, rh.hit.v);
      }
      break;
    }
    case EmbreeMode::k16: {
      alignas(64) RTCRayHit16 rh;
      alignas(64) int valid[16];
      for (size_t first = 0; first < n; first += 16) {
        const size_t count = std::min<size_t>(16, n - first);
        LoadPacket(rays, first, count, rh.ray, valid);
        for (size_t k = 0; k < 16; ++k) {
          rh.hit.geomID[k] = RTC_INVALID_GEOMETRY_ID;
          rh.hit.instID[0][k] = RTC_INVALID_GEOMETRY_ID;
        }
        rtcIntersect16(valid, scene_, &ctx, &rh);
        for (size_t k = 0; k < count; ++k) {
          StoreHit(hits, first + k, rh.hit.geomID[k], rh.hit.primID[k], rh.ray.tfar[k], rh.hit.u[k],
                   rh.hit.v[k]);
        }
      }
      break;
    }
    case EmbreeMode::kStream: {
      alignas(64) RTCRayHit rh[kEmbreeStreamChunk];
      for (size_t first = 0; first < n; first += kEmbreeStreamChunk) {
        const size_t count = std::min(kEmbreeStreamChunk, n - first);
        for (size_t k = 0; k < count; ++k) {
          LoadRay(rays, first + k, rh[k].ray);
          rh[k].hit.geomID = RTC_INVALID_GEOMETRY_ID;
          rh[k].hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
        }
        rtcIntersect1M(scene_, &ctx, rh, static_cast<unsigned>(count), sizeof(RTCRayHit));
        for (size_t k = 0; k < count; ++k) {
          StoreHit(hits, first + k, rh[k].hit.geomID, rh[k].hit.primID, rh[k].ray.tfar, rh[k].hit.u,
                   rh[k].hit.v);
        }
      }
      break;
    }
  }
}

void EmbreePeer::Occluded(EmbreeMode mode, const RayStreamView& rays, int32_t* occluded,
                          Coherence hint) const {
  RTCIntersectContext ctx = Context(hint);
  const size_t n = rays.size;
  // Embree marks an occluded ray by setting tfar to -inf.
  switch (mode) {
    case EmbreeMode::k1: {
      for (size_t i = 0; i < n; ++i) {
        RTCRay r;
        LoadRay(rays, i, r);
        rtcOccluded1(scene_, &ctx, &r);
        occluded[i] = r.tfar == -kInf ? 1 : 0;
      }
      break;
    }
    case EmbreeMode::k16: {
      alignas(64) RTCRay16 r;
      alignas(64) int valid[16];
      for (size_t first = 0; first < n; first += 16) {
        const size_t count = std::min<size_t>(16, n - first);
        LoadPacket(rays, first, count, r, valid);
        rtcOccluded16(valid, scene_, &ctx, &r);
        for (size_t k = 0; k < count; ++k) occluded[first + k] = r.tfar[k] == -kInf ? 1 : 0;
      }
      break;
    }
    case EmbreeMode::kStream: {
      alignas(64) RTCRay r[kEmbreeStreamChunk];
      for (size_t first = 0; first < n; first += kEmbreeStreamChunk) {
        const size_t count = std::min(kEmbreeStreamChunk, n - first);
        for (size_t k = 0; k < count; ++k) LoadRay(rays, first + k, r[k]);
        rtcOccluded1M(scene_, &ctx, r, static_cast<unsigned>(count), sizeof(RTCRay));
        for (size_t k = 0; k < count; ++k) occluded[first + k] = r[k].tfar == -kInf ? 1 : 0;
      }
      break;
    }
  }
}

void EmbreePeer::Intersect1(const float o[3], const float d[3], float tmin, float tmax, float& t,
                            float& u, float& v, int32_t& prim) const {
  RTCIntersectContext ctx = Context(Coherence::kIncoherent);
  RTCRayHit rh;
  rh.ray.org_x = o[0];
  rh.ray.org_y = o[1];
  rh.ray.org_z = o[2];
  rh.ray.tnear = tmin;
  rh.ray.dir_x = d[0];
  rh.ray.dir_y = d[1];
  rh.ray.dir_z = d[2];
  rh.ray.time = 0.0f;
  rh.ray.tfar = tmax;
  rh.ray.mask = ~0u;
  rh.ray.id = 0;
  rh.ray.flags = 0;
  rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
  rh.hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
  rtcIntersect1(scene_, &ctx, &rh);
  const bool hit = rh.hit.geomID != RTC_INVALID_GEOMETRY_ID;
  t = hit ? rh.ray.tfar : kInf;
  u = hit ? rh.hit.u : 0.0f;
  v = hit ? rh.hit.v : 0.0f;
  prim = hit ? static_cast<int32_t>(rh.hit.primID) : -1;
}

}  // namespace rs::bench
