// The cost of one DDA step and of one ray/triangle test per Highway target, each measured on the
// kernel itself in a tight loop: every benchmark iteration runs the same kernel call twice on the
// same rays, once short and once long, and the difference of the two times is divided by the
// difference of the work (cell steps or ray/triangle tests). Ray setup, lane refills, the call and
// its dynamic dispatch cost the same in both and drop out, which whole-run time divided by counts
// (dda_bench's cpu_ticks/ray) cannot do.
//
// DdaStep/<target>/<stream|single>, DdaStep/scalar: IntersectStreamDda, IntersectSingleDda and the
// scalar oracle (ref::AccelIntersect) on the "corners" grid (64^3 cells, empty where the rays go,
// empty-space skipping off): 1024 rays through the middle of the grid with tmax cut at about 5
// and about 74 cells. TriTest/<target|ref>/<test>/<1x4|Nx1>: IntersectBundles (kAuto width) per
// ray, ref::IntersectBundles, and IntersectStream on 1024 rays against one cell of 16 and one of
// 64 triangles (the same 16 and 48 more; bench/kernels/tri_workload.h).
//
// Counters: ticks/step, ticks/test = wall-clock rdtsc ticks; cpu_ticks/step, cpu_ticks/test = this
// thread's CPU time x tsc_ghz (robust when other processes share the cores). Neither is a core
// cycle count: hardware performance counters are not available on these machines (KVM guest
// without a PMU), so the figures assume the core runs at the TSC rate. The benchmark's own time
// column is one iteration (short + long run), not the per-step figure.
#include <benchmark/benchmark.h>
#include <hwy/targets.h>

#include <cstdint>
#include <cstdio>
#include <limits>
#include <memory>
#include <random>
#include <string>
#include <vector>

#include "bench/common/bench_main.h"
#include "bench/common/tsc.h"
#include "bench/kernels/dda_workload.h"
#include "bench/kernels/tri_workload.h"
#include "include/raystream/raystream.h"
#include "kernels/accel_impl.h"
#include "kernels/dda_simd.h"
#include "kernels/tri_bundles.h"
#include "kernels/tri_intersect.h"
#include "streams/ray_stream.h"

namespace rs::bench {
namespace {

constexpr size_t kRays = 1024;
constexpr float kInf = std::numeric_limits<float>::infinity();

// Times of the short and the long run and their work, summed over the benchmark's iterations.
struct Pair {
  uint64_t ticks[2] = {0, 0};
  double cpu[2] = {0.0, 0.0};
  double work[2] = {0.0, 0.0};  // cell steps or ray/triangle tests of one run

  // run(k) does run k (0 short, 1 long) once and returns its work.
  template <class Run>
  void Measure(Run&& run) {
    for (int k = 0; k < 2; ++k) {
      const uint64_t t0 = Ticks();
      const double c0 = ThreadCpuSeconds();
      const double w = run(k);
      cpu[k] += ThreadCpuSeconds() - c0;
      ticks[k] += Ticks() - t0;
      work[k] += w;
      benchmark::ClobberMemory();
    }
  }

  // Marginal ticks and CPU ticks per unit of work ("step" or "test").
  void Report(benchmark::State& state, const char* unit) const {
    const double dwork = work[1] - work[0];
    if (dwork <= 0.0) {
      state.SkipWithError("the long run did no more work than the short one");
      return;
    }
    const double dticks = static_cast<double>(ticks[1]) - static_cast<double>(ticks[0]);
    const double dcpu = (cpu[1] - cpu[0]) * TscGhz() * 1e9;
    state.counters[std::string("ticks/") + unit] = dticks / dwork;
    state.counters[std::string("cpu_ticks/") + unit] = dcpu / dwork;
  }
};

// ---------------------------------------------------------------------------------------------
// One DDA step.

struct DdaData {
  std::unique_ptr<Accel> accel;
  RayStream rays[2];  // tmax short, long
  HitStream hits;
  uint64_t scalar_steps[2] = {0, 0};
  std::string error;
};

DdaData& GetDda() {
  static std::unique_ptr<DdaData> data;
  if (data) return *data;
  data = std::make_unique<DdaData>();
  DdaData& d = *data;
  const Scene scene = CornersScene();
  BuildOptions options;
  options.grid = GridKind::kUniform;
  options.lambda = 32768.0f;   // 8 triangles: 64^3 cells
  options.empty_skip = false;  // every cell is entered: each step is one cell
  options.packets = false;
  d.accel = std::make_unique<Accel>(scene.mesh(), options);
  // Origins in the middle of the bottom of the cube, directions mostly +z: the rays stay at
  // least 0.15 from the sides, far from the corner cells that hold the triangles.
  std::mt19937 gen(20261202);
  std::uniform_real_distribution<float> u(0.0f, 1.0f);
  const float tmax[2] = {0.05f, 0.95f};
  for (size_t i = 0; i < kRays; ++i) {
    const float o[3] = {0.35f + 0.3f * u(gen), 0.35f + 0.3f * u(gen), 0.02f};
    const float dir[3] = {0.4f * u(gen) - 0.2f, 0.4f * u(gen) - 0.2f, 1.0f};
    for (int k = 0; k < 2; ++k) {
      d.rays[k].Push(o[0], o[1], o[2], dir[0], dir[1], dir[2], 0.0f, tmax[k],
                     static_cast<uint32_t>(i), 1.0f, 1.0f, 1.0f, 0, RayKind::kPrimary);
    }
  }
  d.hits.Resize(kRays);
  const Accel::Impl& impl = AccelImpl(*d.accel);
  for (int k = 0; k < 2; ++k) {
    d.rays[k].FillPadding();
    TraceStats st;
    d.hits.Reset();
    ref::AccelIntersect(impl, d.rays[k].view(), d.hits.view(), &st);
    d.scalar_steps[k] = st.cell_steps;
    for (size_t i = 0; i < kRays; ++i) {
      if (d.hits.view().prim[i] >= 0) d.error = "a step-benchmark ray hits a triangle";
    }
  }
  return d;
}

enum class DdaForm { kStream, kSingle, kScalar };

void BM_DdaStep(benchmark::State& state, DdaForm form, int64_t target) {
  DdaData& d = GetDda();
  if (!d.error.empty()) {
    state.SkipWithError(d.error.c_str());
    return;
  }
  if (target != 0) hwy::SetSupportedTargetsForTest(target);
  const Accel::Impl& impl = AccelImpl(*d.accel);
  DdaOptions options = impl.dda_options;
  options.empty_skip = false;
  const HitStreamView hits = d.hits.view();
  auto run = [&](int k) {
    const RayStreamView rays = d.rays[k].view();
    TraceStats st;
    if (form == DdaForm::kStream) {
      ForEachFramePiece(impl, rays, rays.size, [&](const RayStreamView& r, size_t first) {
        IntersectStreamDda(impl.dda, r, SubView(hits, first, r.size), options, &st);
      });
    } else if (form == DdaForm::kSingle) {
      for (size_t i = 0; i < rays.size; ++i) {
        RayHit h;
        IntersectSingleDda(impl.dda, rays.ox[i] - impl.shift[0], rays.oy[i] - impl.shift[1],
                           rays.oz[i] - impl.shift[2], rays.dx[i], rays.dy[i], rays.dz[i],
                           rays.tmin[i], rays.tmax[i], &h, &st);
        hits.prim[i] = h.prim;
      }
    } else {
      ref::AccelIntersect(impl, rays, hits, &st);
    }
    return st;
  };
  // Same cells as the scalar DDA, and still no hit, before anything is timed.
  for (int k = 0; k < 2; ++k) {
    const TraceStats st = run(k);
    bool miss = true;
    for (size_t i = 0; i < kRays; ++i) miss = miss && hits.prim[i] < 0;
    if (st.cell_steps != d.scalar_steps[k] || !miss) {
      hwy::SetSupportedTargetsForTest(0);
      state.SkipWithError("cell steps or hits differ from the scalar DDA");
      return;
    }
  }
  Pair pair;
  for (auto _ : state) {
    pair.Measure([&](int k) { return static_cast<double>(run(k).cell_steps); });
  }
  pair.Report(state, "step");
  state.counters["steps/ray"] = static_cast<double>(d.scalar_steps[1]) / kRays;
  state.counters["short_steps/ray"] = static_cast<double>(d.scalar_steps[0]) / kRays;
  state.SetLabel(form == DdaForm::kScalar ? "scalar DDA" : DdaTargetName());
  hwy::SetSupportedTargetsForTest(0);
}

// ---------------------------------------------------------------------------------------------
// One ray/triangle test.

struct TriData {
  TriWorkload w;       // 64 triangles (Cell(0)) and the rays
  TriBundles first16;  // the workload's first 16 triangles as one cell
  HitStream hits;
};

TriData& GetTri() {
  static std::unique_ptr<TriData> data;
  if (data) return *data;
  data = std::make_unique<TriData>();
  MakeTriWorkload(64, kRays, 20261122, &data->w);
  std::vector<uint32_t> ids(16);
  for (uint32_t t = 0; t < 16; ++t) ids[t] = t;
  BuildTriBundleList(data->w.tris, ids.data(), ids.size(), &data->first16);
  data->hits.Resize(kRays);
  return *data;
}

enum class TriForm { k1x4, kNx1 };

void BM_TriTest(benchmark::State& state, TriForm form, TriTest test, int64_t target) {
  TriData& d = GetTri();
  const TriBundleSpan spans[2] = {d.first16.Cell(0), d.w.span()};
  const bool oracle = target == 0;
  if (!oracle) hwy::SetSupportedTargetsForTest(target);
  const HitStreamView hits = d.hits.view();
  RayStreamView rays = d.w.rays.view();
  std::vector<int32_t> prims[2];
  auto run = [&](int k) {
    const TriBundleSpan& span = spans[k];
    if (form == TriForm::kNx1) {
      d.hits.Reset();
      if (oracle) {
        ref::IntersectStream(rays, span, test, hits);
      } else {
        IntersectStream(rays, span, test, hits);
      }
    } else {
      for (size_t i = 0; i < d.w.prepared_rays.size(); ++i) {
        ClosestHit hit;
        if (oracle) {
          ref::IntersectBundles(d.w.prepared_rays[i], span, 0.0f, kInf, test, &hit);
        } else {
          IntersectBundles(d.w.prepared_rays[i], span, 0.0f, kInf, test, BundleWidth::kAuto, &hit);
        }
        hits.prim[i] = hit.prim;
      }
    }
    return static_cast<double>(kRays * span.lanes());
  };
  // The SIMD kernel hits what the oracle hits, before anything is timed.
  for (int k = 0; k < 2; ++k) {
    run(k);
    prims[k].assign(hits.prim, hits.prim + kRays);
    std::vector<int32_t> want(kRays);
    for (size_t i = 0; i < kRays; ++i) {
      ClosestHit hit;
      ref::IntersectBundles(d.w.prepared_rays[i], spans[k], 0.0f, kInf, test, &hit);
      want[i] = hit.prim;
    }
    if (want != prims[k]) {
      hwy::SetSupportedTargetsForTest(0);
      state.SkipWithError("hits differ from rs::ref");
      return;
    }
  }
  Pair pair;
  for (auto _ : state) pair.Measure(run);
  pair.Report(state, "test");
  size_t hit_rays = 0;
  for (const int32_t p : prims[1]) hit_rays += p >= 0;
  state.counters["hit_rays"] = static_cast<double>(hit_rays) / kRays;
  state.SetLabel(oracle ? "scalar oracle" : hwy::TargetName(target));
  hwy::SetSupportedTargetsForTest(0);
}

void RegisterAll() {
  for (const int64_t t : hwy::SupportedAndGeneratedTargets()) {
    const std::string name = hwy::TargetName(t);
    benchmark::RegisterBenchmark(("DdaStep/" + name + "/stream").c_str(), BM_DdaStep,
                                 DdaForm::kStream, t);
    benchmark::RegisterBenchmark(("DdaStep/" + name + "/single").c_str(), BM_DdaStep,
                                 DdaForm::kSingle, t);
  }
  benchmark::RegisterBenchmark("DdaStep/scalar", BM_DdaStep, DdaForm::kScalar, int64_t{0});
  std::vector<std::pair<int64_t, std::string>> targets;
  for (const int64_t t : hwy::SupportedAndGeneratedTargets()) {
    targets.push_back({t, hwy::TargetName(t)});
  }
  targets.push_back({0, "ref"});
  for (const auto& [target, tname] : targets) {
    for (const TriTest test : {TriTest::kWatertight, TriTest::kMollerTrumbore}) {
      const std::string tn = test == TriTest::kWatertight ? "watertight" : "moller";
      benchmark::RegisterBenchmark(("TriTest/" + tname + "/" + tn + "/1x4").c_str(), BM_TriTest,
                                   TriForm::k1x4, test, target);
      benchmark::RegisterBenchmark(("TriTest/" + tname + "/" + tn + "/Nx1").c_str(), BM_TriTest,
                                   TriForm::kNx1, test, target);
    }
  }
}

}  // namespace
}  // namespace rs::bench

int main(int argc, char** argv) {
  return rs::bench::RunBenchmarkMain(
      argc, argv,
      {{"method",
        "per step / per test = (long run - short run) / (long work - short work) on the same "
        "rays: setup, refills, call and dispatch drop out; ticks = wall-clock rdtsc, cpu_ticks = "
        "thread CPU time x tsc_ghz; not core cycles (no hardware perf counters on these "
        "machines)"}},
      rs::bench::RegisterAll);
}
