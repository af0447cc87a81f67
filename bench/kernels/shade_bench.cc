// Shading cost per SIMD target against the scalar oracle: rdtsc ticks per shaded hit for rs::Shade
// forced to each Highway target (hwy::SetSupportedTargetsForTest) and for rs::ref::Shade, on the
// primary hits of erw6 and spherebox, in streams of 1024 rays and in renderer-sized tasks of 20
// rays. Names: "shade/<scene>/<stream1024|task20>/<TARGET|ref>". Every target is validated against
// ref:: (framebuffer bits and the multiset of rays) before anything is timed.
//
// Cycle counts: hardware perf counters (cycles, instructions) are not available on these
// machines (KVM guest without a PMU: `perf stat -e cycles` says <not supported>), so the counters
// are rdtsc reference ticks at the constant TSC rate (tsc_ghz in the context), not core cycles:
// ticks/hit is wall clock, cpu_ticks/hit is this thread's CPU time converted at the TSC rate.
#include <benchmark/benchmark.h>
#include <hwy/targets.h>

#include <algorithm>
#include <array>
#include <bit>
#include <chrono>
#include <cstdio>
#include <cstring>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "bench/common/bench_main.h"
#include "bench/common/tsc.h"
#include "kernels/shade.h"
#include "scenes/load.h"
#include "sched/framebuffer.h"
#include "streams/ray_stream.h"
#include "streams/raygen.h"

namespace rs::bench {
namespace {

// 64x64 primary hits: inputs (~300 KB) stay in L2 across iterations, as a task's rays and hits
// do in the renderer (they were just traced); outputs go to a per-chunk buffer that stays hot.
constexpr int kWidth = 64;
constexpr int kHeight = 64;
constexpr size_t kStreamChunk = 1024;
constexpr size_t kTaskSize = 20;

// A scene, its accel and the primary rays of a kWidth x kHeight image with their closest hits.
struct Workload {
  Scene scene;
  std::unique_ptr<Accel> accel;
  RayStream rays;
  HitStream hits;
  size_t num_hits = 0;
  ShadeOptions options;
  std::string error;  // validation failure: every benchmark of the scene is skipped
};

Workload& GetWorkload(const std::string& name) {
  static std::map<std::string, std::unique_ptr<Workload>> cache;
  auto& slot = cache[name];
  if (slot) return *slot;
  slot = std::make_unique<Workload>();
  Workload& w = *slot;
  w.scene = LoadScene(name);
  w.accel = std::make_unique<Accel>(w.scene.mesh());
  const CameraBasis basis = MakeCameraBasis(w.scene.camera, kWidth, kHeight);
  AppendPrimaryRays(basis, Tile{0, 0, kWidth, kHeight}, RayOrder::kScanline, w.rays);
  w.rays.FillPadding();
  const size_t n = w.rays.size();
  w.hits = HitStream(n);
  w.hits.Resize(n);
  w.hits.Reset();
  w.accel->Intersect(w.rays.view(), w.hits.view());
  for (size_t i = 0; i < n; ++i) w.num_hits += w.hits.view().prim[i] >= 0 ? 1 : 0;
  w.options.max_depth = 4;
  w.options.stages = ShadeStagesFor(w.scene, w.options);
  return w;
}

// The rays of `s` as sorted bit patterns: the kernels emit in different orders.
std::vector<std::array<uint32_t, 14>> SortedRays(RayStream& s) {
  const RayStreamView v = s.view();
  std::vector<std::array<uint32_t, 14>> keys;
  for (size_t i = 0; i < s.size(); ++i) {
    auto b = [](float x) { return std::bit_cast<uint32_t>(x); };
    keys.push_back({b(v.ox[i]), b(v.oy[i]), b(v.oz[i]), b(v.dx[i]), b(v.dy[i]), b(v.dz[i]),
                    b(v.tmin[i]), b(v.tmax[i]), v.pixel[i], b(v.wr[i]), b(v.wg[i]), b(v.wb[i]),
                    static_cast<uint32_t>(v.depth[i]), static_cast<uint32_t>(v.kind[i])});
  }
  std::sort(keys.begin(), keys.end());
  return keys;
}

// rs::Shade on the currently selected target must equal ref::Shade bit for bit.
std::string Validate(Workload& w) {
  Framebuffer fa(kWidth, kHeight), fb(kWidth, kHeight);
  ContributionStream ca, cb;
  RayStream sa, sb;
  ref::Shade(w.scene, w.options, w.rays.view(), w.hits.view(), ca, sa, nullptr);
  Shade(w.scene, w.options, w.rays.view(), w.hits.view(), cb, sb, nullptr);
  fa.Add(ca.view());
  fb.Add(cb.view());
  if (std::memcmp(fa.sums(), fb.sums(), fa.num_pixels() * 3 * sizeof(int64_t)) != 0) {
    return "framebuffer differs from ref::Shade";
  }
  if (SortedRays(sa) != SortedRays(sb)) return "secondary rays differ from ref::Shade";
  return "";
}

// One pass over the workload per iteration, in chunks of `chunk` rays, each copied beforehand
// into its own aligned, padded stream (as the renderer hands tasks to Shade). `target` 0 runs
// ref::Shade. Each call's contributions are added to the framebuffer right after it (as the
// renderer does), which keeps accumulating (fixed point, far from overflow).
void BM_Shade(benchmark::State& state, const std::string& scene, size_t chunk, int64_t target) {
  Workload& w = GetWorkload(scene);
  if (target != 0) hwy::SetSupportedTargetsForTest(target);
  const std::string error = target != 0 ? Validate(w) : std::string();
  if (!error.empty()) {
    hwy::SetSupportedTargetsForTest(0);
    state.SkipWithError(error.c_str());
    return;
  }
  const size_t n = w.rays.size();
  // Tasks: aligned, padded streams of `chunk` rays (as the renderer hands to Shade).
  std::vector<RayStream> task_rays;
  std::vector<HitStream> task_hits;
  for (size_t first = 0; first < n; first += chunk) {
    const size_t count = std::min(chunk, n - first);
    RayStream r;
    HitStream h(count);
    h.Resize(count);
    h.Reset();
    const RayStreamView all = w.rays.view();
    for (size_t i = 0; i < count; ++i) {
      r.PushFrom(all, first + i);
      h.view().t[i] = w.hits.view().t[first + i];
      h.view().u[i] = w.hits.view().u[first + i];
      h.view().v[i] = w.hits.view().v[first + i];
      h.view().prim[i] = w.hits.view().prim[first + i];
    }
    r.FillPadding();
    task_rays.push_back(std::move(r));
    task_hits.push_back(std::move(h));
  }
  Framebuffer fb(kWidth, kHeight);
  ContributionStream contributions(chunk + kStreamPad);
  RayStream secondary;
  secondary.Reserve(chunk * (w.scene.lights.size() + 2) + kStreamPad);
  ShadeStats stats;
  const uint64_t t0 = Ticks();
  const double cpu0 = ThreadCpuSeconds();
  for (auto _ : state) {
    for (size_t k = 0; k < task_rays.size(); ++k) {
      secondary.Clear();
      contributions.Clear();
      if (target == 0) {
        ref::Shade(w.scene, w.options, task_rays[k].view(), task_hits[k].view(), contributions,
                   secondary, &stats);
      } else {
        Shade(w.scene, w.options, task_rays[k].view(), task_hits[k].view(), contributions,
              secondary, &stats);
      }
      fb.Add(contributions.view());
    }
    benchmark::DoNotOptimize(secondary.size());
  }
  const double ticks = static_cast<double>(Ticks() - t0);
  const double cpu = ThreadCpuSeconds() - cpu0;
  hwy::SetSupportedTargetsForTest(0);
  const double hits = static_cast<double>(state.iterations()) * static_cast<double>(w.num_hits);
  state.SetItemsProcessed(static_cast<int64_t>(state.iterations()) * static_cast<int64_t>(n));
  if (hits > 0) {
    state.counters["ticks/hit"] = ticks / hits;
    state.counters["cpu_ticks/hit"] = cpu * TscGhz() * 1e9 / hits;
  }
  state.counters["hits"] = static_cast<double>(w.num_hits);
  state.counters["spawned/hit"] =
      hits > 0 ? static_cast<double>(stats.spawned[0] + stats.spawned[1] + stats.spawned[2] +
                                     stats.spawned[3]) /
                     hits
               : 0.0;
}

void RegisterAll() {
  for (const std::string scene : {"erw6", "spherebox"}) {
    for (const size_t chunk : {kStreamChunk, kTaskSize}) {
      const std::string prefix =
          "shade/" + scene + "/" + (chunk == kTaskSize ? "task20" : "stream1024") + "/";
      for (const int64_t t : hwy::SupportedAndGeneratedTargets()) {
        benchmark::RegisterBenchmark((prefix + hwy::TargetName(t)).c_str(), BM_Shade, scene,
                                     chunk, t)
            ->Unit(benchmark::kMillisecond);
      }
      benchmark::RegisterBenchmark((prefix + "ref").c_str(), BM_Shade, scene, chunk, int64_t{0})
          ->Unit(benchmark::kMillisecond);
    }
  }
}

}  // namespace
}  // namespace rs::bench

int main(int argc, char** argv) {
  return rs::bench::RunBenchmarkMain(
      argc, argv,
      {{"cycles", "rdtsc reference ticks (no hardware perf counters in this KVM guest)"}},
      rs::bench::RegisterAll);
}
