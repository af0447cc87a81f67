/* A C program that links raystream: build a grid over its own quad, trace 5 rays (exact-size,
 * unaligned arrays) for closest hits and occlusion, check the results, then check that misuse is
 * an error code and reaches the error callback; then a scene of two geometries (32- and 16-bit
 * indices, a byte stride, masks) and an instance, traced, updated and traced again, with geomID,
 * instID, t and Ng checked against the exact values. Uses only <raystream/raystream_c.h>. */
#include <raystream/raystream_c.h>

#include <math.h>
#include <stdio.h>
#include <string.h>

static int g_callbacks = 0;
static void OnError(void* user, RSError code, const char* message) {
  (void)user;
  ++g_callbacks;
  printf("error callback: %d %s\n", (int)code, message);
}

/* The scene part: returns the number of wrong results. */
static int RunScene(void) {
  float quad0[] = {0, 0, 0, 1, 0, 0, 1, 1, 0, 0, 1, 0}; /* z = 0, x in [0, 1] */
  const uint32_t idx32[] = {0, 1, 2, 0, 2, 3};
  const float quad1[] = {2, 0, 0.5f, 9, 3, 0, 0.5f, 9, 3, 1, 0.5f, 9, 2, 1, 0.5f, 9}; /* stride 16 B */
  const uint16_t idx16[] = {0, 1, 2, 0, 2, 3};
  const float xfm[12] = {2, 0, 0, 4, 0, 2, 0, 0, 0, 0, 0.5f, -1}; /* x in [4, 6], z = -1 */
  int failures = 0;
  RSScene scene = rsNewScene(NULL);
  if (scene == NULL) return 1;
  RSGeometryDesc g;
  rsInitGeometryDesc(&g);
  g.positions = quad0, g.num_vertices = 4, g.indices = idx32, g.num_triangles = 2, g.mask = 1;
  uint32_t geom0 = 0, geom1 = 0, inst0 = 0;
  if (rsSceneAttachGeometry(scene, &g, &geom0) != RS_ERROR_NONE) ++failures;
  g.positions = quad1, g.stride_bytes = 16, g.indices = idx16, g.index_type = RS_INDEX_UINT16;
  g.mask = 2, g.mode = RS_BUFFER_SHARED;
  if (rsSceneAttachGeometry(scene, &g, &geom1) != RS_ERROR_NONE) ++failures;
  /* An instance of geometry 0 (the copy taken at attach time), mask 4. */
  if (rsSceneAttachInstance(scene, geom0, xfm, 4, &inst0) != RS_ERROR_NONE) ++failures;
  if (rsSceneCommit(scene) != RS_ERROR_NONE) ++failures;

  enum { kRays = 5 };
  const float xs[kRays] = {0.5f, 2.5f, 2.5f, 5.0f, 5.0f};
  const uint32_t mask[kRays] = {~0u, ~0u, 1u, ~0u, 3u}; /* ray 2 skips geometry 1, 4 the instance */
  float ox[kRays], oy[kRays], oz[kRays], dx[kRays], dy[kRays], dz[kRays], tn[kRays], tf[kRays];
  for (int i = 0; i < kRays; ++i) {
    ox[i] = xs[i], oy[i] = 0.25f, oz[i] = 2.0f, dx[i] = 0, dy[i] = 0, dz[i] = -1;
    tn[i] = 0, tf[i] = INFINITY;
  }
  RSRays rays = {ox, oy, oz, dx, dy, dz, tn, tf, mask, NULL, kRays};
  float t[kRays], u[kRays], v[kRays], nx[kRays], ny[kRays], nz[kRays];
  int32_t prim[kRays], geom[kRays], inst[kRays];
  RSHits hits = {t, u, v, nx, ny, nz, prim, geom, inst, kRays};
  const int32_t want_geom[kRays] = {(int32_t)geom0, (int32_t)geom1, -1, (int32_t)geom0, -1};
  const int32_t want_inst[kRays] = {-1, -1, -1, (int32_t)inst0, -1};
  float want_t[kRays] = {2.0f, 1.5f, INFINITY, 3.0f, INFINITY};
  const float want_nz[kRays] = {1, 1, 0, 2, 0};
  for (int pass = 0; pass < 2; ++pass) {
    if (rsSceneIntersect(scene, &rays, &hits) != RS_ERROR_NONE) ++failures;
    for (int i = 0; i < kRays; ++i) {
      printf("scene pass %d ray %d: geom %d inst %d prim %d t %.3f Ng (%.1f %.1f %.1f)\n", pass, i,
             geom[i], inst[i], prim[i], t[i], nx[i], ny[i], nz[i]);
      if (geom[i] != want_geom[i] || inst[i] != want_inst[i] || nz[i] != want_nz[i]) ++failures;
      if (isinf(want_t[i]) ? !isinf(t[i]) : fabsf(t[i] - want_t[i]) > 1e-6f * want_t[i]) ++failures;
    }
    /* Move geometry 0 down to z = -0.5: its grid is rebuilt, the instance follows it. */
    for (int k = 0; k < 4; ++k) quad0[3 * k + 2] = -0.5f;
    if (rsSceneUpdateGeometry(scene, geom0, quad0, 12) != RS_ERROR_NONE) ++failures;
    if (rsSceneIntersect(scene, &rays, &hits) != RS_ERROR_INVALID_ARGUMENT) ++failures; /* edited */
    (void)rsGetError();
    if (rsSceneCommit(scene) != RS_ERROR_NONE) ++failures;
    want_t[0] = 2.5f, want_t[3] = 3.25f; /* instance: z = 0.5 * -0.5 - 1 */
  }
  rsReleaseScene(scene);
  return failures;
}

int main(void) {
  const float positions[] = {0, 0, 0, 1, 0, 0, 1, 1, 0, 0, 1, 0};
  const uint32_t indices[] = {0, 1, 2, 0, 2, 3};
  RSMesh mesh = {positions, 4, 3, indices, 2};
  rsSetErrorFunction(OnError, NULL);
  RSAccel accel = rsNewAccel(&mesh, NULL);
  if (accel == NULL) return 1;

  enum { kRays = 5 };
  const float xs[kRays] = {0.25f, 0.75f, 0.5f, 2.0f, 0.5f};
  const float ys[kRays] = {0.75f, 0.25f, 0.5f, 2.0f, 0.5f};
  float ox[kRays], oy[kRays], oz[kRays], dx[kRays], dy[kRays], dz[kRays], tmin[kRays], tmax[kRays];
  for (int i = 0; i < kRays; ++i) {
    ox[i] = xs[i], oy[i] = ys[i], oz[i] = 2.0f;
    dx[i] = 0.0f, dy[i] = 0.0f, dz[i] = -1.0f;
    tmin[i] = 0.0f, tmax[i] = i == 4 ? 1.5f : INFINITY; /* ray 4 stops short of the quad */
  }
  RSRayStream rays = {ox, oy, oz, dx, dy, dz, tmin, tmax, kRays};
  float t[kRays], u[kRays], v[kRays];
  int32_t prim[kRays], occluded[kRays];
  RSHitStream hits = {t, u, v, prim, kRays};
  int failures = 0;
  if (rsIntersect(accel, &rays, &hits) != RS_ERROR_NONE) ++failures;
  if (rsOccluded(accel, &rays, occluded) != RS_ERROR_NONE) ++failures;
  for (int i = 0; i < kRays; ++i) {
    printf("ray %d: prim %d t %.3f u %.3f v %.3f occluded %d\n", i, prim[i], t[i], u[i], v[i],
           occluded[i]);
    const int should_hit = i < 3;
    if ((prim[i] >= 0) != should_hit || (occluded[i] != 0) != should_hit) ++failures;
    if (should_hit && fabsf(t[i] - 2.0f) > 1e-6f) ++failures;
  }
  RSAccelInfo info;
  if (rsGetAccelInfo(accel, &info) != RS_ERROR_NONE || info.triangles != 2) ++failures;

  /* Misuse: an error code, the thread's last error, the callback; never a crash. */
  RSHitStream short_hits = {t, u, v, prim, kRays - 1};
  if (rsIntersect(accel, &rays, &short_hits) != RS_ERROR_INVALID_ARGUMENT) ++failures;
  if (rsGetError() != RS_ERROR_INVALID_ARGUMENT) ++failures;
  if (strstr(rsGetErrorMessage(), "hits.size") == NULL) ++failures;
  if (rsGetError() != RS_ERROR_NONE) ++failures; /* cleared */
  RSRayStream no_tmin = rays;
  no_tmin.tmin = NULL;
  if (rsOccluded(accel, &no_tmin, occluded) != RS_ERROR_INVALID_ARGUMENT) ++failures;
  if (rsIntersect(NULL, &rays, &hits) != RS_ERROR_INVALID_ARGUMENT) ++failures;
  const uint32_t bad_indices[] = {0, 1, 7};
  RSMesh bad = {positions, 4, 3, bad_indices, 1};
  if (rsNewAccel(&bad, NULL) != NULL) ++failures;
  RSBuildOptions options;
  rsInitBuildOptions(&options);
  options.lambda = -1.0f;
  if (rsNewAccel(&mesh, &options) != NULL) ++failures;
  if (g_callbacks != 5) ++failures;

  /* A moving mesh: the quad moved to z = -1 and rebuilt in place; a bad rebuild is an error and
   * the accel is not traced until it is rebuilt. */
  float moved[12];
  for (int k = 0; k < 12; ++k) moved[k] = k % 3 == 2 ? -1.0f : positions[k];
  RSMesh moved_mesh = {moved, 4, 3, indices, 2};
  if (rsRebuildAccel(accel, &moved_mesh, NULL) != RS_ERROR_NONE) ++failures;
  if (rsIntersect(accel, &rays, &hits) != RS_ERROR_NONE || fabsf(t[0] - 3.0f) > 1e-6f) ++failures;
  if (rsRebuildAccel(accel, &bad, NULL) != RS_ERROR_INVALID_ARGUMENT) ++failures;
  if (rsIntersect(accel, &rays, &hits) == RS_ERROR_NONE) ++failures;
  if (strstr(rsGetErrorMessage(), "Rebuild failed") == NULL) ++failures;
  if (rsRebuildAccel(accel, &mesh, NULL) != RS_ERROR_NONE) ++failures;
  if (rsIntersect(accel, &rays, &hits) != RS_ERROR_NONE || fabsf(t[0] - 2.0f) > 1e-6f) ++failures;
  if (g_callbacks != 7) ++failures;
  failures += RunScene();
  rsReleaseAccel(accel);
  rsReleaseAccel(NULL);
  printf("raystream %s (C API): %s\n", rsGetVersion(), failures == 0 ? "ok" : "WRONG");
  return failures == 0 ? 0 : 1;
}
