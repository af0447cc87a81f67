// SIMD ray/triangle tests over triangle bundles (kernels/tri_bundles.h), Highway dynamic
// dispatch: 1 ray x 4 triangles (2 or 4 bundles per vector on AVX2/AVX-512) and N rays x 1
// triangle; watertight (Woop, Benthin, Wald 2013) and Moller-Trumbore. Scalar oracles: rs::ref.
#pragma once

#include <cstddef>
#include <cstdint>
#include <limits>

#include "include/raystream/raystream.h"
#include "kernels/tri_bundles.h"
#include "kernels/triangle.h"

namespace rs {

enum class TriTest : int32_t {
  kWatertight = 0,      // the scalar IntersectWatertightPermuted, lane by lane
  kMollerTrumbore = 1,  // the scalar IntersectMollerTrumbore, lane by lane
};

// Triangles per SIMD vector in the 1-ray kernels: kOne = one bundle (4 lanes; 1 lane at a time
// on the SCALAR target), kTwo = 2 bundles (8 lanes) where vectors have >= 8 lanes, kFour = 4
// bundles (16 lanes, AVX-512 only; 8 lanes on AVX2). Each steps down to narrower vectors for a
// cell's remaining bundles. kAuto = the fastest measured on the chosen target: kFour on
// AVX-512, kTwo on AVX2, kOne below (see kAutoBundleLanes). All widths give identical results.
enum class BundleWidth : int32_t { kAuto = 0, kOne = 1, kTwo = 2, kFour = 4 };

// Per-ray constants of the 1-ray kernels: the watertight shear (PrepareWatertightRay; rays
// failing RayIsValid have sz = NaN) and the raw origin and direction for Moller-Trumbore.
struct PreparedRay {
  WatertightRay wt;
  float o[3];
  float d[3];
  bool valid;  // RayIsValid: invalid rays never hit, at the cost of one branch per call
};

inline PreparedRay PrepareRay(float ox, float oy, float oz, float dx, float dy, float dz) {
  PreparedRay r;
  r.wt = PrepareWatertightRay(ox, oy, oz, dx, dy, dz);
  r.o[0] = ox;
  r.o[1] = oy;
  r.o[2] = oz;
  r.d[0] = dx;
  r.d[1] = dy;
  r.d[2] = dz;
  r.valid = RayIsValid(ox, oy, oz, dx, dy, dz);
  return r;
}

// The same from a SIMD setup stored SoA (lane i of arrays o[3], d[3], the permuted origin wo[3],
// shear[3] and k[3], as ValidRayLanes / SetupWatertightLanes produced them); the ray is valid.
inline PreparedRay PreparedRayFromLanes(const float* const o[3], const float* const d[3],
                                        const float* const wo[3], const float* const shear[3],
                                        const int32_t* const k[3], size_t i) {
  PreparedRay r;
  for (int a = 0; a < 3; ++a) {
    r.wt.o[a] = wo[a][i];
    r.o[a] = o[a][i];
    r.d[a] = d[a][i];
  }
  r.wt.sx = shear[0][i];
  r.wt.sy = shear[1][i];
  r.wt.sz = shear[2][i];
  r.wt.kx = k[0][i];
  r.wt.ky = k[1][i];
  r.wt.kz = k[2][i];
  r.valid = true;
  return r;
}

// Closest hit so far of one ray (in/out of IntersectBundles). A fresh one is a miss.
struct ClosestHit {
  float t = std::numeric_limits<float>::infinity();
  float u = 0.0f;  // barycentric of vertex 1
  float v = 0.0f;  // barycentric of vertex 2
  int32_t prim = -1;
};

// Calling from a traversal, per ray: PreparedRay ray = PrepareRay(o, d); ClosestHit hit; then
// per occupied cell: IntersectBundles(ray, bundles.Cell(cell), tmin, tmax, kWatertight, kAuto,
// &hit), and stop when hit.t <= the cell's exit t. Triangles met again in later cells need no
// mailbox for correctness (same t, same id: no change). A SIMD traversal compiled with
// foreach_target includes kernels/tri_intersect-inl.h and calls BundlesT<...> inline instead,
// saving the dynamic dispatch per cell.
//
// 1 ray x the bundles of `tris` (one grid cell), closest hit. A lane hits iff the scalar test
// (TriTest) accepts it with t in (tmin, min(tmax, hit->t)] (+inf tmax is clamped to FLT_MAX,
// as in the scalar tests); it replaces *hit iff t < hit->t, or t == hit->t and its id is lower
// (prim -1 counts as +inf): the scalar DDA's rule, so the result does not depend on the order
// of cells, bundles or lanes. Returns true iff *hit changed.
// Precision: t, u, v and prim are bit-identical to the scalar test on every target (no FMA;
// exact-zero watertight edge functions are redone in double as in the scalar code).
// Padding lanes, NaN-vertex (degenerate) lanes, invalid rays (!ray.valid) and NaN tmin/tmax
// never hit. `tris.vertices` must be 16-B aligned (TriBundles guarantees it). No allocation.
bool IntersectBundles(const PreparedRay& ray, const TriBundleSpan& tris, float tmin, float tmax,
                      TriTest test, BundleWidth width, ClosestHit* hit);

// 1 ray x the bundles of `tris`, any hit with t in (tmin, tmax]: returns true at the first
// vector with a hit. Same validity rules as IntersectBundles.
bool OccludedBundles(const PreparedRay& ray, const TriBundleSpan& tris, float tmin, float tmax,
                     TriTest test, BundleWidth width);

// N rays x 1 triangle, for each triangle of `tris` in turn (rays in lanes, the triangle
// broadcast): updates hits.t/u/v/prim of every ray i < rays.size for which a triangle is
// accepted with the rule of IntersectBundles, taking hits.t[i] and hits.prim[i] as the
// closest hit so far (start from HitStream::Reset: t = +inf, prim = -1) and rays.tmax[i] as
// the upper bound. Results are bit-identical to calling the scalar test per ray and triangle.
// Preconditions: hits.size == rays.size; ox..dz, tmin, tmax, t, u, v, prim are 64-B aligned
// and padded to PaddedSize(size) (RayStream/HitStream). Padding lanes [size, PaddedSize) are
// read but never written with a different value. Per vector of rays the watertight shear is
// set up once (3 divisions) and reused for every triangle of `tris`: pass a whole cell's list.
void IntersectStream(const RayStreamView& rays, const TriBundleSpan& tris, TriTest test,
                     const HitStreamView& hits);

namespace ref {

// Scalar oracles with the same contracts: the triangle.h tests, lane by lane in span order
// (padding lanes, id < 0, are skipped).
bool IntersectBundles(const PreparedRay& ray, const TriBundleSpan& tris, float tmin, float tmax,
                      TriTest test, ClosestHit* hit);
bool OccludedBundles(const PreparedRay& ray, const TriBundleSpan& tris, float tmin, float tmax,
                     TriTest test);
void IntersectStream(const RayStreamView& rays, const TriBundleSpan& tris, TriTest test,
                     const HitStreamView& hits);

}  // namespace ref
}  // namespace rs
