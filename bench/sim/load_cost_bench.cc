// Table 1 of the Cell paper (average SPU cycles to load 8 bytes, section 3.4) against the
// simulator's memory model, whose every parameter comes from the hardware facts of
// shared/CELL-FACTS.md (sim/config.h), none fitted to Table 1. Prints the parameters with their
// sources, then per scene the work per visited cell (the compute model on that scene's counts)
// and each row's error against the paper, and the largest error.
//
//   load_cost_bench [--out DIR] [--quick]
//
// --out writes DIR/table1.md and DIR/table1.csv (bench/results/sim/ holds the committed run).
// The model is deterministic: its figures do not depend on the machine or its load.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include "include/raystream/raystream.h"
#include "scenes/load.h"
#include "sched/render.h"
#include "sim/cell_renderer.h"
#include "sim/load_bench.h"

namespace rs {
namespace {

using sim::SimConfig;

std::string Fmt(const char* format, double a = 0, double b = 0, double c = 0, double d = 0) {
  char buf[256];
  std::snprintf(buf, sizeof(buf), format, a, b, c, d);
  return buf;
}

struct Param {
  const char* name;
  double value;
  const char* source;
};

std::vector<Param> Params(const SimConfig& c) {
  const sim::MemoryTiming& m = c.memory;
  return {
      {"clock (GHz)", c.clock_hz / 1e9, "CELL-FACTS 1: 3.2 GHz (Benthin et al. RT'06; PS3)"},
      {"line round trip", double(sim::MemoryTiming::kLineRoundTripCycles),
       "Kistler et al. 2006: one 128-B line < 100 ns = 320 cycles"},
      {"dma_issue_cycles", double(m.dma_issue_cycles), "Kistler et al.: issue < 4 ns"},
      {"dma_wait_cycles", double(m.dma_wait_cycles),
       "SDK-PT cbet_3pipedr: 2 channel instructions x 6"},
      {"mic_line_cycles", double(m.mic_line_cycles), "128 B at 25.6 GB/s (MIC/XDR) = 8 B/cycle"},
      {"dma_latency_cycles", double(m.dma_latency_cycles), "320 - issue - line - wait"},
      {"mfc_bus_slots", double(m.mfc_bus_slots),
       "MFC queue, 16 entries (cbe_mfc.h); Kistler: non-blocking DMAs overlap"},
      {"atomic_issue_cycles", double(m.atomic_issue_cycles), "an MFC command: issue < 4 ns"},
      {"atomic_status_cycles", double(m.atomic_status_cycles), "SDK-PT: channel read 6"},
      {"atomic_latency_cycles", double(m.atomic_latency_cycles),
       "CELL-FACTS 4 rule 7, a miss pays a line fetch: 320 - issue - line - status"},
      {"sw_cache hit_cycles", double(c.sw_cache.hit_cycles),
       "Codeplay Offload's 4-way 128-B cache: read hit 28"},
      {"sw_cache miss_extra_cycles", double(c.sw_cache.miss_extra_cycles),
       "estimate (no IBM figure), plus a synchronous line DMA"},
      {"sw_cache capacity (KiB)",
       double(c.sw_cache.sets * c.sw_cache.ways * c.sw_cache.line_bytes) / 1024.0,
       "IBM cache-api.h: 64 sets x 4 ways x 128 B; the dataset fits (\"very cache friendly\")"},
      {"ls_load", double(c.costs.ls_load), "SDK-PT cbet_3pipedr: LS load 6"},
      {"dda_step", double(c.costs.dda_step), "paper 3.3: 21 cycles per grid cell"},
  };
}

struct SceneRow {
  std::string scene;
  double steps_per_visit = 0;
  double bundles_per_visit = 0;
  sim::LoadWork work;
  sim::LoadCosts costs;
};

SceneRow Measure(const std::string& name, int w, int h, const SimConfig& config) {
  const Scene scene = LoadScene(name);
  const Accel accel(scene.mesh());
  RenderOptions o;
  o.width = w;
  o.height = h;
  o.max_depth = 4;
  const FrameContext ctx = MakeFrameContext(scene, accel, scene.camera, o);
  Framebuffer fb(w, h);
  sim::CellRenderer renderer(config);
  const sim::CellFrameStats s = renderer.Render(ctx, fb);
  // Cells a traversal steps through per cell it visits, and bundles tested per visit (the cells
  // visited by secondary rays at once included: they count steps and bundles too).
  const double visits = double(s.totals.visits + s.totals.at_once_visits);
  if (visits <= 0) throw Error("load_cost_bench: scene " + name + " visits no cell");
  SceneRow r;
  r.scene = name;
  r.steps_per_visit = double(s.totals.cell_steps) / visits;
  r.bundles_per_visit = double(s.totals.bundles) / visits;
  r.work = sim::LoadWorkOf(config.costs, r.steps_per_visit, r.bundles_per_visit);
  sim::LoadBenchOptions lo;
  lo.traverse_cycles = r.work.traverse_cycles;
  lo.visit_cycles = r.work.visit_cycles;
  r.costs = sim::MeasureLoadCosts(config, lo);
  return r;
}

double ErrorPct(double model, double paper) { return 100.0 * (model - paper) / paper; }

// The five methods from cheapest to dearest ("4 0 3 2 1" = atomic async, SW cache, ...), ties
// (within 0.5 cycles) joined by '='.
std::string Ranking(const double (&cycles)[5]) {
  int order[5] = {0, 1, 2, 3, 4};
  std::stable_sort(order, order + 5, [&](int a, int b) { return cycles[a] < cycles[b]; });
  std::string s;
  for (int i = 0; i < 5; ++i) {
    if (i > 0) s += std::fabs(cycles[order[i]] - cycles[order[i - 1]]) < 0.5 ? " = " : " < ";
    s += sim::kLoadCostNames[order[i]];
  }
  return s;
}

int Main(int argc, char** argv) {
  std::string out;
  bool quick = false;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--out" && i + 1 < argc) {
      out = argv[++i];
    } else if (a == "--quick") {
      quick = true;
    } else {
      std::fprintf(stderr, "usage: load_cost_bench [--out DIR] [--quick]\n");
      return 2;
    }
  }
  const SimConfig config;
  std::string md =
      "# Table 1 of the Cell paper against the hardware-derived memory model\n\n"
      "Written by `bench/sim/load_cost_bench.cc` (`load_cost_bench --out bench/results/sim`). The "
      "simulator is deterministic, so these figures do not depend on the machine.\n\n"
      "## Parameters (sim/config.h), none fitted to Table 1\n\n| parameter | value | source |\n"
      "|---|---:|---|\n";
  std::printf("Parameters (sim/config.h, from shared/CELL-FACTS.md; none fitted to Table 1):\n");
  for (const Param& p : Params(config)) {
    std::printf("  %-28s %8.4g  %s\n", p.name, p.value, p.source);
    md += std::string("| ") + p.name + " | " + Fmt("%.4g", p.value) + " | " + p.source + " |\n";
  }
  const int w = quick ? 64 : 256, h = quick ? 48 : 192;
  std::string csv =
      "scene,steps_per_visit,bundles_per_visit,traverse_cycles,visit_cycles,method,paper_cycles,"
      "model_cycles,error_pct\n";
  md += Fmt("\n## Table 1 rows (work per ray from a %.0fx%.0f depth-4 render of each scene)\n\n", w,
            h);
  md += "| scene | work per ray (traverse + visit) | method | paper | model | error |\n"
        "|---|---|---|---:|---:|---:|\n";
  double worst_all = 0;
  for (const char* name : {"erw6", "spherebox"}) {
    const SceneRow r = Measure(name, w, h, config);
    std::printf("\n%s: %.2f cell steps and %.2f bundles per visited cell -> traverse %u + visit %u "
                "cycles per ray\n",
                name, r.steps_per_visit, r.bundles_per_visit, r.work.traverse_cycles,
                r.work.visit_cycles);
    std::printf("  %-14s %8s %8s %9s\n", "method", "paper", "model", "error");
    double worst = 0;
    for (int i = 0; i < 5; ++i) {
      const double paper = sim::kPaperLoadCosts[i], model = r.costs.cycles[i];
      const double err = ErrorPct(model, paper);
      worst = std::max(worst, std::fabs(err));
      std::printf("  %-14s %8.0f %8.1f %+8.1f %%\n", sim::kLoadCostNames[i], paper, model, err);
      csv += r.scene + Fmt(",%.3f,%.3f", r.steps_per_visit, r.bundles_per_visit) +
             Fmt(",%.0f,%.0f,", r.work.traverse_cycles, r.work.visit_cycles) +
             sim::kLoadCostNames[i] + Fmt(",%.0f,%.1f,%.1f\n", paper, model, err);
      md += "| " + r.scene +
            Fmt(" | %.0f + %.0f | ", r.work.traverse_cycles, r.work.visit_cycles) +
            sim::kLoadCostNames[i] + Fmt(" | %.0f | %.0f | %+.1f %% |\n", paper, model, err);
    }
    std::printf("  largest |error|: %.1f %%; cheapest first: model %s, paper %s\n", worst,
                Ranking(r.costs.cycles).c_str(), Ranking(sim::kPaperLoadCosts).c_str());
    md += "| " + r.scene + " | | cheapest first | " + Ranking(sim::kPaperLoadCosts) + " | " +
          Ranking(r.costs.cycles) + " | |\n";
    worst_all = std::max(worst_all, worst);
  }
  std::printf("\nTolerance reached against Table 1: every row within %.0f %% of the paper "
              "(no row is fitted).\n",
              std::ceil(worst_all));
  md += Fmt("\nLargest |error| over all rows: %.1f %%.\n", worst_all);
  if (!out.empty()) {
    std::filesystem::create_directories(out);
    std::ofstream(out + "/table1.csv") << csv;
    std::ofstream(out + "/table1.md") << md;
    std::printf("wrote %s/table1.md and table1.csv\n", out.c_str());
  }
  return 0;
}

}  // namespace
}  // namespace rs

int main(int argc, char** argv) {
  try {
    return rs::Main(argc, argv);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "load_cost_bench: %s\n", e.what());
    return 1;
  }
}
