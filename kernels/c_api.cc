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

RSAccel rsNewAccel(const RSMesh* mesh, const RSBuildOptions* options) {
  RSAccel out = nullptr;
  Guard([&] {
    if (mesh == nullptr) throw rs::Error("rsNewAccel: mesh is NULL");
    rs::BuildOptions o;
    if (options != nullptr) {
      if (options->empty_skip != 0 && options->empty_skip != 1) {
        throw rs::Error("rsNewAccel: empty_skip must be 0 or 1");
      }
      if (options->packets != 0 && options->packets != 1) {
        throw rs::Error("rsNewAccel: packets must be 0 or 1");
      }
      o.lambda = options->lambda;
      o.max_resolution = options->max_resolution;
      o.grid = static_cast<rs::GridKind>(options->grid);
      o.subgrid_threshold = options->subgrid_threshold;
      o.micro_cache = options->micro_cache;
      o.empty_skip = options->empty_skip == 1;
      o.packets = options->packets == 1;
    }
    rs::MeshView m;
    m.positions = mesh->positions;
    m.num_vertices = mesh->num_vertices;
    m.stride = mesh->stride;
    m.indices = mesh->indices;
    m.num_triangles = mesh->num_triangles;
    out = new RSAccelTy{rs::Accel(m, o)};
  });
  return out;
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

}  // extern "C"
