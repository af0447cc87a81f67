// Run time against image error: renders spherebox and erw6 with the serial reference renderer
// for maximum depth 0..9 and weight cutoffs {0, 1e-3, 1e-2, 5e-2}, and measures each image's
// RMSE and PSNR against a depth-16, cutoff-0 render. Writes depth_sweep.csv and depth_sweep.md
// (tables + the "depth at which PSNR exceeds 40 dB" headline) to --out;
// bench/scripts/plot_depth_sweep.py draws time against error from the CSV. `--quick` (the meson
// benchmark smoke run) uses a small image and depths 0..3. PSNR uses peak 1.0 (display white) over
// the linear rgb floats.
// Time is the render thread's CPU time (CLOCK_THREAD_CPUTIME_ID; the serial renderer runs on
// one thread), the minimum over --reps renders: on a shared 2-core machine wall time mostly
// measures the other processes. The CSV also has the frame wall time.
#include <fmt/format.h>
#include <time.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <limits>
#include <string>
#include <vector>

#include "scenes/load.h"
#include "sched/render.h"

namespace rs::bench {
namespace {

struct Config {
  int width = 256;
  int height = 256;
  int max_depth = 9;      // sweep 0..max_depth
  int ref_depth = 16;     // the reference image
  int reps = 3;           // time = minimum over reps renders
  std::vector<std::string> scenes{"spherebox", "erw6"};
  std::vector<float> cutoffs{0.0f, 1e-3f, 1e-2f, 5e-2f};
  std::string out = ".";
};

struct Row {
  std::string scene;
  int depth = 0;
  float cutoff = 0;
  double seconds = 0;       // thread CPU time
  double wall_seconds = 0;  // frame wall time (FrameStats::total_seconds)
  double shade_seconds = 0;
  uint64_t rays = 0;
  uint64_t bounce_rays = 0;  // reflection + refraction rays traced
  uint64_t culled = 0;
  double rmse = 0;
  double psnr = 0;
};

double Rmse(const std::vector<float>& a, const std::vector<float>& b) {
  double sum = 0;
  for (size_t i = 0; i < a.size(); ++i) {
    const double d = static_cast<double>(a[i]) - static_cast<double>(b[i]);
    sum += d * d;
  }
  return a.empty() ? 0.0 : std::sqrt(sum / static_cast<double>(a.size()));
}

double Psnr(double rmse) {
  return rmse > 0 ? 20.0 * std::log10(1.0 / rmse) : std::numeric_limits<double>::infinity();
}

double ThreadCpuSeconds() {
  timespec ts;
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return static_cast<double>(ts.tv_sec) + 1e-9 * static_cast<double>(ts.tv_nsec);
}

// Renders `reps` times (the same image every time: the renderer is deterministic) and keeps the
// stats of the render with the least CPU time, which goes to *cpu_seconds.
RenderResult Render(const Scene& scene, const Accel& accel, int depth, float cutoff,
                    const Config& c, double* cpu_seconds) {
  RenderOptions o;
  o.width = c.width;
  o.height = c.height;
  o.max_depth = depth;
  o.weight_cutoff = cutoff;
  RenderResult best;
  for (int r = 0; r < std::max(1, c.reps); ++r) {
    const double t0 = ThreadCpuSeconds();
    RenderResult res = RenderImage(scene, accel, scene.camera, o);
    const double cpu = ThreadCpuSeconds() - t0;
    if (r == 0 || cpu < *cpu_seconds) {
      best = std::move(res);
      *cpu_seconds = cpu;
    }
  }
  return best;
}

std::string Fmt(double psnr) { return std::isinf(psnr) ? "inf" : fmt::format("{:.1f}", psnr); }

int Main(int argc, char** argv) {
  Config c;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&]() -> std::string {
      if (i + 1 >= argc) {
        std::fprintf(stderr, "depth_sweep_bench: %s needs a value\n", a.c_str());
        std::exit(2);
      }
      return argv[++i];
    };
    if (a == "--quick") {
      c.width = c.height = 64;
      c.max_depth = 3;
      c.ref_depth = 8;
      c.reps = 1;
    } else if (a == "--out") {
      c.out = next();
    } else if (a == "--size") {
      c.width = c.height = std::atoi(next().c_str());
    } else if (a == "--reps") {
      c.reps = std::atoi(next().c_str());
    } else if (a == "--max-depth") {
      c.max_depth = std::atoi(next().c_str());
    } else {
      std::fprintf(stderr,
                   "usage: depth_sweep_bench [--quick] [--out DIR] [--size N] [--reps N] "
                   "[--max-depth N]\n");
      return 2;
    }
  }
  std::filesystem::create_directories(c.out);
  std::vector<Row> rows;
  std::vector<double> ref_seconds;
  for (const std::string& name : c.scenes) {
    const Scene scene = LoadScene(name);
    const Accel accel(scene.mesh());
    double ref_cpu = 0;
    const RenderResult ref = Render(scene, accel, c.ref_depth, 0.0f, c, &ref_cpu);
    ref_seconds.push_back(ref_cpu);
    std::printf("%s: reference depth %d cutoff 0: %.3f s CPU, %llu rays\n", name.c_str(),
                c.ref_depth, ref_cpu,
                static_cast<unsigned long long>(ref.stats.TotalRays()));
    for (const float cutoff : c.cutoffs) {
      for (int depth = 0; depth <= c.max_depth; ++depth) {
        double cpu = 0;
        const RenderResult r = Render(scene, accel, depth, cutoff, c, &cpu);
        Row row;
        row.scene = name;
        row.depth = depth;
        row.cutoff = cutoff;
        row.seconds = cpu;
        row.wall_seconds = r.stats.total_seconds;
        row.shade_seconds = r.stats.shade_seconds;
        row.rays = r.stats.TotalRays();
        row.bounce_rays = r.stats.rays[static_cast<int>(RayKind::kReflection)] +
                          r.stats.rays[static_cast<int>(RayKind::kRefraction)];
        row.culled = r.stats.shade.culled;
        row.rmse = Rmse(r.rgb, ref.rgb);
        row.psnr = Psnr(row.rmse);
        std::printf("  depth %d cutoff %g: %.4f s CPU  rays %llu  rmse %.3g  psnr %s dB\n", depth,
                    static_cast<double>(cutoff), row.seconds,
                    static_cast<unsigned long long>(row.rays), row.rmse, Fmt(row.psnr).c_str());
        rows.push_back(row);
      }
    }
  }

  // CSV: one row per (scene, cutoff, depth).
  {
    std::ofstream csv(c.out + "/depth_sweep.csv");
    csv << "scene,width,height,max_depth,cutoff,seconds,wall_seconds,shade_seconds,rays,"
           "bounce_rays,culled,rmse,psnr_db\n";
    for (const Row& r : rows) {
      csv << fmt::format("{},{},{},{},{},{:.6f},{:.6f},{:.6f},{},{},{},{:.6g},{}\n", r.scene,
                         c.width, c.height, r.depth, r.cutoff, r.seconds, r.wall_seconds,
                         r.shade_seconds, r.rays, r.bounce_rays, r.culled, r.rmse, Fmt(r.psnr));
    }
  }
  // Markdown: per scene, depth x cutoff tables of time and PSNR, and the 40 dB headline.
  std::ofstream md(c.out + "/depth_sweep.md");
  md << fmt::format(
      "# Run time against error: maximum depth x weight cutoff\n\n"
      "Serial reference renderer (rs::RenderImage, SIMD shading, dynamic dispatch), {}x{} "
      "pixels, time = render thread CPU time, least of {} renders (the machine is shared; "
      "wall times are in the CSV). Error against a depth-{} cutoff-0 render: RMSE over linear "
      "rgb, PSNR = 20 log10(1 / RMSE) (peak 1.0). Ray counts are in the CSV.\n\n",
      c.width, c.height, std::max(1, c.reps), c.ref_depth);
  for (size_t si = 0; si < c.scenes.size(); ++si) {
    const std::string& name = c.scenes[si];
    md << fmt::format("## {} (reference: depth {}, {:.3f} s CPU)\n\n", name, c.ref_depth,
                      ref_seconds[si]);
    md << "| depth |";
    for (const float cut : c.cutoffs) md << fmt::format(" time ms (cutoff {}) | PSNR dB |", cut);
    md << "\n|---|";
    for (size_t k = 0; k < c.cutoffs.size(); ++k) md << "---|---|";
    md << "\n";
    for (int depth = 0; depth <= c.max_depth; ++depth) {
      md << fmt::format("| {} |", depth);
      for (const float cut : c.cutoffs) {
        for (const Row& r : rows) {
          if (r.scene == name && r.depth == depth && r.cutoff == cut) {
            md << fmt::format(" {:.1f} | {} |", 1e3 * r.seconds, Fmt(r.psnr));
          }
        }
      }
      md << "\n";
    }
    md << "\n";
    for (const float cut : c.cutoffs) {
      const Row* at40 = nullptr;
      const Row* deepest = nullptr;
      for (const Row& r : rows) {
        if (r.scene != name || r.cutoff != cut) continue;
        if (at40 == nullptr && r.psnr > 40.0) at40 = &r;
        if (r.depth == c.max_depth) deepest = &r;
      }
      if (at40 != nullptr && deepest != nullptr) {
        md << fmt::format(
            "- cutoff {}: PSNR exceeds 40 dB from depth {} ({:.1f} dB, {:.1f} ms = {:.0f}% of "
            "depth {}'s {:.1f} ms, {} dB)\n",
            cut, at40->depth, at40->psnr, 1e3 * at40->seconds,
            100.0 * at40->seconds / deepest->seconds, c.max_depth, 1e3 * deepest->seconds,
            Fmt(deepest->psnr));
      } else {
        md << fmt::format("- cutoff {}: PSNR never exceeds 40 dB up to depth {}\n", cut,
                          c.max_depth);
      }
    }
    md << "\n";
  }
  std::printf("wrote %s/depth_sweep.csv and %s/depth_sweep.md\n", c.out.c_str(), c.out.c_str());
  return 0;
}

}  // namespace
}  // namespace rs::bench

int main(int argc, char** argv) {
  try {
    return rs::bench::Main(argc, argv);
  } catch (const rs::Error& e) {
    std::fprintf(stderr, "depth_sweep_bench: %s\n", e.what());
    return 1;
  }
}
