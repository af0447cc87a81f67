// rs::TraceScene (several geometries, instances, masks, updates) over one rs::Accel per geometry, and
// the owning trace-only streams rs::RayBuffer / rs::HitBuffer. Scalar code compiled once (not per
// Highway target), so the top level is the same on every target.
#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <new>
#include <optional>
#include <string>
#include <vector>

#include "include/raystream/raystream.h"

namespace rs {
namespace {

constexpr float kInf = std::numeric_limits<float>::infinity();

// One allocation of `arrays` 4-byte arrays of PaddedSize(n) elements each, 64-B aligned.
void* AllocateArrays(size_t n, size_t arrays) {
  if (n > (std::numeric_limits<size_t>::max() / 4 - kStreamPad) / (4 * arrays)) {
    throw Error("stream buffer: " + std::to_string(n) + " elements are too many");
  }
  return ::operator new(arrays * PaddedSize(n) * 4, std::align_val_t{kStreamAlign});
}
void FreeArrays(void* p) {
  if (p != nullptr) ::operator delete(p, std::align_val_t{kStreamAlign});
}

}  // namespace

// ---- RayBuffer / HitBuffer ---------------------------------------------------------------------

RayBuffer::RayBuffer(size_t size) { Resize(size); }
RayBuffer::~RayBuffer() { FreeArrays(storage_); }
RayBuffer::RayBuffer(RayBuffer&& o) noexcept { *this = std::move(o); }
RayBuffer& RayBuffer::operator=(RayBuffer&& o) noexcept {
  if (this == &o) return *this;
  FreeArrays(storage_);
  storage_ = o.storage_, mask_ = o.mask_, id_ = o.id_, size_ = o.size_;
  std::copy(o.f_, o.f_ + 8, f_);
  o.storage_ = nullptr, o.mask_ = nullptr, o.id_ = nullptr, o.size_ = 0;
  std::fill(o.f_, o.f_ + 8, nullptr);
  return *this;
}

void RayBuffer::Resize(size_t size) {
  void* storage = AllocateArrays(size, 10);
  FreeArrays(storage_);
  storage_ = storage;
  const size_t n = PaddedSize(size);
  float* base = static_cast<float*>(storage);
  for (int a = 0; a < 8; ++a) {
    f_[a] = base + a * n;
    std::fill(f_[a], f_[a] + n, a == 7 ? kInf : 0.0f);
  }
  mask_ = reinterpret_cast<uint32_t*>(base + 8 * n);
  id_ = reinterpret_cast<uint32_t*>(base + 9 * n);
  std::fill(mask_, mask_ + n, ~0u);
  for (size_t i = 0; i < n; ++i) id_[i] = static_cast<uint32_t>(i);
  size_ = size;
}

RayView RayBuffer::View() const {
  return RayView{f_[0], f_[1], f_[2], f_[3], f_[4], f_[5], f_[6], f_[7], mask_, id_, size_};
}

HitBuffer::HitBuffer(size_t size) { Resize(size); }
HitBuffer::~HitBuffer() { FreeArrays(storage_); }
HitBuffer::HitBuffer(HitBuffer&& o) noexcept { *this = std::move(o); }
HitBuffer& HitBuffer::operator=(HitBuffer&& o) noexcept {
  if (this == &o) return *this;
  FreeArrays(storage_);
  storage_ = o.storage_, size_ = o.size_;
  std::copy(o.f_, o.f_ + 6, f_);
  std::copy(o.i_, o.i_ + 3, i_);
  o.storage_ = nullptr, o.size_ = 0;
  std::fill(o.f_, o.f_ + 6, nullptr);
  std::fill(o.i_, o.i_ + 3, nullptr);
  return *this;
}

void HitBuffer::Resize(size_t size) {
  void* storage = AllocateArrays(size, 9);
  FreeArrays(storage_);
  storage_ = storage;
  const size_t n = PaddedSize(size);
  float* base = static_cast<float*>(storage);
  for (int a = 0; a < 6; ++a) {
    f_[a] = base + a * n;
    std::fill(f_[a], f_[a] + n, a == 0 ? kInf : 0.0f);
  }
  for (int a = 0; a < 3; ++a) {
    i_[a] = reinterpret_cast<int32_t*>(base + (6 + a) * n);
    std::fill(i_[a], i_[a] + n, -1);
  }
  size_ = size;
}

HitView HitBuffer::View() {
  return HitView{f_[0], f_[1], f_[2], f_[3], f_[4], f_[5], i_[0], i_[1], i_[2], size_};
}

// ---- Scene -------------------------------------------------------------------------------------

namespace {

struct Geometry {
  BufferMode mode = BufferMode::kCopy;
  std::vector<float> copy;            // kCopy: packed xyz
  const float* positions = nullptr;   // copy.data() or the caller's buffer
  size_t stride = 3;                  // floats
  size_t num_vertices = 0;
  std::vector<uint32_t> indices;      // always 32-bit, packed
  uint32_t mask = ~0u;
  bool instance_only = false;
  bool dirty = true;                  // Accel to (re)build at Commit
  std::optional<Accel> accel;
  double lo[3] = {0, 0, 0}, hi[3] = {0, 0, 0};  // referenced vertices, padded; lo > hi: empty

  const float* Vertex(uint32_t i) const { return positions + size_t{i} * stride; }
  size_t num_triangles() const { return indices.size() / 3; }
};

struct Instance {
  uint32_t geom = 0;
  float m[12] = {};    // object to world, row-major 3x4
  float inv[12] = {};  // world to object
  uint32_t mask = ~0u;
};

std::string Str(size_t x) { return std::to_string(x); }

void CheckStride(const char* what, const void* positions, size_t stride_bytes) {
  if (stride_bytes < 12 || stride_bytes % 4 != 0) {
    throw Error(std::string(what) + ": position stride " + Str(stride_bytes) +
                " bytes is not a multiple of 4 of at least 12");
  }
  if (reinterpret_cast<uintptr_t>(positions) % 4 != 0) {
    throw Error(std::string(what) + ": positions are not 4-byte aligned");
  }
}

// Sets the geometry's positions from the caller's buffer (copied or kept).
void SetPositions(const char* what, Geometry* g, const void* positions, size_t stride_bytes) {
  if (positions == nullptr && g->num_vertices > 0) {
    throw Error(std::string(what) + ": " + Str(g->num_vertices) + " vertices but no positions");
  }
  CheckStride(what, positions, stride_bytes);
  const size_t stride = stride_bytes / 4;
  const float* p = static_cast<const float*>(positions);
  if (g->mode == BufferMode::kShared) {
    g->copy.clear();
    g->positions = p;
    g->stride = stride;
  } else {
    std::vector<float> copy(3 * g->num_vertices);
    for (size_t i = 0; i < g->num_vertices; ++i) {
      std::memcpy(&copy[3 * i], p + i * stride, 3 * sizeof(float));
    }
    g->copy.swap(copy);
    g->positions = g->copy.data();
    g->stride = 3;
  }
  g->dirty = true;
}

Geometry MakeGeometry(const char* what, const GeometryDesc& d) {
  if (d.mode != BufferMode::kCopy && d.mode != BufferMode::kShared) {
    throw Error(std::string(what) + ": unknown buffer mode " + Str(size_t(d.mode)));
  }
  if (d.index_type != IndexType::kUInt32 && d.index_type != IndexType::kUInt16) {
    throw Error(std::string(what) + ": unknown index type " + Str(size_t(d.index_type)));
  }
  if (d.num_triangles > size_t{std::numeric_limits<int32_t>::max()}) {
    throw Error(std::string(what) + ": " + Str(d.num_triangles) +
                " triangles exceed the limit of 2^31 - 1 (hit ids are int32)");
  }
  if (d.num_vertices > size_t{std::numeric_limits<uint32_t>::max()}) {
    throw Error(std::string(what) + ": " + Str(d.num_vertices) + " vertices exceed 2^32 - 1");
  }
  if (d.indices == nullptr && d.num_triangles > 0) {
    throw Error(std::string(what) + ": " + Str(d.num_triangles) + " triangles but no indices");
  }
  Geometry g;
  g.mode = d.mode;
  g.num_vertices = d.num_vertices;
  g.mask = d.mask;
  g.instance_only = d.instance_only;
  g.indices.resize(3 * d.num_triangles);
  for (size_t i = 0; i < g.indices.size(); ++i) {
    g.indices[i] = d.index_type == IndexType::kUInt32
                       ? static_cast<const uint32_t*>(d.indices)[i]
                       : static_cast<const uint16_t*>(d.indices)[i];
    if (g.indices[i] >= d.num_vertices) {
      throw Error(std::string(what) + ": triangle " + Str(i / 3) + ": vertex index " +
                  Str(g.indices[i]) + " out of range (" + Str(d.num_vertices) + " vertices)");
    }
  }
  SetPositions(what, &g, d.positions, d.stride_bytes);
  return g;
}

// Bounds of the referenced vertices (exact, in double), padded by 2^-16 of their magnitude so
// that the box test in double never rejects a ray the float kernels hit.
void ComputeBounds(Geometry* g) {
  for (int a = 0; a < 3; ++a) g->lo[a] = INFINITY, g->hi[a] = -INFINITY;
  for (const uint32_t i : g->indices) {
    const float* p = g->Vertex(i);
    for (int a = 0; a < 3; ++a) {
      g->lo[a] = std::min(g->lo[a], double{p[a]});
      g->hi[a] = std::max(g->hi[a], double{p[a]});
    }
  }
  if (g->indices.empty()) return;
  double mag = 0;
  for (int a = 0; a < 3; ++a) mag = std::max({mag, std::fabs(g->lo[a]), std::fabs(g->hi[a])});
  const double pad = mag * 0x1p-16 + 1e-30;
  for (int a = 0; a < 3; ++a) g->lo[a] -= pad, g->hi[a] += pad;
}

// Inverse of a 3x4 affine transform (in double, rounded to float); throws for NaN/Inf entries
// or a singular (or numerically singular) 3x3 part.
void InvertTransform(const char* what, const float* m, float* inv) {
  if (m == nullptr) throw Error(std::string(what) + ": transform is null");
  for (int i = 0; i < 12; ++i) {
    if (!std::isfinite(m[i])) {
      throw Error(std::string(what) + ": transform element " + Str(size_t(i)) + " is not finite");
    }
  }
  const double a = m[0], b = m[1], c = m[2], d = m[4], e = m[5], f = m[6], g = m[8], h = m[9],
               k = m[10];
  const double c00 = e * k - f * h, c01 = f * g - d * k, c02 = d * h - e * g;
  const double det = a * c00 + b * c01 + c * c02;
  double scale = 0;
  for (const double x : {a, b, c, d, e, f, g, h, k}) scale = std::max(scale, std::fabs(x));
  if (!(std::fabs(det) > 1e-12 * scale * scale * scale) || !std::isfinite(1.0 / det)) {
    throw Error(std::string(what) + ": transform is singular (determinant " +
                std::to_string(det) + ")");
  }
  const double r[9] = {c00 / det, (c * h - b * k) / det, (b * f - c * e) / det,
                       c01 / det, (a * k - c * g) / det, (c * d - a * f) / det,
                       c02 / det, (b * g - a * h) / det, (a * e - b * d) / det};
  for (int row = 0; row < 3; ++row) {
    double t = 0;
    for (int col = 0; col < 3; ++col) {
      inv[4 * row + col] = static_cast<float>(r[3 * row + col]);
      t -= r[3 * row + col] * double{m[4 * col + 3]};
    }
    inv[4 * row + 3] = static_cast<float>(t);
  }
  for (int i = 0; i < 12; ++i) {
    if (!std::isfinite(inv[i])) throw Error(std::string(what) + ": inverse is not finite");
  }
}

// Slab test in double against a padded box: may the ray hit inside the box with t in
// (tnear, tfar]? (Conservative: the interval ends are widened by 2^-16.)
bool MayHit(const double lo[3], const double hi[3], const float o[3], const float d[3],
            float tnear, float tfar) {
  if (!(lo[0] <= hi[0])) return false;  // empty geometry
  double t0 = -INFINITY, t1 = INFINITY;
  for (int a = 0; a < 3; ++a) {
    if (d[a] == 0.0f) {
      if (!(o[a] >= lo[a] && o[a] <= hi[a])) return false;
      continue;
    }
    const double inv = 1.0 / double{d[a]};
    double ta = (lo[a] - o[a]) * inv, tb = (hi[a] - o[a]) * inv;
    if (ta > tb) std::swap(ta, tb);
    t0 = std::max(t0, ta), t1 = std::min(t1, tb);
  }
  const double slack = 0x1p-16;
  return t0 <= t1 && t1 >= double{tnear} - slack * std::fabs(double{tnear}) &&
         t0 <= double{tfar} + slack * std::fabs(double{tfar});
}

// p' = M p (+ translation if `point`), in float, written out step by step (same on every target).
void Transform(const float* m, const float p[3], bool point, float out[3]) {
  for (int r = 0; r < 3; ++r) {
    float s = m[4 * r] * p[0];
    s = s + m[4 * r + 1] * p[1];
    s = s + m[4 * r + 2] * p[2];
    if (point) s = s + m[4 * r + 3];
    out[r] = s;
  }
}

void CheckView(const RayView& r, const char* what) {
  if (r.size == 0) return;
  const float* arrays[] = {r.ox, r.oy, r.oz, r.dx, r.dy, r.dz, r.tnear, r.tfar};
  const char* names[] = {"ox", "oy", "oz", "dx", "dy", "dz", "tnear", "tfar"};
  for (int i = 0; i < 8; ++i) {
    if (arrays[i] == nullptr) {
      throw Error(std::string("TraceScene::") + what + ": rays." + names[i] + " is null for " +
                  Str(r.size) + " rays");
    }
  }
}

// Scratch streams of a trace call: the sub-stream of one object's candidate rays.
struct SubStream {
  std::vector<float> f[8];
  std::vector<float> t, u, v;
  std::vector<int32_t> prim;
  std::vector<size_t> index;  // sub-stream ray -> caller's ray
  explicit SubStream(size_t n) : t(n), u(n), v(n), prim(n) {
    for (auto& a : f) a.resize(n);
    index.reserve(n);
  }
  RayStreamView Rays() {
    RayStreamView r;
    r.ox = f[0].data(), r.oy = f[1].data(), r.oz = f[2].data();
    r.dx = f[3].data(), r.dy = f[4].data(), r.dz = f[5].data();
    r.tmin = f[6].data(), r.tmax = f[7].data();
    r.size = index.size();
    return r;
  }
  HitStreamView Hits() { return HitStreamView{t.data(), u.data(), v.data(), prim.data(), index.size()}; }
};

}  // namespace

struct TraceScene::Impl {
  BuildOptions options;
  std::vector<Geometry> geoms;
  std::vector<Instance> insts;
  bool committed = false;  // Commit ran and nothing was edited since
  bool ever_committed = false;

  Geometry& Geom(const char* what, uint32_t id) {
    if (id >= geoms.size()) {
      throw Error(std::string("TraceScene::") + what + ": no geometry " + Str(id) + " (" +
                  Str(geoms.size()) + " attached)");
    }
    return geoms[id];
  }

  // Calls f(geom, instance or nullptr, inst_id or -1) for every traced object, in the tie order.
  template <class F>
  void ForEachObject(const F& f) const {
    for (size_t g = 0; g < geoms.size(); ++g) {
      if (!geoms[g].instance_only) f(static_cast<int32_t>(g), nullptr, -1);
    }
    for (size_t i = 0; i < insts.size(); ++i) {
      f(static_cast<int32_t>(insts[i].geom), &insts[i], static_cast<int32_t>(i));
    }
  }

  // Gathers the rays that may hit object (g, inst) into `s` (object space), skipping those
  // `skip` says are done; tfar_now gives each ray's current tfar.
  template <class Skip, class Tfar>
  void Gather(const RayView& rays, const Geometry& g, const Instance* inst, uint32_t mask,
              const Skip& skip, const Tfar& tfar_now, SubStream* s) const {
    s->index.clear();
    for (size_t i = 0; i < rays.size; ++i) {
      if (skip(i)) continue;
      const uint32_t ray_mask = rays.mask != nullptr ? rays.mask[i] : ~0u;
      if ((ray_mask & mask) == 0) continue;
      float o[3] = {rays.ox[i], rays.oy[i], rays.oz[i]};
      float d[3] = {rays.dx[i], rays.dy[i], rays.dz[i]};
      if (inst != nullptr) {
        float ob[3], db[3];
        Transform(inst->inv, o, true, ob);
        Transform(inst->inv, d, false, db);
        std::copy(ob, ob + 3, o), std::copy(db, db + 3, d);
      }
      const float tfar = tfar_now(i);
      if (!MayHit(g.lo, g.hi, o, d, rays.tnear[i], tfar)) continue;
      const size_t k = s->index.size();
      s->index.push_back(i);
      for (int a = 0; a < 3; ++a) s->f[a][k] = o[a], s->f[3 + a][k] = d[a];
      s->f[6][k] = rays.tnear[i], s->f[7][k] = tfar;
    }
  }
};

TraceScene::TraceScene(const BuildOptions& options) : impl_(std::make_unique<Impl>()) {
  Accel check(MeshView{}, options);  // throws rs::Error for bad options
  impl_->options = options;
}
TraceScene::~TraceScene() = default;
TraceScene::TraceScene(TraceScene&&) noexcept = default;
TraceScene& TraceScene::operator=(TraceScene&&) noexcept = default;

namespace {
TraceScene::Impl& Live(const std::unique_ptr<TraceScene::Impl>& impl, const char* what) {
  if (!impl) throw Error(std::string("TraceScene::") + what + ": this TraceScene was moved from");
  return *impl;
}
}  // namespace

uint32_t TraceScene::AttachGeometry(const GeometryDesc& desc) {
  Impl& m = Live(impl_, "AttachGeometry");
  if (m.geoms.size() >= size_t{std::numeric_limits<int32_t>::max()}) {
    throw Error("TraceScene::AttachGeometry: too many geometries");
  }
  m.geoms.push_back(MakeGeometry("TraceScene::AttachGeometry", desc));
  m.committed = false;
  return static_cast<uint32_t>(m.geoms.size() - 1);
}

void TraceScene::ReplaceGeometry(uint32_t geom_id, const GeometryDesc& desc) {
  Impl& m = Live(impl_, "ReplaceGeometry");
  Geometry& g = m.Geom("ReplaceGeometry", geom_id);
  g = MakeGeometry("TraceScene::ReplaceGeometry", desc);
  m.committed = false;
}

void TraceScene::UpdateGeometry(uint32_t geom_id, const void* positions, size_t stride_bytes) {
  Impl& m = Live(impl_, "UpdateGeometry");
  Geometry& g = m.Geom("UpdateGeometry", geom_id);
  SetPositions("TraceScene::UpdateGeometry", &g, positions, stride_bytes);
  m.committed = false;
}

uint32_t TraceScene::AttachInstance(uint32_t geom_id, const float transform[12], uint32_t mask) {
  Impl& m = Live(impl_, "AttachInstance");
  m.Geom("AttachInstance", geom_id);
  if (m.insts.size() >= size_t{std::numeric_limits<int32_t>::max()}) {
    throw Error("TraceScene::AttachInstance: too many instances");
  }
  Instance inst;
  inst.geom = geom_id;
  inst.mask = mask;
  InvertTransform("TraceScene::AttachInstance", transform, inst.inv);
  std::copy(transform, transform + 12, inst.m);
  m.insts.push_back(inst);
  m.committed = false;
  return static_cast<uint32_t>(m.insts.size() - 1);
}

void TraceScene::SetInstanceTransform(uint32_t inst_id, const float transform[12]) {
  Impl& m = Live(impl_, "SetInstanceTransform");
  if (inst_id >= m.insts.size()) {
    throw Error("TraceScene::SetInstanceTransform: no instance " + Str(inst_id) + " (" +
                Str(m.insts.size()) + " attached)");
  }
  Instance& inst = m.insts[inst_id];
  float inv[12];
  InvertTransform("TraceScene::SetInstanceTransform", transform, inv);
  std::copy(inv, inv + 12, inst.inv);
  std::copy(transform, transform + 12, inst.m);
  m.committed = false;
}

void TraceScene::Commit() {
  Impl& m = Live(impl_, "Commit");
  for (size_t id = 0; id < m.geoms.size(); ++id) {
    Geometry& g = m.geoms[id];
    if (!g.dirty) continue;
    MeshView mesh;
    mesh.positions = g.positions;
    mesh.num_vertices = g.num_vertices;
    mesh.stride = g.stride;
    mesh.indices = g.indices.data();
    mesh.num_triangles = g.num_triangles();
    try {
      if (g.accel) {
        g.accel->Rebuild(mesh, m.options);  // an updated geometry: its last build's memory
      } else {
        g.accel.emplace(mesh, m.options);
      }
    } catch (const Error& e) {
      g.accel.reset();
      throw Error("TraceScene::Commit: geometry " + Str(id) + ": " + e.what());
    }
    ComputeBounds(&g);
    g.dirty = false;
  }
  m.committed = true;
  m.ever_committed = true;
}

size_t TraceScene::num_geometries() const { return Live(impl_, "num_geometries").geoms.size(); }
size_t TraceScene::num_instances() const { return Live(impl_, "num_instances").insts.size(); }

namespace {
const TraceScene::Impl& Ready(const std::unique_ptr<TraceScene::Impl>& impl, const char* what) {
  const TraceScene::Impl& m = Live(impl, what);
  if (!m.ever_committed) throw Error(std::string("TraceScene::") + what + ": the scene was never committed");
  if (!m.committed) {
    throw Error(std::string("TraceScene::") + what + ": the scene was edited since its last Commit");
  }
  return m;
}
}  // namespace

void TraceScene::Intersect(const RayView& rays, const HitView& hits) const {
  const Impl& m = Ready(impl_, "Intersect");
  if (hits.size != rays.size) {
    throw Error("TraceScene::Intersect: hits.size " + Str(hits.size) + " differs from rays.size " +
                Str(rays.size));
  }
  CheckView(rays, "Intersect");
  if (rays.size > 0 && (!hits.t || !hits.u || !hits.v || !hits.ng_x || !hits.ng_y ||
                        !hits.ng_z || !hits.prim || !hits.geom || !hits.inst)) {
    throw Error("TraceScene::Intersect: a hit array is null for " + Str(rays.size) + " rays");
  }
  const size_t n = rays.size;
  for (size_t i = 0; i < n; ++i) {
    hits.t[i] = kInf, hits.u[i] = 0, hits.v[i] = 0;
    hits.prim[i] = -1, hits.geom[i] = -1, hits.inst[i] = -1;
  }
  SubStream s(n);
  m.ForEachObject([&](int32_t geom, const Instance* inst, int32_t inst_id) {
    const Geometry& g = m.geoms[size_t(geom)];
    m.Gather(
        rays, g, inst, inst != nullptr ? inst->mask : g.mask, [](size_t) { return false; },
        [&](size_t i) { return hits.geom[i] >= 0 ? hits.t[i] : rays.tfar[i]; }, &s);
    if (s.index.empty()) return;
    g.accel->Intersect(s.Rays(), s.Hits());
    for (size_t k = 0; k < s.index.size(); ++k) {
      const size_t i = s.index[k];
      if (s.prim[k] < 0) continue;
      // Strictly closer than a hit of an earlier object (the tie rule); t <= tfar by the trace.
      if (hits.geom[i] >= 0 && !(s.t[k] < hits.t[i])) continue;
      hits.t[i] = s.t[k], hits.u[i] = s.u[k], hits.v[i] = s.v[k];
      hits.prim[i] = s.prim[k], hits.geom[i] = geom, hits.inst[i] = inst_id;
    }
  });
  // Ng = (p1 - p0) x (p2 - p0) of the hit triangle; for instances times inv^T.
  for (size_t i = 0; i < n; ++i) {
    float ng[3] = {0, 0, 0};
    if (hits.geom[i] >= 0) {
      const Geometry& g = m.geoms[size_t(hits.geom[i])];
      const uint32_t* tri = &g.indices[3 * size_t(hits.prim[i])];
      const float *p0 = g.Vertex(tri[0]), *p1 = g.Vertex(tri[1]), *p2 = g.Vertex(tri[2]);
      const float e1[3] = {p1[0] - p0[0], p1[1] - p0[1], p1[2] - p0[2]};
      const float e2[3] = {p2[0] - p0[0], p2[1] - p0[1], p2[2] - p0[2]};
      ng[0] = e1[1] * e2[2] - e1[2] * e2[1];
      ng[1] = e1[2] * e2[0] - e1[0] * e2[2];
      ng[2] = e1[0] * e2[1] - e1[1] * e2[0];
      if (hits.inst[i] >= 0) {
        const float* inv = m.insts[size_t(hits.inst[i])].inv;
        float w[3];
        for (int c = 0; c < 3; ++c) {
          float sum = inv[c] * ng[0];
          sum = sum + inv[4 + c] * ng[1];
          sum = sum + inv[8 + c] * ng[2];
          w[c] = sum;
        }
        std::copy(w, w + 3, ng);
      }
    }
    hits.ng_x[i] = ng[0], hits.ng_y[i] = ng[1], hits.ng_z[i] = ng[2];
  }
}

void TraceScene::Occluded(const RayView& rays, int32_t* occluded) const {
  const Impl& m = Ready(impl_, "Occluded");
  CheckView(rays, "Occluded");
  if (rays.size > 0 && occluded == nullptr) {
    throw Error("TraceScene::Occluded: occluded is null for " + Str(rays.size) + " rays");
  }
  std::fill(occluded, occluded + rays.size, 0);
  SubStream s(rays.size);
  m.ForEachObject([&](int32_t geom, const Instance* inst, int32_t) {
    const Geometry& g = m.geoms[size_t(geom)];
    m.Gather(
        rays, g, inst, inst != nullptr ? inst->mask : g.mask,
        [&](size_t i) { return occluded[i] != 0; }, [&](size_t i) { return rays.tfar[i]; }, &s);
    if (s.index.empty()) return;
    g.accel->Occluded(s.Rays(), s.prim.data());
    for (size_t k = 0; k < s.index.size(); ++k) {
      if (s.prim[k] != 0) occluded[s.index[k]] = 1;
    }
  });
}

}  // namespace rs
