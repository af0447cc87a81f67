// Coherent 64-ray packets (kernels/packet_dda.h) on every compiled target against the scalar DDA
// (TraceClosestTwoLevel / TraceAnyTwoLevel): same triangle, t/u/v bit for bit, same occlusion,
// on camera rays in scanline and tile order, shadow rays to a point light, parallel bundles on
// cell boundaries with +-0 components, rays at the vertices and edges of a closed sphere, NaN
// and Inf rays inside coherent packets, 1e5 offsets and 1e-4 scales, flat and two-level grids;
// incoherent packets fall back to the stream DDA; rs::Accel with packets on equals packets off;
// shadow packets leaving a large floor (conference) never hit it.
#include <doctest/doctest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <string>
#include <thread>
#include <vector>

#include "include/raystream/raystream.h"
#include "kernels/accel_impl.h"
#include "kernels/dda.h"
#include "kernels/dda_simd.h"
#include "kernels/grid.h"
#include "kernels/packet_dda.h"
#include "kernels/triangle.h"
#include "kernels/two_level.h"
#include "scenes/icosphere.h"
#include "scenes/load.h"
#include "streams/ray_stream.h"
#include "tests/kernels/dda_util.h"
#include "tests/kernels/geometry_util.h"
#include "tests/kernels/spawn_util.h"
#include "tests/test_util.h"

namespace rs {
namespace {

using test::F;
using test::Rng;
using test::Soup;

using test::Built;
using test::kInf;
using test::kNaN;
using test::MakeStream;
using test::Ray;
using test::SameBits;

// Pinhole camera rays over w x h pixels from `eye` towards `at`, in scanline order or in 8x8
// tiles (64 rays: one packet per tile).
std::vector<Ray> CameraRays(const float eye[3], const float at[3], int w, int h, bool tiles) {
  double f[3], up[3] = {0, 1, 0}, rt[3], u[3];
  double len = 0;
  for (int a = 0; a < 3; ++a) {
    f[a] = double(at[a]) - eye[a];
    len += f[a] * f[a];
  }
  len = std::sqrt(len);
  for (double& c : f) c /= len;
  if (std::fabs(f[1]) > 0.99) {
    up[1] = 0;
    up[2] = 1;
  }
  rt[0] = f[1] * up[2] - f[2] * up[1];
  rt[1] = f[2] * up[0] - f[0] * up[2];
  rt[2] = f[0] * up[1] - f[1] * up[0];
  const double rl = std::sqrt(rt[0] * rt[0] + rt[1] * rt[1] + rt[2] * rt[2]);
  for (double& c : rt) c /= rl;
  u[0] = rt[1] * f[2] - rt[2] * f[1];
  u[1] = rt[2] * f[0] - rt[0] * f[2];
  u[2] = rt[0] * f[1] - rt[1] * f[0];
  const double tan_half = std::tan(30.0 * 3.14159265358979 / 180.0);
  const double aspect = double(w) / h;
  std::vector<Ray> rays;
  auto push = [&](int x, int y) {
    const double sx = (2.0 * (x + 0.5) / w - 1.0) * tan_half * aspect;
    const double sy = (1.0 - 2.0 * (y + 0.5) / h) * tan_half;
    Ray r;
    for (int a = 0; a < 3; ++a) {
      r.o[a] = eye[a];
      r.d[a] = F(f[a] + sx * rt[a] + sy * u[a]);
    }
    rays.push_back(r);
  };
  if (tiles) {
    for (int ty = 0; ty < h; ty += 8) {
      for (int tx = 0; tx < w; tx += 8) {
        for (int y = ty; y < std::min(h, ty + 8); ++y) {
          for (int x = tx; x < std::min(w, tx + 8); ++x) push(x, y);
        }
      }
    }
  } else {
    for (int y = 0; y < h; ++y) {
      for (int x = 0; x < w; ++x) push(x, y);
    }
  }
  return rays;
}

// Scalar oracle on one structure.
struct Oracle {
  std::vector<RayHit> hit;
  std::vector<int32_t> any;
  size_t hits = 0, occluded = 0;
};

Oracle RunOracle(const Built& b, const std::vector<Ray>& rays) {
  Oracle o;
  o.hit.resize(rays.size());
  o.any.resize(rays.size());
  for (size_t i = 0; i < rays.size(); ++i) {
    const Ray& r = rays[i];
    TraceClosestTwoLevel(b.grid, b.two, b.tris, r.o[0], r.o[1], r.o[2], r.d[0], r.d[1], r.d[2],
                         r.tmin, r.tmax, &o.hit[i], nullptr);
    o.any[i] = TraceAnyTwoLevel(b.grid, b.two, b.tris, r.o[0], r.o[1], r.o[2], r.d[0], r.d[1],
                                r.d[2], r.tmin, r.tmax, nullptr)
                   ? 1
                   : 0;
    o.hits += o.hit[i].prim >= 0;
    o.occluded += o.any[i];
  }
  return o;
}

// Shadow rays from the oracle's hits (pulled back towards the origin by a relative 1e-4) to
// `light`, tmax just short of it (primary misses spawn nothing).
std::vector<Ray> ShadowRays(const std::vector<Ray>& primary, const Oracle& o,
                            const float light[3]) {
  std::vector<Ray> rays;
  for (size_t i = 0; i < primary.size(); ++i) {
    if (o.hit[i].prim < 0) continue;
    const Ray& p = primary[i];
    Ray r;
    for (int a = 0; a < 3; ++a) {
      r.o[a] = F(p.o[a] + double(o.hit[i].t) * (1.0 - 1e-4) * p.d[a]);
      r.d[a] = F(double(light[a]) - r.o[a]);
    }
    r.tmin = 0.0f;
    r.tmax = F(1.0 - 1e-5);  // d reaches the light at t = 1
    rays.push_back(r);
  }
  return rays;
}

// Packets of parallel rays (d along an axis, the other components +0 or -0, or slightly
// tilted) whose origins lie on cell boundary planes and edges of the grid.
std::vector<Ray> BoundaryBundles(Rng& rng, const Built& b) {
  std::vector<Ray> rays;
  const Grid& g = b.grid;
  auto boundary = [&](int a, int k) { return F(double(g.lo[a]) + double(k) * g.cell_size[a]); };
  for (int axis = 0; axis < 3; ++axis) {
    for (const float sign : {1.0f, -1.0f}) {
      for (int kind = 0; kind < 3; ++kind) {
        const int a1 = (axis + 1) % 3, a2 = (axis + 2) % 3;
        for (int i = 0; i < 64; ++i) {
          Ray r;
          r.d[axis] = sign;
          r.d[a1] = kind == 0 ? 0.0f : kind == 1 ? -0.0f : F(1e-3 * (i % 8));
          r.d[a2] = kind == 2 ? F(-1e-3 * (i / 8)) : (i % 2 ? 0.0f : -0.0f);
          r.o[axis] = sign > 0 ? g.lo[axis] - 0.5f : g.hi[axis] + 0.5f;
          r.o[a1] = boundary(a1, int(rng.Below(uint32_t(g.res[a1] + 1))));
          r.o[a2] = i % 3 == 0 ? boundary(a2, int(rng.Below(uint32_t(g.res[a2] + 1))))
                               : rng.UniformF(g.lo[a2], g.hi[a2]);
          rays.push_back(r);
        }
      }
    }
  }
  return rays;
}

// Every target: IntersectCoherent / OccludedCoherent against the oracle, bit for bit; returns
// the packets traced as packets (dispatch target) and checks that some were.
struct PacketStats {
  uint64_t packets = 0, refused = 0, regrouped = 0;
};

PacketStats CheckCoherent(const Built& b, const std::vector<Ray>& rays, const std::string& what) {
  const Oracle o = RunOracle(b, rays);
  const size_t n = rays.size();
  RayStream stream = MakeStream(rays);
  DdaOptions options;
  PacketStats ps;
  test::ForEachTarget([&](const char* target) {
    INFO(what, ": target ", std::string(target), ", rays ", n);
    HitStream hits(n);
    hits.Resize(n);
    hits.Reset();
    const HitStreamView hv = hits.view();
    for (size_t i = 0; i < n; ++i) {  // garbage that must be overwritten
      hv.t[i] = 7.0f;
      hv.prim[i] = 3;
    }
    TraceStats st;
    IntersectCoherent(b.dda, stream.view(), hv, options, &st);
    size_t bad = 0;
    for (size_t i = 0; i < n; ++i) {
      const RayHit& e = o.hit[i];
      if (e.prim == hv.prim[i] && SameBits(e.t, hv.t[i]) && SameBits(e.u, hv.u[i]) &&
          SameBits(e.v, hv.v[i])) {
        continue;
      }
      if (++bad <= 3) {
        const Ray& r = rays[i];
        INFO("ray ", i, " o ", r.o[0], " ", r.o[1], " ", r.o[2], " d ", r.d[0], " ", r.d[1], " ",
             r.d[2], " tmin ", r.tmin, " tmax ", r.tmax, ": packet prim ", hv.prim[i], " t ",
             hv.t[i], ", scalar prim ", e.prim, " t ", e.t);
        CHECK(e.prim == hv.prim[i]);
      }
    }
    CHECK(bad == 0);
    CHECK(st.rays == n);
    std::vector<int32_t> occluded(n + 1, 77);
    TraceStats sa;
    OccludedCoherent(b.dda, stream.view(), occluded.data(), options, &sa);
    size_t any_bad = 0;
    for (size_t i = 0; i < n; ++i) any_bad += occluded[i] != o.any[i];
    CHECK(any_bad == 0);
    CHECK(occluded[n] == 77);
    CHECK(sa.rays == n);
    CHECK(st.packets - st.packets_regrouped + st.packets_refused ==
          (n + kCoherentPacketRays - 1) / kCoherentPacketRays * (n >= kCoherentPacketRays ? 1 : 0));
    CHECK(st.packets_regrouped <= st.packets);
    if (std::string(target) == hwy::TargetName(hwy::SupportedAndGeneratedTargets()[0])) {
      ps.packets = st.packets;
      ps.refused = st.packets_refused;
      ps.regrouped = st.packets_regrouped;
    }
  });
  MESSAGE(what, ": ", n, " rays, ", o.hits, " hits, ", o.occluded, " occluded; packets ",
          ps.packets, " (", ps.regrouped, " regrouped), refused ", ps.refused);
  return ps;
}

void CheckScene(const MeshView& mesh, const std::string& name, int w, int h) {
  Rng rng(91);
  for (const auto& [lambda, threshold] : {std::pair{0.5f, -1}, std::pair{4.0f, -1},
                                          std::pair{1.0f, 8}}) {
    const Built b(mesh, lambda, threshold);
    if (threshold >= 0 && b.two.empty()) continue;
    const std::string what = name + (threshold < 0 ? " flat" : " two-level") + " lambda " +
                             std::to_string(lambda);
    const Grid& g = b.grid;
    const float c[3] = {0.5f * (g.lo[0] + g.hi[0]), 0.5f * (g.lo[1] + g.hi[1]),
                        0.5f * (g.lo[2] + g.hi[2])};
    const float ext = std::max({g.hi[0] - g.lo[0], g.hi[1] - g.lo[1], g.hi[2] - g.lo[2]});
    // from outside, from inside looking along +x, and looking down -y
    const float out_eye[3] = {c[0] + 0.3f * ext, c[1] + 0.2f * ext, c[2] + 1.3f * ext};
    const float in_at[3] = {g.hi[0], c[1], c[2]};
    const float down_eye[3] = {c[0] + 0.01f * ext, c[1] + 0.45f * ext, c[2]};
    const float down_at[3] = {c[0], g.lo[1], c[2] + 0.001f * ext};
    // scanline order at 4x the width (a packet is a quarter row), and 8x8 tiles
    std::vector<Ray> primary = CameraRays(out_eye, c, 4 * w, h / 4, false);
    const std::vector<Ray> inside = CameraRays(c, in_at, w, h, true);
    const std::vector<Ray> down = CameraRays(down_eye, down_at, w / 2, h / 2, true);
    primary.insert(primary.end(), inside.begin(), inside.end());
    primary.insert(primary.end(), down.begin(), down.end());
    const PacketStats pp = CheckCoherent(b, primary, what + " camera rays");
    CHECK(pp.packets > 0);
    const Oracle o = RunOracle(b, primary);
    const float light[3] = {c[0] - 0.1f * ext, g.hi[1] - 0.05f * ext, c[2] + 0.1f * ext};
    const std::vector<Ray> shadow = ShadowRays(primary, o, light);
    const PacketStats ps = CheckCoherent(b, shadow, what + " shadow rays");
    CHECK(ps.packets > 0);
    CheckCoherent(b, BoundaryBundles(rng, b), what + " boundary bundles");
  }
}

TEST_CASE("procedural scenes: camera, shadow and boundary packets equal the scalar DDA") {
  for (const char* name : {"cornell", "erw6", "spherebox", "amphitheater:1"}) {
    const Scene scene = LoadScene(name);
    CheckScene(scene.mesh(), name, 64, 48);
  }
}

TEST_CASE("shared scenes: camera and shadow packets equal the scalar DDA") {
  for (const auto& [file, name] :
       {std::pair{"bunny/bun_zipper.ply", "bunny"}, std::pair{"sponza/sponza.obj", "sponza"},
        std::pair{"conference/conference.obj", "conference"}}) {
    if (!test::HaveSharedScene(file)) continue;
    const Scene scene = LoadScene(name);
    CheckScene(scene.mesh(), name, 64, 32);
  }
}

TEST_CASE("closed sphere at 1e5: packets of rays at vertices and edges from inside never leak") {
  // scenes/icosphere.h: coordinates snapped so that edge midpoints and o + d are exact floats
  const Icosphere ico = MakeIcosphere(4, 100.0, {1e5, 1e5, 1e5}, 64.0);
  Soup s;
  for (const auto& v : ico.v) s.AddVertex(v[0], v[1], v[2]);
  for (const auto& t : ico.tri) s.indices.insert(s.indices.end(), {t[0], t[1], t[2]});
  std::vector<std::array<float, 3>> targets(ico.v.begin(), ico.v.end());
  for (const auto& t : ico.tri) {
    for (int k = 0; k < 3; ++k) {
      const auto& a = ico.v[t[k]];
      const auto& b = ico.v[t[(k + 1) % 3]];
      targets.push_back({(a[0] + b[0]) * 0.5f, (a[1] + b[1]) * 0.5f, (a[2] + b[2]) * 0.5f});
    }
  }
  // one origin on the 2^-7 lattice inside; rays sorted by direction, so that consecutive rays
  // are neighbours (coherent packets)
  const float o[3] = {100001.0f, 99998.0f, 100000.5f};
  std::vector<Ray> rays;
  for (const auto& t : targets) {
    Ray r;
    for (int a = 0; a < 3; ++a) {
      r.o[a] = o[a];
      r.d[a] = t[a] - o[a];
    }
    rays.push_back(r);
  }
  std::sort(rays.begin(), rays.end(), [](const Ray& x, const Ray& y) {
    const int bx = int(std::floor(x.d[2] / 25.0f)), by = int(std::floor(y.d[2] / 25.0f));
    return bx != by ? bx < by : std::atan2(x.d[1], x.d[0]) < std::atan2(y.d[1], y.d[0]);
  });
  for (const float lambda : {0.5f, 4.0f}) {
    const Built b(s.view(), lambda, -1);
    const PacketStats ps = CheckCoherent(b, rays, "sphere vertices and edges");
    CHECK(ps.packets > 0);
    const Oracle orc = RunOracle(b, rays);
    CHECK(orc.hits == rays.size());  // watertight: every ray hits the closed sphere
  }
}

TEST_CASE("invalid rays inside coherent packets, huge offsets and tiny scales") {
  Rng rng(7);
  for (const auto& range : {std::pair{1e5, 1e5 + 20.0}, std::pair{-1e-4, 1e-4}}) {
    const double lo = range.first, hi = range.second;
    INFO("range ", lo, " .. ", hi);
    const Soup soup = test::RandomSoup(rng, 400, lo, hi, 0.2 * (hi - lo));
    const Built b(soup.view(), 4.0f, -1);
    const Grid& g = b.grid;
    const float c[3] = {0.5f * (g.lo[0] + g.hi[0]), 0.5f * (g.lo[1] + g.hi[1]),
                        0.5f * (g.lo[2] + g.hi[2])};
    const float ext = g.hi[0] - g.lo[0];
    const float eye[3] = {c[0] + 0.2f * ext, c[1] + 0.3f * ext, c[2] + 1.5f * ext};
    std::vector<Ray> rays = CameraRays(eye, c, 48, 32, true);
    // poison some lanes of coherent packets: NaN/Inf components, zero direction, empty ranges
    for (size_t i = 5; i < rays.size(); i += 37) {
      Ray& r = rays[i];
      switch ((i / 37) % 6) {
        case 0: r.o[1] = kNaN; break;
        case 1: r.d[2] = kInf; break;
        case 2: r.d[0] = r.d[1] = r.d[2] = 0.0f; break;
        case 3: r.tmin = kNaN; break;
        case 4: r.tmax = -1.0f; break;
        default: r.o[0] = -kInf; break;
      }
    }
    const PacketStats ps = CheckCoherent(b, rays, "camera rays with invalid lanes");
    CHECK(ps.packets > 0);
  }
  // a packet of only invalid rays, and streams shorter than a packet
  const Soup soup = test::RandomSoup(rng, 50, -1, 1, 0.3);
  const Built b(soup.view(), 4.0f, -1);
  std::vector<Ray> bad(70, Ray{{0, 0, 0}, {kNaN, 1, 0}});
  CheckCoherent(b, bad, "all invalid");
  const float eye[3] = {0.1f, 0.2f, 3.0f}, at[3] = {0, 0, 0};
  std::vector<Ray> few = CameraRays(eye, at, 7, 9, false);
  CheckCoherent(b, few, "63 rays");
}

TEST_CASE("incoherent rays are refused per packet and traced by the stream DDA") {
  Rng rng(11);
  const Soup soup = test::RandomSoup(rng, 500, -1, 1, 0.3);
  const Built b(soup.view(), 2.0f, -1);
  std::vector<Ray> rays(64 * 20);
  for (Ray& r : rays) {
    for (float& x : r.o) x = rng.UniformF(-1.2, 1.2);
    rng.Direction(r.d);
  }
  const PacketStats ps = CheckCoherent(b, rays, "random rays");
  CHECK(ps.refused == 20);
  // coherent and incoherent packets interleaved
  const float eye[3] = {0.1f, 0.2f, 3.0f}, at[3] = {0, 0, 0};
  const std::vector<Ray> cam = CameraRays(eye, at, 64, 20, false);
  std::vector<Ray> mixed;
  for (size_t p = 0; p < 20; ++p) {
    const std::vector<Ray>& from = p % 3 == 1 ? rays : cam;
    mixed.insert(mixed.end(), from.begin() + 64 * p, from.begin() + 64 * (p + 1));
  }
  const PacketStats pm = CheckCoherent(b, mixed, "mixed");
  CHECK(pm.packets > 0);
  CHECK(pm.refused >= 6);
}

TEST_CASE("refused packets are regrouped by direction and origin into packets") {
  // Rows of a wide camera (a 64-ray run spans the whole field of view: refused), and two opposite
  // cameras interleaved ray by ray (every run goes both ways: refused). Sorted by direction and
  // origin, their rays form packets again. Results stay the oracle's on every target
  // (CheckCoherent), whatever the order.
  Rng rng(12);
  const Soup soup = test::RandomSoup(rng, 500, -1, 1, 0.3);
  const Built b(soup.view(), 2.0f, -1);
  const float eye[3] = {0.1f, 0.2f, 3.0f}, at[3] = {0, 0, 0};
  const float eye2[3] = {-0.1f, -0.2f, -3.0f};
  const std::vector<Ray> a = CameraRays(eye, at, 64, 40, false);
  const std::vector<Ray> c = CameraRays(eye2, at, 64, 40, false);
  const PacketStats pa = CheckCoherent(b, a, "wide camera rows");
  CHECK(pa.refused > 0);
  CHECK(pa.regrouped > 0);
  std::vector<Ray> mixed;
  for (size_t i = 0; i < a.size(); ++i) {
    mixed.push_back(a[i]);
    mixed.push_back(c[i]);
  }
  // 5120 rays: several regroup sets of 1024 rays
  const PacketStats pm = CheckCoherent(b, mixed, "interleaved cameras");
  CHECK(pm.refused > 20);
  CHECK(2 * pm.regrouped >= pm.refused);
  // a set below two packets goes to the stream DDA as it is
  const std::vector<Ray> tail(mixed.begin() + 2048, mixed.begin() + 2048 + 100);
  const PacketStats pt = CheckCoherent(b, tail, "interleaved cameras, 100 rays");
  CHECK(pt.regrouped == 0);
}

// Regression (conference): coherent shadow packets leaving the big floor quad from 3.05e-5 above
// it (OffsetRayOrigin) towards a light: per literal ray of tests/kernels/spawn_util.h, the ray
// itself and 63 neighbours from an 8x8 patch of floor points around its origin, with unit
// directions too (reflection rays). On every target the packets (N rays x 1 triangle) equal the
// scalar DDA bit for bit, and neither they, the per-ray stream DDA nor the single-ray DDA
// report a hit (nothing but the floor and a small tetrahedron away from the rays).
TEST_CASE("regression: conference floor, coherent shadow packets from 3.05e-5 above it") {
  Soup soup;
  soup.AddTriangle(test::kFloorA, test::kFloorB, test::kFloorC);
  soup.AddTriangle(test::kFloorB, test::kFloorD, test::kFloorC);
  const float t0[3] = {-900, 500, 600}, t1[3] = {-850, 500, 600}, t2[3] = {-900, 550, 600};
  const float t3[3] = {-900, 500, 650};
  soup.AddTriangle(t0, t1, t2);
  soup.AddTriangle(t0, t1, t3);
  soup.AddTriangle(t0, t2, t3);
  soup.AddTriangle(t1, t2, t3);
  std::vector<Ray> rays;
  for (const bool unit : {false, true}) {
    for (const test::FloorRay& fr : test::kFloorRays) {
      const double light[3] = {double(fr.o[0]) + fr.d[0], double(fr.o[1]) + fr.d[1],
                               double(fr.o[2]) + fr.d[2]};
      for (int k = 0; k < 64; ++k) {
        Ray r;
        if (k == 0) {
          std::copy(fr.o, fr.o + 3, r.o);
          std::copy(fr.d, fr.d + 3, r.d);
        } else {
          const glm::vec3 p(F(fr.o[0] + 0.37 * (k % 8 - 4)), test::kFloorA[1],
                            F(fr.o[2] + 0.29 * (k / 8 - 4)));
          // 3.05e-5 = 2^-15 above the floor, as the literal rays (unit 16: 16 ulps of 16)
          const glm::vec3 o = OffsetRayOrigin(p, glm::vec3(0.0f, 1.0f, 0.0f), 16.0f);
          for (int a = 0; a < 3; ++a) {
            r.o[a] = o[a];
            r.d[a] = F(light[a] - o[a]);
          }
        }
        r.tmin = 0.0f;
        r.tmax = test::kFloorRayTmax;
        if (unit) {
          const double len = std::sqrt(double(r.d[0]) * r.d[0] + double(r.d[1]) * r.d[1] +
                                       double(r.d[2]) * r.d[2]);
          for (float& c : r.d) c = F(c / len);
          r.tmax = kInf;
        }
        rays.push_back(r);
      }
    }
  }
  for (const auto& [lambda, threshold] : {std::pair{4.0f, -1}, std::pair{1.0f, 0}}) {
    const Built b(soup.view(), lambda, threshold);
    const std::string what =
        std::string("conference floor shadow packets, ") + (threshold < 0 ? "flat" : "two-level");
    const Oracle o = RunOracle(b, rays);
    CHECK(o.hits == 0);
    CHECK(o.occluded == 0);
    const PacketStats ps = CheckCoherent(b, rays, what);
    CHECK(ps.packets > 0);
    RayStream stream = MakeStream(rays);
    const size_t n = rays.size();
    test::ForEachTarget([&](const char* target) {
      INFO(what, ": target ", std::string(target));
      HitStream hits(n);
      hits.Resize(n);
      hits.Reset();
      IntersectStreamDda(b.dda, stream.view(), hits.view(), DdaOptions{}, nullptr);
      std::vector<int32_t> occluded(n, 77);
      OccludedStreamDda(b.dda, stream.view(), occluded.data(), DdaOptions{}, nullptr);
      size_t stream_hits = 0, stream_occluded = 0, single_hits = 0;
      for (size_t i = 0; i < n; ++i) {
        stream_hits += hits.view().prim[i] >= 0;
        stream_occluded += occluded[i] != 0;
        const Ray& r = rays[i];
        RayHit h;
        single_hits += IntersectSingleDda(b.dda, r.o[0], r.o[1], r.o[2], r.d[0], r.d[1], r.d[2],
                                          r.tmin, r.tmax, &h, nullptr);
        single_hits += OccludedSingleDda(b.dda, r.o[0], r.o[1], r.o[2], r.d[0], r.d[1], r.d[2],
                                         r.tmin, r.tmax, nullptr);
      }
      CHECK(stream_hits == 0);
      CHECK(stream_occluded == 0);
      CHECK(single_hits == 0);
    });
  }
}

// Any-hit packets across empty space (the packet walk's skip-ring checks: PredictEmpty and the
// small-box test read DdaGrid::skip before the occupancy bits): a 100 x 100 floor at y = 0 and
// small occluders far apart below a point light. Shadow rays from points on the floor (origins
// on the surface, and 1e-4 above it) converge on the light; rays end exactly at an occluder's
// vertex, edge midpoint or inside it (tmax = 1, and one float short); rays along +y and
// grazing the floor. Every target, flat and two-level grids, against the scalar oracle.
TEST_CASE("shadow packets across empty space: skip rings, tmax at a triangle, surface origins") {
  Soup soup;
  const float f0[3] = {-50, 0, -50}, f1[3] = {50, 0, -50}, f2[3] = {-50, 0, 50};
  const float f3[3] = {50, 0, 50};
  soup.AddTriangle(f0, f1, f2);
  soup.AddTriangle(f1, f3, f2);
  // occluders: horizontal triangles (exact float vertices), 8 units wide
  const float occ[][3] = {{-30, 12, -30}, {20, 25, -10}, {-10, 40, 25}, {30, 8, 30}};
  for (const auto& c : occ) {
    const float a[3] = {c[0] - 4, c[1], c[2] - 4}, b[3] = {c[0] + 4, c[1], c[2] - 4};
    const float d[3] = {c[0], c[1], c[2] + 4};
    soup.AddTriangle(a, b, d);
  }
  const float light[3] = {3, 60, -2};
  std::vector<Ray> rays;
  // floor points in scanline runs of 64 over a 256 x 32 lattice (a run spans 24 units: slopes
  // within 0.4 of each other, coherent)
  for (const float lift : {0.0f, 1e-4f}) {
    for (int j = 0; j < 32; ++j) {
      for (int i = 0; i < 256; ++i) {
        Ray r;
        r.o[0] = F(-48.0 + 0.375 * i);
        r.o[1] = lift;
        r.o[2] = F(-48.0 + 3.0 * j);
        for (int a = 0; a < 3; ++a) r.d[a] = F(double(light[a]) - r.o[a]);
        r.tmin = 0.0f;
        r.tmax = 1.0f;
        rays.push_back(r);
      }
    }
  }
  // ending exactly at an occluder: its vertices, edge midpoints and centroid-ish interior points
  for (const auto& c : occ) {
    const float targets[][3] = {{c[0] - 4, c[1], c[2] - 4}, {c[0] + 4, c[1], c[2] - 4},
                                {c[0], c[1], c[2] + 4},     {c[0], c[1], c[2] - 4},
                                {c[0] - 2, c[1], c[2]},     {c[0], c[1], c[2]}};
    for (const auto& t : targets) {
      for (int k = 0; k < 64; ++k) {
        Ray r;
        r.o[0] = F(t[0] + 0.25 * (k % 8 - 4));
        r.o[1] = 0.0f;
        r.o[2] = F(t[2] + 0.25 * (k / 8 - 4));
        for (int a = 0; a < 3; ++a) r.d[a] = t[a] - r.o[a];  // exact: small integers / 4
        r.tmin = 0.0f;
        r.tmax = k % 2 == 0 ? 1.0f : std::nextafter(1.0f, 0.0f);
        rays.push_back(r);
      }
    }
  }
  // along +y from the floor (some under occluders), and grazing it along +x
  for (int k = 0; k < 256; ++k) {
    Ray up;
    up.o[0] = F(-34.0 + 0.125 * (k % 64));
    up.o[1] = 0.0f;
    up.o[2] = F(-34.0 + 2.0 * (k / 64));
    up.d[0] = k % 3 == 0 ? -0.0f : 0.0f;
    up.d[1] = 1.0f;
    up.d[2] = 0.0f;
    up.tmin = 0.0f;
    up.tmax = k % 4 == 0 ? 12.0f : 59.0f;  // 12: exactly at the first occluder's plane
    rays.push_back(up);
  }
  for (int k = 0; k < 128; ++k) {
    Ray g;
    g.o[0] = -49.0f;
    g.o[1] = k % 2 == 0 ? 0.0f : 1e-6f;
    g.o[2] = F(-40.0 + 0.5 * k);
    g.d[0] = 1.0f;
    g.d[1] = k % 4 < 2 ? 1e-7f : -1e-7f;
    g.d[2] = 0.0f;
    g.tmin = 0.0f;
    g.tmax = 98.0f;
    rays.push_back(g);
  }
  for (const auto& [lambda, threshold] : {std::pair{4.0f, -1}, std::pair{1.0f, 0}}) {
    const Built b(soup.view(), lambda, threshold);
    const std::string what =
        std::string("sparse shadow packets, ") + (threshold < 0 ? "flat" : "two-level");
    const Oracle o = RunOracle(b, rays);
    CHECK(o.occluded > 0);
    CHECK(o.occluded < rays.size());
    const PacketStats ps = CheckCoherent(b, rays, what);
    CHECK(ps.packets > 0);
  }
}

TEST_CASE("rs::Accel: packets on equal packets off on a procedural scene") {
  const Scene scene = LoadScene("spherebox");
  BuildOptions on, off;
  off.packets = false;
  const Accel a(scene.mesh(), on), b(scene.mesh(), off);
  const Grid& g = AccelImpl(a).grid;
  const float c[3] = {0.5f * (g.lo[0] + g.hi[0]), 0.5f * (g.lo[1] + g.hi[1]),
                      0.5f * (g.lo[2] + g.hi[2])};
  const float at[3] = {g.hi[0], c[1], c[2]};
  const std::vector<Ray> rays = CameraRays(c, at, 512, 16, false);  // a packet: 1/8 row
  RayStream stream = MakeStream(rays);
  const size_t n = rays.size();
  HitStream ha(n), hb(n);
  ha.Resize(n);
  hb.Resize(n);
  TraceStats sa, sb;
  a.Intersect(stream.view(), ha.view(), &sa);
  b.Intersect(stream.view(), hb.view(), &sb);
  size_t diff = 0;
  for (size_t i = 0; i < n; ++i) {
    diff += !(ha.view().prim[i] == hb.view().prim[i] && SameBits(ha.view().t[i], hb.view().t[i]) &&
              SameBits(ha.view().u[i], hb.view().u[i]) && SameBits(ha.view().v[i], hb.view().v[i]));
  }
  CHECK(diff == 0);
  CHECK(sa.packets > 0);
  CHECK(sb.packets == 0);
  CHECK(sa.rays == n);
  CHECK(sb.rays == n);
}

TEST_CASE("rs::Accel: concurrent packet traces from two threads equal one thread's") {
  // the packet kernels keep their scratch on the caller's stack: no shared state (run under
  // ThreadSanitizer with -Db_sanitize=thread)
  const Scene scene = LoadScene("erw6");
  const Accel accel(scene.mesh());
  const Grid& g = AccelImpl(accel).grid;
  const float c[3] = {0.5f * (g.lo[0] + g.hi[0]), 0.5f * (g.lo[1] + g.hi[1]),
                      0.5f * (g.lo[2] + g.hi[2])};
  const float at[3] = {g.hi[0], c[1], c[2]};
  const std::vector<Ray> rays = CameraRays(c, at, 256, 32, false);
  RayStream stream = MakeStream(rays);
  const size_t n = rays.size();
  HitStream ref(n);
  ref.Resize(n);
  accel.Intersect(stream.view(), ref.view());
  std::vector<int32_t> ref_any(n);
  accel.Occluded(stream.view(), ref_any.data());
  HitStream out[2] = {HitStream(n), HitStream(n)};
  std::vector<int32_t> any[2] = {std::vector<int32_t>(n), std::vector<int32_t>(n)};
  TraceStats st[2];
  std::thread threads[2];
  for (int k = 0; k < 2; ++k) {
    out[k].Resize(n);
    threads[k] = std::thread([&, k] {
      for (int rep = 0; rep < 3; ++rep) {
        accel.Intersect(stream.view(), out[k].view(), &st[k]);
        accel.Occluded(stream.view(), any[k].data(), &st[k]);
      }
    });
  }
  for (std::thread& t : threads) t.join();
  for (int k = 0; k < 2; ++k) {
    size_t diff = 0;
    for (size_t i = 0; i < n; ++i) {
      diff += out[k].view().prim[i] != ref.view().prim[i] ||
              !SameBits(out[k].view().t[i], ref.view().t[i]) || any[k][i] != ref_any[i];
    }
    CHECK(diff == 0);
    CHECK(st[k].packets > 0);
  }
}

}  // namespace
}  // namespace rs
