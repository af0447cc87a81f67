// Fixed-point framebuffer: the same contributions in any order and from any number of threads
// give identical bits; NaN is dropped, out-of-range values are clamped, conversion is exact.
#include "sched/framebuffer.h"

#include <doctest/doctest.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstring>
#include <limits>
#include <mutex>
#include <random>
#include <thread>
#include <vector>

#include "include/raystream/raystream.h"
#include "streams/ray_stream.h"
#include "tests/test_util.h"

namespace rs {
namespace {

struct Contribution {
  uint32_t pixel;
  float r, g, b;
};

std::vector<Contribution> RandomContributions(size_t n, uint32_t pixels, uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> mag(-12.0f, 3.0f);  // 2^-12 .. 2^3, many scales
  std::uniform_real_distribution<float> unit(0.0f, 1.0f);
  std::vector<Contribution> c(n);
  for (auto& x : c) {
    x.pixel = static_cast<uint32_t>(rng() % pixels);
    x.r = std::exp2(mag(rng)) * unit(rng);
    x.g = std::exp2(mag(rng)) * unit(rng);
    x.b = std::exp2(mag(rng)) * unit(rng);
  }
  return c;
}

bool SameBits(const std::vector<float>& a, const std::vector<float>& b) {
  return a.size() == b.size() && std::memcmp(a.data(), b.data(), a.size() * sizeof(float)) == 0;
}

TEST_CASE("order independence: shuffled contributions from 4 threads give identical bits") {
  const int w = 16, h = 8;
  const auto contribs = RandomContributions(200000, w * h, 42);

  Framebuffer serial(w, h);
  for (const auto& c : contribs) serial.Add(c.pixel, c.r, c.g, c.b);
  const std::vector<float> want = serial.ToRgb();

  // Float summation of the same data is order-dependent: the test data can tell orders apart.
  auto float_sum = [&](const std::vector<Contribution>& cs) {
    std::vector<float> s(static_cast<size_t>(3 * w * h), 0.0f);
    for (const auto& c : cs) {
      s[3 * c.pixel] += c.r;
      s[3 * c.pixel + 1] += c.g;
      s[3 * c.pixel + 2] += c.b;
    }
    return s;
  };
  auto shuffled = contribs;
  std::mt19937 rng(7);
  std::shuffle(shuffled.begin(), shuffled.end(), rng);
  CHECK_FALSE(SameBits(float_sum(contribs), float_sum(shuffled)));

  for (int round = 0; round < 3; ++round) {
    std::shuffle(shuffled.begin(), shuffled.end(), rng);
    Framebuffer fb(w, h);
    std::vector<std::thread> threads;
    const size_t per = shuffled.size() / 4;
    for (size_t t = 0; t < 4; ++t) {
      threads.emplace_back([&, t] {
        const size_t end = t == 3 ? shuffled.size() : (t + 1) * per;
        for (size_t i = t * per; i < end; ++i) {
          fb.Add(shuffled[i].pixel, shuffled[i].r, shuffled[i].g, shuffled[i].b);
        }
      });
    }
    for (auto& th : threads) th.join();
    CHECK(SameBits(fb.ToRgb(), want));
    CHECK(std::memcmp(fb.sums(), serial.sums(), sizeof(int64_t) * 3 * w * h) == 0);
    CHECK(fb.dropped_nan() == 0);
    CHECK(fb.clamped() == 0);
  }

  // Partial framebuffers (e.g. one per MPI rank) merge to the same bits.
  Framebuffer a(w, h), b(w, h);
  for (size_t i = 0; i < shuffled.size(); ++i) {
    (i % 3 == 0 ? a : b).Add(shuffled[i].pixel, shuffled[i].r, shuffled[i].g, shuffled[i].b);
  }
  a.Accumulate(b);
  CHECK(SameBits(a.ToRgb(), want));
  Framebuffer other_size(w + 1, h);
  CHECK_THROWS_AS(a.Accumulate(other_size), Error);
}

TEST_CASE("conversion: exact for dyadic values, 2^-32 resolution") {
  Framebuffer fb(3, 2);
  fb.Add(4, 0.5f, 0.25f, 1.0f);
  fb.Add(4, 0.25f, 0.25f, 2.5f);
  std::vector<float> rgb = fb.ToRgb();
  REQUIRE(rgb.size() == 18);
  CHECK(rgb[12] == 0.75f);
  CHECK(rgb[13] == 0.5f);
  CHECK(rgb[14] == 3.5f);
  for (size_t i = 0; i < rgb.size(); ++i) {
    if (i < 12 || i > 14) CHECK(rgb[i] == 0.0f);
  }
  // 1000 x 1e-3 sums to 1 within the fixed-point resolution (float summation would drift).
  Framebuffer acc(1, 1);
  for (int i = 0; i < 1000; ++i) acc.Add(0, 1e-3f, 1e-6f, 0.0f);
  rgb = acc.ToRgb();
  CHECK(rgb[0] == doctest::Approx(1000.0 * static_cast<double>(1e-3f)).epsilon(1e-7));
  CHECK(rgb[1] == doctest::Approx(1000.0 * static_cast<double>(1e-6f)).epsilon(1e-6));
  bool nan = false, clamped = false;
  CHECK(Framebuffer::ToFixed(1.0f, &nan, &clamped) == (int64_t{1} << 32));
  // The smallest representable step: 2^-32 rounds to 1, 2^-34 rounds to 0.
  CHECK(Framebuffer::ToFixed(std::ldexp(1.0f, -32), &nan, &clamped) == 1);
  CHECK(Framebuffer::ToFixed(std::ldexp(1.0f, -34), &nan, &clamped) == 0);
  CHECK_FALSE(nan);
  CHECK_FALSE(clamped);
}

TEST_CASE("conversion rounds to nearest even, as std::nearbyint: ties, 2^23 boundary, sweep") {
  bool nan = false, clamped = false;
  const auto reference = [](float c) {
    return static_cast<int64_t>(std::nearbyint(c * 4294967296.0f));
  };
  // ties at 2^-33 (0.5 step) and 3 * 2^-33 (1.5 steps): to even
  CHECK(Framebuffer::ToFixed(std::ldexp(1.0f, -33), &nan, &clamped) == 0);
  CHECK(Framebuffer::ToFixed(std::ldexp(3.0f, -33), &nan, &clamped) == 2);
  CHECK(Framebuffer::ToFixed(std::ldexp(5.0f, -33), &nan, &clamped) == 2);
  // around 2^-9 (c * 2^32 = 2^23, where floats become integers)
  for (float c = std::ldexp(1.0f, -9); c > std::ldexp(1.0f, -10);) {
    c = std::nextafter(c, 0.0f);
    CHECK(Framebuffer::ToFixed(c, &nan, &clamped) == reference(c));
    if (reference(c) < (int64_t{1} << 23) - 64) break;
  }
  for (float c = std::ldexp(1.0f, -9), k = 0; k < 64; ++k, c = std::nextafter(c, 1.0f)) {
    CHECK(Framebuffer::ToFixed(c, &nan, &clamped) == reference(c));
  }
  // a log-uniform sweep over [2^-40, 2^8]
  std::mt19937 rng(5);
  std::uniform_real_distribution<float> e(-40.0f, 8.0f);
  size_t bad = 0;
  for (int i = 0; i < 200000; ++i) {
    const float c = std::exp2(e(rng));
    bad += Framebuffer::ToFixed(c, &nan, &clamped) != reference(c) ? 1 : 0;
  }
  CHECK(bad == 0);
  CHECK_FALSE(nan);
  CHECK_FALSE(clamped);
}

TEST_CASE("NaN contributions are dropped and counted; out-of-range ones clamped") {
  const float nan = std::numeric_limits<float>::quiet_NaN();
  const float inf = std::numeric_limits<float>::infinity();
  Framebuffer fb(2, 2);
  fb.Add(1, 0.5f, 0.5f, 0.5f);
  fb.Add(1, nan, 1.0f, 1.0f);  // the whole contribution is dropped
  fb.Add(1, 1.0f, 1.0f, nan);
  CHECK(fb.dropped_nan() == 2);
  CHECK(fb.clamped() == 0);
  std::vector<float> rgb = fb.ToRgb();
  CHECK(rgb[3] == 0.5f);
  CHECK(rgb[4] == 0.5f);
  CHECK(rgb[5] == 0.5f);

  fb.Add(2, 1e9f, -1.0f, inf);
  fb.Add(3, -inf, kMaxContribution, 0.0f);
  CHECK(fb.clamped() == 2);  // counted per contribution, not per channel
  rgb = fb.ToRgb();
  CHECK(rgb[6] == kMaxContribution);
  CHECK(rgb[7] == 0.0f);
  CHECK(rgb[8] == kMaxContribution);
  CHECK(rgb[9] == 0.0f);
  CHECK(rgb[10] == kMaxContribution);

  // 2^19 maximal contributions to one channel still fit in int64 (documented headroom).
  Framebuffer big(1, 1);
  for (int i = 0; i < (1 << 19) - 1; ++i) big.Add(0, kMaxContribution, 0.0f, 0.0f);
  CHECK(big.sums()[0] > 0);
  CHECK(big.ToRgb()[0] == static_cast<float>(kMaxContribution * ((1 << 19) - 1)));

  fb.Clear();
  CHECK(fb.dropped_nan() == 0);
  CHECK(fb.clamped() == 0);
  for (const float x : fb.ToRgb()) CHECK(x == 0.0f);
}

TEST_CASE("Add(ContributionView) == Add per contribution: sums, NaN drops and clamps") {
  const float nan = std::numeric_limits<float>::quiet_NaN();
  const float inf = std::numeric_limits<float>::infinity();
  std::mt19937 rng(12);
  std::uniform_real_distribution<float> unit(0.0f, 2.0f);
  ContributionStream c;
  for (int i = 0; i < 1000; ++i) {
    const uint32_t pixel = static_cast<uint32_t>(rng() % 12);
    float r = unit(rng), g = unit(rng), b = unit(rng);
    if (i % 37 == 0) g = nan;
    if (i % 41 == 0) r = -1.0f;
    if (i % 43 == 0) b = inf;
    c.Push(pixel, r, g, b);
  }
  Framebuffer one(4, 3), all(4, 3);
  const ContributionView v = c.view();
  for (size_t i = 0; i < v.size; ++i) one.Add(v.pixel[i], v.r[i], v.g[i], v.b[i]);
  all.Add(v);
  CHECK(std::memcmp(one.sums(), all.sums(), 12 * 3 * sizeof(int64_t)) == 0);
  CHECK(all.dropped_nan() == one.dropped_nan());
  CHECK(all.dropped_nan() == 28);  // i % 37 == 0 for i < 1000
  CHECK(all.clamped() == one.clamped());
  CHECK(all.clamped() > 0);
  all.Add(ContributionView{});  // empty: nothing
  CHECK(std::memcmp(one.sums(), all.sums(), 12 * 3 * sizeof(int64_t)) == 0);
}

TEST_CASE("ContributionsToFixed == ContributionToFixed lane by lane, on every SIMD target") {
  // Every edge of the conversion in every lane position: NaN in one channel, -0, negatives,
  // infinities, above the clamp, denormals, ties of the rounding, the 2^23 boundary of the float
  // trick, random values; lengths that end mid-vector; with and without a skip mask.
  const float nan = std::numeric_limits<float>::quiet_NaN();
  const float inf = std::numeric_limits<float>::infinity();
  const std::vector<float> edges = {0.0f, -0.0f, -1.0f, nan, inf, -inf, 1e9f, kMaxContribution,
                                    std::nextafter(kMaxContribution, inf),
                                    std::numeric_limits<float>::denorm_min(),
                                    std::ldexp(1.0f, -33), std::ldexp(3.0f, -33),
                                    std::ldexp(5.0f, -33), std::ldexp(1.0f, -9),
                                    std::nextafter(std::ldexp(1.0f, -9), 0.0f), 0.5f, 1.0f};
  std::mt19937 rng(21);
  std::uniform_real_distribution<float> e(-40.0f, 13.0f);
  const size_t n = 1000;
  std::vector<float> ch[3];
  std::vector<int32_t> skip(n);
  for (size_t i = 0; i < n; ++i) {
    for (int c = 0; c < 3; ++c) {
      const uint32_t pick = rng() % 4;
      ch[c].push_back(pick == 0 ? edges[rng() % edges.size()] : std::exp2(e(rng)));
    }
    skip[i] = rng() % 5 == 0 ? static_cast<int32_t>(rng() % 3) - 1 : 0;  // -1, 0 or 1
  }
  test::ForEachTarget([&](const char* target) {
    CAPTURE(target);
    for (const bool masked : {false, true}) {
      for (const size_t len : {size_t{0}, size_t{1}, size_t{7}, size_t{17}, n}) {
        CAPTURE(len);
        std::vector<int64_t> out[3];
        for (auto& o : out) o.assign(len, -7);
        uint64_t nans = 3, clamps = 5;  // added to, not reset
        ContributionsToFixed(ch[0].data(), ch[1].data(), ch[2].data(),
                             masked ? skip.data() : nullptr, len, out[0].data(), out[1].data(),
                             out[2].data(), &nans, &clamps);
        uint64_t want_nans = 3, want_clamps = 5;
        size_t bad = 0;
        for (size_t i = 0; i < len; ++i) {
          int64_t f[3] = {0, 0, 0};
          if (!masked || skip[i] == 0) {
            bool clamped = false;
            if (ContributionToFixed(ch[0][i], ch[1][i], ch[2][i], f, &clamped)) {
              want_clamps += clamped ? 1 : 0;
            } else {
              f[0] = f[1] = f[2] = 0;
              ++want_nans;
            }
          }
          for (int c = 0; c < 3; ++c) bad += out[c][i] != f[c] ? 1 : 0;
        }
        CHECK(bad == 0);
        CHECK(nans == want_nans);
        CHECK(clamps == want_clamps);
        if (len == n) {
          CHECK(want_nans > 3);
          CHECK(want_clamps > 5);
        }
      }
    }
  });
}

TEST_CASE("Add with a skip mask == Add of the unskipped contributions") {
  std::mt19937 rng(4);
  std::uniform_real_distribution<float> unit(0.0f, 3.0f);
  const size_t n = 777;
  std::vector<uint32_t> pixel(n);
  std::vector<float> r(n), g(n), b(n);
  std::vector<int32_t> skip(n);
  for (size_t i = 0; i < n; ++i) {
    pixel[i] = static_cast<uint32_t>(rng() % 10);
    r[i] = unit(rng);
    g[i] = i % 50 == 0 ? std::numeric_limits<float>::quiet_NaN() : unit(rng);
    b[i] = i % 30 == 0 ? 5000.0f : unit(rng);
    skip[i] = rng() % 3 == 0 ? 1 : 0;
  }
  Framebuffer one(5, 2), all(5, 2);
  for (size_t i = 0; i < n; ++i) {
    if (skip[i] == 0) one.Add(pixel[i], r[i], g[i], b[i]);
  }
  all.Add(pixel.data(), r.data(), g.data(), b.data(), skip.data(), n);
  CHECK(std::memcmp(one.sums(), all.sums(), 10 * 3 * sizeof(int64_t)) == 0);
  CHECK(all.dropped_nan() == one.dropped_nan());
  CHECK(all.clamped() == one.clamped());
  CHECK(one.dropped_nan() > 0);
  CHECK(one.clamped() > 0);
}

// Contributions with NaN, negative, infinite, huge and zero channels and skip flags, as arrays.
struct ContributionArrays {
  std::vector<uint32_t> pixel;
  std::vector<float> r, g, b;
  std::vector<int32_t> skip;
};
ContributionArrays HostileContributions(size_t n, uint32_t pixels, uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> unit(0.0f, 2.0f);
  ContributionArrays c;
  for (size_t i = 0; i < n; ++i) {
    c.pixel.push_back(static_cast<uint32_t>(rng() % pixels));
    float r = unit(rng), g = unit(rng), b = unit(rng);
    if (i % 37 == 0) g = std::numeric_limits<float>::quiet_NaN();
    if (i % 41 == 0) r = -1.0f;
    if (i % 43 == 0) b = std::numeric_limits<float>::infinity();
    if (i % 47 == 0) r = 1e30f;
    if (i % 11 == 0) r = g = b = 0.0f;  // black: nothing to add
    c.r.push_back(r);
    c.g.push_back(g);
    c.b.push_back(b);
    c.skip.push_back(rng() % 5 == 0 ? 1 : 0);
  }
  return c;
}

TEST_CASE("PixelSumTable: the sums and counters of Framebuffer::Add, across flushes") {
  // 30,000 pixels: far more than a table holds, so it flushes when half full many times; a
  // small image: many contributions per pixel meet in the table.
  for (const int w : {200, 7}) {
    const int h = w == 200 ? 150 : 3;
    INFO("image ", w, "x", h);
    const uint32_t pixels = uint32_t(w * h);
    const ContributionArrays c = HostileContributions(100000, pixels, 21);
    Framebuffer direct(w, h), combined(w, h);
    std::mutex lock;
    PixelSumTable table;
    // in calls of varying size (the engine's calls), some over the 256-contribution block
    for (size_t i = 0, k = 1; i < c.pixel.size(); i += k, k = k * 7 % 601 + 1) {
      const size_t n = std::min(k, c.pixel.size() - i);
      direct.Add(c.pixel.data() + i, c.r.data() + i, c.g.data() + i, c.b.data() + i,
                 c.skip.data() + i, n);
      table.Add(combined, lock, c.pixel.data() + i, c.r.data() + i, c.g.data() + i,
                c.b.data() + i, c.skip.data() + i, n);
      CHECK(table.size() < PixelSumTable::kSlots / 2);  // the lock is free: flushed at half
    }
    table.Flush(combined, lock);
    CHECK(table.size() == 0);
    CHECK(std::memcmp(direct.sums(), combined.sums(), size_t(pixels) * 3 * sizeof(int64_t)) == 0);
    CHECK(combined.dropped_nan() == direct.dropped_nan());
    CHECK(combined.clamped() == direct.clamped());
    CHECK(direct.dropped_nan() > 0);
    CHECK(direct.clamped() > 0);
    // Clear drops what is held: nothing more arrives
    table.Add(combined, lock, c.pixel.data(), c.r.data(), c.g.data(), c.b.data(), nullptr, 100);
    table.Clear();
    table.Flush(combined, lock);
    CHECK(std::memcmp(direct.sums(), combined.sums(), size_t(pixels) * 3 * sizeof(int64_t)) == 0);
    CHECK(combined.dropped_nan() == direct.dropped_nan());
  }
}

TEST_CASE("PixelSumTable: runs of neighbouring pixels, as a renderer's tiles send them") {
  // Slots are buckets of 8 neighbouring pixels: 32x32 tiles of a 1024-wide image, each tile's
  // pixels five times over (a light after another), rows 1024 apart and tiles 32 apart.
  const int w = 1024, h = 128;
  std::vector<uint32_t> pixel;
  for (int ty = 0; ty < h; ty += 32) {
    for (int tx = 0; tx < w; tx += 32) {
      for (int light = 0; light < 5; ++light) {
        for (int y = ty; y < ty + 32; ++y) {
          for (int x = tx; x < tx + 32; ++x) pixel.push_back(uint32_t(y * w + x));
        }
      }
    }
  }
  std::vector<float> r(pixel.size()), g(pixel.size()), b(pixel.size());
  for (size_t i = 0; i < pixel.size(); ++i) {
    r[i] = 0.001f * float(i % 977);
    g[i] = 0.5f;
    b[i] = float(i % 3);
  }
  Framebuffer direct(w, h), combined(w, h);
  direct.Add(pixel.data(), r.data(), g.data(), b.data(), nullptr, pixel.size());
  std::mutex lock;
  PixelSumTable table;
  for (size_t i = 0; i < pixel.size(); i += 1000) {
    const size_t n = std::min<size_t>(1000, pixel.size() - i);
    table.Add(combined, lock, &pixel[i], &r[i], &g[i], &b[i], nullptr, n);
  }
  table.Flush(combined, lock);
  CHECK(std::memcmp(direct.sums(), combined.sums(), size_t(w * h) * 3 * sizeof(int64_t)) == 0);
}

TEST_CASE("PixelSumTable: a busy lock delays the flush to 7/8 full, same sums") {
  const int w = 100, h = 100;
  const ContributionArrays c = HostileContributions(20000, uint32_t(w * h), 9);
  Framebuffer direct(w, h), combined(w, h);
  direct.Add(c.pixel.data(), c.r.data(), c.g.data(), c.b.data(), c.skip.data(), c.pixel.size());
  std::mutex lock;
  PixelSumTable table;
  size_t most = 0;
  // another thread holds the lock while the table fills
  std::atomic<bool> held{false}, release{false};
  std::thread holder([&] {
    const std::lock_guard<std::mutex> hold(lock);
    held.store(true);
    while (!release.load()) std::this_thread::yield();
  });
  while (!held.load()) std::this_thread::yield();
  size_t i = 0;
  for (; i < c.pixel.size() && table.size() + 1 < PixelSumTable::kSlots / 8 * 7; ++i) {
    table.Add(combined, lock, &c.pixel[i], &c.r[i], &c.g[i], &c.b[i], &c.skip[i], 1);
    most = std::max(most, table.size());
  }
  CHECK(most > PixelSumTable::kSlots / 2);  // kept filling past half
  release.store(true);
  holder.join();
  table.Add(combined, lock, c.pixel.data() + i, c.r.data() + i, c.g.data() + i, c.b.data() + i,
            c.skip.data() + i, c.pixel.size() - i);
  table.Flush(combined, lock);
  CHECK(std::memcmp(direct.sums(), combined.sums(), size_t(w * h) * 3 * sizeof(int64_t)) == 0);
  CHECK(combined.dropped_nan() == direct.dropped_nan());
  CHECK(combined.clamped() == direct.clamped());
}

TEST_CASE("PixelSumTable: 4 threads, one table each and one lock, give the serial bits") {
  const int w = 64, h = 48;
  const uint32_t pixels = uint32_t(w * h);
  const ContributionArrays c = HostileContributions(80000, pixels, 5);
  Framebuffer serial(w, h), shared(w, h);
  serial.Add(c.pixel.data(), c.r.data(), c.g.data(), c.b.data(), c.skip.data(), c.pixel.size());
  std::mutex lock;
  std::vector<std::thread> threads;
  const size_t part = c.pixel.size() / 4;
  for (size_t t = 0; t < 4; ++t) {
    threads.emplace_back([&, t] {
      PixelSumTable table;
      for (size_t i = t * part; i < (t + 1) * part; i += 100) {
        table.Add(shared, lock, c.pixel.data() + i, c.r.data() + i, c.g.data() + i,
                  c.b.data() + i, c.skip.data() + i, std::min<size_t>(100, (t + 1) * part - i));
      }
      table.Flush(shared, lock);
    });
  }
  for (auto& t : threads) t.join();
  CHECK(std::memcmp(serial.sums(), shared.sums(), size_t(pixels) * 3 * sizeof(int64_t)) == 0);
  CHECK(shared.dropped_nan() == serial.dropped_nan());
  CHECK(shared.clamped() == serial.clamped());
}

TEST_CASE("size checks and moves") {
  CHECK_THROWS_AS(Framebuffer(0, 5), Error);
  CHECK_THROWS_AS(Framebuffer(5, -1), Error);
  CHECK_THROWS_AS(Framebuffer(70000, 70000), Error);
  Framebuffer a(4, 3);
  a.Add(11, 1.0f, 2.0f, 3.0f);
  Framebuffer b(std::move(a));
  CHECK(b.width() == 4);
  CHECK(b.height() == 3);
  CHECK(b.ToRgb()[35] == 3.0f);
}

}  // namespace
}  // namespace rs
