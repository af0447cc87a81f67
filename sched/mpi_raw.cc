// The hidden raw framebuffer dump (--dump-raw) of every backend, and whether MPI was built in:
// exact integer images make "bit-identical to the serial backend" checkable from a shell test.
#include <cstdio>
#include <fstream>
#include <string>

#include <fmt/core.h>

#include "include/raystream/raystream.h"
#include "sched/mpi_backend.h"

namespace rs {

bool MpiBuilt() {
#ifdef RS_HAVE_MPI
  return true;
#else
  return false;
#endif
}

void WriteRawFramebuffer(const std::string& path, const Framebuffer& fb) {
  const std::string tmp = path + ".tmp";
  {
    std::ofstream f(tmp, std::ios::binary | std::ios::trunc);
    if (!f) throw Error(fmt::format("{}: cannot open for writing", path));
    const int32_t size[2] = {fb.width(), fb.height()};
    f.write("RSFB", 4);
    f.write(reinterpret_cast<const char*>(size), sizeof(size));
    f.write(reinterpret_cast<const char*>(fb.sums()),
            static_cast<std::streamsize>(fb.num_pixels() * 3 * sizeof(int64_t)));
    if (!f) {
      std::remove(tmp.c_str());
      throw Error(fmt::format("{}: write failed", path));
    }
  }
  if (std::rename(tmp.c_str(), path.c_str()) != 0) {
    std::remove(tmp.c_str());
    throw Error(fmt::format("{}: cannot rename the temporary file into place", path));
  }
}

}  // namespace rs
