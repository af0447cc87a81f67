// The C API (include/raystream/raystream_c.h) over rs::Accel: every C++ exception becomes an
// error code, the thread's last error and the error callback; nothing escapes into C.
#include "include/raystream/raystream_c.h"

#include <atomic>
#include <exception>
#include <new>
#include <string>

#include "include/raystream/raystream.h"

struct RSAccelTy {
  rs::Accel accel;
};

struct RSSceneTy {
  rs::TraceScene scene;
};

namespace {

struct Callback {
  RSErrorFunction function = nullptr;
  void* user = nullptr;
};
std::atomic<Callback*> g_callback{nullptr};  // leaked on replacement: set rarely, read often

thread_local RSError t_error = RS_ERROR_NONE;
thread_local std::string t_message;

RSError Fail(RSError code, const char* message) {
  t_error = code;
  try {
    t_message = message;
  } catch (...) {
    t_message.clear();
  }
  const Callback* c = g_callback.load(std::memory_order_acquire);
  if (c != nullptr && c->function != nullptr) c->function(c->user, code, message);
  return code;
}

// Runs f, turning exceptions into error codes.
template <class F>
RSError Guard(F&& f) {
  try {
    f();
    return RS_ERROR_NONE;
  } catch (const rs::Error& e) {
    return Fail(RS_ERROR_INVALID_ARGUMENT, e.what());
  } catch (const std::bad_alloc&) {
    return Fail(RS_ERROR_OUT_OF_MEMORY, "out of memory");
  } catch (const std::exception& e) {
    return Fail(RS_ERROR_UNKNOWN, e.what());
  } catch (...) {
    return Fail(RS_ERROR_UNKNOWN, "unknown error");
  }
}

rs::RayStreamView View(const RSRayStream& r) {
  rs::RayStreamView v;
  // The kernels read rays only; RayStreamView's pointers are non-const for the renderer's sake.
  v.ox = const_cast<float*>(r.ox), v.oy = const_cast<float*>(r.oy);
  v.oz = const_cast<float*>(r.oz), v.dx = const_cast<float*>(r.dx);
  v.dy = const_cast<float*>(r.dy), v.dz = const_cast<float*>(r.dz);
  v.tmin = const_cast<float*>(r.tmin), v.tmax = const_cast<float*>(r.tmax);
  v.size = r.size;
  return v;
}

rs::BuildOptions Options(const RSBuildOptions* options, const char* what) {
  rs::BuildOptions o;
  if (options == nullptr) return o;
  if (options->empty_skip != 0 && options->empty_skip != 1) {
    throw rs::Error(std::string(what) + ": empty_skip must be 0 or 1");
  }
  if (options->packets != 0 && options->packets != 1) {
    throw rs::Error(std::string(what) + ": packets must be 0 or 1");
  }
  o.lambda = options->lambda;
  o.max_resolution = options->max_resolution;
  o.grid = static_cast<rs::GridKind>(options->grid);
  o.subgrid_threshold = options->subgrid_threshold;
  o.micro_cache = options->micro_cache;
  o.empty_skip = options->empty_skip == 1;
  o.packets = options->packets == 1;
  return o;
}

rs::GeometryDesc Desc(const RSGeometryDesc* d, const char* what) {
  if (d == nullptr) throw rs::Error(std::string(what) + ": desc is NULL");
  if (d->instance_only != 0 && d->instance_only != 1) {
    throw rs::Error(std::string(what) + ": instance_only must be 0 or 1");
  }
  rs::GeometryDesc g;
  g.positions = d->positions;
  g.num_vertices = d->num_vertices;
  g.stride_bytes = d->stride_bytes;
  g.indices = d->indices;
  g.index_type = static_cast<rs::IndexType>(d->index_type);
  g.num_triangles = d->num_triangles;
  g.mask = d->mask;
  g.mode = static_cast<rs::BufferMode>(d->mode);
  g.instance_only = d->instance_only == 1;
  return g;
}

rs::TraceScene& SceneOf(RSScene scene, const char* what) {
  if (scene == nullptr) throw rs::Error(std::string(what) + ": scene is NULL");
  return scene->scene;
}

}  // namespace

extern "C" {

void rsSetErrorFunction(RSErrorFunction function, void* user) {
  Callback* c = function != nullptr ? new (std::nothrow) Callback{function, user} : nullptr;
  g_callback.store(c, std::memory_order_release);
}

RSError rsGetError(void) {
  const RSError e = t_error;
  t_error = RS_ERROR_NONE;
  return e;
}

const char* rsGetErrorMessage(void) { return t_message.c_str(); }

const char* rsGetVersion(void) { return rs::Version(); }

void rsInitBuildOptions(RSBuildOptions* options) {
  if (options == nullptr) {
    Fail(RS_ERROR_INVALID_ARGUMENT, "rsInitBuildOptions: options is NULL");
    return;
  }
  const rs::BuildOptions d;
  options->lambda = d.lambda;
  options->max_resolution = d.max_resolution;
  options->grid = static_cast<RSGridKind>(d.grid);
  options->subgrid_threshold = d.subgrid_threshold;
  options->micro_cache = d.micro_cache;
  options->empty_skip = d.empty_skip ? 1 : 0;
  options->packets = d.packets ? 1 : 0;
}

namespace {
rs::MeshView MeshOf(const RSMesh& mesh) {
  rs::MeshView m;
  m.positions = mesh.positions;
  m.num_vertices = mesh.num_vertices;
  m.stride = mesh.stride;
  m.indices = mesh.indices;
  m.num_triangles = mesh.num_triangles;
  return m;
}
}  // namespace

RSAccel rsNewAccel(const RSMesh* mesh, const RSBuildOptions* options) {
  RSAccel out = nullptr;
  Guard([&] {
    if (mesh == nullptr) throw rs::Error("rsNewAccel: mesh is NULL");
    const rs::BuildOptions o = Options(options, "rsNewAccel");
    out = new RSAccelTy{rs::Accel(MeshOf(*mesh), o)};
  });
  return out;
}

RSError rsRebuildAccel(RSAccel accel, const RSMesh* mesh, const RSBuildOptions* options) {
  return Guard([&] {
    if (accel == nullptr || mesh == nullptr) throw rs::Error("rsRebuildAccel: accel or mesh is NULL");
    accel->accel.Rebuild(MeshOf(*mesh), Options(options, "rsRebuildAccel"));
  });
}

void rsReleaseAccel(RSAccel accel) { delete accel; }

RSError rsIntersect(RSAccel accel, const RSRayStream* rays, const RSHitStream* hits) {
  return Guard([&] {
    if (accel == nullptr || rays == nullptr || hits == nullptr) {
      throw rs::Error("rsIntersect: accel, rays or hits is NULL");
    }
    accel->accel.Intersect(View(*rays),
                           rs::HitStreamView{hits->t, hits->u, hits->v, hits->prim, hits->size});
  });
}

RSError rsOccluded(RSAccel accel, const RSRayStream* rays, int32_t* occluded) {
  return Guard([&] {
    if (accel == nullptr || rays == nullptr) throw rs::Error("rsOccluded: accel or rays is NULL");
    accel->accel.Occluded(View(*rays), occluded);
  });
}

RSError rsGetAccelInfo(RSAccel accel, RSAccelInfo* info) {
  return Guard([&] {
    if (accel == nullptr || info == nullptr) throw rs::Error("rsGetAccelInfo: accel or info is NULL");
    const rs::AccelInfo a = accel->accel.Info();
    info->triangles = a.triangles;
    info->cells = a.cells;
    info->references = a.references;
    for (int i = 0; i < 3; ++i) info->resolution[i] = a.resolution[i];
    info->lambda = a.lambda;
    info->bytes = a.bytes;
  });
}

void rsInitGeometryDesc(RSGeometryDesc* desc) {
  if (desc == nullptr) {
    Fail(RS_ERROR_INVALID_ARGUMENT, "rsInitGeometryDesc: desc is NULL");
    return;
  }
  const rs::GeometryDesc d;
  desc->positions = d.positions;
  desc->num_vertices = d.num_vertices;
  desc->stride_bytes = d.stride_bytes;
  desc->indices = d.indices;
  desc->index_type = static_cast<RSIndexType>(d.index_type);
  desc->num_triangles = d.num_triangles;
  desc->mask = d.mask;
  desc->mode = static_cast<RSBufferMode>(d.mode);
  desc->instance_only = d.instance_only ? 1 : 0;
}

RSScene rsNewScene(const RSBuildOptions* options) {
  RSScene out = nullptr;
  Guard([&] { out = new RSSceneTy{rs::TraceScene(Options(options, "rsNewScene"))}; });
  return out;
}

void rsReleaseScene(RSScene scene) { delete scene; }

RSError rsSceneAttachGeometry(RSScene scene, const RSGeometryDesc* desc, uint32_t* geom_id) {
  return Guard([&] {
    rs::TraceScene& s = SceneOf(scene, "rsSceneAttachGeometry");
    if (geom_id == nullptr) throw rs::Error("rsSceneAttachGeometry: geom_id is NULL");
    *geom_id = s.AttachGeometry(Desc(desc, "rsSceneAttachGeometry"));
  });
}

RSError rsSceneReplaceGeometry(RSScene scene, uint32_t geom_id, const RSGeometryDesc* desc) {
  return Guard([&] {
    SceneOf(scene, "rsSceneReplaceGeometry")
        .ReplaceGeometry(geom_id, Desc(desc, "rsSceneReplaceGeometry"));
  });
}

RSError rsSceneUpdateGeometry(RSScene scene, uint32_t geom_id, const void* positions,
                              size_t stride_bytes) {
  return Guard([&] {
    SceneOf(scene, "rsSceneUpdateGeometry").UpdateGeometry(geom_id, positions, stride_bytes);
  });
}

RSError rsSceneAttachInstance(RSScene scene, uint32_t geom_id, const float* transform,
                              uint32_t mask, uint32_t* inst_id) {
  return Guard([&] {
    rs::TraceScene& s = SceneOf(scene, "rsSceneAttachInstance");
    if (inst_id == nullptr) throw rs::Error("rsSceneAttachInstance: inst_id is NULL");
    *inst_id = s.AttachInstance(geom_id, transform, mask);
  });
}

RSError rsSceneSetInstanceTransform(RSScene scene, uint32_t inst_id, const float* transform) {
  return Guard([&] {
    SceneOf(scene, "rsSceneSetInstanceTransform").SetInstanceTransform(inst_id, transform);
  });
}

RSError rsSceneCommit(RSScene scene) {
  return Guard([&] { SceneOf(scene, "rsSceneCommit").Commit(); });
}

RSError rsSceneIntersect(RSScene scene, const RSRays* rays, const RSHits* hits) {
  return Guard([&] {
    rs::TraceScene& s = SceneOf(scene, "rsSceneIntersect");
    if (rays == nullptr || hits == nullptr) throw rs::Error("rsSceneIntersect: rays or hits is NULL");
    s.Intersect(rs::RayView{rays->ox, rays->oy, rays->oz, rays->dx, rays->dy, rays->dz,
                            rays->tnear, rays->tfar, rays->mask, rays->id, rays->size},
                rs::HitView{hits->t, hits->u, hits->v, hits->ng_x, hits->ng_y, hits->ng_z,
                            hits->prim, hits->geom, hits->inst, hits->size});
  });
}

RSError rsSceneOccluded(RSScene scene, const RSRays* rays, int32_t* occluded) {
  return Guard([&] {
    rs::TraceScene& s = SceneOf(scene, "rsSceneOccluded");
    if (rays == nullptr) throw rs::Error("rsSceneOccluded: rays is NULL");
    s.Occluded(rs::RayView{rays->ox, rays->oy, rays->oz, rays->dx, rays->dy, rays->dz,
                           rays->tnear, rays->tfar, rays->mask, rays->id, rays->size},
               occluded);
  });
}

}  // extern "C"
