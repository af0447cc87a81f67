// rs::Accel, the public API: mesh validation errors (message content), empty meshes, strided
// positions, Intersect vs Occluded consistency, stats accumulation, Info, padding lanes left
// untouched, moves and concurrent tracing.
#include <doctest/doctest.h>

#include <cmath>
#include <limits>
#include <string>
#include <thread>
#include <vector>

#include "include/raystream/raystream.h"
#include "kernels/accel_impl.h"
#include "kernels/reference.h"
#include "streams/ray_stream.h"
#include "tests/kernels/geometry_util.h"

namespace rs {
namespace {

using test::Rng;
using test::Soup;

constexpr float kInf = std::numeric_limits<float>::infinity();
constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();

std::string BuildError(const MeshView& mesh, const BuildOptions& options = {}) {
  try {
    const Accel accel(mesh, options);
  } catch (const Error& e) {
    return e.what();
  }
  return "";
}

TEST_CASE("validation: index out of range and non-finite vertices name triangle and vertex") {
  Soup s;
  for (int i = 0; i < 40; ++i) s.AddVertex(float(i), float(i % 7), float(i % 3));
  for (uint32_t t = 0; t < 13; ++t) s.indices.insert(s.indices.end(), {t, t + 1, t + 2});
  s.indices[3 * 12 + 1] = 99;
  CHECK(BuildError(s.view()) == "triangle 12: vertex index 99 out of range (40 vertices)");
  s.indices[3 * 12 + 1] = 40;  // one past the end
  CHECK(BuildError(s.view()) == "triangle 12: vertex index 40 out of range (40 vertices)");
  s.indices[3 * 12 + 1] = 13;
  CHECK(BuildError(s.view()).empty());

  // index 4 is first used by triangle 2 = {2, 3, 4}, as its vertex 2
  for (const float bad : {kNaN, kInf, -kInf}) {
    Soup b = s;
    b.positions[3 * 4 + 2] = bad;
    const std::string msg = BuildError(b.view());
    INFO(msg);
    CHECK(msg.find("triangle 2: vertex 2 (index 4) has a non-finite position (4, 4, ") == 0);
    CHECK(msg.find("non-finite") != std::string::npos);
    CHECK(msg.find(bad == kInf ? "inf" : bad == -kInf ? "-inf" : "nan") != std::string::npos);
  }
  // a NaN in a vertex that no triangle uses is fine
  Soup unused = s;
  unused.AddVertex(kNaN, kNaN, kNaN);
  CHECK(BuildError(unused.view()).empty());

  MeshView m = s.view();
  m.stride = 2;
  CHECK(BuildError(m).find("stride 2") != std::string::npos);
  m = s.view();
  m.indices = nullptr;
  CHECK(BuildError(m).find("no index array") != std::string::npos);
  m = s.view();
  m.positions = nullptr;
  CHECK(BuildError(m).find("no position array") != std::string::npos);
  BuildOptions o;
  o.lambda = -1.0f;  // 0 is the cost model's choice (accel_api_test)
  CHECK(BuildError(s.view(), o).find("lambda") != std::string::npos);
  o.lambda = kNaN;
  CHECK(BuildError(s.view(), o).find("lambda") != std::string::npos);
  o = BuildOptions();
  o.max_resolution = 0;
  CHECK(BuildError(s.view(), o).find("max_resolution") != std::string::npos);
}

// Rays and hits with sentinel padding: lanes >= size must be untouched by the kernels.
struct Streams {
  RayStream rays;
  HitStream hits;
  std::vector<int32_t> occluded;
  void Finish() {
    rays.FillPadding();
    hits.Resize(rays.size());
    HitStreamView h = hits.view();
    for (size_t i = 0; i < PaddedSize(rays.size()); ++i) {
      h.t[i] = -7.0f;
      h.u[i] = h.v[i] = -8.0f;
      h.prim[i] = 12345;
    }
    occluded.assign(PaddedSize(rays.size()), 77);
  }
  void CheckPadding() {
    HitStreamView h = hits.view();
    for (size_t i = rays.size(); i < PaddedSize(rays.size()); ++i) {
      CHECK(h.t[i] == -7.0f);
      CHECK(h.prim[i] == 12345);
      CHECK(occluded[i] == 77);
    }
  }
};

void AddRandomRays(Rng& rng, size_t n, Streams* s) {
  for (size_t i = 0; i < n; ++i) {
    float o[3], d[3];
    for (float& x : o) x = rng.UniformF(-1.5, 1.5);
    rng.Direction(d);
    s->rays.Push(o[0], o[1], o[2], d[0], d[1], d[2], 0.0f, kInf, uint32_t(i), 1, 1, 1, 0,
                 RayKind::kPrimary);
  }
  s->Finish();
}

TEST_CASE("empty mesh: builds, never hits, Info is all zero") {
  const Accel accel(MeshView{});
  Streams s;
  Rng rng(1);
  AddRandomRays(rng, 17, &s);
  TraceStats stats;
  accel.Intersect(s.rays.view(), s.hits.view(), &stats);
  accel.Occluded(s.rays.view(), s.occluded.data(), &stats);
  const HitStreamView h = s.hits.view();
  for (size_t i = 0; i < 17; ++i) {
    CHECK(h.prim[i] == -1);
    CHECK(h.t[i] == kInf);
    CHECK(s.occluded[i] == 0);
  }
  s.CheckPadding();
  CHECK(stats.rays == 34);
  CHECK(stats.cell_steps == 0);
  const AccelInfo info = accel.Info();
  CHECK(info.triangles == 0);
  CHECK(info.cells == 0);
  CHECK(info.references == 0);
  CHECK(std::string(info.kind) == "uniform");
  // all-degenerate mesh: same, but the triangles are counted
  Soup deg;
  const float a[3] = {0, 0, 0}, b[3] = {1, 1, 1}, c[3] = {2, 2, 2};
  deg.AddTriangle(a, b, c);
  deg.AddTriangle(a, a, c);
  const Accel accel2(deg.view());
  CHECK(accel2.Info().triangles == 2);
  CHECK(accel2.Info().degenerate_triangles == 2);
  CHECK(accel2.Info().cells == 0);
}

Soup TestSoup(Rng& rng) {
  Soup s = test::RandomSoup(rng, 2000, -1.0, 1.0, 0.12);
  const Soup big = test::RandomSoup(rng, 20, -1.0, 1.0, 0.8);
  const uint32_t base = uint32_t(s.positions.size() / 3);
  s.positions.insert(s.positions.end(), big.positions.begin(), big.positions.end());
  for (const uint32_t i : big.indices) s.indices.push_back(i + base);
  return s;
}

TEST_CASE("stride != 3: interleaved positions give identical hits") {
  Rng rng(2);
  const Soup s = TestSoup(rng);
  // stride 7: xyz, then 4 junk floats (NaN included: never read)
  std::vector<float> interleaved;
  for (size_t v = 0; v < s.positions.size() / 3; ++v) {
    interleaved.insert(interleaved.end(), {s.positions[3 * v], s.positions[3 * v + 1],
                                           s.positions[3 * v + 2], kNaN, 1e30f, -1.0f, kInf});
  }
  MeshView m = s.view();
  m.positions = interleaved.data();
  m.stride = 7;
  const Accel a3(s.view()), a7(m);
  Streams s3, s7;
  AddRandomRays(rng, 2000, &s3);
  for (size_t i = 0; i < 2000; ++i) s7.rays.PushFrom(s3.rays.view(), i);
  s7.Finish();
  a3.Intersect(s3.rays.view(), s3.hits.view());
  a7.Intersect(s7.rays.view(), s7.hits.view());
  const HitStreamView h3 = s3.hits.view(), h7 = s7.hits.view();
  int hits = 0;
  for (size_t i = 0; i < 2000; ++i) {
    CHECK(h3.prim[i] == h7.prim[i]);
    CHECK(h3.t[i] == h7.t[i]);
    hits += h3.prim[i] >= 0;
  }
  CHECK(hits > 150);
  CHECK(a3.Info().references == a7.Info().references);
}

TEST_CASE("Intersect agrees with the double reference; Occluded agrees with Intersect") {
  Rng rng(3);
  const Soup s = TestSoup(rng);
  const Accel accel(s.view());
  Streams st;
  AddRandomRays(rng, 3000, &st);
  TraceStats stats;
  accel.Intersect(st.rays.view(), st.hits.view(), &stats);
  accel.Occluded(st.rays.view(), st.occluded.data(), &stats);
  st.CheckPadding();
  const RayStreamView r = st.rays.view();
  const HitStreamView h = st.hits.view();
  int hits = 0, same = 0;
  for (size_t i = 0; i < 3000; ++i) {
    CHECK(st.occluded[i] == (h.prim[i] >= 0 ? 1 : 0));
    hits += h.prim[i] >= 0;
    const ref::Hit rh = ref::IntersectClosest(
        s.view(), ref::MakeRay(r.ox[i], r.oy[i], r.oz[i], r.dx[i], r.dy[i], r.dz[i], 0.0f, kInf));
    same += rh.prim == h.prim[i];
    if (rh.prim == h.prim[i] && rh.prim >= 0) {
      CHECK(h.t[i] == doctest::Approx(rh.t).epsilon(1e-4));
      CHECK(h.u[i] == doctest::Approx(rh.u).epsilon(1e-3).scale(1.0));
      CHECK(h.v[i] == doctest::Approx(rh.v).epsilon(1e-3).scale(1.0));
    }
  }
  CHECK(hits > 250);
  CHECK(same >= 2997);  // ties and edge decisions are rare (dda_test classifies them)

  // Occluded with tmax just below / at the closest hit: no blocker before it, blocked at it
  Streams before, at;
  for (size_t i = 0; i < 3000; ++i) {
    if (h.prim[i] < 0) continue;
    before.rays.Push(r.ox[i], r.oy[i], r.oz[i], r.dx[i], r.dy[i], r.dz[i], 0.0f,
                     std::nextafter(h.t[i], 0.0f), 0, 1, 1, 1, 1, RayKind::kShadow);
    at.rays.Push(r.ox[i], r.oy[i], r.oz[i], r.dx[i], r.dy[i], r.dz[i], 0.0f, h.t[i], 0, 1, 1, 1,
                 1, RayKind::kShadow);
  }
  before.Finish();
  at.Finish();
  accel.Occluded(before.rays.view(), before.occluded.data());
  accel.Occluded(at.rays.view(), at.occluded.data());
  accel.Intersect(before.rays.view(), before.hits.view());
  int blocked_before = 0, blocked_at = 0;
  for (size_t i = 0; i < before.rays.size(); ++i) {
    blocked_before += before.occluded[i];
    blocked_at += at.occluded[i];
    CHECK(before.hits.view().prim[i] == -1);
  }
  CHECK(blocked_before == 0);
  CHECK(blocked_at == int(at.rays.size()));
  before.CheckPadding();
  at.CheckPadding();
}

TEST_CASE("stats accumulate (never reset) and count steps and tests") {
  Rng rng(4);
  const Soup s = TestSoup(rng);
  const Accel accel(s.view());
  Streams st;
  AddRandomRays(rng, 500, &st);
  TraceStats stats;
  accel.Intersect(st.rays.view(), st.hits.view(), &stats);
  const TraceStats once = stats;
  CHECK(once.rays == 500);
  CHECK(once.cell_steps >= 500 / 2);
  CHECK(once.triangle_tests > 0);
  accel.Intersect(st.rays.view(), st.hits.view(), &stats);
  CHECK(stats.rays == 1000);
  CHECK(stats.cell_steps == 2 * once.cell_steps);
  CHECK(stats.triangle_tests == 2 * once.triangle_tests);
  TraceStats occ;
  accel.Occluded(st.rays.view(), st.occluded.data(), &occ);
  CHECK(occ.rays == 500);
  CHECK(occ.cell_steps <= once.cell_steps);  // any-hit stops at the first hit
  accel.Intersect(st.rays.view(), st.hits.view(), nullptr);  // null stats is allowed
}

TEST_CASE("stream sizes 1, 15, 16, 17 and invalid rays in a stream") {
  Rng rng(5);
  const Soup s = TestSoup(rng);
  const Accel accel(s.view());
  for (const size_t n : {size_t{1}, size_t{15}, size_t{16}, size_t{17}}) {
    Streams st;
    AddRandomRays(rng, n, &st);
    accel.Intersect(st.rays.view(), st.hits.view());
    accel.Occluded(st.rays.view(), st.occluded.data());
    st.CheckPadding();
  }
  Streams st;
  st.rays.Push(kNaN, 0, 0, 1, 0, 0, 0, kInf, 0, 1, 1, 1, 0, RayKind::kPrimary);
  st.rays.Push(0, 0, 0, 0, 0, 0, 0, kInf, 0, 1, 1, 1, 0, RayKind::kPrimary);
  st.rays.Push(0, 0, 0, 1, kInf, 0, 0, kInf, 0, 1, 1, 1, 0, RayKind::kPrimary);
  st.rays.Push(0, 0, 0, 1, 0, 0, kNaN, kInf, 0, 1, 1, 1, 0, RayKind::kPrimary);
  st.rays.Push(0, 0, 0, 1, 0, 0, 0, kNaN, 0, 1, 1, 1, 0, RayKind::kPrimary);
  st.Finish();
  accel.Intersect(st.rays.view(), st.hits.view());
  accel.Occluded(st.rays.view(), st.occluded.data());
  for (size_t i = 0; i < 5; ++i) {
    CHECK(st.hits.view().prim[i] == -1);
    CHECK(st.hits.view().t[i] == kInf);
    CHECK(st.occluded[i] == 0);
  }
}

TEST_CASE("Info, degenerate triangles, moves, concurrent tracing") {
  Rng rng(6);
  Soup s = TestSoup(rng);
  // 3 degenerate triangles, one of them right where rays are aimed
  const float a[3] = {0, 0, 0}, b[3] = {0.5f, 0.5f, 0.5f}, c[3] = {1, 1, 1};
  s.AddTriangle(a, b, c);
  s.AddTriangle(a, a, a);
  s.AddTriangle(b, c, c);
  const Accel built(s.view());
  const AccelInfo info = built.Info();
  CHECK(info.triangles == s.triangles());
  CHECK(info.degenerate_triangles == 3);
  CHECK(info.cells == size_t(info.resolution[0]) * info.resolution[1] * info.resolution[2]);
  CHECK(info.occupied_cells > 0);
  CHECK(info.occupied_cells <= info.cells);
  CHECK(info.references >= info.triangles - 3);
  CHECK(info.max_per_cell > 0);
  CHECK(info.bytes > info.references * 4);
  CHECK(info.build_seconds >= 0.0);
  CHECK(std::string(info.kind) == "uniform");
  for (int k = 0; k < 3; ++k) {
    CHECK(info.bounds_lo[k] < -0.5f);
    CHECK(info.bounds_hi[k] > 0.5f);
    CHECK(info.bounds_lo[k] > -1.01f);  // padded only slightly
    CHECK(info.bounds_hi[k] < 1.01f);
  }
  Accel accel = Accel(s.view());  // move construction
  Accel moved(MeshView{});
  moved = std::move(accel);  // move assignment
  CHECK(AccelImpl(moved).grid.num_refs == info.references);

  // rays through the degenerate segment never report its ids
  Streams st;
  for (int i = 0; i < 200; ++i) {
    const float t = rng.UniformF(0.05, 0.95);
    const float o[3] = {rng.UniformF(-2, 2), rng.UniformF(-2, 2), rng.UniformF(-2, 2)};
    st.rays.Push(o[0], o[1], o[2], t - o[0], t - o[1], t - o[2], 0.0f, kInf, 0, 1, 1, 1, 0,
                 RayKind::kPrimary);
  }
  st.Finish();
  moved.Intersect(st.rays.view(), st.hits.view());
  for (size_t i = 0; i < st.rays.size(); ++i) CHECK(st.hits.view().prim[i] < int32_t(s.triangles() - 3));

  // two threads tracing the same rays with one Accel get identical results
  Streams big, copy;
  AddRandomRays(rng, 4000, &big);
  for (size_t i = 0; i < 4000; ++i) copy.rays.PushFrom(big.rays.view(), i);
  copy.Finish();
  std::thread other([&] { moved.Intersect(copy.rays.view(), copy.hits.view()); });
  moved.Intersect(big.rays.view(), big.hits.view());
  other.join();
  for (size_t i = 0; i < 4000; ++i) {
    CHECK(big.hits.view().prim[i] == copy.hits.view().prim[i]);
    CHECK(big.hits.view().t[i] == copy.hits.view().t[i]);
  }
}

}  // namespace
}  // namespace rs
