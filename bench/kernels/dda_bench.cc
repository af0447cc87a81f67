// SIMD 3D-DDA traversal (kernels/dda_simd.h) against the scalar DDA: rays/s per Highway target
// for the stream kernel ("Dda/<target>/<workload>") and the Cell paper's single-ray form
// ("DdaSingle/<target>/<workload>"), the scalar oracle ("DdaScalar/<workload>"), the micro-cache
// off ("DdaNoCache/..."), flat vs two-level grids ("Grid/<scene>/<kind>"), grid build speed
// ("Build/<scene>/<what>", items = triangles) and its phases ("BuildPhase/<scene>/<phase>").
//
// Workloads: bunny primary rays (scene camera), spherebox random rays (origins in the bounds,
// uniform directions), conference and amphitheater:16 primary rays from the bounds' centre and
// random rays. Every workload is validated once against the scalar DDA (identical hits) before
// it is timed. Environment: RS_DDA_BENCH_RAYS=n (random rays, default 65536), RS_DDA_BENCH_SIZE=W
// (primary rays W x W, default 256). Shared scenes that are missing are skipped.
//
// Counters: cpu_ticks/ray = this thread's CPU time per ray in rdtsc reference ticks (CPU seconds x
// tsc_ghz; robust when other processes share the cores), the whole traversal (setup, steps,
// triangle tests, lane refills) divided by the rays; ticks/ray is the same from wall-clock rdtsc;
// steps/ray and tests/ray are the work per ray. None is a per-step or per-test cost (that is
// step_bench) nor a core cycle count: hardware performance counters are not available on these
// machines (KVM guest without a PMU).
#include <benchmark/benchmark.h>
#include <hwy/targets.h>


#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "bench/common/bench_main.h"
#include "bench/common/tsc.h"
#include "bench/kernels/dda_workload.h"
#include "include/raystream/raystream.h"
#include "kernels/accel_impl.h"
#include "kernels/dda_simd.h"
#include "kernels/grid.h"
#include "kernels/tri_bundles.h"
#include "kernels/triangle.h"
#include "kernels/two_level.h"
#include "scenes/load.h"
#include "streams/ray_stream.h"
#include "streams/raygen.h"

namespace rs::bench {
namespace {

size_t EnvSize(const char* name, size_t fallback) {
  const char* v = std::getenv(name);
  if (v == nullptr) return fallback;
  const long n = std::strtol(v, nullptr, 10);
  return n > 0 ? size_t(n) : fallback;
}

const char* ProbeFile(const std::string& scene) {
  if (scene == "bunny") return "bunny/bun_zipper.ply";
  if (scene == "conference") return "conference/conference.obj";
  if (scene == "sponza") return "sponza/sponza.obj";
  if (scene == "office-graz") return "office-graz/office-graz.obj";
  return nullptr;
}

bool Available(const std::string& scene) {
  const char* file = ProbeFile(scene);
  if (file == nullptr) return true;
  try {
    FindSceneFile(file);
    return true;
  } catch (const Error&) {
    return false;
  }
}

// A loaded scene, shared by the workloads on it.
struct SceneData {
  Scene scene;
  glm::vec3 lo{0.0f}, hi{0.0f};
};

SceneData& GetScene(const std::string& name) {
  static std::map<std::string, std::unique_ptr<SceneData>> cache;
  auto& slot = cache[name];
  if (!slot) {
    slot = std::make_unique<SceneData>();
    slot->scene = name == "corners" ? CornersScene() : LoadScene(name);
    slot->scene.Bounds(slot->lo, slot->hi);
  }
  return *slot;
}

enum class Rays { kPrimary, kPrimaryInside, kRandom };

RayStream MakeRays(const SceneData& s, Rays kind) {
  RayStream rays;
  if (kind == Rays::kRandom) {
    AppendRandomRays(s.lo, s.hi, EnvSize("RS_DDA_BENCH_RAYS", 65536), rays);
  } else {
    const int w = int(EnvSize("RS_DDA_BENCH_SIZE", 256));
    Camera camera = s.scene.camera;
    if (kind == Rays::kPrimaryInside) {  // room scenes: from the centre of the bounds along +x
      camera.eye = 0.5f * (s.lo + s.hi);
      camera.look_at = camera.eye + glm::vec3(1.0f, 0.0f, 0.0f);
      camera.fov_y_deg = 60.0f;
    }
    AppendPrimaryRays(MakeCameraBasis(camera, w, w), Tile{0, 0, w, w}, RayOrder::kScanline, rays);
  }
  rays.FillPadding();
  return rays;
}

struct Workload {
  std::string name;  // "<scene>/<rays>"
  std::string scene;
  Rays rays;
  GridKind grid;
  float lambda;
};

// One workload's structure, rays and scalar reference results.
struct WorkData {
  std::unique_ptr<Accel> accel;
  RayStream rays;
  HitStream ref;
  HitStream hits;
  TraceStats ref_stats;
  std::string error;
};

WorkData& GetWork(const Workload& w) {
  static std::map<std::string, std::unique_ptr<WorkData>> cache;
  const std::string key =
      w.scene + "/" + std::to_string(int(w.rays)) + "/" + std::to_string(int(w.grid)) + "/" +
      std::to_string(w.lambda);
  auto& slot = cache[key];
  if (slot) return *slot;
  slot = std::make_unique<WorkData>();
  WorkData& d = *slot;
  try {
    SceneData& s = GetScene(w.scene);
    BuildOptions options;
    options.grid = w.grid;
    options.lambda = w.lambda;
    d.accel = std::make_unique<Accel>(s.scene.mesh(), options);
    d.rays = MakeRays(s, w.rays);
    const size_t n = d.rays.size();
    d.ref.Resize(n);
    d.hits.Resize(n);
    d.ref.Reset();
    ref::AccelIntersect(AccelImpl(*d.accel), d.rays.view(), d.ref.view(), &d.ref_stats);
  } catch (const Error& e) {
    d.error = e.what();
  }
  return d;
}

// Identical hits (prim, t bits) or an error message naming the first difference.
std::string Validate(const WorkData& d, const HitStreamView& got, const char* what) {
  const HitStreamView ref = const_cast<HitStream&>(d.ref).view();
  for (size_t i = 0; i < d.rays.size(); ++i) {
    if (ref.prim[i] != got.prim[i] || std::memcmp(&ref.t[i], &got.t[i], sizeof(float)) != 0) {
      return std::string(what) + ": ray " + std::to_string(i) + " differs from the scalar DDA";
    }
  }
  return "";
}

void Report(benchmark::State& state, uint64_t ticks, double cpu_seconds, const TraceStats& st,
            size_t rays) {
  const double iters = double(state.iterations());
  const double cpu_ticks = cpu_seconds * TscGhz() * 1e9;
  state.SetItemsProcessed(state.iterations() * int64_t(rays));
  if (st.cell_steps > 0) {
    state.counters["steps/ray"] = double(st.cell_steps) / (iters * double(rays));
  }
  if (st.triangle_tests > 0) {
    state.counters["tests/ray"] = double(st.triangle_tests) / (iters * double(rays));
  }
  state.counters["cpu_ticks/ray"] = cpu_ticks / (iters * double(rays));
  state.counters["ticks/ray"] = double(ticks) / (iters * double(rays));
  if (st.cache_lookups > 0) {
    state.counters["cache_hit"] = double(st.cache_hits) / double(st.cache_lookups);
  }
}

// kind: 0 stream, 1 single-ray form, 2 stream without micro-cache, 3 stream without empty-space
// skipping; target 0 = normal dispatch.
void BM_Dda(benchmark::State& state, Workload w, int64_t target, int kind) {
  WorkData& d = GetWork(w);
  if (!d.error.empty()) {
    state.SkipWithError(d.error.c_str());
    return;
  }
  hwy::SetSupportedTargetsForTest(target);
  const Accel::Impl& m = AccelImpl(*d.accel);
  const RayStreamView rays = d.rays.view();
  const HitStreamView hits = d.hits.view();
  DdaOptions options = m.dda_options;
  if (kind == 2) options.micro_cache = 0;
  // corners: rays through empty cells, every cell stepped (no jumps), as the scalar DDA does
  if (kind == 3 || w.scene == "corners") options.empty_skip = false;
  auto run = [&](TraceStats* st) {
    if (kind == 1) {
      for (size_t i = 0; i < rays.size; ++i) {
        RayHit h;
        IntersectSingleDda(m.dda, rays.ox[i] - m.shift[0], rays.oy[i] - m.shift[1],
                           rays.oz[i] - m.shift[2], rays.dx[i], rays.dy[i], rays.dz[i],
                           rays.tmin[i], rays.tmax[i], &h, st);
        hits.t[i] = h.t;
        hits.prim[i] = h.prim;
      }
    } else {
      ForEachFramePiece(m, rays, rays.size, [&](const RayStreamView& r, size_t first) {
        IntersectStreamDda(m.dda, r, SubView(hits, first, r.size), options, st);
      });
    }
  };
  TraceStats check;
  run(&check);
  const std::string error = Validate(d, hits, "SIMD DDA");
  if (!error.empty()) {
    hwy::SetSupportedTargetsForTest(0);
    state.SkipWithError(error.c_str());
    return;
  }
  TraceStats st;
  const uint64_t t0 = Ticks();
  const double c0 = ThreadCpuSeconds();
  for (auto _ : state) {
    run(&st);
    benchmark::ClobberMemory();
  }
  Report(state, Ticks() - t0, ThreadCpuSeconds() - c0, st, rays.size);
  const AccelInfo info = d.accel->Info();
  state.counters["subgrids"] = double(info.subgrids);
  state.SetLabel(std::string(DdaTargetName()) + " " + info.kind);
  hwy::SetSupportedTargetsForTest(0);
}

void BM_Scalar(benchmark::State& state, Workload w) {
  WorkData& d = GetWork(w);
  if (!d.error.empty()) {
    state.SkipWithError(d.error.c_str());
    return;
  }
  TraceStats st;
  const uint64_t t0 = Ticks();
  const double c0 = ThreadCpuSeconds();
  for (auto _ : state) {
    ref::AccelIntersect(AccelImpl(*d.accel), d.rays.view(), d.hits.view(), &st);
    benchmark::ClobberMemory();
  }
  Report(state, Ticks() - t0, ThreadCpuSeconds() - c0, st, d.rays.size());
}

// Grid build, items = triangles. "grid/lambda:L" = BuildGrid alone on gathered triangles;
// "accel" = Accel construction with default options (triangle gather, lambda choice, grid,
// sub-grids if the cost model wants them, bundles, occupancy words); "accel-two-level" = the
// same with every cell above 32 triangles refined at lambda 4.
void BM_Build(benchmark::State& state, std::string scene, int what, float lambda) {
  if (!Available(scene)) {
    state.SkipWithError(("scene missing: " + scene).c_str());
    return;
  }
  SceneData& s = GetScene(scene);
  const MeshView mesh = s.scene.mesh();
  BuildOptions options;
  if (what == 2) {
    options.grid = GridKind::kTwoLevel;
    options.lambda = lambda;
  }
  TriangleSoA tris;
  BuildTriangleSoA(mesh, &tris);
  for (auto _ : state) {
    if (what == 0) {
      Grid g;
      BuildGrid(tris, lambda, options.max_resolution, &g);
      benchmark::DoNotOptimize(g.num_refs);
    } else {
      const Accel accel(mesh, options);
      benchmark::DoNotOptimize(accel.Info().references);
    }
  }
  state.SetItemsProcessed(state.iterations() * int64_t(mesh.num_triangles));
}

// Build phases one at a time, as rs::Accel runs them with default options ("BuildPhase/<scene>/
// <phase>", items = triangles): soa (gather + degenerate flags), bounds, lambda (the cost model's
// choice), grid (BuildGrid at that lambda), two-level (BuildTwoLevel, only if kAuto tries it),
// bundles (of the leaves Accel traces), dda (BuildDdaGrid: bundles, skip rings, occupancy words).
// Each phase's inputs are built once outside the timing loop; the output is rebuilt every time.
void BM_BuildPhase(benchmark::State& state, std::string scene, int phase) {
  if (!Available(scene)) {
    state.SkipWithError(("scene missing: " + scene).c_str());
    return;
  }
  SceneData& s = GetScene(scene);
  const MeshView mesh = s.scene.mesh();
  const BuildOptions options;
  const GridCostModel model;
  TriangleSoA tris;
  BuildTriangleSoA(mesh, &tris);
  const GridBounds bounds = ComputeGridBounds(tris);
  const float lambda = ChooseLambda(tris, bounds, options.max_resolution, model);
  Grid grid;
  BuildGrid(tris, bounds, lambda, options.max_resolution, &grid);
  const bool may_refine = TwoLevelCostBound(grid, options.subgrid_threshold, model) <
                          kTwoLevelMinGain * FlatGridCost(grid, model);
  TwoLevelGrid two;
  if (may_refine) BuildTwoLevel(grid, tris, options.subgrid_threshold, true, model, &two);
  if (!two.empty() &&
      !(TwoLevelGridCost(grid, two, model) < kTwoLevelMinGain * FlatGridCost(grid, model))) {
    two = TwoLevelGrid();
  }
  if (phase == 4 && !may_refine) {
    state.SkipWithError("kAuto builds no second level on this scene");
    return;
  }
  for (auto _ : state) {
    switch (phase) {
      case 0: {
        TriangleSoA t;
        BuildTriangleSoA(mesh, &t);
        benchmark::DoNotOptimize(t.num_degenerate);
        break;
      }
      case 1:
        benchmark::DoNotOptimize(ComputeGridBounds(tris).num_valid);
        break;
      case 2:
        benchmark::DoNotOptimize(ChooseLambda(tris, bounds, options.max_resolution, model));
        break;
      case 3: {
        Grid g;
        BuildGrid(tris, bounds, lambda, options.max_resolution, &g);
        benchmark::DoNotOptimize(g.num_refs);
        break;
      }
      case 4: {
        TwoLevelGrid t;
        BuildTwoLevel(grid, tris, options.subgrid_threshold, true, model, &t);
        benchmark::DoNotOptimize(t.num_records);
        break;
      }
      case 5: {
        TriBundles p;
        BuildTriBundles(two.empty() ? grid : two.leaves, tris, &p);
        benchmark::DoNotOptimize(p.num_bundles);
        break;
      }
      default: {
        DdaGrid d;
        BuildDdaGrid(grid, &two, tris, &d);
        benchmark::DoNotOptimize(d.top_words32);
        break;
      }
    }
  }
  state.SetItemsProcessed(state.iterations() * int64_t(mesh.num_triangles));
}

std::string TargetName(int64_t t) { return hwy::TargetName(t); }

void RegisterAll() {
  // lambda 4 (the kUniform default) and the cost model's choice for these scenes (0.5); corners: a
  // 64^3 grid with 8 occupied cells (lambda 32768 over 8 triangles)
  const std::vector<Workload> speedup = {
      {"bunny/primary", "bunny", Rays::kPrimary, GridKind::kUniform, 4.0f},
      {"bunny/primary/lambda:0.5", "bunny", Rays::kPrimary, GridKind::kUniform, 0.5f},
      {"spherebox/random", "spherebox", Rays::kRandom, GridKind::kUniform, 4.0f},
      {"spherebox/random/lambda:0.5", "spherebox", Rays::kRandom, GridKind::kUniform, 0.5f},
      {"corners/random", "corners", Rays::kRandom, GridKind::kUniform, 32768.0f},
  };
  for (const Workload& w : speedup) {
    if (!Available(w.scene)) continue;
    benchmark::RegisterBenchmark(("DdaScalar/" + w.name).c_str(), BM_Scalar, w)
        ->Unit(benchmark::kMillisecond);
    for (const int64_t t : hwy::SupportedAndGeneratedTargets()) {
      benchmark::RegisterBenchmark(("Dda/" + TargetName(t) + "/" + w.name).c_str(), BM_Dda, w, t,
                                   0)
          ->Unit(benchmark::kMillisecond);
    }
    for (const int64_t t : hwy::SupportedAndGeneratedTargets()) {
      benchmark::RegisterBenchmark(("DdaSingle/" + TargetName(t) + "/" + w.name).c_str(), BM_Dda,
                                   w, t, 1)
          ->Unit(benchmark::kMillisecond);
    }
    benchmark::RegisterBenchmark(("DdaNoCache/" + w.name).c_str(), BM_Dda, w, int64_t{0}, 2)
        ->Unit(benchmark::kMillisecond);
    benchmark::RegisterBenchmark(("DdaNoSkip/" + w.name).c_str(), BM_Dda, w, int64_t{0}, 3)
        ->Unit(benchmark::kMillisecond);
  }
  // flat vs two-level (dispatch target): forced (every cell above 32 triangles refined) and the
  // cost model's choice (kAuto without auto lambda), at lambda 4 and 0.5
  for (const auto& [scene, rays, label] :
       {std::tuple{"conference", Rays::kPrimaryInside, "primary"},
        std::tuple{"conference", Rays::kRandom, "random"},
        std::tuple{"amphitheater:16", Rays::kPrimary, "primary"},
        std::tuple{"amphitheater:16", Rays::kRandom, "random"}}) {
    if (!Available(scene)) continue;
    for (const float lambda : {4.0f, 0.5f}) {
      for (const GridKind kind : {GridKind::kUniform, GridKind::kTwoLevel, GridKind::kAuto}) {
        const Workload w{std::string(scene) + "/" + label, scene, rays, kind, lambda};
        const char* kname = kind == GridKind::kUniform   ? "flat"
                            : kind == GridKind::kTwoLevel ? "two-level"
                                                          : "auto";
        char lam[16];
        std::snprintf(lam, sizeof lam, "%g", double(lambda));
        const std::string name = "Grid/" + w.name + "/" + kname + "/lambda:" + lam;
        benchmark::RegisterBenchmark(name.c_str(), BM_Dda, w, int64_t{0}, 0)
            ->Unit(benchmark::kMillisecond);
      }
    }
  }
  for (const char* scene : {"bunny", "spherebox", "conference", "amphitheater:16"}) {
    if (!Available(scene)) continue;
    const std::string prefix = std::string("Build/") + scene;
    benchmark::RegisterBenchmark((prefix + "/grid/lambda:4").c_str(), BM_Build,
                                 std::string(scene), 0, 4.0f)
        ->Unit(benchmark::kMillisecond);
    benchmark::RegisterBenchmark((prefix + "/grid/lambda:0.5").c_str(), BM_Build,
                                 std::string(scene), 0, 0.5f)
        ->Unit(benchmark::kMillisecond);
    benchmark::RegisterBenchmark((prefix + "/accel").c_str(), BM_Build, std::string(scene), 1,
                                 0.0f)
        ->Unit(benchmark::kMillisecond);
    benchmark::RegisterBenchmark((prefix + "/accel-two-level").c_str(), BM_Build,
                                 std::string(scene), 2, 4.0f)
        ->Unit(benchmark::kMillisecond);
  }
  for (const char* scene : {"bunny", "sponza", "office-graz", "conference", "spherebox"}) {
    if (!Available(scene)) continue;
    static constexpr const char* kPhases[] = {"soa",       "bounds",  "lambda", "grid",
                                              "two-level", "bundles", "dda"};
    for (int phase = 0; phase < 7; ++phase) {
      benchmark::RegisterBenchmark(
          (std::string("BuildPhase/") + scene + "/" + kPhases[phase]).c_str(), BM_BuildPhase,
          std::string(scene), phase)
          ->Unit(benchmark::kMillisecond);
    }
  }
}

}  // namespace
}  // namespace rs::bench

int main(int argc, char** argv) {
  return rs::bench::RunBenchmarkMain(
      argc, argv,
      {{"ticks", "cpu_ticks/ray = thread CPU time x tsc_ghz / rays (ticks/ray: wall-clock "
                 "rdtsc), the whole traversal per ray; one step or test alone: step_bench; "
                 "hardware perf counters (core cycles) are not available on these machines "
                 "(KVM guest without a PMU)"},
       {"dispatch_target", rs::DdaTargetName()}},
      rs::bench::RegisterAll);
}
