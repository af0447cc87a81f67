/* raystream's C API: the same library (libraystream) behind opaque handles and error codes, for C
 * programs and for bindings (Rust, Python, ...). Errors are reported like Embree's device errors:
 * every call that fails returns (or records) an RSError code, the calling thread's last error is
 * read with rsGetError (which clears it), and an optional callback set with
 * rsSetErrorFunction receives every error with its message. No call aborts on bad input.
 * Results are those of the C++ API (include/raystream/raystream.h) bit for bit. */
#ifndef RAYSTREAM_C_H_
#define RAYSTREAM_C_H_

#include <stddef.h>
#include <stdint.h>

#if defined(__GNUC__) || defined(__clang__)
#define RS_C_API __attribute__((visibility("default")))
#else
#define RS_C_API
#endif

#ifdef __cplusplus
extern "C" {
#endif

typedef enum RSError {
  RS_ERROR_NONE = 0,
  RS_ERROR_INVALID_ARGUMENT = 1, /* a null or inconsistent argument, a bad option or mesh */
  RS_ERROR_OUT_OF_MEMORY = 2,
  RS_ERROR_UNKNOWN = 3
} RSError;

/* Called on every error with the code and a one-line message (valid during the call only), on
 * the thread that met the error. NULL removes the callback. Process-wide; set it before other
 * threads call into the library. */
typedef void (*RSErrorFunction)(void* user, RSError code, const char* message);
RS_C_API void rsSetErrorFunction(RSErrorFunction function, void* user);
/* The calling thread's last error since the previous rsGetError (RS_ERROR_NONE if none), and its
 * message ("" if none; valid until the thread's next call into the library). rsGetError clears
 * the code. */
RS_C_API RSError rsGetError(void);
RS_C_API const char* rsGetErrorMessage(void);

/* Library version ("0.1.0"). */
RS_C_API const char* rsGetVersion(void);

/* A caller-owned triangle mesh (as rs::MeshView): xyz float positions with a stride in floats
 * (>= 3), 3 indices per triangle. The library copies what it needs. */
typedef struct RSMesh {
  const float* positions;
  size_t num_vertices;
  size_t stride;
  const uint32_t* indices;
  size_t num_triangles;
} RSMesh;

typedef enum RSGridKind {
  RS_GRID_AUTO = 0,
  RS_GRID_UNIFORM = 1,
  RS_GRID_TWO_LEVEL = 2,
  RS_GRID_IRREGULAR = 3 /* rs::GridKind::kIrregular */
} RSGridKind;

/* rs::BuildOptions; rsInitBuildOptions fills the defaults. */
typedef struct RSBuildOptions {
  float lambda; /* 0: chosen by the grid cost model (RS_GRID_AUTO) or 4; > 0: as given */
  int max_resolution;
  RSGridKind grid;
  int subgrid_threshold;
  int micro_cache;
  int empty_skip; /* 0 or 1 */
  int packets;    /* 0 or 1 */
} RSBuildOptions;
RS_C_API void rsInitBuildOptions(RSBuildOptions* options);

/* SoA ray and hit streams (as rs::RayStreamView / HitStreamView): arrays of exactly `size`
 * elements, any alignment. t in (tmin, tmax]; prim -1 and t +inf on a miss. */
typedef struct RSRayStream {
  const float* ox;
  const float* oy;
  const float* oz;
  const float* dx;
  const float* dy;
  const float* dz;
  const float* tmin;
  const float* tmax;
  size_t size;
} RSRayStream;

typedef struct RSHitStream {
  float* t;
  float* u;
  float* v;
  int32_t* prim;
  size_t size;
} RSHitStream;

typedef struct RSAccelInfo {
  size_t triangles;
  size_t cells;
  size_t references;
  int resolution[3];
  float lambda;
  size_t bytes;
} RSAccelInfo;

/* The acceleration structure. rsNewAccel returns NULL on error (options NULL: the defaults).
 * A built RSAccel may be traced from several threads at once; rsReleaseAccel(NULL) is a no-op. */
typedef struct RSAccelTy* RSAccel;
RS_C_API RSAccel rsNewAccel(const RSMesh* mesh, const RSBuildOptions* options);
RS_C_API void rsReleaseAccel(RSAccel accel);
/* Rebuilds `accel` for `mesh` in its own memory (rs::Accel::Rebuild: a moving mesh rebuilt every
 * frame maps no fresh page). On an error the accel must be rebuilt before it is traced again
 * (tracing returns the error until then). Not thread-safe with tracing of the same accel. */
RS_C_API RSError rsRebuildAccel(RSAccel accel, const RSMesh* mesh, const RSBuildOptions* options);

/* Closest hits / any hits (occluded[i] = 1 or 0). Return RS_ERROR_NONE, or the error (nothing is
 * written then): a null accel, stream or array, hits->size != rays->size. */
RS_C_API RSError rsIntersect(RSAccel accel, const RSRayStream* rays, const RSHitStream* hits);
RS_C_API RSError rsOccluded(RSAccel accel, const RSRayStream* rays, int32_t* occluded);
RS_C_API RSError rsGetAccelInfo(RSAccel accel, RSAccelInfo* info);

/* ---- The scene model (rs::TraceScene): several geometries, instances, masks, updates ----------- */

/* Trace-only rays (rs::RayView): arrays of exactly `size` elements, any alignment; t in
 * (tnear, tfar] (Embree: [tnear, tfar]); mask NULL: all ones; id is not read. */
typedef struct RSRays {
  const float* ox;
  const float* oy;
  const float* oz;
  const float* dx;
  const float* dy;
  const float* dz;
  const float* tnear;
  const float* tfar;
  const uint32_t* mask;
  const uint32_t* id;
  size_t size;
} RSRays;

/* Closest hits (rs::HitView): a miss has t +inf and prim = geom = inst = -1; ng is the
 * unnormalized geometric normal (p1-p0)x(p2-p0) in world space; inst -1 unless instanced. */
typedef struct RSHits {
  float* t;
  float* u;
  float* v;
  float* ng_x;
  float* ng_y;
  float* ng_z;
  int32_t* prim;
  int32_t* geom;
  int32_t* inst;
  size_t size;
} RSHits;

typedef enum RSIndexType { RS_INDEX_UINT32 = 0, RS_INDEX_UINT16 = 1 } RSIndexType;
/* RS_BUFFER_COPY: positions copied; RS_BUFFER_SHARED: the caller keeps the position buffer alive
 * and unchanged while the scene uses it (rs::BufferMode). */
typedef enum RSBufferMode { RS_BUFFER_COPY = 0, RS_BUFFER_SHARED = 1 } RSBufferMode;

/* rs::GeometryDesc; rsInitGeometryDesc fills the defaults (stride 12, 32-bit indices, mask all
 * ones, copied, not instance-only). */
typedef struct RSGeometryDesc {
  const void* positions;
  size_t num_vertices;
  size_t stride_bytes;
  const void* indices;
  RSIndexType index_type;
  size_t num_triangles;
  uint32_t mask;
  RSBufferMode mode;
  int instance_only; /* 0 or 1 */
} RSGeometryDesc;
RS_C_API void rsInitGeometryDesc(RSGeometryDesc* desc);

/* A scene (rs::TraceScene, same rules): edits take effect at rsSceneCommit; tracing a scene never
 * committed or edited since is an error. rsNewScene returns NULL on error (options NULL: the
 * defaults); rsReleaseScene(NULL) is a no-op. Ids are returned through *geom_id / *inst_id. */
typedef struct RSSceneTy* RSScene;
RS_C_API RSScene rsNewScene(const RSBuildOptions* options);
RS_C_API void rsReleaseScene(RSScene scene);
RS_C_API RSError rsSceneAttachGeometry(RSScene scene, const RSGeometryDesc* desc,
                                       uint32_t* geom_id);
RS_C_API RSError rsSceneReplaceGeometry(RSScene scene, uint32_t geom_id,
                                        const RSGeometryDesc* desc);
RS_C_API RSError rsSceneUpdateGeometry(RSScene scene, uint32_t geom_id, const void* positions,
                                       size_t stride_bytes);
/* transform: 12 floats, 3x4 row-major object to world, invertible and finite. */
RS_C_API RSError rsSceneAttachInstance(RSScene scene, uint32_t geom_id, const float* transform,
                                       uint32_t mask, uint32_t* inst_id);
RS_C_API RSError rsSceneSetInstanceTransform(RSScene scene, uint32_t inst_id,
                                             const float* transform);
RS_C_API RSError rsSceneCommit(RSScene scene);
RS_C_API RSError rsSceneIntersect(RSScene scene, const RSRays* rays, const RSHits* hits);
RS_C_API RSError rsSceneOccluded(RSScene scene, const RSRays* rays, int32_t* occluded);

#ifdef __cplusplus
}
#endif

#endif /* RAYSTREAM_C_H_ */
