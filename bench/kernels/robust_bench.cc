// Robustness at 1e6 rays, with Embree beside raystream (tests/kernels/tri_simd_test.cc and
// tests/kernels/shade_test.cc check the same properties for raystream): (1) watertightness:
// rays from inside a closed icosphere at 1e5 from the origin aimed exactly at its vertices and
// edge midpoints, misses counted for the watertight and Moller-Trumbore kernels (scalar, 1x4
// and N x 1 on every Highway target), rs::Accel and Embree 3 robust (1 / 16 / 1M); (2) self-hits:
// secondary rays spawned by rs::Shade on closed spheres near, at and far from the origin, traced
// with rs::Accel, counting hits on the spawning triangle. Prints counts, not times.
//
// Usage: robust_bench [--rays N] [--secondary N]  (defaults 1e6 each).
// Exit status 1 if a watertight kernel or rs::Accel misses a ray, or a spawned ray self-hits
// (or, on the convex test spheres, an outward ray hits or an inward ray misses).
#include <hwy/targets.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <map>
#include <memory>
#include <random>
#include <string>
#include <utility>
#include <vector>

#include "include/raystream/raystream.h"
#include "kernels/dda_simd.h"
#include "kernels/grid.h"
#include "kernels/shade.h"
#include "kernels/tri_bundles.h"
#include "kernels/tri_intersect.h"
#include "kernels/triangle.h"
#include "scenes/scene.h"
#include "sched/framebuffer.h"
#include "streams/ray_stream.h"
#include "streams/raygen.h"
#include "tests/support/watertight.h"
#if RS_HAVE_EMBREE
#include "bench/peer/embree_peer.h"
#endif

namespace rs::bench {
namespace {

using test::MakeWatertightSetup;  // tests/support/watertight.h
using test::Misses;
using test::WatertightSetup;

constexpr float kInf = std::numeric_limits<float>::infinity();

double Seconds(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

// ---------------------------------------------------------------------------------------------
// (1) Watertightness.

// 1 ray x the bundles of its cell (scalar oracle if `simd` is false, else the dispatched SIMD
// kernel at `width`).
Misses CountBundleMisses(const WatertightSetup& s, TriTest test, bool simd, BundleWidth width) {
  Misses m;
  const RayStreamView r = const_cast<RayStream&>(s.rays).view();
  for (size_t i = 0; i < r.size; ++i) {
    const PreparedRay pr = PrepareRay(r.ox[i], r.oy[i], r.oz[i], r.dx[i], r.dy[i], r.dz[i]);
    const TriBundleSpan span = s.bundles.Cell(r.pixel[i]);
    ClosestHit h;
    if (simd) {
      IntersectBundles(pr, span, 0.0f, kInf, test, width, &h);
    } else {
      ref::IntersectBundles(pr, span, 0.0f, kInf, test, &h);
    }
    if (h.prim < 0) (s.IsVertexRay(i) ? m.vertex : m.edge) += 1;
  }
  return m;
}

// N rays x 1 triangle: all rays of a cell as one stream against the cell's triangles.
Misses CountStreamMisses(const WatertightSetup& s, TriTest test) {
  Misses m;
  RayStream stream(64);
  HitStream hits(64);
  const RayStreamView r = const_cast<RayStream&>(s.rays).view();
  for (const auto& [first, end] : s.cell_rays) {
    stream.Clear();
    for (size_t i = first; i < end; ++i) stream.PushFrom(r, i);
    stream.FillPadding();
    hits.Resize(stream.size());
    hits.Reset();
    IntersectStream(stream.view(), s.bundles.Cell(r.pixel[first]), test, hits.view());
    for (size_t i = first; i < end; ++i) {
      if (hits.view().prim[i - first] < 0) (s.IsVertexRay(i) ? m.vertex : m.edge) += 1;
    }
  }
  return m;
}

Misses CountHitMisses(const WatertightSetup& s, const HitStreamView& hits) {
  Misses m;
  for (size_t i = 0; i < hits.size; ++i) {
    if (hits.prim[i] < 0) (s.IsVertexRay(i) ? m.vertex : m.edge) += 1;
  }
  return m;
}

Misses CountOccludedMisses(const WatertightSetup& s, const std::vector<int32_t>& occluded) {
  Misses m;
  for (size_t i = 0; i < s.rays.size(); ++i) {
    if (occluded[i] == 0) (s.IsVertexRay(i) ? m.vertex : m.edge) += 1;
  }
  return m;
}

void PrintMisses(const char* what, const Misses& m, const WatertightSetup& s) {
  const size_t n = s.rays.size();
  std::printf("  %-44s %8zu %8zu %8zu   (%.3g per 1e6)\n", what, m.vertex, m.edge, m.total(),
              1e6 * static_cast<double>(m.total()) / static_cast<double>(n));
}

// Returns the number of watertight-kernel and rs::Accel misses (must be 0).
size_t RunWatertight(size_t n) {
  const auto t0 = std::chrono::steady_clock::now();
  WatertightSetup s;
  const std::string error = MakeWatertightSetup(6, n, &s);
  if (!error.empty()) {
    std::printf("watertightness: setup failed: %s\n", error.c_str());
    return 1;
  }
  const size_t edge_rays = s.rays.size() - s.vertex_rays;
  std::printf(
      "== Watertightness: %zu rays from inside a closed icosphere (%zu triangles, radius 100, "
      "centre (1e5, 1e5, 1e5), vertices on the 2^-6 lattice) ==\n"
      "%zu rays aim exactly at its %zu vertices, %zu exactly at the midpoints of its %zu edges "
      "(o + d == target exactly; origins within 50 of the centre). A miss is a ray that finds\n"
      "no triangle. Kernel rows test each ray against the triangles around its target (the "
      "vertex fan or the edge's 2 triangles); rs::Accel and Embree trace the whole mesh.\n",
      s.rays.size(), s.ico.tri.size(), s.vertex_rays, s.num_vertex_cells, edge_rays,
      s.bundles.num_cells - s.num_vertex_cells);
  std::printf("  %-44s %8s %8s %8s\n", "tracer", "vertex", "edge", "total");
  size_t must_be_zero = 0;
  for (const TriTest test : {TriTest::kWatertight, TriTest::kMollerTrumbore}) {
    const bool wt = test == TriTest::kWatertight;
    const std::string name = wt ? "watertight" : "Moller-Trumbore";
    const Misses scalar = CountBundleMisses(s, test, false, BundleWidth::kAuto);
    PrintMisses((name + " scalar (ref::)").c_str(), scalar, s);
    if (wt) must_be_zero += scalar.total();
    for (const int64_t target : hwy::SupportedAndGeneratedTargets()) {
      hwy::SetSupportedTargetsForTest(target);
      const std::string t = hwy::TargetName(target);
      const Misses bundles = CountBundleMisses(s, test, true, BundleWidth::kAuto);
      const Misses one = CountBundleMisses(s, test, true, BundleWidth::kOne);
      const Misses stream = CountStreamMisses(s, test);
      PrintMisses((name + " 1x4 (auto width) " + t).c_str(), bundles, s);
      PrintMisses((name + " 1x4 (one bundle) " + t).c_str(), one, s);
      PrintMisses((name + " N x 1 " + t).c_str(), stream, s);
      if (wt) must_be_zero += bundles.total() + one.total() + stream.total();
    }
    hwy::SetSupportedTargetsForTest(0);
  }
  const MeshView mesh = s.mesh();
  HitStream hits(s.rays.size());
  hits.Resize(s.rays.size());
  std::vector<int32_t> occluded(s.rays.size());
  {
    const Accel accel(mesh);
    hits.Reset();
    accel.Intersect(s.rays.view(), hits.view());
    const Misses closest = CountHitMisses(s, hits.view());
    accel.Occluded(s.rays.view(), occluded.data());
    const Misses any = CountOccludedMisses(s, occluded);
    const AccelInfo info = accel.Info();
    const std::string target = info.simd_target;
    PrintMisses(("rs::Accel Intersect (watertight, " + target + ")").c_str(), closest, s);
    PrintMisses(("rs::Accel Occluded (watertight, " + target + ")").c_str(), any, s);
    must_be_zero += closest.total() + any.total();
  }
#if RS_HAVE_EMBREE
  {
    const EmbreePeer embree(mesh);
    for (int mode = 0; mode < kNumEmbreeModes; ++mode) {
      const auto m = static_cast<EmbreeMode>(mode);
      hits.Reset();
      embree.Intersect(m, s.rays.view(), hits.view(), Coherence::kIncoherent);
      const Misses closest = CountHitMisses(s, hits.view());
      embree.Occluded(m, s.rays.view(), occluded.data(), Coherence::kIncoherent);
      const Misses any = CountOccludedMisses(s, occluded);
      const std::string name =
          std::string("Embree ") + EmbreeVersion() + " robust " + EmbreeModeName(m);
      PrintMisses((name + " intersect").c_str(), closest, s);
      PrintMisses((name + " occluded").c_str(), any, s);
    }
  }
#else
  std::printf("  (Embree rows skipped: built without Embree)\n");
#endif
  std::printf("watertight kernels + rs::Accel misses: %zu (must be 0); %.1f s\n\n", must_be_zero,
              Seconds(t0));
  return must_be_zero;
}

// ---------------------------------------------------------------------------------------------
// (2) Self-hits of spawned secondary rays.

// A scene holding one closed sphere of glass (reflection and refraction) and one point light.
Scene SphereScene(const glm::vec3& centre, float radius) {
  Scene scene;
  scene.name = "glass-sphere";
  scene.source = "procedural (robust_bench)";
  const Icosphere ico = MakeIcosphere(4, 1.0, {0.0, 0.0, 0.0}, 0.0);
  for (const auto& v : ico.v)
    scene.positions.push_back(centre + radius * glm::vec3(v[0], v[1], v[2]));
  for (const auto& t : ico.tri) scene.triangles.push_back(glm::uvec3(t[0], t[1], t[2]));
  Material glass;
  glass.name = "glass";
  glass.diffuse = glm::vec3(0.8f);
  glass.specular = glm::vec3(0.5f);
  glass.shininess = 20.0f;
  glass.reflectivity = 0.2f;
  glass.transmission = 0.7f;
  glass.ior = 1.5f;
  scene.materials.push_back(glass);
  scene.material_ids.assign(scene.triangles.size(), 0);
  PointLight light;
  light.position = centre + 4.0f * radius * glm::normalize(glm::vec3(0.3f, 1.0f, 0.5f));
  scene.lights.push_back(light);
  ValidateScene(scene);
  scene.features = ComputeFeatures(scene);
  return scene;
}

struct SelfHits {
  size_t spawned[kNumRayKinds] = {};
  size_t self[kNumRayKinds] = {};
  size_t other[kNumRayKinds] = {};   // hit another triangle
  size_t missed[kNumRayKinds] = {};  // hit nothing
  size_t total_spawned() const {
    size_t n = 0;
    for (size_t k : spawned) n += k;
    return n;
  }
  size_t total_self() const {
    size_t n = 0;
    for (size_t k : self) n += k;
    return n;
  }
};

// One view of `scene` (camera on a direction around the sphere, the sphere filling most of a
// size x size image): primary hits by rs::Accel, shaded by rs::Shade (the SIMD kernel, which
// spawns shadow, reflection and refraction rays from robustly offset origins), the spawned
// rays traced by rs::Accel; a spawned ray hitting its parent's triangle is a self-hit.
void ShadeView(const Scene& scene, const Accel& accel, const glm::vec3& centre, float radius,
               const glm::vec3& dir, int size, SelfHits* out) {
  Camera camera;
  camera.eye = centre + 3.0f * radius * dir;
  camera.look_at = centre;
  camera.up = std::fabs(dir.y) > 0.9f ? glm::vec3(1, 0, 0) : glm::vec3(0, 1, 0);
  camera.fov_y_deg = 42.0f;
  RayStream primary;
  AppendPrimaryRays(MakeCameraBasis(camera, size, size), Tile{0, 0, size, size},
                    RayOrder::kScanline, primary);
  primary.FillPadding();
  HitStream hits(primary.size());
  hits.Resize(primary.size());
  hits.Reset();
  accel.Intersect(primary.view(), hits.view());
  Framebuffer fb(size, size);
  RayStream secondary;
  ShadeOptions options;  // max_depth 4, cutoff 1e-3, stages from the scene
  ContributionStream contributions;
  Shade(scene, options, primary.view(), hits.view(), contributions, secondary);
  fb.Add(contributions.view());
  secondary.FillPadding();
  HitStream sec_hits(secondary.size());
  sec_hits.Resize(secondary.size());
  sec_hits.Reset();
  accel.Intersect(secondary.view(), sec_hits.view());
  const RayStreamView rv = secondary.view();
  const HitStreamView sh = sec_hits.view();
  const HitStreamView ph = hits.view();
  for (size_t i = 0; i < secondary.size(); ++i) {
    const int kind = rv.kind[i];
    const int32_t parent = ph.prim[rv.pixel[i]];  // primary ray i is pixel i (scanline)
    out->spawned[kind] += 1;
    if (sh.prim[i] == parent) {
      out->self[kind] += 1;
    } else if (sh.prim[i] >= 0) {
      out->other[kind] += 1;
    } else {
      out->missed[kind] += 1;
    }
  }
}

// Returns the number of self-hits plus wrong results (must be 0): on a closed convex sphere with
// the light outside, shadow and reflection rays leave outward and must hit nothing, refraction
// rays enter and must hit another triangle.
size_t RunSelfHits(size_t n) {
  const auto t0 = std::chrono::steady_clock::now();
  struct Sphere {
    glm::vec3 centre;
    float radius;
    const char* where;
  };
  const Sphere spheres[] = {{glm::vec3(0.0f), 1.0f, "r 1 at the origin"},
                            {glm::vec3(0.01f, -0.02f, 0.0f), 0.03f, "r 0.03 near 0 (|p| < 1/32)"},
                            {glm::vec3(1e5f, 1e5f, 1e5f), 100.0f, "r 100 at (1e5, 1e5, 1e5)"}};
  SelfHits per_sphere[3];
  std::vector<std::unique_ptr<Scene>> scenes;
  std::vector<std::unique_ptr<Accel>> accels;
  for (const Sphere& sp : spheres) {
    scenes.push_back(std::make_unique<Scene>(SphereScene(sp.centre, sp.radius)));
    accels.push_back(std::make_unique<Accel>(scenes.back()->mesh()));
  }
  // Views on a spherical Fibonacci spiral, round robin over the spheres, until n rays spawned.
  size_t total = 0;
  int views = 0;
  const float golden = 2.39996323f;
  for (int k = 0; total < n || k < 3; ++k) {  // every sphere at least once
    const float z = 1.0f - 2.0f * (static_cast<float>(k % 64) + 0.5f) / 64.0f;
    const float r = std::sqrt(std::max(0.0f, 1.0f - z * z));
    const glm::vec3 dir(r * std::cos(golden * static_cast<float>(k)), z,
                        r * std::sin(golden * static_cast<float>(k)));
    const int s = k % 3;
    const size_t before = per_sphere[s].total_spawned();
    ShadeView(*scenes[s], *accels[s], spheres[s].centre, spheres[s].radius, dir, 256,
              &per_sphere[s]);
    total += per_sphere[s].total_spawned() - before;
    ++views;
  }
  std::printf(
      "== Self-hits: %zu secondary rays spawned by rs::Shade (dispatch target %s), traced by "
      "rs::Accel ==\n"
      "Closed glass icospheres (5120 triangles, reflection 0.2, transmission 0.7, one point "
      "light), %d views of 256x256 primary rays. Outward rays (shadow, reflection) should hit\n"
      "nothing (convex), inward refraction rays another triangle; a self-hit is a hit on the "
      "triangle the ray was spawned from.\n",
      total, DdaTargetName(), views);
  std::printf("  %-30s %-10s %9s %9s %12s %9s\n", "sphere", "kind", "spawned", "self-hits",
              "hit another", "missed");
  size_t self = 0, wrong = 0;
  for (int s = 0; s < 3; ++s) {
    const SelfHits& h = per_sphere[s];
    for (int kind = 1; kind < kNumRayKinds; ++kind) {
      std::printf("  %-30s %-10s %9zu %9zu %12zu %9zu\n", spheres[s].where,
                  RayKindName(static_cast<RayKind>(kind)), h.spawned[kind], h.self[kind],
                  h.other[kind], h.missed[kind]);
    }
    self += h.total_self();
    const int shadow = static_cast<int>(RayKind::kShadow);
    const int reflection = static_cast<int>(RayKind::kReflection);
    const int refraction = static_cast<int>(RayKind::kRefraction);
    wrong += h.other[shadow] + h.other[reflection] + h.missed[refraction];
  }
  std::printf(
      "self-hits: %zu of %zu spawned rays (must be 0); wrong results (outward rays "
      "hitting, inward rays missing): %zu (must be 0); %.1f s\n\n",
      self, total, wrong, Seconds(t0));
  return self + wrong;
}

size_t ParseCount(const char* text) {
  const double v = std::strtod(text, nullptr);
  return v >= 1.0 ? static_cast<size_t>(v) : 0;
}

int Main(int argc, char** argv) {
  size_t rays = 1000000, secondary = 1000000;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    if (arg == "--rays" && i + 1 < argc) {
      rays = ParseCount(argv[++i]);
    } else if (arg == "--secondary" && i + 1 < argc) {
      secondary = ParseCount(argv[++i]);
    } else {
      std::fprintf(stderr, "usage: robust_bench [--rays N] [--secondary N]\n");
      return 2;
    }
  }
  if (rays == 0 || secondary == 0) {
    std::fprintf(stderr, "robust_bench: counts must be >= 1\n");
    return 2;
  }
  std::printf("robust_bench: raystream %s, Highway dispatch target %s\n\n", Version(),
              DdaTargetName());
  const size_t leaks = RunWatertight(rays);
  const size_t self = RunSelfHits(secondary);  // self-hits + wrong results
  return leaks == 0 && self == 0 ? 0 : 1;
}

}  // namespace
}  // namespace rs::bench

int main(int argc, char** argv) { return rs::bench::Main(argc, argv); }
