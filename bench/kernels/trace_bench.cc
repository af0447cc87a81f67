// raystream vs Embree 3 in the same run (methodology of ../shared/ANCHORS.md): rays/s per scene
// and ray set for rs::Accel and Embree 1 / 16 / 1M, build Mtris/s, time to image, rdtsc ticks
// per ray. Names are "<set>/<scene>/<tracer>", e.g. --benchmark_filter=primary/bunny/.
//
// Defaults: 512x512 ray sets, --benchmark_min_time=0.2, one run (about 2-3 minutes in all).
// Environment: RS_BENCH_FULL=1 runs the ANCHORS sweep (1024x1024 rays, min time 0.5 s, median
// of 5); RS_BENCH_SIZE=WxH sets the ray-set image size; RS_BENCH_SCENES=a,b,c picks scenes
// (default bunny,sponza,office-graz,conference,spherebox; missing shared scenes are skipped);
// RS_BENCH_ISA=avx2 holds both raystream and Embree to AVX2 (bench/common/bench_main.h);
// RS_BENCH_GRID and RS_BENCH_LAMBDA set rs::Accel's BuildOptions (BenchBuildOptions).
// Ratios "vs_embree*" are raystream speed / Embree speed (> 1: raystream faster), from CPU time.
#include <benchmark/benchmark.h>
#include <sys/resource.h>
#include <unistd.h>
#ifdef __GLIBC__
#include <malloc.h>  // malloc_trim (build-cold)
#endif

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <map>
#include <memory>
#include <sstream>
#include <string>
#include <utility>
#include <vector>

#include "bench/common/bench_scenes.h"
#include "bench/common/bench_main.h"
#include "bench/common/tsc.h"
#include "bench/peer/embree_peer.h"
#include "bench/peer/ray_sets.h"
#include "include/raystream/raystream.h"
#include "kernels/accel_impl.h"
#include "scenes/load.h"
#include "streams/ray_stream.h"

namespace rs::bench {
namespace {

constexpr const char* kCycleNote =
    "ticks/ray counts rdtsc reference ticks (constant-rate TSC, see tsc_ghz; wall clock), "
    "cpu_ticks/ray the thread's CPU time in the same ticks; neither is core cycles: hardware "
    "perf counters (cycles, instructions) are not available on these machines (KVM guest "
    "without a PMU). Rates use CPU time.";

struct Config {
  int width = 512;
  int height = 512;
  int frame_size = 1024;  // time to image: always one 1024x1024 frame (ANCHORS.md)
  int repetitions = 1;
  double min_time = 0.2;
  std::vector<std::string> scenes{"bunny", "sponza", "office-graz", "conference", "spherebox"};
};

Config& Cfg() {
  static Config config;
  return config;
}

// ---------------------------------------------------------------------------------------------
// Validation: raystream and Embree must agree on a set before either is timed on it.

// Hit counts and per-ray agreement of two tracers on one set. Closest hits on different
// triangles at (nearly) the same t count as the same result: scenes with coplanar overlapping
// triangles (office-graz) have many exact ties, each tracer breaking them its own way.
struct HitCompare {
  size_t n = 0;
  size_t hits_a = 0;
  size_t hits_b = 0;
  size_t same = 0;  // same triangle, or a tie (t within 1e-4 relative), or same occlusion
  bool Ok() const {
    const size_t diff = hits_a > hits_b ? hits_a - hits_b : hits_b - hits_a;
    const double tol = std::max(2.0, 1e-4 * static_cast<double>(n));
    return static_cast<double>(diff) <= tol &&
           static_cast<double>(same) >= (1.0 - 1e-3) * static_cast<double>(n);
  }
  std::string Str(const char* a, const char* b) const {
    std::ostringstream s;
    s << a << " " << hits_a << " hits, " << b << " " << hits_b << ", same result "
      << (n ? 100.0 * static_cast<double>(same) / static_cast<double>(n) : 100.0) << " %";
    return s.str();
  }
};

HitCompare CompareHits(const HitStreamView& a, const HitStreamView& b, size_t n) {
  HitCompare c;
  c.n = n;
  for (size_t i = 0; i < n; ++i) {
    c.hits_a += a.prim[i] >= 0 ? 1 : 0;
    c.hits_b += b.prim[i] >= 0 ? 1 : 0;
    const bool tie =
        a.prim[i] >= 0 && b.prim[i] >= 0 && std::fabs(a.t[i] - b.t[i]) <= 1e-4f * std::fabs(b.t[i]);
    c.same += a.prim[i] == b.prim[i] || tie ? 1 : 0;
  }
  return c;
}

HitCompare CompareOccluded(const int32_t* a, const int32_t* b, size_t n) {
  HitCompare c;
  c.n = n;
  for (size_t i = 0; i < n; ++i) {
    c.hits_a += a[i] != 0 ? 1 : 0;
    c.hits_b += b[i] != 0 ? 1 : 0;
    c.same += (a[i] != 0) == (b[i] != 0) ? 1 : 0;
  }
  return c;
}

// ---------------------------------------------------------------------------------------------
// Per-scene data, loaded on first use by a benchmark of that scene (benchmarks run in
// registration order, scene after scene, so only one scene is held at a time).

struct SceneData {
  std::string name;
  std::string load_error;
  Scene scene;
  MeshView mesh;
  std::unique_ptr<Accel> accel;
  std::unique_ptr<LightBuffer> light_buffer;  // over accel, for the light set
  std::unique_ptr<EmbreePeer> embree;
  RaySets sets;
  HitStream hits;                  // scratch for timed closest-hit runs
  AlignedArray<int32_t> occluded;  // scratch for timed occlusion runs
  bool validated[kNumRaySets] = {};
  std::string validation_error[kNumRaySets];
  TraceStats stats[kNumRaySets];  // raystream's work on each set (from the validation pass)
  // Time to image: the frame's primary rays and per-iteration scratch.
  RayStream frame_primary;
  HitStream frame_hits;
  RayStream frame_shadow;
  RayStream frame_light;
  AlignedArray<int32_t> frame_occluded;
  std::unique_ptr<EmbreePeer> rebuild_peer;  // rebuilt every iteration (build and frame)
  std::unique_ptr<Accel> rebuilt;             // rebuilt in place (rebuild/ and frame/)
  std::unique_ptr<LightBuffer> rebuilt_light;  // over `rebuilt`, rebuilt in place (frame/)
  glm::vec3 light{0.0f};
};

std::unique_ptr<SceneData>& Current() {
  static std::unique_ptr<SceneData> current;
  return current;
}

SceneData& GetScene(const std::string& name) {
  auto& current = Current();
  if (current && current->name == name) return *current;
  current.reset();  // free the previous scene first: conference's sets are large
  auto data = std::make_unique<SceneData>();
  data->name = name;
  try {
    const auto t0 = std::chrono::steady_clock::now();
    data->scene = LoadScene(name);
    data->mesh = data->scene.mesh();
    data->accel = std::make_unique<Accel>(data->mesh, BenchBuildOptions("trace_bench"));
    data->embree = std::make_unique<EmbreePeer>(data->mesh);
    data->sets = MakeRaySets(data->scene, *data->embree, Cfg().width, Cfg().height);
    data->light = data->sets.light;
    const float light[3] = {data->light.x, data->light.y, data->light.z};
    data->light_buffer = std::make_unique<LightBuffer>(*data->accel, light);
    const LightBufferInfo lbi = data->light_buffer->Info();
    std::fprintf(stderr,
                 "[trace_bench] %s: light buffer %zu cells (at most %d along an axis), %zu "
                 "references (%.2f per triangle, at most %zu in a cell), %zu always, %.1f MB\n",
                 name.c_str(), lbi.cells, lbi.resolution, lbi.references,
                 double(lbi.references) / double(std::max<size_t>(1, data->mesh.num_triangles)),
                 lbi.longest, lbi.always, double(lbi.bytes) * 1e-6);
    const size_t n =
        std::max({data->sets.primary.size(), data->sets.shadow.size(), data->sets.diffuse.size()});
    data->hits.Resize(n);
    data->hits.Reset();
    data->occluded.Reserve(n);
    std::fprintf(stderr,
                 "[trace_bench] %s: %zu triangles, %dx%d rays: %zu primary hits, %zu shadow, "
                 "%zu diffuse rays (setup %.1f s)\n",
                 name.c_str(), data->mesh.num_triangles, Cfg().width, Cfg().height,
                 data->sets.primary_hit_count, data->sets.shadow.size(), data->sets.diffuse.size(),
                 std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
  } catch (const std::exception& e) {
    data->load_error = "loading " + name + ": " + e.what();
    std::fprintf(stderr, "[trace_bench] %s\n", data->load_error.c_str());
  }
  current = std::move(data);
  return *current;
}

// Checks once per scene and set, before any timing, that raystream and all three Embree modes
// agree (hit or occluded counts within max(2, 1e-4 n), same result or a tie for >= 99.9 % of
// rays; kernels/embree_agreement_test holds the strict check). Records raystream's TraceStats.
// Returns "" when they agree, else the reason (the benchmark is then skipped with it).
const std::string& Validate(SceneData& d, RaySet set) {
  const int s = static_cast<int>(set);
  if (d.validated[s]) return d.validation_error[s];
  d.validated[s] = true;
  RayStream& rays = d.sets.rays(set);
  const RayStreamView view = rays.view();
  const size_t n = view.size;
  const Coherence hint = RaySetCoherence(set);
  std::string report = std::string(RaySetName(set)) + "/" + d.name + ": ";
  bool ok = true;
  if (set == RaySet::kShadow || set == RaySet::kLight) {
    AlignedArray<int32_t> ours(n), theirs(n);
    if (set == RaySet::kLight) {
      // the light buffer must give the grid's results exactly (light_buffer_test)
      d.light_buffer->Occluded(view, ours.data(), &d.stats[s]);
      d.accel->Occluded(view, theirs.data());
      for (size_t i = 0; i < n; ++i) {
        if (ours[i] != theirs[i]) {
          ok = false;
          report += "light buffer differs from the grid at ray " + std::to_string(i) + "; ";
          break;
        }
      }
    } else {
      d.accel->Occluded(view, ours.data(), &d.stats[s]);
    }
    for (int m = 0; m < kNumEmbreeModes; ++m) {
      const auto mode = static_cast<EmbreeMode>(m);
      d.embree->Occluded(mode, view, theirs.data(), hint);
      const HitCompare c = CompareOccluded(ours.data(), theirs.data(), n);
      ok = ok && c.Ok();
      report += (m ? "; " : "") + c.Str("raystream", EmbreeModeName(mode));
    }
  } else {
    HitStream ours(n), theirs(n);
    ours.Resize(n);
    theirs.Resize(n);
    ours.Reset();
    d.accel->Intersect(view, ours.view(), &d.stats[s]);
    for (int m = 0; m < kNumEmbreeModes; ++m) {
      const auto mode = static_cast<EmbreeMode>(m);
      theirs.Reset();
      d.embree->Intersect(mode, view, theirs.view(), hint);
      const HitCompare c = CompareHits(ours.view(), theirs.view(), n);
      ok = ok && c.Ok();
      report += (m ? "; " : "") + c.Str("raystream", EmbreeModeName(mode));
    }
  }
  std::fprintf(stderr, "[trace_bench] validate %s %s\n", report.c_str(), ok ? "OK" : "FAILED");
  if (!ok) d.validation_error[s] = "validation failed: " + report;
  return d.validation_error[s];
}

// ---------------------------------------------------------------------------------------------
// Benchmarks.

// Per-item cost of a timed loop, from its rdtsc ticks (wall clock: includes time this thread
// was descheduled) and its thread CPU time converted to ticks at the TSC rate ("cpu_ticks").
struct TickMeter {
  uint64_t t0 = Ticks();
  double cpu0 = ThreadCpuSeconds();
  void Report(benchmark::State& state, size_t items_per_iteration, const char* name,
              const char* cpu_name) const {
    const uint64_t ticks = Ticks() - t0;
    const double cpu = ThreadCpuSeconds() - cpu0;
    const double items =
        static_cast<double>(state.iterations()) * static_cast<double>(items_per_iteration);
    if (items <= 0) return;
    state.counters[name] = static_cast<double>(ticks) / items;
    state.counters[cpu_name] = cpu * TscGhz() * 1e9 / items;
  }
};

// "<set>/<scene>/raystream" or "<set>/<scene>/embree{1,16,1M}": one pass over the set per
// iteration.
void BM_Trace(benchmark::State& state, const std::string& scene, RaySet set, int tracer) {
  SceneData& d = GetScene(scene);
  if (!d.load_error.empty()) {
    state.SkipWithError(d.load_error.c_str());
    return;
  }
  const std::string& error = Validate(d, set);
  if (!error.empty()) {
    state.SkipWithError(error.c_str());
    return;
  }
  const RayStreamView rays = d.sets.rays(set).view();
  HitStreamView hits = d.hits.view();
  hits.size = rays.size;
  const Coherence hint = RaySetCoherence(set);
  const bool occlusion = set == RaySet::kShadow || set == RaySet::kLight;
  const TickMeter meter;
  for (auto _ : state) {
    if (tracer == -1) {
      if (set == RaySet::kLight) {
        d.light_buffer->Occluded(rays, d.occluded.data());
      } else if (occlusion) {
        d.accel->Occluded(rays, d.occluded.data());
      } else {
        d.accel->Intersect(rays, hits);
      }
    } else if (tracer == -3) {  // the light set through the grid (Accel::Occluded)
      d.accel->Occluded(rays, d.occluded.data());
    } else if (tracer == -2) {  // the same structure without packets: the per-ray stream DDA
      const Accel::Impl& m = AccelImpl(*d.accel);
      ForEachFramePiece(m, rays, rays.size, [&](const RayStreamView& piece, size_t first) {
        if (occlusion) {
          OccludedStreamDda(m.dda, piece, d.occluded.data() + first, m.dda_options, nullptr);
        } else {
          IntersectStreamDda(m.dda, piece, SubView(hits, first, piece.size), m.dda_options,
                             nullptr);
        }
      });
    } else {
      const auto mode = static_cast<EmbreeMode>(tracer);
      if (occlusion) {
        d.embree->Occluded(mode, rays, d.occluded.data(), hint);
      } else {
        d.embree->Intersect(mode, rays, hits, hint);
      }
    }
    benchmark::ClobberMemory();
  }
  meter.Report(state, rays.size, "ticks/ray", "cpu_ticks/ray");
  if (tracer == -1 && rays.size > 0) {
    // What the grid costs per ray: DDA cell steps and ray/triangle tests.
    const TraceStats& st = d.stats[static_cast<int>(set)];
    state.counters["cells/ray"] =
        static_cast<double>(st.cell_steps) / static_cast<double>(rays.size);
    state.counters["tests/ray"] =
        static_cast<double>(st.triangle_tests) / static_cast<double>(rays.size);
    // share of the rays traced in packets (BuildOptions::packets; the rest per ray)
    if (st.rays > 0) {
      state.counters["packet_share"] =
          static_cast<double>(st.packet_rays) / static_cast<double>(st.rays);
    }
  }
  state.SetItemsProcessed(state.iterations() * static_cast<int64_t>(rays.size));
}

// Minor page faults of this thread so far (first touches of fresh memory).
double ThreadMinorFaults() {
  rusage u{};
  getrusage(RUSAGE_THREAD, &u);
  return static_cast<double>(u.ru_minflt);
}

// "build/<scene>/raystream" (grid) or "build/<scene>/embree" (BVH, robust, medium quality):
// items are triangles, so items_per_second is triangles/s. Warm: each build reuses the memory
// the one before freed, as long as the C library keeps it (glibc does for these sizes, but
// whether it does depends on its trimming heuristics and the order of frees in the build).
// "build-cold/<scene>/...": the C library's free memory is handed back to the system before
// each build (malloc_trim(0), not timed), so every build first-touches all its memory, as the
// one build of the `raystream` command does: the command's `grid build` line reports this
// build (same options: the defaults; `--threads 1`, else on the render's threads). faults/build
// counts the minor page faults (each costs a kernel entry and a page zeroed: a large share of a
// cold build).
// "rebuild/<scene>/...": the structure of a moving mesh rebuilt in place, as a renderer of a
// dynamic scene does every frame: Accel::Rebuild (its memory and its temporaries' taken back)
// against Embree's rtcUpdateGeometryBuffer + rtcCommitScene on the same scene (EmbreePeer::
// Update; Embree reuses its BVH memory). "rebuild-2t/<scene>/raystream": the same with
// build_threads = 2, timed by the wall clock (the build's parallel speed-up over rebuild/ on
// an idle 2-core machine; the same structure as one thread builds).
enum class BuildMode { kWarm, kCold, kInPlace };
constexpr const char* kBuildGroups[] = {"build/", "build-cold/", "rebuild/"};

void BM_Build(benchmark::State& state, const std::string& scene, bool embree, BuildMode mode,
              int threads = 1) {
  const bool cold = mode == BuildMode::kCold;
  BuildOptions options = BenchBuildOptions("trace_bench");
  options.build_threads = threads;
  SceneData& d = GetScene(scene);
  if (!d.load_error.empty()) {
    state.SkipWithError(d.load_error.c_str());
    return;
  }
  if (embree && !d.rebuild_peer) d.rebuild_peer = std::make_unique<EmbreePeer>(d.mesh);
  const TickMeter meter;
  double faults = 0;
  for (auto _ : state) {
    if (cold) {
      state.PauseTiming();
#ifdef __GLIBC__
      malloc_trim(0);
#endif
      state.ResumeTiming();
    }
    const double faults0 = ThreadMinorFaults();
    if (embree && mode == BuildMode::kInPlace) {
      d.rebuild_peer->Update(d.mesh);
    } else if (embree) {
      d.rebuild_peer->Build(d.mesh);
    } else if (mode == BuildMode::kInPlace) {
      if (!d.rebuilt) d.rebuilt = std::make_unique<Accel>(d.mesh, options);
      d.rebuilt->Rebuild(d.mesh, options);
      benchmark::DoNotOptimize(d.rebuilt.get());
    } else {
      Accel accel(d.mesh, options);
      benchmark::DoNotOptimize(&accel);
    }
    faults += ThreadMinorFaults() - faults0;
  }
  // (build-cold: the tick counters include the untimed trims; items_per_second does not)
  meter.Report(state, d.mesh.num_triangles, "ticks/tri", "cpu_ticks/tri");
  if (state.iterations() > 0) {
    state.counters["faults/build"] = faults / static_cast<double>(state.iterations());
  }
  state.SetItemsProcessed(state.iterations() * static_cast<int64_t>(d.mesh.num_triangles));
}

// "build-light/<scene>/raystream": rs::LightBuffer's build over the scene's Accel for the
// benchmark light (items are triangles), rebuilt in place as the renderer does every frame (a
// new LightBuffer per iteration measured the allocator: its fresh pages made single runs vary
// 2-8x).
void BM_BuildLight(benchmark::State& state, const std::string& scene) {
  SceneData& d = GetScene(scene);
  if (!d.load_error.empty()) {
    state.SkipWithError(d.load_error.c_str());
    return;
  }
  const float light[3] = {d.light.x, d.light.y, d.light.z};
  const TickMeter meter;
  LightBuffer lb(*d.accel, light);
  for (auto _ : state) {
    lb.Rebuild(*d.accel, light);
    benchmark::DoNotOptimize(&lb);
  }
  meter.Report(state, d.mesh.num_triangles, "ticks/tri", "cpu_ticks/tri");
  state.SetItemsProcessed(state.iterations() * static_cast<int64_t>(d.mesh.num_triangles));
}

// "frame/<scene>/<tracer>": time to image for one frame_size^2 frame of a dynamic scene:
// the rebuild in place (as rebuild/), primary closest hits, shadow ray generation from those
// hits, occlusion (raystream-light: the light buffer's rebuild in place and its rays). Primary
// rays are generated once, outside the timing. Items are frames (items_per_second = fps).
void BM_Frame(benchmark::State& state, const std::string& scene, int tracer) {
  SceneData& d = GetScene(scene);
  if (!d.load_error.empty()) {
    state.SkipWithError(d.load_error.c_str());
    return;
  }
  if (d.frame_primary.empty()) {
    MakePrimaryRays(d.scene, Cfg().frame_size, Cfg().frame_size, d.frame_primary);
    d.frame_hits.Resize(d.frame_primary.size());
    d.frame_occluded.Reserve(d.frame_primary.size());
  }
  if (tracer >= 0 && !d.rebuild_peer) d.rebuild_peer = std::make_unique<EmbreePeer>(d.mesh);
  const BuildOptions options = BenchBuildOptions("trace_bench");  // once, not per frame
  if (tracer < 0 && !d.rebuilt) d.rebuilt = std::make_unique<Accel>(d.mesh, options);
  const float light[3] = {d.light.x, d.light.y, d.light.z};
  // created untimed, as the Accel above: every timed frame rebuilds both in place (a first
  // frame that created the light buffer paid its construction and fresh pages too, and the
  // large scenes' frame rows run one iteration: conference's raystream-light row took 503 ms
  // against 337 for the same frame with the Accel's shadow rays)
  if (tracer == -3 && !d.rebuilt_light) {
    d.rebuilt_light = std::make_unique<LightBuffer>(*d.rebuilt, light);
  }
  const RayStreamView primary = d.frame_primary.view();
  const HitStreamView hits = d.frame_hits.view();
  size_t shadow_rays = 0;
  size_t occluded = 0;
  for (auto _ : state) {
    if (tracer < 0) d.rebuilt->Rebuild(d.mesh, options);
    if (tracer == -3) {  // raystream-light: the shadow rays from the light, a LightBuffer
      const Accel& accel = *d.rebuilt;
      accel.Intersect(primary, hits);
      MakeShadowRays(d.scene, primary, hits, d.light, d.frame_shadow);
      MakeLightRays(d.frame_shadow.view(), d.light, d.frame_light);
      d.rebuilt_light->Rebuild(accel, light);
      d.rebuilt_light->Occluded(d.frame_light.view(), d.frame_occluded.data());
    } else if (tracer < 0) {
      const Accel& accel = *d.rebuilt;
      accel.Intersect(primary, hits);
      MakeShadowRays(d.scene, primary, hits, d.light, d.frame_shadow);
      accel.Occluded(d.frame_shadow.view(), d.frame_occluded.data());
    } else {
      const auto mode = static_cast<EmbreeMode>(tracer);
      d.rebuild_peer->Update(d.mesh);
      d.rebuild_peer->Intersect(mode, primary, hits, Coherence::kCoherent);
      MakeShadowRays(d.scene, primary, hits, d.light, d.frame_shadow);
      d.rebuild_peer->Occluded(mode, d.frame_shadow.view(), d.frame_occluded.data(),
                               Coherence::kCoherent);
    }
    shadow_rays = d.frame_shadow.size();
    benchmark::ClobberMemory();
  }
  for (size_t i = 0; i < shadow_rays; ++i) occluded += d.frame_occluded[i] != 0 ? 1 : 0;
  state.counters["shadow_rays"] = static_cast<double>(shadow_rays);
  state.counters["occluded"] = static_cast<double>(occluded);
  state.SetItemsProcessed(state.iterations());
}

// ---------------------------------------------------------------------------------------------
// Reporting: adds the raystream/Embree speed ratios to the raystream rows (from the Embree rows
// of the same run, same aggregate) and prints a summary table at the end.

// "<group>/<scene>/<tracer>" -> ("<group>/<scene>", "<tracer>").
std::pair<std::string, std::string> SplitName(const std::string& name) {
  const size_t slash = name.rfind('/');
  if (slash == std::string::npos) return {name, ""};
  return {name.substr(0, slash), name.substr(slash + 1)};
}

template <class Base>
class RatioReporter : public Base {
 public:
  using Base::Base;
  using Run = benchmark::BenchmarkReporter::Run;

  void ReportRuns(const std::vector<Run>& runs) override {
    std::vector<Run> copy = runs;
    for (Run& run : copy) {
      if (run.error_occurred) continue;
      const auto it = run.counters.find("items_per_second");
      if (it == run.counters.end()) continue;
      const double rate = it->second.value;
      const auto [group, tracer] = SplitName(run.run_name.function_name);
      const std::string agg = run.run_type == Run::RT_Aggregate ? run.aggregate_name : "";
      if (!agg.empty() && agg != "mean" && agg != "median") continue;
      const std::pair<std::string, std::string> key{group, agg};
      if (rates_.find(key) == rates_.end()) order_.push_back(key);
      rates_[key][tracer] = rate;
      if (tracer != "raystream") continue;
      for (const auto& [other, other_rate] : rates_[{group, agg}]) {
        if (other == "raystream" || other_rate <= 0) continue;
        run.counters["vs_" + other] = benchmark::Counter(rate / other_rate);
      }
    }
    Base::ReportRuns(copy);
  }

  // Mrays/s (Mtris/s for build, ms per frame for frame) and ratios, one line per group.
  void PrintSummary(std::FILE* out) const {
    std::fprintf(out,
                 "\n== raystream vs Embree %s (same run; vs = raystream speed / Embree speed) ==\n"
                 "%s\n",
                 EmbreeVersion(), kCycleNote);
    for (const auto& key : order_) {
      const auto& [group, agg] = key;
      const auto& tracers = rates_.at(key);
      if (!agg.empty() && agg != "median") continue;
      const bool frame = group.rfind("frame/", 0) == 0;
      const bool build = group.rfind("build", 0) == 0 ||  // build/, build-cold/, build-light/
                         group.rfind("rebuild", 0) == 0;    // rebuild/, rebuild-2t/
      const auto ours = tracers.find("raystream");
      std::fprintf(out, "%-24s", group.c_str());
      for (const auto& [tracer, rate] : tracers) {
        if (frame) {
          std::fprintf(out, "  %s %.1f ms", tracer.c_str(), 1e3 / rate);
        } else {
          std::fprintf(out, "  %s %.2f %s", tracer.c_str(), rate * 1e-6,
                       build ? "Mtris/s" : "Mrays/s");
        }
      }
      if (ours != tracers.end()) {
        for (const auto& [tracer, rate] : tracers) {
          if (tracer == "raystream" || rate <= 0) continue;
          std::fprintf(out, "  vs_%s %.3f", tracer.c_str(), ours->second / rate);
        }
      }
      std::fprintf(out, "\n");
    }
  }

 private:
  // (group, aggregate) -> tracer -> items per second; order_ keeps the order of the runs.
  std::map<std::pair<std::string, std::string>, std::map<std::string, double>> rates_;
  std::vector<std::pair<std::string, std::string>> order_;
};

void Configure() {
  Config& c = Cfg();
  const char* full = std::getenv("RS_BENCH_FULL");
  if (full != nullptr && std::string(full) != "0" && std::string(full) != "") {
    c.width = c.height = 1024;
    c.repetitions = 5;
    c.min_time = 0.5;
  }
  BenchSize("trace_bench", &c.width, &c.height);
  c.scenes = BenchScenes(c.scenes);
}

// Rates use the CPU time of the (single) benchmark thread, Google Benchmark's default, not wall
// time: these 2-core machines are shared, and a descheduled tracer would look slow. Embree runs
// with threads=1, so its build and traversal run on this thread too; on an idle machine the two
// agree. Minimum time and repetitions come in as default flags (see Main), which keeps the names
// bare ("primary/bunny/raystream") and lets the command line override them.
template <class F>
void Add(const std::string& name, F&& fn) {
  benchmark::RegisterBenchmark(name.c_str(), std::forward<F>(fn))->Unit(benchmark::kMillisecond);
}

void Register(const std::string& scene) {
  for (const BuildMode mode : {BuildMode::kWarm, BuildMode::kCold, BuildMode::kInPlace}) {
    const std::string group = kBuildGroups[int(mode)] + scene;
    Add(group + "/embree", [scene, mode](benchmark::State& s) { BM_Build(s, scene, true, mode); });
    Add(group + "/raystream",
        [scene, mode](benchmark::State& s) { BM_Build(s, scene, false, mode); });
  }
  benchmark::RegisterBenchmark(("rebuild-2t/" + scene + "/raystream").c_str(),
                               [scene](benchmark::State& s) {
                                 BM_Build(s, scene, false, BuildMode::kInPlace, 2);
                               })
      ->Unit(benchmark::kMillisecond)
      ->UseRealTime();
  for (int si = 0; si < kNumRaySets; ++si) {
    const auto set = static_cast<RaySet>(si);
    const std::string prefix = std::string(RaySetName(set)) + "/" + scene + "/";
    for (int m = 0; m < kNumEmbreeModes; ++m) {
      Add(prefix + EmbreeModeName(static_cast<EmbreeMode>(m)),
          [scene, set, m](benchmark::State& s) { BM_Trace(s, scene, set, m); });
    }
    Add(prefix + "raystream", [scene, set](benchmark::State& s) { BM_Trace(s, scene, set, -1); });
    if (set == RaySet::kLight) {  // raystream = the LightBuffer; raystream-grid = the Accel
      Add(prefix + "raystream-grid",
          [scene, set](benchmark::State& s) { BM_Trace(s, scene, set, -3); });
      continue;
    }
    Add(prefix + "raystream-rays",
        [scene, set](benchmark::State& s) { BM_Trace(s, scene, set, -2); });
  }
  Add("build-light/" + scene + "/raystream",
      [scene](benchmark::State& s) { BM_BuildLight(s, scene); });
  for (int m = 0; m < kNumEmbreeModes; ++m) {
    Add("frame/" + scene + "/" + EmbreeModeName(static_cast<EmbreeMode>(m)),
        [scene, m](benchmark::State& s) { BM_Frame(s, scene, m); });
  }
  Add("frame/" + scene + "/raystream", [scene](benchmark::State& s) { BM_Frame(s, scene, -1); });
  Add("frame/" + scene + "/raystream-light",
      [scene](benchmark::State& s) { BM_Frame(s, scene, -3); });
}

int Main(int argc, char** argv) {
  // Initialize consumes the --benchmark_* flags, so look for the output format first.
  bool json = false;
  for (int i = 1; i < argc; ++i) json = json || std::string(argv[i]) == "--benchmark_format=json";
  std::fprintf(json ? stderr : stdout, "[trace_bench] %s\n", kCycleNote);
  Configure();
  ApplyIsaEnv();
  const Config& c = Cfg();
  for (const std::string& scene : c.scenes) {
    if (SceneAvailable("trace_bench", scene)) Register(scene);
  }
  benchmark::AddCustomContext(
      "embree", std::string(EmbreeVersion()) + " (robust, medium build quality, threads=1)");
  benchmark::AddCustomContext("ray_sets", std::to_string(c.width) + "x" + std::to_string(c.height) +
                                              ", frame " + std::to_string(c.frame_size) + "x" +
                                              std::to_string(c.frame_size));
  AddTscContext();
  benchmark::AddCustomContext("cycles", kCycleNote);
  benchmark::AddCustomContext("ratios", "vs_X = raystream speed / X speed, same run");

  // Defaults for this suite, placed before the user's flags so that those win.
  std::vector<std::string> defaults = {"--benchmark_min_time=" + std::to_string(c.min_time)};
  if (c.repetitions > 1) {
    defaults.push_back("--benchmark_repetitions=" + std::to_string(c.repetitions));
    defaults.push_back("--benchmark_report_aggregates_only=true");
  }
  std::vector<char*> args = {argv[0]};
  for (std::string& flag : defaults) args.push_back(flag.data());
  for (int i = 1; i < argc; ++i) args.push_back(argv[i]);
  int args_count = static_cast<int>(args.size());
  args.push_back(nullptr);
  benchmark::Initialize(&args_count, args.data());
  if (benchmark::ReportUnrecognizedArguments(args_count, args.data())) return 1;
  if (json) {
    RatioReporter<benchmark::JSONReporter> reporter;
    benchmark::RunSpecifiedBenchmarks(&reporter);
    reporter.PrintSummary(stderr);
  } else {
    // Not tabular: the raystream rows carry extra counters, which would repeat the header.
    const auto opts =
        isatty(1) ? benchmark::ConsoleReporter::OO_Color : benchmark::ConsoleReporter::OO_None;
    RatioReporter<benchmark::ConsoleReporter> reporter(opts);
    benchmark::RunSpecifiedBenchmarks(&reporter);
    reporter.PrintSummary(stdout);
  }
  benchmark::Shutdown();
  Current().reset();
  return 0;
}

}  // namespace
}  // namespace rs::bench

int main(int argc, char** argv) { return rs::bench::Main(argc, argv); }
