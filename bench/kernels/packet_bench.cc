// Coherent 64-ray packets (kernels/packet_dda.h) against the per-ray stream DDA, per Highway
// target, on the ANCHORS.md ray sets (bench/peer/ray_sets.h): primary rays in scanline order and
// one shadow ray per primary hit. "Packet/<target>/<scene>/<set>" runs IntersectCoherent /
// OccludedCoherent, "PerRay/<target>/<scene>/<set>" IntersectStreamDda / OccludedStreamDda on the
// same structure (rs::Accel's, cost-model grid). Both are validated once against each other
// (identical hits) before timing. Counters: cpu_ticks/ray (thread CPU time in rdtsc ticks; not core
// cycles: no hardware counters on these machines), packet_share (rays traced in packets),
// cells/ray and tests/ray. Environment: RS_BENCH_SIZE=WxH (default 512x512), RS_BENCH_SCENES=a,b.
// Under callgrind (bench/scripts/run_callgrind.sh) it gives instructions per ray of both forms.
#include <benchmark/benchmark.h>
#include <hwy/targets.h>

#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "bench/common/tsc.h"
#include "bench/peer/ray_sets.h"
#include "include/raystream/raystream.h"
#include "kernels/accel_impl.h"
#include "kernels/dda_simd.h"
#include "kernels/packet_dda.h"
#include "scenes/load.h"
#include "streams/ray_stream.h"

namespace rs::bench {
namespace {

struct Data {
  Scene scene;
  std::unique_ptr<Accel> accel;
  RayStream primary, shadow;
  HitStream hits;
  std::vector<int32_t> occluded;
  std::string error;
};

int g_width = 512, g_height = 512;

Data& Get(const std::string& name) {
  static std::map<std::string, std::unique_ptr<Data>> cache;
  auto& slot = cache[name];
  if (slot) return *slot;
  slot = std::make_unique<Data>();
  Data& d = *slot;
  try {
    d.scene = LoadScene(name);
    d.accel = std::make_unique<Accel>(d.scene.mesh());
    MakePrimaryRays(d.scene, g_width, g_height, d.primary);
    HitStream h(d.primary.size());
    h.Resize(d.primary.size());
    d.accel->Intersect(d.primary.view(), h.view());
    MakeShadowRays(d.scene, d.primary.view(), h.view(), BenchLight(d.scene), d.shadow);
    const size_t n = std::max(d.primary.size(), d.shadow.size());
    d.hits = HitStream(n);
    d.hits.Resize(n);
    d.occluded.resize(n + 1);
  } catch (const Error& e) {
    d.error = e.what();
  }
  return d;
}

// Runs one form over one set; returns the results for the validation.
void Run(Data& d, bool shadow, bool packets, TraceStats* st, HitStreamView hits,
         int32_t* occluded) {
  const Accel::Impl& m = AccelImpl(*d.accel);
  const RayStreamView rays = shadow ? d.shadow.view() : d.primary.view();
  hits.size = rays.size;
  ForEachFramePiece(m, rays, rays.size, [&](const RayStreamView& r, size_t first) {
    const HitStreamView h = SubView(hits, first, r.size);
    int32_t* const o = occluded + first;
    if (shadow) {
      packets ? OccludedCoherent(m.dda, r, o, m.dda_options, st)
              : OccludedStreamDda(m.dda, r, o, m.dda_options, st);
    } else {
      packets ? IntersectCoherent(m.dda, r, h, m.dda_options, st)
              : IntersectStreamDda(m.dda, r, h, m.dda_options, st);
    }
  });
}

std::string Validate(Data& d, bool shadow) {
  const size_t n = shadow ? d.shadow.size() : d.primary.size();
  HitStream a(n), b(n);
  a.Resize(n);
  b.Resize(n);
  std::vector<int32_t> oa(n + 1), ob(n + 1);
  Run(d, shadow, true, nullptr, a.view(), oa.data());
  Run(d, shadow, false, nullptr, b.view(), ob.data());
  size_t bad = 0;
  for (size_t i = 0; i < n; ++i) {
    if (shadow) {
      bad += oa[i] != ob[i];
    } else {
      bad += a.view().prim[i] != b.view().prim[i] ||
             std::memcmp(&a.view().t[i], &b.view().t[i], sizeof(float)) != 0;
    }
  }
  return bad == 0 ? "" : std::to_string(bad) + " rays differ between packets and per-ray walk";
}

void BM(benchmark::State& state, const std::string& scene, bool shadow, bool packets,
        int64_t target) {
  Data& d = Get(scene);
  if (!d.error.empty()) {
    state.SkipWithError(d.error.c_str());
    return;
  }
  hwy::SetSupportedTargetsForTest(target);
  const std::string error = Validate(d, shadow);
  if (!error.empty()) {
    hwy::SetSupportedTargetsForTest(0);
    state.SkipWithError(error.c_str());
    return;
  }
  const size_t n = shadow ? d.shadow.size() : d.primary.size();
  TraceStats st;
  Run(d, shadow, packets, &st, d.hits.view(), d.occluded.data());
  const double c0 = ThreadCpuSeconds();
  for (auto _ : state) {
    Run(d, shadow, packets, nullptr, d.hits.view(), d.occluded.data());
    benchmark::ClobberMemory();
  }
  const double cpu = ThreadCpuSeconds() - c0;
  const double items = double(state.iterations()) * double(n);
  state.counters["cpu_ticks/ray"] = items > 0 ? cpu * TscGhz() * 1e9 / items : 0;
  state.counters["cells/ray"] = double(st.cell_steps) / double(n);
  state.counters["tests/ray"] = double(st.triangle_tests) / double(n);
  if (packets) state.counters["packet_share"] = double(st.packet_rays) / double(st.rays);
  state.SetItemsProcessed(int64_t(items));
  hwy::SetSupportedTargetsForTest(0);
}

}  // namespace
}  // namespace rs::bench

int main(int argc, char** argv) {
  using namespace rs::bench;
  BenchSize("packet_bench", &g_width, &g_height);
  // a scene that does not load is skipped with its error (Get)
  for (const std::string& scene :
       BenchScenes({"bunny", "sponza", "office-graz", "conference", "spherebox"})) {
    for (const bool shadow : {false, true}) {
      for (const int64_t t : hwy::SupportedAndGeneratedTargets()) {
        for (const bool packets : {true, false}) {
          const std::string name = std::string(packets ? "Packet/" : "PerRay/") +
                                   hwy::TargetName(t) + "/" + scene +
                                   (shadow ? "/shadow" : "/primary");
          benchmark::RegisterBenchmark(name.c_str(), BM, scene, shadow, packets, t)
              ->Unit(benchmark::kMillisecond);
        }
      }
    }
  }
  benchmark::Initialize(&argc, argv);
  std::printf("cycles: cpu_ticks/ray = thread CPU time x tsc_ghz per ray (rdtsc reference ticks, "
              "not core cycles: hardware perf counters are not available on these machines)\n");
  benchmark::RunSpecifiedBenchmarks();
  benchmark::Shutdown();
  return 0;
}
