// The `raystream` command: render a scene to an image, or print what a scene and its grid hold.
// Every user-input problem ends in one clear line on stderr and a non-zero exit status.
#include <CLI/CLI.hpp>
#include <fmt/core.h>
#include <nlohmann/json.hpp>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <exception>
#include <fstream>
#include <string>
#include <vector>

#include "include/raystream/raystream.h"
#include "scenes/image_io.h"
#include "scenes/load.h"
#include "sched/render.h"

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
      {"bounds", {{"lo", {a.bounds_lo[0], a.bounds_lo[1], a.bounds_lo[2]}},
                  {"hi", {a.bounds_hi[0], a.bounds_hi[1], a.bounds_hi[2]}}}},
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
        {"build_seconds", a.build_seconds}}},
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
  fmt::print("features     lights={} specular={} reflection={} transmission={} textures={} "
             "large={}\n",
             f["lights"].get<bool>(), f["specular"].get<bool>(), f["reflection"].get<bool>(),
             f["transmission"].get<bool>(), f["textures"].get<bool>(), f["large"].get<bool>());
}

struct InfoArgs {
  std::string scene = kDefaultScene;
  bool json = false;
  float lambda = BuildOptions{}.lambda;
};

int RunInfo(const InfoArgs& args) {
  const Scene scene = LoadScene(args.scene);
  BuildOptions build;
  build.lambda = args.lambda;
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
  std::string backend = "serial";
  int task_size = RenderOptions{}.task_size;
  std::string order = "scanline";
  float cutoff = RenderOptions{}.weight_cutoff;
  float lambda = BuildOptions{}.lambda;
  std::string stats;
  bool quiet = false;
};

// "frame#.png" -> "frame0007.png"; names without '#' are used as they are.
std::string FrameFileName(const std::string& pattern, int frame) {
  const size_t hash = pattern.find('#');
  if (hash == std::string::npos) return pattern;
  return pattern.substr(0, hash) + fmt::format("{:04d}", frame) + pattern.substr(hash + 1);
}

Json StatsJson(int frame, const FrameStats& s) {
  Json rays = Json::object();
  for (int k = 0; k < kNumRayKinds; ++k) rays[RayKindName(RayKind(k))] = s.rays[k];
  return Json{{"frame", frame},
              {"rays", rays},
              {"tasks", s.tasks},
              {"cell_steps", s.trace.cell_steps},
              {"triangle_tests", s.trace.triangle_tests},
              {"seconds", s.total_seconds},
              {"trace_seconds", s.trace_seconds},
              {"shade_seconds", s.shade_seconds},
              {"mrays_per_second", s.MraysPerSecond()}};
}

int RunRender(const RenderArgs& args) {
  if (args.backend != "serial") {
    throw Error(fmt::format("--backend {}: not available in this build (available: serial)",
                            args.backend));
  }
  if (args.width <= 0 || args.height <= 0 || args.width > 16384 || args.height > 16384) {
    throw Error(fmt::format("--width/--height must be within 1..16384 (got {}x{})", args.width,
                            args.height));
  }
  const std::string out = args.out.empty() ? args.scene + ".png" : args.out;
  const bool tty = isatty(fileno(stderr)) != 0;

  const auto t_load = std::chrono::steady_clock::now();
  const Scene scene = LoadScene(args.scene);
  const double load_seconds = Seconds(std::chrono::steady_clock::now() - t_load);

  BuildOptions build;
  build.lambda = args.lambda;
  const Accel accel(scene.mesh(), build);
  const AccelInfo info = accel.Info();

  RenderOptions options;
  options.width = args.width;
  options.height = args.height;
  options.max_depth = args.depth;
  options.task_size = args.task_size;
  options.weight_cutoff = args.cutoff;
  options.order = args.order == "block" ? RayOrder::kBlock4x2 : RayOrder::kScanline;

  Json stats_json = Json::array();
  FrameStats total;  // counters summed over frames
  double total_seconds = 0;
  RenderResult last;
  for (int frame = 0; frame < args.frames; ++frame) {
    const Camera camera = scene.path.At(frame, args.speed, scene.camera);
    last = RenderImage(scene, accel, camera, options);
    total.Merge(last.stats);
    total_seconds += last.stats.total_seconds;
    stats_json.push_back(StatsJson(frame, last.stats));
    const bool write = frame + 1 == args.frames || out.find('#') != std::string::npos;
    if (write) WriteImage(FrameFileName(out, frame), args.width, args.height, last.rgb);
    if (args.frames > 1 && !args.quiet) {
      fmt::print(stderr, "{}frame {}/{}  {:.1f} ms  {:.2f} Mrays/s{}", tty ? "\r" : "",
                 frame + 1, args.frames, 1e3 * last.stats.total_seconds, last.stats.MraysPerSecond(),
                 tty ? "" : "\n");
    }
  }
  if (args.frames > 1 && !args.quiet && tty) fmt::print(stderr, "\n");

  if (!args.stats.empty()) {
    std::ofstream f(args.stats);
    f << Json{{"scene", scene.name}, {"backend", args.backend}, {"frames", stats_json}}.dump(2)
      << "\n";
    if (!f) throw Error(fmt::format("{}: cannot write statistics file", args.stats));
  }
  if (!args.quiet) {
    fmt::print("scene      {}: {} triangles, {} lights, grid {}x{}x{}\n", scene.name,
               info.triangles, scene.lights.size(), info.resolution[0], info.resolution[1],
               info.resolution[2]);
    fmt::print("load       {:.1f} ms, grid build {:.1f} ms ({:.1f} Mtris/s)\n",
               1e3 * load_seconds, 1e3 * info.build_seconds,
               info.build_seconds > 0 ? info.triangles / info.build_seconds * 1e-6 : 0.0);
    fmt::print("image      {}x{}, depth {}, {} frame(s), backend {}\n", args.width, args.height,
               args.depth, args.frames, args.backend);
    std::string by_kind;
    uint64_t rays = 0;
    for (int k = 0; k < kNumRayKinds; ++k) {
      by_kind += fmt::format("{}{} {}", k ? ", " : "", total.rays[k], RayKindName(RayKind(k)));
      rays += total.rays[k];
    }
    fmt::print("rays       {} ({})\n", rays, by_kind);
    fmt::print("trace      {:.1f} ms in {} tasks ({:.1f} ms tracing, {:.1f} ms shading), "
               "{:.2f} Mrays/s\n",
               1e3 * total_seconds, total.tasks, 1e3 * total.trace_seconds,
               1e3 * total.shade_seconds, total_seconds > 0 ? rays / total_seconds * 1e-6 : 0.0);
    fmt::print("wrote      {}\n", FrameFileName(out, args.frames - 1));
  }
  return 0;
}

int Main(int argc, char** argv) {
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
  render->add_option("--out", r.out,
                     "output image (default SCENE.png); a '#' becomes the frame number and "
                     "writes every frame, otherwise only the last frame is written");
  render->add_option("--backend", r.backend, "scheduler: serial")->capture_default_str();
  render->add_option("--task-size", r.task_size, "rays per task")
      ->check(CLI::Range(1, 1 << 20))
      ->capture_default_str();
  render->add_option("--order", r.order, "primary ray order")
      ->check(CLI::IsMember({"scanline", "block"}))
      ->capture_default_str();
  render->add_option("--cutoff", r.cutoff, "drop secondary rays whose weight is below this")
      ->capture_default_str();
  render->add_option("--lambda", r.lambda, "grid density: cells per triangle")
      ->check(CLI::Range(0.01f, 64.0f))
      ->capture_default_str();
  render->add_option("--stats", r.stats, "write per-frame statistics as JSON to this file");
  render->add_flag("--quiet,-q", r.quiet, "print nothing on success");

  InfoArgs i;
  CLI::App* info = app.add_subcommand("info", "print a scene's size, grid and features");
  info->add_option("--scene", i.scene, scene_help)->capture_default_str();
  info->add_flag("--json", i.json, "print JSON");
  info->add_option("--lambda", i.lambda, "grid density: cells per triangle")
      ->check(CLI::Range(0.01f, 64.0f))
      ->capture_default_str();

  CLI::App* scenes = app.add_subcommand("scenes", "list built-in scenes and the search path");

  CLI11_PARSE(app, argc, argv);
  try {
    if (*render) return RunRender(r);
    if (*info) return RunInfo(i);
    if (*scenes) {
      fmt::print("procedural:");
      for (const auto& n : ProceduralSceneNames()) fmt::print(" {}", n);
      fmt::print("\nscene files:");
      for (const auto& n : BuiltinSceneFileNames()) fmt::print(" {}", n);
      fmt::print("\nsearch path ($RAYSTREAM_SCENES first):\n");
      for (const auto& d : SceneSearchPath()) fmt::print("  {}\n", d);
      return 0;
    }
  } catch (const Error& e) {
    fmt::print(stderr, "raystream: error: {}\n", e.what());
    return 1;
  } catch (const std::exception& e) {
    fmt::print(stderr, "raystream: internal error: {}\n", e.what());
    return 2;
  }
  return 0;
}

}  // namespace
}  // namespace rs

int main(int argc, char** argv) { return rs::Main(argc, argv); }
