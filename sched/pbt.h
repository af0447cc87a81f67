// Prediction Binary Tree (PBT) tiling after Cosenza et al., "On Estimating the Effectiveness of
// Temporal and Spatial Coherence in Parallel Ray Tracing" (shared/papers/pbt-temporal-spatial-
// coherence.md): re-tiles the image between frames from measured tile times (PBT-Update,
// Algorithm 1) and assigns the tiles to workers (PBT-Greedy, PBT-Visit, PBT-Random, §4-5).
#pragma once

#include <cstddef>
#include <cstdint>
#include <span>
#include <string>
#include <utility>
#include <vector>

#include "streams/raygen.h"  // rs::Tile: [x0, x1) x [y0, y1)

namespace rs {

// The axis a node's tile is cut along: kX cuts the x extent (left / right children), kY the y
// extent (top / bottom children).
enum class PbtAxis : int8_t { kX = 0, kY = 1 };

// One node of the tree. Leaves are the tiles; child[0] is the left (kX) or top (kY) half.
struct PbtNode {
  Tile tile;
  int32_t parent = -1;
  int32_t child[2] = {-1, -1};  // both -1 for a leaf
  int32_t depth = 0;            // root = 0
  PbtAxis axis = PbtAxis::kX;   // inner nodes: the axis the tile was cut along
  double estimate = 0.0;        // e(l): a leaf's predicted time; inner: sum over its leaves
  double measured = 0.0;        // t(l): last measured time; leaves made by Update inherit
                                // t(a) / 2 (split) or t(b1) + t(b2) (merge)
  int32_t worker = -1;          // leaves: the PBT-Greedy affinity (§4), in [0, num_workers)
  bool IsLeaf() const { return child[0] < 0; }
};

struct PbtUpdateOptions {
  // Hard bound on split-merge steps per Update (the paper proves termination in exact
  // arithmetic and reports 5-10 steps; the bound guards floating point and huge inputs).
  // 0 = automatic: 16 * m + 64.
  int max_steps = 0;
};

struct PbtUpdateStats {
  int steps = 0;                 // split-merge operations performed
  bool hit_step_bound = false;   // stopped by max_steps, not by the paper's condition
  double variance_before = 0.0;  // sigma_T^2 of the leaf estimates after copying t into e
  double variance_after = 0.0;   // sigma_T^2 of the leaf estimates of the returned tree
};

// What PBT-Update predicts a rectangle's cost with, instead of the paper's e(a) / 2 for split
// halves and sums of the last estimates (e.g. CostMap, sched/cost_map.h). Predict must be
// non-negative and finite, and additive up to rounding (a rectangle's prediction = the sum of
// its two halves'), so the tree's inner sums stay consistent.
class PbtPredictor {
 public:
  virtual double Predict(const Tile& tile) const = 0;

 protected:
  ~PbtPredictor() = default;
};

// The PBT of §3: a binary tree over a width x height image with exactly m = k * n leaves (n
// workers, k = tiles_per_worker), every inner node with two children, the leaves partitioning the
// image. Leaf (tile) index i is the i-th leaf of the in-order (left-to-right) visit; indices are
// renumbered by every Update. Single-threaded: the master owns the tree. Update, Variance and
// SetMeasuredTimes allocate nothing (but the message of an rs::Error they throw): the
// constructor sizes every buffer for the 2m - 1 nodes, and a split-merge keeps the node count.
//
// Choices where the paper leaves freedom (documented here once):
// - Split axes alternate with depth (§3). The paper does not say which axis the root uses; we
//   cut the root along the longer image side (kX if width >= height) and alternate from there.
//   A node whose extent along its depth's axis is 1 pixel is cut along the other axis; a 1x1
//   leaf cannot be split.
// - Splits in PBT-Update halve the tile (the first half gets floor(extent / 2) pixels). The
//   initial tree cuts each node in proportion to the leaves below it (floor(q/2) : ceil(q/2)),
//   so for any m (not only powers of two) the initial tiles have nearly equal area (rounding to
//   whole pixels; tiny images may deviate more); for m a power of two on an image whose sides
//   divide evenly these are exact halves.
// - Initial PBT-Greedy affinity: the in-order leaves in runs of k per worker (leaf i -> i / k).
class Pbt {
 public:
  // Throws rs::Error if width or height < 1, width * height >= 2^31, num_workers < 1,
  // tiles_per_worker < 1, or m = num_workers * tiles_per_worker exceeds the pixel count (a
  // tile holds at least one pixel). Initial estimates are 0.
  Pbt(int width, int height, int num_workers, int tiles_per_worker = 1);

  int width() const { return width_; }
  int height() const { return height_; }
  int num_workers() const { return num_workers_; }
  int tiles_per_worker() const { return tiles_per_worker_; }
  size_t NumLeaves() const { return leaves_.size(); }  // m, constant

  // Node ids of the leaves in in-order; position = tile index.
  std::span<const int32_t> LeafNodes() const { return leaves_; }
  const PbtNode& Node(int32_t id) const { return nodes_[static_cast<size_t>(id)]; }
  int32_t Root() const { return 0; }
  const Tile& LeafTile(size_t i) const { return Node(leaves_[i]).tile; }
  double LeafEstimate(size_t i) const { return Node(leaves_[i]).estimate; }

  std::vector<Tile> Tiles() const;           // per tile index
  std::vector<double> Estimates() const;     // e(l) per tile index: the next frame's prediction
  std::vector<int32_t> LeafWorkers() const;  // PBT-Greedy affinity per tile index
  // The same into `out` (resized to m; its capacity is kept, so no allocation once it held m).
  void Tiles(std::vector<Tile>& out) const;
  void Estimates(std::vector<double>& out) const;

  // sigma_T^2 = (1/m) sum_l (e(l) - mu_T)^2 over the leaves (§3).
  double Variance() const;

  // Algorithm 1, lines 2-4: t(l) <- times[i], e(l) <- t(l) for tile index i; inner nodes get
  // the sums. times.size() must be m; throws rs::Error naming the tile if the size differs or a
  // time is negative, NaN or infinite. Does not change the tiling.
  void SetMeasuredTimes(std::span<const double> times);

  // Algorithm 1, lines 5-17, on the current estimates: repeated split-merge until
  // e(a)^2 <= 4 e(b1) e(b2). Keeps m; renumbers tiles; keeps the PBT-Greedy affinities (§4).
  // Deviations needed to make the algorithm well defined (see pbt.cc): a is the costliest
  // *splittable* leaf (not 1x1), and (b1, b2) is the cheapest sibling-leaf pair not containing
  // a; if either does not exist the update stops. Never raises the variance (beyond rounding).
  PbtUpdateStats Update(const PbtUpdateOptions& options = {});

  // SetMeasuredTimes(times) then Update(options): what the master runs after each frame.
  PbtUpdateStats Update(std::span<const double> times, const PbtUpdateOptions& options = {});

  // PBT-Update with a predictor (the cost map of the frame, reprojected to the next camera):
  // SetMeasuredTimes(times), then every leaf's estimate e(l) <- predictor.Predict(l's tile),
  // then the split-merge loop of Update where a split's halves get predictor.Predict of their
  // tiles (not e(a) / 2) and a merge gets e(b1) + e(b2). The stopping test is the exact
  // variance drop of the step: replacing (a, b1, b2) by (a1, a2, b1 + b2) lowers sum e^2 by
  // 2 (e(a1) e(a2) - e(b1) e(b2)), so the loop runs while e(a1) e(a2) > e(b1) e(b2) (with
  // halves e(a) / 2 this is the paper's e(a)^2 > 4 e(b1) e(b2)); the variance strictly drops,
  // so the loop ends. Allocates nothing, as Update.
  PbtUpdateStats Update(std::span<const double> times, const PbtPredictor& predictor,
                        const PbtUpdateOptions& options = {});

  // Structural self-check (for tests): root covers the image, children partition their parent
  // along the stored axis, parent links, m leaves, inner estimates = sums (1e-9 relative), each
  // worker holds k leaves. Returns "" if consistent, else a description of the first problem.
  std::string Validate() const;

 private:
  int32_t NewNode();
  void Build(int32_t id, int num_leaves);
  PbtAxis SplitAxis(const PbtNode& node) const;  // axis for halving a leaf (assumes >= 2 px)
  void SplitTiles(const PbtNode& node, Tile& t0, Tile& t1) const;  // the halves SplitLeaf makes
  // Halves a leaf into two new leaves, estimates e0 and e1 (< 0: e(a) / 2 each, the paper's).
  void SplitLeaf(int32_t id, double e0 = -1.0, double e1 = -1.0);
  PbtUpdateStats Run(const PbtUpdateOptions& options, const PbtPredictor* predictor);
  void RebuildLeafOrder();
  void RecomputeSums();

  int width_ = 0;
  int height_ = 0;
  int num_workers_ = 0;
  int tiles_per_worker_ = 0;
  PbtAxis root_axis_ = PbtAxis::kX;
  std::vector<PbtNode> nodes_;  // node 0 is the root; 2m - 1 live nodes
  std::vector<int32_t> free_;   // ids of unused nodes (children removed by a merge)
  std::vector<int32_t> leaves_;
  std::vector<int32_t> stack_;  // scratch of the tree walks (capacity 2m - 1)
  std::vector<int32_t> order_;  // scratch of RecomputeSums: pre-order node ids (capacity 2m - 1)
};

// ---------------------------------------------------------------------------------------------
// Tile-to-worker assignment. For every policy, each tile index appears in exactly one worker's
// list, once; a worker's list is the order it processes its tiles in.

struct Assignment {
  std::vector<std::vector<int32_t>> tiles;  // per worker: tile indices, in processing order
  std::vector<double> predicted_load;       // per worker: sum of the estimates of its tiles
  double PredictedMakespan() const;         // max predicted_load (0 for no workers)
};

// PBT-Greedy (§4): every tile goes to the worker it is affine to. Tiles untouched by a
// split-merge keep the previous frame's worker; when a splits into (a1, a2) and (b1, b2) merge
// into b, a1 gets a's worker, a2 gets b1's, b gets b2's. Each worker keeps exactly k tiles.
// A worker's tiles are listed in in-order (spatial) order.
Assignment AssignPbtGreedy(const Pbt& pbt);

// Each policy also fills a caller's Assignment: `out` is overwritten (the same result), and its
// vectors keep their capacity, so a call allocates nothing once each worker's list has held as
// many tiles as it gets (Greedy: k every frame; Random: floor or ceil(m/n); Visit: varies).
void AssignPbtGreedy(const Pbt& pbt, Assignment& out);

// PBT-Visit (§4): tiles follow the in-order visit of the tree, cut into n contiguous runs of
// about equal predicted load (tile i goes to worker floor(n * (P_i + e_i / 2) / E), P_i the sum
// of the estimates before i, E the total; runs of m / n tiles if E = 0). With balanced leaves
// this is k tiles per worker, and a worker keeps a spatially compact region frame to frame.
Assignment AssignPbtVisit(const Pbt& pbt);
void AssignPbtVisit(const Pbt& pbt, Assignment& out);

// Random assignment: a seeded random permutation of the tiles dealt round-robin (each worker
// gets floor(m/n) or ceil(m/n) tiles). PBT-Random (§5) calls it each frame on the updated PBT
// (estimates = pbt.Estimates()); the static random baseline of §5 keeps a Pbt that is never
// updated and calls it with the same seed every frame. Deterministic for a seed on every
// platform (mt19937_64, own Fisher-Yates). Throws rs::Error if num_workers < 1.
Assignment AssignRandom(std::span<const double> estimates, int num_workers, uint64_t seed);
void AssignRandom(std::span<const double> estimates, int num_workers, uint64_t seed,
                  Assignment& out);
Assignment AssignPbtRandom(const Pbt& pbt, uint64_t seed);

// Not in the paper, for comparison: longest-processing-time-first list scheduling (tiles by
// decreasing estimate, ties by index, each onto the least-loaded worker, ties by id).
Assignment AssignLpt(std::span<const double> estimates, int num_workers);
// The same into `out`, with `order` as the sort's scratch: allocates nothing once out's lists
// and order have held as many tiles.
void AssignLpt(std::span<const double> estimates, int num_workers, Assignment& out,
               std::vector<int32_t>& order);

// The §2 master-worker execution, demand driven, with the §4 affinity as preference (a model of
// the frame, not a scheduler): all workers start at time 0; a worker that becomes free (earliest
// first, ties by id) takes the next tile of its own list in `affinity`; when its list is empty,
// the master gives it the last tile still waiting in the list of the worker with the most
// waiting predicted work (estimates; ties by id), so the donor keeps its spatial order. A tile
// takes tile_times[t]. Throws rs::Error if the sizes differ or a tile index is out of range.
struct DemandDrivenRun {
  std::vector<std::vector<int32_t>> executed;  // per worker: tiles in execution order
  std::vector<double> finish;                  // per worker: busy time (no idle gaps)
  size_t non_affine = 0;                       // tiles run by a worker they were not affine to
};
DemandDrivenRun SimulateDemandDriven(const Assignment& affinity, std::span<const double> estimates,
                                     std::span<const double> tile_times);

// The §2 master handing a frame's tiles out on request in PBT order, with the §4 affinity as the
// preference ("when a worker asks for a tile the master node tries to assign an affine tile"):
// requester r (of R) is affine to the tiles whose list v has v % R == r; a request gets the
// first waiting tile affine to it in PBT order (tile index = the in-order leaf), else the first
// waiting tile in PBT order. Every tile is handed out once per Load. One master: not
// thread-safe (the tiles backend's render threads call Next under one lock). Next and Waiting
// never allocate; Load allocates only when the tile or requester count grows.
class DemandMaster {
 public:
  // owner: per tile the list holding it (TilePlanFrame::owner), each >= 0; requesters >= 1.
  // Throws rs::Error naming the tile or the count.
  void Load(std::span<const int32_t> owner, int requesters);
  // The next tile for requester r in [0, requesters) (assert), or -1 when none is left;
  // *affine: the tile is one of r's.
  int32_t Next(int requester, bool* affine);
  size_t Waiting() const { return waiting_; }

 private:
  std::vector<int32_t> affine_;  // tile indices grouped by requester, each group in PBT order
  std::vector<size_t> group_;    // requester r's group: affine_[group_[r], group_[r + 1])
  std::vector<size_t> cursor_;   // per requester: its first position not known to be taken
  std::vector<uint8_t> taken_;   // per tile
  size_t next_ = 0;              // the first tile index not known to be taken
  size_t waiting_ = 0;
};

// The §2 frame model of a DemandMaster: `requesters` workers free at time 0; the earliest free
// (ties by id) asks for a tile and is busy for its tile_times[t]. Throws rs::Error if the sizes
// differ (and as DemandMaster::Load).
DemandDrivenRun SimulateDemandMaster(std::span<const int32_t> owner, int requesters,
                                     std::span<const double> tile_times);

// Both frame models with their state kept between calls (the tile plan runs one a frame):
// Driven / Master give the finish times and non_affine of SimulateDemandDriven /
// SimulateDemandMaster (bit-identical), but not the executed lists (left empty), and allocate
// only when the worker or tile count grows. The result is valid until the next call. Throws as
// those.
class DemandDrivenModel {
 public:
  const DemandDrivenRun& Driven(const Assignment& affinity, std::span<const double> estimates,
                                std::span<const double> tile_times);
  const DemandDrivenRun& Master(std::span<const int32_t> owner, int requesters,
                                std::span<const double> tile_times);

 private:
  friend DemandDrivenRun SimulateDemandDriven(const Assignment&, std::span<const double>,
                                              std::span<const double>);
  friend DemandDrivenRun SimulateDemandMaster(std::span<const int32_t>, int,
                                              std::span<const double>);
  template <class NextTile>
  void Run(size_t n, std::span<const double> tile_times, NextTile next);

  bool keep_executed_ = false;  // the Simulate* functions record DemandDrivenRun::executed
  DemandDrivenRun run_;
  std::vector<std::pair<double, size_t>> free_at_;  // min-heap: (time a worker is free, worker)
  std::vector<size_t> head_, tail_;  // Driven: per worker, its waiting tiles in affinity.tiles[w]
  std::vector<double> waiting_load_;  // Driven: per worker, the estimates of its waiting tiles
  DemandMaster master_;
};

// ---------------------------------------------------------------------------------------------
// Measures.

// sigma^2 = (1/m) sum (e_i - mu)^2, mu the mean (two-pass); 0 for an empty span.
double LeafVariance(std::span<const double> estimates);

// Relative prediction error of §5 / Table 1: |predicted - measured| / measured. 0 if both are
// 0; +inf if measured is 0 and predicted is not.
double PredictionError(double predicted, double measured);

// Table 1: the share of tiles whose estimate has an error up to 5 %, 10 % and 15 % (the
// paper's rows "95th", "90th", "85th percentile"). Error <= x is tested with a 1e-9 relative
// slack so decimal inputs such as 1.1 vs 1.0 count as 10 %. Shares are in [0, 1]; all 0 for no
// tiles. Throws rs::Error if the sizes differ.
struct PredictionAccuracy {
  size_t tiles = 0;
  double within5 = 0.0;
  double within10 = 0.0;
  double within15 = 0.0;
};
PredictionAccuracy MeasurePredictionAccuracy(std::span<const double> predicted,
                                             std::span<const double> measured);

// Per-worker time: the sum of tile_times over the worker's tiles. Throws rs::Error if a tile
// index is out of range.
std::vector<double> WorkerTimes(const Assignment& assignment, std::span<const double> tile_times);

// Frame imbalance: slowest worker / mean worker time (>= 1; 1 if the mean is 0 or no workers).
double FrameImbalance(std::span<const double> worker_times);

}  // namespace rs
