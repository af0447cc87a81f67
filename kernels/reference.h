// Test oracle: the watertight ray/triangle test in double precision on double-converted
// inputs, brute force over every triangle (no grid), plus a chunked variant (Morton-sorted
// triangle chunks with double boxes) that gives the same answers fast enough for big meshes.
#pragma once

#include <cstddef>
#include <cstdint>
#include <limits>
#include <vector>

#include "include/raystream/raystream.h"

namespace rs::ref {

// A ray converted to double once (float -> double is exact), with the watertight test's
// per-ray constants (kx, ky, kz, shear) computed in double. valid is false for rays that
// never hit (rs::RayIsValid: NaN/Inf component or |d| < kMinDirection on every axis).
struct Ray {
  double o[3];
  double d[3];
  double tmin;
  double tmax;
  double sx, sy, sz;
  int kx, ky, kz;
  bool valid;
};
Ray MakeRay(float ox, float oy, float oz, float dx, float dy, float dz, float tmin, float tmax);

// prim = -1, t = +inf for a miss.
struct Hit {
  double t = std::numeric_limits<double>::infinity();
  double u = 0.0;  // barycentric of vertex 1
  double v = 0.0;  // barycentric of vertex 2
  int32_t prim = -1;
};

// Watertight test (Woop, Benthin, Wald 2013) in double on double vertices: t in
// (ray.tmin, tmax], both windings. Does not check degeneracy (the callers skip triangles
// rs::IsDegenerateTriangle flags). Returns false for invalid rays.
bool IntersectTriangle(const Ray& ray, const double p0[3], const double p1[3],
                       const double p2[3], double tmax, Hit* hit);

// The float vertices of triangle i of `mesh`, converted to double.
void TriangleVertices(const MeshView& mesh, size_t i, double p[3][3]);

// Brute force over all non-degenerate triangles: the closest hit in (tmin, tmax]; on equal t
// the lowest triangle id wins. O(triangles) per ray.
Hit IntersectClosest(const MeshView& mesh, const Ray& ray);
// True if any non-degenerate triangle is hit in (tmin, tmax].
bool IntersectAny(const MeshView& mesh, const Ray& ray);

// Same answers as IntersectClosest / IntersectAny (identical tie rule), but triangles are
// sorted by the Morton code of their centroid into chunks of 16, chunks into groups of 32,
// each with a double bounding box enlarged by 1e-9 of the scene size; a ray tests only the
// triangles of chunks whose box its segment (tmin, best t] touches. Independent of the grid
// code on purpose. Copies what it needs; the mesh may be freed afterwards.
class ChunkedMesh {
 public:
  explicit ChunkedMesh(const MeshView& mesh);
  Hit IntersectClosest(const Ray& ray) const;
  bool IntersectAny(const Ray& ray) const;
  size_t triangles() const { return ids_.size(); }

 private:
  struct Box {
    double lo[3];
    double hi[3];
  };
  static bool SegmentTouches(const Box& box, const Ray& ray, double tmax);
  template <bool kAnyHit>
  bool Trace(const Ray& ray, Hit* hit) const;

  std::vector<double> verts_;  // 9 per sorted triangle
  std::vector<int32_t> ids_;   // mesh id of each sorted triangle
  std::vector<Box> chunk_boxes_;
  std::vector<Box> group_boxes_;
};

}  // namespace rs::ref
