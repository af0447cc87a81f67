// Ray/triangle test cost per Highway target (kernels/tri_intersect.h): 1 ray x 4-wide bundles
// (each bundle width) and N rays x 1 triangle, watertight and Moller-Trumbore, closest and any
// hit, against the scalar oracles, on one cell of 16 or 64 random triangles
// (bench/kernels/tri_workload.h). Names: "<kernel>/<target|ref>/<test>[/<width>]/tris:<n>"; items
// are ray/triangle tests.
//
// Counters: cpu_ticks/test = this thread's CPU time in rdtsc reference ticks (CPU seconds x
// tsc_ghz) of a whole pass divided by its ray/triangle tests (the call and dispatch per ray
// included; step_bench subtracts them); ticks/test = the same from wall-clock rdtsc. Neither is a
// core cycle count: hardware performance counters (cycles, instructions) are not available on
// these machines (KVM guest without a PMU). bench/scripts/run_callgrind.sh counts instructions on the same workload.
#include <benchmark/benchmark.h>
#include <hwy/targets.h>

#include <chrono>
#include <cstdio>
#include <cstring>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "bench/common/bench_main.h"
#include "bench/common/tsc.h"
#include "bench/kernels/tri_workload.h"
#include "kernels/tri_intersect.h"

namespace rs::bench {
namespace {

constexpr size_t kRays = 4096;
constexpr uint32_t kSeed = 20261122;
constexpr float kInf = std::numeric_limits<float>::infinity();

TriWorkload& GetWorkload(size_t num_tris) {
  static std::map<size_t, std::unique_ptr<TriWorkload>> cache;
  auto& slot = cache[num_tris];
  if (!slot) {
    slot = std::make_unique<TriWorkload>();
    MakeTriWorkload(num_tris, kRays, kSeed, slot.get());
  }
  return *slot;
}

const char* TestName(TriTest test) {
  return test == TriTest::kWatertight ? "watertight" : "moller";
}
const char* WidthName(BundleWidth width) {
  switch (width) {
    case BundleWidth::kAuto: return "auto";
    case BundleWidth::kOne: return "x4";
    case BundleWidth::kTwo: return "x8";
    case BundleWidth::kFour: return "x16";
  }
  return "?";
}

enum class Kernel { kClosest1x4, kAny1x4, kStreamNx1 };

// One pass over the workload's rays; results into `hits` (closest, 1 x 4 and N x 1) or `any`.
// target 0 runs the scalar oracle (rs::ref).
void RunPass(const TriWorkload& w, Kernel kernel, TriTest test, BundleWidth width, bool oracle,
             HitStream& hits, std::vector<int32_t>& any) {
  const TriBundleSpan span = w.span();
  if (kernel == Kernel::kStreamNx1) {
    hits.Reset();
    RayStreamView rays = const_cast<RayStream&>(w.rays).view();
    if (oracle) {
      ref::IntersectStream(rays, span, test, hits.view());
    } else {
      IntersectStream(rays, span, test, hits.view());
    }
    return;
  }
  const HitStreamView h = hits.view();
  for (size_t i = 0; i < w.prepared_rays.size(); ++i) {
    const PreparedRay& r = w.prepared_rays[i];
    if (kernel == Kernel::kAny1x4) {
      any[i] = oracle ? ref::OccludedBundles(r, span, 0.0f, kInf, test)
                      : OccludedBundles(r, span, 0.0f, kInf, test, width);
    } else {
      ClosestHit hit;
      if (oracle) {
        ref::IntersectBundles(r, span, 0.0f, kInf, test, &hit);
      } else {
        IntersectBundles(r, span, 0.0f, kInf, test, width, &hit);
      }
      h.t[i] = hit.t;
      h.u[i] = hit.u;
      h.v[i] = hit.v;
      h.prim[i] = hit.prim;
    }
  }
}

void BM_Tri(benchmark::State& state, size_t num_tris, Kernel kernel, TriTest test,
            BundleWidth width, int64_t target) {
  const TriWorkload& w = GetWorkload(num_tris);
  const size_t n = w.rays.size();
  HitStream want(n), got(n);
  want.Resize(n);
  got.Resize(n);
  std::vector<int32_t> want_any(n), got_any(n);
  RunPass(w, kernel, test, width, true, want, want_any);
  if (target != 0) hwy::SetSupportedTargetsForTest(target);
  // Validate once against the oracle, bit for bit, before timing.
  RunPass(w, kernel, test, width, target == 0, got, got_any);
  size_t hit_rays = 0;
  for (size_t i = 0; i < n; ++i) {
    const bool same = kernel == Kernel::kAny1x4
                          ? want_any[i] == got_any[i]
                          : std::memcmp(&want.view().t[i], &got.view().t[i], sizeof(float)) == 0 &&
                                want.view().prim[i] == got.view().prim[i];
    if (!same) {
      hwy::SetSupportedTargetsForTest(0);
      state.SkipWithError(("ray " + std::to_string(i) + " differs from rs::ref").c_str());
      return;
    }
    hit_rays += kernel == Kernel::kAny1x4 ? (want_any[i] != 0) : (want.view().prim[i] >= 0);
  }
  const uint64_t t0 = Ticks();
  const double c0 = ThreadCpuSeconds();
  for (auto _ : state) {
    RunPass(w, kernel, test, width, target == 0, got, got_any);
    benchmark::ClobberMemory();
  }
  const double cpu = ThreadCpuSeconds() - c0;
  const double ticks = static_cast<double>(Ticks() - t0);
  hwy::SetSupportedTargetsForTest(0);
  const double tests =
      static_cast<double>(state.iterations()) * static_cast<double>(w.tests_per_pass());
  state.SetItemsProcessed(static_cast<int64_t>(tests));
  state.counters["cpu_ticks/test"] = cpu * TscGhz() * 1e9 / tests;
  state.counters["ticks/test"] = ticks / tests;
  state.counters["hit_rays"] = static_cast<double>(hit_rays) / static_cast<double>(n);
  // Any-hit stops early: count what ran as if every lane were tested (an upper bound), and say so.
  if (kernel == Kernel::kAny1x4) state.SetLabel("items = all lanes (early exit not subtracted)");
}

void RegisterAll() {
  std::vector<std::pair<int64_t, std::string>> targets;
  for (const int64_t t : hwy::SupportedAndGeneratedTargets())
    targets.push_back({t, hwy::TargetName(t)});
  targets.push_back({0, "ref"});
  for (const size_t num_tris : {size_t{16}, size_t{64}}) {
    const std::string tris = "/tris:" + std::to_string(num_tris);
    for (const auto& [target, tname] : targets) {
      for (const TriTest test : {TriTest::kWatertight, TriTest::kMollerTrumbore}) {
        const std::string tn = std::string(TestName(test));
        const bool oracle = target == 0;
        for (const BundleWidth width :
             {BundleWidth::kAuto, BundleWidth::kOne, BundleWidth::kTwo, BundleWidth::kFour}) {
          if (oracle && width != BundleWidth::kAuto) continue;
          const std::string wn = oracle ? "" : std::string("/") + WidthName(width);
          benchmark::RegisterBenchmark(("Tri1x4/" + tname + "/" + tn + wn + tris).c_str(), BM_Tri,
                                       num_tris, Kernel::kClosest1x4, test, width, target)
              ->Unit(benchmark::kMicrosecond);
        }
        benchmark::RegisterBenchmark(("TriNx1/" + tname + "/" + tn + tris).c_str(), BM_Tri,
                                     num_tris, Kernel::kStreamNx1, test, BundleWidth::kAuto, target)
            ->Unit(benchmark::kMicrosecond);
      }
      const std::string wn = target == 0 ? "" : "/auto";
      benchmark::RegisterBenchmark(("TriAny1x4/" + tname + "/watertight" + wn + tris).c_str(),
                                   BM_Tri, num_tris, Kernel::kAny1x4, TriTest::kWatertight,
                                   BundleWidth::kAuto, target)
          ->Unit(benchmark::kMicrosecond);
    }
  }
}

}  // namespace
}  // namespace rs::bench

int main(int argc, char** argv) {
  return rs::bench::RunBenchmarkMain(
      argc, argv,
      {{"ticks", "cpu_ticks/test = thread CPU time x tsc_ghz of a pass / its ray/triangle tests "
                 "(ticks/test: wall-clock rdtsc); hardware perf counters (core cycles) are not "
                 "available on these machines (KVM guest without a PMU)"},
       {"workload", "1 cell of 16 or 64 random triangles, 4096 rays "
                    "(bench/kernels/tri_workload.h); items = ray/triangle tests"}},
      rs::bench::RegisterAll);
}
