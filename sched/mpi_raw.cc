// The hidden raw framebuffer dump (--dump-raw) of every backend, and whether MPI was built in:
// exact integer images make "bit-identical to the serial backend" checkable from a shell test.
#include <cstdio>
#include <fstream>
#include <string>

#include <fmt/core.h>

#include "include/raystream/raystream.h"
#include "sched/mpi_backend.h"
#include "scenes/image_io.h"  // WriteFileAtomically

namespace rs {

bool MpiBuilt() {
#ifdef RS_HAVE_MPI
  return true;
#else
  return false;
#endif
}

std::string RawFramebufferBytes(const Framebuffer& fb) {
  const int32_t size[2] = {fb.width(), fb.height()};
  std::string bytes = "RSFB";
  bytes.append(reinterpret_cast<const char*>(size), sizeof(size));
  bytes.append(reinterpret_cast<const char*>(fb.sums()), fb.num_pixels() * 3 * sizeof(int64_t));
  return bytes;
}

void WriteRawFramebuffer(const std::string& path, const Framebuffer& fb) {
  WriteFileAtomically(path, RawFramebufferBytes(fb), "raw framebuffer");
}

}  // namespace rs
