// Host scheduler measurements written as CSV tables (plotted by bench/scripts/sched_plot.py): the
// iRT paper's fps / speed-up against threads (Figs. 3-5), idle time per thread (Fig. 6) and
// aggregate queue time (Fig. 7); the Cell paper's tile sizes and shapes (Fig. 3); the PBT paper's
// prediction accuracy (Table 1), frame imbalance static vs PBT, and PBT-Greedy / PBT-Visit vs
// PBT-Random on amphitheater:1 and :32 (Fig. 4).
// Usage: sched_bench --out DIR [--quick] [--only LIST].
#include <fmt/core.h>
#include <fmt/ranges.h>
#include <sys/resource.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <map>
#include <memory>
#include <numeric>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "include/raystream/raystream.h"
#include "scenes/load.h"
#include "sched/backends.h"
#include "sched/render.h"

namespace rs {
namespace {

struct Args {
  std::string out = "sched_results";
  bool quick = false;  // tiny sizes: checks the pipeline, numbers mean nothing
  std::set<std::string> only;
  // --only pbt: the tile costs fed to PBT (--pbt-costs work,cpu,wall) and the rays per kernel
  // call (--pbt-batches 1024,20: the default batch, whose coherent 64-ray packets make a tile's
  // cost vary more from frame to frame, and the iRT paper's 20, per-ray traversal like the
  // PBT paper's tracer).
  std::vector<PbtCost> pbt_costs = {PbtCost::kWork, PbtCost::kCpu, PbtCost::kWall};
  std::vector<int> pbt_batches = {RenderOptions{}.batch, 20};
  int pbt_size = 512;  // --pbt-size: the image's width and height (the PBT paper's 512x512)
  // --pbt-predict paper,costmap: PBT-Update's predictors (tile_plan.h PbtPredict); the paper's
  // is the Table 1 row as published, the cost map the default of the renderer.
  std::vector<PbtPredict> pbt_predicts = {PbtPredict::kPaper, PbtPredict::kCostMap};
  int pbt_block = BackendOptions{}.pbt_cost_block;  // --pbt-block: the cost map's block
  bool pbt_reproject = true;  // --pbt-reproject 0: no next camera (the map is not moved)
  // --pbt-assigns: the assignments of the work and cpu rows (default all five).
  std::vector<PbtAssign> pbt_assigns = {PbtAssign::kStatic, PbtAssign::kRandom, PbtAssign::kGreedy,
                                        PbtAssign::kVisit, PbtAssign::kCounter, PbtAssign::kLpt};
  // --pbt-backends tiles,lock,lfree,local: the backends of the PBT rows. The queue backends feed
  // PBT their tiles' work only (no time of their own): their rows are the work cost's.
  std::vector<BackendKind> pbt_backends = {BackendKind::kTiles};
};

bool Want(const Args& a, const std::string& part) { return a.only.empty() || a.only.count(part); }

bool HaveScene(const std::string& file) {
  try {
    FindSceneFile(file);
    return true;
  } catch (const Error& e) {
    fmt::print("skipped: {}\n", e.what());
    return false;
  }
}

std::string LoadAverage() {
  std::ifstream f("/proc/loadavg");
  std::string one, five, fifteen;
  f >> one >> five >> fifteen;
  return one.empty() ? "?" : one + " " + five + " " + fifteen;
}

// User + system CPU time of the whole process (all threads).
double ProcessCpuSeconds() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return static_cast<double>(u.ru_utime.tv_sec + u.ru_stime.tv_sec) +
         1e-6 * static_cast<double>(u.ru_utime.tv_usec + u.ru_stime.tv_usec);
}

double Median(std::vector<double> v) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  const size_t n = v.size();
  return n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

double Mean(const std::vector<double>& v) {
  return v.empty() ? 0.0 : std::accumulate(v.begin(), v.end(), 0.0) / static_cast<double>(v.size());
}

struct Loaded {
  Scene scene;
  std::unique_ptr<Accel> accel;
};

Loaded Load(const std::string& name) {
  Loaded l{LoadScene(name), nullptr};
  l.accel = std::make_unique<Accel>(l.scene.mesh());
  return l;
}

RenderOptions Options(int w, int h) {
  RenderOptions o;
  o.width = w;
  o.height = h;
  o.max_depth = 4;
  return o;
}

class Csv {
 public:
  Csv(const std::filesystem::path& path, const std::string& header) : f_(path) {
    if (!f_) throw Error(path.string() + ": cannot write");
    f_ << header << "\n";
    fmt::print("  -> {}\n", path.string());
  }
  template <class... T>
  void Row(fmt::format_string<T...> format, T&&... args) {
    f_ << fmt::format(format, std::forward<T>(args)...) << "\n";
    f_.flush();
  }

 private:
  std::ofstream f_;
};

// ---------------------------------------------------------------------------------------------
// iRT Figs. 3-7: every backend at 1, 2, 4, 8 threads, frames interleaved across configurations
// (round r renders one frame with every renderer) so background load hits them alike.

struct Config {
  BackendOptions options;
  std::string label;  // "LOCK" ...
  std::unique_ptr<HostRenderer> renderer;
  std::vector<double> seconds, cpu, est, thread_cpu, idle_per_thread, queue, imbalance, mrays;
  std::vector<std::vector<double>> thread_idle, thread_busy, thread_queue;  // [thread][frame]
};

void Scaling(const Args& a, const std::filesystem::path& dir) {
  const unsigned cores = std::max(1u, std::thread::hardware_concurrency());
  const std::vector<std::string> scenes =
      a.quick ? std::vector<std::string>{"cornell"}
              : std::vector<std::string>{"bunny", "conference", "office-graz"};
  const int size = a.quick ? 48 : 300;
  const int rounds = a.quick ? 2 : 4;  // the first is warm-up
  const std::vector<int> threads = {1, 2, 4, 8};
  Csv table(dir / "scaling.csv",
            "scene,backend,threads,frames,median_ms,min_ms,fps,speedup,efficiency,speedup_self,"
            "mrays_per_s,cpu_ms,cpu_utilization,est_ms,est_fps,est_speedup,est_efficiency,"
            "work_inflation,idle_ms_per_thread,queue_ms_aggregate,imbalance,load_avg");
  Csv per_thread(dir / "idle_threads.csv", "scene,backend,threads,thread,idle_ms,busy_ms,queue_ms");
  for (const std::string& name : scenes) {
    if (name != "cornell" && !HaveScene(name == "bunny"        ? "bunny/bun_zipper.ply"
                                        : name == "conference" ? "conference/conference.obj"
                                                               : "office-graz/office-graz.obj")) {
      continue;
    }
    const Loaded l = Load(name);
    const RenderOptions ro = Options(size, size);
    const FrameContext ctx =
        MakeFrameContext(l.scene, *l.accel, l.scene.path.At(0, 1.0f, l.scene.camera), ro);
    std::vector<Config> configs;
    auto add = [&](BackendKind kind, int n, const std::string& label) {
      Config c;
      c.options.kind = kind;
      c.options.threads = n;
      c.label = label;
      c.renderer = std::make_unique<HostRenderer>(c.options);
      c.thread_idle.resize(static_cast<size_t>(n));
      c.thread_busy.resize(static_cast<size_t>(n));
      c.thread_queue.resize(static_cast<size_t>(n));
      configs.push_back(std::move(c));
    };
    add(BackendKind::kSerial, 1, "serial");
    for (const int n : threads) {
      add(BackendKind::kLock, n, "LOCK");
      add(BackendKind::kLockFree, n, "LFREE");
      add(BackendKind::kLocal, n, "LOCAL");
      add(BackendKind::kTiles, n, "TILES32");
    }
    Framebuffer fb(size, size);
    const std::string load_before = LoadAverage();
    fmt::print("scaling {} {}x{}: {} configurations x {} rounds (load {})\n", name, size, size,
               configs.size(), rounds, load_before);
    for (int r = 0; r < rounds; ++r) {
      for (Config& c : configs) {
        fb.Clear();
        const double cpu0 = ProcessCpuSeconds();
        const HostFrameStats& s = c.renderer->RenderFrame(ctx, fb);
        const double cpu = ProcessCpuSeconds() - cpu0;
        if (r == 0) continue;
        c.seconds.push_back(s.total.total_seconds);
        c.cpu.push_back(cpu);
        c.est.push_back(s.ContentionFreeSeconds(static_cast<int>(cores)));
        double thread_cpu = s.app_cpu_seconds;
        for (const ThreadStats& t : s.threads) thread_cpu += t.cpu_seconds;
        c.thread_cpu.push_back(thread_cpu);
        c.mrays.push_back(s.total.MraysPerSecond());
        c.idle_per_thread.push_back(s.IdleSeconds() / static_cast<double>(s.threads.size()));
        c.queue.push_back(s.QueueSeconds());
        c.imbalance.push_back(s.imbalance);
        for (size_t t = 0; t < s.threads.size(); ++t) {
          c.thread_idle[t].push_back(s.threads[t].idle_seconds);
          c.thread_busy[t].push_back(s.threads[t].busy_seconds);
          c.thread_queue[t].push_back(s.threads[t].queue_seconds);
        }
      }
    }
    const std::string load = LoadAverage();
    const double serial = Median(configs[0].seconds);
    const double serial_est = Median(configs[0].est);
    const double serial_cpu = Median(configs[0].thread_cpu);
    std::map<std::string, double> one_thread;  // backend -> median seconds at 1 thread
    for (const Config& c : configs) {
      if (c.options.threads == 1) one_thread[c.label] = Median(c.seconds);
    }
    for (Config& c : configs) {
      const double med = Median(c.seconds);
      const double speedup = med > 0 ? serial / med : 0;
      const double self = med > 0 ? one_thread[c.label] / med : 0;
      const double cpu = Median(c.cpu);
      const double est = Median(c.est);
      const double est_speedup = est > 0 ? serial_est / est : 0;
      table.Row(
          "{},{},{},{},{:.3f},{:.3f},{:.3f},{:.3f},{:.3f},{:.3f},{:.3f},{:.3f},{:.3f},{:.3f},"
          "{:.3f},{:.3f},{:.3f},{:.3f},{:.4f},{:.4f},{:.4f},{}",
          name, c.label, c.options.threads, c.seconds.size(), 1e3 * med,
          1e3 * *std::min_element(c.seconds.begin(), c.seconds.end()), med > 0 ? 1.0 / med : 0,
          speedup, speedup / c.options.threads, self, Median(c.mrays), 1e3 * cpu,
          med > 0 ? cpu / med : 0, 1e3 * est, est > 0 ? 1.0 / est : 0, est_speedup,
          est_speedup / c.options.threads, serial_cpu > 0 ? Median(c.thread_cpu) / serial_cpu : 0,
          1e3 * Mean(c.idle_per_thread), 1e3 * Mean(c.queue), Mean(c.imbalance), load);
      for (size_t t = 0; t < c.thread_idle.size(); ++t) {
        per_thread.Row("{},{},{},{},{:.4f},{:.4f},{:.4f}", name, c.label, c.options.threads, t,
                       1e3 * Mean(c.thread_idle[t]), 1e3 * Mean(c.thread_busy[t]),
                       1e3 * Mean(c.thread_queue[t]));
      }
      fmt::print(
          "  {:8s} {} thr: {:8.1f} ms  speed-up {:.2f} (self {:.2f})  cpu {:.2f} cores  "
          "contention-free {:.1f} ms, speed-up {:.2f}  idle/thread {:.2f} ms  queue {:.2f} ms\n",
          c.label, c.options.threads, 1e3 * med, speedup, self, med > 0 ? cpu / med : 0, 1e3 * est,
          est_speedup, 1e3 * Mean(c.idle_per_thread), 1e3 * Mean(c.queue));
      std::fflush(stdout);
    }
  }
}

// ---------------------------------------------------------------------------------------------
// Cell paper Fig. 3: tile sizes and shapes (atomic tile counter), 2 threads.

void TileShapes(const Args& a, const std::filesystem::path& dir) {
  const std::string name = a.quick ? "cornell" : "office-graz";
  if (!a.quick && !HaveScene("office-graz/office-graz.obj")) return;
  const int w = a.quick ? 64 : 640, h = a.quick ? 48 : 480;
  const int rounds = a.quick ? 2 : 4;
  const int threads = 2;
  struct Shape {
    int tw, th;
    const char* family;
  };
  const std::vector<Shape> shapes = {{8, 8, "square"},   {16, 16, "square"}, {32, 32, "square"},
                                     {64, 64, "square"}, {40, 32, "1280px"}, {80, 16, "1280px"},
                                     {160, 8, "1280px"}, {320, 4, "1280px"}, {640, 2, "1280px"},
                                     {640, 1, "row"}};
  const Loaded l = Load(name);
  const FrameContext ctx =
      MakeFrameContext(l.scene, *l.accel, l.scene.path.At(0, 1.0f, l.scene.camera), Options(w, h));
  Csv table(dir / "tiles.csv",
            "scene,width,height,threads,shape,family,tile_w,tile_h,tiles,median_ms,fps,est_ms,"
            "counter_us_per_frame,idle_ms_per_thread,imbalance,mean_tile_ms,mean_tile_cpu_ms,"
            "load_avg");
  std::vector<std::unique_ptr<HostRenderer>> renderers;
  std::vector<std::vector<HostFrameStats>> stats(shapes.size());
  for (const Shape& s : shapes) {
    BackendOptions o;
    o.kind = BackendKind::kTiles;
    o.threads = threads;
    o.tile_width = s.tw;
    o.tile_height = s.th;
    renderers.push_back(std::make_unique<HostRenderer>(o));
  }
  fmt::print("tile shapes {} {}x{}, {} threads (load {})\n", name, w, h, threads, LoadAverage());
  Framebuffer fb(w, h);
  for (int r = 0; r < rounds; ++r) {
    for (size_t i = 0; i < shapes.size(); ++i) {
      fb.Clear();
      const HostFrameStats& s = renderers[i]->RenderFrame(ctx, fb);
      if (r > 0) stats[i].push_back(s);
    }
  }
  for (size_t i = 0; i < shapes.size(); ++i) {
    std::vector<double> sec, est, counter, idle, imb, tile, tile_cpu;
    for (const HostFrameStats& s : stats[i]) {
      sec.push_back(s.total.total_seconds);
      est.push_back(s.ContentionFreeSeconds(2));
      counter.push_back(s.QueueSeconds());
      idle.push_back(s.IdleSeconds() / threads);
      imb.push_back(s.imbalance);
      double t = 0, c = 0;
      for (const TileRecord& rec : s.tiles) {
        t += rec.seconds;
        c += rec.cpu_seconds;
      }
      const double n = s.tiles.empty() ? 1.0 : static_cast<double>(s.tiles.size());
      tile.push_back(t / n);
      tile_cpu.push_back(c / n);
    }
    const double med = Median(sec);
    table.Row(
        "{},{},{},{},{}x{},{},{},{},{},{:.3f},{:.3f},{:.3f},{:.2f},{:.3f},{:.4f},{:.4f},{:.4f},{}",
        name, w, h, threads, shapes[i].tw, shapes[i].th, shapes[i].family, shapes[i].tw,
        shapes[i].th, stats[i].front().tiles.size(), 1e3 * med, 1.0 / med, 1e3 * Median(est),
        1e6 * Mean(counter), 1e3 * Mean(idle), Mean(imb), 1e3 * Mean(tile), 1e3 * Mean(tile_cpu),
        LoadAverage());
    fmt::print(
        "  {:>4}x{:<3} {:5} tiles {:8.1f} ms (contention-free {:.1f} ms)  counter {:.1f} us\n",
        shapes[i].tw, shapes[i].th, stats[i].front().tiles.size(), 1e3 * med, 1e3 * Median(est),
        1e6 * Mean(counter));
  }
}

// ---------------------------------------------------------------------------------------------
// PBT paper: prediction accuracy over a walk-through (Table 1) and frame imbalance, static
// tiling vs PBT-Random / Greedy / Visit; n = 32 PBT workers (the paper's) run by 2 threads. Tile
// costs fed to PBT: work (the deterministic count, sched/tile_plan.h: the same numbers in every
// run, whatever the load), cpu (the rendering thread's CPU time) and wall (the paper's). With
// the work cost the accuracy does not depend on the assignment (the tiling does not), so the
// assignments differ only in their imbalance. Imbalance: worker = slowest / mean of the
// workers' lists as assigned (no stealing); demand = the paper's demand-driven master-worker
// (§2, with the §4 affinity) on the measured costs (TilePlanReport::demand_imbalance); counter
// (not in the paper): no lists, the n workers take the tiles costliest-predicted first. Queue
// backends (--pbt-backends): the same walk-throughs with the PBT tiles feeding lock / lfree /
// local queues, work cost only (their tiles' rays, and the cost map of their rays per block).
void PbtAccuracy(const Args& a, const std::filesystem::path& dir) {
  const std::string name = "erw6";
  const int size = a.quick ? 64 : a.pbt_size;
  const int frames = a.quick ? 4 : 20;
  const int workers = a.quick ? 4 : 32;
  const Loaded l = Load(name);
  Csv table(dir / "pbt.csv",
            "scene,size,batch,clock,assign,k,speed,workers,threads,frames,within5,within10,"
            "within15,worker_imbalance,demand_imbalance,thread_imbalance,median_ms,update_steps,"
            "load_avg,predict,block,lpt_imbalance,backend");
  Csv per_frame(dir / "pbt_frames.csv",
                "batch,clock,assign,k,speed,frame,within5,within10,within15,worker_imbalance,"
                "demand_imbalance,variance_before,variance_after,steps,ms,predict,lpt_imbalance,"
                "backend");
  fmt::print("PBT {} {}x{}, n = {} workers on 2 threads, {} frames (load {})\n", name, size, size,
             workers, frames, LoadAverage());
  struct Run {
    PbtCost cost;
    PbtAssign assign;
    PbtPredict predict;
    BackendKind backend;
  };
  std::vector<Run> runs;
  for (const BackendKind backend : a.pbt_backends) {
    for (const PbtPredict predict : a.pbt_predicts) {
      for (const PbtCost cost : a.pbt_costs) {
        // The queue backends' tiles have no time of their own: work rows only.
        if (backend != BackendKind::kTiles && cost != PbtCost::kWork) continue;
        if (cost == PbtCost::kWall) {
          runs.push_back({cost, PbtAssign::kRandom, predict, backend});  // noisy: one assignment
          continue;
        }
        for (const PbtAssign as : a.pbt_assigns) {
          // static is never updated: it has no predictor, one run is enough.
          if (as == PbtAssign::kStatic && predict != a.pbt_predicts.front()) continue;
          runs.push_back({cost, as, predict, backend});
        }
      }
    }
  }
  for (const int batch : a.pbt_batches) {
    for (const Run& run : runs) {
      const BackendKind kind = run.backend;
      for (const int k : {1, 4}) {
        for (const float speed : {1.0f, 2.0f}) {
          BackendOptions o;
          o.kind = kind;
          o.threads = 2;
          o.pbt_tiles_per_worker = k;
          o.pbt_workers = workers;
          o.assign = run.assign;
          o.pbt_cost = run.cost;
          o.pbt_predict = run.predict;
          o.pbt_cost_block = a.pbt_block;
          o.seed = 12345;
          HostRenderer r(o);
          Framebuffer fb(size, size);
          RenderOptions ro = Options(size, size);
          ro.batch = batch;
          std::vector<double> w5, w10, w15, wimb, dimb, timb, ms, steps, limb;
          for (int f = 0; f < frames; ++f) {
            const Camera cam = l.scene.path.At(f, speed, l.scene.camera);
            fb.Clear();
            FrameContext ctx = MakeFrameContext(l.scene, *l.accel, cam, ro);
            if (a.pbt_reproject && f + 1 < frames) SetNextCamera(ctx, l.scene.path.At(f + 1, speed, l.scene.camera));
            const HostFrameStats& s = r.RenderFrame(ctx, fb);
            per_frame.Row(
                "{},{},{},{},{},{},{:.4f},{:.4f},{:.4f},{:.4f},{:.4f},{:.6g},{:.6g},{},{:.3f},{},"
                "{:.4f},{}",
                batch, PbtCostName(run.cost), PbtAssignName(run.assign), k, speed, f,
                s.accuracy.within5, s.accuracy.within10, s.accuracy.within15, s.worker_imbalance,
                s.demand_imbalance, s.update.variance_before, s.update.variance_after,
                s.update.steps, 1e3 * s.total.total_seconds, PbtPredictName(run.predict),
                s.lpt_imbalance, BackendName(kind));
            if (f == 0) continue;  // no prediction yet; and warm-up
            w5.push_back(s.accuracy.within5);
            w10.push_back(s.accuracy.within10);
            w15.push_back(s.accuracy.within15);
            wimb.push_back(s.worker_imbalance);
            dimb.push_back(s.demand_imbalance);
            timb.push_back(s.imbalance);
            ms.push_back(s.total.total_seconds);
            steps.push_back(s.update.steps);
            limb.push_back(s.lpt_imbalance);
          }
          table.Row(
              "{},{},{},{},{},{},{},{},{},{},{:.4f},{:.4f},{:.4f},{:.4f},{:.4f},{:.4f},{:.3f},{:."
              "2f},{},{},{},{:.4f},{}",
              name, size, batch, PbtCostName(run.cost), PbtAssignName(run.assign), k, speed,
              workers, o.threads, frames - 1, Mean(w5), Mean(w10), Mean(w15), Mean(wimb),
              Mean(dimb), Mean(timb), 1e3 * Median(ms), Mean(steps), LoadAverage(),
              PbtPredictName(run.predict), a.pbt_block, Mean(limb), BackendName(kind));
          fmt::print(
              "  {:5} batch {:4} {:4} {:7} {:7} k={} x{}: within 5/10/15 % = {:.1f} / {:.1f} / "
              "{:.1f} %, imbalance worker {:.3f} demand {:.3f} lpt {:.3f}\n",
              BackendName(kind), batch, PbtCostName(run.cost), PbtPredictName(run.predict),
              PbtAssignName(run.assign), k, speed, 100 * Mean(w5), 100 * Mean(w10), 100 * Mean(w15),
              Mean(wimb), Mean(dimb), Mean(limb));
        }
      }
    }
  }
}

// Calibration of the deterministic tile cost (sched/tile_plan.h TileWorkCost): every tile's CPU
// time against its four counts (rays, cell steps, triangle tests, shading calls), one render
// thread, a few frames of several procedural scenes; non-negative least squares without
// intercept. Writes calibrate.csv (one row per tile) and calibrate.txt (coefficients, fit
// quality, the line for tile_plan.cc). The first frame of each scene is a warm-up, not used.

// Solves the normal equations A^T A x = A^T b (columns scaled to unit norm first) by Gaussian
// elimination with partial pivoting.
std::vector<double> LeastSquares(const std::vector<std::vector<double>>& a,
                                 const std::vector<double>& b) {
  const size_t n = a.empty() ? 0 : a[0].size();
  std::vector<double> scale(n, 0.0);
  for (const auto& row : a) {
    for (size_t j = 0; j < n; ++j) scale[j] += row[j] * row[j];
  }
  for (double& x : scale) x = x > 0 ? 1.0 / std::sqrt(x) : 1.0;
  std::vector<std::vector<double>> m(n, std::vector<double>(n + 1, 0.0));
  for (size_t r = 0; r < a.size(); ++r) {
    for (size_t i = 0; i < n; ++i) {
      for (size_t j = 0; j < n; ++j) m[i][j] += a[r][i] * scale[i] * a[r][j] * scale[j];
      m[i][n] += a[r][i] * scale[i] * b[r];
    }
  }
  for (size_t c = 0; c < n; ++c) {
    size_t pivot = c;
    for (size_t r = c + 1; r < n; ++r) {
      if (std::abs(m[r][c]) > std::abs(m[pivot][c])) pivot = r;
    }
    std::swap(m[c], m[pivot]);
    if (m[c][c] == 0) continue;
    for (size_t r = 0; r < n; ++r) {
      if (r == c) continue;
      const double f = m[r][c] / m[c][c];
      for (size_t k = c; k <= n; ++k) m[r][k] -= f * m[c][k];
    }
  }
  std::vector<double> x(n, 0.0);
  for (size_t i = 0; i < n; ++i) x[i] = m[i][i] != 0 ? m[i][n] / m[i][i] * scale[i] : 0.0;
  return x;
}

void Calibrate(const Args& a, const std::filesystem::path& dir) {
  const std::vector<std::string> scenes =
      a.quick ? std::vector<std::string>{"cornell"}
              : std::vector<std::string>{"erw6", "cornell", "spherebox", "amphitheater:4"};
  const int size = a.quick ? 48 : 256;
  const int frames = a.quick ? 2 : 4;  // the first is a warm-up
  Csv table(dir / "calibrate.csv",
            "scene,frame,x0,y0,x1,y1,rays,cell_steps,triangle_tests,shading_calls,cpu_seconds,"
            "seconds");
  std::vector<std::vector<double>> rows;
  std::vector<double> cpu;
  fmt::print("calibration: {} at {}x{}, 16x16 tiles, 1 render thread (load {})\n",
             fmt::format("{}", fmt::join(scenes, ", ")), size, size, LoadAverage());
  for (const std::string& name : scenes) {
    const Loaded l = Load(name);
    BackendOptions o;
    o.kind = BackendKind::kTiles;
    o.threads = 1;
    o.tile_width = o.tile_height = 16;
    HostRenderer r(o);
    Framebuffer fb(size, size);
    for (int f = 0; f < frames; ++f) {
      fb.Clear();
      const Camera cam = l.scene.path.At(f, 1.0f, l.scene.camera);
      const HostFrameStats& s =
          r.RenderFrame(MakeFrameContext(l.scene, *l.accel, cam, Options(size, size)), fb);
      if (f == 0) continue;
      for (const TileRecord& t : s.tiles) {
        const TileWork& w = t.counts;
        table.Row("{},{},{},{},{},{},{},{},{},{},{:.9f},{:.9f}", name, f, t.tile.x0, t.tile.y0,
                  t.tile.x1, t.tile.y1, w.rays, w.cell_steps, w.triangle_tests, w.shading_calls,
                  t.cpu_seconds, t.seconds);
        rows.push_back({static_cast<double>(w.rays), static_cast<double>(w.cell_steps),
                        static_cast<double>(w.triangle_tests),
                        static_cast<double>(w.shading_calls)});
        cpu.push_back(t.cpu_seconds);
      }
    }
  }
  // Non-negative least squares by elimination: a count whose coefficient comes out negative
  // (collinear with the others, e.g. shading calls with rays) is dropped and the rest refitted.
  std::vector<bool> used(4, true);
  std::vector<double> x(4, 0.0);
  for (;;) {
    std::vector<size_t> cols;
    for (size_t j = 0; j < 4; ++j) {
      if (used[j]) cols.push_back(j);
    }
    std::vector<std::vector<double>> sub;
    for (const auto& row : rows) {
      std::vector<double> r;
      for (const size_t j : cols) r.push_back(row[j]);
      sub.push_back(r);
    }
    const std::vector<double> y = LeastSquares(sub, cpu);
    x.assign(4, 0.0);
    size_t worst = 4;
    for (size_t i = 0; i < cols.size(); ++i) {
      x[cols[i]] = y[i];
      if (y[i] < 0 && (worst == 4 || y[i] < x[worst])) worst = cols[i];
    }
    if (worst == 4) break;
    used[worst] = false;
  }
  const TileWorkCoefficients fit{x[0], x[1], x[2], x[3]};
  std::string dropped;
  const char* names[4] = {"per_ray", "per_cell_step", "per_triangle_test", "per_shading_call"};
  for (size_t j = 0; j < 4; ++j) {
    if (!used[j]) dropped += std::string(" ") + names[j];
  }
  // Fit quality: R^2 of the fit, and the share of tiles whose fitted cost is within 10 % / 25 %
  // of their CPU time (the calibration machine's noise included).
  double mean = 0;
  for (const double c : cpu) mean += c;
  mean /= static_cast<double>(std::max<size_t>(cpu.size(), 1));
  double ss_res = 0, ss_tot = 0;
  size_t in10 = 0, in25 = 0;
  for (size_t i = 0; i < rows.size(); ++i) {
    const TileWork w{static_cast<uint64_t>(rows[i][0]), static_cast<uint64_t>(rows[i][1]),
                     static_cast<uint64_t>(rows[i][2]), static_cast<uint64_t>(rows[i][3])};
    const double e = TileWorkCost(w, fit);
    ss_res += (cpu[i] - e) * (cpu[i] - e);
    ss_tot += (cpu[i] - mean) * (cpu[i] - mean);
    const double err = PredictionError(e, cpu[i]);
    in10 += err <= 0.10;
    in25 += err <= 0.25;
  }
  const double n = static_cast<double>(std::max<size_t>(rows.size(), 1));
  std::ofstream txt(dir / "calibrate.txt");
  const std::string text = fmt::format(
      "tiles: {}\nload average: {}\nper_ray {:.4g} s\nper_cell_step {:.4g} s\n"
      "per_triangle_test {:.4g} s\nper_shading_call {:.4g} s\n{}R^2 {:.4f}\n"
      "fitted cost within 10 % of the tile's CPU time: {:.1f} % of tiles, within 25 %: {:.1f} %\n"
      "tile_plan.cc: {{{:.3e}, {:.3e}, {:.3e}, {:.3e}}}\n"
      "command: sched_bench --out DIR --only calibrate (bench/scripts/run_sched_bench.sh BUILD "
      "DIR --only calibrate)\n",
      rows.size(), LoadAverage(), fit.per_ray, fit.per_cell_step, fit.per_triangle_test,
      fit.per_shading_call,
      dropped.empty() ? "" : "dropped (negative fit, collinear with the others):" + dropped + "\n",
      ss_tot > 0 ? 1.0 - ss_res / ss_tot : 0.0, 100.0 * in10 / n, 100.0 * in25 / n, fit.per_ray,
      fit.per_cell_step, fit.per_triangle_test, fit.per_shading_call);
  txt << text;
  fmt::print("{}", text);
}

// PBT paper Fig. 4: locality-aware assignment on small and large scenes. Two real workers (the
// two cores, each with its own L2), k tiles each, frames of the walk-through.
void Amphitheater(const Args& a, const std::filesystem::path& dir) {
  const int size = a.quick ? 48 : 256;
  const int frames = a.quick ? 3 : 16;
  const int rounds_k = a.quick ? 2 : 8;
  Csv table(dir / "amphitheater.csv",
            "scene,triangles,size,assign,steal,k,threads,frames,median_ms,mean_ms,est_ms,"
            "mean_tile_ms,mean_tile_cpu_ms,worker_imbalance,thread_imbalance,load_avg");
  for (const std::string name : {"amphitheater:1", "amphitheater:32"}) {
    const Loaded l = Load(name);
    fmt::print("{} ({} triangles) {}x{}, k = {}, 2 threads (load {})\n", name,
               l.scene.triangles.size(), size, size, rounds_k, LoadAverage());
    struct Variant {
      PbtAssign assign;
      bool steal;
    };
    const Variant variants[] = {{PbtAssign::kStatic, false}, {PbtAssign::kRandom, false},
                                {PbtAssign::kGreedy, false}, {PbtAssign::kVisit, false},
                                {PbtAssign::kGreedy, true},  {PbtAssign::kVisit, true}};
    const size_t nv = std::size(variants);
    std::vector<std::unique_ptr<HostRenderer>> renderers;
    for (const Variant& v : variants) {
      BackendOptions o;
      o.kind = BackendKind::kTiles;
      o.threads = 2;
      o.pbt_tiles_per_worker = rounds_k;
      o.assign = v.assign;
      o.pbt_steal = v.steal;
      o.pbt_cost = PbtCost::kCpu;
      o.seed = 777;
      renderers.push_back(std::make_unique<HostRenderer>(o));
    }
    std::vector<std::vector<double>> sec(nv), est(nv), tile(nv), tile_cpu(nv), imb(nv), timb(nv);
    Framebuffer fb(size, size);
    for (int f = 0; f < frames; ++f) {  // interleaved: frame f with every assignment
      const FrameContext ctx = MakeFrameContext(
          l.scene, *l.accel, l.scene.path.At(f, 1.0f, l.scene.camera), Options(size, size));
      for (size_t i = 0; i < nv; ++i) {
        fb.Clear();
        const HostFrameStats& s = renderers[i]->RenderFrame(ctx, fb);
        if (f == 0) continue;
        sec[i].push_back(s.total.total_seconds);
        est[i].push_back(s.ContentionFreeSeconds(2));
        double t = 0, c = 0;
        for (const TileRecord& r : s.tiles) {
          t += r.seconds;
          c += r.cpu_seconds;
        }
        tile[i].push_back(t / static_cast<double>(s.tiles.size()));
        tile_cpu[i].push_back(c / static_cast<double>(s.tiles.size()));
        imb[i].push_back(s.worker_imbalance);
        timb[i].push_back(s.imbalance);
      }
    }
    for (size_t i = 0; i < nv; ++i) {
      const char* assign = PbtAssignName(variants[i].assign);
      table.Row("{},{},{},{},{},{},2,{},{:.3f},{:.3f},{:.3f},{:.4f},{:.4f},{:.4f},{:.4f},{}", name,
                l.scene.triangles.size(), size, assign, variants[i].steal ? 1 : 0, rounds_k,
                frames - 1, 1e3 * Median(sec[i]), 1e3 * Mean(sec[i]), 1e3 * Median(est[i]),
                1e3 * Mean(tile[i]), 1e3 * Mean(tile_cpu[i]), Mean(imb[i]), Mean(timb[i]),
                LoadAverage());
      fmt::print(
          "  {:6}{:6}: {:7.2f} ms per frame (median; contention-free {:.2f}), tile {:.3f} ms "
          "({:.3f} ms CPU), imbalance {:.3f} (threads {:.3f})\n",
          assign, variants[i].steal ? "+steal" : "", 1e3 * Median(sec[i]), 1e3 * Median(est[i]),
          1e3 * Mean(tile[i]), 1e3 * Mean(tile_cpu[i]), Mean(imb[i]), Mean(timb[i]));
    }
  }
}

int Main(int argc, char** argv) {
  std::setvbuf(stdout, nullptr, _IOLBF, 0);  // progress lines as they happen, also into a file
  Args a;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    if (arg == "--out" && i + 1 < argc) {
      a.out = argv[++i];
    } else if (arg == "--pbt-costs" && i + 1 < argc) {
      a.pbt_costs.clear();
      std::string list = argv[++i];
      for (size_t start = 0; start <= list.size();) {
        const size_t comma = list.find(',', start);
        const std::string item =
            list.substr(start, comma == std::string::npos ? std::string::npos : comma - start);
        PbtCost cost;
        if (!ParsePbtCost(item, &cost)) {
          fmt::print(stderr, "sched_bench: --pbt-costs {}: expected wall, cpu, work\n", item);
          return 2;
        }
        a.pbt_costs.push_back(cost);
        if (comma == std::string::npos) break;
        start = comma + 1;
      }
    } else if (arg == "--pbt-batches" && i + 1 < argc) {
      a.pbt_batches.clear();
      std::string list = argv[++i];
      for (size_t start = 0; start <= list.size();) {
        const size_t comma = list.find(',', start);
        a.pbt_batches.push_back(std::atoi(list.substr(start, comma - start).c_str()));
        if (comma == std::string::npos) break;
        start = comma + 1;
      }
    } else if (arg == "--pbt-predict" && i + 1 < argc) {
      a.pbt_predicts.clear();
      const std::string list = argv[++i];
      for (size_t start = 0; start <= list.size();) {
        const size_t comma = std::min(list.find(',', start), list.size());
        const std::string item = list.substr(start, comma - start);
        PbtPredict predict;
        if (!ParsePbtPredict(item, &predict)) {
          fmt::print(stderr, "sched_bench: --pbt-predict {}: expected paper, costmap\n", item);
          return 2;
        }
        a.pbt_predicts.push_back(predict);
        start = comma + 1;
      }
    } else if (arg == "--pbt-reproject" && i + 1 < argc) {
      a.pbt_reproject = std::string(argv[++i]) != "0";
    } else if (arg == "--pbt-assigns" && i + 1 < argc) {
      a.pbt_assigns.clear();
      const std::string list = argv[++i];
      for (size_t start = 0; start <= list.size();) {
        const size_t comma = std::min(list.find(',', start), list.size());
        const std::string item = list.substr(start, comma - start);
        PbtAssign assign;
        if (!ParsePbtAssign(item, &assign)) {
          fmt::print(stderr,
                     "sched_bench: --pbt-assigns {}: expected static, random, greedy, visit, "
                     "counter, lpt\n",
                     item);
          return 2;
        }
        a.pbt_assigns.push_back(assign);
        start = comma + 1;
      }
    } else if (arg == "--pbt-backends" && i + 1 < argc) {
      a.pbt_backends.clear();
      const std::string list = argv[++i];
      for (size_t start = 0; start <= list.size();) {
        const size_t comma = std::min(list.find(',', start), list.size());
        const std::string item = list.substr(start, comma - start);
        BackendKind kind;
        if (!ParseBackendKind(item, &kind) || kind == BackendKind::kSerial) {
          fmt::print(stderr, "sched_bench: --pbt-backends {}: expected tiles, lock, lfree, local\n",
                     item);
          return 2;
        }
        a.pbt_backends.push_back(kind);
        start = comma + 1;
      }
    } else if (arg == "--pbt-block" && i + 1 < argc) {
      a.pbt_block = std::atoi(argv[++i]);
      if (a.pbt_block < 1 || a.pbt_block > 256) {
        fmt::print(stderr, "sched_bench: --pbt-block {}: expected 1 .. 256\n", argv[i]);
        return 2;
      }
    } else if (arg == "--pbt-size" && i + 1 < argc) {
      a.pbt_size = std::atoi(argv[++i]);
      if (a.pbt_size < 16 || a.pbt_size > 4096) {
        fmt::print(stderr, "sched_bench: --pbt-size {}: expected 16 .. 4096\n", argv[i]);
        return 2;
      }
    } else if (arg == "--quick") {
      a.quick = true;
    } else if (arg == "--only" && i + 1 < argc) {
      std::string list = argv[++i];
      size_t start = 0;
      while (start <= list.size()) {
        const size_t comma = list.find(',', start);
        a.only.insert(
            list.substr(start, comma == std::string::npos ? std::string::npos : comma - start));
        if (comma == std::string::npos) break;
        start = comma + 1;
      }
    } else {
      fmt::print(stderr,
                 "usage: sched_bench [--out DIR] [--quick] [--only scaling,tiles,pbt,amphitheater,"
                 "calibrate] [--pbt-costs work,cpu,wall] [--pbt-batches 1024,20] [--pbt-size 512] "
                 "[--pbt-predict paper,costmap] [--pbt-block 4] [--pbt-reproject 1] "
                 "[--pbt-assigns static,random,greedy,visit,counter,lpt] "
                 "[--pbt-backends tiles,lock,lfree,local]\n");
      return 2;
    }
  }
  const std::filesystem::path dir(a.out);
  std::filesystem::create_directories(dir);
  const unsigned cores = std::thread::hardware_concurrency();
  // A partial run (--only) keeps the full run's meta.txt: its own goes to meta_PARTS.txt.
  std::string meta_name = "meta.txt";
  if (!a.only.empty()) {
    meta_name = "meta";
    for (const std::string& part : a.only) meta_name += "_" + part;
    meta_name += ".txt";
  }
  {
    std::ofstream meta(dir / meta_name);
    std::string command = "sched_bench";
    for (int i = 1; i < argc; ++i) command += std::string(" ") + argv[i];
    const std::string note = fmt::format(
        "hardware threads: {}. Runs with more than {} render threads OVERSUBSCRIBE this machine: "
        "their threads time-share the cores, so their speed-up cannot exceed ~{}.\n",
        cores, cores, cores);
    meta << note << "command: " << command << "\n"
         << "load average at start: " << LoadAverage() << "\n"
         << "mode: " << (a.quick ? "quick (tiny sizes, numbers meaningless)" : "full") << "\n";
    fmt::print("{}", note);
  }
  if (Want(a, "scaling")) Scaling(a, dir);
  if (Want(a, "tiles")) TileShapes(a, dir);
  if (Want(a, "pbt")) PbtAccuracy(a, dir);
  if (Want(a, "amphitheater")) Amphitheater(a, dir);
  if (Want(a, "calibrate")) Calibrate(a, dir);
  {
    std::ofstream meta(dir / meta_name, std::ios::app);
    meta << "load average at end: " << LoadAverage() << "\n";
  }
  return 0;
}

}  // namespace
}  // namespace rs

int main(int argc, char** argv) {
  try {
    return rs::Main(argc, argv);
  } catch (const std::exception& e) {
    fmt::print(stderr, "sched_bench: {}\n", e.what());
    return 1;
  }
}
