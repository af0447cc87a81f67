/* A C program that links raystream: build a grid over its own quad, trace 5 rays (exact-size,
 * unaligned arrays) for closest hits and occlusion, check the results, then check that misuse is
 * an error code and reaches the error callback. Uses only <raystream/raystream_c.h>. */
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
  rsReleaseAccel(accel);
  rsReleaseAccel(NULL);
  printf("raystream %s (C API): %s\n", rsGetVersion(), failures == 0 ? "ok" : "WRONG");
  return failures == 0 ? 0 : 1;
}
