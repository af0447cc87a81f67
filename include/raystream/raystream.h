// raystream public API: build a grid over caller-owned triangles, trace SoA ray streams.
// This header (standard library only) is all a tracer that links raystream needs: pkg-config
// raystream, or CMake find_package(raystream) and the target raystream::raystream.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <stdexcept>
#include <string>

// The library's version; Version() returns the same string at run time.
#define RS_VERSION_MAJOR 0
#define RS_VERSION_MINOR 1
#define RS_VERSION_PATCH 0
#define RS_VERSION_STRING "0.1.0"

// What libraystream exports: everything marked RS_API, nothing else.
#if defined(__GNUC__) || defined(__clang__)
#define RS_API __attribute__((visibility("default")))
#else
#define RS_API
#endif

namespace rs {

// Stream arrays of any alignment and exactly `size` elements are accepted. Arrays aligned to
// kStreamAlign bytes and holding PaddedSize(size) elements are traced in place to the end;
// otherwise the last size % kStreamPad rays pass through a padded copy (a few rays).
inline constexpr size_t kStreamAlign = 64;
inline constexpr size_t kStreamPad = 16;  // floats per 64 B: the widest vector (AVX-512)
constexpr size_t PaddedSize(size_t n) {
  return n == 0 ? kStreamPad : (n + kStreamPad - 1) / kStreamPad * kStreamPad;
}

// All user-input errors (bad mesh, bad scene file, bad option, misuse of an Accel) are thrown as
// rs::Error with a message naming the file and the line or element. The kernels under Accel's
// checked entry points never throw.
class RS_API Error : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

enum class RayKind : int32_t { kPrimary = 0, kShadow = 1, kReflection = 2, kRefraction = 3 };
inline constexpr int kNumRayKinds = 4;
RS_API const char* RayKindName(RayKind kind);

// A stream of rays, one pointer per component (SoA). The geometric fields (o, d, tmin, tmax)
// are all the trace functions read (none may be null when size > 0); pixel, weight, depth and
// kind are carried for the renderer and may be null for callers that only trace. Directions need not be normalized;
// t is measured in units of |d|. Views do not own their data.
struct RayStreamView {
  float* ox = nullptr;
  float* oy = nullptr;
  float* oz = nullptr;
  float* dx = nullptr;
  float* dy = nullptr;
  float* dz = nullptr;
  float* tmin = nullptr;
  float* tmax = nullptr;
  uint32_t* pixel = nullptr;  // pixel id (y * width + x) the ray contributes to
  float* wr = nullptr;        // weight: product of BRDF factors along the path (rgb);
  float* wg = nullptr;        // for shadow rays, the light contribution if unoccluded
  float* wb = nullptr;
  int32_t* depth = nullptr;   // bounces so far (0 for primary rays)
  int32_t* kind = nullptr;    // RayKind
  size_t size = 0;
};

// Closest-hit results. prim = -1 and t = +inf for a miss; u, v are the barycentrics of
// vertices 1 and 2 (hit point = (1-u-v)·p0 + u·p1 + v·p2).
struct HitStreamView {
  float* t = nullptr;
  float* u = nullptr;
  float* v = nullptr;
  int32_t* prim = nullptr;
  size_t size = 0;
};

// Caller-owned triangle mesh: positions are xyz floats with a stride (in floats, >= 3);
// indices are 3 per triangle. Accel copies what it needs; the mesh may be freed after Build.
struct MeshView {
  const float* positions = nullptr;
  size_t num_vertices = 0;
  size_t stride = 3;
  const uint32_t* indices = nullptr;
  size_t num_triangles = 0;
};

enum class GridKind : int { kAuto = 0, kUniform = 1, kTwoLevel = 2, kIrregular = 3 };

struct BuildOptions {
  // Grid density: cells ~= lambda * triangles (Cleary/Wyvill). 0 (the default): chosen by the
  // grid cost model under kAuto, 4 under kUniform and kTwoLevel; > 0: used as given.
  float lambda = 0.0f;
  int max_resolution = 512;  // per axis
  // kUniform: one grid at `lambda`. kTwoLevel: the grid at `lambda`, and every cell holding more
  // than subgrid_threshold triangles gets an 8x8x8 sub-grid (Cell paper 3.8). kAuto: lambda
  // from the grid cost model when `lambda` is 0 (else `lambda`), then only the cells whose
  // sub-grid the cost model finds cheaper are refined; AccelInfo::kind says what was built.
  // kIrregular: the grid of kAuto for coherent packets, and an irregular grid (cells of varying
  // size, merged and expanded over empty space: Perard-Gayot et al. 2017) for every ray traced
  // one per lane (incoherent rays, and those the packets refuse). Same hits in every case.
  GridKind grid = GridKind::kAuto;
  int subgrid_threshold = 32;  // kTwoLevel: refine cells with more triangles; kAuto: candidates
  int micro_cache = 8;         // traversal micro-cache entries (0 = off, at most 16)
  // Jump over blocks of empty cells where the grid has enough of them (results unchanged).
  bool empty_skip = true;
  // Trace each run of 64 consecutive rays whose directions agree in sign along one axis as one
  // packet that walks the grid slice by slice (coherent grid traversal; results unchanged).
  // Pays for primary and shadow rays in scanline or tile order; others fall back per packet.
  bool packets = true;
  // Threads of the build (the lambda choice and the grid's binning and lists): the calling
  // thread and the library's build threads, started on first use and kept for the process
  // (parked between builds; a build that finds them busy starts threads of its own). The
  // structure, and so every result, is the same for any count; 1 (the default) builds on the
  // calling thread only. Values below 1 count as 1, above 64 as 64.
  int build_threads = 1;
};

// Figures about a built structure, as printed by `raystream info`.
struct AccelInfo {
  size_t triangles = 0;
  size_t degenerate_triangles = 0;  // zero-area: kept in the mesh, never hit, not binned
  float bounds_lo[3] = {0, 0, 0};
  float bounds_hi[3] = {0, 0, 0};
  int resolution[3] = {0, 0, 0};
  size_t cells = 0;
  size_t occupied_cells = 0;
  size_t references = 0;  // sum over cells of triangles per cell
  size_t max_per_cell = 0;
  double build_seconds = 0;
  size_t bytes = 0;  // its triangles (SoA and interleaved: 73 B each), grids and bundles
  const char* kind = "uniform";  // "uniform", "two-level" (the grid of the packets)
  size_t irregular_cells = 0;     // cells of the irregular grid (GridKind::kIrregular), or 0
  size_t irregular_references = 0;
  float lambda = 0.0f;            // the lambda the top-level grid was built with
  size_t subgrids = 0;            // refined cells (8x8x8 sub-grids, one 128-B record each)
  size_t sub_references = 0;      // triangle references held by sub-cells
  double cost_estimate = 0.0;     // expected cost per ray, in empty cell steps (two_level.h)
  double flat_cost_estimate = 0.0;  // the same for the top-level grid alone
  const char* simd_target = "";   // the Highway target the traversal kernels dispatch to
  // Share of the top-level cells inside an empty 5x5x5 block, and whether traversal jumps over
  // such blocks (BuildOptions::empty_skip, used when the share makes it pay: accel.cc).
  double empty_block_share = 0.0;
  bool empty_skip = false;
  // The frame the structures are built in: the triangles are stored at world - frame_shift
  // (all 0 unless the mesh lies farther from the origin than its size; see Accel).
  float frame_shift[3] = {0, 0, 0};
};

struct TraceStats {
  uint64_t rays = 0;
  uint64_t cell_steps = 0;      // cells entered (top-level and sub-grid cells; not the empty
                                // cells that BuildOptions::empty_skip jumps over)
  uint64_t triangle_tests = 0;  // ray/triangle tests (SIMD: 4-triangle bundle lanes holding one)
  // The traversal micro-cache (BuildOptions::micro_cache).
  uint64_t cache_lookups = 0;
  uint64_t cache_hits = 0;
  uint64_t empty_skips = 0;  // jumps over blocks of empty cells (BuildOptions::empty_skip)
  // 64-ray packets traced together (BuildOptions::packets), and the stream's 64-ray runs refused
  // (not coherent, or diverging too much). The rays of refused runs are regrouped by direction
  // and origin and tried as packets once more (packets_regrouped of the `packets`); what is
  // refused again goes to the per-ray walk. packets - packets_regrouped + packets_refused is the
  // number of 64-ray runs of the streams.
  uint64_t packets = 0;
  uint64_t packets_refused = 0;
  uint64_t packet_rays = 0;  // rays of the packets counted in `packets`
  uint64_t packets_regrouped = 0;
};

// The acceleration structure: a uniform grid with an occupancy bit array and CSR cell lists,
// optionally with 8x8x8 sub-grids in its densest cells (BuildOptions::grid), traced by SIMD
// stream kernels (Highway dynamic dispatch; results identical on every CPU target).
// Thread-safe for concurrent Intersect/Occluded calls once built; a call allocates nothing and
// uses about 130 KB of the calling thread's stack (packet scratch; 12 KB more for a far mesh).
// A mesh farther from the origin than its own size is stored translated to its centre (exact)
// and the rays' origins are translated as they enter, so its grid is as fine as at the origin.
// Coordinate range: the watertight test multiplies three coordinates relative to the ray
// origin, so vertices and ray origins must stay within magnitude 2^39 (about 5.5e11) to keep
// its products finite, and triangles larger than about 2^-40 to keep them from underflowing.
// Scale a scene outside that range by a power of two (exact: no rounding changes, hits scale
// back exactly), as the raystream renderer does for every scene it loads.
class RS_API Accel {
 public:
  // Throws rs::Error if an index is out of range or a vertex of a referenced triangle is
  // NaN/Inf (message names the triangle and vertex). An empty mesh builds an Accel that
  // never hits.
  explicit Accel(const MeshView& mesh, const BuildOptions& options = {});
  ~Accel();
  Accel(Accel&&) noexcept;
  Accel& operator=(Accel&&) noexcept;

  // Rebuilds for `mesh` (the same mesh moved, or another one) with `options`, reusing this
  // Accel's memory: the arrays of the last build and its temporaries (kept between rebuilds) are
  // taken back where they fit, so a rebuild of the same size maps no fresh page. Throws as the
  // constructor; on a throw this Accel must be rebuilt before it is used again (its calls throw
  // "the last Rebuild failed"). A moved-from Accel may be rebuilt. Not thread-safe with calls
  // on this Accel; LightBuffers of it must be rebuilt after.
  void Rebuild(const MeshView& mesh, const BuildOptions& options = {});

  // Closest hit with t in (tmin, tmax] for rays[0, size). Throws rs::Error if hits.size !=
  // rays.size, a ray or hit array is null while size > 0, or this Accel was moved from.
  // Rays with NaN/Inf components or zero direction never hit. Results are exact in the sense of
  // the watertight test (Woop, Benthin, Wald 2013): no ray passes between two triangles sharing
  // an edge. On equal t the lower triangle id wins. Optional stats are accumulated (not reset).
  void Intersect(const RayStreamView& rays, const HitStreamView& hits,
                 TraceStats* stats = nullptr) const;
  // Any hit with t in (tmin, tmax]: occluded[i] = 1 if ray i is blocked, else 0. May stop at the
  // first hit found. Throws rs::Error like Intersect (occluded null while size > 0).
  void Occluded(const RayStreamView& rays, int32_t* occluded, TraceStats* stats = nullptr) const;

  // Throws rs::Error if this Accel was moved from.
  AccelInfo Info() const;

  struct Impl;

 private:
  friend const Impl& AccelImpl(const Accel& accel);  // kernels/accel_impl.h: not installed
  std::unique_ptr<Impl> impl_;
};

struct LightBufferInfo {
  int resolution = 0;     // the most cells along an axis of a cube face (0: nothing can be hit)
  size_t cells = 0;       // over the six faces, each a grid over the window its triangles cover
  size_t references = 0;  // triangle ids in the cells' lists
  size_t always = 0;      // triangles touching the light, read by every ray
  size_t longest = 0;     // the longest cell's list (without the always list)
  size_t bytes = 0;
  double build_seconds = 0.0;
};

// Shadow rays to one point light, traced from the light (a light buffer: Haines & Greenberg,
// "The light buffer: a shadow-testing accelerator", IEEE CG&A 1986). The Accel's triangles are
// binned by the directions under which the light sees them, on the six faces of a cube around
// it, each cell listing its triangles by ascending distance: a ray that starts exactly at the
// light reads the one cell of its direction and tests, SIMD over the list, the triangles nearer
// than its tmax, stopping at the first hit. Any other ray is traced by the Accel. Occluded gives
// Accel::Occluded's results bit for bit, for any rays. To shade a point p with the light at L,
// trace origin L, direction p - L, t in (0, 1 - epsilon]: the same segment as a ray from p.
// Borrows `accel` (it must outlive the LightBuffer and not move); build per light (and again
// when the light or the geometry moves). Thread-safe for concurrent Occluded calls; a call
// allocates nothing (about 12 KB of stack).
class RS_API LightBuffer {
 public:
  // Throws rs::Error if `light` is null or not finite, or the Accel was moved from.
  LightBuffer(const Accel& accel, const float light[3]);
  ~LightBuffer();
  LightBuffer(LightBuffer&&) noexcept;
  LightBuffer& operator=(LightBuffer&&) noexcept;

  // Rebuilds for `accel` (a rebuilt Accel of a moving scene, or the same one) and `light`,
  // reusing this buffer's memory where it is large enough: a rebuild of the same size touches
  // no fresh page. Throws as the constructor (or if moved from); on a throw the buffer must be
  // rebuilt before it is used again.
  void Rebuild(const Accel& accel, const float light[3]);

  // Any hit with t in (tmin, tmax], as Accel::Occluded (same contract and errors).
  void Occluded(const RayStreamView& rays, int32_t* occluded, TraceStats* stats = nullptr) const;
  LightBufferInfo Info() const;

  struct Impl;

 private:
  std::unique_ptr<Impl> impl_;
};

// ---- Trace-only streams and the scene model (TraceScene) ------------------------------------------------

// The rays a TraceScene traces (SoA, one pointer per component; none may be null when size > 0 except
// mask). Any alignment and exactly `size` elements are accepted; RayBuffer gives 64-B aligned,
// padded arrays. A hit is reported for t in (tnear, tfar], open at tnear (Embree 3 uses the
// closed [tnear, tfar]: a hit exactly at tnear counts there, not here). Directions need not be
// normalized; t is in units of |d|. mask null: every ray has mask ~0u. id is the caller's
// (carried by RayBuffer, never read by tracing).
struct RayView {
  const float* ox = nullptr;
  const float* oy = nullptr;
  const float* oz = nullptr;
  const float* dx = nullptr;
  const float* dy = nullptr;
  const float* dz = nullptr;
  const float* tnear = nullptr;
  const float* tfar = nullptr;
  const uint32_t* mask = nullptr;
  const uint32_t* id = nullptr;
  size_t size = 0;
};

// Closest hits of a TraceScene (none may be null when size > 0). A miss: t = +inf, u = v = 0,
// ng = 0, prim = geom = inst = -1. ng is the unnormalized geometric normal (p1-p0) x (p2-p0)
// (Embree's convention), in world space: for an instance, the object-space normal times the
// inverse transpose of the transform's 3x3 part. inst is -1 for a hit on a geometry itself.
struct HitView {
  float* t = nullptr;
  float* u = nullptr;
  float* v = nullptr;
  float* ng_x = nullptr;
  float* ng_y = nullptr;
  float* ng_z = nullptr;
  int32_t* prim = nullptr;
  int32_t* geom = nullptr;
  int32_t* inst = nullptr;
  size_t size = 0;
};

// Owning ray storage: each component a 64-B aligned array of PaddedSize(size()) elements (the
// padding holds rays that never hit: zero direction). Resize keeps no contents: every ray is
// reset to o = d = 0, tnear = 0, tfar = +inf, mask = ~0u, id = its index. Not copyable; a
// moved-from buffer has size 0. Accessors give mutable arrays; View() the trace-only view.
class RS_API RayBuffer {
 public:
  explicit RayBuffer(size_t size = 0);
  ~RayBuffer();
  RayBuffer(RayBuffer&& other) noexcept;
  RayBuffer& operator=(RayBuffer&& other) noexcept;
  RayBuffer(const RayBuffer&) = delete;
  RayBuffer& operator=(const RayBuffer&) = delete;
  void Resize(size_t size);
  size_t size() const { return size_; }
  float* ox() { return f_[0]; }
  float* oy() { return f_[1]; }
  float* oz() { return f_[2]; }
  float* dx() { return f_[3]; }
  float* dy() { return f_[4]; }
  float* dz() { return f_[5]; }
  float* tnear() { return f_[6]; }
  float* tfar() { return f_[7]; }
  uint32_t* mask() { return mask_; }
  uint32_t* id() { return id_; }
  RayView View() const;

 private:
  void* storage_ = nullptr;
  float* f_[8] = {};
  uint32_t* mask_ = nullptr;
  uint32_t* id_ = nullptr;
  size_t size_ = 0;
};

// Owning hit storage (HitView's arrays, 64-B aligned, PaddedSize(size()) elements each).
// Resize keeps no contents (every hit reset to a miss). Not copyable; a moved-from buffer has
// size 0.
class RS_API HitBuffer {
 public:
  explicit HitBuffer(size_t size = 0);
  ~HitBuffer();
  HitBuffer(HitBuffer&& other) noexcept;
  HitBuffer& operator=(HitBuffer&& other) noexcept;
  HitBuffer(const HitBuffer&) = delete;
  HitBuffer& operator=(const HitBuffer&) = delete;
  void Resize(size_t size);
  size_t size() const { return size_; }
  const float* t() const { return f_[0]; }
  const float* u() const { return f_[1]; }
  const float* v() const { return f_[2]; }
  const float* ng_x() const { return f_[3]; }
  const float* ng_y() const { return f_[4]; }
  const float* ng_z() const { return f_[5]; }
  const int32_t* prim() const { return i_[0]; }
  const int32_t* geom() const { return i_[1]; }
  const int32_t* inst() const { return i_[2]; }
  HitView View();

 private:
  void* storage_ = nullptr;
  float* f_[6] = {};
  int32_t* i_[3] = {};
  size_t size_ = 0;
};

enum class IndexType : int { kUInt32 = 0, kUInt16 = 1 };
enum class BufferMode : int {
  kCopy = 0,    // the scene copies positions and indices at attach/update time
  kShared = 1,  // the scene keeps the caller's position pointer (indices are always copied):
                // the caller keeps that buffer alive and unchanged until the geometry is
                // replaced, updated from another buffer or the scene is destroyed; a change to
                // its contents takes effect only through UpdateGeometry + Commit
};

// A caller's triangle geometry: xyz float positions with a stride in bytes (a multiple of 4, at
// least 12; positions 4-byte aligned), 3 indices per triangle (16- or 32-bit, packed).
// mask: a ray traces this geometry only if (ray mask & mask) != 0. instance_only: the geometry
// is traced only through its instances, not by itself.
struct GeometryDesc {
  const void* positions = nullptr;
  size_t num_vertices = 0;
  size_t stride_bytes = 12;
  const void* indices = nullptr;
  IndexType index_type = IndexType::kUInt32;
  size_t num_triangles = 0;
  uint32_t mask = ~0u;
  BufferMode mode = BufferMode::kCopy;
  bool instance_only = false;
};

// Several triangle geometries and instances of them, traced together. Each geometry has its own
// Accel (a grid, the kernels above: watertight, results identical on every Highway target); the
// top level is linear in the number of objects (each geometry not instance_only, and each
// instance): per object a box test per ray in double, the rays that pass are compacted, traced
// with tfar = the closest t so far and merged. Fine for tens of objects, not for thousands.
// Instances: rays are moved into object space by the inverse transform (scalar float code, the
// same on every target); t carries over since directions are not renormalized. Instance hits
// agree with the geometry pre-transformed into world space within float rounding of the
// transform (in tests: t within 1e-5 relative, u, v within 1e-4), not bit for bit.
// Equal t (deterministic rule): objects are visited in a fixed order, geometries by ascending
// geomID, then instances by ascending instID, and a later object replaces a hit only with a
// strictly smaller t; within one object the lower primID wins. So on a tie the geometry beats
// any instance, the lower geomID / instID wins, then the lower primID.
// Edits (Attach*, Update*, Replace*, SetInstanceTransform) take effect at Commit, which rebuilds
// only the Accels of attached, replaced or updated geometries and recomputes the top-level boxes.
// Tracing a scene that was never committed, or edited since its last Commit, throws rs::Error.
// Thread-safe for concurrent Intersect/Occluded calls between Commits.
class RS_API TraceScene {
 public:
  explicit TraceScene(const BuildOptions& options = {});
  ~TraceScene();
  TraceScene(TraceScene&&) noexcept;
  TraceScene& operator=(TraceScene&&) noexcept;

  // Returns the geomID (0, 1, ... in attach order). Throws rs::Error for null arrays (with
  // counts > 0), a bad stride or index type, an index >= num_vertices, more than 2^31 - 1
  // triangles. Non-finite positions of referenced vertices are reported by Commit.
  uint32_t AttachGeometry(const GeometryDesc& desc);
  // Replaces geometry `geom_id` (any topology); its instances now instance the new one.
  void ReplaceGeometry(uint32_t geom_id, const GeometryDesc& desc);
  // New vertex positions for geometry `geom_id`, same num_vertices and triangles. kCopy:
  // copied; kShared: the scene keeps `positions` instead of the previous buffer.
  void UpdateGeometry(uint32_t geom_id, const void* positions, size_t stride_bytes);
  // An instance of geometry `geom_id`: object-to-world transform, 3x4 row-major
  // (x' = m[0] x + m[1] y + m[2] z + m[3], ...), invertible and finite; mask as a geometry's.
  // Returns the instID (0, 1, ... in attach order).
  uint32_t AttachInstance(uint32_t geom_id, const float transform[12], uint32_t mask = ~0u);
  void SetInstanceTransform(uint32_t inst_id, const float transform[12]);
  void Commit();

  size_t num_geometries() const;
  size_t num_instances() const;

  // Closest hits (HitView). Throws rs::Error if hits.size != rays.size, an array is null while
  // size > 0, the scene is not committed or was moved from. NaN/Inf rays never hit.
  void Intersect(const RayView& rays, const HitView& hits) const;
  // occluded[i] = 1 if ray i hits anything in (tnear, tfar], else 0.
  void Occluded(const RayView& rays, int32_t* occluded) const;

  struct Impl;

 private:
  std::unique_ptr<Impl> impl_;
};

// Library version, RS_VERSION_STRING of the library actually loaded, e.g. "0.1.0".
RS_API const char* Version();

}  // namespace rs
