// Fixed, small workloads for instruction counting under callgrind (bench/scripts/run_callgrind.sh):
// runs ONE pass of one hot kernel on one Highway target and prints the work it did (rays, ray-cell
// steps, ray/triangle tests, shaded hits), so callgrind's count for the kernel function
// (--toggle-collect, printed by --print-toggle) divides into instructions per unit of work.
//
// Usage: kernel_counts --kernel K [--target T] [--workload W] [--print-toggle | --list-targets]
//   K: dda (SIMD stream DDA, rs::Accel::Intersect), dda_single (the Cell paper's single-ray form),
//      tri1x4 (1 ray x 4-wide triangle bundles, closest hit), any1x4 (any hit), trinx1 (N rays x 1
//      triangle), shade (rs::Shade), packet (coherent 64-ray packets, IntersectCoherent; the
//      count includes the packets left to the stream DDA). T: a Highway target name (AVX2,
//      SSE4, ...), "ref" for the scalar oracle, or omitted for dynamic dispatch. W (dda,
//      dda_single, packet): corners (an almost empty 64^3 grid: DDA steps alone), spherebox
//      (random rays), bunny (primary rays), bunny256 and spherebox256 (256 x 256 primary rays:
//      bunny from its camera, spherebox from the centre along +x).
#include <hwy/targets.h>

#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <memory>
#include <string>
#include <vector>

#include "bench/kernels/dda_workload.h"
#include "bench/kernels/tri_workload.h"
#include "include/raystream/raystream.h"
#include "kernels/accel_impl.h"
#include "kernels/dda_simd.h"
#include "kernels/packet_dda.h"
#include "kernels/shade.h"
#include "kernels/tri_intersect.h"
#include "scenes/load.h"
#include "sched/framebuffer.h"
#include "streams/ray_stream.h"
#include "streams/raygen.h"

namespace rs::bench {
namespace {

constexpr float kInf = std::numeric_limits<float>::infinity();
constexpr size_t kRandomRays = 4096;
constexpr int kPrimarySize = 64;      // bunny primary rays: 64 x 64
constexpr int kShadeSize = 64;        // spherebox primary hits shaded: 64 x 64
constexpr size_t kShadeChunk = 1024;  // rays per Shade call, as in shade_bench
constexpr size_t kTriCell = 16;       // triangles in the tri* workload cell
constexpr size_t kTriRays = 4096;
constexpr uint32_t kTriSeed = 20261122;

struct Args {
  std::string kernel;
  std::string target;  // "" = dispatch, "ref" = scalar oracle
  std::string workload = "corners";
  bool print_toggle = false;
  bool list_targets = false;
};

// The function whose inclusive instruction count is the kernel's, as a callgrind
// --toggle-collect pattern (demangled name, '*' wildcard).
std::string TogglePattern(const Args& a, const std::string& target) {
  if (a.target == "ref") {
    if (a.kernel == "dda") return "rs::ref::AccelIntersect(*";
    if (a.kernel == "tri1x4") return "rs::ref::IntersectBundles(*";
    if (a.kernel == "any1x4") return "rs::ref::OccludedBundles(*";
    if (a.kernel == "trinx1") return "rs::ref::IntersectStream(*";
    if (a.kernel == "shade") return "rs::ref::Shade(*";
    return "";
  }
  if (a.kernel == "packet") return "rs::IntersectCoherent(*";
  const std::string ns = "rs::N_" + target + "::";
  if (a.kernel == "dda") return ns + "IntersectStreamDda(*";
  if (a.kernel == "dda_single") return ns + "IntersectSingleDda(*";
  if (a.kernel == "tri1x4") return ns + "IntersectBundles(*";
  if (a.kernel == "any1x4") return ns + "OccludedBundles(*";
  if (a.kernel == "trinx1") return ns + "IntersectStream(*";
  if (a.kernel == "shade") return ns + "ShadeSimd(*";
  return "";
}

// Random rays: origins uniform in the scene's bounds, directions uniform (fixed seed).
void RandomRays(const Scene& s, RayStream& rays) {
  glm::vec3 lo, hi;
  s.Bounds(lo, hi);
  AppendRandomRays(lo, hi, kRandomRays, rays);
}

int RunDda(const Args& a) {
  Scene scene;
  BuildOptions options;
  RayStream rays;
  if (a.workload == "corners") {
    scene = CornersScene();
    options.grid = GridKind::kUniform;
    options.lambda = 32768.0f;
    RandomRays(scene, rays);
  } else if (a.workload == "spherebox") {
    scene = LoadScene("spherebox");
    RandomRays(scene, rays);
  } else if (a.workload == "bunny" || a.workload == "bunny256" || a.workload == "spherebox256") {
    const bool big = a.workload != "bunny";
    scene = LoadScene(a.workload == "spherebox256" ? "spherebox" : "bunny");
    Camera camera = scene.camera;
    if (a.workload == "spherebox256") {  // inside the room, along +x
      glm::vec3 lo, hi;
      scene.Bounds(lo, hi);
      camera.eye = 0.5f * (lo + hi);
      camera.look_at = camera.eye + glm::vec3(1.0f, 0.0f, 0.0f);
    }
    const int size = big ? 4 * kPrimarySize : kPrimarySize;
    AppendPrimaryRays(MakeCameraBasis(camera, size, size), Tile{0, 0, size, size},
                      RayOrder::kScanline, rays);
    rays.FillPadding();
  } else {
    std::fprintf(stderr, "kernel_counts: unknown workload %s\n", a.workload.c_str());
    return 2;
  }
  const Accel accel(scene.mesh(), options);
  HitStream hits(rays.size());
  hits.Resize(rays.size());
  hits.Reset();
  TraceStats st;
  const Accel::Impl& m = AccelImpl(accel);
  if (a.kernel == "dda_single") {
    const RayStreamView r = rays.view();
    for (size_t i = 0; i < r.size; ++i) {
      RayHit h;
      IntersectSingleDda(m.dda, r.ox[i] - m.shift[0], r.oy[i] - m.shift[1], r.oz[i] - m.shift[2],
                         r.dx[i], r.dy[i], r.dz[i], r.tmin[i], r.tmax[i], &h, &st);
    }
  } else if (a.target == "ref") {
    ref::AccelIntersect(m, rays.view(), hits.view(), &st);
  } else {
    ForEachFramePiece(m, rays.view(), rays.size(), [&](const RayStreamView& r, size_t first) {
      const HitStreamView h = SubView(hits.view(), first, r.size);
      a.kernel == "packet" ? IntersectCoherent(m.dda, r, h, m.dda_options, &st)
                           : IntersectStreamDda(m.dda, r, h, m.dda_options, &st);
    });
  }
  const AccelInfo info = accel.Info();
  std::printf(
      "kernel_counts: workload=%s grid=%s res=%dx%dx%d triangles=%zu rays=%zu steps=%llu "
      "tests=%llu\n",
      a.workload.c_str(), info.kind, info.resolution[0], info.resolution[1], info.resolution[2],
      info.triangles, rays.size(), static_cast<unsigned long long>(st.cell_steps),
      static_cast<unsigned long long>(st.triangle_tests));
  return 0;
}

int RunTri(const Args& a) {
  TriWorkload w;
  MakeTriWorkload(kTriCell, kTriRays, kTriSeed, &w);
  const TriBundleSpan span = w.span();
  const bool oracle = a.target == "ref";
  size_t hit = 0;
  if (a.kernel == "trinx1") {
    HitStream hits(w.rays.size());
    hits.Resize(w.rays.size());
    hits.Reset();
    if (oracle) {
      ref::IntersectStream(w.rays.view(), span, TriTest::kWatertight, hits.view());
    } else {
      IntersectStream(w.rays.view(), span, TriTest::kWatertight, hits.view());
    }
    for (size_t i = 0; i < w.rays.size(); ++i) hit += hits.view().prim[i] >= 0 ? 1 : 0;
  } else {
    for (const PreparedRay& r : w.prepared_rays) {
      if (a.kernel == "any1x4") {
        hit += oracle
                   ? ref::OccludedBundles(r, span, 0.0f, kInf, TriTest::kWatertight)
                   : OccludedBundles(r, span, 0.0f, kInf, TriTest::kWatertight, BundleWidth::kAuto);
      } else {
        ClosestHit h;
        if (oracle) {
          ref::IntersectBundles(r, span, 0.0f, kInf, TriTest::kWatertight, &h);
        } else {
          IntersectBundles(r, span, 0.0f, kInf, TriTest::kWatertight, BundleWidth::kAuto, &h);
        }
        hit += h.prim >= 0 ? 1 : 0;
      }
    }
  }
  std::printf(
      "kernel_counts: workload=cell%zu test=watertight width=auto rays=%zu tests=%zu "
      "hit_rays=%zu\n",
      kTriCell, w.rays.size(), w.tests_per_pass(), hit);
  return 0;
}

int RunShade(const Args& a) {
  Scene scene = LoadScene("spherebox");
  const Accel accel(scene.mesh());
  RayStream rays;
  AppendPrimaryRays(MakeCameraBasis(scene.camera, kShadeSize, kShadeSize),
                    Tile{0, 0, kShadeSize, kShadeSize}, RayOrder::kScanline, rays);
  rays.FillPadding();
  const size_t n = rays.size();
  HitStream hits(n);
  hits.Resize(n);
  hits.Reset();
  accel.Intersect(rays.view(), hits.view());
  ShadeOptions options;
  options.max_depth = 4;
  options.stages = ShadeStagesFor(scene, options);
  // Chunks copied into their own padded streams beforehand, as the renderer hands tasks over.
  std::vector<RayStream> chunk_rays;
  std::vector<HitStream> chunk_hits;
  size_t num_hits = 0;
  for (size_t first = 0; first < n; first += kShadeChunk) {
    const size_t count = std::min(kShadeChunk, n - first);
    RayStream r;
    HitStream h(count);
    h.Resize(count);
    for (size_t i = 0; i < count; ++i) {
      r.PushFrom(rays.view(), first + i);
      h.view().t[i] = hits.view().t[first + i];
      h.view().u[i] = hits.view().u[first + i];
      h.view().v[i] = hits.view().v[first + i];
      h.view().prim[i] = hits.view().prim[first + i];
      num_hits += h.view().prim[i] >= 0 ? 1 : 0;
    }
    r.FillPadding();
    chunk_rays.push_back(std::move(r));
    chunk_hits.push_back(std::move(h));
  }
  Framebuffer fb(kShadeSize, kShadeSize);
  ContributionStream contributions(kShadeChunk + kStreamPad);
  RayStream secondary;
  secondary.Reserve(kShadeChunk * (scene.lights.size() + 2) + kStreamPad);
  ShadeStats stats;
  size_t spawned = 0;
  for (size_t k = 0; k < chunk_rays.size(); ++k) {
    secondary.Clear();
    contributions.Clear();
    if (a.target == "ref") {
      ref::Shade(scene, options, chunk_rays[k].view(), chunk_hits[k].view(), contributions,
                 secondary, &stats);
    } else {
      Shade(scene, options, chunk_rays[k].view(), chunk_hits[k].view(), contributions, secondary,
            &stats);
    }
    fb.Add(contributions.view());
    spawned += secondary.size();
  }
  std::printf(
      "kernel_counts: workload=spherebox%dx%d rays=%zu hits=%zu lights=%zu spawned=%zu "
      "stages=0x%x\n",
      kShadeSize, kShadeSize, n, num_hits, scene.lights.size(), spawned, options.stages);
  return 0;
}

int Main(int argc, char** argv) {
  Args a;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    auto value = [&](std::string* out) {
      if (i + 1 >= argc) return false;
      *out = argv[++i];
      return true;
    };
    bool ok = true;
    if (arg == "--kernel") {
      ok = value(&a.kernel);
    } else if (arg == "--target") {
      ok = value(&a.target);
    } else if (arg == "--workload") {
      ok = value(&a.workload);
    } else if (arg == "--print-toggle") {
      a.print_toggle = true;
    } else if (arg == "--list-targets") {
      a.list_targets = true;
    } else {
      ok = false;
    }
    if (!ok) {
      std::fprintf(stderr, "kernel_counts: bad argument %s (see the header of kernel_counts.cc)\n",
                   arg.c_str());
      return 2;
    }
  }
  if (a.list_targets) {  // under valgrind: what this CPU (as valgrind shows it) supports
    for (const int64_t t : hwy::SupportedAndGeneratedTargets())
      std::printf("%s ", hwy::TargetName(t));
    std::printf("\ndispatch=%s\n", DdaTargetName());
    return 0;
  }
  std::string target_name = DdaTargetName();
  if (!a.target.empty() && a.target != "ref") {
    int64_t chosen = 0;
    for (const int64_t t : hwy::SupportedAndGeneratedTargets()) {
      if (a.target == hwy::TargetName(t)) chosen = t;
    }
    if (chosen == 0) {
      std::fprintf(stderr, "kernel_counts: target %s not supported here\n", a.target.c_str());
      return 2;
    }
    hwy::SetSupportedTargetsForTest(chosen);
    target_name = a.target;
  }
  const std::string toggle = TogglePattern(a, target_name);
  if (toggle.empty()) {
    std::fprintf(stderr, "kernel_counts: unknown kernel '%s' (or no oracle for it)\n",
                 a.kernel.c_str());
    return 2;
  }
  if (a.print_toggle) {
    std::printf("%s\n", toggle.c_str());
    return 0;
  }
  std::printf("kernel_counts: kernel=%s target=%s toggle=%s\n", a.kernel.c_str(),
              a.target == "ref" ? "ref" : target_name.c_str(), toggle.c_str());
  try {
    if (a.kernel == "dda" || a.kernel == "dda_single" || a.kernel == "packet") return RunDda(a);
    if (a.kernel == "shade") return RunShade(a);
    return RunTri(a);
  } catch (const Error& e) {
    std::fprintf(stderr, "kernel_counts: %s\n", e.what());
    return 1;
  }
}

}  // namespace
}  // namespace rs::bench

int main(int argc, char** argv) { return rs::bench::Main(argc, argv); }
