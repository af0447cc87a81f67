// SoA ray streams: push/grow/padding invariants, range copies and the tail seal, and stable
// compaction (sizes 0, 1, N; padding refilled; optional arrays absent); contribution streams:
// push, growth, no reallocation once reserved.
#include "streams/ray_stream.h"

#include <doctest/doctest.h>

#include <cmath>
#include <cstdint>
#include <random>
#include <vector>

#include "streams/compact.h"

namespace rs {
namespace {

// Ray i gets values derived from `id` so its identity survives moves.
void PushTagged(RayStream& s, int id) {
  const float f = static_cast<float>(id);
  s.Push(f, f + 0.25f, f + 0.5f, -f, 1.0f, 2.0f, 0.125f * f, 1000.0f + f,
         static_cast<uint32_t>(7 * id + 1), 0.5f * f, 0.25f * f, 0.125f * f, id % 5,
         static_cast<RayKind>(id % kNumRayKinds));
}

void CheckTagged(const RayStreamView& v, size_t i, int id) {
  INFO("lane ", i, " expected ray ", id);
  const float f = static_cast<float>(id);
  CHECK(v.ox[i] == f);
  CHECK(v.oy[i] == f + 0.25f);
  CHECK(v.oz[i] == f + 0.5f);
  CHECK(v.dx[i] == -f);
  CHECK(v.dy[i] == 1.0f);
  CHECK(v.dz[i] == 2.0f);
  CHECK(v.tmin[i] == 0.125f * f);
  CHECK(v.tmax[i] == 1000.0f + f);
  CHECK(v.pixel[i] == static_cast<uint32_t>(7 * id + 1));
  CHECK(v.wr[i] == 0.5f * f);
  CHECK(v.wg[i] == 0.25f * f);
  CHECK(v.wb[i] == 0.125f * f);
  CHECK(v.depth[i] == id % 5);
  CHECK(v.kind[i] == id % kNumRayKinds);
}

void CheckPadding(RayStream& s) {
  const RayStreamView v = s.view();
  CHECK(s.capacity() % kStreamPad == 0);
  CHECK(s.capacity() >= PaddedSize(s.size()));
  for (size_t i = s.size(); i < s.capacity(); ++i) {
    INFO("padding lane ", i);
    CHECK(std::isnan(v.ox[i]));
    CHECK(std::isnan(v.dx[i]));
    CHECK(v.tmax[i] < v.tmin[i]);
    CHECK(v.wr[i] == 0.0f);
  }
}

TEST_CASE("RayStream: push, growth keeps contents, alignment, padding sentinel") {
  RayStream s;
  CHECK(s.empty());
  for (int i = 0; i < 100; ++i) PushTagged(s, i);
  REQUIRE(s.size() == 100);
  const RayStreamView v = s.view();
  CHECK(reinterpret_cast<uintptr_t>(v.ox) % kStreamAlign == 0);
  CHECK(reinterpret_cast<uintptr_t>(v.kind) % kStreamAlign == 0);
  for (int i = 0; i < 100; ++i) CheckTagged(v, static_cast<size_t>(i), i);
  s.FillPadding();
  CheckPadding(s);

  RayStream copy;
  for (int i = 0; i < 100; i += 3) copy.PushFrom(v, static_cast<size_t>(i));
  const RayStreamView cv = copy.view();
  for (size_t j = 0; j < copy.size(); ++j) CheckTagged(cv, j, static_cast<int>(3 * j));
}

TEST_CASE("RayStream::Append and CopyRays copy ranges array by array; SealTail") {
  RayStream s;
  for (int i = 0; i < 100; ++i) PushTagged(s, i);
  const RayStreamView v = s.view();
  for (const size_t n : {size_t{0}, size_t{1}, size_t{15}, size_t{17}, size_t{60}}) {
    INFO("n ", n);
    RayStream to;
    PushTagged(to, 500);
    to.Append(v, 33, n);  // after an existing ray, from an unaligned start
    REQUIRE(to.size() == 1 + n);
    const RayStreamView tv = to.view();
    CheckTagged(tv, 0, 500);
    for (size_t j = 0; j < n; ++j) CheckTagged(tv, 1 + j, static_cast<int>(33 + j));
    // SealTail: the next kStreamPad lanes (inside the capacity) become padding rays, the lanes
    // after them are left alone.
    RayStream big;
    big.Reserve(200);
    for (int i = 0; i < 150; ++i) PushTagged(big, i);
    big.Resize(n);
    big.SealTail();
    const RayStreamView bv = big.view();
    for (size_t i = n; i < n + kStreamPad; ++i) {
      INFO("sealed lane ", i);
      CHECK(std::isnan(bv.ox[i]));
      CHECK(bv.tmax[i] < bv.tmin[i]);
      CHECK(bv.wr[i] == 0.0f);
    }
    CheckTagged(bv, n + kStreamPad, static_cast<int>(n + kStreamPad));
  }
  // A view without the optional arrays: the same defaults as CopyRay (pixel 0, weight 1,
  // depth 0, primary).
  RayStreamView bare = v;
  bare.pixel = nullptr;
  bare.wr = bare.wg = bare.wb = nullptr;
  bare.depth = bare.kind = nullptr;
  RayStream to;
  to.Append(bare, 7, 3);
  const RayStreamView tv = to.view();
  for (size_t j = 0; j < 3; ++j) {
    CHECK(tv.ox[j] == static_cast<float>(7 + j));
    CHECK(tv.pixel[j] == 0u);
    CHECK(tv.wr[j] == 1.0f);
    CHECK(tv.wb[j] == 1.0f);
    CHECK(tv.depth[j] == 0);
    CHECK(tv.kind[j] == static_cast<int32_t>(RayKind::kPrimary));
  }
}

TEST_CASE("SoaArrays: one allocation, arrays back to back and aligned, growth keeps contents") {
  SoaArrays<3> a;
  CHECK(a.capacity() == 0);
  a.Reserve(5, "test arrays");
  const size_t cap = a.capacity();
  REQUIRE(cap >= 5);
  CHECK(cap % kStreamPad == 0);
  for (size_t k = 0; k < 3; ++k) {
    CHECK(reinterpret_cast<uintptr_t>(a.array<float>(k)) % 64 == 0);
    if (k > 0) CHECK(a.array<float>(k) == a.array<float>(k - 1) + cap);
    for (size_t i = 0; i < cap; ++i) CHECK(a.array<uint32_t>(k)[i] == 0u);  // zeroed
    for (size_t i = 0; i < cap; ++i) a.array<int32_t>(k)[i] = static_cast<int32_t>(100 * k + i);
  }
  const float* before = a.array<float>(0);
  a.Reserve(cap, "test arrays");  // no growth: same block
  CHECK(a.array<float>(0) == before);
  a.Reserve(3 * cap + 1, "test arrays");
  REQUIRE(a.capacity() >= 3 * cap + 1);
  for (size_t k = 0; k < 3; ++k) {
    size_t kept = 0, zero = 0;
    for (size_t i = 0; i < cap; ++i) kept += a.array<int32_t>(k)[i] == int32_t(100 * k + i);
    for (size_t i = cap; i < a.capacity(); ++i) zero += a.array<int32_t>(k)[i] == 0;
    CHECK(kept == cap);
    CHECK(zero == a.capacity() - cap);
  }
  // Moved: the block goes along, the source is empty.
  const float* block = a.array<float>(0);
  SoaArrays<3> b(std::move(a));
  CHECK(b.array<float>(0) == block);
  CHECK(a.capacity() == 0);
  // A RayStream's 14 arrays are one such block; its view follows growth and moves.
  RayStream s(20);
  RayStreamView v = s.view();
  CHECK(v.oy == v.ox + s.capacity());
  CHECK(reinterpret_cast<const void*>(v.kind) ==
        reinterpret_cast<const void*>(v.ox + 13 * s.capacity()));
  s.Resize(5);
  v.ox[4] = 42.0f;
  s.Reserve(1000);
  v = s.view();
  CHECK(v.size == 5);
  CHECK(v.ox[4] == 42.0f);
  CHECK(v.kind == reinterpret_cast<int32_t*>(v.ox + 13 * s.capacity()));
  RayStream t(std::move(s));
  CHECK(t.view().ox == v.ox);
  CHECK(t.view().size == 5);
}

TEST_CASE("SealRays: every array of the lanes gets the never-hit sentinel") {
  RayStream s;
  for (int i = 0; i < 40; ++i) PushTagged(s, i + 1);
  const RayStreamView v = s.view();
  SealRays(v, 7, 23);
  for (size_t i = 0; i < 40; ++i) {
    const bool sealed = i >= 7 && i < 23;
    CHECK(std::isnan(v.ox[i]) == sealed);
    CHECK(std::isnan(v.dz[i]) == sealed);
    if (sealed) {
      CHECK(v.tmin[i] > v.tmax[i]);
      CHECK(v.pixel[i] == 0u);
      CHECK(v.wr[i] == 0.0f);
      CHECK(v.wb[i] == 0.0f);
      CHECK(v.depth[i] == 0);
      CHECK(v.kind[i] == 0);
    }
  }
  SealRays(v, 5, 5);  // empty range: nothing written
  CHECK(!std::isnan(v.ox[5]));
}

TEST_CASE("ContributionStream: push, growth keeps contents, alignment, reserve, clear") {
  ContributionStream s;
  CHECK(s.empty());
  CHECK(s.view().size == 0);
  for (int i = 0; i < 100; ++i) {
    const float f = static_cast<float>(i);
    s.Push(static_cast<uint32_t>(3 * i), f, -f, 0.5f * f);
  }
  REQUIRE(s.size() == 100);
  CHECK(s.capacity() % kStreamPad == 0);
  CHECK(s.capacity() >= PaddedSize(s.size()));
  const ContributionView v = s.view();
  CHECK(v.size == 100);
  CHECK(reinterpret_cast<uintptr_t>(v.pixel) % kStreamAlign == 0);
  CHECK(reinterpret_cast<uintptr_t>(v.r) % kStreamAlign == 0);
  CHECK(reinterpret_cast<uintptr_t>(v.g) % kStreamAlign == 0);
  CHECK(reinterpret_cast<uintptr_t>(v.b) % kStreamAlign == 0);
  for (int i = 0; i < 100; ++i) {
    const float f = static_cast<float>(i);
    CHECK(v.pixel[i] == static_cast<uint32_t>(3 * i));
    CHECK(v.r[i] == f);
    CHECK(v.g[i] == -f);
    CHECK(v.b[i] == 0.5f * f);
  }
  // Reserved: no reallocation until the capacity is used up, Clear keeps the capacity, and a
  // Resize within it keeps the arrays too.
  ContributionStream r(1000);
  const size_t capacity = r.capacity();
  CHECK(capacity >= 1000);
  const uint32_t* pixel = r.pixel_data();
  const float* red = r.r_data();
  for (int round = 0; round < 3; ++round) {
    r.Clear();
    CHECK(r.empty());
    for (size_t i = 0; i < capacity; ++i) r.Push(static_cast<uint32_t>(i), 1.0f, 2.0f, 3.0f);
    CHECK(r.pixel_data() == pixel);
    CHECK(r.r_data() == red);
    CHECK(r.capacity() == capacity);
  }
  r.Resize(10);
  CHECK(r.pixel_data() == pixel);
  CHECK(r.view().pixel[9] == 9u);
  // One more than the capacity grows (at least doubling) and keeps the contents.
  r.Resize(capacity);
  r.Push(7, 4.0f, 5.0f, 6.0f);
  CHECK(r.capacity() >= 2 * capacity);
  CHECK(r.size() == capacity + 1);
  CHECK(r.view().pixel[capacity - 1] == static_cast<uint32_t>(capacity - 1));
  CHECK(r.view().b[capacity] == 6.0f);
}

TEST_CASE("CompactRays: sizes 0 and 1") {
  RayStream s;
  const int32_t none[1] = {0};
  CHECK(CompactRays(s, none) == 0);
  CHECK(s.size() == 0);
  CheckPadding(s);

  PushTagged(s, 9);
  const int32_t keep[1] = {5};  // any nonzero keeps
  CHECK(CompactRays(s, keep) == 1);
  CheckTagged(s.view(), 0, 9);
  CheckPadding(s);
  CHECK(CompactRays(s, none) == 0);
  CHECK(s.size() == 0);
  CheckPadding(s);  // the old ray 0 is now a padding lane
}

TEST_CASE("CompactRays: stable, random flags, sizes around the padding width") {
  std::mt19937 rng(1234);
  for (const int n : {2, 15, 16, 17, 31, 33, 100, 257}) {
    for (const int density : {0, 10, 50, 90, 100}) {
      INFO("n ", n, " keep % ", density);
      RayStream s;
      for (int i = 0; i < n; ++i) PushTagged(s, i);
      std::vector<int32_t> keep(static_cast<size_t>(n));
      std::vector<int> want;
      for (int i = 0; i < n; ++i) {
        keep[static_cast<size_t>(i)] =
            static_cast<int>(rng() % 100) < density ? static_cast<int32_t>(rng() % 7 + 1) : 0;
        if (keep[static_cast<size_t>(i)] != 0) want.push_back(i);
      }
      const size_t got = CompactRays(s, keep.data());
      REQUIRE(got == want.size());
      REQUIRE(s.size() == want.size());
      const RayStreamView v = s.view();
      for (size_t j = 0; j < want.size(); ++j) CheckTagged(v, j, want[j]);
      CheckPadding(s);
    }
  }
}

TEST_CASE("CompactRays on a view: optional arrays may be null, size untouched") {
  RayStream s;
  for (int i = 0; i < 20; ++i) PushTagged(s, i);
  RayStreamView v = s.view();
  v.pixel = nullptr;
  v.wr = v.wg = v.wb = nullptr;
  v.depth = nullptr;
  v.kind = nullptr;
  std::vector<int32_t> keep(20, 0);
  keep[3] = keep[4] = keep[19] = 1;
  CHECK(CompactRays(v, keep.data()) == 3);
  CHECK(v.size == 20);
  CHECK(s.size() == 20);
  const RayStreamView full = s.view();
  CHECK(full.ox[0] == 3.0f);
  CHECK(full.ox[1] == 4.0f);
  CHECK(full.ox[2] == 19.0f);
  CHECK(full.tmax[2] == 1019.0f);
  // The untouched optional arrays still hold the original order.
  CHECK(full.pixel[0] == 1u);
  CHECK(full.pixel[2] == 15u);
}

}  // namespace
}  // namespace rs
