// Stable stream compaction (see compact.h). Scalar for now; a Highway CompressStore version
// can sit beside it, checked against this one.
#include "streams/compact.h"

namespace rs {

namespace {

template <typename T>
void MoveIfPresent(T* a, size_t to, size_t from) {
  if (a != nullptr) a[to] = a[from];
}

}  // namespace

size_t CompactRays(const RayStreamView& rays, const int32_t* keep) {
  size_t n = 0;
  for (size_t i = 0; i < rays.size; ++i) {
    if (keep[i] == 0) continue;
    if (n != i) {  // n < i: moving forward never overwrites a ray not yet visited
      rays.ox[n] = rays.ox[i];
      rays.oy[n] = rays.oy[i];
      rays.oz[n] = rays.oz[i];
      rays.dx[n] = rays.dx[i];
      rays.dy[n] = rays.dy[i];
      rays.dz[n] = rays.dz[i];
      rays.tmin[n] = rays.tmin[i];
      rays.tmax[n] = rays.tmax[i];
      MoveIfPresent(rays.pixel, n, i);
      MoveIfPresent(rays.wr, n, i);
      MoveIfPresent(rays.wg, n, i);
      MoveIfPresent(rays.wb, n, i);
      MoveIfPresent(rays.depth, n, i);
      MoveIfPresent(rays.kind, n, i);
    }
    ++n;
  }
  return n;
}

size_t CompactRays(RayStream& rays, const int32_t* keep) {
  const size_t n = CompactRays(rays.view(), keep);
  rays.Resize(n);
  rays.FillPadding();
  return n;
}

}  // namespace rs
