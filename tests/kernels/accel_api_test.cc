// The public entry points of rs::Accel as a tracer calls them: arrays of exactly `size`
// elements at any alignment (each one ending at a guard page, so any read or write past its end
// faults) give the padded, aligned stream's results for every size 0..100 on every target;
// misuse (sizes that differ, null arrays, a moved-from Accel, a bad lambda) is an rs::Error, never
// a crash; lambda is used as given under the default grid kind; Rebuild gives a fresh build's
// Accel from the old one's memory.
#include <doctest/doctest.h>
#include <sys/mman.h>
#include <unistd.h>

#include <cmath>
#include <cstdint>
#include <cstring>
#include <random>
#include <string>
#include <vector>

#include "include/raystream/raystream.h"
#include "streams/block_memory.h"  // SystemBlockCount
#include "streams/ray_stream.h"
#include "tests/test_util.h"

namespace rs {
namespace {

// `n` elements of T ending exactly at a PROT_NONE page, `shift` bytes off the page's alignment
// at the start (so they are unaligned for shift % 64 != 0).
template <class T>
class GuardedArray {
 public:
  GuardedArray(size_t n, size_t shift) {
    const size_t page = static_cast<size_t>(sysconf(_SC_PAGESIZE));
    const size_t bytes = n * sizeof(T) + shift;
    pages_ = (bytes + page - 1) / page + 1;
    base_ = static_cast<char*>(
        mmap(nullptr, pages_ * page, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0));
    REQUIRE(base_ != MAP_FAILED);
    char* guard = base_ + (pages_ - 1) * page;
    REQUIRE(mprotect(guard, page, PROT_NONE) == 0);
    data_ = reinterpret_cast<T*>(guard - n * sizeof(T));
    (void)shift;
  }
  ~GuardedArray() { munmap(base_, pages_ * static_cast<size_t>(sysconf(_SC_PAGESIZE))); }
  GuardedArray(const GuardedArray&) = delete;
  GuardedArray& operator=(const GuardedArray&) = delete;
  T* data() { return data_; }

 private:
  char* base_ = nullptr;
  size_t pages_ = 0;
  T* data_ = nullptr;
};

// A closed box of 12 triangles, [-1, 1]^3, and a floor of 32 triangles below it.
struct Scene {
  std::vector<float> p;
  std::vector<uint32_t> idx;
  MeshView View() const {
    MeshView m;
    m.positions = p.data();
    m.num_vertices = p.size() / 3;
    m.indices = idx.data();
    m.num_triangles = idx.size() / 3;
    return m;
  }
};

Scene Box() {
  Scene s;
  for (int i = 0; i < 8; ++i) {
    s.p.insert(s.p.end(), {i & 1 ? 1.f : -1.f, i & 2 ? 1.f : -1.f, i & 4 ? 1.f : -1.f});
  }
  const uint32_t faces[6][4] = {{0, 1, 3, 2}, {4, 6, 7, 5}, {0, 4, 5, 1},
                                {2, 3, 7, 6}, {0, 2, 6, 4}, {1, 5, 7, 3}};
  for (const auto& f : faces) s.idx.insert(s.idx.end(), {f[0], f[1], f[2], f[0], f[2], f[3]});
  for (int y = 0; y < 4; ++y) {
    for (int x = 0; x < 4; ++x) {
      const uint32_t b = static_cast<uint32_t>(s.p.size() / 3);
      for (int c = 0; c < 4; ++c) {
        s.p.insert(s.p.end(), {-4.f + 2.f * float(x + (c & 1)), -2.f, -4.f + 2.f * float(y + (c >> 1))});
      }
      s.idx.insert(s.idx.end(), {b, b + 1, b + 3, b, b + 3, b + 2});
    }
  }
  return s;
}

struct Rays {
  std::vector<float> f[8];  // ox oy oz dx dy dz tmin tmax
  explicit Rays(size_t n) {
    std::mt19937 rng(static_cast<uint32_t>(n) * 7919u + 1u);
    std::uniform_real_distribution<float> u(-1.f, 1.f);
    for (auto& v : f) v.resize(n);
    for (size_t i = 0; i < n; ++i) {
      // From a ring around the box toward points near it: hits on the box and the floor, misses.
      const float a = 6.2831853f * float(i) / float(n + 1);
      f[0][i] = 5 * std::cos(a), f[1][i] = 0.5f * u(rng), f[2][i] = 5 * std::sin(a);
      f[3][i] = 1.5f * u(rng) - f[0][i], f[4][i] = 1.5f * u(rng) - 1.0f, f[5][i] = 1.5f * u(rng) - f[2][i];
      f[6][i] = 0, f[7][i] = i % 5 == 0 ? 0.5f : INFINITY;
    }
  }
};

TEST_CASE("arrays of exactly `size` elements, unaligned, next to a guard page: padded results") {
  const Scene scene = Box();
  test::ForEachTarget([&](const char* target) {
    for (const bool packets : {true, false}) {
      BuildOptions o;
      o.packets = packets;
      const Accel accel(scene.View(), o);
      for (size_t n = 0; n <= 100; n += (n < 20 ? 1 : 7)) {
        CAPTURE(target);
        CAPTURE(packets);
        CAPTURE(n);
        const Rays r(n);
        // The reference: padded, aligned copies.
        const size_t pn = PaddedSize(n);
        std::vector<std::vector<float>> pad(8);
        RayStreamView want_rays;
        float** fields[8] = {&want_rays.ox, &want_rays.oy, &want_rays.oz, &want_rays.dx,
                             &want_rays.dy, &want_rays.dz, &want_rays.tmin, &want_rays.tmax};
        alignas(64) static float storage[8][128];
        alignas(64) static float wt[128], wu[128], wv[128];
        alignas(64) static int32_t wp[128], wocc[128];
        for (int a = 0; a < 8; ++a) {
          std::fill(storage[a], storage[a] + pn, 0.0f);
          std::copy(r.f[a].begin(), r.f[a].end(), storage[a]);
          *fields[a] = storage[a];
        }
        want_rays.size = n;
        accel.Intersect(want_rays, HitStreamView{wt, wu, wv, wp, n});
        accel.Occluded(want_rays, wocc);
        // The caller's exact arrays, 4 bytes off 64-byte alignment.
        std::vector<std::unique_ptr<GuardedArray<float>>> g;
        RayStreamView rays;
        float** got_fields[8] = {&rays.ox, &rays.oy, &rays.oz, &rays.dx,
                                 &rays.dy, &rays.dz, &rays.tmin, &rays.tmax};
        for (int a = 0; a < 8; ++a) {
          g.push_back(std::make_unique<GuardedArray<float>>(n, 4));
          std::copy(r.f[a].begin(), r.f[a].end(), g.back()->data());
          *got_fields[a] = g.back()->data();
        }
        rays.size = n;
        GuardedArray<float> t(n, 4), u(n, 4), v(n, 4);
        GuardedArray<int32_t> prim(n, 4), occ(n, 4);
        accel.Intersect(rays, HitStreamView{t.data(), u.data(), v.data(), prim.data(), n});
        accel.Occluded(rays, occ.data());
        int hits = 0;
        for (size_t i = 0; i < n; ++i) {
          CHECK(prim.data()[i] == wp[i]);
          CHECK(std::memcmp(&t.data()[i], &wt[i], sizeof(float)) == 0);
          CHECK(std::memcmp(&u.data()[i], &wu[i], sizeof(float)) == 0);
          CHECK(std::memcmp(&v.data()[i], &wv[i], sizeof(float)) == 0);
          CHECK(occ.data()[i] == wocc[i]);
          CHECK(occ.data()[i] == (prim.data()[i] >= 0 ? 1 : 0));
          hits += prim.data()[i] >= 0;
        }
        if (n >= 20) CHECK(hits > 0);
      }
    }
  });
}

TEST_CASE("misuse is an rs::Error naming the problem, never a crash") {
  const Scene scene = Box();
  Accel accel(scene.View());
  alignas(64) float a[16] = {}, b[16] = {}, c[16] = {}, d[16] = {};
  alignas(64) int32_t p[16] = {};
  RayStreamView rays{a, a, a, b, b, b, c, d};
  rays.size = 4;
  auto what = [](auto&& f) {
    try {
      f();
    } catch (const Error& e) {
      return std::string(e.what());
    }
    return std::string();
  };
  CHECK(what([&] { accel.Intersect(rays, HitStreamView{a, b, c, p, 5}); }).find("hits.size 5") !=
        std::string::npos);
  RayStreamView no_tmin = rays;
  no_tmin.tmin = nullptr;
  CHECK(what([&] { accel.Intersect(no_tmin, HitStreamView{a, b, c, p, 4}); }).find("rays.tmin") !=
        std::string::npos);
  CHECK(what([&] { accel.Occluded(no_tmin, p); }).find("rays.tmin") != std::string::npos);
  CHECK(what([&] { accel.Occluded(rays, nullptr); }).find("occluded is null") !=
        std::string::npos);
  CHECK(what([&] { accel.Intersect(rays, HitStreamView{a, b, c, nullptr, 4}); })
            .find("hit array") != std::string::npos);
  // Empty streams need no arrays.
  accel.Intersect(RayStreamView{}, HitStreamView{});
  accel.Occluded(RayStreamView{}, nullptr);
  const Accel moved = std::move(accel);
  CHECK(moved.Info().triangles == 44u);
  CHECK(what([&] { accel.Intersect(rays, HitStreamView{a, b, c, p, 4}); }).find("moved from") !=
        std::string::npos);
  CHECK(what([&] { accel.Occluded(rays, p); }).find("moved from") != std::string::npos);
  CHECK(what([&] { (void)accel.Info(); }).find("moved from") != std::string::npos);
  BuildOptions bad;
  bad.lambda = -1;
  CHECK(what([&] { Accel x(scene.View(), bad); }).find("lambda") != std::string::npos);
  bad.lambda = NAN;
  CHECK(what([&] { Accel x(scene.View(), bad); }).find("lambda") != std::string::npos);
}

// An n x n height field of quads over [-4, 4]^2 near y = -2 (2 n^2 triangles), `phase` moving
// its waves: a mesh large enough for huge-page blocks and refined cells.
Scene Field(int n, float phase) {
  Scene s;
  for (int z = 0; z <= n; ++z) {
    for (int x = 0; x <= n; ++x) {
      const float fx = -4.f + 8.f * float(x) / float(n), fz = -4.f + 8.f * float(z) / float(n);
      s.p.insert(s.p.end(), {fx, -2.f + 0.7f * std::sin(3.f * fx + phase) * std::cos(2.f * fz), fz});
    }
  }
  const auto at = [n](int x, int z) { return static_cast<uint32_t>(z * (n + 1) + x); };
  for (int z = 0; z < n; ++z) {
    for (int x = 0; x < n; ++x) {
      s.idx.insert(s.idx.end(), {at(x, z), at(x + 1, z), at(x + 1, z + 1), at(x, z),
                                 at(x + 1, z + 1), at(x, z + 1)});
    }
  }
  return s;
}

// Everything Info reports but the build time is equal, and the hits of a ray set are bit equal.
void CheckSameAccel(const Accel& got, const Accel& want) {
  const AccelInfo g = got.Info(), w = want.Info();
  CHECK(g.triangles == w.triangles);
  CHECK(g.degenerate_triangles == w.degenerate_triangles);
  for (int a = 0; a < 3; ++a) {
    CHECK(g.bounds_lo[a] == w.bounds_lo[a]);
    CHECK(g.bounds_hi[a] == w.bounds_hi[a]);
    CHECK(g.resolution[a] == w.resolution[a]);
  }
  CHECK(g.cells == w.cells);
  CHECK(g.occupied_cells == w.occupied_cells);
  CHECK(g.references == w.references);
  CHECK(g.max_per_cell == w.max_per_cell);
  CHECK(g.bytes == w.bytes);
  CHECK(std::string(g.kind) == w.kind);
  CHECK(g.irregular_cells == w.irregular_cells);
  CHECK(g.irregular_references == w.irregular_references);
  CHECK(g.lambda == w.lambda);
  CHECK(g.subgrids == w.subgrids);
  CHECK(g.sub_references == w.sub_references);
  CHECK(g.empty_skip == w.empty_skip);
  const size_t n = 2000;
  Rays r(n);
  RayStreamView rays;
  float** fields[8] = {&rays.ox, &rays.oy, &rays.oz, &rays.dx, &rays.dy, &rays.dz, &rays.tmin,
                       &rays.tmax};
  for (int a = 0; a < 8; ++a) *fields[a] = r.f[a].data();
  rays.size = n;
  std::vector<float> t[2], u[2], v[2];
  std::vector<int32_t> prim[2], occ[2];
  const Accel* accels[2] = {&got, &want};
  for (int k = 0; k < 2; ++k) {
    t[k].resize(n), u[k].resize(n), v[k].resize(n), prim[k].resize(n), occ[k].resize(n);
    accels[k]->Intersect(rays, HitStreamView{t[k].data(), u[k].data(), v[k].data(),
                                             prim[k].data(), n});
    accels[k]->Occluded(rays, occ[k].data());
  }
  CHECK(prim[0] == prim[1]);
  CHECK(occ[0] == occ[1]);
  CHECK(std::memcmp(t[0].data(), t[1].data(), n * sizeof(float)) == 0);
  CHECK(std::memcmp(u[0].data(), u[1].data(), n * sizeof(float)) == 0);
  CHECK(std::memcmp(v[0].data(), v[1].data(), n * sizeof(float)) == 0);
}

TEST_CASE("Rebuild: the same Accel as a fresh build, for meshes larger, moved and smaller") {
  const Scene box = Box(), field = Field(120, 0.0f), moved = Field(120, 0.9f),
              small = Field(15, 0.3f);
  for (const GridKind kind :
       {GridKind::kAuto, GridKind::kUniform, GridKind::kTwoLevel, GridKind::kIrregular}) {
    for (const int threads : {1, 2}) {
      CAPTURE(int(kind));
      CAPTURE(threads);
      BuildOptions o;
      o.grid = kind;
      o.build_threads = threads;
      Accel accel(box.View(), o);
      for (const Scene* s : {&field, &moved, &small, &field, &box}) {
        accel.Rebuild(s->View(), o);
        CheckSameAccel(accel, Accel(s->View(), o));
      }
    }
  }
}

TEST_CASE("Rebuild of the same mesh takes every block back from the last one") {
  const Scene field = Field(200, 0.0f);  // 80,000 triangles
  BuildOptions o;
  o.build_threads = 1;  // (threads may take each other's blocks in any order)
  Accel accel(field.View(), o);
  accel.Rebuild(field.View(), o);  // the constructor keeps no temporaries: this one maps them
  const size_t blocks = SystemBlockCount();
  accel.Rebuild(field.View(), o);
  accel.Rebuild(field.View(), o);
  CHECK(SystemBlockCount() == blocks);
  CheckSameAccel(accel, Accel(field.View(), o));
}

TEST_CASE("a Rebuild that throws leaves an Accel that says so until it is rebuilt") {
  const Scene box = Box();
  Scene bad = Field(10, 0.0f);
  bad.p[7] = NAN;
  Accel accel(box.View());
  CHECK_THROWS_WITH_AS(accel.Rebuild(bad.View()), doctest::Contains("non-finite"), Error);
  alignas(64) float a[16] = {}, b[16] = {}, c[16] = {}, d[16] = {};
  alignas(64) int32_t p[16] = {};
  RayStreamView rays{a, a, a, b, b, b, c, d};
  rays.size = 4;
  CHECK_THROWS_WITH_AS(accel.Intersect(rays, HitStreamView{a, b, c, p, 4}),
                       doctest::Contains("last Rebuild failed"), Error);
  CHECK_THROWS_WITH_AS(accel.Occluded(rays, p), doctest::Contains("last Rebuild failed"), Error);
  CHECK_THROWS_WITH_AS((void)accel.Info(), doctest::Contains("last Rebuild failed"), Error);
  const float light[3] = {0, 5, 0};
  CHECK_THROWS_WITH_AS(LightBuffer(accel, light), doctest::Contains("last Rebuild failed"), Error);
  accel.Rebuild(box.View());
  CheckSameAccel(accel, Accel(box.View()));
  // A moved-from Accel can be rebuilt.
  const Accel moved = std::move(accel);
  accel.Rebuild(box.View());
  CheckSameAccel(accel, moved);
}

TEST_CASE("lambda: 0 lets the cost model choose; a positive lambda is used under every kind") {
  const Scene scene = Box();
  for (const GridKind kind :
       {GridKind::kAuto, GridKind::kUniform, GridKind::kTwoLevel, GridKind::kIrregular}) {
    BuildOptions o;
    o.grid = kind;
    o.lambda = 2.5f;
    CHECK(Accel(scene.View(), o).Info().lambda == 2.5f);
    o.lambda = 0;
    const float chosen = Accel(scene.View(), o).Info().lambda;
    if (kind == GridKind::kAuto || kind == GridKind::kIrregular) {
      CHECK(chosen > 0);
    } else {
      CHECK(chosen == 4.0f);
    }
  }
}

// AddressSanitizer aborts on an allocation this large instead of failing it (its default
// allocator_may_return_null=0), so the case runs in the other builds only.
#if defined(__SANITIZE_ADDRESS__)
constexpr bool kAsan = true;
#else
constexpr bool kAsan = false;
#endif

TEST_CASE("an allocation that fails is an rs::Error naming what and how much, not an abort" *
          doctest::skip(kAsan)) {
  try {
    (void)AllocateAlignedOrThrow<float>(size_t{1} << 44, "the test's rays");  // 64 TiB
    FAIL("64 TiB allocated");
  } catch (const Error& e) {
    const std::string what = e.what();
    CHECK(what.find("out of memory: cannot allocate 65536.0 GiB for the test's rays") !=
          std::string::npos);
  }
}

TEST_CASE("version macros and Version() agree") {
  CHECK(std::string(Version()) == RS_VERSION_STRING);
  CHECK(std::string(RS_VERSION_STRING) == std::to_string(RS_VERSION_MAJOR) + "." +
                                              std::to_string(RS_VERSION_MINOR) + "." +
                                              std::to_string(RS_VERSION_PATCH));
}

}  // namespace
}  // namespace rs
