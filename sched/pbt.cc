// Prediction Binary Tree: construction, PBT-Update (Algorithm 1 of Cosenza et al., §3), the §4
// tile assignments and the §5 measures. Plain scalar code run once per frame by the master.
#include "sched/pbt.h"

#include <algorithm>
#include <cassert>
#include <cmath>
#include <cstdio>
#include <functional>
#include <limits>
#include <numeric>
#include <random>
#include <string>
#include <utility>

#include "include/raystream/raystream.h"

namespace rs {
namespace {

PbtAxis Other(PbtAxis axis) { return axis == PbtAxis::kX ? PbtAxis::kY : PbtAxis::kX; }

int Extent(const Tile& t, PbtAxis axis) { return axis == PbtAxis::kX ? t.Width() : t.Height(); }

// Cuts `t` along `axis` after `first` pixels (0 < first < extent) into the two children.
void Cut(const Tile& t, PbtAxis axis, int first, Tile& a, Tile& b) {
  a = t;
  b = t;
  if (axis == PbtAxis::kX) {
    a.x1 = t.x0 + first;
    b.x0 = a.x1;
  } else {
    a.y1 = t.y0 + first;
    b.y0 = a.y1;
  }
}

std::string TileString(const Tile& t) {
  char buf[96];
  std::snprintf(buf, sizeof(buf), "[%d,%d)x[%d,%d)", t.x0, t.x1, t.y0, t.y1);
  return buf;
}

bool SameTile(const Tile& a, const Tile& b) {
  return a.x0 == b.x0 && a.y0 == b.y0 && a.x1 == b.x1 && a.y1 == b.y1;
}

// Empties a's lists for num_workers workers, keeping every vector's capacity.
void ResetAssignment(int num_workers, Assignment& a) {
  a.tiles.resize(static_cast<size_t>(num_workers));
  for (std::vector<int32_t>& list : a.tiles) list.clear();
  a.predicted_load.assign(static_cast<size_t>(num_workers), 0.0);
}

void Give(Assignment& a, size_t worker, size_t tile, double estimate) {
  a.tiles[worker].push_back(static_cast<int32_t>(tile));
  a.predicted_load[worker] += estimate;
}

// sigma^2 of value(0), ..., value(m - 1): two passes in index order.
template <class Value>
double TwoPassVariance(size_t m, Value value) {
  if (m == 0) return 0.0;
  const double count = static_cast<double>(m);
  double sum = 0.0;
  for (size_t i = 0; i < m; ++i) sum += value(i);
  const double mean = sum / count;
  double sq = 0.0;
  for (size_t i = 0; i < m; ++i) sq += (value(i) - mean) * (value(i) - mean);
  return sq / count;
}

}  // namespace

// ---------------------------------------------------------------------------------------------
// Construction.

Pbt::Pbt(int width, int height, int num_workers, int tiles_per_worker)
    : width_(width),
      height_(height),
      num_workers_(num_workers),
      tiles_per_worker_(tiles_per_worker) {
  if (width < 1 || height < 1) {
    throw Error("Pbt: image size " + std::to_string(width) + "x" + std::to_string(height) +
                " must be at least 1x1");
  }
  const int64_t pixels = int64_t{width} * height;
  if (pixels >= (int64_t{1} << 31)) {
    throw Error("Pbt: image " + std::to_string(width) + "x" + std::to_string(height) +
                " has 2^31 or more pixels");
  }
  if (num_workers < 1) throw Error("Pbt: num_workers " + std::to_string(num_workers) + " < 1");
  if (tiles_per_worker < 1) {
    throw Error("Pbt: tiles_per_worker " + std::to_string(tiles_per_worker) + " < 1");
  }
  const int64_t m = int64_t{num_workers} * tiles_per_worker;
  if (m > pixels) {
    throw Error("Pbt: " + std::to_string(m) + " tiles (num_workers " + std::to_string(num_workers) +
                " x tiles_per_worker " + std::to_string(tiles_per_worker) + ") exceed the " +
                std::to_string(pixels) + " pixels of a " + std::to_string(width) + "x" +
                std::to_string(height) + " image");
  }
  root_axis_ = width >= height ? PbtAxis::kX : PbtAxis::kY;
  // Every buffer at its bound: a split-merge frees two nodes and takes them again, so the node
  // count stays 2m - 1 and Update never allocates.
  const size_t bound = static_cast<size_t>(2 * m - 1);
  nodes_.reserve(bound);
  free_.reserve(2);
  leaves_.reserve(static_cast<size_t>(m));
  stack_.reserve(bound);  // each node is pushed once per walk
  order_.reserve(bound);
  const int32_t root = NewNode();
  nodes_[static_cast<size_t>(root)].tile = Tile{0, 0, width, height};
  Build(root, static_cast<int>(m));
  RebuildLeafOrder();
  // Initial affinity: runs of k in-order leaves per worker (spatially compact, §4).
  for (size_t i = 0; i < leaves_.size(); ++i) {
    nodes_[static_cast<size_t>(leaves_[i])].worker =
        static_cast<int32_t>(i / static_cast<size_t>(tiles_per_worker_));
  }
}

int32_t Pbt::NewNode() {
  if (!free_.empty()) {
    const int32_t id = free_.back();
    free_.pop_back();
    nodes_[static_cast<size_t>(id)] = PbtNode{};
    return id;
  }
  nodes_.emplace_back();
  return static_cast<int32_t>(nodes_.size() - 1);
}

// Initial tree: a node with q >= 2 leaves below it is cut along its depth's axis (the other if
// that extent is 1) at the position proportional to floor(q/2) : ceil(q/2), and the leaf counts
// are then clamped so each side has at least as many pixels as leaves (possible since the
// node has >= q pixels). Recursion depth <= m (each level has >= 2 leaves per node).
void Pbt::Build(int32_t id, int num_leaves) {
  if (num_leaves <= 1) return;
  const PbtNode node = nodes_[static_cast<size_t>(id)];
  const PbtAxis axis = SplitAxis(node);
  const int extent = Extent(node.tile, axis);
  const int64_t across = Extent(node.tile, Other(axis));
  const int q1_ideal = num_leaves / 2;
  int first = static_cast<int>(
      std::lround(static_cast<double>(extent) * q1_ideal / static_cast<double>(num_leaves)));
  first = std::clamp(first, 1, extent - 1);
  const int64_t area0 = int64_t{first} * across;
  const int64_t area1 = int64_t{extent - first} * across;
  const int64_t q1 = std::clamp<int64_t>(q1_ideal, std::max<int64_t>(1, num_leaves - area1),
                                         std::min<int64_t>(area0, num_leaves - 1));
  Tile t0, t1;
  Cut(node.tile, axis, first, t0, t1);
  const int32_t c0 = NewNode();
  const int32_t c1 = NewNode();
  PbtNode& n = nodes_[static_cast<size_t>(id)];
  n.axis = axis;
  n.child[0] = c0;
  n.child[1] = c1;
  for (int s = 0; s < 2; ++s) {
    PbtNode& c = nodes_[static_cast<size_t>(n.child[s])];
    c.tile = s == 0 ? t0 : t1;
    c.parent = id;
    c.depth = n.depth + 1;
  }
  Build(c0, static_cast<int>(q1));
  Build(c1, num_leaves - static_cast<int>(q1));
}

// §3: children of nodes on alternating levels are cut along alternating axes; the root uses
// root_axis_. A node that is 1 pixel along its level's axis uses the other one.
PbtAxis Pbt::SplitAxis(const PbtNode& node) const {
  const PbtAxis preferred = (node.depth % 2 == 0) ? root_axis_ : Other(root_axis_);
  return Extent(node.tile, preferred) >= 2 ? preferred : Other(preferred);
}

void Pbt::SplitTiles(const PbtNode& node, Tile& t0, Tile& t1) const {
  const PbtAxis axis = SplitAxis(node);
  Cut(node.tile, axis, Extent(node.tile, axis) / 2, t0, t1);
}

// Algorithm 1, lines 11-13: a leaf becomes inner; each half predicts e(a) / 2 (the paper), or
// e0 and e1 (a predictor's).
void Pbt::SplitLeaf(int32_t id, double e0, double e1) {
  const PbtNode node = nodes_[static_cast<size_t>(id)];
  const PbtAxis axis = SplitAxis(node);
  Tile t0, t1;
  SplitTiles(node, t0, t1);
  const int32_t c0 = NewNode();
  const int32_t c1 = NewNode();
  PbtNode& n = nodes_[static_cast<size_t>(id)];
  n.axis = axis;
  n.child[0] = c0;
  n.child[1] = c1;
  const bool halves = e0 < 0.0 || e1 < 0.0;
  for (int s = 0; s < 2; ++s) {
    PbtNode& c = nodes_[static_cast<size_t>(n.child[s])];
    c.tile = s == 0 ? t0 : t1;
    c.parent = id;
    c.depth = n.depth + 1;
    // e(a) / 2 is exact in binary floating point (barring subnormals).
    c.estimate = halves ? n.estimate * 0.5 : (s == 0 ? e0 : e1);
    c.measured = n.measured * 0.5;
    c.worker = n.worker;  // the caller sets the §4 affinities
  }
  if (!halves) n.estimate = e0 + e1;
}

void Pbt::RebuildLeafOrder() {
  leaves_.clear();
  stack_.assign(1, Root());
  while (!stack_.empty()) {
    const int32_t id = stack_.back();
    stack_.pop_back();
    const PbtNode& n = nodes_[static_cast<size_t>(id)];
    if (n.IsLeaf()) {
      leaves_.push_back(id);
    } else {
      stack_.push_back(n.child[1]);
      stack_.push_back(n.child[0]);
    }
  }
}

void Pbt::RecomputeSums() {
  // Pre-order list, then children before parents by walking it backwards.
  order_.clear();
  stack_.assign(1, Root());
  while (!stack_.empty()) {
    const int32_t id = stack_.back();
    stack_.pop_back();
    order_.push_back(id);
    const PbtNode& n = nodes_[static_cast<size_t>(id)];
    if (!n.IsLeaf()) {
      stack_.push_back(n.child[1]);
      stack_.push_back(n.child[0]);
    }
  }
  for (auto it = order_.rbegin(); it != order_.rend(); ++it) {
    PbtNode& n = nodes_[static_cast<size_t>(*it)];
    if (n.IsLeaf()) continue;
    const PbtNode& c0 = nodes_[static_cast<size_t>(n.child[0])];
    const PbtNode& c1 = nodes_[static_cast<size_t>(n.child[1])];
    n.estimate = c0.estimate + c1.estimate;
    n.measured = c0.measured + c1.measured;
  }
}

// ---------------------------------------------------------------------------------------------
// Queries.

std::vector<Tile> Pbt::Tiles() const {
  std::vector<Tile> out;
  Tiles(out);
  return out;
}

std::vector<double> Pbt::Estimates() const {
  std::vector<double> out;
  Estimates(out);
  return out;
}

void Pbt::Tiles(std::vector<Tile>& out) const {
  out.resize(leaves_.size());
  for (size_t i = 0; i < leaves_.size(); ++i) out[i] = LeafTile(i);
}

void Pbt::Estimates(std::vector<double>& out) const {
  out.resize(leaves_.size());
  for (size_t i = 0; i < leaves_.size(); ++i) out[i] = LeafEstimate(i);
}

std::vector<int32_t> Pbt::LeafWorkers() const {
  std::vector<int32_t> out;
  out.reserve(leaves_.size());
  for (const int32_t id : leaves_) out.push_back(Node(id).worker);
  return out;
}

double Pbt::Variance() const {
  return TwoPassVariance(leaves_.size(), [&](size_t i) { return LeafEstimate(i); });
}

// ---------------------------------------------------------------------------------------------
// PBT-Update.

void Pbt::SetMeasuredTimes(std::span<const double> times) {
  if (times.size() != leaves_.size()) {
    throw Error("Pbt::SetMeasuredTimes: " + std::to_string(times.size()) + " times for " +
                std::to_string(leaves_.size()) + " tiles");
  }
  for (size_t i = 0; i < times.size(); ++i) {
    if (!std::isfinite(times[i]) || times[i] < 0.0) {
      throw Error("Pbt::SetMeasuredTimes: tile " + std::to_string(i) + " " +
                  TileString(LeafTile(i)) + " has time " + std::to_string(times[i]) +
                  " (must be finite and >= 0)");
    }
  }
  // Algorithm 1, lines 2-4: e(l) <- t(l).
  for (size_t i = 0; i < times.size(); ++i) {
    PbtNode& n = nodes_[static_cast<size_t>(leaves_[i])];
    n.measured = times[i];
    n.estimate = times[i];
  }
  RecomputeSums();
}

PbtUpdateStats Pbt::Update(std::span<const double> times, const PbtUpdateOptions& options) {
  SetMeasuredTimes(times);
  return Update(options);
}

PbtUpdateStats Pbt::Update(std::span<const double> times, const PbtPredictor& predictor,
                           const PbtUpdateOptions& options) {
  SetMeasuredTimes(times);
  for (const int32_t id : leaves_) {
    PbtNode& n = nodes_[static_cast<size_t>(id)];
    n.estimate = predictor.Predict(n.tile);
  }
  RecomputeSums();
  return Run(options, &predictor);
}

PbtUpdateStats Pbt::Update(const PbtUpdateOptions& options) { return Run(options, nullptr); }

// Algorithm 1 (§3), lines 5-17. Each split-merge replaces (a, b1, b2) by (a/2, a/2, b1 + b2):
// the sum and m are unchanged, and sum e^2 drops by (e(a)^2 - 4 e(b1) e(b2)) / 2, so m sigma^2
// drops by the same amount; the loop runs only while that is > 0, so the variance strictly
// decreases (the paper's termination argument). Two deviations make the algorithm well defined:
//  - Line 6 takes the costliest leaf that can be split (>= 2 pixels); a 1x1 leaf cannot be. The
//    variance argument holds for any a, not only the maximum.
//  - Line 7 skips the sibling pair that contains a (splitting a and merging it with its sibling
//    at once is contradictory; the paper leaves the case open, e.g. m = 2 with one costly
//    tile). With no such pair (m <= 2, or the only pair contains a) the tree is final.
// Ties go to the first leaf / pair in in-order. The §4 PBT-Greedy affinities follow the paper:
// a1 <- worker(a), a2 <- worker(b1), b <- worker(b2), so every worker keeps k leaves.
// With a predictor the halves are predicted and the stopping test is the exact variance drop
// (pbt.h); the termination argument is the same.
PbtUpdateStats Pbt::Run(const PbtUpdateOptions& options, const PbtPredictor* predictor) {
  if (options.max_steps < 0) {
    throw Error("Pbt::Update: max_steps " + std::to_string(options.max_steps) + " < 0");
  }
  const int64_t m = static_cast<int64_t>(leaves_.size());
  const int64_t max_steps = options.max_steps > 0 ? options.max_steps : 16 * m + 64;
  PbtUpdateStats stats;
  stats.variance_before = Variance();
  for (;;) {
    // Line 6: l_a = argmax e(l) over the splittable leaves.
    int32_t a = -1;
    for (const int32_t id : leaves_) {
      const PbtNode& n = Node(id);
      if (n.tile.NumPixels() < 2) continue;
      if (a < 0 || n.estimate > Node(a).estimate) a = id;
    }
    if (a < 0) break;
    // Line 7: (l_b1, l_b2) = the sibling leaves minimizing e(b1) e(b2), a excluded. A pair is
    // visited once, from its first child.
    int32_t pair_parent = -1;
    double best = 0.0;
    for (const int32_t id : leaves_) {
      const PbtNode& n = Node(id);
      if (n.parent < 0) continue;
      const PbtNode& p = Node(n.parent);
      if (p.child[0] != id || !Node(p.child[1]).IsLeaf()) continue;
      if (id == a || p.child[1] == a) continue;
      const double product = n.estimate * Node(p.child[1]).estimate;
      if (pair_parent < 0 || product < best) {
        pair_parent = n.parent;
        best = product;
      }
    }
    if (pair_parent < 0) break;
    // Line 8: stop when e(a)^2 <= 4 e(b1) e(b2) (true for e(a) = 0, and for overflow to inf);
    // with a predictor when e(a1) e(a2) <= e(b1) e(b2).
    double e0 = -1.0, e1 = -1.0;
    if (predictor != nullptr) {
      Tile t0, t1;
      SplitTiles(Node(a), t0, t1);
      e0 = predictor->Predict(t0);
      e1 = predictor->Predict(t1);
      if (e0 * e1 <= best) break;
    } else {
      const double ea = Node(a).estimate;
      if (ea * ea <= 4.0 * best) break;
    }
    if (stats.steps >= max_steps) {
      stats.hit_step_bound = true;
      break;
    }
    // Lines 14-15: merge b1, b2 into their parent b (first, so the split reuses their ids).
    PbtNode& b = nodes_[static_cast<size_t>(pair_parent)];
    const PbtNode b1 = Node(b.child[0]);
    const PbtNode b2 = Node(b.child[1]);
    free_.push_back(b.child[1]);
    free_.push_back(b.child[0]);
    b.child[0] = -1;
    b.child[1] = -1;
    b.estimate = b1.estimate + b2.estimate;
    b.measured = b1.measured + b2.measured;
    b.worker = b2.worker;
    // Lines 11-13: split a into a1, a2 with e(a) / 2 each (or their predictions).
    SplitLeaf(a, e0, e1);
    const PbtNode& an = Node(a);
    nodes_[static_cast<size_t>(an.child[0])].worker = an.worker;
    nodes_[static_cast<size_t>(an.child[1])].worker = b1.worker;
    ++stats.steps;
    RebuildLeafOrder();
  }
  RecomputeSums();
  stats.variance_after = Variance();
  return stats;
}

// ---------------------------------------------------------------------------------------------
// Self-check.

std::string Pbt::Validate() const {
  if (nodes_.empty()) return "no nodes";
  const PbtNode& root = Node(Root());
  if (root.parent != -1 || !SameTile(root.tile, Tile{0, 0, width_, height_})) {
    return "root " + TileString(root.tile) + " is not the image";
  }
  const size_t m = static_cast<size_t>(num_workers_) * static_cast<size_t>(tiles_per_worker_);
  std::vector<int> per_worker(static_cast<size_t>(num_workers_), 0);
  size_t leaves = 0;
  std::vector<int32_t> stack{Root()};
  while (!stack.empty()) {
    const int32_t id = stack.back();
    stack.pop_back();
    const PbtNode& n = Node(id);
    const std::string where = "node " + std::to_string(id) + " " + TileString(n.tile);
    if (n.tile.NumPixels() == 0) return where + " is empty";
    if (n.IsLeaf()) {
      if (n.child[1] != -1) return where + " has only one child";
      if (leaves >= leaves_.size() || leaves_[leaves] != id) return where + " out of leaf order";
      ++leaves;
      if (n.worker < 0 || n.worker >= num_workers_) return where + " has no worker";
      ++per_worker[static_cast<size_t>(n.worker)];
      continue;
    }
    const PbtNode& c0 = Node(n.child[0]);
    const PbtNode& c1 = Node(n.child[1]);
    if (c0.parent != id || c1.parent != id) return where + ": child with a wrong parent";
    if (c0.depth != n.depth + 1 || c1.depth != n.depth + 1) return where + ": child depth";
    Tile t0, t1;
    const int first = n.axis == PbtAxis::kX ? c0.tile.x1 - n.tile.x0 : c0.tile.y1 - n.tile.y0;
    if (first < 1 || first >= Extent(n.tile, n.axis)) return where + ": cut outside the tile";
    Cut(n.tile, n.axis, first, t0, t1);
    if (!SameTile(t0, c0.tile) || !SameTile(t1, c1.tile)) {
      return where + ": children " + TileString(c0.tile) + " " + TileString(c1.tile) +
             " do not partition it";
    }
    const double sum = c0.estimate + c1.estimate;
    if (std::abs(n.estimate - sum) > 1e-9 * std::max(1.0, std::abs(sum))) {
      return where + ": estimate is not the sum of its children";
    }
    stack.push_back(n.child[1]);
    stack.push_back(n.child[0]);
  }
  if (leaves != leaves_.size() || leaves != m) {
    return std::to_string(leaves) + " leaves, expected " + std::to_string(m);
  }
  for (size_t w = 0; w < per_worker.size(); ++w) {
    if (per_worker[w] != tiles_per_worker_) {
      return "worker " + std::to_string(w) + " holds " + std::to_string(per_worker[w]) +
             " leaves, expected " + std::to_string(tiles_per_worker_);
    }
  }
  return "";
}

// ---------------------------------------------------------------------------------------------
// Assignments.

double Assignment::PredictedMakespan() const {
  double best = 0.0;
  for (const double load : predicted_load) best = std::max(best, load);
  return best;
}

Assignment AssignPbtGreedy(const Pbt& pbt) {
  Assignment a;
  AssignPbtGreedy(pbt, a);
  return a;
}

void AssignPbtGreedy(const Pbt& pbt, Assignment& a) {
  ResetAssignment(pbt.num_workers(), a);
  const auto leaves = pbt.LeafNodes();
  for (size_t i = 0; i < leaves.size(); ++i) {
    Give(a, static_cast<size_t>(pbt.Node(leaves[i]).worker), i, pbt.LeafEstimate(i));
  }
}

Assignment AssignPbtVisit(const Pbt& pbt) {
  Assignment a;
  AssignPbtVisit(pbt, a);
  return a;
}

void AssignPbtVisit(const Pbt& pbt, Assignment& a) {
  const size_t n = static_cast<size_t>(pbt.num_workers());
  const size_t m = pbt.NumLeaves();
  ResetAssignment(pbt.num_workers(), a);
  double total = 0.0;
  for (size_t i = 0; i < m; ++i) total += pbt.LeafEstimate(i);
  double prefix = 0.0;
  for (size_t i = 0; i < m; ++i) {
    const double e = pbt.LeafEstimate(i);
    size_t w;
    if (total > 0.0) {
      const double mid = (prefix + 0.5 * e) / total;  // in [0, 1], non-decreasing in i
      w = std::min(n - 1, static_cast<size_t>(mid * static_cast<double>(n)));
    } else {
      w = i * n / m;
    }
    Give(a, w, i, e);
    prefix += e;
  }
}

Assignment AssignRandom(std::span<const double> estimates, int num_workers, uint64_t seed) {
  Assignment a;
  AssignRandom(estimates, num_workers, seed, a);
  return a;
}

void AssignRandom(std::span<const double> estimates, int num_workers, uint64_t seed,
                  Assignment& a) {
  if (num_workers < 1) throw Error("AssignRandom: num_workers " + std::to_string(num_workers));
  const size_t m = estimates.size();
  const size_t n = static_cast<size_t>(num_workers);
  // The permutation is dealt round-robin, so it is kept in the lists themselves: position r of
  // the permutation is a.tiles[r % n][r / n]. Start from the identity.
  ResetAssignment(num_workers, a);
  for (size_t r = 0; r < m; ++r) a.tiles[r % n].push_back(static_cast<int32_t>(r));
  const auto at = [&](size_t r) -> int32_t& { return a.tiles[r % n][r / n]; };
  // Fisher-Yates with a modulo draw: mt19937_64 is specified by the standard, unlike
  // std::shuffle / uniform_int_distribution, so the result is the same everywhere.
  std::mt19937_64 rng(seed);
  for (size_t i = m; i > 1; --i) {
    const size_t j = static_cast<size_t>(rng() % i);
    std::swap(at(i - 1), at(j));
  }
  // Each worker's load summed in its list order (the order the tiles were dealt to it).
  for (size_t w = 0; w < n; ++w) {
    for (const int32_t t : a.tiles[w]) a.predicted_load[w] += estimates[static_cast<size_t>(t)];
  }
}

Assignment AssignPbtRandom(const Pbt& pbt, uint64_t seed) {
  return AssignRandom(pbt.Estimates(), pbt.num_workers(), seed);
}

Assignment AssignLpt(std::span<const double> estimates, int num_workers) {
  Assignment a;
  std::vector<int32_t> order;
  AssignLpt(estimates, num_workers, a, order);
  return a;
}

void AssignLpt(std::span<const double> estimates, int num_workers, Assignment& a,
               std::vector<int32_t>& order) {
  if (num_workers < 1) throw Error("AssignLpt: num_workers " + std::to_string(num_workers));
  order.resize(estimates.size());
  std::iota(order.begin(), order.end(), int32_t{0});
  // Decreasing estimate, ties by index: a strict total order, so std::sort gives what a stable
  // sort on the estimate alone gives, without its temporary buffer.
  std::sort(order.begin(), order.end(), [&](int32_t x, int32_t y) {
    const double ex = estimates[static_cast<size_t>(x)], ey = estimates[static_cast<size_t>(y)];
    return ex != ey ? ex > ey : x < y;
  });
  ResetAssignment(num_workers, a);
  for (const int32_t t : order) {
    const size_t i = static_cast<size_t>(t);
    const size_t w =
        static_cast<size_t>(std::min_element(a.predicted_load.begin(), a.predicted_load.end()) -
                            a.predicted_load.begin());
    Give(a, w, i, estimates[i]);
  }
}

// The §2 frame: n workers free at time 0; the one free first (ties by id) asks next(w, &affine)
// for a tile (-1: nothing left, the worker is done) and is busy for tile_times[t]. free_at_ is a
// min-heap kept as std::priority_queue keeps its vector (push_heap / pop_heap, std::greater).
template <class NextTile>
void DemandDrivenModel::Run(size_t n, std::span<const double> tile_times, NextTile next) {
  using Event = std::pair<double, size_t>;  // (time the worker becomes free, worker)
  const std::greater<Event> later;
  run_.executed.resize(keep_executed_ ? n : 0);
  for (std::vector<int32_t>& list : run_.executed) list.clear();
  run_.finish.assign(n, 0.0);
  run_.non_affine = 0;
  free_at_.clear();
  for (size_t w = 0; w < n; ++w) {
    free_at_.push_back({0.0, w});
    std::push_heap(free_at_.begin(), free_at_.end(), later);
  }
  while (!free_at_.empty()) {
    std::pop_heap(free_at_.begin(), free_at_.end(), later);
    const auto [now, w] = free_at_.back();
    free_at_.pop_back();
    bool affine = true;
    const int32_t tile = next(w, &affine);
    if (tile < 0) continue;  // nothing left: this worker is done
    if (!affine) ++run_.non_affine;
    if (keep_executed_) run_.executed[w].push_back(tile);
    run_.finish[w] = now + tile_times[static_cast<size_t>(tile)];
    free_at_.push_back({run_.finish[w], w});
    std::push_heap(free_at_.begin(), free_at_.end(), later);
  }
}

const DemandDrivenRun& DemandDrivenModel::Driven(const Assignment& affinity,
                                                 std::span<const double> estimates,
                                                 std::span<const double> tile_times) {
  if (estimates.size() != tile_times.size()) {
    throw Error("SimulateDemandDriven: " + std::to_string(estimates.size()) + " estimates for " +
                std::to_string(tile_times.size()) + " tile times");
  }
  const size_t n = affinity.tiles.size();
  // Worker w's waiting tiles: affinity.tiles[w][head_[w], tail_[w]); it takes its own from the
  // front, a thief from the back.
  head_.assign(n, 0);
  tail_.resize(n);
  waiting_load_.assign(n, 0.0);
  for (size_t w = 0; w < n; ++w) {
    for (const int32_t t : affinity.tiles[w]) {
      if (t < 0 || static_cast<size_t>(t) >= tile_times.size()) {
        throw Error("SimulateDemandDriven: worker " + std::to_string(w) + " has tile " +
                    std::to_string(t) + " of " + std::to_string(tile_times.size()));
      }
      waiting_load_[w] += estimates[static_cast<size_t>(t)];
    }
    tail_[w] = affinity.tiles[w].size();
  }
  Run(n, tile_times, [&](size_t w, bool* affine) -> int32_t {
    size_t donor = w;
    if (head_[w] == tail_[w]) {
      donor = n;
      for (size_t v = 0; v < n; ++v) {
        if (head_[v] != tail_[v] && (donor == n || waiting_load_[v] > waiting_load_[donor])) {
          donor = v;
        }
      }
      if (donor == n) return -1;
    }
    int32_t tile;
    if (donor == w) {
      tile = affinity.tiles[w][head_[w]++];
    } else {
      tile = affinity.tiles[donor][--tail_[donor]];
      *affine = false;
    }
    waiting_load_[donor] -= estimates[static_cast<size_t>(tile)];
    return tile;
  });
  return run_;
}

const DemandDrivenRun& DemandDrivenModel::Master(std::span<const int32_t> owner, int requesters,
                                                 std::span<const double> tile_times) {
  if (owner.size() != tile_times.size()) {
    throw Error("SimulateDemandMaster: " + std::to_string(owner.size()) + " tiles for " +
                std::to_string(tile_times.size()) + " tile times");
  }
  master_.Load(owner, requesters);
  Run(static_cast<size_t>(requesters), tile_times, [&](size_t w, bool* affine) {
    return master_.Next(static_cast<int>(w), affine);
  });
  return run_;
}

DemandDrivenRun SimulateDemandDriven(const Assignment& affinity, std::span<const double> estimates,
                                     std::span<const double> tile_times) {
  DemandDrivenModel model;
  model.keep_executed_ = true;
  return model.Driven(affinity, estimates, tile_times);
}

void DemandMaster::Load(std::span<const int32_t> owner, int requesters) {
  if (requesters < 1) {
    throw Error("DemandMaster: " + std::to_string(requesters) + " requesters (need at least 1)");
  }
  const size_t m = owner.size();
  const size_t r_count = static_cast<size_t>(requesters);
  group_.assign(r_count + 1, 0);
  for (size_t t = 0; t < m; ++t) {
    if (owner[t] < 0) {
      throw Error("DemandMaster: tile " + std::to_string(t) + " has no list (owner " +
                  std::to_string(owner[t]) + ")");
    }
    ++group_[static_cast<size_t>(owner[t]) % r_count + 1];
  }
  for (size_t r = 0; r < r_count; ++r) group_[r + 1] += group_[r];
  // Counting sort by requester, tiles in increasing index: each group is in PBT order.
  cursor_.assign(group_.begin(), group_.end() - 1);
  affine_.resize(m);
  for (size_t t = 0; t < m; ++t) {
    affine_[cursor_[static_cast<size_t>(owner[t]) % r_count]++] = static_cast<int32_t>(t);
  }
  cursor_.assign(group_.begin(), group_.end() - 1);
  taken_.assign(m, 0);
  next_ = 0;
  waiting_ = m;
}

int32_t DemandMaster::Next(int requester, bool* affine) {
  assert(requester >= 0 && static_cast<size_t>(requester) + 1 < group_.size());
  const size_t r = static_cast<size_t>(requester);
  // Positions before a cursor are taken, so each cursor only moves forward: O(m + R) a frame.
  size_t& mine = cursor_[r];
  while (mine < group_[r + 1] && taken_[static_cast<size_t>(affine_[mine])] != 0) ++mine;
  size_t tile;
  if (mine < group_[r + 1]) {
    tile = static_cast<size_t>(affine_[mine++]);
    *affine = true;
  } else {
    while (next_ < taken_.size() && taken_[next_] != 0) ++next_;
    if (next_ == taken_.size()) return -1;
    tile = next_++;
    *affine = false;
  }
  taken_[tile] = 1;
  --waiting_;
  return static_cast<int32_t>(tile);
}

DemandDrivenRun SimulateDemandMaster(std::span<const int32_t> owner, int requesters,
                                     std::span<const double> tile_times) {
  DemandDrivenModel model;
  model.keep_executed_ = true;
  return model.Master(owner, requesters, tile_times);
}

// ---------------------------------------------------------------------------------------------
// Measures.

double LeafVariance(std::span<const double> estimates) {
  return TwoPassVariance(estimates.size(), [&](size_t i) { return estimates[i]; });
}

double PredictionError(double predicted, double measured) {
  if (measured == 0.0) {
    return predicted == 0.0 ? 0.0 : std::numeric_limits<double>::infinity();
  }
  return std::abs(predicted - measured) / std::abs(measured);
}

PredictionAccuracy MeasurePredictionAccuracy(std::span<const double> predicted,
                                             std::span<const double> measured) {
  if (predicted.size() != measured.size()) {
    throw Error("MeasurePredictionAccuracy: " + std::to_string(predicted.size()) +
                " predictions for " + std::to_string(measured.size()) + " measured tiles");
  }
  PredictionAccuracy acc;
  acc.tiles = predicted.size();
  if (acc.tiles == 0) return acc;
  constexpr double kSlack = 1.0 + 1e-9;
  size_t c5 = 0, c10 = 0, c15 = 0;
  for (size_t i = 0; i < predicted.size(); ++i) {
    const double err = PredictionError(predicted[i], measured[i]);  // NaN compares false: a miss
    c5 += err <= 0.05 * kSlack;
    c10 += err <= 0.10 * kSlack;
    c15 += err <= 0.15 * kSlack;
  }
  const double m = static_cast<double>(acc.tiles);
  acc.within5 = static_cast<double>(c5) / m;
  acc.within10 = static_cast<double>(c10) / m;
  acc.within15 = static_cast<double>(c15) / m;
  return acc;
}

std::vector<double> WorkerTimes(const Assignment& assignment, std::span<const double> tile_times) {
  std::vector<double> out(assignment.tiles.size(), 0.0);
  for (size_t w = 0; w < assignment.tiles.size(); ++w) {
    for (const int32_t t : assignment.tiles[w]) {
      if (t < 0 || static_cast<size_t>(t) >= tile_times.size()) {
        throw Error("WorkerTimes: worker " + std::to_string(w) + " has tile " + std::to_string(t) +
                    ", but there are " + std::to_string(tile_times.size()) + " tile times");
      }
      out[w] += tile_times[static_cast<size_t>(t)];
    }
  }
  return out;
}

double FrameImbalance(std::span<const double> worker_times) {
  if (worker_times.empty()) return 1.0;
  double sum = 0.0, slowest = 0.0;
  for (const double t : worker_times) {
    sum += t;
    slowest = std::max(slowest, t);
  }
  const double mean = sum / static_cast<double>(worker_times.size());
  return mean > 0.0 ? slowest / mean : 1.0;
}

}  // namespace rs
