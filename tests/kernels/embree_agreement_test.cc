// raystream (rs::Accel) against Embree 3 in robust mode on the shared and procedural scenes:
// the same closest triangle and occlusion answer for >= 99.999 % of rays up to exact/near ties,
// and no disagreement in which raystream contradicts the double reference (rs::ref) beyond float
// rounding. Prints the counts. Also tests the Embree peer itself on a hand-made quad.
#include <doctest/doctest.h>

#include <cmath>
#include <cstdio>
#include <limits>
#include <memory>
#include <string>
#include <vector>

#include "bench/peer/embree_peer.h"
#include "bench/peer/ray_sets.h"
#include "include/raystream/raystream.h"
#include "kernels/reference.h"
#include "scenes/load.h"
#include "streams/ray_stream.h"
#include "tests/test_util.h"

namespace rs {
namespace {

using bench::Coherence;
using bench::EmbreeMode;
using bench::EmbreePeer;

constexpr float kInf = std::numeric_limits<float>::infinity();
constexpr double kTieRel = 1e-5;  // "near tie": t within 1e-5 relative (rs::ref)
constexpr double kMinSameFraction = 0.99999;
constexpr uint64_t kRandomSeed = 0x0e3b7ee5eedull;

// ---------------------------------------------------------------------------------------------
// The peer on a hand-made scene: a unit quad (2 triangles) in the plane z = 0.

struct QuadMesh {
  std::vector<float> positions = {0, 0, 0, 1, 0, 0, 1, 1, 0, 0, 1, 0};
  std::vector<uint32_t> indices = {0, 1, 2, 0, 2, 3};
  MeshView view() const {
    MeshView m;
    m.positions = positions.data();
    m.num_vertices = 4;
    m.stride = 3;
    m.indices = indices.data();
    m.num_triangles = 2;
    return m;
  }
};

// n rays down the z axis from z = 5 at x, y in a row: ray i hits the quad iff x < 1,
// triangle 0 (below the diagonal y = x) iff y < x.
RayStream QuadRays(size_t n) {
  RayStream rays;
  for (size_t i = 0; i < n; ++i) {
    const float x = 0.05f + 0.1f * static_cast<float>(i % 20);  // 10 of 20 columns hit
    const float y = (i % 3 == 0) ? 0.02f : 0.9f;
    rays.Push(x, y, 5.0f, 0.0f, 0.0f, -1.0f, 0.0f, kInf, static_cast<uint32_t>(i), 1, 1, 1, 0,
              RayKind::kPrimary);
  }
  rays.FillPadding();
  return rays;
}

TEST_CASE("EmbreePeer: quad, every mode, sizes around the packet and chunk widths") {
  const QuadMesh quad;
  const EmbreePeer peer(quad.view());
  CHECK(peer.num_triangles() == 2);
  CHECK(peer.build_seconds() >= 0.0);
  for (const size_t n : {size_t{1}, size_t{15}, size_t{16}, size_t{17}, size_t{255}, size_t{256},
                         size_t{257}, size_t{600}}) {
    RayStream rays = QuadRays(n);
    for (int m = 0; m < bench::kNumEmbreeModes; ++m) {
      const auto mode = static_cast<EmbreeMode>(m);
      INFO("n = ", n, ", mode = ", bench::EmbreeModeName(mode));
      HitStream hits(n + 1);  // room for the sentinel at [n]
      hits.Resize(n);
      hits.Reset();
      // A sentinel past the end must survive (the peer writes [0, n) only).
      hits.view().prim[n] = 12345;
      peer.Intersect(mode, rays.view(), hits.view(), Coherence::kCoherent);
      AlignedArray<int32_t> occluded(n + 1);
      occluded[n] = 777;
      peer.Occluded(mode, rays.view(), occluded.data(), Coherence::kIncoherent);
      size_t wrong = 0;
      for (size_t i = 0; i < n; ++i) {
        const RayStreamView r = rays.view();
        const bool inside = r.ox[i] < 1.0f;
        const int32_t want = !inside ? -1 : (r.oy[i] < r.ox[i] ? 0 : 1);
        const HitStreamView h = hits.view();
        if (h.prim[i] != want || occluded[i] != (inside ? 1 : 0)) ++wrong;
        if (inside && std::fabs(h.t[i] - 5.0f) > 1e-6f) ++wrong;
        if (inside) {
          // hit point from barycentrics matches the ray's (x, y)
          const uint32_t* tri = quad.indices.data() + 3 * want;
          const float* p0 = quad.positions.data() + 3 * tri[0];
          const float* p1 = quad.positions.data() + 3 * tri[1];
          const float* p2 = quad.positions.data() + 3 * tri[2];
          const float w = 1.0f - h.u[i] - h.v[i];
          const float x = w * p0[0] + h.u[i] * p1[0] + h.v[i] * p2[0];
          const float y = w * p0[1] + h.u[i] * p1[1] + h.v[i] * p2[1];
          if (std::fabs(x - r.ox[i]) > 1e-5f || std::fabs(y - r.oy[i]) > 1e-5f) ++wrong;
        } else if (!std::isinf(h.t[i]) || h.u[i] != 0.0f || h.v[i] != 0.0f) {
          ++wrong;
        }
      }
      CHECK(wrong == 0);
      CHECK(hits.view().prim[n] == 12345);
      CHECK(occluded[n] == 777);
    }
  }
}

TEST_CASE("EmbreePeer: tmin/tmax bound the hit, rebuild replaces the scene, empty mesh") {
  QuadMesh quad;
  EmbreePeer peer(quad.view());
  const float o[3] = {0.7f, 0.2f, 5.0f};
  const float d[3] = {0.0f, 0.0f, -1.0f};
  float t, u, v;
  int32_t prim;
  peer.Intersect1(o, d, 0.0f, kInf, t, u, v, prim);
  CHECK(prim == 0);
  CHECK(t == doctest::Approx(5.0f).epsilon(1e-6));
  peer.Intersect1(o, d, 0.0f, 4.99f, t, u, v, prim);  // segment ends before the quad
  CHECK(prim == -1);
  CHECK(std::isinf(t));
  peer.Intersect1(o, d, 5.01f, kInf, t, u, v, prim);  // starts behind it
  CHECK(prim == -1);

  // Rebuild with the quad moved to z = 2: the new scene answers.
  for (size_t i = 2; i < quad.positions.size(); i += 3) quad.positions[i] = 2.0f;
  peer.Build(quad.view());
  peer.Intersect1(o, d, 0.0f, kInf, t, u, v, prim);
  CHECK(prim == 0);
  CHECK(t == doctest::Approx(3.0f).epsilon(1e-6));

  peer.Build(MeshView{});
  CHECK(peer.num_triangles() == 0);
  peer.Intersect1(o, d, 0.0f, kInf, t, u, v, prim);
  CHECK(prim == -1);
}

// ---------------------------------------------------------------------------------------------
// Agreement on real scenes.

struct ClosestTally {
  size_t n = 0;
  size_t hits_ours = 0;
  size_t hits_embree = 0;
  size_t same = 0;          // same triangle (or both miss)
  size_t ties = 0;          // different triangles, both hit by rs::ref with t within kTieRel
  size_t ambiguous = 0;     // the answer flips within float rounding (edge or grazing hit)
  size_t embree_wrong = 0;  // ours is right or ambiguous, Embree's answer is not
  size_t ours_wrong = 0;    // ours contradicts the double reference beyond rounding
  size_t t_off = 0;         // same triangle, t differs by more than 1e-4 relative
  double max_t_rel = 0;
  std::vector<std::string> examples;  // literal rays where ours is wrong
};

struct OccludedTally {
  size_t n = 0;
  size_t occluded_ours = 0;
  size_t occluded_embree = 0;
  size_t same = 0;
  size_t ambiguous = 0;
  size_t embree_wrong = 0;
  size_t ours_wrong = 0;
  std::vector<std::string> examples;
};

std::string RayLiteral(const RayStreamView& r, size_t i) {
  char buf[256];
  std::snprintf(buf, sizeof(buf), "o (%a, %a, %a) d (%a, %a, %a) t [%a, %a]", r.ox[i], r.oy[i],
                r.oz[i], r.dx[i], r.dy[i], r.dz[i], r.tmin[i], r.tmax[i]);
  return buf;
}

bool NearTie(double a, double b) {
  return std::isfinite(a) && std::isfinite(b) &&
         std::fabs(a - b) <= kTieRel * std::max(std::fabs(a), std::fabs(b));
}

// The double watertight test of rs::ref (same shear, double inputs) with a margin: each 2D
// edge function is turned into the signed distance of the ray from that projected edge and
// compared with +-delta. loose: within delta outside the triangle or inside; tight: more than
// delta inside. delta = 2^-20 (16 float ulps) of the largest |coordinate| of the origin and
// the vertices: the rounding of the float test's first step (p - o) and shear. A hit that is
// loose but not tight may be found or missed by any float tracer.
struct MarginHit {
  bool loose = false;
  bool tight = false;
  double t = std::numeric_limits<double>::infinity();  // plane distance (units of |d|)
  double delta_t = 0;  // delta in units of t along the ray (for tmin/tmax comparisons)
};

MarginHit MarginTest(const ref::Ray& ray, const double p[3][3]) {
  MarginHit h;
  if (!ray.valid) return h;
  double m = 0;
  for (int k = 0; k < 3; ++k) {
    m = std::max(m, std::fabs(ray.o[k]));
    for (int j = 0; j < 3; ++j) m = std::max(m, std::fabs(p[j][k]));
  }
  const double delta = std::ldexp(m, -20);
  const int kx = ray.kx, ky = ray.ky, kz = ray.kz;
  double x[3], y[3], z[3];
  for (int j = 0; j < 3; ++j) {
    z[j] = p[j][kz] - ray.o[kz];
    x[j] = (p[j][kx] - ray.o[kx]) - ray.sx * z[j];
    y[j] = (p[j][ky] - ray.o[ky]) - ray.sy * z[j];
  }
  // e[j]: edge function of the edge opposite vertex j (rs::ref's u, v, w)
  const double e[3] = {x[2] * y[1] - y[2] * x[1], x[0] * y[2] - y[0] * x[2],
                       x[1] * y[0] - y[1] * x[0]};
  const double det = e[0] + e[1] + e[2];
  if (det == 0.0) return h;
  const double sign = det > 0.0 ? 1.0 : -1.0;
  h.loose = h.tight = true;
  for (int j = 0; j < 3; ++j) {
    const int a = (j + 1) % 3, b = (j + 2) % 3;
    const double len = std::hypot(x[b] - x[a], y[b] - y[a]);
    const double dist = len > 0.0 ? sign * e[j] / len : 0.0;
    h.loose = h.loose && dist >= -delta;
    h.tight = h.tight && dist > delta;
  }
  h.t = (e[0] * z[0] + e[1] * z[1] + e[2] * z[2]) * ray.sz / det;
  const double dlen = std::sqrt(ray.d[0] * ray.d[0] + ray.d[1] * ray.d[1] + ray.d[2] * ray.d[2]);
  h.delta_t = delta / dlen;
  return h;
}

// The double-precision reference, built on first need (only disagreements consult it).
class Reference {
 public:
  explicit Reference(const MeshView& mesh) : mesh_(mesh) {}
  const ref::ChunkedMesh& chunked() {
    if (!chunked_) chunked_ = std::make_unique<ref::ChunkedMesh>(mesh_);
    return *chunked_;
  }
  // t of `prim` along the ray by the double watertight test, +inf if it misses (or prim < 0).
  double TriangleT(const ref::Ray& ray, int32_t prim) const {
    if (prim < 0) return std::numeric_limits<double>::infinity();
    double p[3][3];
    ref::TriangleVertices(mesh_, static_cast<size_t>(prim), p);
    ref::Hit hit;
    if (!ref::IntersectTriangle(ray, p[0], p[1], p[2], ray.tmax, &hit)) {
      return std::numeric_limits<double>::infinity();
    }
    return hit.t;
  }
  MarginHit Margin(const ref::Ray& ray, int32_t prim) const {
    double p[3][3];
    ref::TriangleVertices(mesh_, static_cast<size_t>(prim), p);
    return MarginTest(ray, p);
  }
  // The exact hit `hit` stays a hit under any rounding: tight, and t clear of tmin and tmax.
  bool Robust(const ref::Ray& ray, const ref::Hit& hit) const {
    if (hit.prim < 0) return false;
    const MarginHit m = Margin(ray, hit.prim);
    const double slack = m.delta_t + kTieRel * hit.t;
    return m.tight && hit.t > ray.tmin + slack && hit.t < ray.tmax - slack;
  }
  // A float tracer may report `prim`: within rounding of the triangle, t within [tmin, tmax].
  bool Plausible(const ref::Ray& ray, int32_t prim, double* t) const {
    const MarginHit m = Margin(ray, prim);
    const double slack = m.delta_t + kTieRel * std::fabs(m.t);
    *t = m.t;
    return m.loose && m.t >= ray.tmin - slack && m.t <= ray.tmax + slack;
  }

 private:
  MeshView mesh_;
  std::unique_ptr<ref::ChunkedMesh> chunked_;
};

ref::Ray RefRay(const RayStreamView& r, size_t i) {
  return ref::MakeRay(r.ox[i], r.oy[i], r.oz[i], r.dx[i], r.dy[i], r.dz[i], r.tmin[i], r.tmax[i]);
}

enum class Verdict { kRight, kTie, kAmbiguous, kWrong };

// Judges one tracer's closest hit `prim` against the exact closest hit `truth`.
Verdict JudgeClosest(const Reference& reference, const ref::Ray& ray, const ref::Hit& truth,
                     int32_t prim) {
  if (prim == truth.prim) return Verdict::kRight;
  const bool truth_robust = reference.Robust(ray, truth);
  if (prim < 0) return truth_robust ? Verdict::kWrong : Verdict::kAmbiguous;
  double t = 0;
  if (!reference.Plausible(ray, prim, &t)) return Verdict::kWrong;
  if (truth.prim < 0) return Verdict::kAmbiguous;  // grazes prim; exactly, nothing is hit
  if (NearTie(reference.TriangleT(ray, prim), truth.t)) return Verdict::kTie;
  // prim is hit within rounding; wrong only if a robust hit lies clearly before it.
  if (t <= truth.t * (1.0 + kTieRel)) return Verdict::kAmbiguous;
  return truth_robust ? Verdict::kWrong : Verdict::kAmbiguous;
}

ClosestTally CompareClosest(Reference& reference, const RayStreamView& rays,
                            const HitStreamView& ours, const HitStreamView& embree) {
  ClosestTally c;
  c.n = rays.size;
  for (size_t i = 0; i < rays.size; ++i) {
    const int32_t a = ours.prim[i];
    const int32_t b = embree.prim[i];
    c.hits_ours += a >= 0 ? 1 : 0;
    c.hits_embree += b >= 0 ? 1 : 0;
    if (a == b) {
      ++c.same;
      if (a >= 0) {
        const double rel = std::fabs(static_cast<double>(ours.t[i]) - embree.t[i]) /
                           std::max(1e-30, static_cast<double>(std::fabs(embree.t[i])));
        c.max_t_rel = std::max(c.max_t_rel, rel);
        c.t_off += rel > 1e-4 ? 1 : 0;
      }
      continue;
    }
    const ref::Ray ray = RefRay(rays, i);
    // Fast path: both triangles are hit exactly at (nearly) the same distance.
    if (a >= 0 && b >= 0 && NearTie(reference.TriangleT(ray, a), reference.TriangleT(ray, b))) {
      ++c.ties;
      continue;
    }
    const ref::Hit truth = reference.chunked().IntersectClosest(ray);
    const Verdict va = JudgeClosest(reference, ray, truth, a);
    const Verdict vb = JudgeClosest(reference, ray, truth, b);
    if (va == Verdict::kWrong) {
      ++c.ours_wrong;
      if (c.examples.size() < 5) {
        c.examples.push_back(RayLiteral(rays, i) + ": raystream " + std::to_string(a) +
                             ", embree " + std::to_string(b) + ", ref " +
                             std::to_string(truth.prim));
      }
    } else if (vb == Verdict::kWrong) {
      ++c.embree_wrong;
    } else if (va == Verdict::kTie || vb == Verdict::kTie) {
      ++c.ties;
    } else {
      ++c.ambiguous;
    }
  }
  return c;
}

// Judges one tracer's occlusion answer against the exact any-hit answer; `blocker` is the
// tracer's closest hit for the ray (used when it claims occlusion that the reference denies).
Verdict JudgeOccluded(Reference& reference, const ref::Ray& ray, bool truth, bool occluded,
                      int32_t blocker) {
  if (occluded == truth) return Verdict::kRight;
  if (occluded) {
    double t = 0;
    return blocker >= 0 && reference.Plausible(ray, blocker, &t) ? Verdict::kAmbiguous
                                                                 : Verdict::kWrong;
  }
  return reference.Robust(ray, reference.chunked().IntersectClosest(ray)) ? Verdict::kWrong
                                                                          : Verdict::kAmbiguous;
}

OccludedTally CompareOccluded(Reference& reference, const Accel& accel, const EmbreePeer& embree,
                              const RayStreamView& rays, const int32_t* ours,
                              const int32_t* theirs) {
  OccludedTally c;
  c.n = rays.size;
  RayStream one;
  HitStream one_hit(1);
  one_hit.Resize(1);
  for (size_t i = 0; i < rays.size; ++i) {
    const bool a = ours[i] != 0;
    const bool b = theirs[i] != 0;
    c.occluded_ours += a ? 1 : 0;
    c.occluded_embree += b ? 1 : 0;
    if (a == b) {
      ++c.same;
      continue;
    }
    const ref::Ray ray = RefRay(rays, i);
    const bool truth = reference.chunked().IntersectAny(ray);
    // Each tracer's own closest hit on the same segment names the triangle it saw.
    one.Clear();
    one.PushFrom(rays, i);
    one.FillPadding();
    one_hit.Reset();
    accel.Intersect(one.view(), one_hit.view());
    const int32_t ours_blocker = one_hit.view().prim[0];
    float t, u, v;
    int32_t embree_blocker;
    const float o[3] = {rays.ox[i], rays.oy[i], rays.oz[i]};
    const float d[3] = {rays.dx[i], rays.dy[i], rays.dz[i]};
    embree.Intersect1(o, d, rays.tmin[i], rays.tmax[i], t, u, v, embree_blocker);
    const Verdict va = JudgeOccluded(reference, ray, truth, a, ours_blocker);
    const Verdict vb = JudgeOccluded(reference, ray, truth, b, embree_blocker);
    if (va == Verdict::kWrong) {
      ++c.ours_wrong;
      if (c.examples.size() < 5) {
        c.examples.push_back(RayLiteral(rays, i) + ": raystream " + std::to_string(a) +
                             ", embree " + std::to_string(b) + ", ref " + std::to_string(truth));
      }
    } else if (vb == Verdict::kWrong) {
      ++c.embree_wrong;
    } else {
      ++c.ambiguous;
    }
  }
  return c;
}

double Fraction(size_t part, size_t n) {
  return n ? static_cast<double>(part) / static_cast<double>(n) : 1.0;
}

// The agreement criteria. Literal same-triangle agreement cannot reach 99.999 % on scenes with
// coplanar overlapping triangles (office-graz, erw6's boxes on the floor): those rays are exact
// ties that each tracer breaks its own way. So the 99.999 % bound applies to rays on which the
// two agree or disagree only by an exact/near tie or within float rounding; raystream must
// never contradict the double reference beyond rounding; Embree may, rarely (ANCHORS.md: it is
// not fully watertight), and more than 1e-4 of the rays would mean a broken harness.
void CheckClosest(const std::string& what, const ClosestTally& c) {
  MESSAGE(what, ": ", c.n, " rays, hits raystream ", c.hits_ours, " / embree ", c.hits_embree,
          ", same triangle ", c.same, " (", 100.0 * Fraction(c.same, c.n), " %), ties ", c.ties,
          ", within rounding ", c.ambiguous, ", embree wrong ", c.embree_wrong,
          ", raystream wrong ", c.ours_wrong, ", same-triangle t max rel diff ", c.max_t_rel, " (",
          c.t_off, " > 1e-4)");
  for (const std::string& e : c.examples) MESSAGE("  raystream wrong: ", e);
  INFO(what);
  CHECK(c.ours_wrong == 0);
  CHECK(Fraction(c.same + c.ties + c.ambiguous, c.n) >= kMinSameFraction);
  CHECK(Fraction(c.embree_wrong, c.n) <= 1e-4);
  // Same triangle, different t: grazing hits and hits at tiny t (spawned rays) amplify the
  // float rounding of t; more than 1e-3 of the rays would mean a broken t.
  CHECK(Fraction(c.t_off, c.n) <= 1e-3);
}

void CheckOccluded(const std::string& what, const OccludedTally& c) {
  MESSAGE(what, ": ", c.n, " rays, occluded raystream ", c.occluded_ours, " / embree ",
          c.occluded_embree, ", same ", c.same, " (", 100.0 * Fraction(c.same, c.n),
          " %), within rounding ", c.ambiguous, ", embree wrong ", c.embree_wrong,
          ", raystream wrong ", c.ours_wrong);
  for (const std::string& e : c.examples) MESSAGE("  raystream wrong: ", e);
  INFO(what);
  CHECK(c.ours_wrong == 0);
  CHECK(Fraction(c.same + c.ambiguous, c.n) >= kMinSameFraction);
  CHECK(Fraction(c.embree_wrong, c.n) <= 1e-4);
}

void CheckScene(const std::string& name) {
  const Scene scene = LoadScene(name);
  const MeshView mesh = scene.mesh();
  const Accel accel(mesh);
  const EmbreePeer embree(mesh);
  Reference reference(mesh);

  bench::RaySets sets = bench::MakeRaySets(scene, embree, 256, 256);
  RayStream random;
  bench::MakeRandomRays(scene, 100000, kRandomSeed, random);
  // The primary set must see the scene (else the test would be vacuous).
  CHECK(sets.primary_hit_count > sets.primary.size() / 20);

  struct Closest {
    const char* what;
    RayStream* rays;
    Coherence hint;
  };
  for (const Closest& set : {Closest{"primary 256x256", &sets.primary, Coherence::kCoherent},
                             Closest{"random 100k", &random, Coherence::kIncoherent},
                             Closest{"diffuse", &sets.diffuse, Coherence::kIncoherent}}) {
    const RayStreamView rays = set.rays->view();
    HitStream ours(rays.size), theirs(rays.size);
    ours.Resize(rays.size);
    theirs.Resize(rays.size);
    ours.Reset();
    theirs.Reset();
    accel.Intersect(rays, ours.view());
    embree.Intersect(EmbreeMode::k1, rays, theirs.view(), set.hint);
    CheckClosest(name + " " + set.what + " closest",
                 CompareClosest(reference, rays, ours.view(), theirs.view()));
    // Embree's packet and stream forms give Embree's single-ray answers.
    for (const EmbreeMode mode : {EmbreeMode::k16, EmbreeMode::kStream}) {
      HitStream other(rays.size);
      other.Resize(rays.size);
      other.Reset();
      embree.Intersect(mode, rays, other.view(), set.hint);
      size_t same = 0, ties = 0;
      for (size_t i = 0; i < rays.size; ++i) {
        const int32_t a = other.view().prim[i], b = theirs.view().prim[i];
        if (a == b) {
          ++same;
        } else if (a >= 0 && b >= 0) {
          const ref::Ray ray = RefRay(rays, i);
          ties += NearTie(reference.TriangleT(ray, a), reference.TriangleT(ray, b)) ? 1 : 0;
        }
      }
      INFO(name, " ", set.what, " ", bench::EmbreeModeName(mode), " vs embree1: same ", same,
           ", ties ", ties);
      CHECK(Fraction(same + ties, rays.size) >= kMinSameFraction);
    }
  }

  for (const Closest& set : {Closest{"shadow", &sets.shadow, Coherence::kCoherent},
                             Closest{"random 100k", &random, Coherence::kIncoherent}}) {
    const RayStreamView rays = set.rays->view();
    AlignedArray<int32_t> ours(rays.size), theirs(rays.size);
    accel.Occluded(rays, ours.data());
    embree.Occluded(EmbreeMode::k1, rays, theirs.data(), set.hint);
    CheckOccluded(name + " " + set.what + " occluded",
                  CompareOccluded(reference, accel, embree, rays, ours.data(), theirs.data()));
  }
}

// Procedural scenes need no files.
TEST_CASE("raystream vs Embree robust: spherebox") { CheckScene("spherebox"); }
TEST_CASE("raystream vs Embree robust: erw6") { CheckScene("erw6"); }

// Shared scenes: skipped locally when missing, a failure under CI=true.
TEST_CASE("raystream vs Embree robust: bunny") {
  if (test::HaveSharedScene("bunny/bun_zipper.ply")) CheckScene("bunny");
}
TEST_CASE("raystream vs Embree robust: teapot") {
  if (test::HaveSharedScene("teapot/teapot.obj")) CheckScene("teapot");
}
TEST_CASE("raystream vs Embree robust: sponza") {
  if (test::HaveSharedScene("sponza/sponza.obj")) CheckScene("sponza");
}
TEST_CASE("raystream vs Embree robust: office-graz") {
  if (test::HaveSharedScene("office-graz/office-graz.obj")) CheckScene("office-graz");
}
TEST_CASE("raystream vs Embree robust: conference") {
  if (test::HaveSharedScene("conference/conference.obj")) CheckScene("conference");
}
TEST_CASE("raystream vs Embree robust: sibenik") {
  if (test::HaveSharedScene("sibenik/sibenik.obj")) CheckScene("sibenik");
}

}  // namespace
}  // namespace rs
