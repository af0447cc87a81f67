// Scalar comparison of the irregular grid with the grid rs::Accel builds (uniform or two-level):
// the diffuse rays of trace_bench (one per primary hit of a WxH image), traced by both scalar
// traversals and both SIMD stream kernels; prints cells, tests, build and trace time of each,
// the cost model's figures (the irregular grid's over its cells' own regions), and whether every
// hit agrees (exit status 1 if one differs). Times are one run: a hint, not a benchmark. Options: RS_IRR_TOP, RS_IRR_SUB (lambdas), RS_IRR_MERGE,
// RS_IRR_EXPAND (0/1).
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>

#include "bench/peer/ray_sets.h"
#include "include/raystream/raystream.h"
#include "kernels/accel_impl.h"
#include "kernels/dda_simd.h"
#include "kernels/irregular.h"
#include "kernels/irregular_simd.h"
#include "scenes/load.h"
#include "streams/ray_stream.h"

namespace {
double Now() {
  return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
}
double Env(const char* name, double fallback) {
  const char* v = std::getenv(name);
  return v != nullptr ? std::atof(v) : fallback;
}
}  // namespace

int main(int argc, char** argv) {
  using namespace rs;
  if (argc < 2) {
    std::fprintf(stderr, "usage: %s SCENE [WIDTH HEIGHT]\n", argv[0]);
    return 2;
  }
  const int width = argc > 3 ? std::atoi(argv[2]) : 256;
  const int height = argc > 3 ? std::atoi(argv[3]) : 256;
  try {
    const Scene scene = LoadScene(argv[1]);
    const Accel accel(scene.mesh());
    RayStream primary, diffuse;
    bench::MakePrimaryRays(scene, width, height, primary);
    HitStream h(primary.size());
    h.Resize(primary.size());
    accel.Intersect(primary.view(), h.view());
    bench::MakeDiffuseRays(scene, primary.view(), h.view(), 7, diffuse);
    const Accel::Impl& m = AccelImpl(accel);
    {  // into the Accel's frame (kernels/accel_impl.h): every trace below calls the kernels
      const RayStreamView v = diffuse.view();
      for (size_t i = 0; i < v.size; ++i) {
        v.ox[i] -= m.shift[0];
        v.oy[i] -= m.shift[1];
        v.oz[i] -= m.shift[2];
      }
    }
    IrregularOptions opt;
    opt.top_lambda = float(Env("RS_IRR_TOP", opt.top_lambda));
    opt.sub_lambda = float(Env("RS_IRR_SUB", opt.sub_lambda));
    opt.merge = Env("RS_IRR_MERGE", 1) != 0;
    opt.expand = Env("RS_IRR_EXPAND", 1) != 0;
    opt.model.visit = Env("RS_IRR_VISIT", opt.model.visit);
    opt.model.triangle = Env("RS_IRR_TRI", opt.model.triangle);
    IrregularGrid irr;
    double t = Now();
    BuildIrregularGrid(m.triangles, ComputeGridBounds(m.triangles), opt, 512, &irr);
    const double build = Now() - t;
    for (int rep = int(Env("RS_IRR_BUILDS", 0)); rep > 0; --rep) {  // for profilers
      BuildIrregularGrid(m.triangles, ComputeGridBounds(m.triangles), opt, 512, &irr);
    }
    const RayStreamView r = diffuse.view();
    const size_t n = r.size;
    std::vector<RayHit> a(n), b(n);
    TraceStats sa, sb;
    t = Now();
    for (size_t i = 0; i < n; ++i) {
      TraceClosestTwoLevel(m.grid, m.two_level, m.triangles, r.ox[i], r.oy[i], r.oz[i], r.dx[i],
                           r.dy[i], r.dz[i], r.tmin[i], r.tmax[i], &a[i], &sa);
    }
    const double ta = Now() - t;
    t = Now();
    for (size_t i = 0; i < n; ++i) {
      TraceClosestIrregular(irr, m.triangles, r.ox[i], r.oy[i], r.oz[i], r.dx[i], r.dy[i],
                            r.dz[i], r.tmin[i], r.tmax[i], &b[i], &sb);
    }
    const double tb = Now() - t;
    size_t differ = 0;
    for (size_t i = 0; i < n; ++i) differ += a[i].prim != b[i].prim || a[i].t != b[i].t;
    std::printf("%s: %zu diffuse rays, differ=%zu\n", argv[1], n, differ);
    std::printf("  accel %-9s cost %7.2f  cells/ray %6.2f tests/ray %6.2f  %.3f s  build %.3f s  %.1f MB\n",
                m.two_level.empty() ? "uniform" : "two-level", m.cost_estimate,
                double(sa.cell_steps) / n, double(sa.triangle_tests) / n, ta, m.build_seconds,
                double(m.grid.Bytes() + m.two_level.Bytes()) / 1e6);
    std::printf("  irregular cost %7.2f  cells/ray %6.2f tests/ray %6.2f  %.3f s  build %.3f s  %.1f MB\n",
                irr.region_cost, double(sb.cell_steps) / n, double(sb.triangle_tests) / n,
                tb, build, double(irr.Bytes()) / 1e6);
    std::printf("  accel flat cost %.2f; irregular tables: %zu top, %zu sub-cell entries\n",
                m.flat_cost_estimate, irr.num_top, irr.num_fine);
    std::printf("  irregular: top %dx%dx%d depth %d, base cells %zu, merges %zu, cells %zu "
                "(occupied %zu), refs %zu, expanded %zu; time ratio irregular/accel %.3f\n",
                irr.top_res[0], irr.top_res[1], irr.top_res[2], irr.depth, irr.base_cells,
                irr.merged, irr.num_cells, irr.lists.occupied_cells, irr.lists.num_refs,
                irr.expanded, tb / ta);
    // the SIMD stream kernels: Accel's grid against the irregular grid, best of 3
    IrregularDda idda;
    BuildIrregularDda(irr, m.triangles, &idda);
    HitStream ha(n), hb(n);
    ha.Resize(n);
    hb.Resize(n);
    for (int rep = int(Env("RS_IRR_LOOP", 0)); rep > 0; --rep) {
      IntersectStreamIrregular(idda, r, hb.view(), nullptr);  // for profilers
    }
    double sa_best = 1e30, sb_best = 1e30;
    TraceStats s1, s2;
    for (int rep = 0; rep < 3; ++rep) {
      s1 = s2 = TraceStats();
      t = Now();
      IntersectStreamDda(m.dda, r, ha.view(), m.dda_options, &s1);
      sa_best = std::min(sa_best, Now() - t);
      t = Now();
      IntersectStreamIrregular(idda, r, hb.view(), &s2);
      sb_best = std::min(sb_best, Now() - t);
    }
    size_t simd_differ = 0;
    for (size_t i = 0; i < n; ++i) {
      simd_differ += ha.view().prim[i] != hb.view().prim[i] || ha.view().t[i] != hb.view().t[i] ||
                     hb.view().prim[i] != b[i].prim;
    }
    std::printf("  SIMD %s: stream DDA %.4f s (cells/ray %.2f tests/ray %.2f), irregular %.4f s "
                "(cells/ray %.2f tests/ray %.2f), ratio irregular/DDA %.3f, differ=%zu\n",
                DdaTargetName(), sa_best, double(s1.cell_steps) / n, double(s1.triangle_tests) / n,
                sb_best, double(s2.cell_steps) / n, double(s2.triangle_tests) / n,
                sb_best / sa_best, simd_differ);
    return differ == 0 && simd_differ == 0 ? 0 : 1;
  } catch (const Error& e) {
    std::fprintf(stderr, "%s\n", e.what());
    return 1;
  }
}
