// Stable stream compaction (see compact.h), scalar: a loop of copies over the SoA arrays.
#include "streams/compact.h"

namespace rs {

size_t CompactRays(const RayStreamView& rays, const int32_t* keep) {
  size_t n = 0;
  for (size_t i = 0; i < rays.size; ++i) {
    if (keep[i] == 0) continue;
    if (n != i) CopyRay(rays, i, rays, n);  // n < i: never overwrites a ray not yet visited
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
