// The `raystream` command: render a scene to an image, or print what a scene and its grid hold.
// Every user-input problem ends in one clear line on stderr and a non-zero exit status.
#include <CLI/CLI.hpp>
#ifdef RS_MIMALLOC
#include <mimalloc.h>
#endif
#include <fcntl.h>
#include <fmt/core.h>
#include <nlohmann/json.hpp>
#include <sys/resource.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <exception>
#include <optional>
#include <string>
#include <system_error>
#include <thread>
#include <vector>

#include "include/raystream/raystream.h"
#include "scenes/image_io.h"
#include "scenes/load.h"
#include "sched/backend.h"
#include "sched/backends.h"
#include "sched/render.h"
#include "sched/mpi_backend.h"     // --backend mpi
#include "sim/cell_renderer.h"  // --backend cell

namespace rs {
namespace {

using Json = nlohmann::ordered_json;

double Seconds(std::chrono::steady_clock::duration d) {
  return std::chrono::duration<double>(d).count();
}

Json FeaturesJson(const SceneFeatures& f) {
  return Json{{"lights", f.lights},           {"specular", f.specular},
              {"reflection", f.reflection},   {"transmission", f.transmission},
              {"textures", f.textures},       {"triangles", f.triangles},
              {"large", f.large}};
}

Json InfoJson(const Scene& scene, const AccelInfo& a) {
  const double per_occupied = a.occupied_cells ? double(a.references) / a.occupied_cells : 0.0;
  return Json{
      {"scene", scene.name},
      {"source", scene.source},
      {"triangles", a.triangles},
      {"vertices", scene.positions.size()},
      {"degenerate_triangles", a.degenerate_triangles},
      {"materials", scene.materials.size()},
      {"textures", scene.textures.size()},
      {"lights", scene.lights.size()},
      {"path_frames", scene.path.frames},
      // in the scene's own units (the grid is built on the NormalizeScale'd coordinates)
      {"bounds", {{"lo", {a.bounds_lo[0] / scene.coordinate_scale,
                          a.bounds_lo[1] / scene.coordinate_scale,
                          a.bounds_lo[2] / scene.coordinate_scale}},
                  {"hi", {a.bounds_hi[0] / scene.coordinate_scale,
                          a.bounds_hi[1] / scene.coordinate_scale,
                          a.bounds_hi[2] / scene.coordinate_scale}}}},
      {"coordinate_scale", scene.coordinate_scale},
      {"frame_shift", {a.frame_shift[0] / scene.coordinate_scale,
                       a.frame_shift[1] / scene.coordinate_scale,
                       a.frame_shift[2] / scene.coordinate_scale}},
      {"grid",
       {{"kind", a.kind},
        {"resolution", {a.resolution[0], a.resolution[1], a.resolution[2]}},
        {"cells", a.cells},
        {"occupied_cells", a.occupied_cells},
        {"occupied_fraction", a.cells ? double(a.occupied_cells) / a.cells : 0.0},
        {"references", a.references},
        {"triangles_per_occupied_cell", per_occupied},
        {"max_triangles_per_cell", a.max_per_cell},
        {"bytes", a.bytes},
        {"build_seconds", a.build_seconds},
        {"lambda", a.lambda},
        {"subgrids", a.subgrids},
        {"sub_references", a.sub_references},
        {"cost_estimate", a.cost_estimate},
        {"flat_cost_estimate", a.flat_cost_estimate},
        {"simd_target", a.simd_target},
        {"empty_block_share", a.empty_block_share},
        {"empty_skip", a.empty_skip},
        {"irregular_cells", a.irregular_cells},
        {"irregular_references", a.irregular_references}}},
      {"features", FeaturesJson(scene.features)}};
}

void PrintInfo(const Json& j) {
  const auto& g = j["grid"];
  const auto& f = j["features"];
  fmt::print("scene        {} ({})\n", j["scene"].get<std::string>(),
             j["source"].get<std::string>());
  fmt::print("triangles    {} ({} zero-area or non-finite, never hit)\n",
             j["triangles"].get<size_t>(), j["degenerate_triangles"].get<size_t>());
  fmt::print("vertices     {}\n", j["vertices"].get<size_t>());
  fmt::print("materials    {}, textures {}, lights {}, path frames {}\n",
             j["materials"].get<size_t>(), j["textures"].get<size_t>(),
             j["lights"].get<size_t>(), j["path_frames"].get<int>());
  const auto& lo = j["bounds"]["lo"];
  const auto& hi = j["bounds"]["hi"];
  fmt::print("bounds       ({:.4g}, {:.4g}, {:.4g}) .. ({:.4g}, {:.4g}, {:.4g})\n",
             lo[0].get<float>(), lo[1].get<float>(), lo[2].get<float>(), hi[0].get<float>(),
             hi[1].get<float>(), hi[2].get<float>());
  if (const float k = j["coordinate_scale"].get<float>(); k != 1.0f) {
    fmt::print("scale        rendered with coordinates x 2^{} (outside [2^-20, 2^20])\n",
               std::ilogb(k));
  }
  if (const auto& s = j["frame_shift"]; s[0] != 0.0 || s[1] != 0.0 || s[2] != 0.0) {
    fmt::print("frame        built around ({:.7g}, {:.7g}, {:.7g}) (farther from the origin than "
               "its size)\n",
               s[0].get<float>(), s[1].get<float>(), s[2].get<float>());
  }
  fmt::print("grid         {} {}x{}x{} = {} cells, {} occupied ({:.1f} %)\n",
             g["kind"].get<std::string>(), g["resolution"][0].get<int>(),
             g["resolution"][1].get<int>(), g["resolution"][2].get<int>(),
             g["cells"].get<size_t>(), g["occupied_cells"].get<size_t>(),
             100.0 * g["occupied_fraction"].get<double>());
  fmt::print("per cell     {:.2f} triangles per occupied cell, max {}, {} references\n",
             g["triangles_per_occupied_cell"].get<double>(),
             g["max_triangles_per_cell"].get<size_t>(), g["references"].get<size_t>());
  fmt::print("grid build   {:.2f} ms, {:.1f} MiB\n", 1e3 * g["build_seconds"].get<double>(),
             g["bytes"].get<size_t>() / 1048576.0);
  fmt::print("grid choice  lambda {:.2g}, {} 8x8x8 sub-grids ({} references), cost {:.1f} per ray "
             "(flat {:.1f}), traversal {}\n",
             g["lambda"].get<double>(), g["subgrids"].get<size_t>(),
             g["sub_references"].get<size_t>(), g["cost_estimate"].get<double>(),
             g["flat_cost_estimate"].get<double>(), g["simd_target"].get<std::string>());
  fmt::print("empty space  {:.1f} % of cells in empty 5x5x5 blocks, empty-space skipping {}\n",
             100.0 * g["empty_block_share"].get<double>(),
             g["empty_skip"].get<bool>() ? "on" : "off");
  if (const size_t cells = g["irregular_cells"].get<size_t>(); cells > 0) {
    fmt::print("irregular    {} cells, {} references (the rays traced one per lane)\n", cells,
               g["irregular_references"].get<size_t>());
  }
  fmt::print("features     lights={} specular={} reflection={} transmission={} textures={} "
             "large={}\n",
             f["lights"].get<bool>(), f["specular"].get<bool>(), f["reflection"].get<bool>(),
             f["transmission"].get<bool>(), f["textures"].get<bool>(), f["large"].get<bool>());
}

struct InfoArgs {
  std::string scene = kDefaultScene;
  bool json = false;
  float lambda = 0.0f;  // 0: chosen by the grid cost model (BuildOptions::lambda)
  std::string grid = "auto";
};

// --lambda: 0 (the default) lets the grid cost model choose; anything else is used as given.
// --grid: BuildOptions::grid by name (the CLI checks the name).
void SetBuild(float lambda, const std::string& grid, BuildOptions* build) {
  if (lambda > 0.0f) build->lambda = lambda;
  build->grid = grid == "uniform"     ? GridKind::kUniform
                : grid == "two-level" ? GridKind::kTwoLevel
                : grid == "irregular" ? GridKind::kIrregular
                                      : GridKind::kAuto;
}

constexpr const char* kGridHelp =
    "acceleration structure: auto (a uniform grid, with 8x8x8 sub-grids where the cost model "
    "finds them cheaper), uniform, two-level, or irregular (auto's grid for coherent packets and "
    "an irregular grid for the rays traced one by one: diffuse, reflected and refracted rays)";

int RunInfo(const InfoArgs& args) {
  const Scene scene = LoadScene(args.scene);
  BuildOptions build;
  SetBuild(args.lambda, args.grid, &build);
  const Accel accel(scene.mesh(), build);
  const Json j = InfoJson(scene, accel.Info());
  if (args.json) {
    fmt::print("{}\n", j.dump(2));
  } else {
    PrintInfo(j);
  }
  return 0;
}

struct RenderArgs {
  std::string scene = kDefaultScene;
  int width = 512;
  int height = 512;
  int depth = RenderOptions{}.max_depth;
  int frames = 1;
  float speed = 1.0f;
  std::string out;
  std::string backend = "tiles";  // the fastest on a multi-core machine (README)
  int task_size = RenderOptions{}.task_size;
  int batch = RenderOptions{}.batch;
  int ray_budget = RenderOptions{}.ray_budget;
  std::string order;  // empty: RenderOptions' default (block8x8)
  float cutoff = RenderOptions{}.weight_cutoff;
  float lambda = 0.0f;  // 0: chosen by the grid cost model
  std::string grid = "auto";  // --grid (BuildOptions::grid)
  std::string stats;
  bool quiet = false;
  // Host schedulers (sched/backends.h).
  int threads = 0;  // 0: every hardware thread for lock, lfree, local, tiles; 1 otherwise
  std::string tile = "32x32";
  int pbt = 0;
  int pbt_workers = 0;
  std::string assign;    // empty: the backend's default (PbtAssignFor)
  std::string pbt_cost;  // empty: the backend's default (wall; cell: its simulated cycles)
  std::string pbt_predict;  // empty: the default (costmap)
  uint64_t seed = 1;
  bool steal = false;
  bool demand = false;
  bool queue_stats = true;
  int spes = 6;  // --backend cell: simulated SPEs
  double mpi_timeout = 120;  // --backend mpi: bound on every wait of the master for a worker
  std::string dump_raw;      // hidden: raw fixed-point framebuffer (sched/mpi_backend.h)
};

// "32x32", "640x2", "300x1" -> width, height. Throws rs::Error naming the option.
void ParseTileShape(const std::string& text, int& width, int& height) {
  const size_t x = text.find_first_of("xX");
  auto number = [&](const std::string& part) {
    if (part.empty() || part.size() > 6 || part.find_first_not_of("0123456789") != std::string::npos) {
      throw Error(fmt::format("--tile {}: expected WIDTHxHEIGHT, e.g. 32x32 or 640x2", text));
    }
    return std::stoi(part);
  };
  if (x == std::string::npos) number("");
  width = number(text.substr(0, x));
  height = number(text.substr(x + 1));
  if (width < 1 || height < 1) {
    throw Error(fmt::format("--tile {}: width and height must be at least 1", text));
  }
}

// The PBT assignment the backend runs: --assign, or its default (cell: one shared counter,
// costliest tile first; the others: PBT-Random). Throws rs::Error naming the option.
PbtAssign PbtAssignFor(const RenderArgs& args) {
  PbtAssign assign = args.backend == "cell" ? PbtAssign::kCounter : PbtAssign::kRandom;
  if (!args.assign.empty() && !ParsePbtAssign(args.assign, &assign)) {
    throw Error(fmt::format("--assign {}: expected random, greedy, visit, static, counter or lpt",
                            args.assign));
  }
  return assign;
}

// --pbt-cost (alias --pbt-time): wall (the default), cpu or work (the default of the queue
// backends with --pbt, whose tiles have no time of their own).
PbtCost PbtCostFor(const RenderArgs& args) {
  BackendKind kind = BackendKind::kTiles;
  const bool queues = args.pbt > 0 && ParseBackendKind(args.backend, &kind) &&
                      (kind == BackendKind::kLock || kind == BackendKind::kLockFree ||
                       kind == BackendKind::kLocal);
  PbtCost cost = queues ? PbtCost::kWork : PbtCost::kWall;
  if (!args.pbt_cost.empty() && !ParsePbtCost(args.pbt_cost, &cost)) {
    throw Error(fmt::format("--pbt-cost {}: expected wall, cpu or work", args.pbt_cost));
  }
  return cost;
}

// --pbt-predict: costmap (the default) or paper. Throws rs::Error naming the option.
PbtPredict PbtPredictFor(const RenderArgs& args) {
  PbtPredict predict = PbtPredict::kCostMap;
  if (!args.pbt_predict.empty() && !ParsePbtPredict(args.pbt_predict, &predict)) {
    throw Error(fmt::format("--pbt-predict {}: expected paper or costmap", args.pbt_predict));
  }
  return predict;
}

// Every option a backend cannot honour is an error naming the option and the backend (checked
// before anything is loaded or rendered). An option left at its default is not "given".
void CheckBackendOptions(const RenderArgs& args) {
  const std::string& b = args.backend;
  const bool cell = b == "cell", mpi = b == "mpi";
  BackendKind kind = BackendKind::kSerial;
  if (!cell && !mpi && !ParseBackendKind(b, &kind)) return;  // the registry names it
  const bool tiles = !cell && !mpi && kind == BackendKind::kTiles;
  const bool serial = !cell && !mpi && kind == BackendKind::kSerial;
  const bool tiled = tiles || cell || mpi;
  const bool pbt = args.pbt > 0;
  auto fail = [&](const std::string& option, const std::string& why) {
    throw Error(fmt::format("{}: {}", option, why));
  };
  if (args.tile != "32x32" && !tiled) {
    fail("--tile " + args.tile,
         fmt::format("the {} backend cuts the image into tasks, not tiles (use --backend tiles, "
                     "cell or mpi)",
                     b));
  }
  if (args.tile != "32x32" && pbt) {
    fail("--tile " + args.tile, fmt::format("with --pbt the PBT makes the tiles (backend {})", b));
  }
  const bool queues = !cell && !mpi && (kind == BackendKind::kLock ||
                                         kind == BackendKind::kLockFree ||
                                         kind == BackendKind::kLocal);
  if (pbt && !tiled && !queues) {
    fail(fmt::format("--pbt {}", args.pbt),
         fmt::format("PBT tiling needs --backend lock, lfree, local, tiles, cell or mpi, not {}",
                     b));
  }
  // The PBT's options need a PBT.
  const bool seed_given = args.seed != 1;
  const bool pbt_cost_given = !args.pbt_cost.empty();
  if (!pbt) {
    if (args.pbt_workers != 0) {
      fail(fmt::format("--pbt-workers {}", args.pbt_workers), "needs --pbt k");
    }
    if (!args.assign.empty()) fail("--assign " + args.assign, "needs --pbt k");
    if (seed_given) fail(fmt::format("--seed {}", args.seed), "needs --pbt k");
    if (args.steal) fail("--steal", "needs a PBT tiling (--backend tiles --pbt k)");
    if (args.demand) fail("--demand", "needs a PBT tiling (--backend tiles --pbt k)");
    if (pbt_cost_given) fail("--pbt-cost " + args.pbt_cost, "needs --pbt k");
    if (!args.pbt_predict.empty()) fail("--pbt-predict " + args.pbt_predict, "needs --pbt k");
  } else {
    PbtPredictFor(args);  // a bad value is an error before anything is loaded
    const PbtAssign assign = PbtAssignFor(args);
    const PbtCost cost = PbtCostFor(args);
    if (seed_given && assign != PbtAssign::kRandom && assign != PbtAssign::kStatic) {
      fail(fmt::format("--seed {}", args.seed),
           fmt::format("only --assign random and static use a seed, not {} (backend {})",
                       PbtAssignName(assign), b));
    }
    if (cell && args.steal) {
      fail("--steal", "the cell backend's SPEs take tiles only from their own list (the SPE "
                      "program reads no other SPE's counter); use --assign counter for tiles "
                      "on demand");
    }
    if (args.demand && !tiles) {
      fail("--demand",
           mpi ? "the mpi backend's master always hands tiles out on demand (a worker's own list "
                 "first, then the last tile of the list with most work waiting)"
               : fmt::format("the demand-driven master runs the tiles backend's threads, not {}",
                             b));
    }
    if (args.demand && args.steal) {
      fail("--demand", "with --steal: the master hands out every tile, there is nothing to steal");
    }
    if (args.demand && assign == PbtAssign::kCounter) {
      fail("--demand", "--assign counter has no per-worker lists to prefer (it is demand driven "
                       "already, costliest tile first)");
    }
    if (args.steal && assign == PbtAssign::kCounter) {
      fail("--steal", fmt::format("--assign counter has no per-worker lists to steal from "
                                  "(backend {})",
                                  b));
    }
    if (queues && cost != PbtCost::kWork) {
      fail("--pbt-cost " + args.pbt_cost,
           fmt::format("the {} backend traces a tile's rays on whichever thread pops them, mixed "
                       "with other tiles' rays in one batch, so a tile has no wall or CPU time "
                       "of its own (--pbt-cost work, the default there, counts its rays)",
                       b));
    }
    if (cell && pbt_cost_given && cost != PbtCost::kWork) {
      fail("--pbt-cost " + args.pbt_cost,
           "the cell backend feeds PBT its simulated tile cycles, its deterministic work "
           "(--pbt-cost work or none)");
    }
    if (mpi && args.pbt_workers != 0) {
      fail(fmt::format("--pbt-workers {}", args.pbt_workers),
           "the mpi backend's PBT workers are its worker ranks (mpirun -np N: N - 1)");
    }
  }
  // Options of one backend only.
  if (!cell && args.spes != 6) {
    fail(fmt::format("--spes {}", args.spes), "needs --backend cell, not " + b);
  }
  if (!mpi && args.mpi_timeout != 120) {
    fail(fmt::format("--mpi-timeout {:g}", args.mpi_timeout), "needs --backend mpi, not " + b);
  }
  if (!args.queue_stats && (serial || cell || mpi)) {
    fail("--no-queue-stats", fmt::format("the {} backend has no queue operations to time", b));
  }
  if (cell) {
    if (args.task_size != RenderOptions{}.task_size) {
      fail(fmt::format("--task-size {}", args.task_size),
           "the cell backend's SPE ray pipeline keeps 8 rays in flight, it has no tasks");
    }
    if (args.batch != RenderOptions{}.batch) {
      fail(fmt::format("--batch {}", args.batch),
           "the cell backend's SPE ray pipeline keeps 8 rays in flight, it has no batches");
    }
    if (args.ray_budget != RenderOptions{}.ray_budget) {
      fail(fmt::format("--ray-budget {}", args.ray_budget),
           "the cell backend's SPEs bound their rays in flight by the local store");
    }
    if (!args.order.empty()) {
      fail("--order " + args.order,
           "the cell backend's SPEs generate primary rays in their own sub-tile order");
    }
    if (!args.dump_raw.empty()) fail("--dump-raw", "not written by the cell backend");
  }
}

BackendOptions MakeBackendOptions(const RenderArgs& args) {
  BackendOptions o;
  if (!ParseBackendKind(args.backend, &o.kind)) {
    throw Error(fmt::format("--backend {}: not a host backend", args.backend));
  }
  o.threads = args.threads;
  ParseTileShape(args.tile, o.tile_width, o.tile_height);
  o.pbt_tiles_per_worker = args.pbt;
  o.pbt_workers = args.pbt_workers;
  o.assign = PbtAssignFor(args);
  o.pbt_cost = PbtCostFor(args);
  o.pbt_predict = PbtPredictFor(args);
  o.seed = args.seed;
  o.pbt_steal = args.steal;
  o.pbt_demand = args.demand;
  o.queue_stats = args.queue_stats;
  if (o.kind == BackendKind::kSerial && o.threads != 1) {
    throw Error(fmt::format("--threads {}: the serial backend runs one thread (use lock, lfree, "
                            "local or tiles)", o.threads));
  }
  ValidateBackendOptions(o);
  return o;
}

// "frame#.png" -> "frame0007.png"; names without '#' are used as they are.
std::string FrameFileName(const std::string& pattern, int frame) {
  const size_t hash = pattern.find('#');
  if (hash == std::string::npos) return pattern;
  return pattern.substr(0, hash) + fmt::format("{:04d}", frame) + pattern.substr(hash + 1);
}

// Every backend the command links, by name (sched/backend.h).
BackendRegistry Backends() {
  BackendRegistry registry;
  RegisterHostBackends(registry);
  sim::RegisterCellBackend(registry);
  RegisterMpiBackend(registry);
  return registry;
}

bool IsHostBackend(const std::string& name) {
  BackendKind kind;
  return ParseBackendKind(name, &kind);
}

// What the backend's factory gets: the host options (validated for the host backends; for cell
// and mpi the tiling, PBT and threads fields they read), the frames' options, the rest.
BackendConfig MakeBackendConfig(const RenderArgs& args, const RenderOptions& options) {
  BackendConfig c;
  if (IsHostBackend(args.backend)) {
    c.host = MakeBackendOptions(args);
  } else {
    c.host.threads = args.threads;
    ParseTileShape(args.tile, c.host.tile_width, c.host.tile_height);
    c.host.pbt_tiles_per_worker = args.pbt;
    c.host.pbt_workers = args.pbt_workers;
    c.host.assign = PbtAssignFor(args);
    c.host.pbt_cost = PbtCostFor(args);
    c.host.pbt_predict = PbtPredictFor(args);
    c.host.seed = args.seed;
    c.host.pbt_steal = args.steal;
    c.host.queue_stats = args.queue_stats;
  }
  if (args.backend == "cell" && args.threads != 1) {
    throw Error(fmt::format("--threads {}: the cell backend simulates --spes SPEs on one host "
                            "thread", args.threads));
  }
  c.render = options;
  c.scene = args.scene;
  c.spes = args.spes;
  c.mpi_timeout_seconds = args.mpi_timeout;
  c.fixed_sums = !args.dump_raw.empty();
  return c;
}

int ReportException(std::exception_ptr error) noexcept;

// The one frame loop of every backend: set up (load, build), render the camera path's frames,
// write the images ('#': every frame as it completes; otherwise the last after Finish), the
// statistics (one writer, JSON or CSV) and the summary.
int RunRender(RenderArgs args) {
  if (args.threads == 0) {
    args.threads = IsHostBackend(args.backend) && args.backend != "serial"
                       ? std::max(1, static_cast<int>(std::thread::hardware_concurrency()))
                       : 1;
  }
  CheckBackendOptions(args);
  if (!args.stats.empty() && !StatsFileFormatOk(args.stats)) {
    throw Error(fmt::format("--stats {}: statistics file must end in .json or .csv", args.stats));
  }
  if (args.width <= 0 || args.height <= 0 || args.width > 16384 || args.height > 16384) {
    throw Error(fmt::format("--width/--height must be within 1..16384 (got {}x{})", args.width,
                            args.height));
  }
  RenderOptions options;
  options.width = args.width;
  options.height = args.height;
  options.max_depth = args.depth;
  options.task_size = args.task_size;
  options.batch = args.batch;
  options.ray_budget = args.ray_budget;
  options.weight_cutoff = args.cutoff;
  if (args.order == "scanline") options.order = RayOrder::kScanline;
  if (args.order == "block4x2" || args.order == "block") options.order = RayOrder::kBlock4x2;
  if (args.order == "block8x8") options.order = RayOrder::kBlock8x8;
  const std::string out = args.out.empty() ? args.scene + ".png" : args.out;
  const bool tty = isatty(fileno(stderr)) != 0;
  // Every output can be written (folder exists, writable, a known image format) before any work.
  CheckImageOutputPath(FrameFileName(out, 0));
  if (!args.stats.empty()) CheckOutputPath(args.stats);
  if (!args.dump_raw.empty()) CheckOutputPath(FrameFileName(args.dump_raw, 0));

  const BackendRegistry registry = Backends();
  const std::unique_ptr<Backend> backend =
      registry.Make(args.backend, MakeBackendConfig(args, options));
  std::optional<Scene> scene;
  std::optional<Accel> accel;
  double load_seconds = 0;
  std::string note;
  bool set_up = false;
  try {
    set_up = backend->Setup([&] {
      const auto t_load = std::chrono::steady_clock::now();
      scene.emplace(LoadScene(args.scene));
      load_seconds = Seconds(std::chrono::steady_clock::now() - t_load);
      BuildOptions build;
      SetBuild(args.lambda, args.grid, &build);
      build.build_threads = args.threads;  // the same structure on any count, built sooner
      accel.emplace(backend->Build(*scene, build, args.width, &note));
    });
  } catch (...) {
    // Printed while the backend lives: the mpi backend finalizes MPI when it goes, and mpirun
    // may then end this rank (the others exit with status 1 at once) before the line is out.
    return ReportException(std::current_exception());
  }
  if (!set_up) return 1;  // another MPI rank printed the error
  const bool owner = backend->owns_image();
  if (owner && !note.empty() && !args.quiet) fmt::print(stderr, "raystream: note: {}\n", note);
  const AccelInfo info = accel->Info();
  if (owner && info.triangles > 0 && info.degenerate_triangles == info.triangles) {
    fmt::print(stderr,
               "raystream: warning: {}: all {} triangles have zero area or a non-finite vertex "
               "and are never hit; the image shows the background only\n",
               scene->source, info.triangles);
  }

  // shadow rays from each light through its light buffer (the same image, faster); built once
  // (the scene and its lights do not move), on the render's threads
  const auto t_lights = std::chrono::steady_clock::now();
  const std::vector<LightBuffer> light_buffers = BuildLightBuffers(*scene, *accel, args.threads);
  const double light_seconds = Seconds(std::chrono::steady_clock::now() - t_lights);

  std::vector<FrameReport> reports;
  reports.reserve(owner ? static_cast<size_t>(args.frames) : 0);
  // Every output of the run is staged (a complete, fsynced temporary beside its target) and put
  // in place only when all of them are: a failed run writes nothing, not frame 0 when frame 2
  // fails, not the image when the statistics fail (scenes/image_io.h). Staged files that are
  // not committed remove their temporaries; SIGINT and SIGTERM remove them too (Main).
  std::vector<StagedFile> staged;
  std::vector<float> rgb;
  const auto write = [&](int frame) {
    const Framebuffer& fb = *backend->image();
    if (fb.storage() == Framebuffer::Storage::kResolved) {
      staged.push_back(StageImage(FrameFileName(out, frame), args.width, args.height, fb.resolved()));
    } else {
      fb.ToRgb(rgb);
      staged.push_back(StageImage(FrameFileName(out, frame), args.width, args.height, rgb));
    }
    if (!args.dump_raw.empty()) {
      staged.push_back(StageFile(FrameFileName(args.dump_raw, frame), RawFramebufferBytes(fb),
                                 "raw framebuffer"));
    }
  };
  const int last = args.frames - 1;
  for (int frame = 0; frame <= last; ++frame) {
    const Camera camera = scene->path.At(frame, args.speed, scene->camera);
    FrameContext ctx;
    try {
      ctx = MakeFrameContext(*scene, *accel, camera, options);
      ctx.light_buffers = light_buffers;
      // PBT's cost map moves this frame's costs to the next frame's view.
      if (frame < last) SetNextCamera(ctx, scene->path.At(frame + 1, args.speed, scene->camera));
    } catch (const Error& e) {
      throw Error(fmt::format("{}: camera path frame {}: {}", scene->source, frame, e.what()));
    }
    backend->BeginFrame(ctx);
    const FrameReport& report = backend->EndFrame();
    if (!owner) continue;
    reports.push_back(report);
    if (frame < last && out.find('#') != std::string::npos) write(frame);
    if (args.frames > 1 && !args.quiet) {
      const FrameStats& s = report.stats.total;
      const std::string extra = backend->ProgressNote(report);
      fmt::print(stderr, "{}frame {}/{}  {:.1f} ms  {:.2f} Mrays/s{}{}", tty ? "\r" : "",
                 frame + 1, args.frames, 1e3 * s.total_seconds, s.MraysPerSecond(),
                 extra.empty() ? "" : "  " + extra, tty ? "" : "\n");
    }
  }
  if (owner && args.frames > 1 && !args.quiet && tty) fmt::print(stderr, "\n");
  backend->Finish();  // mpi: every worker has said goodbye; only complete frames are written
  if (!owner) return 0;
  write(last);

  FrameStats total;  // counters summed over frames
  double total_seconds = 0;
  for (const FrameReport& r : reports) {
    total.Merge(r.stats.total);
    total_seconds += r.stats.total.total_seconds;
  }
  if (total.budget_dropped > 0) {
    fmt::print(stderr,
               "raystream: warning: {} bounce rays dropped: the ray tree passed --ray-budget {} "
               "rays per primary ray (or a queue backend's rays-in-flight cap); the image is "
               "incomplete\n",
               total.budget_dropped, args.ray_budget);
  }
  if (!args.stats.empty()) {
    staged.push_back(StageFile(args.stats, FrameReportsText(args.stats, scene->name, *backend,
                                                           reports),
                               "statistics"));
  }
  for (StagedFile& f : staged) f.Commit();
  if (args.quiet) return 0;
  fmt::print("scene      {}: {} triangles, {} lights, grid {} {}x{}x{}\n", scene->name,
             info.triangles, scene->lights.size(), info.kind, info.resolution[0],
             info.resolution[1], info.resolution[2]);
  fmt::print("load       {:.1f} ms, grid build {:.1f} ms ({:.1f} Mtris/s), {} light buffer{} "
             "{:.1f} ms ({} thread{})\n",
             1e3 * load_seconds, 1e3 * info.build_seconds,
             info.build_seconds > 0 ? info.triangles / info.build_seconds * 1e-6 : 0.0,
             light_buffers.size(), light_buffers.size() == 1 ? "" : "s", 1e3 * light_seconds,
             args.threads, args.threads == 1 ? "" : "s");
  fmt::print("image      {}x{}, depth {}, {} frame(s), backend {}\n", args.width, args.height,
             args.depth, args.frames, backend->Describe());
  std::string by_kind;
  const uint64_t rays = total.TotalRays();
  for (int k = 0; k < kNumRayKinds; ++k) {
    by_kind += fmt::format("{}{} {}", k ? ", " : "", total.rays[k], RayKindName(RayKind(k)));
  }
  fmt::print("rays       {} ({})\n", rays, by_kind);
  const auto per_call = [&](RayKind k) {
    const uint64_t calls = total.trace_calls[static_cast<int>(k)];
    return calls > 0 ? static_cast<double>(total.rays[static_cast<int>(k)]) / calls : 0.0;
  };
  if (total.trace_calls[static_cast<int>(RayKind::kPrimary)] > 0) {
    fmt::print("kernels    {:.0f} primary, {:.0f} shadow rays per call (batch {}), "
               "{:.1f} % of rays in coherent packets\n",
               per_call(RayKind::kPrimary), per_call(RayKind::kShadow), args.batch,
               total.trace.rays > 0 ? 100.0 * total.trace.packet_rays / total.trace.rays : 0.0);
  }
  const std::string scheduling =
      total.schedule_seconds > 0
          ? fmt::format(", {:.1f} ms scheduling", 1e3 * total.schedule_seconds)
          : std::string();
  fmt::print("trace      {:.1f} ms in {} tasks ({:.1f} ms tracing, {:.1f} ms shading{}), "
             "{:.2f} Mrays/s\n",
             1e3 * total_seconds, total.tasks, 1e3 * total.trace_seconds,
             1e3 * total.shade_seconds, scheduling,
             total_seconds > 0 ? rays / total_seconds * 1e-6 : 0.0);
  fmt::print("{}", backend->Summary(reports));
  fmt::print("wrote      {}\n", FrameFileName(out, last));
  return 0;
}

// One line on stderr; never throws (a closed or full stderr loses the line, nothing else).
void PrintError(const char* kind, const std::string& what) noexcept {
  std::fprintf(stderr, "raystream: %s: %s\n", kind, what.c_str());
  std::fflush(stderr);
}

// The one line for an exception that ends the command, and the exit status: 1 for errors, 2 for
// an internal error.
int ReportException(std::exception_ptr error) noexcept {
  try {
    std::rethrow_exception(error);
  } catch (const Error& e) {
    PrintError("error", e.what());
  } catch (const std::system_error& e) {  // fmt: a write to stdout failed (full disk, pipe)
    PrintError("error", std::string("cannot write to standard output: ") + e.what());
  } catch (const std::bad_alloc&) {
    PrintError("error", "out of memory");
  } catch (const std::exception& e) {
    PrintError("internal error", e.what());
    return 2;
  } catch (...) {
    PrintError("internal error", "unknown exception");
    return 2;
  }
  return 1;
}

// Everything written to stdout reached it, or the run fails (e.g. `info >/dev/full`).
int FlushStdout(int status) {
  errno = 0;
  if (std::fflush(stdout) != 0 || std::ferror(stdout)) {
    throw Error(fmt::format("cannot write to standard output: {}",
                            errno != 0 ? std::strerror(errno) : "write error"));
  }
  return status;
}

void CheckFinite(const char* option, float value) {
  if (!std::isfinite(value)) throw Error(fmt::format("{} {}: must be a finite number", option, value));
}

// SIGINT, SIGTERM, SIGHUP: remove this process's temporary outputs, then die of the signal.
extern "C" void OnSignal(int sig) {
  RemoveTemporaries();
  signal(sig, SIG_DFL);
  raise(sig);
}

// A closed stdin, stdout or stderr (`2>&-`) becomes /dev/null, so that no output of ours lands in
// a file that later takes its number, and writing to it cannot fail.
void OpenStdio() {
  for (int fd = 0; fd <= 2; ++fd) {
    if (fcntl(fd, F_GETFD) == -1 && errno == EBADF) {
      const int got = open("/dev/null", fd == 0 ? O_RDONLY : O_WRONLY);
      if (got != fd && got >= 0) close(got);
    }
  }
}

int Main(int argc, char** argv) {
  OpenStdio();
  struct sigaction action = {};
  action.sa_handler = OnSignal;
  sigemptyset(&action.sa_mask);
  for (const int sig : {SIGINT, SIGTERM, SIGHUP}) sigaction(sig, &action, nullptr);
  CLI::App app{"raystream: SIMD ray-stream kernels, render and inspect scenes"};
  app.require_subcommand(1);
  app.set_version_flag("--version", std::string(Version()));

  std::string scene_help = "scene name or file (.json, .obj, .ply, ...); built in:";
  for (const auto& n : ProceduralSceneNames()) scene_help += " " + n;
  for (const auto& n : BuiltinSceneFileNames()) scene_help += " " + n;

  RenderArgs r;
  CLI::App* render = app.add_subcommand("render", "render a scene to an image (PNG, EXR)");
  render->add_option("--scene", r.scene, scene_help)->capture_default_str();
  render->add_option("--width", r.width, "image width")->capture_default_str();
  render->add_option("--height", r.height, "image height")->capture_default_str();
  render->add_option("--depth", r.depth, "maximum ray depth (0: primary and shadow rays only)")
      ->check(CLI::Range(0, 64))
      ->capture_default_str();
  render->add_option("--frames", r.frames, "frames of the scene's walk-through")
      ->check(CLI::Range(1, 100000))
      ->capture_default_str();
  render->add_option("--speed", r.speed, "camera speed along the path (1 or 2)")
      ->check(CLI::Range(0.0f, 64.0f))
      ->capture_default_str();
  CLI::Option* out_option = render->add_option("--out", r.out,
                     "output image (default SCENE.png); a '#' becomes the frame number and "
                     "writes every frame, otherwise only the last frame is written");
  render->add_option("--backend", r.backend,
                     "scheduler: serial (the reference, one thread), lock, lfree, local, tiles "
                     "(the default), cell, mpi (under mpirun)")
      ->capture_default_str();
  render->add_option("--spes", r.spes,
                     "cell backend: simulated SPEs (--tile, --pbt, --pbt-workers, --assign and "
                     "--seed apply)")
      ->check(CLI::Range(1, 8))
      ->capture_default_str();
  render->add_option("--threads", r.threads,
                     "render threads (lock, lfree, local, tiles; mpi: per worker); default: every "
                     "hardware thread, 1 for serial, cell and mpi")
      ->check(CLI::Range(1, 1024))
      ->capture_default_str();
  render->add_option("--tile", r.tile, "tiles backend: tile shape WxH (8x8, 32x32, 640x2, ...)")
      ->capture_default_str();
  render->add_option("--pbt", r.pbt,
                     "PBT tiling with k tiles per worker (0: off; not serial; lock, lfree, "
                     "local: the tiles feed the queues)")
      ->check(CLI::Range(0, 4096))
      ->capture_default_str();
  render->add_option("--pbt-workers", r.pbt_workers,
                     "PBT workers n (0: --threads; cell: --spes; mpi: the worker ranks)")
      ->check(CLI::Range(0, 65536))
      ->capture_default_str();
  render->add_option("--assign", r.assign,
                     "PBT tile assignment: random, greedy, visit, static, counter, lpt (lists by "
                     "longest predicted tile first onto the least loaded worker; default "
                     "random; cell: counter)");
  render->add_option("--pbt-cost,--pbt-time", r.pbt_cost,
                     "tile cost fed to PBT-Update: wall (default), cpu, or work (deterministic "
                     "counts; cell: its simulated cycles; lock, lfree, local: work only)")
      ->check(CLI::IsMember({"wall", "cpu", "work"}));
  render->add_option("--pbt-predict", r.pbt_predict,
                     "PBT-Update's predictor: costmap (default: the frame's per-block cost map, "
                     "moved to the next camera; each tile, split half and merged pair predicted "
                     "as the sum of its blocks) or paper (split halves e/2, Algorithm 1 as "
                     "published)");
  render->add_option("--seed", r.seed, "seed of PBT-Random and static assignments")
      ->check(CLI::Validator(
          [](std::string& v) {
            return v.find_first_not_of("0123456789") == std::string::npos && !v.empty()
                       ? std::string()
                       : std::string("expected a non-negative integer");
          },
          "UINT", "non-negative integer"))
      ->capture_default_str();
  render->add_flag("--steal", r.steal,
                   "PBT: a thread done with its tiles takes waiting tiles of the most loaded "
                   "worker (demand-driven with affinity)");
  render->add_flag("--demand", r.demand,
                   "PBT, tiles backend: the paper's demand-driven master; a free thread asks for "
                   "a tile and gets the next in PBT order, one of its own lists' if any is left "
                   "(--assign gives the affinity)");
  render->add_flag("!--no-queue-stats", r.queue_stats, "do not time queue operations");
  render->add_option("--task-size", r.task_size, "rays per task")
      ->check(CLI::Range(1, 1 << 20))
      ->capture_default_str();
  render->add_option("--batch", r.batch,
                     "rays per kernel call: a worker traces up to this many rays of one "
                     "generation as one stream (queue backends pop ceil(batch / task-size) tasks)")
      ->check(CLI::Range(1, RenderOptions::kMaxBatch))
      ->capture_default_str();
  render->add_option("--ray-budget", r.ray_budget,
                     "rays traced per primary ray (its whole tree) before its bounce rays are "
                     "dropped with a warning: the guard against exponential ray trees")
      ->check(CLI::Range(1, 1 << 30))
      ->capture_default_str();
  render->add_option("--order", r.order,
                     "primary ray order inside a tile: block8x8 (the default: each 64-ray packet "
                     "is an 8x8 square of pixels, the smallest footprint), block4x2 (or block), "
                     "scanline")
      ->check(CLI::IsMember({"scanline", "block", "block4x2", "block8x8"}));
  render->add_option("--cutoff", r.cutoff, "drop secondary rays whose weight is below this")
      ->capture_default_str();
  render->add_option("--lambda", r.lambda, "grid density: cells per triangle (0: chosen by the grid cost model)")
      ->check(CLI::Range(0.0f, 64.0f))
      ->capture_default_str();
  render->add_option("--grid", r.grid, kGridHelp)
      ->check(CLI::IsMember({"auto", "uniform", "two-level", "irregular"}))
      ->capture_default_str();
  render->add_option("--mpi-timeout", r.mpi_timeout,
                     "mpi backend: bound on every wait of the master for a worker (setup, "
                     "tile, result transfer, end of run); a worker that misses it ends the run "
                     "with an error naming its rank")
      ->check(CLI::Range(0.001, 1e6))
      ->capture_default_str();
  render->add_option("--dump-raw", r.dump_raw)->group("");  // hidden: exact framebuffer dump
  render->add_option("--stats", r.stats,
                     "write per-frame, per-thread and per-tile statistics to this file (.json or "
                     ".csv)");
  render->add_flag("--quiet,-q", r.quiet, "print nothing on success");

  InfoArgs i;
  CLI::App* info = app.add_subcommand("info", "print a scene's size, grid and features");
  info->add_option("--scene", i.scene, scene_help)->capture_default_str();
  info->add_flag("--json", i.json, "print JSON");
  info->add_option("--lambda", i.lambda, "grid density: cells per triangle (0: chosen by the grid cost model)")
      ->check(CLI::Range(0.0f, 64.0f))
      ->capture_default_str();
  info->add_option("--grid", i.grid, kGridHelp)
      ->check(CLI::IsMember({"auto", "uniform", "two-level", "irregular"}))
      ->capture_default_str();

  CLI::App* scenes = app.add_subcommand("scenes", "list built-in scenes and the search path");

  CLI11_PARSE(app, argc, argv);
  try {
    if (out_option->count() > 0 && r.out.empty()) throw Error("--out '': empty file name");
    CheckFinite("--speed", r.speed);
    CheckFinite("--cutoff", r.cutoff);
    CheckFinite("--lambda", r.lambda);
    CheckFinite("--lambda", i.lambda);
    if (*render) return FlushStdout(RunRender(r));
    if (*info) return FlushStdout(RunInfo(i));
    if (*scenes) {
      fmt::print("procedural:");
      for (const auto& n : ProceduralSceneNames()) fmt::print(" {}", n);
      fmt::print("\nscene files:");
      for (const auto& n : BuiltinSceneFileNames()) fmt::print(" {}", n);
      fmt::print("\nsearch path ($RAYSTREAM_SCENES first):\n");
      for (const auto& d : SceneSearchPath()) fmt::print("  {}\n", d);
      return FlushStdout(0);
    }
  } catch (...) {
    return ReportException(std::current_exception());
  }
  return 0;
}

}  // namespace
}  // namespace rs

// A tight address-space limit (ulimit -v, RLIMIT_AS) must end in one line and exit 1, but the
// static initialisers of the shared libraries (thread pools, malloc arenas, registries) run before
// main and abort or segfault when they cannot map memory.
// An executable's .preinit_array runs after the dynamic loader has mapped every library (a limit
// too small for that is the loader's own "error while loading shared libraries", exit 127) and
// before any library's initialiser: check there that the limit leaves the headroom they and a
// small render need. Only the C library and raw system calls are used here.
namespace {
// Measured here (2 CPUs, Debian 12): the libraries map ~26 MB (OpenImageIO, ~500 MB more with
// its libraries, is a module loaded on first use that checks the limit itself:
// scenes/image_io.cc), and an 8x8 render on every hardware thread runs from a 128 MB limit on
// (each thread's stack and malloc arena); between this check and what a run needs, allocation
// failures inside main are the ordinary one-line "out of memory" error.
constexpr unsigned long long kStartHeadroomMb = 96;

void CheckAddressSpace(int, char**, char**) {
  rlimit limit{};
  if (getrlimit(RLIMIT_AS, &limit) != 0 || limit.rlim_cur == RLIM_INFINITY) return;
  unsigned long long pages = 0;  // what is mapped now: the executable, every library, the stack
  if (const int fd = open("/proc/self/statm", O_RDONLY | O_CLOEXEC); fd >= 0) {
    char text[64];
    const ssize_t n = read(fd, text, sizeof text - 1);
    close(fd);
    if (n > 0) {
      text[n] = '\0';
      pages = std::strtoull(text, nullptr, 10);
    }
  }
  const unsigned long long mb = 1ull << 20;
  const unsigned long long mapped_mb = pages * static_cast<unsigned long long>(sysconf(_SC_PAGESIZE)) / mb;
  const unsigned long long need_mb = mapped_mb + kStartHeadroomMb;
  if (limit.rlim_cur / mb >= need_mb) return;
  char line[256];
  const int len = std::snprintf(
      line, sizeof line,
      "raystream: error: address-space limit (ulimit -v) %llu MB is below the %llu MB the "
      "command needs to start (%llu MB of shared libraries mapped + %llu MB for their "
      "initialisation and a small render)\n",
      static_cast<unsigned long long>(limit.rlim_cur / mb), need_mb, mapped_mb, kStartHeadroomMb);
  if (len > 0) {
    [[maybe_unused]] const ssize_t w = write(2, line, static_cast<size_t>(len) < sizeof line ? len : sizeof line - 1);
  }
  _exit(1);
}

[[gnu::section(".preinit_array"), gnu::used]] void (*const kCheckAddressSpace)(int, char**,
                                                                              char**) =
    CheckAddressSpace;
}  // namespace

int main(int argc, char** argv) {
#ifdef RS_MIMALLOC
  // 2 MiB pages for the heap from here on (madvised transparent huge pages where explicit ones
  // are not reserved): the scene loader's vectors and the render's buffers are first touched
  // once each, a page fault per 2 MiB instead of per 4 KiB. `raystream render --scene conference`
  // (1 thread, 1024x1024) spent more time in those faults than in loading and building.
  mi_option_enable(mi_option_large_os_pages);
#endif
  return rs::Main(argc, argv);
}
