// The renderer's time to image, raystream vs Embree 3 in the same run: the serial frame engine
// (rs::SerialRenderer, one thread, depth 4) renders each scene through rs::Accel (its shadow
// rays through one rs::LightBuffer per light, as the raystream command does) and through
// Embree (bench/peer/embree_tracer.h: every ray, the shadow rays from the light too), with the
// same camera (BenchCamera: ANCHORS.md's views), the
// scene's lights and shading, and the same default RenderOptions (batch, ray_budget). Rows:
//   render/<scene>/<tracer>  one frame, the structure built once before timing;
//   image/<scene>/<tracer>   time to image of a dynamic scene: the structure rebuilt in place
//                            (Accel::Rebuild and LightBuffer::Rebuild, or EmbreePeer::Update:
//                            rtcUpdateGeometryBuffer + rtcCommitScene) + frame, every iteration.
// Before timing, both images are rendered once and compared; a scene whose images differ
// (beyond kPixelTolerance) in more than 0.1 % of pixels fails its rows (diff_pixels and
// max_abs_diff are on every row). Counters: frame_s (the renderer's wall time; build_s on image
// rows), Mrays/s over the row's time, trace / shade / kernel (= trace + shade) / outside shares
// of frame_s, rays/call_<kind> (rays per kernel call), rays_<kind> per frame, ns/ray_<kind>
// (the tracer's time per ray of that kind: where the two sides differ), packet_share
// (raystream: rays traced in 64-ray packets), and on the raystream rows time_vs_embree16 =
// raystream CPU time / the Embree row's median CPU time (run just before it, same process).
// A summary of the medians and ratios is printed at the end.
// Environment: RS_BENCH_SIZE=WxH (default 1024x1024), RS_BENCH_SCENES=a,b,c (default
// erw6,bunny,sponza,office-graz,conference; missing shared scenes are skipped),
// RS_BENCH_GRID and RS_BENCH_LAMBDA (raystream's BuildOptions: BenchBuildOptions).
#include <benchmark/benchmark.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <map>
#include <memory>
#include <span>
#include <string>
#include <vector>

#include "bench/common/bench_scenes.h"
#include "bench/common/tsc.h"
#include "bench/peer/embree_peer.h"
#include "bench/peer/embree_tracer.h"
#include "bench/peer/ray_sets.h"
#include "include/raystream/raystream.h"
#include "scenes/load.h"
#include "sched/engine.h"
#include "sched/framebuffer.h"
#include "sched/render.h"

namespace rs::bench {
namespace {

// rtcIntersect16 / rtcOccluded16: the fastest mode on every coherent set (ANCHORS.md).
constexpr EmbreeMode kEmbreeMode = EmbreeMode::k16;
// A pixel differs when a channel differs by more than this, relative to max(1, value): far
// above the rounding of Embree's t, u, v against ours, far below a different triangle's shade.
constexpr float kPixelTolerance = 1e-3f;
constexpr double kMaxDifferingShare = 1e-3;  // 0.1 % of the pixels

struct Config {
  int width = 1024;
  int height = 1024;
  int depth = 4;
  std::vector<std::string> scenes{"erw6", "bunny", "sponza", "office-graz", "conference"};
} g_config;

// One scene, loaded by the first benchmark that needs it (rows run scene after scene, so only
// one scene is held at a time), with both structures built and the image check done.
struct SceneData {
  std::string name;
  std::string error;  // load failure or image mismatch: every row of the scene is skipped
  Scene scene;
  MeshView mesh;
  std::unique_ptr<Accel> accel;
  std::vector<LightBuffer> light_buffers;  // over accel: raystream's shadow rays
  std::unique_ptr<EmbreePeer> peer;
  std::unique_ptr<Accel> rebuilt;  // image rows: rebuilt in place every iteration
  Camera camera;
  RenderOptions options;
  SerialRenderer renderer;  // keeps its arenas between frames, as a walk-through would
  Framebuffer fb;
  size_t differing_pixels = 0;  // Embree vs raystream image, beyond kPixelTolerance
  size_t inexact_pixels = 0;    // not bit-identical
  double max_abs_diff = 0;
};

std::unique_ptr<SceneData> g_current;

// Renders the frame of `d` through `tracer` (nullptr: accel and its light buffers) into a
// cleared d.fb.
FrameStats RenderOnce(SceneData& d, const Accel& accel, std::span<const LightBuffer> buffers,
                      const Tracer* tracer) {
  FrameContext ctx = MakeFrameContext(d.scene, accel, d.camera, d.options);
  ctx.tracer = tracer;
  ctx.light_buffers = buffers;
  d.fb.Clear();
  return d.renderer.Render(ctx, d.fb);
}

// Renders both images once and counts the pixels that differ.
void CheckImages(SceneData& d) {
  const EmbreeTracer embree(*d.peer, kEmbreeMode);
  RenderOnce(d, *d.accel, {}, &embree);
  const std::vector<float> theirs = d.fb.ToRgb();
  RenderOnce(d, *d.accel, d.light_buffers, nullptr);
  const std::vector<float> ours = d.fb.ToRgb();
  for (size_t p = 0; p < d.fb.num_pixels(); ++p) {
    bool differs = false, inexact = false;
    for (size_t c = 3 * p; c < 3 * p + 3; ++c) {
      const float diff = std::fabs(ours[c] - theirs[c]);
      d.max_abs_diff = std::max(d.max_abs_diff, static_cast<double>(diff));
      inexact = inexact || diff != 0.0f;
      differs = differs || diff > kPixelTolerance * std::max({1.0f, ours[c], theirs[c]});
    }
    d.differing_pixels += differs ? 1 : 0;
    d.inexact_pixels += inexact ? 1 : 0;
  }
  const double share =
      static_cast<double>(d.differing_pixels) / static_cast<double>(d.fb.num_pixels());
  std::fprintf(stderr,
               "[render_bench] image check %s: %zu of %zu pixels differ (%.4f %%; %zu not "
               "bit-identical), max abs difference %.3g: %s\n",
               d.name.c_str(), d.differing_pixels, d.fb.num_pixels(), 100.0 * share,
               d.inexact_pixels, d.max_abs_diff, share > kMaxDifferingShare ? "FAILED" : "OK");
  if (share > kMaxDifferingShare) {
    d.error = "image check failed: " + std::to_string(d.differing_pixels) +
              " pixels differ between raystream and Embree (> 0.1 %)";
  }
}

SceneData& GetScene(const std::string& name) {
  if (g_current && g_current->name == name) return *g_current;
  g_current.reset();  // free the previous scene first
  g_current = std::make_unique<SceneData>();
  SceneData& d = *g_current;
  d.name = name;
  try {
    d.scene = LoadScene(name);
    d.mesh = d.scene.mesh();
    d.accel = std::make_unique<Accel>(d.mesh, BenchBuildOptions("render_bench"));
    d.light_buffers = BuildLightBuffers(d.scene, *d.accel);
    d.peer = std::make_unique<EmbreePeer>(d.mesh);
    d.camera = BenchCamera(d.scene);
    d.options.width = g_config.width;
    d.options.height = g_config.height;
    d.options.max_depth = g_config.depth;
    d.fb = Framebuffer(d.options.width, d.options.height);
    std::fprintf(stderr, "[render_bench] %s: %zu triangles, %zu lights, %dx%d depth %d\n",
                 name.c_str(), d.mesh.num_triangles, d.scene.lights.size(), d.options.width,
                 d.options.height, d.options.max_depth);
    CheckImages(d);
  } catch (const std::exception& e) {
    d.error = "loading " + name + ": " + e.what();
    std::fprintf(stderr, "[render_bench] %s\n", d.error.c_str());
  }
  return d;
}

// Thread CPU seconds per iteration of every run, by row name: the ratios and the summary.
std::map<std::string, std::vector<double>>& Runs() {
  static std::map<std::string, std::vector<double>> runs;
  return runs;
}

// The tracer's ns per ray of each kind of every row (its last run), by row name: the summary.
std::map<std::string, std::array<double, kNumRayKinds>>& KindNs() {
  static std::map<std::string, std::array<double, kNumRayKinds>> ns;
  return ns;
}

double Median(std::vector<double> v) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  return v.size() % 2 ? v[v.size() / 2] : 0.5 * (v[v.size() / 2 - 1] + v[v.size() / 2]);
}

std::string RowName(bool rebuild, const std::string& scene, bool embree) {
  return std::string(rebuild ? "image/" : "render/") + scene + "/" +
         (embree ? EmbreeModeName(kEmbreeMode) : "raystream");
}

// One row. CPU time of this thread (Embree runs with threads=1 on it too) drives the rates and
// ratios, as in trace_bench; frame_s / build_s and the shares are the renderer's wall clock.
void BM_Render(benchmark::State& state, const std::string& scene, bool embree, bool rebuild) {
  SceneData& d = GetScene(scene);
  if (!d.error.empty()) {
    state.SkipWithError(d.error.c_str());
    return;
  }
  const EmbreeTracer tracer(*d.peer, kEmbreeMode);
  std::vector<LightBuffer> rebuilt_lights;  // rebuilt in place every iteration (image rows)
  const auto rebuild_ours = [&] {  // the grid's and the light buffers' build
    if (!d.rebuilt) d.rebuilt = std::make_unique<Accel>(d.mesh, BenchBuildOptions("render_bench"));
    d.rebuilt->Rebuild(d.mesh);
    RebuildLightBuffers(d.scene, *d.rebuilt, &rebuilt_lights);
  };
  // One untimed rebuild first, so every timed one is a moving scene's steady state, as on
  // Embree's side (its scene, d.peer, exists before the first Update): a first iteration that
  // created the light buffers first-touched their memory, and the rows of a large scene run
  // once or twice (conference's image row, run once: 913 ms, 477 of them building, against
  // about 475 ms for a warm image).
  if (rebuild && !embree) rebuild_ours();
  FrameStats last, sum;
  double build_seconds = 0, cpu_seconds = 0;
  for (auto _ : state) {
    state.PauseTiming();
    d.fb.Clear();
    state.ResumeTiming();
    const double cpu0 = ThreadCpuSeconds();
    const auto t0 = std::chrono::steady_clock::now();
    if (rebuild && embree) d.peer->Update(d.mesh);
    if (rebuild && !embree) rebuild_ours();
    build_seconds += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    last = embree ? RenderOnce(d, *d.accel, {}, &tracer)
           : rebuild ? RenderOnce(d, *d.rebuilt, rebuilt_lights, nullptr)
                     : RenderOnce(d, *d.accel, d.light_buffers, nullptr);
    cpu_seconds += ThreadCpuSeconds() - cpu0;
    sum.trace_seconds += last.trace_seconds;
    for (int k = 0; k < kNumRayKinds; ++k) sum.trace_kind_seconds[k] += last.trace_kind_seconds[k];
    sum.shade_seconds += last.shade_seconds;
    sum.total_seconds += last.total_seconds;
  }
  // Per-frame counts are the same every iteration (`last`); times are means.
  const double n = static_cast<double>(state.iterations());
  const double frame = sum.total_seconds / n;
  const double build = build_seconds / n;
  const double rays = static_cast<double>(last.TotalRays());
  auto& c = state.counters;
  c["frame_s"] = frame;
  if (rebuild) {
    c["build_s"] = build;
    c["build_share"] = build / (build + frame);
  }
  c["Mrays/s"] = rays / (frame + (rebuild ? build : 0)) * 1e-6;
  c["trace_share"] = sum.trace_seconds / sum.total_seconds;
  c["shade_share"] = sum.shade_seconds / sum.total_seconds;
  c["kernel_share"] = (sum.trace_seconds + sum.shade_seconds) / sum.total_seconds;
  c["outside_share"] = 1.0 - (sum.trace_seconds + sum.shade_seconds) / sum.total_seconds;
  for (const RayKind kind : {RayKind::kPrimary, RayKind::kShadow}) {
    const int k = static_cast<int>(kind);
    c[std::string("rays/call_") + RayKindName(kind)] =
        last.trace_calls[k]
            ? static_cast<double>(last.rays[k]) / static_cast<double>(last.trace_calls[k])
            : 0.0;
  }
  for (int k = 0; k < kNumRayKinds; ++k) {
    const std::string kind = RayKindName(static_cast<RayKind>(k));
    c["rays_" + kind] = static_cast<double>(last.rays[k]);
    // the tracer's time per ray of each kind (raystream: the Accel or the light buffers;
    // Embree: rtcIntersect16 / rtcOccluded16), the same rays on both rows
    if (last.rays[k] == 0) continue;
    const double ns = sum.trace_kind_seconds[k] / n / static_cast<double>(last.rays[k]) * 1e9;
    c["ns/ray_" + kind] = ns;
    KindNs()[RowName(rebuild, scene, embree)][static_cast<size_t>(k)] = ns;
  }
  if (!embree && last.trace.rays > 0) {
    c["packet_share"] =
        static_cast<double>(last.trace.packet_rays) / static_cast<double>(last.trace.rays);
  }
  c["diff_pixels"] = static_cast<double>(d.differing_pixels);
  c["max_abs_diff"] = d.max_abs_diff;
  // Rows run Embree first, so the raystream row divides by the Embree median of this process.
  const double ours = cpu_seconds / n;
  Runs()[RowName(rebuild, scene, embree)].push_back(ours);
  const double theirs = embree ? 0.0 : Median(Runs()[RowName(rebuild, scene, true)]);
  if (theirs > 0) c[std::string("time_vs_") + EmbreeModeName(kEmbreeMode)] = ours / theirs;
  state.SetItemsProcessed(state.iterations() * static_cast<int64_t>(last.TotalRays()));
}

// Median CPU ms per frame of every row and raystream ÷ Embree, one line per scene.
void PrintSummary(std::FILE* out) {
  std::fprintf(out,
               "\n== render_bench summary: median thread CPU ms; ratio = raystream time / Embree "
               "(%s, %s) time, same run ==\n",
               EmbreeVersion(), EmbreeModeName(kEmbreeMode));
  for (const std::string& scene : g_config.scenes) {
    std::string line;
    for (const bool rebuild : {false, true}) {
      const double theirs = Median(Runs()[RowName(rebuild, scene, true)]);
      const double ours = Median(Runs()[RowName(rebuild, scene, false)]);
      if (theirs <= 0 || ours <= 0) continue;
      char part[160];
      std::snprintf(part, sizeof(part), "  %s: embree %.1f ms, raystream %.1f ms, ratio %.3f",
                    rebuild ? "time to image" : "frame", 1e3 * theirs, 1e3 * ours, ours / theirs);
      line += part;
    }
    if (!line.empty()) std::fprintf(out, "%-12s%s\n", scene.c_str(), line.c_str());
    // the frame rows' tracer time per ray of each kind: which rays make the difference
    const auto theirs = KindNs().find(RowName(false, scene, true));
    const auto ours = KindNs().find(RowName(false, scene, false));
    if (theirs == KindNs().end() || ours == KindNs().end()) continue;
    std::string kinds;
    for (int k = 0; k < kNumRayKinds; ++k) {
      const double a = theirs->second[static_cast<size_t>(k)];
      const double b = ours->second[static_cast<size_t>(k)];
      if (a <= 0 || b <= 0) continue;
      char part[120];
      std::snprintf(part, sizeof(part), "  %s %.1f / %.1f (%.2f)",
                    RayKindName(static_cast<RayKind>(k)), a, b, b / a);
      kinds += part;
    }
    if (!kinds.empty()) {
      std::fprintf(out, "%-12s  tracer ns per ray, embree / raystream (ratio):%s\n", "",
                   kinds.c_str());
    }
  }
}

void Register(const std::string& scene) {
  for (const bool rebuild : {false, true}) {
    for (const bool embree : {true, false}) {  // Embree first: the raystream row's ratio
      benchmark::RegisterBenchmark(
          RowName(rebuild, scene, embree).c_str(),
          [=](benchmark::State& s) { BM_Render(s, scene, embree, rebuild); })
          ->Unit(benchmark::kMillisecond);
    }
  }
}

int Main(int argc, char** argv) {
  bool json = false;  // Initialize consumes the --benchmark_* flags: look first
  for (int i = 1; i < argc; ++i) json = json || std::string(argv[i]) == "--benchmark_format=json";
  Config& c = g_config;
  BenchSize("render_bench", &c.width, &c.height);
  c.scenes = BenchScenes(c.scenes);
  for (const std::string& scene : c.scenes) {
    if (SceneAvailable("render_bench", scene)) Register(scene);
  }
  benchmark::AddCustomContext("embree", std::string(EmbreeVersion()) +
                                            " (robust, medium build quality, threads=1, " +
                                            EmbreeModeName(kEmbreeMode) + ")");
  benchmark::AddCustomContext("render", std::to_string(c.width) + "x" + std::to_string(c.height) +
                                            ", depth " + std::to_string(c.depth) +
                                            ", SerialRenderer (1 thread), default RenderOptions");
  benchmark::AddCustomContext("time_vs_embree", "raystream CPU time / Embree CPU time, same run");
  benchmark::Initialize(&argc, argv);
  if (benchmark::ReportUnrecognizedArguments(argc, argv)) return 1;
  benchmark::RunSpecifiedBenchmarks();
  PrintSummary(json ? stderr : stdout);
  benchmark::Shutdown();
  g_current.reset();
  return 0;
}

}  // namespace
}  // namespace rs::bench

int main(int argc, char** argv) { return rs::bench::Main(argc, argv); }
