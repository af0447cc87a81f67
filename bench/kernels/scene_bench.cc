// rs::TraceScene costs: updating one geometry of an 8-geometry scene (UpdateGeometry + Commit:
// one grid rebuilt) against building the whole scene again, and closest-hit tracing of the same
// rays through the C API (rsSceneIntersect) against the C++ API (TraceScene::Intersect), per
// Highway target. Results are validated (C equals C++ bit for bit) before timing.
#include <hwy/targets.h>

#include <cmath>
#include <cstdlib>
#include <cstring>
#include <random>
#include <string>
#include <vector>

#include "bench/common/bench_main.h"
#include "include/raystream/raystream.h"
#include "include/raystream/raystream_c.h"

namespace rs::bench {
namespace {

constexpr int kGeometries = 8;
constexpr size_t kGrid = 96;  // per geometry: a 96x96 height field, 18432 triangles
constexpr size_t kRays = 1 << 16;

struct Mesh {
  std::vector<float> p;
  std::vector<uint32_t> idx;
};

// Height field g, shifted along x so that the geometries sit side by side.
Mesh HeightField(int g, float phase) {
  Mesh m;
  for (size_t y = 0; y <= kGrid; ++y) {
    for (size_t x = 0; x <= kGrid; ++x) {
      const float fx = float(x) / float(kGrid), fy = float(y) / float(kGrid);
      m.p.insert(m.p.end(), {float(g) + fx, fy, 0.1f * std::sin(20 * fx + phase) * std::cos(17 * fy)});
    }
  }
  for (size_t y = 0; y < kGrid; ++y) {
    for (size_t x = 0; x < kGrid; ++x) {
      const uint32_t a = uint32_t(y * (kGrid + 1) + x), b = a + 1, c = a + uint32_t(kGrid) + 1;
      m.idx.insert(m.idx.end(), {a, b, c + 1, a, c + 1, c});
    }
  }
  return m;
}

const std::vector<Mesh>& Meshes() {
  static const std::vector<Mesh> meshes = [] {
    std::vector<Mesh> v;
    for (int g = 0; g < kGeometries; ++g) v.push_back(HeightField(g, float(g)));
    return v;
  }();
  return meshes;
}

GeometryDesc Desc(const Mesh& m) {
  GeometryDesc d;
  d.positions = m.p.data();
  d.num_vertices = m.p.size() / 3;
  d.indices = m.idx.data();
  d.num_triangles = m.idx.size() / 3;
  return d;
}

TraceScene BuildScene() {
  TraceScene s;
  for (const Mesh& m : Meshes()) s.AttachGeometry(Desc(m));
  s.Commit();
  return s;
}

void BM_UpdateOne(benchmark::State& state) {
  TraceScene s = BuildScene();
  const Mesh moved = HeightField(3, 1.5f);
  const Mesh& orig = Meshes()[3];
  bool flip = false;
  for (auto _ : state) {
    s.UpdateGeometry(3, (flip ? orig : moved).p.data(), 12);
    s.Commit();
    flip = !flip;
  }
  state.SetItemsProcessed(state.iterations() * int64_t(orig.idx.size() / 3));
  state.SetLabel("triangles rebuilt per iteration: 1 of 8 geometries");
}

void BM_FullRebuild(benchmark::State& state) {
  for (auto _ : state) benchmark::DoNotOptimize(BuildScene());
  state.SetItemsProcessed(state.iterations() * int64_t(kGeometries * 2 * kGrid * kGrid));
}

RayBuffer& Rays() {
  static RayBuffer rays = [] {
    RayBuffer r(kRays);
    std::mt19937 rng(42);
    std::uniform_real_distribution<float> u(0.0f, 1.0f);
    for (size_t i = 0; i < kRays; ++i) {
      r.ox()[i] = kGeometries * u(rng), r.oy()[i] = u(rng), r.oz()[i] = 1.0f;
      r.dx()[i] = 0.2f * (u(rng) - 0.5f), r.dy()[i] = 0.2f * (u(rng) - 0.5f), r.dz()[i] = -1.0f;
    }
    return r;
  }();
  return rays;
}

struct CScene {
  RSScene scene = rsNewScene(nullptr);
  CScene() {
    for (const Mesh& m : Meshes()) {
      RSGeometryDesc d;
      rsInitGeometryDesc(&d);
      d.positions = m.p.data(), d.num_vertices = m.p.size() / 3;
      d.indices = m.idx.data(), d.num_triangles = m.idx.size() / 3;
      uint32_t id;
      if (rsSceneAttachGeometry(scene, &d, &id) != RS_ERROR_NONE) std::abort();
    }
    if (rsSceneCommit(scene) != RS_ERROR_NONE) std::abort();
  }
  ~CScene() { rsReleaseScene(scene); }
};

RSRays CRays(const RayView& v) {
  return RSRays{v.ox, v.oy, v.oz, v.dx, v.dy, v.dz, v.tnear, v.tfar, v.mask, v.id, v.size};
}
RSHits CHits(const HitView& h) {
  return RSHits{h.t, h.u, h.v, h.ng_x, h.ng_y, h.ng_z, h.prim, h.geom, h.inst, h.size};
}

void BM_Trace(benchmark::State& state, bool c_api, int64_t target) {
  hwy::SetSupportedTargetsForTest(target);
  const TraceScene s = BuildScene();
  const CScene cs;
  const RayView rays = Rays().View();
  HitBuffer hits(kRays), check(kRays);
  // Validate once: the C API gives the C++ API's results bit for bit, most rays hit.
  s.Intersect(rays, check.View());
  const RSRays cr = CRays(rays);
  const HitView hv = hits.View();
  const RSHits ch = CHits(hv);
  if (rsSceneIntersect(cs.scene, &cr, &ch) != RS_ERROR_NONE ||
      std::memcmp(hits.t(), check.t(), kRays * 4) != 0 ||
      std::memcmp(hits.prim(), check.prim(), kRays * 4) != 0 ||
      std::memcmp(hits.geom(), check.geom(), kRays * 4) != 0) {
    state.SkipWithError("C and C++ results differ");
  }
  for (auto _ : state) {
    if (c_api) {
      rsSceneIntersect(cs.scene, &cr, &ch);
    } else {
      s.Intersect(rays, hv);
    }
    benchmark::ClobberMemory();
  }
  state.SetItemsProcessed(state.iterations() * int64_t(kRays));
  hwy::SetSupportedTargetsForTest(0);
}

void RegisterAll() {
  benchmark::RegisterBenchmark("SceneUpdate/one_of_8", BM_UpdateOne)->Unit(benchmark::kMillisecond);
  benchmark::RegisterBenchmark("SceneUpdate/full_rebuild_8", BM_FullRebuild)
      ->Unit(benchmark::kMillisecond);
  for (const int64_t t : hwy::SupportedAndGeneratedTargets()) {
    const std::string name = hwy::TargetName(t);
    benchmark::RegisterBenchmark(("SceneTrace/cpp/" + name).c_str(), BM_Trace, false, t)
        ->Unit(benchmark::kMillisecond);
    benchmark::RegisterBenchmark(("SceneTrace/c/" + name).c_str(), BM_Trace, true, t)
        ->Unit(benchmark::kMillisecond);
  }
}

}  // namespace
}  // namespace rs::bench

int main(int argc, char** argv) {
  return rs::bench::RunBenchmarkMain(
      argc, argv,
      {{"scene", "8 height fields of 18432 triangles each; 65536 rays from above"}},
      rs::bench::RegisterAll);
}
