// Light buffer (Haines & Greenberg 1986, "The light buffer: a shadow-testing accelerator"): the
// triangles of a scene binned by the directions under which one point light sees them, on the
// six faces of a cube around the light, each cell listing its triangles by ascending distance.
// A shadow ray traced from the light reads the one cell of its direction and tests that cell's
// triangles nearer than its far end; no cell walk. rs::LightBuffer (raystream.h) wraps it.
//
// Why a cell lists every triangle a ray of its directions can hit (the lists are conservative):
// the watertight test (kernels/triangle.h) translates the vertices to the ray origin, here the
// light, in float (rounding relative to each vertex's distance from the light) and decides the
// edge functions on those coordinates; what it accepts lies within a few float ulps of angle of
// the triangle as seen from the light. A triangle is binned into every cell its projection,
// clipped to the face's pyramid widened by kLightMargin and enlarged by kLightMargin (about 84
// float ulps) on each side, overlaps; the ray's face coordinates are rounded once or twice.
// Triangles that pass within 1e-6 of their size of the light (or through it) have no stable
// projection and are listed in an extra list every ray reads.
// Why the distance cut is exact: a triangle at distance `near` from the light is hit at t with
// t |d| >= near up to the rounding of t (relative to the vertices' distances); each reference
// stores reach = near (1 - kLightReachSlack) - kLightReachSlack x (farthest vertex distance),
// rounded down (to a float, then to its 24 leading bits: the build's sort key), and a ray with
// tmax stops reading its cell at the first reach > tmax |d| (rounded up).
#pragma once

#include <hwy/aligned_allocator.h>

#include <cstddef>
#include <cstdint>

#include "include/raystream/raystream.h"
#include "kernels/triangle.h"

namespace rs {

inline constexpr double kLightMargin = 1e-5;       // face coordinates (tangents in [-1, 1])
inline constexpr double kLightReachSlack = 1e-5;   // relative, see above
// Cells per triangle: coarse cells, long lists culled a vector of references at a time. Measured
// (trace_bench light rays, 1024x1024, AVX-512, raystream / Embree rtcOccluded1M, 04:28 UTC, load
// 0.7): 1 cell per triangle office-graz 0.70, conference 0.63, sponza 0.61; 1/4: 0.87, 0.76,
// 0.63; 1/16: 0.85, 1.11, 0.63; 1/32: 0.92, 1.08, 0.89; 1/64: 0.83, 1.26, 0.80; 1/128: 0.70,
// 1.35, 0.73; 1/256: 0.74, 1.18, 0.66.
inline constexpr double kLightCellsPerTriangle = 1.0 / 32.0;
inline constexpr size_t kLightRefsPerTriangle = 8;  // reference budget, as the grid's
inline constexpr int kLightMaxRes = 2048;           // cells per face axis, at most
inline constexpr size_t kLightChunk = 256;          // rays per OccludedLightBuffer call, at most

// The edge-plane cull of a light buffer reference (kernels/light_buffer_trace.cc: a vector of
// references at a time against the box of face coordinates of a walk's rays). For the
// triangle's vertices q_a = v_a - light (in float, as the watertight test translates them) and
// each edge (b, c) in the watertight test's order ((2, 1), (0, 2), (1, 0)), n = q_b x q_c in
// double, over R_b R_c (the vertices' max-norms), on the reference's face (axis k, sign s, u
// and v axes k + 1, k + 2): g(u, v) = a + b u + c v with (a, b, c) = (s n_k, n_u, n_v) / (R_b
// R_c) is the watertight test's exact edge function U* of the ray of face coordinates (u, v),
// over R_b R_c |d_k|. Stored per reference: a, b, c of the three edges and
// M = max over edges of |a| + |b| + |c| (kLightPlaneFloats floats).
// Why the cull is exact: the test's float edge function differs from U* by at most
// 24.2 ulp R_b R_c W + 65 ulp^2 R_b R_c, W bounding the face-coordinate distance |p - l| per
// axis between the ray's (u, v) and every vertex's projection p (the sheared vertex coordinates
// are q_k (p - l), computed with error 4 ulp R; ulp = 2^-24). A reference whose three vertices
// lie on its face (the rectangle holds their projections) culls the rays of a box when, over
// the whole box, one edge's g stays below -tau and another's above tau, with
// tau = ulp (32 W + 16 M) + 2^-40 (W from the box and the rectangle; 16 M ulp covers the float
// evaluation of g, the rounding of a, b, c and of the rays' (u, v)): then the test's float edge
// functions have opposite signs on every ray of the box and it rejects them all. Planes
// computed in float (ProjectLightBlock: n to 4 ulp R_b R_c, the scale to 2 ulp, so g to
// 12.3 ulp + 2 ulp M) store M + 1; in double (the build's other triangles) M. A reference
// whose vertices do not all project into its rectangle (clipped to the face) has sheared
// coordinates within 2 R instead of R W: it stores M + 4 (16 (M + 4) ulp >= 64 ulp = 32 x 2
// ulp). The list every ray reads stores zeros (never culled).
inline constexpr int kLightPlaneFloats = 10;
// The edges (b, c) of the planes, in the watertight test's U, V, W order (n = q_b x q_c).
inline constexpr int kLightPlaneEdges[3][2] = {{2, 1}, {0, 2}, {1, 0}};
inline constexpr double kLightPlaneUlp = 1.0 / 16777216.0;  // 2^-24

// One cube face's cells: a res_u x res_v grid over the window [lo_u, lo_u + res_u / scale_u) x
// [lo_v, ...) of face coordinates that holds every rectangle binned on the face (a light far
// from the scene sees it under a small angle: its cells go where its triangles are). Cell x of
// face coordinate u is (u - lo_u) scale_u, truncated and clamped to [0, res_u - 1], in float in
// the query and in double from the same floats in the build (kLightMargin, tens of ulps,
// covers the difference); cell (x, y) is base + y res_u + x. A face without triangles has one
// empty cell.
struct LightFaces {
  float lo_u[6] = {}, lo_v[6] = {}, scale_u[6] = {}, scale_v[6] = {};
  int32_t res_u[6] = {}, res_v[6] = {}, top_u[6] = {}, top_v[6] = {};  // top = res - 1
  int32_t base[6] = {};
};

struct LightBufferData {
  float light[3] = {0.0f, 0.0f, 0.0f};        // the rays it answers start here (world)
  float frame_light[3] = {0.0f, 0.0f, 0.0f};  // the same in the triangles' frame: light - shift
  int res = 0;              // the largest cells per axis of any face; 0: no triangle can be hit
  LightFaces faces;
  size_t num_cells = 0;     // sum of the faces' res_u res_v; cell num_cells is the list every ray reads
  size_t num_refs = 0;
  size_t num_always = 0;    // length of that list
  // Face f = 2 k + (d[k] < 0) for the axis k of the largest |d|; its u, v axes are k + 1, k + 2
  // (mod 3).
  hwy::AlignedFreeUniquePtr<uint32_t[]> cell_begin;  // num_cells + 2 offsets
  // per reference, in list order: its reach (ascending in each cell) and the triangle's
  // rectangle on the cell's face (u0 u1 v0 v1, as binned, rounded outwards: a ray whose face
  // coordinates fall outside cannot hit it), SoA so that a vector of references is culled at
  // once, each padded by one vector (reach FLT_MAX); and its triangle's id, whose vertices
  // x0 y0 z0 x1 ... z2 are verts[9 id ...] (TriangleSoA::verts of the Accel, borrowed: one
  // table for all the lights instead of 36 B more per reference, which the build and the
  // query's streams paid for every light).
  hwy::AlignedFreeUniquePtr<float[]> reach, u0, u1, v0, v1;
  hwy::AlignedFreeUniquePtr<uint32_t[]> tri;
  const float* verts = nullptr;
  // per reference, the triangle's three edge planes through the light on the cell's face
  // (LightPlanes below): component c of reference j at planes[c * ref_capacity + j]
  hwy::AlignedFreeUniquePtr<float[]> planes;
  size_t cell_capacity = 0, ref_capacity = 0;  // what the arrays hold (kept by rebuilds)

  bool empty() const { return res == 0; }
  const float* Plane(int c) const { return planes.get() + size_t(c) * ref_capacity; }
  const float* Vertices(size_t ref) const { return verts + 9 * size_t(tri[ref]); }
  size_t Bytes() const { return (num_cells + 2) * 4 + num_refs * (6 + kLightPlaneFloats) * 4; }
};

// Builds the light buffer of `tris` (non-degenerate triangles only) for a light at `light`
// (finite; the caller checks) into *out, reusing its arrays (and the temporaries in *reuse,
// if given) where they are large enough. *out borrows tris.verts. shift: the frame of `tris`
// (rs::Accel's, kernels/accel_impl.h; null: the world's): the build and the queries use the
// light at fl(light - shift), as Accel::Occluded translates the rays' origins.
// cells_per_triangle: about that many cells per triangle, lowered while the references would
// pass kLightRefsPerTriangle per triangle. Throws rs::Error if an allocation fails.
struct LightBuildScratch;
void BuildLightBuffer(const TriangleSoA& tris, const float light[3], double cells_per_triangle,
                      LightBufferData* out, LightBuildScratch* reuse = nullptr,
                      const float* shift = nullptr);

// The build's common case a vector of triangles at a time, in float (kernels/light_buffer_trace.cc):
// for triangles [first, first + count <= kLightProjectBlock) whose three vertices lie at least
// kLightMargin of face coordinate inside one face's pyramid, that face's rectangle (widened by kLightMargin: the float
// rounding, a few ulps of a face coordinate, stays far inside it) and a reach from a lower
// bound of the distance (the larger of the plane's and the bounding box's; float error far
// inside the reach slack). face[j] = -1 for the others (several faces, near the light, outside
// 2^30 of it): the scalar double-precision path decides those. Degenerate triangles are the
// caller's to skip. ProjectLightList computes the same for the triangles ids[0, count <=
// kLightProjectBlock) (read from TriangleSoA::verts), with the same float operations (face,
// rectangle and reach equal to ProjectLightBlock's bit for bit), and their edge planes on that
// face (in float; lanes whose face is -1 are the scalar path's).
inline constexpr size_t kLightProjectBlock = 256;
struct LightProjection {
  int32_t face[kLightProjectBlock];
  float u0[kLightProjectBlock], u1[kLightProjectBlock];
  float v0[kLightProjectBlock], v1[kLightProjectBlock];
  float reach[kLightProjectBlock];
};
void ProjectLightBlock(const TriangleSoA& tris, const float light[3], size_t first, size_t count,
                       LightProjection* out);
// ProjectLightList's output: lanes [0, count) at these pointers, each with room for a whole
// vector past count (its last vector is stored whole).
struct LightProjectionOut {
  int32_t* face;
  float *u0, *u1, *v0, *v1, *reach;
  float* planes[kLightPlaneFloats];
};
void ProjectLightList(const TriangleSoA& tris, const float light[3], const uint32_t* ids,
                      size_t count, const LightProjectionOut& out);

// Any hit with t in (tmin, tmax] of the rays [0, size <= kLightChunk) (arrays of any alignment,
// read and occluded written in whole vectors up to PaddedSize(size)) that start exactly at the light (origin
// == light, all three components) with tmin >= 0: occluded[i] = 1 or 0, the result of Accel::Occluded bit for
// bit. The others are left to the caller: their indices are written to far[0, *num_far) in
// ascending order (far holds rays.size entries). stats: rays (at the light), cell_steps (cells
// read: one or two per ray), triangle_tests (lanes tested). No allocation.
void OccludedLightBuffer(const LightBufferData& lb, const RayStreamView& rays, int32_t* occluded,
                         uint32_t* far, size_t* num_far, TraceStats* stats);

}  // namespace rs
