// Callgrind driver for the any-hit packet kernel: one OccludedCoherent pass over the shadow rays
// of packet_bench (one per primary hit of a WxH image, BenchLight), checked against the per-ray
// OccludedStreamDda first. Count its instructions with
//   valgrind --tool=callgrind --toggle-collect='*OccludedCoherent*' shadow_counts SCENE [W H]
// and divide the Ir by the `rays` it prints. Prints the TraceStats of the pass.
#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>

#include "bench/peer/ray_sets.h"
#include "include/raystream/raystream.h"
#include "kernels/accel_impl.h"
#include "kernels/dda_simd.h"
#include "kernels/packet_dda.h"
#include "scenes/load.h"
#include "streams/ray_stream.h"

int main(int argc, char** argv) {
  using namespace rs;
  if (argc < 2) {
    std::fprintf(stderr, "usage: %s SCENE [WIDTH HEIGHT]\n", argv[0]);
    return 2;
  }
  const int width = argc > 3 ? std::atoi(argv[2]) : 1024;
  const int height = argc > 3 ? std::atoi(argv[3]) : 1024;
  try {
    const Scene scene = LoadScene(argv[1]);
    const Accel accel(scene.mesh());
    RayStream primary, shadow;
    bench::MakePrimaryRays(scene, width, height, primary);
    HitStream h(primary.size());
    h.Resize(primary.size());
    accel.Intersect(primary.view(), h.view());
    bench::MakeShadowRays(scene, primary.view(), h.view(), bench::BenchLight(scene), shadow);
    const Accel::Impl& m = AccelImpl(accel);
    const size_t n = shadow.size();
    std::vector<int32_t> a(n + 1), b(n + 1);
    TraceStats st;
    ForEachFramePiece(m, shadow.view(), n, [&](const RayStreamView& r, size_t first) {
      OccludedStreamDda(m.dda, r, b.data() + first, m.dda_options, nullptr);
      OccludedCoherent(m.dda, r, a.data() + first, m.dda_options, &st);
    });
    size_t bad = 0, occluded = 0;
    for (size_t i = 0; i < n; ++i) {
      bad += a[i] != b[i];
      occluded += a[i] != 0;
    }
    std::printf("shadow_counts: scene=%s rays=%zu occluded=%zu differ=%zu packets=%llu "
                "refused=%llu regrouped=%llu packet_rays=%llu cells=%llu tests=%llu\n",
                argv[1], n, occluded, bad, (unsigned long long)st.packets,
                (unsigned long long)st.packets_refused, (unsigned long long)st.packets_regrouped,
                (unsigned long long)st.packet_rays, (unsigned long long)st.cell_steps,
                (unsigned long long)st.triangle_tests);
    return bad == 0 ? 0 : 1;
  } catch (const Error& e) {
    std::fprintf(stderr, "%s\n", e.what());
    return 1;
  }
}
