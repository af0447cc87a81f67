// Stable stream compaction: keeps the rays whose flag is nonzero, in order. Used to drop dead
// lanes (occluded shadow rays, terminated paths) so later kernels run on full vectors.
#pragma once

#include <cstddef>
#include <cstdint>

#include "include/raystream/raystream.h"
#include "streams/ray_stream.h"

namespace rs {

// In place on a view: ray i (0 <= i < rays.size) is kept iff keep[i] != 0; kept rays move to
// [0, n) in their original order and n is returned. Rays [n, rays.size) are left unspecified;
// rays.size is not changed (a view cannot). Optional arrays (pixel, weights, depth, kind) are
// moved when non-null. `keep` must not alias a ray array. Never allocates.
size_t CompactRays(const RayStreamView& rays, const int32_t* keep);

// Owning version: compacts, sets the stream's size to n and refills the padding lanes
// [n, capacity) with the never-hitting sentinel ray (RayStream::FillPadding). Returns n.
size_t CompactRays(RayStream& rays, const int32_t* keep);

}  // namespace rs
